//! The field's parameters as plain `(name, shape, values)` rows: the one layout both engines
//! read and write, the rows of the `weights` table, and their seeded initialisation.
//!
//! Names are module paths (`grid.table`, `trunk.layers.0.weight`, ...), stable for a given
//! [`FieldSpec`], so a field is rebuilt from its spec and these rows alone, by any engine.
//! Initial values come from [`SplitMix64`] on the host, so a seed gives the same start on every
//! engine and backend.

use super::config::{EncodingKind, FieldSpec};
use super::error::ModelError;
use crate::rng::SplitMix64;

/// One parameter tensor, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedWeight {
    pub name: String,
    pub shape: Vec<usize>,
    pub values: Vec<f32>,
}

/// How one parameter starts.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Init {
    /// Uniform in `[-bound, bound]`.
    Uniform(f32),
    Zero,
}

/// The dense layers `inputs -> hidden (x hidden_layers) -> outputs` of the MLP `prefix`, as
/// (name, [inputs, outputs] or [outputs], init): Kaiming-uniform weights (bound
/// `sqrt(6 / inputs)`, suited to ReLU), zero biases.
fn mlp(
    out: &mut Vec<(String, Vec<usize>, Init)>,
    prefix: &str,
    inputs: usize,
    hidden: usize,
    hidden_layers: usize,
    outputs: usize,
) {
    let mut widths = vec![inputs];
    widths.extend(std::iter::repeat_n(hidden, hidden_layers));
    widths.push(outputs);
    for (i, w) in widths.windows(2).enumerate() {
        let bound = (6.0 / w[0] as f32).sqrt();
        out.push((
            format!("{prefix}.layers.{i}.weight"),
            vec![w[0], w[1]],
            Init::Uniform(bound),
        ));
        out.push((format!("{prefix}.layers.{i}.bias"), vec![w[1]], Init::Zero));
    }
}

/// Every parameter of a field with `spec`, in order: the grid table (grid encoding only), then
/// the trunk (`enc(x) -> [raw density, geometry features]`), the colour head (`[geometry
/// features, enc(d)] -> rgb`) and the semantic head (`geometry features -> logits`).
fn plan(spec: &FieldSpec) -> Vec<(String, Vec<usize>, Init)> {
    let c = &spec.config;
    let mut out = Vec::new();
    if c.encoding == EncodingKind::Grid {
        out.push((
            "grid.table".to_string(),
            vec![
                c.grid.levels * c.grid.table_size(),
                c.grid.features_per_level,
            ],
            Init::Uniform(c.grid.init_scale),
        ));
    }
    let (h, g) = (c.hidden, c.geo_features);
    mlp(
        &mut out,
        "trunk",
        c.position_dim(),
        h,
        c.trunk_layers,
        1 + g,
    );
    mlp(
        &mut out,
        "colour",
        g + c.direction_dim(),
        h,
        c.head_layers,
        3,
    );
    mlp(&mut out, "semantic", g, h, c.head_layers, spec.num_classes);
    out
}

/// Names and shapes of the parameters of a field with `spec`, in order.
pub fn layout(spec: &FieldSpec) -> Vec<(String, Vec<usize>)> {
    plan(spec).into_iter().map(|(n, s, _)| (n, s)).collect()
}

/// The initial parameters of a field with `spec`, drawn in order from `SplitMix64(spec.seed)`.
pub fn initial(spec: &FieldSpec) -> Vec<NamedWeight> {
    let mut rng = SplitMix64::new(spec.seed);
    plan(spec)
        .into_iter()
        .map(|(name, shape, init)| {
            let n = shape.iter().product();
            let values = match init {
                Init::Uniform(b) => (0..n).map(|_| rng.uniform(-b, b)).collect(),
                Init::Zero => vec![0.0; n],
            };
            NamedWeight {
                name,
                shape,
                values,
            }
        })
        .collect()
}

