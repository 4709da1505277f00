//! Moving objects of the bounding-box XML (`timestamp` = a frame): their own table, checked
//! by name, written back by the export and read by the devkit's rule.

use super::*;
use crate::geometry::{
    dynamic_boxes_from_table, dynamic_boxes_to_table, DAffine3, DynamicBox, Primitive,
};

/// A unit-cube object element of class `semantic` (a kittiId), instance `instance`, centred at
/// world `x` metres along the first axis of the fixture's cars, at `timestamp`.
fn cube(n: usize, semantic: i64, instance: i64, x: f64, timestamp: i64) -> String {
    format!(
        "<object{n}>\n  <transform type_id=\"opencv-matrix\"><rows>4</rows><cols>4</cols><dt>f</dt>\
         <data>2. 0. 0. {x} 0. 1. 0. 2000.25 0. 0. 1.5 110. 0. 0. 0. 1.</data></transform>\n  \
         <vertices type_id=\"opencv-matrix\"><rows>8</rows><cols>3</cols><dt>f</dt><data>-0.5 \
         -0.5 -0.5 0.5 -0.5 -0.5 -0.5 0.5 -0.5 0.5 0.5 -0.5 -0.5 -0.5 0.5 0.5 -0.5 0.5 -0.5 0.5 \
         0.5 0.5 0.5 0.5</data></vertices>\n  <faces type_id=\"opencv-matrix\"><rows>12</rows>\
         <cols>3</cols><dt>u</dt><data>0 2 3 0 3 1 4 5 7 4 7 6 0 1 5 0 5 4 2 6 7 2 7 3 0 4 6 0 6 \
         2 1 3 7 1 7 5</data></faces>\n  <semanticId>{semantic}</semanticId>\n  \
         <instanceId>{instance}</instanceId>\n  <timestamp>{timestamp}</timestamp>\n\
         </object{n}>\n"
    )
}

/// The fixture with `extra` object elements appended to its bounding-box XML.
fn fixture_with(name: &str, extra: &[String]) -> (PathBuf, Kitti360Params) {
    let (root, p) = fixture(name);
    let xml = p.file(&p.bboxes);
    let text = std::fs::read_to_string(&xml).unwrap();
    let text = text.replace("</opencv_storage>", &(extra.concat() + "</opencv_storage>"));
    std::fs::write(&xml, text).unwrap();
    (root, p)
}

/// `(globalId, timestamp) -> (index, start_frame, end_frame)` of every object element, the keys
/// the devkit's `Annotation3D` files them under (written here from its description).
fn devkit_objects(text: &str) -> std::collections::BTreeMap<(i64, i64), (i64, i64, i64)> {
    let doc = roxmltree::Document::parse(text).unwrap();
    let field = |obj: roxmltree::Node, tag: &str| -> i64 {
        let c = obj.children().find(|c| c.has_tag_name(tag));
        c.and_then(|c| c.text()).unwrap().trim().parse().unwrap()
    };
    let mut out = std::collections::BTreeMap::new();
    for obj in doc.root_element().children().filter(|c| c.is_element()) {
        let global = field(obj, "semanticId") * 1000 + field(obj, "instanceId");
        let fields = (
            field(obj, "index"),
            field(obj, "start_frame"),
            field(obj, "end_frame"),
        );
        let key = (global, field(obj, "timestamp"));
        assert!(out.insert(key, fields).is_none(), "{key:?} twice");
    }
    out
}

#[test]
fn moving_objects_load_apart_and_export_back_for_the_devkit() {
    // Car 5 (kittiId 13) moves 1 m a frame: boxes at frames 3 and 7 (selected), and 12 (posed,
    // outside the selected 0..=10); cyclist 2 (kittiId 18) only at frame 7.
    let extra = [
        cube(10, 13, 5, 1000.0, 3),
        cube(11, 13, 5, 1004.0, 7),
        cube(12, 13, 5, 1009.0, 12),
        cube(13, 18, 2, 1001.0, 7),
    ];
    let (root, p) = fixture_with("dynamic", &extra);
    let t = run(&p).unwrap();
    // The static primitives are those of the fixture alone.
    assert_eq!(primitives_from_table(&t["primitives"]).unwrap().len(), 2);
    let boxes = dynamic_boxes_from_table(&t["dynamic_boxes"]).unwrap();
    let keys: Vec<(u32, u32)> = boxes.iter().map(|b| (b.object, b.frame)).collect();
    let car = u32::from(labels::CAR) * 1000 + 5;
    let cyclist = labels::by_kitti_id(18).unwrap();
    assert!(cyclist.has_instances, "{}", cyclist.name);
    let bike = u32::from(cyclist.id) * 1000 + 2;
    let mut expected = vec![(car, 3), (car, 7), (bike, 7)];
    expected.sort();
    assert_eq!(keys, expected);
    let at7 = boxes
        .iter()
        .find(|b| (b.object, b.frame) == (car, 7))
        .unwrap();
    assert_eq!(at7.primitive.shape, Shape::Cuboid);
    assert_eq!(
        (at7.primitive.label, at7.primitive.instance),
        (labels::CAR, 5)
    );
    // Recentred on the origin (1001, 2000, 100) like the static primitives.
    let centre = at7.primitive.to_world.translation;
    assert!(
        (centre - DVec3::new(3.0, 0.25, 10.0)).length() < 1e-12,
        "{centre}"
    );

    // `pipe export scene` writes them back: one element per box, keyed by the devkit as
    // (globalId, frame), the object's first and last frame as its span.
    let out = temp("dynamic-export");
    kitti360_export::write(&t, &out).unwrap();
    let q = Kitti360Params {
        root: out.display().to_string(),
        ..p.clone()
    };
    let text = std::fs::read_to_string(q.file(&q.bboxes)).unwrap();
    let objects = devkit_objects(&text);
    assert_eq!(objects.len(), 2 + 3);
    let (_, start, end) = objects[&(13 * 1000 + 5, 3)];
    assert_eq!((start, end), (3, 7));
    assert_eq!(objects[&(13 * 1000 + 5, 7)].1, 3);
    assert_eq!(objects[&(18 * 1000 + 2, 7)].1, 7);
    assert!(objects.keys().filter(|k| k.1 == -1).count() == 2);
    // ... and the loader reads the same boxes from them.
    let again = dynamic_boxes_from_table(&run(&q).unwrap()["dynamic_boxes"]).unwrap();
    assert_eq!(again.len(), boxes.len());
    for (a, b) in again.iter().zip(&boxes) {
        assert_eq!((a.object, a.frame), (b.object, b.frame));
        let d = a.primitive.to_world.matrix3 - b.primitive.to_world.matrix3;
        let dt = a.primitive.to_world.translation - b.primitive.to_world.translation;
        assert!(d.abs().to_cols_array().iter().all(|&x| x < 1e-9) && dt.length() < 1e-9);
    }
    std::fs::remove_dir_all(root).unwrap();
    std::fs::remove_dir_all(out).unwrap();
}

