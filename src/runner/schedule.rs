//! The schedule of a run: which stage comes next. A stage is decided once its inputs are done:
//! skipped (an input failed), cached (a verified entry exists), would run (`--dry-run`), or
//! started on a blocking thread as a [`Job`] when fewer than `--jobs` run. A finished job's
//! outputs feed the keys of the stages below it.

use std::{
    collections::{BTreeMap, BTreeSet, HashMap},
    sync::Arc,
    time::Instant,
};

use tokio::task::JoinSet;

use super::{
    error::{RunError, StageFailure},
    execute::{Finished, Job, Loaded, SceneManifests},
    options::RunOptions,
    parent::{find_parent, short_key, updated_key, Found, Parent},
    plan::{explain, key_of},
    progress::Bars,
    report::{Outcome, RunReport, StageReport},
};
use crate::{
    config::Pipeline,
    dag::Dag,
    error::chain,
    store::{Entry, InputInfo, Manifest, RunRecord, Store},
};

/// A fresh row of the run report for stage `i`.
fn report(
    p: &Pipeline,
    i: usize,
    outcome: Outcome,
    reason: String,
    key: Option<String>,
) -> StageReport {
    StageReport {
        stage: p.stages[i].name.clone(),
        kind: p.stages[i].kind.kind().to_string(),
        outcome,
        reason,
        key,
        wall_s: 0.0,
        cpu_s: 0.0,
        peak_rss_bytes: 0,
        overhead_s: 0.0,
    }
}

/// The record of a stage's run with this key and these inputs.
fn run_record(
    p: &Pipeline,
    i: usize,
    key: String,
    inputs: BTreeMap<String, InputInfo>,
) -> RunRecord {
    let s = &p.stages[i];
    RunRecord {
        key,
        kind: s.kind.kind().into(),
        version: s.kind.version(),
        params: s.params.clone(),
        inputs,
        history: vec![],
    }
}

/// The state of a run between the starts and ends of its stages.
pub(super) struct Scheduler<'a> {
    p: &'a Arc<Pipeline>,
    dag: &'a Dag,
    store: &'a Arc<Store>,
    opts: &'a RunOptions,
    /// Digests of the files outside the cache, by stage.
    external: HashMap<usize, String>,
    /// The stages the run brings up to date.
    selected: BTreeSet<usize>,
    /// The selected stages and what they read (which must be fresh).
    needed: BTreeSet<usize>,
    force: BTreeSet<usize>,
    bars: Bars,
    loaded: Loaded,
    /// Output digests and manifests of the stages done so far.
    digests: HashMap<usize, String>,
    manifests: HashMap<usize, Box<Manifest>>,
    reports: HashMap<usize, StageReport>,
    failed: BTreeSet<usize>,
    /// In a dry run: the stages that would run (their outputs, unknown yet, make everything
    /// downstream of them run too).
    would_run: BTreeSet<usize>,
    /// Entries found corrupt when read this run (moved to trash/), by stage: the stage is
    /// computed again, once, and this is why.
    repairs: HashMap<usize, String>,
    /// Stages started again after such a repair (once each).
    retried: BTreeSet<usize>,
    done: BTreeSet<usize>,
    in_flight: BTreeSet<usize>,
    /// No stage starts any more (after a failure without `--keep-going`).
    stop: bool,
    /// Stages started so far, for `[n/total]`.
    started: usize,
    /// The inputs (with their entries' keys, and the parent of an update) of stages started.
    started_inputs: HashMap<usize, BTreeMap<String, InputInfo>>,
}

