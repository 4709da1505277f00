//! The Slurm executor: the stale scenes go to one job array (`sbatch --array=0-K%M`), each
//! task running `pipe run --scene NAME` on the shared cache; the coordinator follows the array
//! with `squeue` (and `scontrol`/`sacct` for how a task ended), resubmits failed tasks as a
//! new array of just those indices, and `scancel`s everything on Ctrl-C. Nothing here needs
//! Slurm accounting (slurmdbd).

use std::{
    collections::BTreeMap,
    path::{Path, PathBuf},
    process::Command,
    time::Duration,
};

use super::{
    backend::{shell_quote, Backend, Task},
    error::ExecutorError,
};
use crate::{
    config::SlurmConfig,
    error::{chain, IoContext},
    store::write_atomic,
};

/// How a task ended when neither `scontrol` nor `sacct` knows it any more.
pub const UNKNOWN_END: &str = "ended (state unknown to scontrol and sacct)";

pub struct Slurm {
    cfg: SlurmConfig,
    /// The task command up to the scene name, quoted for the shell.
    command: String,
    /// Array index -> scene.
    scenes: Vec<String>,
    dir: PathBuf,
    dry_run: bool,
    /// (job id, array index) -> the task and its last seen state.
    active: BTreeMap<(String, usize), (Task, String)>,
    squeue_failures: u32,
}

