//! A validated pipeline: stage instances with their kind, canonical parameters and inputs.

use std::{collections::BTreeMap, path::PathBuf};

use serde_json::Value;
use stages::Stage;

use super::{error::Loc, slurm::SlurmConfig};

/// One stage instance, validated.
pub struct StageDecl {
    /// The scene this instance belongs to (`None`: a plain or dataset-level stage).
    pub scene: Option<String>,
    /// The name of the stage in the file (`train` for the instance `train@seed1`).
    pub template: String,
    /// Gathered input slots of a dataset stage: slot -> (scene, stage instance) for every
    /// scene, in scene order.
    pub gather: BTreeMap<String, Vec<(String, String)>>,
    pub name: String,
    pub kind: Box<dyn Stage>,
    /// Canonical parameters: every param of the kind, defaults filled in, serialised by the
    /// kind's own type (so `lr: 1` and `lr: 1.0` are the same).
    pub params: Value,
    /// Input slot -> upstream stage instance name.
    pub inputs: BTreeMap<String, String>,
    pub loc: Loc,
}

/// A validated pipeline.
pub struct Pipeline {
    pub file: PathBuf,
    /// Cache directory (absolute or relative to the working directory).
    pub cache_dir: PathBuf,
    /// Stage instances in file order (scene by scene, then the dataset stages).
    pub stages: Vec<StageDecl>,
    /// Scene names in file order; empty when the file declares no `scenes:`.
    pub scenes: Vec<String>,
    /// `executor.slurm` of the file.
    pub slurm: SlurmConfig,
}

impl Pipeline {
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }

    /// Indices of the stage instances of `scene`.
    pub fn scene_stages(&self, scene: &str) -> Vec<usize> {
        (0..self.stages.len())
            .filter(|&i| self.stages[i].scene.as_deref() == Some(scene))
            .collect()
    }

    /// Indices of the dataset-level stages (those of no scene, in a scene pipeline).
    pub fn dataset_stages(&self) -> Vec<usize> {
        if self.scenes.is_empty() {
            return Vec::new();
        }
        (0..self.stages.len())
            .filter(|&i| self.stages[i].scene.is_none())
            .collect()
    }

    /// Instances named `name`: the stage itself, or a template's instance in each of `scenes`.
    pub fn instances(&self, name: &str, scenes: &[String]) -> Vec<usize> {
        if let Some(i) = self.index_of(name) {
            return vec![i];
        }
        (0..self.stages.len())
            .filter(|&i| {
                let s = &self.stages[i];
                s.template == name && s.scene.as_ref().is_some_and(|sc| scenes.contains(sc))
            })
            .collect()
    }
}

impl StageDecl {
    /// Every upstream stage instance, plain and gathered.
    pub fn upstream_names(&self) -> impl Iterator<Item = &String> {
        self.inputs
            .values()
            .chain(self.gather.values().flatten().map(|(_, up)| up))
    }
}
