//! The field's parameters as plain `(name, shape, values)` rows, for the `weights` table, and
//! back. Names are module paths (`grid.table`, `trunk.layers.0.weight`, ...), stable for a given
//! [`FieldSpec`](super::FieldSpec), so a field is rebuilt from its spec + these rows alone.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::{Tensor, TensorData};

use super::RadianceField;

/// One parameter tensor, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct NamedWeight {
    pub name: String,
    pub shape: Vec<usize>,
    pub values: Vec<f32>,
}

struct Collect {
    path: Vec<String>,
    out: Vec<NamedWeight>,
}

impl ModuleVisitor for Collect {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val();
        let shape = t.dims().to_vec();
        let values = t
            .into_data()
            .convert::<f32>()
            .try_to_vec::<f32>()
            .expect("f32 tensor data");
        self.out.push(NamedWeight {
            name: self.path.join("."),
            shape,
            values,
        });
    }
}

struct Replace<'a> {
    path: Vec<String>,
    rows: &'a [NamedWeight],
    used: usize,
    error: Option<String>,
}

impl ModuleMapper for Replace<'_> {
    fn enter_module(&mut self, name: &str, _: &str) {
        self.path.push(name.to_string());
    }
    fn exit_module(&mut self, _: &str, _: &str) {
        self.path.pop();
    }
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let name = self.path.join(".");
        let Some(row) = self.rows.iter().find(|r| r.name == name) else {
            self.error
                .get_or_insert(format!("weights have no row `{name}`"));
            return param;
        };
        let (id, tensor, mapper) = param.consume();
        let dims = tensor.dims().to_vec();
        if row.shape != dims || row.values.len() != dims.iter().product::<usize>() {
            self.error.get_or_insert(format!(
                "weight `{name}` has shape {:?} ({} values); the field expects {dims:?}",
                row.shape,
                row.values.len()
            ));
            return Param::from_mapped_value(id, tensor, mapper);
        }
        self.used += 1;
        let device = tensor.device();
        let value = Tensor::from_data(TensorData::new(row.values.clone(), dims), &device);
        let value = if tensor.is_require_grad() {
            value.require_grad()
        } else {
            value
        };
        Param::from_mapped_value(id, value, mapper)
    }
}

impl RadianceField {
    /// Every parameter, in module order.
    pub fn weights(&self) -> Vec<NamedWeight> {
        let mut c = Collect {
            path: Vec::new(),
            out: Vec::new(),
        };
        self.visit(&mut c);
        c.out
    }

    /// Replaces every parameter by the row of the same name; errors name a missing, misshapen
    /// or unexpected row.
    pub fn load_weights(self, rows: &[NamedWeight]) -> Result<Self, String> {
        let mut r = Replace {
            path: Vec::new(),
            rows,
            used: 0,
            error: None,
        };
        let field = self.map(&mut r);
        if let Some(e) = r.error {
            return Err(e);
        }
        if r.used != rows.len() {
            return Err(format!(
                "{} weight rows do not belong to this field (it has {} parameters)",
                rows.len() - r.used,
                r.used
            ));
        }
        Ok(field)
    }
}

#[cfg(test)]
mod tests {
    use crate::field::{Backend, FieldConfig, FieldSpec};

    #[test]
    fn weights_round_trip_through_rows() {
        let device = Backend::default().device();
        let spec = FieldSpec {
            config: FieldConfig::default(),
            num_classes: 4,
            aabb_min: [0.0; 3],
            aabb_max: [1.0; 3],
            seed: 1,
        };
        let a = spec.init(&device);
        let rows = a.weights();
        let names: Vec<&str> = rows.iter().map(|r| r.name.as_str()).collect();
        assert!(names.contains(&"grid.table"), "{names:?}");
        assert!(names.contains(&"semantic.layers.1.bias"), "{names:?}");
        let b = FieldSpec {
            seed: 2,
            ..spec.clone()
        }
        .init(&device);
        assert_ne!(b.weights(), rows);
        let b = b.load_weights(&rows).unwrap();
        assert_eq!(b.weights(), rows);
        let mut bad = rows.clone();
        bad[0].shape = vec![1];
        assert!(spec.init(&device).load_weights(&bad).is_err());
    }
}
