//! Executes a pipeline: for each selected stage in dependency order, reuse its verified cache
//! entry or run it (on a blocking thread, tokio driving the schedule) and publish the outputs.
//! Also answers "is this stage fresh, and if not, why?" for `pipe status` and `--dry-run`.

use std::{
    collections::{BTreeMap, BTreeSet, HashMap},
    sync::{Arc, Mutex},
    time::Instant,
};

use anyhow::{anyhow, bail, Result};
use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use stages::{Inputs, Tables};
use tokio::task::JoinSet;

use crate::{
    config::Pipeline,
    dag::Dag,
    fingerprint,
    store::{unix_now, Entry, InputInfo, Manifest, RunRecord, Store},
};

/// Freshness of one stage instance.
#[derive(Debug, Clone)]
pub enum State {
    /// A verified entry exists for the current key.
    Fresh(Box<Manifest>),
    /// The stage must run; the sentence says why.
    Stale(String),
}

/// A stage's key (when all its inputs are known) and state.
#[derive(Debug, Clone)]
pub struct Resolved {
    pub key: Option<String>,
    pub inputs: BTreeMap<String, InputInfo>,
    pub state: State,
    /// The entry exists but failed verification.
    pub corrupt: bool,
}

/// Pseudo input slot under which the digest of a stage's external files enters its key.
pub const FILES_SLOT: &str = "@files";

/// Digests of the files outside the cache that stages read (`Stage::external_inputs`), by
/// stage index. Contents are hashed, memoised by path, size, mtime and inode.
pub fn external_digests(p: &Pipeline, store: &Store) -> Result<HashMap<usize, String>> {
    let mut out = HashMap::new();
    for (i, s) in p.stages.iter().enumerate() {
        let paths = s
            .kind
            .external_inputs(&s.params)
            .map_err(|e| anyhow!("stage `{}`: {e}", s.name))?;
        if !paths.is_empty() {
            out.insert(i, store.files_digest(&paths)?);
        }
    }
    Ok(out)
}

/// The key of stage `i` given the output digests of its upstream stages.
fn key_of(
    p: &Pipeline,
    i: usize,
    digests: &HashMap<usize, String>,
    external: &HashMap<usize, String>,
) -> Option<(String, BTreeMap<String, InputInfo>)> {
    let s = &p.stages[i];
    let mut inputs = BTreeMap::new();
    if let Some(d) = external.get(&i) {
        inputs.insert(
            FILES_SLOT.to_string(),
            InputInfo {
                stage: "(files outside the cache)".into(),
                digest: d.clone(),
            },
        );
    }
    for (slot, up) in &s.inputs {
        let u = p.index_of(up).expect("validated");
        inputs.insert(
            slot.clone(),
            InputInfo {
                stage: up.clone(),
                digest: digests.get(&u)?.clone(),
            },
        );
    }
    for (slot, ups) in &s.gather {
        // One digest over every scene's (name, output digest), in scene order.
        let mut h = blake3::Hasher::new();
        for (scene, up) in ups {
            let d = digests.get(&p.index_of(up).expect("validated"))?;
            h.update(scene.as_bytes());
            h.update(&[0]);
            h.update(d.as_bytes());
            h.update(b"\n");
        }
        let template = ups
            .first()
            .and_then(|(_, up)| up.split('@').next())
            .unwrap_or("?");
        inputs.insert(
            slot.clone(),
            InputInfo {
                stage: format!("{template}@* ({} scenes)", ups.len()),
                digest: h.finalize().to_hex().to_string(),
            },
        );
    }
    let by_digest = inputs
        .iter()
        .map(|(k, v)| (k.clone(), v.digest.clone()))
        .collect();
    let key = fingerprint::stage_key(s.kind.kind(), s.kind.version(), &s.params, &by_digest);
    Some((key, inputs))
}

fn show_value(v: &Value) -> String {
    crate::config::shorten(&v.to_string(), 48)
}

