//! The run's progress output, fed by the stage body through [`stages::Progress`]: on a terminal,
//! one bar per running stage (indicatif) with log lines printed above them; elsewhere (Slurm,
//! nohup, CI, a pipe) plain lines, one per stage every ~10 s or 5 % of its work, saying the
//! step, the rate, the time elapsed and the time left, so a log shows what a long run is doing.

use std::{
    io::IsTerminal,
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

/// `PIPE_PROGRESS=lines` (or `bars`) overrides the choice made from whether stderr is a terminal.
const MODE_VAR: &str = "PIPE_PROGRESS";

/// The progress output of a run, on stderr.
#[derive(Clone)]
pub(super) struct Bars {
    multi: MultiProgress,
    lines: bool,
}

impl Bars {
    pub fn new() -> Bars {
        let lines = match std::env::var(MODE_VAR).as_deref() {
            Ok("lines") => true,
            Ok("bars") => false,
            _ => !std::io::stderr().is_terminal(),
        };
        let target = if lines {
            ProgressDrawTarget::hidden()
        } else {
            ProgressDrawTarget::stderr()
        };
        Bars {
            multi: MultiProgress::with_draw_target(target),
            lines,
        }
    }

    /// Prints a line above the bars.
    pub fn log(&self, msg: &str) {
        self.multi.suspend(|| eprintln!("{msg}"));
    }

    /// The progress of stage `name`: a bar, or its log lines.
    pub fn bar(&self, name: &str) -> StageBar {
        let bar = self.multi.add(ProgressBar::new(1));
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>12.bold} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_prefix(name.to_string());
        let lines = self.lines.then(|| {
            Arc::new(Mutex::new(LineLog::new(
                name,
                Instant::now(),
                Cadence::default(),
            )))
        });
        StageBar { bar, lines }
    }
}

/// One stage's progress output.
#[derive(Clone)]
pub(super) struct StageBar {
    bar: ProgressBar,
    lines: Option<Arc<Mutex<LineLog>>>,
}

impl StageBar {
    /// The stage body ended: clears the bar; in line mode, a last line if earlier ones were
    /// printed (a stage too quick for any line stays silent).
    pub fn finish(&self) {
        self.bar.finish_and_clear();
        if let Some(log) = &self.lines {
            let mut log = log.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(line) = log.finish(Instant::now()) {
                eprintln!("{line}");
            }
        }
    }

    /// What the stage body reports into.
    pub fn adapter(&self) -> ProgressAdapter {
        ProgressAdapter(self.clone())
    }
}

/// A stage body's progress, drawn on its bar or written as lines.
pub(super) struct ProgressAdapter(StageBar);

impl stages::Progress for ProgressAdapter {
    fn update(&self, done: u64, total: u64, message: &str) {
        let bar = &self.0.bar;
        bar.set_length(total.max(1));
        bar.set_position(done);
        bar.set_message(message.to_string());
        if let Some(log) = &self.0.lines {
            let mut log = log.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(line) = log.update(Instant::now(), done, total, message) {
                eprintln!("{line}");
            }
        }
    }
}

/// When line mode prints.
#[derive(Debug, Clone, Copy)]
struct Cadence {
    /// A line at least this often while the stage reports progress.
    every: Duration,
    /// A line each time the work crosses another multiple of this fraction...
    step: f64,
    /// ...but never two lines closer than this.
    min_gap: Duration,
}

impl Default for Cadence {
    fn default() -> Self {
        Cadence {
            every: Duration::from_secs(10),
            step: 0.05,
            min_gap: Duration::from_secs(1),
        }
    }
}

/// The line-mode state of one stage: decides when to print and formats the line.
#[derive(Debug)]
struct LineLog {
    name: String,
    cadence: Cadence,
    start: Instant,
    /// When the last line was printed, and how many `cadence.step`s were done then.
    last: Option<(Instant, u64)>,
    done: u64,
    total: u64,
    message: String,
}

impl LineLog {
    fn new(name: &str, start: Instant, cadence: Cadence) -> LineLog {
        LineLog {
            name: name.to_string(),
            cadence,
            start,
            last: None,
            done: 0,
            total: 0,
            message: String::new(),
        }
    }

    fn steps(&self, done: u64, total: u64) -> u64 {
        if total == 0 {
            return 0;
        }
        let frac = (done as f64 / total as f64).clamp(0.0, 1.0);
        (frac / self.cadence.step + 1e-9).floor() as u64
    }

    /// Records an update; the line to print, if one is due.
    fn update(&mut self, now: Instant, done: u64, total: u64, message: &str) -> Option<String> {
        self.done = done;
        self.total = total;
        if self.message != message {
            self.message = message.to_string();
        }
        let steps = self.steps(done, total);
        let (since, steps_then) = match self.last {
            Some((t, s)) => (now.saturating_duration_since(t), s),
            None => (now.saturating_duration_since(self.start), 0),
        };
        let due =
            since >= self.cadence.every || (steps > steps_then && since >= self.cadence.min_gap);
        // The end of known work is the closing line's to say.
        if !due || (total > 0 && done >= total) {
            return None;
        }
        self.last = Some((now, steps));
        Some(self.line(now))
    }

