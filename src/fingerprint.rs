//! Cache keys. A stage's key is the blake3 hash of a canonical serialisation of what determines
//! its outputs: the kind, the kind's code VERSION, the canonical params (defaults filled in,
//! keys sorted) and, per input slot (sorted), the *output digest* of the upstream stage. Keying
//! on upstream outputs rather than upstream keys gives early cutoff: an upstream re-run that
//! writes identical bytes leaves every downstream key unchanged.
//!
//! What does NOT enter the key, on purpose: the stage instance's name, its position in the
//! file, the upstream stage's name (only what it wrote), timing, the tool version.

use std::collections::BTreeMap;

use serde_json::{json, Value};

/// Pseudo input slot under which the digest of a stage's external files enters its key.
pub const FILES_SLOT: &str = "@files";
/// Pseudo input slot under which an updated entry's key holds its parent's key (see
/// `runner::parent`).
pub const PARENT_SLOT: &str = "@parent";

/// `params` without the kind's update-only params ([`stages::Stage::update_only_params`]): what
/// a run from scratch is keyed by, and what a parent's params must equal.
pub fn recipe(kind: &dyn stages::Stage, params: &serde_json::Value) -> serde_json::Value {
    without(params.clone(), kind.update_only_params())
}

/// `params` without the top-level params `names`.
pub fn without(mut params: serde_json::Value, names: &[&str]) -> serde_json::Value {
    if let serde_json::Value::Object(m) = &mut params {
        for name in names {
            m.remove(*name);
        }
    }
    params
}

/// Hex blake3 of the canonical description of a stage run.
pub fn stage_key(
    kind: &str,
    version: u32,
    params: &Value,
    inputs: &BTreeMap<String, String>,
) -> String {
    // serde_json's Map is a BTreeMap (no `preserve_order`), so objects serialise sorted.
    hash_of(&json!({
        "kind": kind,
        "version": version,
        "params": params,
        "inputs": inputs,
    }))
}

/// The key of an entry updated from a parent (whose key is among `inputs`): as
/// [`stage_key`], with the kind's update version where it is not 0.
pub fn update_key(
    kind: &str,
    (version, update_version): (u32, u32),
    params: &Value,
    inputs: &BTreeMap<String, String>,
) -> String {
    if update_version == 0 {
        return stage_key(kind, version, params, inputs);
    }
    hash_of(&json!({
        "kind": kind,
        "version": version,
        "update_version": update_version,
        "params": params,
        "inputs": inputs,
    }))
}

/// Hex blake3 of a canonical description.
fn hash_of(canonical: &Value) -> String {
    blake3::hash(canonical.to_string().as_bytes())
        .to_hex()
        .to_string()
}

/// Digest of a stage's outputs from its files' digests (file name -> hex blake3).
pub fn output_digest(files: &BTreeMap<String, String>) -> String {
    let mut h = blake3::Hasher::new();
    for (name, digest) in files {
        h.update(name.as_bytes());
        h.update(&[0]);
        h.update(digest.as_bytes());
        h.update(b"\n");
    }
    h.finalize().to_hex().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Guards against accidental changes to keying: every user's cache would go stale.
    #[test]
    fn key_of_a_fixed_input_is_pinned() {
        let params = json!({"value": 1, "rows": 3, "salt": "", "sleep_ms": 0, "fail": false});
        let inputs = BTreeMap::from([("src".to_string(), "ab".repeat(32))]);
        let key = stage_key("test_map", 1, &params, &inputs);
        let canonical = format!(
            r#"{{"inputs":{{"src":"{}"}},"kind":"test_map","params":{{"fail":false,"rows":3,"salt":"","sleep_ms":0,"value":1}},"version":1}}"#,
            "ab".repeat(32)
        );
        assert_eq!(key, blake3::hash(canonical.as_bytes()).to_hex().to_string());
        assert_eq!(
            key,
            "f254a7120c81803451b8a904a89dd1fbad4a75cb97dc020fec0eed974e29b5ba"
        );
    }

    /// An update's code version keys updates alone; at 0 an update keys as before it existed.
    #[test]
    fn the_update_version_keys_updates_only() {
        let params = json!({"x": 1});
        let inputs = BTreeMap::from([(PARENT_SLOT.to_string(), "cd".repeat(32))]);
        let plain = stage_key("k", 3, &params, &inputs);
        assert_eq!(update_key("k", (3, 0), &params, &inputs), plain);
        let one = update_key("k", (3, 1), &params, &inputs);
        assert_ne!(one, plain);
        assert_ne!(one, update_key("k", (3, 2), &params, &inputs));
        assert_eq!(one, update_key("k", (3, 1), &params, &inputs));
    }

    #[test]
    fn key_ignores_param_order_but_not_values() {
        let a: Value = serde_json::from_str(r#"{"x": 1, "y": 2}"#).unwrap();
        let b: Value = serde_json::from_str(r#"{"y": 2, "x": 1}"#).unwrap();
        let c: Value = serde_json::from_str(r#"{"y": 2, "x": 2}"#).unwrap();
        let none = BTreeMap::new();
        assert_eq!(stage_key("k", 1, &a, &none), stage_key("k", 1, &b, &none));
        assert_ne!(stage_key("k", 1, &a, &none), stage_key("k", 1, &c, &none));
        assert_ne!(stage_key("k", 1, &a, &none), stage_key("k", 2, &a, &none));
    }

    /// A run from scratch is keyed without the params that only say how to update: setting
    /// them leaves every cached entry current; any other param changes the key.
    #[test]
    fn update_only_params_stay_out_of_the_recipe() {
        let train = stages::kinds::registry()
            .into_iter()
            .find(|k| k.kind() == "train")
            .unwrap();
        let none = BTreeMap::new();
        let key = |v: serde_json::Value| {
            let p = train.canonical_params(&v).unwrap();
            stage_key("train", 1, &recipe(train.as_ref(), &p), &none)
        };
        let plain = key(serde_json::json!({}));
        assert_eq!(
            key(serde_json::json!({"update": {"iterations": 50}})),
            plain
        );
        assert_ne!(key(serde_json::json!({"seed": 3})), plain);
    }
}