/// Appends `param `path` old -> new` for every leaf that differs (nested objects recursively).
fn diff_params(path: &str, old: &Value, new: &Value, why: &mut Vec<String>) {
    match (old, new) {
        (Value::Object(a), Value::Object(b)) => {
            let names: BTreeSet<&String> = a.keys().chain(b.keys()).collect();
            for n in names {
                let p = format!("{path}.{n}");
                match (a.get(n), b.get(n)) {
                    (Some(x), Some(y)) => diff_params(&p, x, y, why),
                    (None, Some(y)) => why.push(format!("param `{p}` added ({})", show_value(y))),
                    (Some(_), None) => why.push(format!("param `{p}` removed")),
                    (None, None) => {}
                }
            }
        }
        (a, b) if a != b => why.push(format!(
            "param `{path}` {} -> {}",
            show_value(a),
            show_value(b)
        )),
        _ => {}
    }
}

/// Why stage `i` (with current key `key`, or unknown) differs from its last recorded run.
fn explain(
    p: &Pipeline,
    i: usize,
    store: &Store,
    key: &str,
    inputs: &BTreeMap<String, InputInfo>,
) -> String {
    let s = &p.stages[i];
    let Some(rec) = store.run_record(&s.name) else {
        return "never run".into();
    };
    if rec.key == key {
        return "its cache entry was removed (gc, or moved aside as corrupt)".into();
    }
    let mut why = Vec::new();
    if rec.kind != s.kind.kind() {
        why.push(format!("kind `{}` -> `{}`", rec.kind, s.kind.kind()));
    } else if rec.version != s.kind.version() {
        why.push(format!(
            "code version of kind `{}` {} -> {}",
            rec.kind,
            rec.version,
            s.kind.version()
        ));
    }
    diff_params(&s.name, &rec.params, &s.params, &mut why);
    let slots: BTreeSet<&String> = rec.inputs.keys().chain(inputs.keys()).collect();
    for slot in slots {
        match (rec.inputs.get(slot), inputs.get(slot)) {
            (Some(a), Some(b)) if slot == FILES_SLOT && a.digest != b.digest => {
                why.push("its input files changed".to_string())
            }
            (Some(a), Some(b)) if a.stage != b.stage => why.push(format!(
                "input `{slot}` now comes from stage `{}` (was `{}`)",
                b.stage, a.stage
            )),
            (Some(a), Some(b)) if a.digest != b.digest => why.push(format!(
                "input `{slot}` changed (stage `{}` wrote different outputs)",
                b.stage
            )),
            (None, Some(b)) => why.push(format!("input `{slot}` connected to stage `{}`", b.stage)),
            (Some(_), None) => why.push(format!("input `{slot}` disconnected")),
            _ => {}
        }
    }
    if why.is_empty() {
        "its cache key changed".into()
    } else {
        why.join("; ")
    }
}

/// Freshness of every stage, in topological order, without running anything.
pub fn resolve(p: &Pipeline, dag: &Dag, store: &Store, full_verify: bool) -> Result<Vec<Resolved>> {
    let external = external_digests(p, store)?;
    let mut out: Vec<Option<Resolved>> = vec![None; p.stages.len()];
    let mut digests: HashMap<usize, String> = HashMap::new();
    for &i in &dag.order {
        let r = match key_of(p, i, &digests, &external) {
            None => {
                let s = &p.stages[i];
                let gathered = s
                    .gather
                    .iter()
                    .flat_map(|(slot, ups)| ups.iter().map(move |(_, up)| (slot, up)));
                let stale_up: Vec<String> = s
                    .inputs
                    .iter()
                    .chain(gathered)
                    .filter(|(_, up)| !digests.contains_key(&p.index_of(up).unwrap()))
                    .map(|(slot, up)| {
                        if slot == up {
                            format!("`{up}`")
                        } else {
                            format!("`{slot}` (stage `{up}`)")
                        }
                    })
                    .collect();
                Resolved {
                    key: None,
                    inputs: BTreeMap::new(),
                    state: State::Stale(format!("waits on stale input {}", stale_up.join(", "))),
                    corrupt: false,
                }
            }
            Some((key, inputs)) => match store.check(&key, full_verify) {
                Entry::Valid(m) => {
                    digests.insert(i, m.output_digest.clone());
                    Resolved {
                        key: Some(key),
                        inputs,
                        state: State::Fresh(m),
                        corrupt: false,
                    }
                }
                Entry::Corrupt(why) => Resolved {
                    key: Some(key),
                    inputs,
                    state: State::Stale(format!("cache entry corrupt: {why}")),
                    corrupt: true,
                },
                Entry::Missing => {
                    let why = explain(p, i, store, &key, &inputs);
                    Resolved {
                        key: Some(key),
                        inputs,
                        state: State::Stale(why),
                        corrupt: false,
                    }
                }
            },
        };
        out[i] = Some(r);
    }
    Ok(out
        .into_iter()
        .map(|r| r.expect("every stage resolved"))
        .collect())
}

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
}

