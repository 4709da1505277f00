//! Updating instead of computing from scratch. A stage whose kind can update
//! ([`stages::Stage::updates`]) and whose inputs (or editable params,
//! [`stages::Stage::editable_params`]) changed starts from its *parent*: the last run of the same
//! stage instance (its run record) with the same kind, code version and params but for those,
//! whose entry and input entries are still in the cache. The updated entry's key is the stage's key
//! with the parent's key added as input `@parent`: the same parent and the same inputs
//! give the same entry, and it never passes for a run from scratch. Where there is no usable
//! parent, the stage computes from scratch and the run log says why.

use std::collections::{BTreeMap, BTreeSet};

use stages::{Changed, Lineage};

use crate::{
    config::Pipeline,
    fingerprint::{self, FILES_SLOT, PARENT_SLOT},
    store::{Entry, InputInfo, Manifest, RunRecord, Store},
};

/// The entry a stage updates, with the entries it was computed from.
#[derive(Debug, Clone)]
pub struct Parent {
    pub manifest: Box<Manifest>,
    /// (slot, the parent's input entry), in slot order.
    pub inputs: Vec<(String, Box<Manifest>)>,
    /// Per slot, the tables the slot reads whose bytes differ from the current inputs'.
    pub changed: Changed,
    /// How the current input entries relate to the parent's.
    pub lineage: Lineage,
    /// The editable params ([`stages::Stage::editable_params`]) the parent ran with other
    /// values of.
    pub edited: Vec<String>,
}

impl Parent {
    /// Whether an input entry of `inputs` is another than the parent's, or the parent ran with
    /// other editable params.
    pub fn differs(&self, inputs: &BTreeMap<String, InputInfo>) -> bool {
        !self.edited.is_empty()
            || self
                .inputs
                .iter()
                .any(|(slot, m)| inputs.get(slot).and_then(|i| i.key.as_ref()) != Some(&m.key))
    }

    /// ``` `scene`.primitives changed ```, ``` param `edits` changed ```: for messages.
    pub fn what_changed(&self) -> String {
        let params = self.edited.iter().map(|n| format!("param `{n}`"));
        match (self.changed.is_empty(), self.edited.is_empty()) {
            (_, true) => describe(&self.changed),
            (true, false) => format!("{} changed", params.collect::<Vec<_>>().join(", ")),
            (false, false) => format!(
                "{}, {} changed",
                describe(&self.changed).trim_end_matches(" changed"),
                params.collect::<Vec<_>>().join(", ")
            ),
        }
    }

    /// The parent's key, shortened for messages.
    pub fn short(&self) -> &str {
        short_key(&self.manifest.key)
    }

    /// The updated entry's key and inputs: the stage's `inputs` plus the parent.
    pub fn key(
        &self,
        p: &Pipeline,
        i: usize,
        inputs: &BTreeMap<String, InputInfo>,
    ) -> (String, BTreeMap<String, InputInfo>) {
        updated_key(p, i, &self.manifest.key, inputs)
    }
}

/// The first 8 characters of a key.
pub fn short_key(key: &str) -> &str {
    &key[..key.len().min(8)]
}

/// Digest of table `table` in entry `m` (its file's blake3).
fn table_digest<'m>(m: &'m Manifest, table: &str) -> Option<&'m str> {
    m.files
        .get(&format!("{table}.parquet"))
        .map(|f| f.blake3.as_str())
}

