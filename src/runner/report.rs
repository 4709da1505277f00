//! What a run did: how each stage ended and why ([`RunReport`], also written to
//! `.pipe/runs/last-run.json`), and the plain-text summary and tables the commands print.

use serde::{Deserialize, Serialize};

/// How a stage ended in a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    Cached,
    Ran,
    /// Updated a previous run's entry ([`stages::Stage::update`]).
    Updated,
    Failed,
    Skipped,
    WouldRun,
}

/// One row of the run summary.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageReport {
    pub stage: String,
    pub kind: String,
    pub outcome: Outcome,
    pub reason: String,
    pub key: Option<String>,
    pub wall_s: f64,
    pub cpu_s: f64,
    pub peak_rss_bytes: u64,
    /// Time the runner spent on this stage beyond the stage body (hashing, loading, writing).
    pub overhead_s: f64,
}

/// The result of `pipe run`, also written to `.pipe/runs/last-run.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunReport {
    pub stages: Vec<StageReport>,
    pub wall_s: f64,
    pub failed: bool,
}

impl RunReport {
    /// How many stages ended with `outcome`.
    pub fn count(&self, outcome: Outcome) -> usize {
        self.stages.iter().filter(|r| r.outcome == outcome).count()
    }
}

/// Human-readable bytes.
pub fn fmt_bytes(b: u64) -> String {
    match b {
        0 => "-".into(),
        b if b >= 1 << 30 => format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64),
        b if b >= 1 << 20 => format!("{:.0} MiB", b as f64 / (1u64 << 20) as f64),
        b if b >= 1 << 10 => format!("{:.0} KiB", b as f64 / 1024.0),
        b => format!("{b} B"),
    }
}

/// Seconds as `1.23s` / `45ms`.
pub fn fmt_secs(s: f64) -> String {
    if s == 0.0 {
        "-".into()
    } else if s < 1.0 {
        format!("{:.0}ms", s * 1000.0)
    } else {
        format!("{s:.2}s")
    }
}

/// A plain text table with aligned columns.
pub fn text_table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut width: Vec<usize> = header.iter().map(|h| h.len()).collect();
    for r in rows {
        for (w, c) in width.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let line = |cells: Vec<String>| {
        let n = cells.len();
        cells
            .into_iter()
            .enumerate()
            .map(|(k, c)| {
                if k + 1 == n {
                    c
                } else {
                    format!("{c:<w$}", w = width[k])
                }
            })
            .collect::<Vec<_>>()
            .join("  ")
    };
    let mut out = line(header.iter().map(|s| s.to_string()).collect());
    out.push('\n');
    for r in rows {
        out.push_str(&line(r.clone()));
        out.push('\n');
    }
    out
}

/// The summary printed after a run.
pub fn summary(rep: &RunReport) -> String {
    let rows: Vec<Vec<String>> = rep
        .stages
        .iter()
        .map(|r| {
            vec![
                r.stage.clone(),
                match r.outcome {
                    Outcome::Cached => "cached",
                    Outcome::Ran => "ran",
                    Outcome::Updated => "updated",
                    Outcome::Failed => "FAILED",
                    Outcome::Skipped => "skipped",
                    Outcome::WouldRun => "would run",
                }
                .to_string(),
                fmt_secs(r.wall_s),
                fmt_secs(r.cpu_s),
                fmt_bytes(r.peak_rss_bytes),
                fmt_secs(r.overhead_s),
                first_line(&r.reason),
            ]
        })
        .collect();
    let mut s = text_table(
        &[
            "stage", "result", "wall", "cpu", "peak rss", "runner", "reason",
        ],
        &rows,
    );
    s.push_str(&format!("total {}\n", fmt_secs(rep.wall_s)));
    s
}

/// The first line of a reason, cut to 100 characters.
fn first_line(s: &str) -> String {
    let l = s.lines().next().unwrap_or("");
    if l.chars().count() > 100 {
        format!("{}...", l.chars().take(97).collect::<String>())
    } else {
        l.to_string()
    }
}