/// How a stage ended in a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    Cached,
    Ran,
    Failed,
    Skipped,
    WouldRun,
}

/// One row of the run summary.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageReport {
    pub stage: String,
    pub kind: String,
    pub outcome: Outcome,
    pub reason: String,
    pub key: Option<String>,
    pub wall_s: f64,
    pub cpu_s: f64,
    pub peak_rss_bytes: u64,
    /// Time the runner spent on this stage beyond the stage body (hashing, loading, writing).
    pub overhead_s: f64,
}

/// The result of `pipe run`, also written to `.pipe/runs/last-run.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunReport {
    pub stages: Vec<StageReport>,
    pub wall_s: f64,
    pub failed: bool,
}

/// Which stages a run touches: the ones it brings up to date, and what they need.
pub fn selection(p: &Pipeline, dag: &Dag, opts: &RunOptions) -> Result<BTreeSet<usize>> {
    let scenes: Vec<String> = match &opts.scenes {
        Scenes::Named(list) => {
            if p.scenes.is_empty() {
                bail!(
                    "--scene {}: {} declares no scenes",
                    list.join(","),
                    p.file.display()
                );
            }
            for sc in list {
                if !p.scenes.contains(sc) {
                    bail!(
                        "--scene {sc}: no scene named `{sc}` in {} (scenes: {})",
                        p.file.display(),
                        p.scenes.join(", ")
                    );
                }
            }
            list.clone()
        }
        _ => p.scenes.clone(),
    };
    let find = |name: &str, flag: &str| {
        let found = p.instances(name, &scenes);
        if found.is_empty() {
            bail!(
                "{flag} {name}: no stage named `{name}` in {}",
                p.file.display()
            );
        }
        Ok(found)
    };
    for f in &opts.force {
        find(f, "--force")?;
    }
    let base: BTreeSet<usize> = match &opts.scenes {
        Scenes::All => (0..p.stages.len()).collect(),
        Scenes::Named(list) => list.iter().flat_map(|sc| p.scene_stages(sc)).collect(),
        Scenes::Dataset => p.dataset_stages().into_iter().collect(),
    };
    Ok(match (&opts.until, &opts.only) {
        (Some(_), Some(_)) => bail!("--until and --only cannot be combined"),
        (Some(u), None) => find(u, "--until")?
            .into_iter()
            .flat_map(|i| dag.ancestors_and_self(i))
            .collect(),
        (None, Some(o)) => find(o, "--only")?.into_iter().collect(),
        (None, None) => base,
    })
}