impl<'a> Scheduler<'a> {
    pub fn new(
        p: &'a Arc<Pipeline>,
        dag: &'a Dag,
        store: &'a Arc<Store>,
        opts: &'a RunOptions,
        selected: BTreeSet<usize>,
        external: HashMap<usize, String>,
    ) -> Scheduler<'a> {
        let force: BTreeSet<usize> = if opts.force_all {
            selected.clone()
        } else {
            opts.force.iter().filter_map(|f| p.index_of(f)).collect()
        };
        // Stages outside the selection that selected ones read (for --only) must be fresh.
        let needed: BTreeSet<usize> = selected
            .iter()
            .flat_map(|&i| dag.ancestors_and_self(i))
            .collect();
        Scheduler {
            p,
            dag,
            store,
            opts,
            external,
            selected,
            needed,
            force,
            bars: Bars::new(),
            loaded: Arc::default(),
            digests: HashMap::new(),
            manifests: HashMap::new(),
            reports: HashMap::new(),
            failed: BTreeSet::new(),
            would_run: BTreeSet::new(),
            repairs: HashMap::new(),
            retried: BTreeSet::new(),
            done: BTreeSet::new(),
            in_flight: BTreeSet::new(),
            stop: false,
            started: 0,
            started_inputs: HashMap::new(),
        }
    }

    /// Decides every stage whose inputs are done, starting jobs on `running`, until nothing
    /// more can be decided before a job ends.
    pub fn start_ready(&mut self, running: &mut JoinSet<Finished>) -> Result<(), RunError> {
        let dag = self.dag;
        let mut progressed = true;
        while progressed && !self.stop {
            progressed = false;
            for &i in &dag.order {
                progressed |= self.visit(i, running)?;
            }
        }
        Ok(())
    }

    /// Decides stage `i` if it is due: whether it did.
    fn visit(&mut self, i: usize, running: &mut JoinSet<Finished>) -> Result<bool, RunError> {
        if self.done.contains(&i) || self.in_flight.contains(&i) || !self.needed.contains(&i) {
            return Ok(false);
        }
        let ups = self.dag.upstream(i);
        if !ups.iter().all(|u| self.done.contains(u)) {
            return Ok(false);
        }
        let p = self.p;
        if let Some(&first) = ups.iter().find(|u| self.would_run.contains(u)) {
            // Dry run: the upstream's new outputs decide this stage's key; it runs after it.
            let why = format!("upstream `{}` would run first", p.stages[first].name);
            if !self.selected.contains(&i) {
                return Err(RunError::NotUpToDate {
                    only: self.opts.only.clone(),
                    stage: p.stages[i].name.clone(),
                    reason: why,
                });
            }
            self.reports
                .insert(i, report(p, i, Outcome::WouldRun, why, None));
            self.would_run.insert(i);
            self.done.insert(i);
            return Ok(true);
        }
        if let Some(&bad) = ups
            .iter()
            .find(|u| self.failed.contains(u) || !self.digests.contains_key(u))
        {
            let why = if self.failed.contains(&bad) {
                format!("upstream `{}` failed", p.stages[bad].name)
            } else {
                format!("upstream `{}` did not run", p.stages[bad].name)
            };
            self.failed.insert(i);
            self.reports
                .insert(i, report(p, i, Outcome::Skipped, why, None));
            self.done.insert(i);
            return Ok(true);
        }
        let ov0 = Instant::now();
        let (key, mut inputs) = key_of(p, i, &self.digests, &self.external).expect("inputs done");
        self.attach_keys(i, &mut inputs);
        // Measuring updates (`RunOptions::prefer_update`): the update, though the entry from
        // scratch is cached.
        let prefer = self.opts.prefer_update
            && matches!(self.parent_for(i, &key, &inputs), Ok(Found::Parent(par)) if par.differs(&inputs))
            && matches!(self.store.check(&key, false), Entry::Valid(_));
        let reason = if prefer {
            "its entry from scratch is cached, but updates are measured".to_string()
        } else {
            let Some(reason) = self.why_run(i, &key, &inputs, ov0)? else {
                return Ok(true);
            };
            reason
        };
        let (key, reason, parent) = match self.parent_for(i, &key, &inputs) {
            Ok(Found::Parent(parent)) => {
                let (ukey, uinputs) = parent.key(p, i, &inputs);
                let why = format!(
                    "{reason}; updating entry {} ({})",
                    parent.short(),
                    parent.what_changed()
                );
                inputs = uinputs;
                let Some(why) = self.why_run(i, &ukey, &inputs, ov0)?.map(|_| why) else {
                    return Ok(true);
                };
                (ukey, why, Some(parent))
            }
            Ok(Found::Current(parent)) => {
                // The last run updated `parent` from these inputs: its entry, unless it is gone
                // (then this computes from scratch).
                let (ukey, uinputs) = updated_key(p, i, &parent, &inputs);
                if let Entry::Valid(m) = self.store.check(&ukey, self.opts.verify) {
                    self.cached(i, &ukey, &uinputs, m, ov0)?;
                    return Ok(true);
                }
                (key, reason, None)
            }
            Err(Some(no)) => (key, format!("{reason}; from scratch: {no}"), None),
            Err(None) => (key, reason, None),
        };
        if !self.selected.contains(&i) {
            return Err(RunError::NotUpToDate {
                only: self.opts.only.clone(),
                stage: p.stages[i].name.clone(),
                reason,
            });
        }
        if self.opts.dry_run {
            self.reports
                .insert(i, report(p, i, Outcome::WouldRun, reason, Some(key)));
            self.would_run.insert(i);
            self.done.insert(i);
            return Ok(true);
        }
        if let Some(why) = self.store.read_only() {
            return Err(RunError::ReadOnly {
                cache: self.store.root().to_path_buf(),
                why: why.to_string(),
                stage: p.stages[i].name.clone(),
                reason,
            });
        }
        if self.in_flight.len() >= self.opts.jobs.max(1) {
            return Ok(false);
        }
        self.started_inputs.insert(i, inputs);
        self.start(i, key, reason, parent, ov0, running);
        Ok(true)
    }

    /// Adds to `inputs` of stage `i` the keys of the entries its slots read.
    fn attach_keys(&self, i: usize, inputs: &mut BTreeMap<String, InputInfo>) {
        let p = self.p;
        for (slot, up) in &p.stages[i].inputs {
            if let (Some(info), Some(m)) = (
                inputs.get_mut(slot),
                self.manifests.get(&p.index_of(up).expect("validated")),
            ) {
                info.key = Some(m.key.clone());
            }
        }
    }

    /// The entry stage `i` updates instead of computing from scratch (see [`find_parent`]). A
    /// forced stage computes its entry again the same way (an update stays an update; where
    /// the entry from scratch of `key` is cached, that is the one the stage stands on).
    fn parent_for(
        &self,
        i: usize,
        key: &str,
        inputs: &BTreeMap<String, InputInfo>,
    ) -> Result<Found, Option<String>> {
        if self.opts.cold || self.repairs.contains_key(&i) {
            return Err(None);
        }
        let forced = self.force.contains(&i);
        if forced
            && !self.opts.prefer_update
            && matches!(self.store.check(key, false), Entry::Valid(_))
        {
            return Err(None);
        }
        let p = self.p;
        let current = |slot: &str| {
            let up = p.stages[i].inputs.get(slot)?;
            self.manifests.get(&p.index_of(up)?).cloned()
        };
        find_parent(p, i, self.store, inputs, &current, forced)
    }

    /// Why stage `i` must run, or `None` when its entry is valid (then it is done: cached).
    /// A corrupt entry is moved aside (not in a dry run).
    fn why_run(
        &mut self,
        i: usize,
        key: &str,
        inputs: &BTreeMap<String, InputInfo>,
        ov0: Instant,
    ) -> Result<Option<String>, RunError> {
        let p = self.p;
        Ok(Some(match self.store.check(key, self.opts.verify) {
            Entry::Valid(m) if !self.force.contains(&i) => {
                self.cached(i, key, inputs, m, ov0)?;
                return Ok(None);
            }
            Entry::Valid(_) => "forced".to_string(),
            // (A read-only cache cannot move it aside: the run stops, saying both.)
            Entry::Corrupt(why) if self.opts.dry_run || self.store.read_only().is_some() => {
                format!("cache entry corrupt: {why}")
            }
            Entry::Corrupt(why) => {
                let dest = self.store.quarantine(key)?;
                let msg = format!("cache entry corrupt: {why} (moved to {})", dest.display());
                let name = &p.stages[i].name;
                self.bars.log(&format!("warning: stage `{name}`: {msg}"));
                msg
            }
            Entry::Missing => match self.repairs.get(&i) {
                Some(why) => why.clone(),
                None => explain(p, i, self.store, key, inputs),
            },
        }))
    }

    /// Stage `i` is up to date: its entry `m` feeds the stages below it.
    fn cached(
        &mut self,
        i: usize,
        key: &str,
        inputs: &BTreeMap<String, InputInfo>,
        m: Box<Manifest>,
        ov0: Instant,
    ) -> Result<(), RunError> {
        let p = self.p;
        self.digests.insert(i, m.output_digest.clone());
        if self.selected.contains(&i) {
            let why = match (&m.parent, &m.redone) {
                (Some(parent), Some(redone)) => {
                    format!("up to date (updated from {}: {redone})", short_key(parent))
                }
                _ => "up to date".into(),
            };
            let mut r = report(p, i, Outcome::Cached, why, Some(key.into()));
            r.overhead_s = ov0.elapsed().as_secs_f64();
            self.reports.insert(i, r);
            // Keep status explanations current even when the entry came from elsewhere.
            let name = &p.stages[i].name;
            if !self.opts.dry_run
                && self.store.read_only().is_none()
                && self.store.run_record(name).map(|r| r.key).as_deref() != Some(key)
            {
                let rec = run_record(p, i, key.into(), inputs.clone());
                self.store.save_run_record(name, rec)?;
            }
        }
        self.manifests.insert(i, m);
        self.done.insert(i);
        Ok(())
    }

    /// Starts computing stage `i` on a blocking thread.
    fn start(
        &mut self,
        i: usize,
        key: String,
        reason: String,
        parent: Option<Parent>,
        ov0: Instant,
        running: &mut JoinSet<Finished>,
    ) {
        let p = self.p;
        let s = &p.stages[i];
        self.started += 1;
        let reason = reason.replace('\n', " ");
        let running_line = format!(
            "[{}/{}] {} `{}` ({}): {reason}",
            self.started,
            self.selected.len(),
            if parent.is_some() {
                "updating"
            } else {
                "running"
            },
            s.name,
            s.kind.kind()
        );
        let bar = self.bars.bar(&s.name);
        let manifest_of = |up: &String| self.manifests[&p.index_of(up).unwrap()].clone();
        let upstream: Vec<(String, Box<Manifest>)> = s
            .inputs
            .iter()
            .map(|(slot, up)| (slot.clone(), manifest_of(up)))
            .collect();
        let gathered: Vec<(String, SceneManifests)> = s
            .gather
            .iter()
            .map(|(slot, ups)| {
                let ms = ups
                    .iter()
                    .map(|(scene, up)| (scene.clone(), manifest_of(up)))
                    .collect();
                (slot.clone(), ms)
            })
            .collect();
        let job = Job {
            p: p.clone(),
            i,
            store: self.store.clone(),
            loaded: self.loaded.clone(),
            key: key.clone(),
            no_wait: self.opts.no_wait,
            forced: self.force.contains(&i),
            upstream,
            gathered,
            inputs: self.started_inputs.get(&i).cloned().unwrap_or_default(),
            parent,
            pre_overhead: ov0.elapsed().as_secs_f64(),
            running_line,
            bar,
            bars: self.bars.clone(),
        };
        self.reports
            .insert(i, report(p, i, Outcome::Ran, reason, Some(key)));
        self.in_flight.insert(i);
        running.spawn_blocking(move || job.run());
    }

    /// Takes in a job that ended: its entry feeds the stages below it, or its failure stops
    /// the run (unless `--keep-going`).
    pub fn finish(&mut self, f: Finished) -> Result<(), RunError> {
        let Finished {
            i,
            result,
            reused,
            wall,
            cpu,
            rss,
        } = f;
        self.in_flight.remove(&i);
        if let Err(StageFailure::InputCorrupt {
            stage, why, moved, ..
        }) = &result
        {
            if self.repair(i, stage, why, moved.as_deref()) {
                return Ok(());
            }
        }
        self.done.insert(i);
        let r = self.reports.get_mut(&i).expect("report created at start");
        r.wall_s = wall;
        r.cpu_s = cpu;
        r.peak_rss_bytes = rss;
        match result {
            Ok((mut m, overhead)) => {
                r.overhead_s += overhead;
                if reused {
                    r.outcome = Outcome::Cached;
                    r.reason = "computed meanwhile by another run".into();
                } else if let (Some(parent), Some(redone)) = (&m.parent, &m.redone) {
                    r.outcome = Outcome::Updated;
                    r.reason = format!("updated from {}: {redone}", short_key(parent));
                }
                let key = r.key.clone().unwrap_or_default();
                let inputs = self.started_inputs.remove(&i).unwrap_or_else(|| {
                    key_of(self.p, i, &self.digests, &self.external)
                        .expect("inputs done")
                        .1
                });
                m.inputs = inputs.clone();
                let rec = run_record(self.p, i, key, inputs);
                self.store.save_run_record(&self.p.stages[i].name, rec)?;
                self.digests.insert(i, m.output_digest.clone());
                self.manifests.insert(i, Box::new(m));
            }
            Err(e) => {
                r.outcome = Outcome::Failed;
                r.reason = chain(&e);
                self.bars.log(&format!("error: {}", r.reason));
                self.failed.insert(i);
                if !self.opts.keep_going {
                    self.stop = true;
                }
            }
        }
        Ok(())
    }

    /// Stage `i` found the entry of its input `up` corrupt when it read it (moved to `moved`):
    /// `up` is computed again and `i` after it. Whether that was arranged (once per stage: a
    /// second failure is reported as a failure).
    fn repair(&mut self, i: usize, up: &str, why: &str, moved: Option<&std::path::Path>) -> bool {
        let Some(u) = self.p.index_of(up) else {
            return false;
        };
        if !self.selected.contains(&u) || !self.retried.insert(i) {
            return false;
        }
        self.reports.remove(&i);
        if self.repairs.contains_key(&u) {
            return true; // another reader found it first: `i` waits for it too
        }
        let msg = match moved {
            Some(d) => format!("cache entry corrupt: {why} (moved to {})", d.display()),
            None => format!("cache entry corrupt: {why}"),
        };
        self.bars.log(&format!(
            "warning: stage `{up}`: {msg}; computing it again for `{}`",
            self.p.stages[i].name
        ));
        self.repairs.insert(u, msg);
        self.done.remove(&u);
        self.reports.remove(&u);
        self.digests.remove(&u);
        self.manifests.remove(&u);
        true
    }

    /// The report of the run, in topological order; selected stages that never started (after
    /// a failure without `--keep-going`) count as skipped.
    pub fn into_report(mut self, wall_s: f64) -> RunReport {
        for &i in &self.dag.order {
            if self.selected.contains(&i) && !self.reports.contains_key(&i) {
                let why = "not started after an earlier failure".into();
                self.reports
                    .insert(i, report(self.p, i, Outcome::Skipped, why, None));
            }
        }
        let stages: Vec<StageReport> = self
            .dag
            .order
            .iter()
            .filter(|i| self.selected.contains(i))
            .filter_map(|i| self.reports.remove(i))
            .collect();
        let failed = stages
            .iter()
            .any(|r| matches!(r.outcome, Outcome::Failed | Outcome::Skipped));
        RunReport {
            stages,
            wall_s,
            failed,
        }
    }
}
