//! Executing one stage, on a blocking thread: take the entry's lock (one writer per entry
//! across every run on the cache), look again whether another run published it meanwhile,
//! load the inputs (gathering every scene's tables for a dataset stage), run the body, check
//! its outputs against the kind's contract and schema files, publish them, and measure wall
//! time, CPU time and peak RSS of the body.

use std::{
    collections::{BTreeMap, BTreeSet, HashSet},
    path::PathBuf,
    sync::{Arc, Mutex},
    time::Instant,
};

use stages::{Inputs, Previous, TableSet, Tables};

use super::{
    error::StageFailure,
    parent::Parent,
    progress::{Bars, StageBar},
};
use crate::{
    config::Pipeline,
    store::{unix_now, Entry, InputInfo, Manifest, PendingEntry, Store, StoreError},
};

/// The manifests of a gathered slot's stage in every scene: (scene, manifest).
pub(super) type SceneManifests = Vec<(String, Box<Manifest>)>;

/// Keys of the entries this run wrote or verified (hashed) already: opening them again reads
/// without hashing every file once more.
pub(super) type Loaded = Arc<Mutex<HashSet<String>>>;

/// Everything the thread that computes stage `i` needs.
pub(super) struct Job {
    pub p: Arc<Pipeline>,
    pub i: usize,
    pub store: Arc<Store>,
    pub loaded: Loaded,
    pub key: String,
    pub no_wait: bool,
    /// Run even if the entry appears meanwhile.
    pub forced: bool,
    /// (slot, manifest of the upstream entry).
    pub upstream: Vec<(String, Box<Manifest>)>,
    /// (slot, the gathered stage's manifest in every scene).
    pub gathered: Vec<(String, SceneManifests)>,
    /// What the key was computed from, for the manifest.
    pub inputs: BTreeMap<String, InputInfo>,
    /// The entry to update instead of computing from scratch.
    pub parent: Option<Parent>,
    /// The runner's time on this stage before the job started, seconds.
    pub pre_overhead: f64,
    /// Printed once the lock is held and the body starts.
    pub running_line: String,
    pub bar: StageBar,
    pub bars: Bars,
}

/// A stage body that ended on its blocking thread: its published manifest and the runner's
/// overhead, or the error; wall/CPU seconds and peak RSS of the body.
pub(super) struct Finished {
    pub i: usize,
    pub result: Result<(Manifest, f64), StageFailure>,
    /// Another run published the entry while this one waited for its lock.
    pub reused: bool,
    pub wall: f64,
    pub cpu: f64,
    pub rss: u64,
}

/// What the body cost.
struct Measured {
    started: f64,
    wall: f64,
    cpu: f64,
    rss: u64,
}

impl Job {
    /// Computes the stage (or finds it computed meanwhile).
    pub fn run(self) -> Finished {
        let f = self.work();
        self.bar.finish();
        f
    }

    fn failed(&self, e: StageFailure) -> Finished {
        Finished {
            i: self.i,
            result: Err(e),
            reused: false,
            wall: 0.0,
            cpu: 0.0,
            rss: 0,
        }
    }

    fn work(&self) -> Finished {
        let name = &self.p.stages[self.i].name;
        // The entry's lock: one writer per entry across every run on this cache.
        let waiting = |holder: &str| {
            self.bars.log(&format!(
                "stage `{name}`: waiting for {holder}, which computes the same entry"
            ))
        };
        let _lock = match self.store.lock_key(&self.key, self.no_wait, waiting) {
            Ok(l) => l,
            Err(source) => {
                return self.failed(StageFailure::Lock {
                    stage: name.clone(),
                    source,
                })
            }
        };
        if !self.forced {
            if let Entry::Valid(m) = self.store.check(&self.key, false) {
                return Finished {
                    i: self.i,
                    result: Ok((*m, self.pre_overhead)),
                    reused: true,
                    wall: 0.0,
                    cpu: 0.0,
                    rss: 0,
                };
            }
        }
        self.bars.log(&self.running_line);
        let ov1 = Instant::now();
        let ins = match self.load_inputs() {
            Ok(ins) => ins,
            Err(e) => return self.failed(e),
        };
        // Streamed output tables are written into the new entry while the stage runs.
        let pending = match self.store.begin(&self.key) {
            Ok(p) => p,
            Err(e) => return self.failed(e.into()),
        };
        let previous = match self.load_parent() {
            Ok(prev) => prev,
            Err(e) => return self.failed(e),
        };
        let load_s = ov1.elapsed().as_secs_f64();
        reset_peak_rss();
        let started = unix_now();
        let (w0, c0) = (Instant::now(), cpu_seconds());
        let previous = previous.as_ref().map(|(outputs, inputs, parent)| Previous {
            outputs,
            inputs: inputs.iter().map(|(k, v)| (k.clone(), v)).collect(),
            changed: &parent.changed,
            lineage: &parent.lineage,
        });
        let parent_entry = self
            .parent
            .as_ref()
            .map(|par| (self.store.entry_dir(&par.manifest.key), &*par.manifest));
        let result = execute(
            &self.p,
            self.i,
            &ins,
            previous.as_ref().zip(parent_entry),
            &pending,
            &self.bar,
        );
        drop(previous);
        let body = Measured {
            started,
            wall: w0.elapsed().as_secs_f64(),
            cpu: cpu_seconds() - c0,
            rss: peak_rss_bytes(),
        };
        self.bar.finish();
        drop(ins);
        let ov2 = Instant::now();
        let published = result.and_then(|tables| self.publish(pending, tables, &body));
        let overhead = load_s + ov2.elapsed().as_secs_f64() + self.pre_overhead;
        Finished {
            i: self.i,
            result: published.map(|m| (m, overhead)),
            reused: false,
            wall: body.wall,
            cpu: body.cpu,
            rss: body.rss,
        }
    }