/// The tables a gathered input slot hands to a dataset stage: for each table the slot reads,
/// every scene's rows with a leading `scene` column, in scene order.
pub fn gather_tables(tables: &[&str], parts: &[(String, Arc<Tables>)]) -> Result<Tables> {
    use arrow::{
        array::{ArrayRef, StringArray},
        datatypes::{DataType, Field, Schema},
        record_batch::RecordBatch,
    };
    let mut out = Tables::new();
    for &t in tables {
        let mut batches = Vec::new();
        let mut schema = None;
        for (scene, part) in parts {
            let b = part
                .get(t)
                .ok_or_else(|| anyhow!("scene `{scene}` has no table `{t}`"))?;
            let mut fields = vec![Arc::new(Field::new("scene", DataType::Utf8, false))];
            fields.extend(b.schema().fields().iter().cloned());
            let sch = Arc::new(Schema::new(fields));
            let mut cols: Vec<ArrayRef> = vec![Arc::new(StringArray::from(vec![
                scene.as_str();
                b.num_rows()
            ]))];
            cols.extend(b.columns().iter().cloned());
            batches.push(RecordBatch::try_new(sch.clone(), cols)?);
            schema = Some(sch);
        }
        let schema = schema.ok_or_else(|| anyhow!("no scenes to gather table `{t}` from"))?;
        out.insert(
            t.to_string(),
            arrow::compute::concat_batches(&schema, &batches)?,
        );
    }
    Ok(out)
}

struct ProgressAdapter(ProgressBar);

impl stages::Progress for ProgressAdapter {
    fn update(&self, done: u64, total: u64, message: &str) {
        self.0.set_length(total.max(1));
        self.0.set_position(done);
        self.0.set_message(message.to_string());
    }
}

fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes into the struct we pass.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Resets the kernel's peak-RSS mark so the next reading covers only what follows.
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|kb| kb.parse::<u64>().ok())
            })
        })
        .map_or(0, |kb| kb * 1024)
}

/// The manifests of a gathered slot's stage in every scene: (scene, manifest).
type SceneManifests = Vec<(String, Box<Manifest>)>;

/// Tables already read from the cache during this run, by key.
type Loaded = Arc<Mutex<HashMap<String, Arc<Tables>>>>;

fn load_cached(store: &Store, loaded: &Loaded, m: &Manifest) -> Result<Arc<Tables>> {
    if let Some(t) = loaded.lock().unwrap().get(&m.key) {
        return Ok(t.clone());
    }
    let t = Arc::new(store.load(m)?);
    loaded.lock().unwrap().insert(m.key.clone(), t.clone());
    Ok(t)
}

/// Runs a stage body and checks its outputs against the kind's contract and schema files.
fn execute(
    p: &Pipeline,
    i: usize,
    inputs: &BTreeMap<String, Arc<Tables>>,
    bar: &ProgressBar,
) -> Result<Tables> {
    let s = &p.stages[i];
    let slots = inputs
        .iter()
        .map(|(k, v)| (k.clone(), v.as_ref()))
        .collect();
    let adapter = ProgressAdapter(bar.clone());
    let tables = s
        .kind
        .run(&s.params, &Inputs::new(slots), &adapter)
        .map_err(|e| anyhow!("stage `{}` (kind `{}`) failed: {e}", s.name, s.kind.kind()))?;
    let written: BTreeSet<&str> = tables.keys().map(String::as_str).collect();
    let declared: BTreeSet<&str> = s.kind.outputs().iter().copied().collect();
    if written != declared {
        bail!(
            "stage `{}` (kind `{}`) wrote tables {:?} but declares {:?}",
            s.name,
            s.kind.kind(),
            written,
            declared
        );
    }
    for (name, batch) in &tables {
        stages::schema::check(name, &batch.schema())
            .map_err(|e| anyhow!("stage `{}` (kind `{}`): {e}", s.name, s.kind.kind()))?;
    }
    Ok(tables)
}

/// A stage body that ended on its blocking thread: its published manifest and the runner's
/// overhead, or the error; wall/CPU seconds and peak RSS of the body.
struct Finished {
    i: usize,
    result: Result<(Manifest, f64)>,
    /// Another run published the entry while this one waited for its lock.
    reused: bool,
    wall: f64,
    cpu: f64,
    rss: u64,
}

