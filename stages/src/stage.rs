//! The contract between the runner and a stage kind: named input tables and validated
//! parameters in, named output tables out; the runner alone knows about hashing, caching,
//! ordering and timing. Every output table has its Arrow schema in `data_schema/<table>.json`
//! ([`crate::schema`]).

use std::{
    collections::{BTreeMap, BTreeSet},
    path::Path,
    path::PathBuf,
};

use arrow::record_batch::RecordBatch;
use schemars::JsonSchema;
use serde::{de::DeserializeOwned, Serialize};
use serde_json::Value;

pub use crate::error::{Result, StageError};
pub use crate::params_doc::ParamDoc;
use crate::stream::Sinks;
pub use crate::stream::{Table, TableSet, TableWriter, Tables};

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

/// The inputs of one stage run: slot name -> the upstream stage's tables; and, under the
/// runner, where streamed output tables go ([`Inputs::writer`]).
pub struct Inputs<'a> {
    slots: BTreeMap<String, &'a TableSet>,
    sinks: Option<&'a dyn Sinks>,
}

impl<'a> Inputs<'a> {
    pub fn new(slots: BTreeMap<String, &'a TableSet>) -> Self {
        Self { slots, sinks: None }
    }

    /// The same inputs, with output tables written through `sinks` as they are produced.
    pub fn with_sinks(self, sinks: &'a dyn Sinks) -> Self {
        Self {
            sinks: Some(sinks),
            ..self
        }
    }

    /// Whether the optional slot `slot` is connected.
    pub fn has(&self, slot: &str) -> bool {
        self.slots.contains_key(slot)
    }

    /// Table `table` of the stage connected to `slot`, as a handle that reads rows on demand.
    pub fn stored(&self, slot: &str, table: &str) -> Result<&'a Table> {
        let tables = self
            .slots
            .get(slot)
            .ok_or_else(|| StageError::Input(format!("input slot `{slot}` is not connected")))?;
        tables.get(table).ok_or_else(|| {
            StageError::Input(format!(
                "input `{slot}` has no table `{table}` (it has: {})",
                tables.names().collect::<Vec<_>>().join(", ")
            ))
        })
    }

    /// Table `table` of the stage connected to `slot`, whole in memory (for small tables, or
    /// tables a stage needs whole; [`Inputs::stored`] reads parts).
    pub fn table(&self, slot: &str, table: &str) -> Result<&'a RecordBatch> {
        self.stored(slot, table)?.whole()
    }

    /// Like [`Inputs::table`] but `None` when the slot is not connected.
    pub fn optional_table(&self, slot: &str, table: &str) -> Result<Option<&'a RecordBatch>> {
        if self.has(slot) {
            self.table(slot, table).map(Some)
        } else {
            Ok(None)
        }
    }

    /// Like [`Inputs::stored`] but `None` when the slot is not connected.
    pub fn optional_stored(&self, slot: &str, table: &str) -> Result<Option<&'a Table>> {
        if self.has(slot) {
            self.stored(slot, table).map(Some)
        } else {
            Ok(None)
        }
    }

    /// A writer for output table `table`, one batch at a time: under the runner each batch is
    /// stored as it comes, so a large table is never held whole.
    pub fn writer(&self, table: &str) -> Result<TableWriter> {
        TableWriter::new(table, self.sinks)
    }
}

/// Input tables held in memory, by slot: for running a stage without the runner (tests, tools).
#[derive(Default)]
pub struct MemoryInputs {
    slots: BTreeMap<String, TableSet>,
}

impl MemoryInputs {
    pub fn new<S: Into<String>>(slots: impl IntoIterator<Item = (S, Tables)>) -> Self {
        Self {
            slots: slots
                .into_iter()
                .map(|(s, t)| (s.into(), TableSet::from(t)))
                .collect(),
        }
    }

    pub fn inputs(&self) -> Inputs<'_> {
        Inputs::new(self.slots.iter().map(|(k, v)| (k.clone(), v)).collect())
    }
}

/// Per input slot, the names of the tables (among those the slot reads) whose bytes differ
/// between a previous run's inputs and the current ones.
pub type Changed = BTreeMap<String, BTreeSet<String>>;

/// The previous run of a stage instance, offered by the runner for [`Stage::update`]: the same
/// kind, code version and params (but for the kind's [`Stage::editable_params`]), computed from
/// inputs that differ only in `changed`. An output table the update leaves out of its tables
/// (and does not stream) is the previous run's, unchanged: the runner links its file.
pub struct Previous<'a> {
    /// Its output tables.
    pub outputs: &'a TableSet,
    /// The inputs it was computed from, by slot.
    pub inputs: BTreeMap<String, &'a TableSet>,
    pub changed: &'a Changed,
    pub lineage: &'a Lineage,
}