    /// The input tables by slot: gathered slots first, then the plain ones.
    fn load_inputs(&self) -> Result<BTreeMap<String, TableSet>, StageFailure> {
        let mut ins = BTreeMap::new();
        for (slot, parts) in &self.gathered {
            let spec = self.p.stages[self.i]
                .kind
                .inputs()
                .iter()
                .find(|x| x.name == slot);
            let tables = spec.map_or(&[][..], |x| x.tables);
            let parts = parts
                .iter()
                .map(|(scene, m)| Ok((scene.clone(), load_cached(&self.store, &self.loaded, m)?)))
                .collect::<Result<Vec<_>, StageFailure>>()?;
            ins.insert(slot.clone(), gather_tables(tables, &parts)?.into());
        }
        for (slot, m) in &self.upstream {
            ins.insert(slot.clone(), load_cached(&self.store, &self.loaded, m)?);
        }
        Ok(ins)
    }

    /// The parent's outputs and inputs, when this job updates one.
    #[allow(clippy::type_complexity)]
    fn load_parent(
        &self,
    ) -> Result<Option<(TableSet, BTreeMap<String, TableSet>, &Parent)>, StageFailure> {
        let Some(parent) = &self.parent else {
            return Ok(None);
        };
        let outputs = load_cached(&self.store, &self.loaded, &parent.manifest)?;
        // Only what the update reads of them: a parent's plan table alone is gigabytes to
        // verify and megabytes of metadata to hold.
        let reads = self.p.stages[self.i].kind.parent_inputs();
        let mut inputs = BTreeMap::new();
        for (slot, m) in &parent.inputs {
            let only: Vec<&str> = reads
                .iter()
                .filter(|(s, _)| s == slot)
                .map(|&(_, t)| t)
                .collect();
            if !only.is_empty() {
                let t = load_some(&self.store, &self.loaded, m, Some(&only))?;
                inputs.insert(slot.clone(), t);
            }
        }
        Ok(Some((outputs, inputs, parent)))
    }

    /// Publishes the body's tables (and the ones it streamed into `pending`) as the entry of
    /// this job's key.
    fn publish(
        &self,
        pending: PendingEntry,
        (tables, redone): (Tables, Option<String>),
        body: &Measured,
    ) -> Result<Manifest, StageFailure> {
        let s = &self.p.stages[self.i];
        let m = Manifest {
            key: self.key.clone(),
            kind: s.kind.kind().into(),
            version: s.kind.version(),
            stage: s.name.clone(),
            params: s.params.clone(),
            inputs: self.inputs.clone(),
            files: BTreeMap::new(),
            schemas: BTreeMap::new(),
            output_digest: String::new(),
            wall_s: body.wall,
            cpu_s: body.cpu,
            peak_rss_bytes: body.rss,
            started: body.started,
            finished: unix_now(),
            tool_version: env!("CARGO_PKG_VERSION").into(),
            parent: redone
                .as_ref()
                .and(self.parent.as_ref())
                .map(|p| p.manifest.key.clone()),
            redone,
        };
        let m = self
            .store
            .publish_pending(pending, m, &tables, self.forced)?;
        self.loaded.lock().unwrap().insert(m.key.clone());
        Ok(m)
    }
}

/// The tables of entry `m`, read on demand; hashed first unless this run wrote or verified the
/// entry already.
fn load_cached(store: &Store, loaded: &Loaded, m: &Manifest) -> Result<TableSet, StageFailure> {
    load_some(store, loaded, m, None)
}