#[test]
fn a_moving_object_outside_the_sequence_or_twice_in_a_frame_is_refused_by_name() {
    // Frame 99: the sequence's poses run from 3 to 12.
    let (root, p) = fixture_with("dynamic-late", &[cube(10, 13, 5, 1000.0, 99)]);
    let e = run(&p).unwrap_err().to_string();
    assert!(e.contains("seq_a.xml"), "{e}");
    assert!(
        e.contains("<object10>/<timestamp>: 99 is outside the sequence's frames 3..=12"),
        "{e}"
    );
    std::fs::remove_dir_all(root).unwrap();
    // A negative frame other than -1.
    let (root, p) = fixture_with("dynamic-negative", &[cube(10, 13, 5, 1000.0, -4)]);
    let e = run(&p).unwrap_err().to_string();
    assert!(e.contains("<object10>/<timestamp>: -4 is outside"), "{e}");
    std::fs::remove_dir_all(root).unwrap();
    // The same object twice at frame 7.
    let twice = [cube(10, 13, 5, 1000.0, 7), cube(11, 13, 5, 1001.0, 7)];
    let (root, p) = fixture_with("dynamic-twice", &twice);
    let e = run(&p).unwrap_err().to_string();
    assert!(
        e.contains(
            "<object10> and <object11> are both object (semanticId 13, instanceId 5) at frame 7"
        ),
        "{e}"
    );
    std::fs::remove_dir_all(root).unwrap();
    // Two moving objects of a stuff class (kittiId 8, fence) in one frame stay two objects.
    let stuff = [cube(10, 8, 3, 1000.0, 7), cube(11, 8, 4, 1001.0, 7)];
    let (root, p) = fixture_with("dynamic-stuff", &stuff);
    let boxes = dynamic_boxes_from_table(&run(&p).unwrap()["dynamic_boxes"]).unwrap();
    let fence = u32::from(labels::by_kitti_id(8).unwrap().id) * 1000;
    let keys: Vec<(u32, u32)> = boxes.iter().map(|b| (b.object, b.frame)).collect();
    assert_eq!(keys, vec![(fence + 3, 7), (fence + 4, 7)]);
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn the_dynamic_boxes_table_round_trips_and_names_bad_rows() {
    let car = |instance: u32, frame: u32, x: f64| DynamicBox {
        object: u32::from(labels::CAR) * 1000 + instance,
        frame,
        primitive: Primitive::new(
            Shape::Cuboid,
            DAffine3::from_translation(DVec3::new(x, 0.0, 0.0)),
            labels::CAR,
            instance,
        )
        .unwrap(),
    };
    let boxes = vec![car(1, 0, 0.0), car(1, 1, 1.0), car(2, 0, 5.0)];
    let t = dynamic_boxes_to_table(&boxes).unwrap();
    assert_eq!(
        *t.schema(),
        *crate::schema::get("dynamic_boxes").unwrap(),
        "the table's schema is data_schema/dynamic_boxes.json"
    );
    let back = dynamic_boxes_from_table(&t).unwrap();
    let keys = |b: &[DynamicBox]| -> Vec<(u32, u32, f64)> {
        b.iter()
            .map(|b| (b.object, b.frame, b.primitive.to_world.translation.x))
            .collect()
    };
    assert_eq!(keys(&back), keys(&boxes));
    // An object id that is not label * 1000 + instance, and an object twice in a frame.
    let mut wrong = boxes.clone();
    wrong[1].object += 1;
    let e = dynamic_boxes_from_table(&dynamic_boxes_to_table(&wrong).unwrap()).unwrap_err();
    assert!(
        e.to_string()
            .contains("table `dynamic_boxes` row 1 column `object`"),
        "{e}"
    );
    let mut twice = boxes.clone();
    twice[1].frame = 0;
    let e = dynamic_boxes_from_table(&dynamic_boxes_to_table(&twice).unwrap()).unwrap_err();
    assert!(
        e.to_string()
            .contains("row 1 column `frame`: object 26001 has a box at frame 0 in row 0"),
        "{e}"
    );
    // No moving objects: an empty table with the schema.
    assert_eq!(dynamic_boxes_to_table(&[]).unwrap().num_rows(), 0);
}
