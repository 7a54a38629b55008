//! Progress of `moonhaul eval` on stderr, so a run of many minutes says where it is: a bar per
//! run of one case, payload and controller (done of total, ETA), drawn only when stderr is a
//! terminal, and always one plain line per finished run, so a log of the evaluation shows how
//! far it got. Stdout carries only the table or the JSON.

use std::time::Instant;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// The runs of one evaluation, counted so each bar and line says which of them it is.
pub struct Progress {
    runs: usize,
    started: usize,
}

/// One run in progress: its bar, advanced by the simulation (from the batch's threads: a
/// [`ProgressBar`] is a shared handle), and what its closing line says.
pub struct Run {
    bar: ProgressBar,
    label: String,
    count: usize,
    what: &'static str,
    started: Instant,
}

impl Progress {
    /// An evaluation of `runs` runs.
    pub fn new(runs: usize) -> Self {
        Progress { runs, started: 0 }
    }

    /// The next run, `label` (e.g. "box scripted deployed"): `count` `what` (missions,
    /// episodes), its bar `len` long in `bar_unit`s (missions, or the control steps of worlds
    /// that step together).
    pub fn start(
        &mut self,
        label: String,
        count: usize,
        what: &'static str,
        len: u64,
        bar_unit: &str,
    ) -> Run {
        self.started += 1;
        // Drawn only once labelled; `stderr()` hides itself when stderr is not a terminal.
        let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::hidden());
        let template = format!(
            "eval [{{prefix}}] {{msg}} [{{bar:30}}] {{pos}}/{{len}} {bar_unit} \
             ({{elapsed}}, ETA {{eta}})"
        );
        if let Ok(style) = ProgressStyle::with_template(&template) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_prefix(format!("{}/{}", self.started, self.runs));
        bar.set_message(label.clone());
        bar.set_draw_target(ProgressDrawTarget::stderr());
        Run {
            bar,
            label: format!("[{}/{}] {label}", self.started, self.runs),
            count,
            what,
            started: Instant::now(),
        }
    }
}

impl Run {
    pub fn bar(&self) -> &ProgressBar {
        &self.bar
    }

    /// Clears the bar and prints the run's line, e.g. "eval: [3/9] box scripted deployed:
    /// 100 missions in 312 s".
    pub fn finish(self) {
        self.bar.finish_and_clear();
        eprintln!(
            "eval: {}: {} {} in {:.0} s",
            self.label,
            self.count,
            self.what,
            self.started.elapsed().as_secs_f64()
        );
    }
}
