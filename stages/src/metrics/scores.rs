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

const fn figure(name: &'static str, label: &'static str) -> MetricInfo {
    MetricInfo {
        name,
        label,
        unit: "",
        scale: 1.0,
        decimals: 3,
        semantic: true,
    }
}

const fn metres(name: &'static str, label: &'static str) -> MetricInfo {
    MetricInfo {
        name,
        label,
        unit: "m",
        scale: 1.0,
        decimals: 2,
        semantic: false,
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
        MethodInfo {
            name: "exact_depth",
            label: "exact depth",
            depends_on_budget: false,
        },
    ],
    metrics: &[
        pct("miou", "mIoU"),
        pct("acc", "Acc"),
        pct("pq", "PQ"),
        pct("pq_panopticapi", "PQ (panopticapi)"),
        pct("mc", "MC"),
        metres("depth_rmse", "depth RMSE"),
        MetricInfo {
            semantic: false,
            ..pct("depth_delta_1_25", "delta<1.25")
        },
        metres("depth_rmse_interior", "depth RMSE inside regions"),
        metres("depth_rmse_exact", "depth RMSE vs exact depth"),
        MetricInfo {
            semantic: false,
            ..pct("depth_delta_1_25_exact", "delta<1.25 vs exact depth")
        },
        metres(
            "depth_rmse_exact_interior",
            "depth RMSE vs exact depth inside regions",
        ),
        figure("review_auroc", "review AUROC"),
        pct("review_recall_5pct", "review recall@5%"),
        pct("review_top20_precision", "review top-20 region precision"),
        figure("review_frame_rank_corr", "review per-frame rank corr."),
        figure("confidence_auroc", "confidence AUROC"),
        pct("confidence_recall_5pct", "confidence recall@5%"),
        pct("confidence_top20_precision", "confidence top-20 region precision"),
        figure("confidence_frame_rank_corr", "confidence per-frame rank corr."),
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
        "depth_rmse_exact",
        "depth_delta_1_25_exact",
        "depth_rmse_exact_interior",
        "review_auroc",
        "review_recall_5pct",
        "review_top20_precision",
        "review_frame_rank_corr",
    ],
    per_baseline: &[
        "miou",
        "acc",
        "pq",
        "pq_panopticapi",
        "mc",
        "depth_rmse",
        "depth_delta_1_25",
        "depth_rmse_interior",
    ],
    ablation: &[
        "depth_rmse",
        "depth_delta_1_25",
        "depth_rmse_interior",
        "depth_rmse_exact",
        "depth_delta_1_25_exact",
        "depth_rmse_exact_interior",
        "miou",
        "acc",
    ],
    plotted: &["miou", "pq", "depth_rmse", "depth_rmse_exact"],
    notes: &[
        "PQ follows the Panoptic NeRF paper: predicted segments under evaluate's min_segment_px (default 100 px) are relabelled sky and GT segments under it are void before matching",
        "depth RMSE inside regions leaves out the LiDAR pixels on a GT class boundary (a different class among the 8 neighbours), where the LiDAR (mounted apart from the camera) and the pixel, or the foreground and background a pixel straddles, disagree: about a third of the LiDAR pixels but over 90 % of the squared error of the whole-image RMSE on the synthetic street (evaluate's depth_breakdown table)",
        "depth RMSE and delta<1.25 vs exact depth score the rendered depth against the scene's exact depth at every pixel centre within 100 m (synthetic scenes only): the geometry itself. The LiDAR metrics above measure it through a scanner mounted 0.3 m from the camera whose points land anywhere in a pixel's footprint; at 1/8 scale, where a pixel spans 8x8 full-size pixels, a point and the pixel centre often see different surfaces at depth edges, so a sharp, correct depth edge costs more RMSE than a blurred one. Inside regions (vs exact depth) leaves out the pixels on a GT class boundary: a pixel there straddles two surfaces, its colour (an average over its footprint) is matched by a mix of both, and its one exact depth (at the centre) is one of them. The `exact depth` baseline row is the scene's exact depth scored by the LiDAR metrics: the floor they set on a perfect geometry",
        "PQ (panopticapi) scores the same maps against the same GT as panopticapi and the Cityscapes and KITTI-360 scripts do: predicted segments as they are, however small; compare with other papers in the convention they state",
    ],
};

/// Why a scene has no scores: what `metrics.json` and the report say when no image was evaluated.
pub const NOT_EVALUATED: &str = "No image was evaluated: the scene has no evaluation frame with \
     GT labels for the evaluated cameras (KITTI-360 has 2D GT for few sequences; the rendered \
     labels of every frame are in the render stage's export)";