/// Runs the pipeline. Stage failures are reported in the result (`failed`), not as `Err`;
/// `Err` means the run could not start or the cache could not be written.
pub async fn run(p: Arc<Pipeline>, opts: &RunOptions) -> Result<RunReport> {
    let t0 = Instant::now();
    let dag = Dag::build(&p)?;
    let selected = selection(&p, &dag, opts)?;
    let store = Arc::new(Store::open(&p.cache_dir)?);
    let _lock = if opts.dry_run {
        None
    } else {
        Some(crate::store::RunLock::acquire(
            store.root(),
            opts.no_wait,
            false,
        )?)
    };
    if !opts.dry_run {
        store.clean_tmp();
    }
    let external = external_digests(&p, &store)?;
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

    let multi = MultiProgress::with_draw_target(ProgressDrawTarget::stderr());
    let log = |msg: String| multi.suspend(|| eprintln!("{msg}"));
    let total = selected.len();
    let loaded: Loaded = Arc::default();
    let mut digests: HashMap<usize, String> = HashMap::new();
    let mut manifests: HashMap<usize, Box<Manifest>> = HashMap::new();
    let mut reports: HashMap<usize, StageReport> = HashMap::new();
    let mut failed_stages: BTreeSet<usize> = BTreeSet::new();
    let mut done: BTreeSet<usize> = BTreeSet::new();
    let mut running: JoinSet<Finished> = JoinSet::new();
    let mut in_flight: BTreeSet<usize> = BTreeSet::new();
    let jobs = opts.jobs.max(1);
    let mut stop = false;
    let mut counter = 0usize;

    let report = |i: usize, outcome: Outcome, reason: String, key: Option<String>| StageReport {
        stage: p.stages[i].name.clone(),
        kind: p.stages[i].kind.kind().to_string(),
        outcome,
        reason,
        key,
        wall_s: 0.0,
        cpu_s: 0.0,
        peak_rss_bytes: 0,
        overhead_s: 0.0,
    };

    loop {
        // Start every stage whose inputs are done.
        let mut progressed = true;
        while progressed && !stop {
            progressed = false;
            for &i in &dag.order {
                if done.contains(&i) || in_flight.contains(&i) || !needed.contains(&i) {
                    continue;
                }
                let ups = dag.upstream(i);
                if !ups.iter().all(|u| done.contains(u)) {
                    continue;
                }
                let s = &p.stages[i];
                if let Some(&bad) = ups
                    .iter()
                    .find(|u| failed_stages.contains(u) || !digests.contains_key(u))
                {
                    let why = if failed_stages.contains(&bad) {
                        format!("upstream `{}` failed", p.stages[bad].name)
                    } else {
                        format!("upstream `{}` did not run", p.stages[bad].name)
                    };
                    failed_stages.insert(i);
                    reports.insert(i, report(i, Outcome::Skipped, why, None));
                    done.insert(i);
                    progressed = true;
                    continue;
                }
                let ov0 = Instant::now();
                let (key, inputs) = key_of(&p, i, &digests, &external).expect("inputs done");
                let entry = store.check(&key, opts.verify);
                let is_selected = selected.contains(&i);
                let mut reason = match entry {
                    Entry::Valid(m) if !force.contains(&i) => {
                        digests.insert(i, m.output_digest.clone());
                        if is_selected {
                            let mut r =
                                report(i, Outcome::Cached, "up to date".into(), Some(key.clone()));
                            r.overhead_s = ov0.elapsed().as_secs_f64();
                            reports.insert(i, r);
                            // Keep status explanations current even when the entry came from elsewhere.
                            if !opts.dry_run
                                && store.run_record(&s.name).map(|r| r.key) != Some(key.clone())
                            {
                                store.save_run_record(
                                    &s.name,
                                    RunRecord {
                                        key: key.clone(),
                                        kind: s.kind.kind().into(),
                                        version: s.kind.version(),
                                        params: s.params.clone(),
                                        inputs: inputs.clone(),
                                        history: vec![],
                                    },
                                )?;
                            }
                        }
                        manifests.insert(i, m);
                        done.insert(i);
                        progressed = true;
                        continue;
                    }
                    Entry::Valid(_) => "forced".to_string(),
                    Entry::Corrupt(why) => {
                        if opts.dry_run {
                            format!("cache entry corrupt: {why}")
                        } else {
                            let dest = store.quarantine(&key)?;
                            let msg =
                                format!("cache entry corrupt: {why} (moved to {})", dest.display());
                            log(format!("warning: stage `{}`: {msg}", s.name));
                            msg
                        }
                    }
                    Entry::Missing => explain(&p, i, &store, &key, &inputs),
                };
                if !is_selected {
                    match &opts.only {
                        Some(only) => bail!(
                            "cannot run only the selected stages: `{only}` needs stage `{}`, which is not up to date ({reason}); run `pipe run --until {only}` first",
                            s.name,
                        ),
                        None => bail!(
                            "cannot run only the selected stages: the dataset stages need stage `{}`, which is not up to date ({reason}); run its scene first",
                            s.name,
                        ),
                    }
                }
                if opts.dry_run {
                    reports.insert(i, report(i, Outcome::WouldRun, reason, Some(key)));
                    done.insert(i);
                    progressed = true;
                    continue;
                }
                if in_flight.len() >= jobs {
                    continue;
                }
                counter += 1;
                reason = reason.replace('\n', " ");
                let running_line = format!(
                    "[{counter}/{total}] running `{}` ({}): {reason}",
                    s.name,
                    s.kind.kind()
                );
                let bar = multi.add(ProgressBar::new(1));
                bar.set_style(
                    ProgressStyle::with_template(
                        "{prefix:>12.bold} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
                    )
                    .unwrap_or_else(|_| ProgressStyle::default_bar()),
                );
                bar.set_prefix(s.name.clone());
                let manifest_of = |up: &String| manifests[&p.index_of(up).unwrap()].clone();
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
                let pre_overhead = ov0.elapsed().as_secs_f64();
                let (p2, store2, loaded2) = (p.clone(), store.clone(), loaded.clone());
                let key2 = key.clone();
                let (no_wait, forced) = (opts.no_wait, force.contains(&i));
                let multi2 = multi.clone();
                reports.insert(i, report(i, Outcome::Ran, reason, Some(key)));
                in_flight.insert(i);
                running.spawn_blocking(move || {
                    let log2 = |msg: String| multi2.suspend(|| eprintln!("{msg}"));
                    let failed = |e: anyhow::Error| Finished {
                        i,
                        result: Err(e),
                        reused: false,
                        wall: 0.0,
                        cpu: 0.0,
                        rss: 0,
                    };
                    // The entry's lock: one writer per entry across every run on this cache.
                    let name = &p2.stages[i].name;
                    let _lock = match store2.lock_key(&key2, no_wait, |holder| {
                        log2(format!(
                            "stage `{name}`: waiting for {holder}, which computes the same entry"
                        ))
                    }) {
                        Ok(l) => l,
                        Err(e) => {
                            bar.finish_and_clear();
                            return failed(e.context(format!("stage `{name}`")));
                        }
                    };
                    if !forced {
                        if let Entry::Valid(m) = store2.check(&key2, false) {
                            bar.finish_and_clear();
                            return Finished {
                                i,
                                result: Ok((*m, pre_overhead)),
                                reused: true,
                                wall: 0.0,
                                cpu: 0.0,
                                rss: 0,
                            };
                        }
                    }
                    log2(running_line);
                    let ov1 = Instant::now();
                    let mut ins = BTreeMap::new();
                    for (slot, parts) in &gathered {
                        let spec = p2.stages[i].kind.inputs().iter().find(|x| x.name == slot);
                        let tables = spec.map_or(&[][..], |x| x.tables);
                        let loaded = parts
                            .iter()
                            .map(|(scene, m)| {
                                load_cached(&store2, &loaded2, m).map(|t| (scene.clone(), t))
                            })
                            .collect::<Result<Vec<_>>>()
                            .and_then(|parts| gather_tables(tables, &parts));
                        match loaded {
                            Ok(t) => {
                                ins.insert(slot.clone(), Arc::new(t));
                            }
                            Err(e) => {
                                bar.finish_and_clear();
                                return failed(e);
                            }
                        }
                    }
                    for (slot, m) in &upstream {
                        match load_cached(&store2, &loaded2, m) {
                            Ok(t) => {
                                ins.insert(slot.clone(), t);
                            }
                            Err(e) => {
                                return Finished {
                                    i,
                                    result: Err(e),
                                    reused: false,
                                    wall: 0.0,
                                    cpu: 0.0,
                                    rss: 0,
                                }
                            }
                        }
                    }
                    let load_s = ov1.elapsed().as_secs_f64();
                    reset_peak_rss();
                    let started = unix_now();
                    let (w0, c0) = (Instant::now(), cpu_seconds());
                    let result = execute(&p2, i, &ins, &bar);
                    let (wall, cpu, rss) = (
                        w0.elapsed().as_secs_f64(),
                        cpu_seconds() - c0,
                        peak_rss_bytes(),
                    );
                    bar.finish_and_clear();
                    drop(ins);
                    let ov2 = Instant::now();
                    let published = result.and_then(|tables| {
                        let s = &p2.stages[i];
                        let m = Manifest {
                            key: key2.clone(),
                            kind: s.kind.kind().into(),
                            version: s.kind.version(),
                            stage: s.name.clone(),
                            params: s.params.clone(),
                            inputs: BTreeMap::new(),
                            files: BTreeMap::new(),
                            schemas: BTreeMap::new(),
                            output_digest: String::new(),
                            wall_s: wall,
                            cpu_s: cpu,
                            peak_rss_bytes: rss,
                            started,
                            finished: unix_now(),
                            tool_version: env!("CARGO_PKG_VERSION").into(),
                        };
                        let m = store2.publish(m, &tables)?;
                        loaded2
                            .lock()
                            .unwrap()
                            .insert(m.key.clone(), Arc::new(tables));
                        Ok(m)
                    });
                    let overhead = load_s + ov2.elapsed().as_secs_f64() + pre_overhead;
                    Finished {
                        i,
                        result: published.map(|m| (m, overhead)),
                        reused: false,
                        wall,
                        cpu,
                        rss,
                    }
                });
                progressed = true;
            }
        }
        let Some(joined) = running.join_next().await else {
            break;
        };
        let Finished {
            i,
            result,
            reused,
            wall,
            cpu,
            rss,
        } = joined.map_err(|e| anyhow!("stage thread panicked: {e}"))?;
        in_flight.remove(&i);
        done.insert(i);
        let s = &p.stages[i];
        let r = reports.get_mut(&i).expect("report created at start");
        r.wall_s = wall;
        r.cpu_s = cpu;
        r.peak_rss_bytes = rss;
        match result {
            Ok((mut m, overhead)) => {
                r.overhead_s += overhead;
                if reused {
                    r.outcome = Outcome::Cached;
                    r.reason = "computed meanwhile by another run".into();
                }
                let key = r.key.clone().unwrap_or_default();
                let (_, inputs) = key_of(&p, i, &digests, &external).expect("inputs done");
                m.inputs = inputs.clone();
                store.save_run_record(
                    &s.name,
                    RunRecord {
                        key,
                        kind: s.kind.kind().into(),
                        version: s.kind.version(),
                        params: s.params.clone(),
                        inputs,
                        history: vec![],
                    },
                )?;
                digests.insert(i, m.output_digest.clone());
                manifests.insert(i, Box::new(m));
            }
            Err(e) => {
                r.outcome = Outcome::Failed;
                r.reason = format!("{e:#}");
                log(format!("error: {e:#}"));
                failed_stages.insert(i);
                if !opts.keep_going {
                    stop = true;
                }
            }
        }
    }
    // Anything selected that never started (after a failure without --keep-going).
    for &i in &dag.order {
        if selected.contains(&i) && !reports.contains_key(&i) {
            reports.insert(
                i,
                report(
                    i,
                    Outcome::Skipped,
                    "not started after an earlier failure".into(),
                    None,
                ),
            );
        }
    }
    let stages: Vec<StageReport> = dag
        .order
        .iter()
        .filter(|i| selected.contains(i))
        .filter_map(|i| reports.remove(i))
        .collect();
    let failed = stages
        .iter()
        .any(|r| matches!(r.outcome, Outcome::Failed | Outcome::Skipped));
    let rep = RunReport {
        stages,
        wall_s: t0.elapsed().as_secs_f64(),
        failed,
    };
    if !opts.dry_run {
        let path = store.root().join("runs").join("last-run.json");
        // Best effort (the summary is printed too), but never a half-written file.
        let _ = crate::store::write_atomic(&path, &serde_json::to_vec_pretty(&rep)?);
    }
    Ok(rep)
}

