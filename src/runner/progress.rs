//! The run's terminal output: one progress bar per running stage (indicatif), fed by the
//! stage body through [`stages::Progress`], and log lines printed above the bars.

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};

/// The bars of a run, on stderr.
#[derive(Clone)]
pub(super) struct Bars(MultiProgress);

impl Bars {
    pub fn new() -> Bars {
        Bars(MultiProgress::with_draw_target(ProgressDrawTarget::stderr()))
    }

    /// Prints a line above the bars.
    pub fn log(&self, msg: &str) {
        self.0.suspend(|| eprintln!("{msg}"));
    }

    /// A new bar for stage `name`.
    pub fn bar(&self, name: &str) -> ProgressBar {
        let bar = self.0.add(ProgressBar::new(1));
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>12.bold} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_prefix(name.to_string());
        bar
    }
}

/// A stage body's progress, drawn on its bar.
pub(super) struct ProgressAdapter(pub ProgressBar);

impl stages::Progress for ProgressAdapter {
    fn update(&self, done: u64, total: u64, message: &str) {
        self.0.set_length(total.max(1));
        self.0.set_position(done);
        self.0.set_message(message.to_string());
    }
}
