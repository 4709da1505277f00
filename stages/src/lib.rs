//! The stage kinds of panoptic-pipe and the contract the runner holds them to.
//!
//! A stage kind is a pure function from named input tables (the outputs of upstream stage
//! instances) and validated parameters to named output tables. It never touches the cache or
//! another stage's files; the runner alone knows about hashing, caching, ordering and timing.
//! Every output table has its Arrow schema in `data_schema/<table>.json` ([`schema`]).

pub mod aggregate;
pub mod compose;
pub mod evaluate;
pub mod field;
pub mod fused;
pub mod geometry;
pub mod labels;
pub mod metrics;
pub mod pngio;
pub mod rays;
pub mod render;
pub mod report;
pub mod sampling;
pub mod scene;
pub mod schema;
pub mod stereo;
pub mod tables;
pub mod testing;
pub mod train;
pub mod train_stage;

use std::{collections::BTreeMap, fmt, path::Path, path::PathBuf};

use arrow::record_batch::RecordBatch;
use serde::{de::DeserializeOwned, Serialize};
use serde_json::Value;

/// Named tables: what a stage writes, and what an upstream stage hands to a downstream one.
pub type Tables = BTreeMap<String, RecordBatch>;

/// Why a stage could not produce its outputs.
#[derive(Debug, Clone, PartialEq)]
pub enum StageError {
    /// The parameters are invalid (the runner reports this as a configuration error, exit 2).
    Params(String),
    /// An input table or file is missing or malformed.
    Input(String),
    /// The computation itself failed (e.g. training diverged).
    Failed(String),
}

impl fmt::Display for StageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StageError::Params(m) => write!(f, "invalid params: {m}"),
            StageError::Input(m) => write!(f, "bad input: {m}"),
            StageError::Failed(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for StageError {}

pub type Result<T, E = StageError> = std::result::Result<T, E>;

/// One named input slot of a stage kind (e.g. `scene` for the rays stage).
#[derive(Debug, Clone, Copy)]
pub struct InputSlot {
    pub name: &'static str,
    /// Tables the stage reads from this slot; the runner checks the upstream stage writes them.
    pub tables: &'static [&'static str],
    pub optional: bool,
    pub doc: &'static str,
}

/// Progress reporting from inside a stage body (drawn by the runner as a bar).
pub trait Progress: Sync {
    /// `done` of `total` units of work, with a short message (e.g. the current losses).
    fn update(&self, done: u64, total: u64, message: &str);
}

/// Progress sink that drops everything (tests, quiet runs).
pub struct NoProgress;
impl Progress for NoProgress {
    fn update(&self, _: u64, _: u64, _: &str) {}
}

/// The inputs of one stage run: slot name -> the upstream stage's tables.
pub struct Inputs<'a> {
    slots: BTreeMap<String, &'a Tables>,
}

impl<'a> Inputs<'a> {
    pub fn new(slots: BTreeMap<String, &'a Tables>) -> Self {
        Self { slots }
    }

    /// Whether the optional slot `slot` is connected.
    pub fn has(&self, slot: &str) -> bool {
        self.slots.contains_key(slot)
    }

    /// Table `table` of the stage connected to `slot`.
    pub fn table(&self, slot: &str, table: &str) -> Result<&'a RecordBatch> {
        let tables = self
            .slots
            .get(slot)
            .ok_or_else(|| StageError::Input(format!("input slot `{slot}` is not connected")))?;
        tables.get(table).ok_or_else(|| {
            StageError::Input(format!(
                "input `{slot}` has no table `{table}` (it has: {})",
                tables.keys().cloned().collect::<Vec<_>>().join(", ")
            ))
        })
    }

    /// Like [`Inputs::table`] but `None` when the slot is not connected.
    pub fn optional_table(&self, slot: &str, table: &str) -> Result<Option<&'a RecordBatch>> {
        if self.has(slot) {
            self.table(slot, table).map(Some)
        } else {
            Ok(None)
        }
    }
}

