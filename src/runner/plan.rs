//! What a run must do, without running anything: every stage's cache key (from its kind,
//! version, params and the output digests of its inputs), whether a verified entry exists for
//! it, and if not, why (compared with the stage's last recorded run); and which stages a run's
//! selection (`--scene`, `--until`, `--only`, `--force`) touches.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use serde_json::Value;

use super::{
    error::RunError,
    options::{RunOptions, Scenes},
    parent::{find_parent, updated_key, Found},
};
use crate::{
    config::{shorten, show_json, Pipeline},
    dag::Dag,
    fingerprint::{self, FILES_SLOT, PARENT_SLOT},
    store::{Entry, InputInfo, Manifest, Store},
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

/// Digests of the files outside the cache that stages read (`Stage::external_inputs`), by
/// stage index. Contents are hashed, memoised by path, size, mtime and inode.
pub fn external_digests(p: &Pipeline, store: &Store) -> Result<HashMap<usize, String>, RunError> {
    let mut out = HashMap::new();
    for (i, s) in p.stages.iter().enumerate() {
        let paths =
            s.kind
                .external_inputs(&s.params)
                .map_err(|source| RunError::ExternalInputs {
                    stage: s.name.clone(),
                    source,
                })?;
        // Before hashing: a directory would be hashed recursively (a whole data set root) and a
        // FIFO would block the read forever.
        for path in &paths {
            if let Some(what) = stages::input_file::not_regular(path) {
                let problem = format!("{}: is {what}, expected a regular file", path.display());
                return Err(RunError::ExternalInputs {
                    stage: s.name.clone(),
                    source: stages::StageError::Input(problem),
                });
            }
        }
        if !paths.is_empty() {
            out.insert(i, store.files_digest(&paths)?);
        }
    }
    Ok(out)
}

/// The key of stage `i` given the output digests of its upstream stages; `None` while one of
/// them has none (it is stale).
pub(super) fn key_of(
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
                key: None,
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
                key: None,
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
                key: None,
            },
        );
    }
    let by_digest = inputs
        .iter()
        .map(|(k, v)| (k.clone(), v.digest.clone()))
        .collect();
    let params = fingerprint::recipe(s.kind.as_ref(), &s.params);
    let key = fingerprint::stage_key(s.kind.kind(), s.kind.version(), &params, &by_digest);
    Some((key, inputs))
}

