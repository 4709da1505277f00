//! What `pipe kinds KIND` prints: a kind's inputs, outputs and parameters, as text (one
//! parameter a line) or as a commented YAML stage for a pipeline file.

use stages::{params_doc, InputSlot, Stage};

/// `pipe kinds KIND`: the kind, its inputs and outputs, and one line per parameter (groups
/// headed by their doc).
pub fn text(k: &dyn Stage) -> String {
    let updates = match k.update_version() {
        0 => String::new(),
        v => format!(", update version {v}"),
    };
    let mut out = format!(
        "{} (version {}{updates}): {}\n",
        k.kind(),
        k.version(),
        k.description()
    );
    for s in k.inputs() {
        out.push_str(&format!(
            "  input  {}{}: {} [{}]\n",
            s.name,
            if s.optional { " (optional)" } else { "" },
            s.doc,
            s.tables.join(", ")
        ));
    }
    out.push_str(&format!("  output {}\n", k.outputs().join(", ")));
    let docs = k.param_docs();
    if docs.is_empty() {
        out.push_str("  no parameters\n");
        return out;
    }
    let leaves = || docs.iter().filter(|d| !d.group);
    let defaults: Vec<String> = docs.iter().map(|d| params_doc::show(&d.default)).collect();
    let w_path = docs.iter().map(|d| d.path.len()).max().unwrap_or(0);
    let w_type = leaves().map(|d| d.ty.len()).max().unwrap_or(0).min(24);
    let w_default = docs
        .iter()
        .zip(&defaults)
        .filter(|(d, _)| !d.group)
        .map(|(_, s)| s.len())
        .max()
        .unwrap_or(0)
        .min(14);
    out.push_str(&format!(
        "\n  {:w_path$}  {:w_type$}  {:w_default$}  what it does\n",
        "parameter", "type", "default"
    ));
    for (d, default) in docs.iter().zip(&defaults) {
        if d.group {
            out.push_str(&format!("\n  {}: {}\n", d.path, d.summary()));
        } else {
            out.push_str(&format!(
                "  {:w_path$}  {:w_type$}  {:w_default$}  {}\n",
                d.path,
                d.ty,
                default,
                d.summary()
            ));
        }
    }
    out
}

/// `pipe kinds KIND --yaml`: a stage of the kind with its inputs and every parameter at its
/// default, each under its doc, to paste into a pipeline file's `stages:`.
pub fn yaml(k: &dyn Stage) -> String {
    let mut out = format!(
        "  # {}\n  {}:\n    uses: {}\n",
        k.description(),
        k.kind(),
        k.kind()
    );
    let (required, optional): (Vec<&InputSlot>, Vec<_>) =
        k.inputs().iter().partition(|s| !s.optional);
    if !required.is_empty() {
        let slots: Vec<String> = required
            .iter()
            .map(|s| format!("{}: {}", s.name, s.name))
            .collect();
        out.push_str(&format!("    inputs: {{{}}}", slots.join(", ")));
        if !optional.is_empty() {
            let names: Vec<&str> = optional.iter().map(|s| s.name).collect();
            out.push_str(&format!("    # optional: {}", names.join(", ")));
        }
        out.push('\n');
    }
    let docs = k.param_docs();
    if !docs.is_empty() {
        out.push_str("    params:\n");
        out.push_str(&params_doc::yaml_params(&docs, 6, 100));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One line per parameter, grouped; the YAML is a stage a pipeline file takes as it is.
    #[test]
    fn train_reads_as_one_parameter_a_line_and_as_a_stage() {
        let train = stages::kinds::find("train").unwrap();
        let t = text(train.as_ref());
        let line = |path: &str| {
            t.lines()
                .find(|l| l.trim_start().starts_with(&format!("{path} ")))
                .unwrap_or_else(|| panic!("no line for `{path}`:\n{t}"))
                .to_string()
        };
        let it = line("schedule.iterations");
        assert!(
            it.contains("integer") && it.contains("1700") && it.contains("steps"),
            "{it}"
        );
        assert!(line("field.encoding").contains("grid | pe"));
        assert!(t.contains("\n  losses: "), "groups are headed:\n{t}");
        assert!(!t.contains("train.train"), "{t}");
        let y = yaml(train.as_ref());
        let doc: serde_yaml::Value = serde_yaml::from_str(&y).unwrap();
        assert_eq!(doc["train"]["uses"], "train");
        assert_eq!(doc["train"]["inputs"]["rays"], "rays");
        assert_eq!(doc["train"]["params"]["schedule"]["iterations"], 1700);
        assert!(y.contains("      # Optimisation steps"), "{y}");
    }
}