/// Human-readable bytes.
pub fn fmt_bytes(b: u64) -> String {
    match b {
        0 => "-".into(),
        b if b >= 1 << 30 => format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64),
        b if b >= 1 << 20 => format!("{:.0} MiB", b as f64 / (1u64 << 20) as f64),
        b if b >= 1 << 10 => format!("{:.0} KiB", b as f64 / 1024.0),
        b => format!("{b} B"),
    }
}

/// Seconds as `1.23s` / `45ms`.
pub fn fmt_secs(s: f64) -> String {
    if s == 0.0 {
        "-".into()
    } else if s < 1.0 {
        format!("{:.0}ms", s * 1000.0)
    } else {
        format!("{s:.2}s")
    }
}

/// A plain text table with aligned columns.
pub fn text_table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut width: Vec<usize> = header.iter().map(|h| h.len()).collect();
    for r in rows {
        for (w, c) in width.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let line = |cells: Vec<String>| {
        let n = cells.len();
        cells
            .into_iter()
            .enumerate()
            .map(|(k, c)| {
                if k + 1 == n {
                    c
                } else {
                    format!("{c:<w$}", w = width[k])
                }
            })
            .collect::<Vec<_>>()
            .join("  ")
    };
    let mut out = line(header.iter().map(|s| s.to_string()).collect());
    out.push('\n');
    for r in rows {
        out.push_str(&line(r.clone()));
        out.push('\n');
    }
    out
}

/// The summary printed after a run.
pub fn summary(rep: &RunReport) -> String {
    let rows: Vec<Vec<String>> = rep
        .stages
        .iter()
        .map(|r| {
            vec![
                r.stage.clone(),
                match r.outcome {
                    Outcome::Cached => "cached",
                    Outcome::Ran => "ran",
                    Outcome::Failed => "FAILED",
                    Outcome::Skipped => "skipped",
                    Outcome::WouldRun => "would run",
                }
                .to_string(),
                fmt_secs(r.wall_s),
                fmt_secs(r.cpu_s),
                fmt_bytes(r.peak_rss_bytes),
                fmt_secs(r.overhead_s),
                first_line(&r.reason),
            ]
        })
        .collect();
    let mut s = text_table(
        &[
            "stage", "result", "wall", "cpu", "peak rss", "runner", "reason",
        ],
        &rows,
    );
    s.push_str(&format!("total {}\n", fmt_secs(rep.wall_s)));
    s
}

fn first_line(s: &str) -> String {
    let l = s.lines().next().unwrap_or("");
    if l.chars().count() > 100 {
        format!("{}...", l.chars().take(97).collect::<String>())
    } else {
        l.to_string()
    }
}