/// The type-erased interface the runner sees. Implement [`TypedStage`] instead.
pub trait Stage: Send + Sync {
    /// Registry name, used in pipeline.yaml `uses:`.
    fn kind(&self) -> &'static str;
    /// Code version: bump whenever outputs change for the same inputs and params.
    fn version(&self) -> u32;
    fn description(&self) -> &'static str;
    fn inputs(&self) -> &'static [InputSlot];
    /// Names of the tables this kind writes (each has `data_schema/<name>.json`).
    fn outputs(&self) -> &'static [&'static str];
    /// Default parameters as a JSON object.
    fn default_params(&self) -> Value;
    /// Checks full parameters (defaults filled in) and returns their canonical form.
    fn canonical_params(&self, params: &Value) -> Result<Value>;
    fn run(&self, params: &Value, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables>;
    /// Writes the stage's human-facing files (PNGs, reports) into `dir`; returns what it wrote.
    fn export(&self, params: &Value, tables: &Tables, dir: &Path) -> Result<Vec<PathBuf>>;
    /// Files and directories outside the cache this run will read (e.g. a KITTI-360 root); the
    /// runner hashes their content into the stage's key, so editing one re-runs the stage.
    fn external_inputs(&self, params: &Value) -> Result<Vec<PathBuf>>;
}

/// A stage kind with typed parameters. Params are a serde struct with `#[serde(default,
/// deny_unknown_fields)]`; its `Default` gives the defaults the cache key fills in.
pub trait TypedStage: Send + Sync {
    type Params: Serialize + DeserializeOwned + Default;
    const KIND: &'static str;
    const VERSION: u32;
    const DESCRIPTION: &'static str;
    const INPUTS: &'static [InputSlot];
    const OUTPUTS: &'static [&'static str];

    /// Semantic checks beyond types (ranges, consistency). Errors name the param.
    fn validate(_params: &Self::Params) -> Result<()> {
        Ok(())
    }
    fn run(
        &self,
        params: &Self::Params,
        inputs: &Inputs,
        progress: &dyn Progress,
    ) -> Result<Tables>;
    fn export(
        &self,
        _params: &Self::Params,
        _tables: &Tables,
        _dir: &Path,
    ) -> Result<Vec<PathBuf>> {
        Ok(Vec::new())
    }
    /// Files outside the cache the stage reads (see [`Stage::external_inputs`]).
    fn external_inputs(&self, _params: &Self::Params) -> Result<Vec<PathBuf>> {
        Ok(Vec::new())
    }
}

fn typed_params<P: DeserializeOwned>(params: &Value) -> Result<P> {
    serde_json::from_value(params.clone()).map_err(|e| StageError::Params(e.to_string()))
}

impl<T: TypedStage> Stage for T {
    fn kind(&self) -> &'static str {
        T::KIND
    }
    fn version(&self) -> u32 {
        T::VERSION
    }
    fn description(&self) -> &'static str {
        T::DESCRIPTION
    }
    fn inputs(&self) -> &'static [InputSlot] {
        T::INPUTS
    }
    fn outputs(&self) -> &'static [&'static str] {
        T::OUTPUTS
    }
    fn default_params(&self) -> Value {
        serde_json::to_value(T::Params::default()).expect("params serialise to JSON")
    }
    fn canonical_params(&self, params: &Value) -> Result<Value> {
        let p: T::Params = typed_params(params)?;
        T::validate(&p)?;
        serde_json::to_value(&p).map_err(|e| StageError::Params(e.to_string()))
    }
    fn run(&self, params: &Value, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let p: T::Params = typed_params(params)?;
        TypedStage::run(self, &p, inputs, progress)
    }
    fn export(&self, params: &Value, tables: &Tables, dir: &Path) -> Result<Vec<PathBuf>> {
        let p: T::Params = typed_params(params)?;
        TypedStage::export(self, &p, tables, dir)
    }
    fn external_inputs(&self, params: &Value) -> Result<Vec<PathBuf>> {
        let p: T::Params = typed_params(params)?;
        TypedStage::external_inputs(self, &p)
    }
}

/// Every stage kind, by name. The runner knows stages only through this.
pub fn registry() -> Vec<Box<dyn Stage>> {
    let mut all: Vec<Box<dyn Stage>> = vec![
        Box::new(scene::SyntheticScene),
        Box::new(scene::kitti360::Kitti360Scene),
        Box::new(stereo::StereoDepth),
        Box::new(rays::Intersect),
        Box::new(train_stage::Train),
        Box::new(render::Render),
        Box::new(evaluate::Evaluate),
        Box::new(report::Report),
        Box::new(aggregate::Aggregate),
    ];
    all.extend(testing::kinds());
    all
}

/// Looks up one kind by name.
pub fn find(kind: &str) -> Option<Box<dyn Stage>> {
    registry().into_iter().find(|s| s.kind() == kind)
}
