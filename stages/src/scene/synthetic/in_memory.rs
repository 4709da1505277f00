//! The synthetic street's tables from a scene generated in memory (tests).

use super::{has_lidar, has_stereo, Generated, ImageTables, RowMaps, SceneParams};
use crate::stage::Inputs;
use crate::{Result, Tables};

/// The tables of a scene generated in memory; equal to what [`super::write_tables`] writes.
pub fn to_tables(p: &SceneParams, g: Generated) -> Result<Tables> {
    let no_slots = Inputs::new(Default::default());
    let mut out = ImageTables::open(&no_slots)?;
    let Generated {
        layout,
        cameras,
        images,
        labelled,
        pseudo,
        stereo,
        lidar,
    } = g;
    let (mut pseudo, mut stereo, mut lidar) =
        (pseudo.into_iter(), stereo.into_iter(), lidar.into_iter());
    for (i, (row, render)) in cameras.iter().zip(images).enumerate() {
        let m = RowMaps {
            render,
            pseudo: if labelled.contains(&i) {
                pseudo.next()
            } else {
                None
            },
            stereo: if has_stereo(row) { stereo.next() } else { None },
            lidar: if has_lidar(row) {
                lidar.next().map(|l| l.1)
            } else {
                None
            },
        };
        out.push(row, m)?;
    }
    let mut t = Tables::new();
    out.finish(p, &cameras, &layout, &mut t)?;
    Ok(t)
}
