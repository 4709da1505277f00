//! Why a primitive or camera is unusable.

use std::fmt;

/// Why a primitive is rejected. Messages name the problem and the offending element.
#[derive(Clone, Debug, PartialEq)]
pub enum GeometryError {
    /// A NaN or infinite number in the named part.
    NonFinite(&'static str),
    /// The transform collapses a local axis (`axis` is 'x', 'y' or 'z'), or its columns are
    /// linearly dependent (`axis` is '?').
    DegenerateTransform {
        axis: char,
    },
    PolygonTooFew {
        n: usize,
    },
    PolygonZeroArea,
    /// Two non-adjacent polygon edges (numbered by their first vertex) cross or touch.
    PolygonSelfIntersecting {
        a: usize,
        b: usize,
    },
    MeshNoFaces,
    MeshIndexOutOfRange {
        face: usize,
        index: u32,
        vertices: usize,
    },
    /// A face repeats a vertex or has zero area.
    MeshDegenerateFace {
        face: usize,
    },
    /// An edge used by a number of faces other than two.
    MeshOpen {
        a: u32,
        b: u32,
        faces: u32,
    },
    /// Two faces traverse an edge in the same direction (a flipped face).
    MeshFlippedFace {
        a: u32,
        b: u32,
    },
    MeshZeroVolume,
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        use GeometryError::*;
        match self {
            NonFinite(what) => write!(f, "non-finite value (NaN or infinity) in {what}"),
            DegenerateTransform { axis: '?' } => write!(
                f,
                "degenerate transform (local axes are linearly dependent: zero volume)"
            ),
            DegenerateTransform { axis } => {
                write!(f, "degenerate transform (zero extent along local {axis})")
            }
            PolygonTooFew { n } => write!(f, "polygon has fewer than 3 vertices (it has {n})"),
            PolygonZeroArea => write!(f, "polygon has zero area"),
            PolygonSelfIntersecting { a, b } => write!(
                f,
                "polygon is self-intersecting: edge {a} crosses edge {b} (edges numbered by their first vertex)"
            ),
            MeshNoFaces => write!(f, "mesh has no faces"),
            MeshIndexOutOfRange { face, index, vertices } => write!(
                f,
                "mesh face {face} refers to vertex {index}, but there are only {vertices} vertices"
            ),
            MeshDegenerateFace { face } => {
                write!(f, "mesh face {face} is degenerate (repeated vertex or zero area)")
            }
            MeshOpen { a, b, faces } => write!(
                f,
                "mesh is not closed: edge ({a},{b}) used by {faces} face{} (every edge needs exactly 2)",
                if *faces == 1 { "" } else { "s" }
            ),
            MeshFlippedFace { a, b } => write!(
                f,
                "mesh has a flipped face: edge ({a},{b}) is traversed in the same direction by both its faces"
            ),
            MeshZeroVolume => write!(f, "mesh encloses zero volume"),
        }
    }
}

impl std::error::Error for GeometryError {}
