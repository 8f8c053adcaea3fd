//! Progress bars on stderr (only when stderr is a terminal), fed by the engine's observer calls.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use preston_solver::observer::{IterationInfo, Observer, Stage};
use std::io::IsTerminal;
use std::sync::Mutex;

/// An [`Observer`] drawing one indicatif bar per stage.
pub struct Bars {
    bar: Mutex<Option<ProgressBar>>,
    enabled: bool,
}

impl Bars {
    /// Bars that draw only when stderr is a terminal (and `--quiet` is not given).
    pub fn new() -> Self {
        Self {
            bar: Mutex::new(None),
            enabled: std::io::stderr().is_terminal() && !crate::summary_output::quiet(),
        }
    }

    fn with_bar(&self, f: impl FnOnce(&ProgressBar)) {
        if let Ok(guard) = self.bar.lock() {
            if let Some(b) = guard.as_ref() {
                f(b);
            }
        }
    }
}

impl Observer for Bars {
    fn start(&self, stage: Stage, total: u64) {
        if !self.enabled {
            return;
        }
        let (label, template) = match stage {
            Stage::Assembly => (
                "assembling R",
                "{msg:14} [{bar:40}] {pos}/{len} dwell points {elapsed}",
            ),
            Stage::Solve => (
                "solving",
                "{msg:14} {spinner} iteration {pos} {elapsed} {prefix}",
            ),
            Stage::Loop => (
                "iterating",
                "{msg:14} [{bar:40}] {pos}/{len} loops {elapsed}",
            ),
        };
        let bar = if total > 0 {
            ProgressBar::new(total)
        } else {
            ProgressBar::new_spinner()
        };
        bar.set_draw_target(ProgressDrawTarget::stderr());
        if let Ok(style) = ProgressStyle::with_template(template) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_message(label);
        if let Ok(mut g) = self.bar.lock() {
            *g = Some(bar);
        }
    }

    fn advance(&self, _stage: Stage, units: u64) {
        self.with_bar(|b| b.inc(units));
    }

    fn finish(&self, _stage: Stage) {
        if let Ok(mut g) = self.bar.lock() {
            if let Some(b) = g.take() {
                b.finish_and_clear();
            }
        }
    }

    fn iteration(&self, info: &IterationInfo) {
        self.with_bar(|b| {
            b.set_position(info.iteration as u64);
            let kkt = info
                .kkt_residual
                .map(|k| format!(" kkt {k:.3e}"))
                .unwrap_or_default();
            b.set_prefix(format!("objective {:.6e}{kkt}", info.objective));
        });
    }
}