/// The parent stage `i` can update, given its current `inputs` (with their entries' keys) and
/// the current entry of each input slot (`current`). `Err(None)`: the stage computes from
/// scratch for a reason not worth a word (its kind never updates, it never ran, `--cold`);
/// `Err(Some(why))`: it could have updated, and why it does not. `again` (`--force`): where the
/// last run already updated an entry from these inputs, that entry is the parent once more.
pub fn find_parent(
    p: &Pipeline,
    i: usize,
    store: &Store,
    inputs: &BTreeMap<String, InputInfo>,
    current: &dyn Fn(&str) -> Option<Box<Manifest>>,
    again: bool,
) -> Result<Found, Option<String>> {
    let s = &p.stages[i];
    if !s.kind.updates() || !s.gather.is_empty() {
        return Err(None);
    }
    let mut rec = store.run_record(&s.name).ok_or(None)?;
    // Params that only say how to update, and those an update takes up (edits), may differ
    // from the parent's.
    let recipe = |v: &serde_json::Value| fingerprint::recipe(s.kind.as_ref(), v);
    let fixed = |v: &serde_json::Value| fingerprint::without(recipe(v), s.kind.editable_params());
    if rec.kind != s.kind.kind()
        || rec.version != s.kind.version()
        || fixed(&rec.params) != fixed(&s.params)
    {
        return Err(None);
    }
    if rec.inputs.get(FILES_SLOT).map(|x| &x.digest) != inputs.get(FILES_SLOT).map(|x| &x.digest) {
        return Err(Some("its input files changed".into()));
    }
    let slots = |m: &BTreeMap<String, InputInfo>| -> BTreeSet<String> {
        m.keys().filter(|k| !k.starts_with('@')).cloned().collect()
    };
    if slots(&rec.inputs) != slots(inputs) {
        return Err(Some("its inputs are connected differently".into()));
    }
    let gone = |what: &str| Some(format!("{what} is no longer in the cache"));
    // The record moved on to another configuration since this one ran: an update this stage
    // made from these very params and inputs stands for it (found in its history).
    if !same_config(s, (&rec.params, &rec.inputs), inputs) {
        if let Some(m) = earlier_update(store, s, &rec.history, inputs) {
            rec = RunRecord::of(m);
        }
    }
    // The last run was an update from these very inputs: its entry is the current one (the
    // same parent and inputs give the same key), not a parent.
    if let Some(grand) = rec.inputs.get(PARENT_SLOT) {
        let same = same_config(s, (&rec.params, &rec.inputs), inputs);
        if same && !again {
            return Ok(Found::Current(grand.digest.clone()));
        }
        if same {
            let m = match store.check(&grand.digest, false) {
                Entry::Valid(m) => m,
                _ => return Err(gone(&format!("its parent {}", short_key(&grand.digest)))),
            };
            rec = RunRecord::of(*m);
        }
    }
    let manifest = match store.check(&rec.key, false) {
        Entry::Valid(m) => m,
        _ => return Err(gone(&format!("its last entry {}", short_key(&rec.key)))),
    };
    let mut parent_inputs = Vec::new();
    let mut changed = Changed::new();
    let mut lineage = Lineage::default();
    for (slot, info) in inputs.iter().filter(|(k, _)| !k.starts_with('@')) {
        let before = rec.inputs[slot].key.as_deref().ok_or_else(|| {
            Some(format!(
                "its last run did not record the entry of input `{slot}`"
            ))
        })?;
        let read = &rec.inputs[slot].digest;
        let old = match store.check(before, false) {
            // The entry as the last run read it (a forced run may since have written other
            // bytes under the same key: nondeterministic on a GPU, or code changed in place).
            Entry::Valid(m) if &m.output_digest == read => m,
            // Gone (collected, say) or rewritten, but an entry with the same bytes serves.
            found => same_bytes(store, read).ok_or_else(|| match found {
                Entry::Valid(_) => Some(format!(
                    "the input `{slot}` of its last run was computed again since, with other \
                     bytes"
                )),
                _ => gone(&format!("the input `{slot}` of its last run")),
            })?,
        };
        let new = current(slot).ok_or_else(|| Some(format!("input `{slot}` has no entry")))?;
        debug_assert_eq!(Some(&new.key), info.key.as_ref());
        let reads = s
            .kind
            .inputs()
            .iter()
            .find(|x| x.name == slot)
            .map_or(&[][..], |x| x.tables);
        let differ: BTreeSet<String> = reads
            .iter()
            .filter(|t| table_digest(&old, t) != table_digest(&new, t))
            .map(|t| t.to_string())
            .collect();
        if !differ.is_empty() {
            changed.insert(slot.clone(), differ);
        }
        if descends(store, &new, &old.key) {
            lineage.descends.insert(slot.clone());
        }
        if (&new.kind, new.version, &new.params) == (&old.kind, old.version, &old.params) {
            lineage.same_recipe.insert(slot.clone());
        }
        parent_inputs.push((slot.clone(), old));
    }
    s.kind
        .can_update(&s.params, &changed, &lineage)
        .map_err(Some)?;
    let edited = s
        .kind
        .editable_params()
        .iter()
        .filter(|n| rec.params.get(**n) != s.params.get(**n))
        .map(|n| n.to_string())
        .collect::<Vec<_>>();
    // Forced after a run from scratch of these very inputs: from scratch again, not an
    // "update" that changes nothing.
    let same_inputs = parent_inputs
        .iter()
        .all(|(slot, m)| inputs[slot].key.as_ref() == Some(&m.key));
    if again && same_inputs && edited.is_empty() {
        return Err(None);
    }
    Ok(Found::Parent(Parent {
        manifest,
        inputs: parent_inputs,
        changed,
        lineage,
        edited,
    }))
}

