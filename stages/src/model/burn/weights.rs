//! A burn field's parameters read back as named rows ([`crate::model::params`] is the layout
//! they follow; [`RadianceField::from_weights`] is the way in).

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::Tensor;

use super::field::RadianceField;
use crate::model::params::NamedWeight;

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
}