    /// The closing line, if the stage printed any before.
    fn finish(&mut self, now: Instant) -> Option<String> {
        self.last?;
        self.last = None;
        if self.total > 0 {
            self.done = self.total;
        }
        Some(self.line(now))
    }

    fn line(&self, now: Instant) -> String {
        let elapsed = now.saturating_duration_since(self.start).as_secs_f64();
        let mut s = format!("{:>12}: {}/{}", self.name, self.done, self.total);
        if self.total > 0 {
            s += &format!(" ({:.0}%)", 100.0 * self.done as f64 / self.total as f64);
        }
        if self.total > 0 {
            let rate = if elapsed > 0.0 {
                self.done as f64 / elapsed
            } else {
                0.0
            };
            s += &format!(", {}/s", short_number(rate));
            s += &format!(", elapsed {}", clock(elapsed));
            if self.done >= self.total {
                s += ", done";
            } else if rate > 0.0 {
                let left = (self.total - self.done) as f64 / rate;
                s += &format!(", ETA {}", clock(left));
            }
        } else {
            s += &format!(", elapsed {}", clock(elapsed));
        }
        if !self.message.is_empty() {
            s += &format!(" | {}", self.message);
        }
        s
    }
}

/// `h:mm:ss`, or `m:ss` under an hour.
fn clock(seconds: f64) -> String {
    let t = seconds.max(0.0).round() as u64;
    let (h, m, s) = (t / 3600, t / 60 % 60, t % 60);
    if h > 0 {
        format!("{h}:{m:02}:{s:02}")
    } else {
        format!("{m}:{s:02}")
    }
}

/// Three significant figures, without exponent for everyday rates.
fn short_number(x: f64) -> String {
    if x >= 100.0 {
        format!("{x:.0}")
    } else if x >= 10.0 {
        format!("{x:.1}")
    } else {
        format!("{x:.2}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn log_at(start: Instant) -> LineLog {
        LineLog::new("train", start, Cadence::default())
    }

    fn secs(t0: Instant, s: f64) -> Instant {
        t0 + Duration::from_secs_f64(s)
    }

    #[test]
    fn a_line_per_five_percent_at_most_once_a_second() {
        let t0 = Instant::now();
        let mut log = log_at(t0);
        // 1000 steps at 100 per second: a 5 % step (50 steps) every 0.5 s, so the 1 s gap rules.
        let printed: Vec<u64> = (1..1000)
            .filter_map(|d| {
                log.update(secs(t0, d as f64 / 100.0), d, 1000, "loss 1")
                    .map(|_| d)
            })
            .collect();
        assert_eq!(printed.first(), Some(&100), "{printed:?}");
        for w in printed.windows(2) {
            assert!(w[1] - w[0] >= 100, "lines closer than 1 s: {printed:?}");
            assert!(
                w[1] - w[0] <= 150,
                "a 5 % step passed without a line: {printed:?}"
            );
        }
        assert!(printed.len() >= 9, "{printed:?}");
    }

    #[test]
    fn slow_work_gets_a_line_every_ten_seconds() {
        let t0 = Instant::now();
        let mut log = log_at(t0);
        // 1000 steps at 1 per second: 5 % takes 50 s, so the 10 s clock rules.
        let printed: Vec<u64> = (1..200)
            .filter_map(|d| log.update(secs(t0, d as f64), d, 1000, "").map(|_| d))
            .collect();
        assert_eq!(printed[..4], [10, 20, 30, 40], "{printed:?}");
    }

    #[test]
    fn the_line_names_stage_step_rate_elapsed_and_eta() {
        let t0 = Instant::now();
        let mut log = log_at(t0);
        let line = log.update(secs(t0, 20.0), 250, 1000, "loss 0.42").unwrap();
        assert_eq!(
            line,
            "       train: 250/1000 (25%), 12.5/s, elapsed 0:20, ETA 1:00 | loss 0.42"
        );
        let last = log.finish(secs(t0, 80.0)).unwrap();
        assert_eq!(
            last,
            "       train: 1000/1000 (100%), 12.5/s, elapsed 1:20, done | loss 0.42"
        );
    }

    #[test]
    fn a_quick_stage_prints_nothing() {
        let t0 = Instant::now();
        let mut log = log_at(t0);
        for d in 1..=100 {
            assert_eq!(log.update(secs(t0, d as f64 * 0.005), d, 100, ""), None);
        }
        assert_eq!(log.finish(secs(t0, 0.6)), None);
    }

    #[test]
    fn unknown_totals_and_clock_formats() {
        let t0 = Instant::now();
        let mut log = log_at(t0);
        let line = log.update(secs(t0, 12.0), 0, 0, "waiting").unwrap();
        assert_eq!(line, "       train: 0/0, elapsed 0:12 | waiting");
        assert_eq!(clock(3725.4), "1:02:05");
        assert_eq!(clock(59.6), "1:00");
    }
}
