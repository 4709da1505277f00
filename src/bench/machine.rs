//! What the bench ran on (CPU model and cores from /proc, memory, kernel, tool version) and how
//! much time the runner itself costs: a no-op `pipe run` and `pipe status`, timed by spawning
//! the current executable.

use std::{
    path::Path,
    process::{Command, Stdio},
    time::Instant,
};

/// The machine, as the report prints it.
#[derive(Debug, Clone)]
pub struct Machine {
    pub cpu: String,
    /// Logical CPUs in /proc/cpuinfo.
    pub cores: usize,
    /// CPUs this process may use.
    pub usable: usize,
    pub memory: String,
    pub kernel: String,
    pub tool_version: String,
}

fn read(path: &str) -> String {
    std::fs::read_to_string(path).unwrap_or_default()
}

/// Reads /proc (fields it cannot read say "unknown").
pub fn machine() -> Machine {
    let cpuinfo = read("/proc/cpuinfo");
    let cpu = cpuinfo
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split_once(':'))
        .map_or("unknown".to_string(), |(_, v)| v.trim().to_string());
    let cores = cpuinfo
        .lines()
        .filter(|l| l.starts_with("processor"))
        .count();
    let memory = read("/proc/meminfo")
        .lines()
        .find(|l| l.starts_with("MemTotal:"))
        .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        .map_or("unknown".to_string(), |kb| {
            format!("{:.1} GiB", kb / (1024.0 * 1024.0))
        });
    let kernel = read("/proc/sys/kernel/osrelease").trim().to_string();
    Machine {
        cpu,
        cores,
        usable: std::thread::available_parallelism().map_or(1, |n| n.get()),
        memory,
        kernel: if kernel.is_empty() {
            "unknown".into()
        } else {
            format!("Linux {kernel}")
        },
        tool_version: format!("pipe {}", env!("CARGO_PKG_VERSION")),
    }
}

/// A timed command: median and min of `repeats` runs, seconds.
#[derive(Debug, Clone)]
pub struct Timing {
    pub what: String,
    pub median_s: f64,
    pub min_s: f64,
    /// Whether every run exited 0.
    pub ok: bool,
}

/// Times `pipe ARGS -f FILE` `repeats` times (after one warm-up run).
pub fn time_command(what: &str, args: &[&str], file: &Path, repeats: usize) -> Timing {
    let exe = std::env::current_exe().ok();
    let mut times = Vec::new();
    let mut ok = exe.is_some();
    if let Some(exe) = exe {
        for k in 0..=repeats {
            let t0 = Instant::now();
            let status = Command::new(&exe)
                .args(args)
                .arg("-f")
                .arg(file)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .status();
            let dt = t0.elapsed().as_secs_f64();
            ok &= status.is_ok_and(|s| s.success());
            if k > 0 {
                times.push(dt);
            }
        }
    }
    times.sort_by(f64::total_cmp);
    Timing {
        what: what.to_string(),
        median_s: times.get(times.len() / 2).copied().unwrap_or(f64::NAN),
        min_s: times.first().copied().unwrap_or(f64::NAN),
        ok,
    }
}
