//! The pipeline files that ran in this cache: `runs/pipelines/<id>.json`, one per file (its
//! absolute path), with the entries its last run reached. `pipe gc` keeps what every such file
//! still reaches, so a cache shared between pipelines (a matrix, several sequences, a
//! colleague's runs) does not lose one pipeline's work to another's gc.

use std::{
    fs,
    path::{Path, PathBuf},
};

use serde::{Deserialize, Serialize};

use crate::error::IoContext;

use super::{
    error::StoreError,
    files::{host_name, unix_now, write_atomic},
    layout::Store,
};

/// A pipeline file that ran in this cache.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct KnownPipeline {
    /// Its absolute path, as the run that used it saw it.
    pub file: PathBuf,
    /// The machine that ran it (a cache shared over NFS sees files of other machines).
    pub host: String,
    /// When it last ran (seconds since the epoch).
    pub last_run: f64,
    /// The entries its last run reached, kept by gc when the file cannot be read any more.
    pub keys: Vec<String>,
}

impl Store {
    fn pipeline_record(&self, file: &Path) -> PathBuf {
        let id = blake3::hash(file.as_os_str().as_encoded_bytes()).to_hex();
        self.dir("runs")
            .join("pipelines")
            .join(format!("{}.json", &id[..16]))
    }

    /// Records that the pipeline `file` (absolute) ran here and reached `keys` (`None`: keep
    /// what its last run recorded, for a run that is starting).
    pub fn record_pipeline(
        &self,
        file: &Path,
        keys: Option<Vec<String>>,
    ) -> Result<(), StoreError> {
        let path = self.pipeline_record(file);
        let keys = match keys {
            Some(k) => k,
            None => read_record(&path).map(|r| r.keys).unwrap_or_default(),
        };
        let rec = KnownPipeline {
            file: file.to_path_buf(),
            host: host_name(),
            last_run: unix_now(),
            keys,
        };
        let dir = path.parent().expect("in runs/pipelines");
        fs::create_dir_all(dir).io_context(|| format!("creating {}", dir.display()))?;
        let json = serde_json::to_vec_pretty(&rec).map_err(|source| StoreError::Json {
            what: path.display().to_string(),
            source,
        })?;
        Ok(write_atomic(&path, &json)?)
    }

    /// Every pipeline file that ran here, oldest run first.
    pub fn known_pipelines(&self) -> Vec<KnownPipeline> {
        let mut out: Vec<KnownPipeline> = fs::read_dir(self.dir("runs").join("pipelines"))
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .filter(|e| {
                        let n = e.file_name();
                        let n = n.to_string_lossy();
                        n.ends_with(".json") && !n.starts_with('.')
                    })
                    .filter_map(|e| read_record(&e.path()))
                    .collect()
            })
            .unwrap_or_default();
        out.sort_by(|a, b| a.last_run.total_cmp(&b.last_run));
        out
    }
}

fn read_record(path: &Path) -> Option<KnownPipeline> {
    serde_json::from_slice(&fs::read(path).ok()?).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pipeline_is_recorded_once_per_file_and_keeps_its_keys_when_a_run_starts() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let (a, b) = (Path::new("/x/a.yaml"), Path::new("/x/b.yaml"));
        store.record_pipeline(a, Some(vec!["k1".into()])).unwrap();
        store.record_pipeline(b, Some(vec!["k2".into()])).unwrap();
        store.record_pipeline(a, None).unwrap();
        let known = store.known_pipelines();
        assert_eq!(known.len(), 2, "{known:?}");
        let a_rec = known.iter().find(|k| k.file == a).unwrap();
        assert_eq!(a_rec.keys, ["k1"]);
        store.record_pipeline(a, Some(vec!["k3".into()])).unwrap();
        let known = store.known_pipelines();
        assert_eq!(known.last().unwrap().file, a, "the latest run comes last");
        assert_eq!(known.last().unwrap().keys, ["k3"]);
    }
}