/// How each input's current entry relates to the one a previous run read.
#[derive(Debug, Clone, Default)]
pub struct Lineage {
    /// The slots whose current entry was itself updated from the entry the previous run read
    /// (so it carries that entry's work on, rather than replacing it).
    pub descends: BTreeSet<String>,
    /// The slots whose current entry the same kind, code version and params computed as the
    /// entry the previous run read: it changed only because its own inputs did.
    pub same_recipe: BTreeSet<String>,
}

impl Lineage {
    /// Whether input `slot`'s current entry was updated from the one the previous run read.
    pub fn descends(&self, slot: &str) -> bool {
        self.descends.contains(slot)
    }

    /// Whether input `slot`'s entry was computed as the previous run's was.
    pub fn same_recipe(&self, slot: &str) -> bool {
        self.same_recipe.contains(slot)
    }
}

impl Previous<'_> {
    /// Table `table` of the previous run's input `slot`.
    pub fn input(&self, slot: &str, table: &str) -> Result<&Table> {
        self.inputs
            .get(slot)
            .and_then(|t| t.get(table))
            .ok_or_else(|| {
                StageError::Input(format!(
                    "the previous run has no input table `{slot}.{table}` (or the kind's \
                     PARENT_INPUTS does not name it)"
                ))
            })
    }

    /// Output table `table` of the previous run.
    pub fn output(&self, table: &str) -> Result<&Table> {
        self.outputs.get(table).ok_or_else(|| {
            StageError::Input(format!("the previous run has no output table `{table}`"))
        })
    }

    /// Whether table `table` of input `slot` changed.
    pub fn changed(&self, slot: &str, table: &str) -> bool {
        self.changed.get(slot).is_some_and(|t| t.contains(table))
    }
}

/// The outputs of an update and what it computed again, for the run log (`12 of 128 images`).
pub struct Updated {
    pub tables: Tables,
    pub redone: String,
}

/// The type-erased interface the runner sees. Implement [`TypedStage`] instead.
pub trait Stage: Send + Sync {
    /// Registry name, used in pipeline.yaml `uses:`.
    fn kind(&self) -> &'static str;
    /// Code version: bump whenever outputs change for the same inputs and params.
    fn version(&self) -> u32;
    /// Version of the update's code ([`TypedStage::UPDATE_VERSION`]): part of an update's key
    /// only.
    fn update_version(&self) -> u32;
    fn description(&self) -> &'static str;
    fn inputs(&self) -> &'static [InputSlot];
    /// Names of the tables this kind writes (each has `data_schema/<name>.json`).
    fn outputs(&self) -> &'static [&'static str];
    /// Default parameters as a JSON object.
    fn default_params(&self) -> Value;
    /// Every parameter with its type, default and doc, in the order the params struct declares
    /// them ([`crate::params_doc`]).
    fn param_docs(&self) -> Vec<ParamDoc>;
    /// The parameters of earlier layouts: `(old dotted path, new path [(note)] or (note))`.
    fn moved_params(&self) -> &'static [(&'static str, &'static str)];
    /// Where a parameter of an earlier layout went: the new key (or a hint) for the old dotted
    /// `path` (`train.lr` -> `optimiser.lr`), `None` when `path` was never moved.
    fn moved_param(&self, path: &str) -> Option<String> {
        crate::params_doc::moved(self.moved_params(), path)
    }
    /// Checks full parameters (defaults filled in) and returns their canonical form.
    fn canonical_params(&self, params: &Value) -> Result<Value>;
    fn run(&self, params: &Value, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables>;
    /// Writes the stage's human-facing files (PNGs, reports) into `dir`; returns what it wrote.
    fn export(&self, params: &Value, tables: &TableSet, dir: &Path) -> Result<Vec<PathBuf>>;
    /// The files outside the cache this run will read (e.g. a KITTI-360 root's); the runner
    /// hashes their content into the stage's key, so editing one re-runs the stage. Each must
    /// be a regular file (or missing, for the stage to report): anything else is an error
    /// before hashing.
    fn external_inputs(&self, params: &Value) -> Result<Vec<PathBuf>>;
    /// How this kind's score table reads, if it scores methods (see [`ScoreSpec`]).
    fn scores(&self) -> Option<&'static ScoreSpec>;
    /// The parameter (dotted path inside the params) that sets how much work the stage does,
    /// e.g. training iterations: what a time-against-error sweep varies.
    fn budget_param(&self) -> Option<&'static str>;
    /// Whether this kind can update a previous run's outputs (see [`Stage::update`]).
    fn updates(&self) -> bool;
    /// Top-level params that change only how an update works, nothing a run from scratch
    /// writes ([`TypedStage::UPDATE_ONLY`]): no part of a run from scratch's key, and a parent
    /// may have run with other values.
    fn update_only_params(&self) -> &'static [&'static str];
    /// Top-level params a parent may differ in, which its update takes up
    /// ([`TypedStage::EDITABLE`]): part of every key, unlike update-only params.
    fn editable_params(&self) -> &'static [&'static str];
    /// The tables of its parent's inputs that [`Stage::update`] reads, as (slot, table)
    /// ([`TypedStage::PARENT_INPUTS`]): the runner opens and verifies only these.
    fn parent_inputs(&self) -> &'static [(&'static str, &'static str)];
    /// Whether [`Stage::update`] can start from a previous run whose inputs differ from the
    /// current ones in `changed` and relate to them as `lineage` says; if not, why (the runner
    /// then computes from scratch).
    fn can_update(
        &self,
        params: &Value,
        changed: &Changed,
        lineage: &Lineage,
    ) -> std::result::Result<(), String>;
    /// Like [`Stage::run`], starting from `previous` and redoing only what its changed inputs
    /// can change. The same previous run and inputs give the same bytes.
    fn update(
        &self,
        params: &Value,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated>;
}

