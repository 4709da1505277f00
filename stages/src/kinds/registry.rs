//! Every stage kind, by name. The runner knows stages only through this.

use super::{
    aggregate, evaluate, intersect, kitti360_scene, motion_stereo, render, report, review,
    stereo_depth, synthetic_scene, testing, train,
};
use crate::stage::Stage;

/// Every stage kind, by name.
pub fn registry() -> Vec<Box<dyn Stage>> {
    let mut all: Vec<Box<dyn Stage>> = vec![
        Box::new(synthetic_scene::SyntheticScene),
        Box::new(kitti360_scene::Kitti360Scene),
        Box::new(stereo_depth::StereoDepth),
        Box::new(motion_stereo::MotionStereo),
        Box::new(intersect::Intersect),
        Box::new(train::Train),
        Box::new(render::Render),
        Box::new(review::Review),
        Box::new(evaluate::Evaluate),
        Box::new(report::Report),
        Box::new(aggregate::Aggregate),
    ];
    all.extend(testing::kinds());
    all
}

/// Looks up one kind by name.
pub fn find(kind: &str) -> Option<Box<dyn Stage>> {
    registry().into_iter().find(|s| s.kind() == kind)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params_doc;

    /// The longest first sentence `pipe kinds KIND` shows on a parameter's line.
    const MAX_SUMMARY: usize = 100;

    /// `pipe kinds KIND` documents every parameter of every kind: a doc comment whose first
    /// sentence fits on its line, and a type.
    #[test]
    fn every_parameter_has_a_short_doc_and_a_type() {
        let mut missing = Vec::new();
        for k in registry().iter().filter(|k| !k.kind().starts_with("test_")) {
            let docs = k.param_docs();
            assert!(!docs.is_empty(), "{} has no parameters", k.kind());
            for d in docs {
                let what = format!("{}: `{}`", k.kind(), d.path);
                if d.doc.is_empty() {
                    missing.push(format!("{what} has no doc comment"));
                } else if d.summary().len() > MAX_SUMMARY {
                    missing.push(format!(
                        "{what}: first sentence of {} characters (at most {MAX_SUMMARY}): {}",
                        d.summary().len(),
                        d.summary()
                    ));
                }
                if d.ty == "any" || d.ty.is_empty() {
                    missing.push(format!("{what} has no type"));
                }
            }
        }
        assert!(missing.is_empty(), "{}", missing.join("\n"));
    }

    /// The commented YAML of `pipe kinds KIND --yaml` is the kind's defaults: pasted into a
    /// pipeline file it validates and changes nothing.
    #[test]
    fn every_kind_s_yaml_block_is_its_defaults() {
        for k in registry() {
            let docs = k.param_docs();
            let text = format!("params:\n{}", params_doc::yaml_params(&docs, 2, 100));
            let v: serde_yaml::Value =
                serde_yaml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}\n{text}", k.kind()));
            let params = serde_json::to_value(&v["params"]).unwrap();
            let params = if params.is_null() {
                serde_json::json!({})
            } else {
                params
            };
            let got = k.canonical_params(&params);
            let want = k.canonical_params(&k.default_params());
            match (got, want) {
                (Ok(g), Ok(w)) => assert_eq!(g, w, "{}:\n{text}", k.kind()),
                // Kinds whose defaults need a value from the user (a KITTI-360 root) fail the
                // same way both times.
                (Err(g), Err(w)) => assert_eq!(g.to_string(), w.to_string(), "{}", k.kind()),
                (g, w) => panic!("{}: {g:?} against the defaults' {w:?}\n{text}", k.kind()),
            }
            // Every parameter, group or not, appears once, under its doc.
            for d in &docs {
                assert!(
                    text.contains(&format!("{}:", d.key())),
                    "{}: `{}` missing",
                    k.kind(),
                    d.path
                );
            }
        }
    }

    /// Every moved parameter names a new place that exists (or a note alone), and no current
    /// parameter is taken for a moved one.
    #[test]
    fn moved_parameters_point_at_parameters_that_exist() {
        for k in registry() {
            let paths: Vec<String> = k.param_docs().into_iter().map(|d| d.path).collect();
            for d in &paths {
                assert_eq!(k.moved_param(d), None, "{}: `{d}` is current", k.kind());
            }
            for (old, _) in k.moved_params() {
                assert!(!paths.contains(&old.to_string()), "{}: `{old}`", k.kind());
                let to = k.moved_param(old).unwrap();
                if !to.starts_with('(') {
                    let to = to.split(' ').next().unwrap().to_string();
                    assert!(paths.contains(&to), "{}: `{old}` -> `{to}`", k.kind());
                }
            }
        }
    }
}