/// Runs a Slurm command; its stdout, or an error with its stderr.
fn slurm(cmd: &str, args: &[String]) -> Result<String, ExecutorError> {
    let out = Command::new(cmd)
        .args(args)
        .output()
        .io_context(|| format!("running `{cmd}` (is Slurm installed and on PATH?)"))?;
    if !out.status.success() {
        return Err(ExecutorError::Slurm {
            command: format!("{cmd} {}", args.join(" ")),
            status: out.status.to_string(),
            stderr: String::from_utf8_lossy(&out.stderr).trim().to_string(),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Array indices as sbatch writes them: runs of consecutive indices as `a-b` (`0-2,5`).
fn array_ranges(indices: &[usize]) -> String {
    let mut sorted = indices.to_vec();
    sorted.sort_unstable();
    let mut parts: Vec<String> = Vec::new();
    let mut k = 0;
    while k < sorted.len() {
        let start = sorted[k];
        while k + 1 < sorted.len() && sorted[k + 1] == sorted[k] + 1 {
            k += 1;
        }
        parts.push(if sorted[k] == start {
            start.to_string()
        } else {
            format!("{start}-{}", sorted[k])
        });
        k += 1;
    }
    parts.join(",")
}

impl Slurm {
    /// `args`: the `pipe` arguments up to `--scene`; `scenes`: the array's scenes by index;
    /// `dir`: where the task script and logs go (on the shared file system).
    pub fn new(
        cfg: &SlurmConfig,
        args: Vec<String>,
        scenes: &[String],
        dir: &Path,
        dry_run: bool,
    ) -> Result<Slurm, ExecutorError> {
        let pipe = match &cfg.pipe {
            Some(p) => p.clone(),
            None => std::env::current_exe()
                .io_context(|| "finding the pipe binary".into())?
                .to_string_lossy()
                .into_owned(),
        };
        let command = std::iter::once(pipe.as_str())
            .chain(args.iter().map(String::as_str))
            .map(shell_quote)
            .collect::<Vec<_>>()
            .join(" ");
        Ok(Slurm {
            cfg: cfg.clone(),
            command,
            scenes: scenes.to_vec(),
            dir: dir.to_path_buf(),
            dry_run,
            active: BTreeMap::new(),
            squeue_failures: 0,
        })
    }

    fn script_path(&self) -> PathBuf {
        self.dir.join("task.sh")
    }

    /// The batch script every array task runs.
    fn script(&self) -> String {
        let scenes: Vec<String> = self.scenes.iter().map(|s| shell_quote(s)).collect();
        format!(
            "#!/bin/bash\n\
             # Written by `pipe run --executor slurm`: array task i runs scene i.\n\
             scenes=({})\n\
             scene=${{scenes[$SLURM_ARRAY_TASK_ID]}}\n\
             exec >>{}/\"$scene.try${{PIPE_TRY:-1}}.log\" 2>&1\n\
             echo \"pipe task: scene $scene, try ${{PIPE_TRY:-1}}, job ${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}} on $(hostname) at $(date -Is)\"\n\
             {}\n\
             exec {} \"$scene\"\n",
            scenes.join(" "),
            shell_quote(&self.dir.to_string_lossy()),
            self.cfg.setup.as_deref().unwrap_or(""),
            self.command
        )
    }

    /// sbatch's arguments for these array indices and try.
    fn sbatch_args(&self, indices: &[usize], attempt: u32) -> Vec<String> {
        let list = array_ranges(indices);
        let throttle = self
            .cfg
            .max_parallel
            .map_or(String::new(), |m| format!("%{m}"));
        let mut a = vec![
            "--parsable".to_string(),
            format!(
                "--job-name={}",
                self.cfg.job_name.as_deref().unwrap_or("pipe")
            ),
            format!("--array={list}{throttle}"),
            format!("--output={}/slurm-%A_%a.out", self.dir.display()),
            format!("--export=ALL,PIPE_TRY={attempt}"),
        ];
        if let Some(x) = &self.cfg.partition {
            a.push(format!("--partition={x}"));
        }
        if let Some(x) = self.cfg.cpus_per_task {
            a.push(format!("--cpus-per-task={x}"));
        }
        if let Some(x) = self.cfg.gpus {
            a.push(format!("--gres=gpu:{x}"));
        }
        if let Some(x) = &self.cfg.mem {
            a.push(format!("--mem={x}"));
        }
        if let Some(x) = &self.cfg.time {
            a.push(format!("--time={x}"));
        }
        a.extend(self.cfg.sbatch_args.iter().cloned());
        a.push(self.script_path().to_string_lossy().into_owned());
        a
    }

    fn job_ids(&self) -> Vec<String> {
        let mut ids: Vec<String> = self.active.keys().map(|(j, _)| j.clone()).collect();
        ids.dedup();
        ids
    }

    /// How a task that left the queue ended: `exit code 0`, or its state and exit code.
    /// `None` while Slurm still counts it as active.
    fn ended_how(job: &str, index: usize) -> Option<String> {
        let id = format!("{job}_{index}");
        let from = |state: &str, code: &str| -> Option<String> {
            let active = [
                "PENDING",
                "RUNNING",
                "CONFIGURING",
                "COMPLETING",
                "SUSPENDED",
                "REQUEUED",
                "RESIZING",
            ];
            if active.contains(&state) {
                return None;
            }
            let (exit, signal) = code.split_once(':').unwrap_or((code, "0"));
            Some(if state == "COMPLETED" && exit == "0" {
                "exit code 0".to_string()
            } else if signal != "0" {
                format!("{state}, exit code {exit}, signal {signal}")
            } else {
                format!("{state}, exit code {exit}")
            })
        };
        if let Ok(out) = slurm(
            "scontrol",
            &["show".into(), "job".into(), "-o".into(), id.clone()],
        ) {
            let field = |name: &str| {
                out.split_whitespace()
                    .find_map(|f| f.strip_prefix(name))
                    .map(str::to_string)
            };
            if let (Some(state), Some(code)) = (field("JobState="), field("ExitCode=")) {
                return from(&state, &code);
            }
        }
        let args: Vec<String> = ["-n", "-X", "-P", "-j", &id, "-o", "State,ExitCode"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        if let Ok(out) = slurm("sacct", &args) {
            if let Some((state, code)) = out.lines().next().and_then(|l| l.split_once('|')) {
                let state = state.split_whitespace().next().unwrap_or(state);
                return from(state, code.trim());
            }
        }
        Some(UNKNOWN_END.to_string())
    }
}

impl Backend for Slurm {
    fn submit(&mut self, tasks: &[Task]) -> Result<(), ExecutorError> {
        if tasks.is_empty() {
            return Ok(());
        }
        let mut by_try: BTreeMap<u32, Vec<&Task>> = BTreeMap::new();
        for t in tasks {
            by_try.entry(t.attempt).or_default().push(t);
        }
        for (attempt, group) in by_try {
            let indices: Vec<usize> = group.iter().map(|t| t.index).collect();
            let args = self.sbatch_args(&indices, attempt);
            if self.dry_run {
                println!(
                    "would write {}:\n{}",
                    self.script_path().display(),
                    self.script()
                );
                println!(
                    "would run: sbatch {}",
                    args.iter()
                        .map(|a| shell_quote(a))
                        .collect::<Vec<_>>()
                        .join(" ")
                );
                continue;
            }
            std::fs::create_dir_all(&self.dir)
                .io_context(|| format!("creating {}", self.dir.display()))?;
            write_atomic(&self.script_path(), self.script().as_bytes())?;
            let out = slurm("sbatch", &args)?;
            let job = out
                .trim()
                .split(';')
                .next()
                .filter(|j| !j.is_empty() && j.chars().all(|c| c.is_ascii_digit()))
                .ok_or_else(|| ExecutorError::NoJobId(out.clone()))?
                .to_string();
            eprintln!(
                "slurm: submitted job array {job} (tasks {}, try {attempt})",
                indices
                    .iter()
                    .map(|i| i.to_string())
                    .collect::<Vec<_>>()
                    .join(",")
            );
            for t in group {
                self.active
                    .insert((job.clone(), t.index), (t.clone(), "PENDING".into()));
            }
        }
        Ok(())
    }

    fn poll(&mut self) -> Result<Vec<(Task, String)>, ExecutorError> {
        if self.active.is_empty() {
            return Ok(Vec::new());
        }
        let ids = self.job_ids().join(",");
        let args: Vec<String> = ["-h", "-r", "-j", &ids, "-o", "%i %T"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let listed = match slurm("squeue", &args) {
            Ok(out) => {
                self.squeue_failures = 0;
                out
            }
            // A job that left the controller entirely is no error: its tasks ended.
            Err(ExecutorError::Slurm { stderr, .. }) if stderr.contains("Invalid job id") => {
                String::new()
            }
            Err(e) => {
                self.squeue_failures += 1;
                if self.squeue_failures >= 30 {
                    return Err(ExecutorError::SqueueFailing(Box::new(e)));
                }
                return Ok(Vec::new());
            }
        };
        let mut seen: BTreeMap<(String, usize), String> = BTreeMap::new();
        for line in listed.lines() {
            let mut it = line.split_whitespace();
            let (Some(id), Some(state)) = (it.next(), it.next()) else {
                continue;
            };
            if let Some((job, idx)) = id.split_once('_') {
                if let Ok(idx) = idx.parse() {
                    seen.insert((job.to_string(), idx), state.to_string());
                }
            }
        }
        let mut ended = Vec::new();
        let keys: Vec<(String, usize)> = self.active.keys().cloned().collect();
        for k in keys {
            if let Some(state) = seen.get(&k) {
                self.active.get_mut(&k).expect("listed").1 = state.clone();
                continue;
            }
            if let Some(how) = Self::ended_how(&k.0, k.1) {
                let (task, _) = self.active.remove(&k).expect("listed");
                ended.push((task, how));
            }
        }
        Ok(ended)
    }

    fn counts(&self) -> (usize, usize) {
        let waiting = self.active.values().filter(|(_, s)| s == "PENDING").count();
        (waiting, self.active.len() - waiting)
    }

    fn cancel(&mut self) -> String {
        let ids = self.job_ids();
        if ids.is_empty() {
            return "no slurm jobs to cancel".into();
        }
        let msg = match slurm("scancel", &ids) {
            Ok(_) => format!("cancelled slurm job(s) {}", ids.join(", ")),
            Err(e) => format!("scancel {} failed: {}", ids.join(" "), chain(&e)),
        };
        self.active.clear();
        msg
    }

    fn poll_interval(&self) -> Duration {
        Duration::from_secs_f64(self.cfg.poll_s.unwrap_or(5.0).clamp(0.1, 600.0))
    }

    fn label(&self) -> String {
        let ids = self.job_ids();
        match ids.len() {
            0 => "slurm".into(),
            1 => format!("slurm job {}", ids[0]),
            _ => format!("slurm jobs {}", ids.join(",")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_indices_are_written_as_ranges() {
        assert_eq!(array_ranges(&[0, 1, 2]), "0-2");
        assert_eq!(array_ranges(&[5, 0, 1, 3]), "0-1,3,5");
        assert_eq!(array_ranges(&[4]), "4");
    }
}