/// Whether a run with `params` and inputs `ins` had the current params (but those that say
/// only how to update) and inputs of stage `s` (their digests).
fn same_config(
    s: &crate::config::StageDecl,
    (params, ins): (&serde_json::Value, &BTreeMap<String, InputInfo>),
    inputs: &BTreeMap<String, InputInfo>,
) -> bool {
    let recipe = |v: &serde_json::Value| fingerprint::recipe(s.kind.as_ref(), v);
    // Every input slot and the external files, by digest (not the parent: it is provenance).
    let digests = |m: &'_ BTreeMap<String, InputInfo>| {
        m.iter()
            .filter(|(k, _)| *k != PARENT_SLOT)
            .map(|(k, v)| (k.clone(), v.digest.clone()))
            .collect::<Vec<_>>()
    };
    recipe(params) == recipe(&s.params) && digests(ins) == digests(inputs)
}

/// The newest update among the entries `history` names that stage `s` made with its current
/// params and inputs.
fn earlier_update(
    store: &Store,
    s: &crate::config::StageDecl,
    history: &[String],
    inputs: &BTreeMap<String, InputInfo>,
) -> Option<Manifest> {
    history.iter().rev().find_map(|k| {
        let m = store.manifest_of(k)?;
        let fits = m.kind == s.kind.kind()
            && m.version == s.kind.version()
            && m.inputs.contains_key(PARENT_SLOT)
            && same_config(s, (&m.params, &m.inputs), inputs);
        fits.then_some(m)
    })
}

/// A valid entry whose outputs have digest `digest`, if the cache holds one.
fn same_bytes(store: &Store, digest: &str) -> Option<Box<Manifest>> {
    store.keys().into_iter().find_map(|k| {
        let m = store
            .manifest_of(&k)
            .filter(|m| m.output_digest == digest)?;
        match store.check(&m.key, false) {
            Entry::Valid(m) => Some(m),
            _ => None,
        }
    })
}

/// Whether entry `m` was updated, directly or through a few updates in between, from the entry
/// `ancestor` (a key); entries no longer cached end the search.
fn descends(store: &Store, m: &Manifest, ancestor: &str) -> bool {
    let mut parent = m.parent.clone();
    for _ in 0..16 {
        match parent {
            Some(k) if k == ancestor => return true,
            Some(k) => match store.check(&k, false) {
                Entry::Valid(up) => parent = up.parent.clone(),
                _ => return false,
            },
            None => return false,
        }
    }
    false
}

/// What [`find_parent`] found.
#[derive(Debug, Clone)]
pub enum Found {
    /// The entry to update.
    Parent(Parent),
    /// The stage's last run updated this parent (key) from the current inputs already.
    Current(String),
}

/// The key and inputs of the entry that updates `parent` (a key) from `inputs`.
pub fn updated_key(
    p: &Pipeline,
    i: usize,
    parent: &str,
    inputs: &BTreeMap<String, InputInfo>,
) -> (String, BTreeMap<String, InputInfo>) {
    let s = &p.stages[i];
    let mut inputs = inputs.clone();
    inputs.insert(
        PARENT_SLOT.into(),
        InputInfo {
            stage: format!("(the entry `{}` updated)", s.name),
            digest: parent.to_string(),
            key: Some(parent.to_string()),
        },
    );
    let by_digest = inputs
        .iter()
        .map(|(k, v)| (k.clone(), v.digest.clone()))
        .collect();
    // An update's key holds every param, those that say how to update included.
    let versions = (s.kind.version(), s.kind.update_version());
    let key = fingerprint::update_key(s.kind.kind(), versions, &s.params, &by_digest);
    (key, inputs)
}

/// ``` `scene`.primitives, `scene`.scene_info changed ```: the changed tables, for messages.
pub fn describe(changed: &Changed) -> String {
    if changed.is_empty() {
        return "no table it reads changed".into();
    }
    let tables: Vec<String> = changed
        .iter()
        .flat_map(|(slot, t)| t.iter().map(move |t| format!("`{slot}`.{t}")))
        .collect();
    format!("{} changed", tables.join(", "))
}