/// [`load_cached`] for the tables `only` names (all with `None`).
fn load_some(
    store: &Store,
    loaded: &Loaded,
    m: &Manifest,
    only: Option<&[&str]>,
) -> Result<TableSet, StageFailure> {
    let trusted = loaded.lock().unwrap().contains(&m.key);
    let t = match store.open_some_tables(m, trusted, only) {
        Err(StoreError::Corrupt(why)) => {
            return Err(StageFailure::InputCorrupt {
                stage: m.stage.clone(),
                key: m.key.clone(),
                why,
                moved: store.quarantine(&m.key).ok(),
            })
        }
        other => other?,
    };
    // A part verified does not vouch for the rest.
    if only.is_none() {
        loaded.lock().unwrap().insert(m.key.clone());
    }
    Ok(t)
}

/// The tables a gathered input slot hands to a dataset stage: for each table the slot reads,
/// every scene's rows with a leading `scene` column, in scene order.
pub fn gather_tables(
    tables: &[&str],
    parts: &[(String, TableSet)],
) -> Result<Tables, StageFailure> {
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
                .ok_or_else(|| StageFailure::GatherMissing {
                    scene: scene.clone(),
                    table: t.to_string(),
                })?
                .whole()
                .map_err(|source| StageFailure::Body {
                    stage: format!("gather of `{t}`"),
                    kind: "dataset".into(),
                    source,
                })?;
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
        let schema = schema.ok_or_else(|| StageFailure::GatherEmpty(t.to_string()))?;
        out.insert(
            t.to_string(),
            arrow::compute::concat_batches(&schema, &batches)?,
        );
    }
    Ok(out)
}

/// Runs a stage body (or its update of `previous`) and checks its outputs against the kind's
/// contract and schema files; with what an update computed again.
/// Runs stage `i`'s body, or its update of `previous` (with the parent entry's directory and
/// manifest: the tables the update leaves out are linked from there).
fn execute(
    p: &Pipeline,
    i: usize,
    inputs: &BTreeMap<String, TableSet>,
    previous: Option<(&Previous, (PathBuf, &Manifest))>,
    pending: &PendingEntry,
    bar: &StageBar,
) -> Result<(Tables, Option<String>), StageFailure> {
    let s = &p.stages[i];
    let (stage, kind) = (s.name.clone(), s.kind.kind().to_string());
    let slots = inputs.iter().map(|(k, v)| (k.clone(), v)).collect();
    let adapter = bar.adapter();
    let inputs = Inputs::new(slots).with_sinks(pending);
    let body = match &previous {
        Some((prev, _)) => s
            .kind
            .update(&s.params, &inputs, prev, &adapter)
            .map(|u| (u.tables, Some(u.redone))),
        None => s.kind.run(&s.params, &inputs, &adapter).map(|t| (t, None)),
    };
    let (tables, redone) = body.map_err(|source| StageFailure::Body {
        stage: stage.clone(),
        kind: kind.clone(),
        source,
    })?;
    let declared: BTreeSet<String> = s.kind.outputs().iter().map(|t| t.to_string()).collect();
    if let Some((_, (dir, parent))) = &previous {
        // What the update left out is the parent's, byte for byte.
        let streamed = pending.streamed();
        let left_out = declared
            .iter()
            .filter(|t| !tables.contains_key(*t) && !streamed.contains(t));
        for t in left_out {
            let file = format!("{t}.parquet");
            if let Some(info) = parent.files.get(&file) {
                pending.keep(t, &dir.join(&file), info.clone())?;
            }
        }
    }
    let mut written: BTreeSet<String> = tables.keys().cloned().collect();
    written.extend(pending.streamed());
    if written != declared {
        return Err(StageFailure::Outputs {
            stage,
            kind,
            written,
            declared,
        });
    }
    for (name, batch) in &tables {
        stages::schema::check(name, &batch.schema()).map_err(|message| StageFailure::Schema {
            stage: stage.clone(),
            kind: kind.clone(),
            message,
        })?;
    }
    Ok((tables, redone))
}

fn cpu_seconds() -> f64 {
    // SAFETY: getrusage writes into the struct we pass.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Resets the kernel's peak-RSS mark so the next reading covers only what follows, after giving
/// the memory freed so far back to the system: glibc keeps freed heap (the scene stage's tables
/// left 1.2 GB resident through every later stage of a full-size run), which would count
/// against the next stage's peak and stay out of other processes' reach.
fn reset_peak_rss() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free heap pages; it takes no pointers.
    unsafe {
        libc::malloc_trim(0);
    }
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
