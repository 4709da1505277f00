//! What a run is asked to do.

/// Which scenes of a scene pipeline a run covers.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub enum Scenes {
    /// Every stage: all scenes and the dataset stages (also a pipeline without scenes).
    #[default]
    All,
    /// The stages of these scenes only (`--scene NAME`).
    Named(Vec<String>),
    /// The dataset stages only; every scene must be up to date already.
    Dataset,
}

/// What to run.
#[derive(Debug, Default, Clone)]
pub struct RunOptions {
    /// Which scenes (of a pipeline with `scenes:`).
    pub scenes: Scenes,
    /// Run this stage and everything it depends on.
    pub until: Option<String>,
    /// Run only this stage (its inputs must be up to date).
    pub only: Option<String>,
    /// Re-run these stages even when cached.
    pub force: Vec<String>,
    pub force_all: bool,
    pub dry_run: bool,
    pub no_wait: bool,
    /// Stages that may run at once (independent branches only).
    pub jobs: usize,
    /// After a failure, go on with what does not depend on it.
    pub keep_going: bool,
    /// Hash every cached file even when unchanged since last verified.
    pub verify: bool,
    /// Compute every stale stage from scratch: no stage updates its previous run.
    pub cold: bool,
    /// Update a stage that can (see [`crate::runner::parent`]) even where its entry from
    /// scratch is cached: for measuring updates (`pipe bench --suite edits`).
    pub prefer_update: bool,
}
