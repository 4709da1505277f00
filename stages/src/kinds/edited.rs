//! The scene's primitives before and after an edit, as the updating kinds (`intersect`,
//! `train`, `render`) read them from the previous run's `scene` input and the current one.

use crate::geometry::{self, Primitive, PrimitiveChanges};
use crate::stage::{Inputs, Previous, Result};

/// The primitives of the previous run's scene (`old`) and of the current one (`new`), matched.
pub(crate) struct Edited {
    pub old: Vec<Primitive>,
    pub new: Vec<Primitive>,
    pub changes: PrimitiveChanges,
}

impl Edited {
    /// Reads slot `scene`'s `primitives` of `previous` and of `inputs`.
    pub fn read(previous: &Previous, inputs: &Inputs) -> Result<Self> {
        let old_table = previous.input("scene", "primitives")?.whole()?;
        let new_table = inputs.table("scene", "primitives")?;
        Ok(Self {
            changes: PrimitiveChanges::between(old_table, new_table)?,
            old: geometry::primitives_from_table(old_table)?,
            new: geometry::primitives_from_table(new_table)?,
        })
    }

    /// The changed primitives' old and new extents ([`PrimitiveChanges::extents`]).
    pub fn extents(&self) -> Vec<Primitive> {
        self.changes.extents(&self.old, &self.new)
    }
}
