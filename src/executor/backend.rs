//! What the coordinator asks of a place that runs scene tasks.

use std::{path::PathBuf, time::Duration};

use super::error::ExecutorError;

/// One try of one scene.
#[derive(Debug, Clone)]
pub struct Task {
    /// Position of the scene among the scenes this run hands out (the array index on Slurm).
    pub index: usize,
    pub scene: String,
    /// 1 for the first try.
    pub attempt: u32,
    /// Where the task's output goes.
    pub log: PathBuf,
}

/// A place that runs tasks.
pub trait Backend {
    /// Starts (or queues) these tasks.
    fn submit(&mut self, tasks: &[Task]) -> Result<(), ExecutorError>;
    /// Tasks that ended since the last call, with how they ended (`exit code 0`,
    /// `CANCELLED`, ...).
    fn poll(&mut self) -> Result<Vec<(Task, String)>, ExecutorError>;
    /// (waiting, running) tasks.
    fn counts(&self) -> (usize, usize);
    /// Stops every task this backend started; says what it did.
    fn cancel(&mut self) -> String;
    /// Seconds between two polls.
    fn poll_interval(&self) -> Duration;
    /// A short name for progress lines (`local`, `slurm job 12`).
    fn label(&self) -> String;
}

/// Single-quotes `s` for a POSIX shell.
pub fn shell_quote(s: &str) -> String {
    if !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./=@:,+%".contains(c))
    {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', "'\\''"))
    }
}
