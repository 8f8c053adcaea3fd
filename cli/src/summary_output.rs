//! Output conventions of the subcommands that print a summary (`solve`, `simulate`, `nc`):
//! `--quiet` keeps stderr to warnings and errors, `--json` prints the summary as exactly one JSON
//! object on stdout.

use preston_solver::setup::IntegrationResolution;
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};

static QUIET: AtomicBool = AtomicBool::new(false);

/// `--quiet` and `--json`.
#[derive(Debug, Clone, Copy, Default, clap::Args)]
pub struct OutputArgs {
    /// Print no summary, notes or progress on stderr (warnings and errors still are).
    #[arg(long)]
    pub quiet: bool,
    /// Print the summary as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

impl OutputArgs {
    /// Makes the flags take effect for this run.
    pub fn apply(&self) {
        QUIET.store(self.quiet, Ordering::Relaxed);
    }
}

/// Whether `--quiet` was given.
pub fn quiet() -> bool {
    QUIET.load(Ordering::Relaxed)
}

/// `eprintln!` unless `--quiet` was given: summaries and notes (warnings use `eprintln!`).
#[macro_export]
macro_rules! note {
    ($($t:tt)*) => {
        if !$crate::summary_output::quiet() {
            $crate::errln!($($t)*);
        }
    };
}

/// Prints `value` as one line of JSON on stdout (a closed pipe is the caller's
/// `std::io::ErrorKind::BrokenPipe`, not an error of the run).
pub fn print_json(value: &serde_json::Value) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    serde_json::to_writer(&mut out, value)?;
    out.write_all(b"\n")?;
    out.flush()?;
    Ok(())
}

/// A residual figure, nm: below 0.1 nm to the decimals the executed residual's integration
/// resolves ([`IntegrationResolution::decimals`]), else (or without an executed run) to three.
pub fn figure_nm(v: f64, resolution: Option<&IntegrationResolution>) -> String {
    match resolution {
        Some(r) if v.abs() < 0.1 => format!("{v:.*}", r.decimals()),
        _ => format!("{v:.3}"),
    }
}

/// What an integration resolution says, after "the" or "the executed": the sample step and how
/// far the residual moves at half of it.
pub fn resolution_phrase(i: &IntegrationResolution) -> String {
    format!(
        "removal integrated in samples of at most {:.4} mm ({} samples): at half that step the residual moves by {:.4} nm RMS, {:.4} nm PV",
        i.sample_step_mm, i.samples, i.rms_change_nm, i.pv_change_nm
    )
}
