//! The local executor's worker processes: each task is `pipe run --scene NAME` (this very
//! binary), at most `jobs` at once, its output in the task's log file.

use std::{
    collections::VecDeque,
    fs::File,
    process::{Child, Command, Stdio},
    time::Duration,
};

use super::{
    backend::{Backend, Task},
    error::ExecutorError,
};
use crate::error::IoContext;

pub struct Local {
    exe: std::path::PathBuf,
    args: Vec<String>,
    jobs: usize,
    queue: VecDeque<Task>,
    running: Vec<(Task, Child)>,
}

impl Local {
    /// `args`: the `pipe` arguments up to `--scene` (see [`super::task_args`]).
    pub fn new(args: Vec<String>, jobs: usize) -> Result<Local, ExecutorError> {
        Ok(Local {
            exe: std::env::current_exe().io_context(|| "finding the pipe binary".into())?,
            args,
            jobs: jobs.max(1),
            queue: VecDeque::new(),
            running: Vec::new(),
        })
    }

    fn start(&mut self, task: Task) -> Result<(), ExecutorError> {
        let what = || format!("creating log file {}", task.log.display());
        let log = File::create(&task.log).io_context(what)?;
        let out = log.try_clone().io_context(what)?;
        let child = Command::new(&self.exe)
            .args(&self.args)
            .arg(&task.scene)
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(log)
            .spawn()
            .io_context(|| format!("starting {}", self.exe.display()))?;
        self.running.push((task, child));
        Ok(())
    }
}

impl Backend for Local {
    fn submit(&mut self, tasks: &[Task]) -> Result<(), ExecutorError> {
        self.queue.extend(tasks.iter().cloned());
        Ok(())
    }

    fn poll(&mut self) -> Result<Vec<(Task, String)>, ExecutorError> {
        let mut ended = Vec::new();
        let mut k = 0;
        while k < self.running.len() {
            let (task, child) = &mut self.running[k];
            let status = child
                .try_wait()
                .io_context(|| format!("waiting for the task of scene {}", task.scene))?;
            match status {
                Some(status) => {
                    let (task, _) = self.running.swap_remove(k);
                    let how = match status.code() {
                        Some(c) => format!("exit code {c}"),
                        None => {
                            use std::os::unix::process::ExitStatusExt;
                            format!("killed by signal {}", status.signal().unwrap_or(0))
                        }
                    };
                    ended.push((task, how));
                }
                None => k += 1,
            }
        }
        while self.running.len() < self.jobs {
            let Some(task) = self.queue.pop_front() else {
                break;
            };
            self.start(task)?;
        }
        Ok(ended)
    }

    fn counts(&self) -> (usize, usize) {
        (self.queue.len(), self.running.len())
    }

    fn cancel(&mut self) -> String {
        let n = self.running.len();
        for (_, child) in &mut self.running {
            let _ = child.kill();
            let _ = child.wait();
        }
        self.running.clear();
        self.queue.clear();
        format!("stopped {n} worker processes")
    }

    fn poll_interval(&self) -> Duration {
        Duration::from_millis(100)
    }

    fn label(&self) -> String {
        format!("local ({} workers)", self.jobs)
    }
}