/// A stage kind with typed parameters. Params are a serde struct with `#[serde(default,
/// deny_unknown_fields)]`; its `Default` gives the defaults the cache key fills in.
pub trait TypedStage: Send + Sync {
    type Params: Serialize + DeserializeOwned + Default + JsonSchema;
    const KIND: &'static str;
    const VERSION: u32;
    const DESCRIPTION: &'static str;
    const INPUTS: &'static [InputSlot];
    const OUTPUTS: &'static [&'static str];
    /// See [`Stage::scores`].
    const SCORES: Option<&'static ScoreSpec> = None;
    /// See [`Stage::budget_param`].
    const BUDGET_PARAM: Option<&'static str> = None;
    /// Parameters that moved: `(old dotted path, new path or hint)`; an old path matches itself
    /// and every path below it, the longest match wins (see [`Stage::moved_param`]).
    const MOVED: &'static [(&'static str, &'static str)] = &[];
    /// See [`Stage::updates`]; a kind that sets it implements [`TypedStage::update`].
    const UPDATES: bool = false;
    /// Bump when [`TypedStage::update`] writes other bytes from the same parent and inputs while
    /// a run from scratch writes the same: updated entries go stale, runs from scratch stay
    /// cached (0: the update's key is that of its inputs, parent and `VERSION` alone).
    const UPDATE_VERSION: u32 = 0;
    /// Top-level params that say only how an update works and change nothing a run from scratch
    /// writes: left out of the key of a run from scratch (so setting them, or adding them to a
    /// kind, leaves every cached entry current), part of an update's key, and a parent may have
    /// run with other values of them ([`Stage::update_only_params`]).
    const UPDATE_ONLY: &'static [&'static str] = &[];
    /// Top-level params whose change [`TypedStage::update`] takes up from a parent that ran with
    /// other values (a source stage's edits of the annotation): a parent may differ in them.
    const EDITABLE: &'static [&'static str] = &[];
    /// See [`Stage::parent_inputs`]: what an update reads of its parent's inputs through
    /// [`Previous::input`] (a parent's tables are opened and verified only where read, since
    /// some are gigabytes).
    const PARENT_INPUTS: &'static [(&'static str, &'static str)] = &[];

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
        _tables: &TableSet,
        _dir: &Path,
    ) -> Result<Vec<PathBuf>> {
        Ok(Vec::new())
    }
    /// Files outside the cache the stage reads (see [`Stage::external_inputs`]).
    fn external_inputs(&self, _params: &Self::Params) -> Result<Vec<PathBuf>> {
        Ok(Vec::new())
    }
    /// See [`Stage::can_update`].
    fn can_update(
        &self,
        _params: &Self::Params,
        _changed: &Changed,
        _lineage: &Lineage,
    ) -> std::result::Result<(), String> {
        Ok(())
    }
    /// See [`Stage::update`].
    fn update(
        &self,
        _params: &Self::Params,
        _inputs: &Inputs,
        _previous: &Previous,
        _progress: &dyn Progress,
    ) -> Result<Updated> {
        Err(StageError::Failed(format!(
            "kind `{}` does not update a previous run",
            Self::KIND
        )))
    }
}

