//! Renders "first primitive hit" pictures through the full `intersect` stage path (tables in,
//! stage run, export): the hand-made street scene and the benchmark's synthetic city.
//!
//! `cargo run -p stages --example first_hit -- <out dir>` (default `target-pictures`)

use stages::{
    geometry::{cameras_to_table, demo, primitives_to_table, CameraRow},
    intervals::IntersectParams,
    kinds::intersect::Intersect,
    NoProgress, Tables, TypedStage,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::path::PathBuf::from(std::env::args().nth(1).unwrap_or("target-pictures".into()));
    let scenes = [
        ("street", demo::street_scene(1408, 376)),
        ("city", demo::city_scene(1000, 1408, 376, 42)),
    ];
    for (name, (prims, cam)) in scenes {
        let rows = vec![CameraRow {
            frame: 0,
            camera: 0,
            eval: true,
            cam,
        }];
        let scene = Tables::from([
            ("cameras".to_string(), cameras_to_table(&rows)?),
            ("primitives".to_string(), primitives_to_table(&prims)?),
        ]);
        let mem = stages::MemoryInputs::new([("scene", scene)]);
        let inputs = mem.inputs();
        let p = IntersectParams {
            cameras: vec![0],
            ..Default::default()
        };
        let start = std::time::Instant::now();
        let tables = Intersect.run(&p, &inputs, &NoProgress)?;
        eprintln!(
            "{name}: {} primitives, planned in {:.2?}",
            prims.len(),
            start.elapsed()
        );
        for f in Intersect.export(&p, &tables.into(), &out.join(name))? {
            println!("{}", f.display());
        }
    }
    Ok(())
}
