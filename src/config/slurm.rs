//! `executor.slurm` of a pipeline file: the resources `pipe run --executor slurm` asks for.

use serde_yaml::Value as Yaml;

use super::{
    error::ConfigError,
    yaml::{yaml_type, Ctx},
};

/// `executor.slurm` of a pipeline file: what `pipe run --executor slurm` asks for per task.
#[derive(Debug, Clone, Default, serde::Deserialize, serde::Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct SlurmConfig {
    /// `--partition`.
    pub partition: Option<String>,
    /// `--cpus-per-task`.
    pub cpus_per_task: Option<u32>,
    /// GPUs per task (`--gres=gpu:N`).
    pub gpus: Option<u32>,
    /// `--mem` (e.g. `16G`).
    pub mem: Option<String>,
    /// `--time` (e.g. `02:00:00`).
    pub time: Option<String>,
    /// At most this many tasks of the array at once (`--array=...%N`).
    pub max_parallel: Option<u32>,
    /// `--job-name` (default `pipe`).
    pub job_name: Option<String>,
    /// More sbatch options, passed as they are (e.g. `--account=proj`, `--qos=normal`).
    pub sbatch_args: Vec<String>,
    /// Shell lines each task runs before `pipe` (e.g. `module load cuda`).
    pub setup: Option<String>,
    /// The `pipe` binary on the compute nodes (default: the coordinator's own binary).
    pub pipe: Option<String>,
    /// Seconds between two looks at the queue (default 5).
    pub poll_s: Option<f64>,
}

/// `executor:` of the file: `slurm:` resources.
pub(super) fn executor_config(cx: &Ctx, v: &Yaml) -> Result<SlurmConfig, ConfigError> {
    let m = match v {
        Yaml::Mapping(m) => m,
        Yaml::Null => return Ok(SlurmConfig::default()),
        other => {
            return Err(cx.err(
                cx.locs.value("executor"),
                None,
                Some("executor"),
                format!(
                    "expected a mapping with `slurm:`, found {}",
                    yaml_type(other)
                ),
            ))
        }
    };
    let mut slurm = SlurmConfig::default();
    for (k, x) in m {
        match k.as_str().unwrap_or("?") {
            "slurm" => {
                slurm = serde_yaml::from_value(x.clone()).map_err(|e| {
                    let msg = e.to_string();
                    let field = msg
                        .strip_prefix("unknown field `")
                        .and_then(|r| r.split('`').next())
                        .map(String::from);
                    let loc = match &field {
                        Some(f) => cx.locs.key(&format!("executor.slurm.{f}")),
                        None => cx.locs.value("executor.slurm"),
                    };
                    cx.err(loc, None, Some("executor.slurm"), msg)
                })?
            }
            other => {
                return Err(cx.err(
                    cx.locs.key(&format!("executor.{other}")),
                    None,
                    Some(other),
                    "unknown key (expected: slurm)",
                ))
            }
        }
    }
    Ok(slurm)
}
