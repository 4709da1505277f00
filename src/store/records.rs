//! Run records: `runs/<stage>.json`, the last successful run of each stage instance (what
//! `pipe status` compares against to say why a stage is stale) and every key it has had (what
//! `pipe gc --keep-all-runs` keeps).

use std::{collections::BTreeMap, fs};

use serde::{Deserialize, Serialize};

use super::{
    entry::{InputInfo, Manifest},
    error::StoreError,
    files::write_atomic,
    layout::Store,
};

/// The last successful run of a stage instance, kept for `pipe status` explanations.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRecord {
    pub key: String,
    pub kind: String,
    pub version: u32,
    pub params: serde_json::Value,
    pub inputs: BTreeMap<String, InputInfo>,
    /// Every key this stage instance has had (for `gc --keep-all-runs`).
    #[serde(default)]
    pub history: Vec<String>,
}

impl RunRecord {
    /// The record of a run that made entry `m` (no history).
    pub fn of(m: Manifest) -> Self {
        Self {
            key: m.key,
            kind: m.kind,
            version: m.version,
            params: m.params,
            inputs: m.inputs,
            history: Vec::new(),
        }
    }
}

impl Store {
    pub fn run_record(&self, stage: &str) -> Option<RunRecord> {
        let bytes = fs::read(self.dir("runs").join(format!("{stage}.json"))).ok()?;
        serde_json::from_slice(&bytes).ok()
    }

    pub fn save_run_record(&self, stage: &str, mut rec: RunRecord) -> Result<(), StoreError> {
        let mut history = self
            .run_record(stage)
            .map(|r| r.history)
            .unwrap_or_default();
        if !history.contains(&rec.key) {
            history.push(rec.key.clone());
        }
        rec.history = history;
        let dest = self.dir("runs").join(format!("{stage}.json"));
        // Removed while the run worked (a clean-up by hand): lay it out again.
        let _ = fs::create_dir_all(self.dir("runs"));
        let json = serde_json::to_vec_pretty(&rec).map_err(|source| StoreError::Json {
            what: dest.display().to_string(),
            source,
        })?;
        Ok(write_atomic(&dest, &json)?)
    }

    /// All run records (stage name -> record).
    pub fn run_records(&self) -> BTreeMap<String, RunRecord> {
        let mut out = BTreeMap::new();
        if let Ok(rd) = fs::read_dir(self.dir("runs")) {
            for e in rd.filter_map(|e| e.ok()) {
                let name = e.file_name().to_string_lossy().into_owned();
                if let Some(stage) = name.strip_suffix(".json").filter(|s| !s.starts_with('.')) {
                    if let Some(r) = self.run_record(stage) {
                        out.insert(stage.to_string(), r);
                    }
                }
            }
        }
        out
    }
}