/// Checks that `rows` are exactly the parameters of `spec` (any order); errors name a
/// missing, misshapen or unexpected row.
pub fn check(spec: &FieldSpec, rows: &[NamedWeight]) -> Result<(), ModelError> {
    let want = layout(spec);
    for (name, shape) in &want {
        let Some(row) = rows.iter().find(|r| &r.name == name) else {
            return Err(ModelError::Weights(format!("weights have no row `{name}`")));
        };
        if &row.shape != shape || row.values.len() != shape.iter().product::<usize>() {
            return Err(ModelError::Weights(format!(
                "weight `{name}` has shape {:?} ({} values); the field expects {shape:?}",
                row.shape,
                row.values.len()
            )));
        }
    }
    if rows.len() != want.len() {
        return Err(ModelError::Weights(format!(
            "{} weight rows do not belong to this field (it has {} parameters)",
            rows.len().saturating_sub(want.len()),
            want.len()
        )));
    }
    Ok(())
}

/// Index of the row called `name`.
pub fn index(rows: &[NamedWeight], name: &str) -> Option<usize> {
    rows.iter().position(|w| w.name == name)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{FieldConfig, GridConfig};

    fn spec(config: FieldConfig) -> FieldSpec {
        FieldSpec {
            config,
            num_classes: 4,
            aabb_min: [0.0; 3],
            aabb_max: [1.0; 3],
            seed: 1,
        }
    }

    #[test]
    fn layout_has_the_documented_names_and_shapes() {
        let s = spec(FieldConfig {
            grid: GridConfig {
                levels: 2,
                log2_table_size: 6,
                features_per_level: 3,
                ..Default::default()
            },
            hidden: 8,
            geo_features: 5,
            trunk_layers: 1,
            head_layers: 1,
            pe_direction_frequencies: 4,
            ..Default::default()
        });
        let l = layout(&s);
        let get = |n: &str| l.iter().find(|(m, _)| m == n).map(|(_, s)| s.clone());
        assert_eq!(l[0].0, "grid.table");
        assert_eq!(get("grid.table"), Some(vec![2 * 64, 3]));
        assert_eq!(get("trunk.layers.0.weight"), Some(vec![6, 8]));
        assert_eq!(get("trunk.layers.1.weight"), Some(vec![8, 6]));
        assert_eq!(get("colour.layers.0.weight"), Some(vec![5 + 27, 8]));
        assert_eq!(get("colour.layers.1.bias"), Some(vec![3]));
        assert_eq!(get("semantic.layers.1.weight"), Some(vec![8, 4]));
        assert_eq!(l.len(), 1 + 4 + 4 + 4);
        let pe = layout(&spec(FieldConfig::pe()));
        assert_eq!(pe[0].0, "trunk.layers.0.weight", "no grid for pe");
    }

    #[test]
    fn initial_values_are_seeded_bounded_and_checked() {
        let s = spec(FieldConfig::default());
        let a = initial(&s);
        assert_eq!(a, initial(&s));
        assert_ne!(
            a,
            initial(&FieldSpec {
                seed: 2,
                ..s.clone()
            })
        );
        check(&s, &a).unwrap();
        let grid = &a[0];
        let b = s.config.grid.init_scale;
        assert!(grid.values.iter().all(|v| v.abs() <= b));
        let w0 = &a[1];
        let bound = (6.0 / w0.shape[0] as f32).sqrt();
        assert!(w0.values.iter().all(|v| v.abs() <= bound));
        assert!(w0.values.iter().any(|v| v.abs() > 0.5 * bound));
        assert!(a[2].values.iter().all(|&v| v == 0.0), "biases start at 0");
        let mut bad = a.clone();
        bad[1].shape = vec![1];
        assert!(check(&s, &bad)
            .unwrap_err()
            .to_string()
            .contains("trunk.layers.0.weight"));
        let mut extra = a.clone();
        extra.push(a[2].clone());
        assert!(check(&s, &extra).is_err());
        assert!(check(&s, &a[1..])
            .unwrap_err()
            .to_string()
            .contains("grid.table"));
    }
}