/// The params as the kind's struct; an error starts with the path of the field it is about
/// (`` `optimiser.lr`: invalid type ... ``) when it is not the top level.
fn typed_params<P: DeserializeOwned>(params: &Value) -> Result<P> {
    serde_path_to_error::deserialize(params.clone()).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        if path.is_empty() || path == "." {
            StageError::Params(inner.to_string())
        } else {
            StageError::Params(format!("`{path}`: {inner}"))
        }
    })
}

impl<T: TypedStage> Stage for T {
    fn kind(&self) -> &'static str {
        T::KIND
    }
    fn version(&self) -> u32 {
        T::VERSION
    }
    fn update_version(&self) -> u32 {
        T::UPDATE_VERSION
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
    fn param_docs(&self) -> Vec<ParamDoc> {
        crate::params_doc::docs::<T::Params>()
    }
    fn moved_params(&self) -> &'static [(&'static str, &'static str)] {
        T::MOVED
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
    fn export(&self, params: &Value, tables: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let p: T::Params = typed_params(params)?;
        TypedStage::export(self, &p, tables, dir)
    }
    fn external_inputs(&self, params: &Value) -> Result<Vec<PathBuf>> {
        let p: T::Params = typed_params(params)?;
        TypedStage::external_inputs(self, &p)
    }
    fn scores(&self) -> Option<&'static ScoreSpec> {
        T::SCORES
    }
    fn budget_param(&self) -> Option<&'static str> {
        T::BUDGET_PARAM
    }
    fn updates(&self) -> bool {
        T::UPDATES
    }
    fn update_only_params(&self) -> &'static [&'static str] {
        T::UPDATE_ONLY
    }
    fn editable_params(&self) -> &'static [&'static str] {
        T::EDITABLE
    }
    fn parent_inputs(&self) -> &'static [(&'static str, &'static str)] {
        T::PARENT_INPUTS
    }
    fn can_update(
        &self,
        params: &Value,
        changed: &Changed,
        lineage: &Lineage,
    ) -> std::result::Result<(), String> {
        if !T::UPDATES {
            return Err(format!("kind `{}` computes from scratch", T::KIND));
        }
        let p: T::Params = typed_params(params).map_err(|e| e.to_string())?;
        TypedStage::can_update(self, &p, changed, lineage)
    }
    fn update(
        &self,
        params: &Value,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated> {
        let p: T::Params = typed_params(params)?;
        TypedStage::update(self, &p, inputs, previous, progress)
    }
}

/// What a kind that scores methods writes, for tools that read its table without knowing the
/// method (`pipe bench`): the table, the methods in it, and how to show each metric.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ScoreSpec {
    /// Table with columns `method` and `metric` (utf8) and `value` (float64; null: undefined).
    pub table: &'static str,
    /// The method the pipeline produces.
    pub method: &'static str,
    /// The other methods scored in the same table, in display order.
    pub baselines: &'static [MethodInfo],
    /// Every metric a report may show, in display order.
    pub metrics: &'static [MetricInfo],
    /// The metric that says how good a run is (e.g. for the time to come near the best run).
    pub headline: &'static str,
    /// Metrics of the method per run (the time-against-error table).
    pub per_run: &'static [&'static str],
    /// Metrics of the baselines.
    pub per_baseline: &'static [&'static str],
    /// Metrics of an ablation table.
    pub ablation: &'static [&'static str],
    /// Metrics drawn against training time.
    pub plotted: &'static [&'static str],
    /// What a reader must know to compare the figures (conventions), one sentence each.
    pub notes: &'static [&'static str],
}

/// A method of a [`ScoreSpec`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MethodInfo {
    pub name: &'static str,
    pub label: &'static str,
    /// Whether its scores depend on the budget of the run (else: a flat line against time).
    pub depends_on_budget: bool,
}

/// How to show one metric of a [`ScoreSpec`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MetricInfo {
    pub name: &'static str,
    /// Short label, e.g. `mIoU`.
    pub label: &'static str,
    /// Unit after scaling, e.g. `%` or `m`.
    pub unit: &'static str,
    /// Shown as `value * scale` with `decimals` digits.
    pub scale: f64,
    pub decimals: usize,
    /// Only meaningful when the run is supervised with labels (a depth metric is not).
    pub semantic: bool,
}

impl ScoreSpec {
    /// The metric called `name`.
    pub fn metric(&self, name: &str) -> Option<&'static MetricInfo> {
        self.metrics.iter().find(|m| m.name == name)
    }
}