fn show_value(v: &Value) -> String {
    shorten(&show_json(v), 48)
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

/// Why stage `i` (with current key `key`) differs from its last recorded run.
pub(super) fn explain(
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
    for slot in slots.into_iter().filter(|s| *s != PARENT_SLOT) {
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

/// `waits on stale input ...`: the inputs of stage `i` that have no output digest yet.
fn waits_on(p: &Pipeline, i: usize, digests: &HashMap<usize, String>) -> String {
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
    format!("waits on stale input {}", stale_up.join(", "))
}

/// Freshness of every stage, in topological order, without running anything.
pub fn resolve(
    p: &Pipeline,
    dag: &Dag,
    store: &Store,
    full_verify: bool,
) -> Result<Vec<Resolved>, RunError> {
    let external = external_digests(p, store)?;
    let mut out: Vec<Option<Resolved>> = vec![None; p.stages.len()];
    let mut digests: HashMap<usize, String> = HashMap::new();
    let mut fresh: HashMap<usize, Box<Manifest>> = HashMap::new();
    for &i in &dag.order {
        let r = match key_of(p, i, &digests, &external) {
            None => Resolved {
                key: None,
                inputs: BTreeMap::new(),
                state: State::Stale(waits_on(p, i, &digests)),
                corrupt: false,
            },
            Some((key, mut inputs)) => {
                let upstream = |slot: &str| {
                    let up = p.stages[i].inputs.get(slot)?;
                    fresh.get(&p.index_of(up)?).cloned()
                };
                for (slot, info) in inputs.iter_mut() {
                    info.key = upstream(slot).map(|m| m.key);
                }
                let (mut key, mut state, mut corrupt) = match store.check(&key, full_verify) {
                    Entry::Valid(m) => (key, State::Fresh(m), false),
                    Entry::Corrupt(why) => {
                        let why = format!("cache entry corrupt: {why}");
                        (key, State::Stale(why), true)
                    }
                    Entry::Missing => {
                        let why = explain(p, i, store, &key, &inputs);
                        (key, State::Stale(why), false)
                    }
                };
                // A stale stage that can update its last run: the updated entry may exist.
                if let (State::Stale(why), false) = (&state, corrupt) {
                    let found = find_parent(p, i, store, &inputs, &upstream, false);
                    let parent = match &found {
                        Ok(Found::Parent(parent)) => parent.manifest.key.clone(),
                        Ok(Found::Current(parent)) => parent.clone(),
                        Err(_) => String::new(),
                    };
                    match found {
                        Ok(found) => {
                            let (ukey, uinputs) = updated_key(p, i, &parent, &inputs);
                            (state, corrupt) = match store.check(&ukey, full_verify) {
                                Entry::Valid(m) => (State::Fresh(m), false),
                                Entry::Corrupt(c) => {
                                    (State::Stale(format!("cache entry corrupt: {c}")), true)
                                }
                                Entry::Missing => (
                                    State::Stale(match found {
                                        Found::Parent(par) => format!(
                                            "{why}; will update entry {} ({})",
                                            par.short(),
                                            par.what_changed()
                                        ),
                                        Found::Current(_) => why.clone(),
                                    }),
                                    false,
                                ),
                            };
                            (key, inputs) = (ukey, uinputs);
                        }
                        Err(Some(no)) => state = State::Stale(format!("{why}; from scratch: {no}")),
                        Err(None) => {}
                    }
                }
                if let State::Fresh(m) = &state {
                    digests.insert(i, m.output_digest.clone());
                    fresh.insert(i, m.clone());
                }
                Resolved {
                    key: Some(key),
                    inputs,
                    state,
                    corrupt,
                }
            }
        };
        out[i] = Some(r);
    }
    Ok(out
        .into_iter()
        .map(|r| r.expect("every stage resolved"))
        .collect())
}

/// Checks that `--scene` names scenes of the pipeline.
pub fn check_scenes(p: &Pipeline, list: &[String]) -> Result<(), RunError> {
    if p.scenes.is_empty() {
        return Err(RunError::NoScenes {
            scenes: list.join(","),
            file: p.file.clone(),
        });
    }
    for sc in list {
        if !p.scenes.contains(sc) {
            return Err(RunError::NoSuchScene {
                scene: sc.clone(),
                file: p.file.clone(),
                known: p.scenes.clone(),
            });
        }
    }
    Ok(())
}

/// The scenes a run's options name, checked against the pipeline (all scenes by default).
fn selected_scenes(p: &Pipeline, opts: &RunOptions) -> Result<Vec<String>, RunError> {
    let Scenes::Named(list) = &opts.scenes else {
        return Ok(p.scenes.clone());
    };
    check_scenes(p, list)?;
    Ok(list.clone())
}

/// Which stages a run touches: the ones it brings up to date, and what they need.
pub fn selection(p: &Pipeline, dag: &Dag, opts: &RunOptions) -> Result<BTreeSet<usize>, RunError> {
    let scenes = selected_scenes(p, opts)?;
    let find = |name: &str, flag: &'static str| {
        let found = p.instances(name, &scenes);
        if found.is_empty() {
            return Err(RunError::NoSuchStage {
                flag,
                name: name.to_string(),
                file: p.file.clone(),
            });
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
        (Some(_), Some(_)) => return Err(RunError::UntilAndOnly),
        (Some(u), None) => find(u, "--until")?
            .into_iter()
            .flat_map(|i| dag.ancestors_and_self(i))
            .collect(),
        (None, Some(o)) => find(o, "--only")?.into_iter().collect(),
        (None, None) => base,
    })
}
