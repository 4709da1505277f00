//! Tiny stage kinds for exercising the runner (caching, early cutoff, failures, kills) without
//! the cost of the real stages. They are registered like any other kind under a `test_` prefix.

use std::{thread, time::Duration};

use arrow::datatypes::Int64Type;
use serde::{Deserialize, Serialize};

use crate::{
    tables, InputSlot, Inputs, Progress, Result, Stage, StageError, TableSet, Tables, TypedStage,
};

/// Behaviour switches shared by the test kinds.
#[derive(Debug, Clone, Default, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Knobs {
    /// Milliseconds to sleep inside the stage body (in 10 ms steps, reporting progress).
    pub sleep_ms: u64,
    /// Fail with an error instead of producing output.
    pub fail: bool,
}

impl Knobs {
    fn apply(&self, progress: &dyn Progress) -> Result<()> {
        let steps = self.sleep_ms.div_ceil(10);
        for i in 0..steps {
            progress.update(i, steps, "sleeping");
            thread::sleep(Duration::from_millis(10));
        }
        if self.fail {
            return Err(StageError::Failed("test stage asked to fail".into()));
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SourceParams {
    /// First value of the sequence.
    pub value: i64,
    /// Number of rows.
    pub rows: u32,
    /// Changes the cache key but not the output (for early-cutoff tests).
    pub salt: String,
    #[serde(flatten)]
    pub knobs: Knobs,
}

impl Default for SourceParams {
    fn default() -> Self {
        Self {
            value: 1,
            rows: 3,
            salt: String::new(),
            knobs: Knobs::default(),
        }
    }
}

/// Emits `rows` numbers starting at `value`.
pub struct TestSource;

impl TypedStage for TestSource {
    type Params = SourceParams;
    const KIND: &'static str = "test_source";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test kind: a sequence of numbers";
    const INPUTS: &'static [InputSlot] = &[];
    const OUTPUTS: &'static [&'static str] = &["test_numbers"];

    fn validate(p: &SourceParams) -> Result<()> {
        if p.rows == 0 {
            return Err(StageError::Params("`rows` must be at least 1".into()));
        }
        Ok(())
    }

    fn run(&self, p: &SourceParams, _: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        p.knobs.apply(progress)?;
        let values = (0..p.rows as i64).map(|i| p.value + i);
        let t = tables::build("test_numbers", vec![tables::prim::<Int64Type>(values)])?;
        Ok(Tables::from([("test_numbers".to_string(), t)]))
    }
}

#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct MapParams {
    /// Every number is multiplied by this.
    pub factor: i64,
    /// Optional modulus applied after the multiplication.
    pub modulo: Option<i64>,
    #[serde(flatten)]
    pub knobs: Knobs,
}

impl Default for MapParams {
    fn default() -> Self {
        Self {
            factor: 2,
            modulo: None,
            knobs: Knobs::default(),
        }
    }
}

/// Multiplies its input numbers (and adds the optional `extra` input's, row by row).
pub struct TestMap;

impl TypedStage for TestMap {
    type Params = MapParams;
    const KIND: &'static str = "test_map";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test kind: numbers times a factor";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "src",
            tables: &["test_numbers"],
            optional: false,
            doc: "numbers to transform",
        },
        InputSlot {
            name: "extra",
            tables: &["test_numbers"],
            optional: true,
            doc: "numbers added row by row",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &["test_numbers"];

    fn run(&self, p: &MapParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        p.knobs.apply(progress)?;
        let src = inputs.table("src", "test_numbers")?;
        let values = tables::get_prim::<Int64Type>(src, "test_numbers", "value")?;
        let extra = match inputs.optional_table("extra", "test_numbers")? {
            Some(t) => tables::get_prim::<Int64Type>(t, "test_numbers", "value")?.to_vec(),
            None => vec![],
        };
        let out = values.iter().enumerate().map(|(i, v)| {
            let x = v * p.factor + extra.get(i).copied().unwrap_or(0);
            match p.modulo {
                Some(m) if m != 0 => x.rem_euclid(m),
                _ => x,
            }
        });
        let t = tables::build("test_numbers", vec![tables::prim::<Int64Type>(out)])?;
        Ok(Tables::from([("test_numbers".to_string(), t)]))
    }

    fn export(
        &self,
        _: &MapParams,
        t: &TableSet,
        dir: &std::path::Path,
    ) -> Result<Vec<std::path::PathBuf>> {
        let table = t.table("test_numbers")?;
        let values = tables::get_prim::<Int64Type>(table, "test_numbers", "value")?;
        let text: String = values.iter().map(|v| format!("{v}\n")).collect();
        let path = dir.join("numbers.txt");
        std::fs::write(&path, text)
            .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))?;
        Ok(vec![path])
    }
}

#[derive(Debug, Clone, Default, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct FileParams {
    /// A text file of numbers, one per line.
    pub path: String,
}

/// Reads numbers from a file outside the cache (exercises `external_inputs`).
pub struct TestFile;

impl TypedStage for TestFile {
    type Params = FileParams;
    const KIND: &'static str = "test_file";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str = "test kind: numbers read from a file";
    const INPUTS: &'static [InputSlot] = &[];
    const OUTPUTS: &'static [&'static str] = &["test_numbers"];

    fn run(&self, p: &FileParams, _: &Inputs, _: &dyn Progress) -> Result<Tables> {
        let text = std::fs::read_to_string(&p.path)
            .map_err(|e| StageError::Input(format!("{}: {e}", p.path)))?;
        let values = text
            .lines()
            .map(|l| {
                l.trim()
                    .parse::<i64>()
                    .map_err(|e| StageError::Input(format!("{}: `{l}`: {e}", p.path)))
            })
            .collect::<Result<Vec<_>>>()?;
        let t = tables::build("test_numbers", vec![tables::prim::<Int64Type>(values)])?;
        Ok(Tables::from([("test_numbers".to_string(), t)]))
    }

    fn external_inputs(&self, p: &FileParams) -> Result<Vec<std::path::PathBuf>> {
        Ok(vec![p.path.clone().into()])
    }
}

pub fn kinds() -> Vec<Box<dyn Stage>> {
    vec![Box::new(TestSource), Box::new(TestMap), Box::new(TestFile)]
}
