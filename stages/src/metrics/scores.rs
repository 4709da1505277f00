//! The methods the evaluation scores, and how its `metrics` table reads for tools that do not
//! know the method (`pipe bench` reads [`SCORES`] through the `evaluate` kind).

use crate::stage::{MethodInfo, MetricInfo, ScoreSpec};

/// Methods in the order tables and reports list them.
pub const METHODS: &[&str] = &[
    "panoptic_nerf",
    "fixed_field",
    "pseudo_labels",
    "first_primitive",
];

const fn pct(name: &'static str, label: &'static str) -> MetricInfo {
    MetricInfo {
        name,
        label,
        unit: "%",
        scale: 100.0,
        decimals: 1,
        semantic: true,
    }
}

/// How the `metrics` table reads (for `pipe bench`).
pub const SCORES: ScoreSpec = ScoreSpec {
    table: "metrics",
    method: "panoptic_nerf",
    baselines: &[
        MethodInfo {
            name: "pseudo_labels",
            label: "pseudo labels",
            depends_on_budget: false,
        },
        MethodInfo {
            name: "first_primitive",
            label: "first primitive",
            depends_on_budget: false,
        },
        MethodInfo {
            name: "fixed_field",
            label: "fixed field",
            depends_on_budget: true,
        },
    ],
    metrics: &[
        pct("miou", "mIoU"),
        pct("acc", "Acc"),
        pct("pq", "PQ"),
        pct("pq_panopticapi", "PQ (panopticapi)"),
        pct("mc", "MC"),
        MetricInfo {
            name: "depth_rmse",
            label: "depth RMSE",
            unit: "m",
            scale: 1.0,
            decimals: 2,
            semantic: false,
        },
        MetricInfo {
            semantic: false,
            ..pct("depth_delta_1_25", "delta<1.25")
        },
        MetricInfo {
            name: "depth_rmse_interior",
            label: "depth RMSE inside regions",
            unit: "m",
            scale: 1.0,
            decimals: 2,
            semantic: false,
        },
    ],
    headline: "miou",
    per_run: &[
        "miou",
        "acc",
        "pq",
        "pq_panopticapi",
        "depth_rmse",
        "depth_delta_1_25",
        "depth_rmse_interior",
    ],
    per_baseline: &["miou", "acc", "pq", "pq_panopticapi", "mc"],
    ablation: &[
        "depth_rmse",
        "depth_delta_1_25",
        "depth_rmse_interior",
        "miou",
        "acc",
    ],
    plotted: &["miou", "pq", "depth_rmse"],
    notes: &[
        "PQ follows the Panoptic NeRF paper: predicted segments under evaluate's min_segment_px (default 100 px) are relabelled sky and GT segments under it are void before matching",
        "depth RMSE inside regions leaves out the LiDAR pixels on a GT class boundary (a different class among the 8 neighbours), where the LiDAR (mounted apart from the camera) and the pixel, or the foreground and background a pixel straddles, disagree: about a third of the LiDAR pixels but over 90 % of the squared error of the whole-image RMSE on the synthetic street (evaluate's depth_breakdown table)",
        "PQ (panopticapi) scores the same maps against the same GT as panopticapi and the Cityscapes and KITTI-360 scripts do: predicted segments as they are, however small; compare with other papers in the convention they state",
    ],
};

/// Why a scene has no scores: what `metrics.json` and the report say when no image was evaluated.
pub const NOT_EVALUATED: &str = "No image was evaluated: the scene has no evaluation frame with \
     GT labels for the evaluated cameras (KITTI-360 has 2D GT for few sequences; the rendered \
     labels of every frame are in the render stage's export)";
