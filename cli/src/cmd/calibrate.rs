//! `preston calibrate`: the tool that actually ran, from the maps measured before and after a
//! run and the program that ran.

use super::map_input::MapInputArgs;
use super::tif_source::TifArgs;
use super::EXIT_NOT_CONVERGED;
use crate::summary_output::{print_json, OutputArgs};
use anyhow::Context;
use preston_io::calibration::{run_calibration, write_calibration, CalibrationInputs};
use preston_io::job::Job;
use preston_io::pipeline::load_tif;
use preston_solver::calibrate::{CalibrationSettings, Prior, MAP_SHIFT_MIN_GAIN};
use preston_solver::machine::gcode::motion::Kinematics;
use std::path::PathBuf;

/// Arguments of `preston calibrate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Map measured before the run (CSV `x_mm,y_mm,z_nm` or any format of `preston map
    /// convert`), on a regular grid (dropouts allowed).
    #[arg(long, value_name = "FILE")]
    pub before: PathBuf,
    /// Map measured after the run, any grid: the before map is resampled at its points.
    #[arg(long, value_name = "FILE")]
    pub after: PathBuf,
    #[command(flatten)]
    pub map_input: MapInputArgs,
    /// The G-code program that ran (any dialect; `preston nc` writes them): executed as the
    /// controller ran it, with the acceleration limit.
    #[arg(long, value_name = "program.nc")]
    pub program: PathBuf,
    #[command(flatten)]
    pub tif: TifArgs,
    /// Job file (TOML): its TIF, and its machine's acceleration limit and corner angle, where
    /// the flags give none.
    #[arg(long, value_name = "JOB.toml")]
    pub job: Option<PathBuf>,
    /// The controller's path acceleration, mm/s^2 (trapezoidal look-ahead; default: the job's,
    /// else every block at its programmed feed).
    #[arg(long, value_name = "MM_PER_S2", allow_negative_numbers = true)]
    pub a_max_mm_per_s2: Option<f64>,
    /// Turn angle above which the tool stops, degrees (default: the job's, else 60).
    #[arg(long, value_name = "DEG", allow_negative_numbers = true)]
    pub corner_angle_deg: Option<f64>,
    /// The program's dialect (default: the one its header names, else iso).
    #[arg(long, value_enum)]
    pub dialect: Option<preston_solver::machine::gcode::dialect::Dialect>,
    /// What to fit: `full` (rate, width, offset, shape, drift, a free-form correction where the
    /// data support it), `shape` (no free-form correction) or `basic` (rate, width and offset).
    #[arg(long, value_enum, default_value = "full")]
    pub model: ModelArg,
    /// Fit a power term (x^2 + y^2) besides the piston and tilt each measurement drops.
    #[arg(long)]
    pub fit_power: bool,
    /// Standard deviation of a shift between the two measurements, mm: how well the part and
    /// the interferometer return to the same place (default: half a pixel of the map before the
    /// run). 0: the maps are in one frame (registered to the part), no shift is tried. A shift is
    /// kept only where it lowers the fit's RMS by 5% or more.
    #[arg(long, value_name = "MM")]
    pub map_shift_sigma_mm: Option<f64>,
    /// Pitch of the convolution lattice, mm (default: the TIF's second-moment radius / 10).
    #[arg(long, value_name = "MM")]
    pub lattice_pitch_mm: Option<f64>,
    /// Write figures: measured and simulated removal, their difference, the calibrated TIF.
    #[arg(long)]
    pub plots: bool,
    #[command(flatten)]
    pub figures: super::figure_args::FigureArgs,
    /// Output directory: calibration.json, tif.csv (the calibrated TIF), removal.csv.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// The calibration's model on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum ModelArg {
    /// Rate, width, offset, shape, drift and a free-form correction.
    Full,
    /// Rate, width, offset, shape and drift.
    Shape,
    /// Rate, width, offset and drift.
    Basic,
}

/// Runs `preston calibrate`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    args.output.apply();
    let job = match &args.job {
        Some(path) => Job::load_with_profile(Some(path), None)?,
        None => Job::default(),
    };
    let (tif, tif_file) = match (&args.job, args.tif.given()) {
        (Some(path), false) => (load_tif(&job, path)?, job.tif.file.clone()),
        _ => (args.tif.load()?, args.tif.tif.first().cloned()),
    };
    let kinematics = Kinematics::of_limit(
        args.a_max_mm_per_s2.or(job.machine.a_max_mm_per_s2),
        args.corner_angle_deg
            .unwrap_or_else(|| job.corner_angle_deg()),
    )?;
    let defaults = CalibrationSettings::default();
    let settings = CalibrationSettings {
        fit_shape: !matches!(args.model, ModelArg::Basic),
        freeform: matches!(args.model, ModelArg::Full),
        fit_power: args.fit_power,
        fit_map_shift: args.map_shift_sigma_mm != Some(0.0),
        lattice_pitch_mm: args.lattice_pitch_mm,
        prior: Prior {
            map_shift_sigma_mm: args.map_shift_sigma_mm.filter(|&s| s != 0.0),
            ..defaults.prior
        },
        ..defaults
    };
    let inputs = CalibrationInputs {
        before: args.map_input.source(args.before.clone(), None),
        after: args.map_input.source(args.after.clone(), None),
        program: args.program.clone(),
        dialect: args.dialect,
        tif,
        tif_file,
        kinematics,
        sample_step_mm: None,
        settings,
    };
    let mut calibrated = run_calibration(&inputs)?;
    write_calibration(
        &mut calibrated,
        &args.out,
        args.plots.then(|| args.figures.style()).as_ref(),
    )
    .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let r = &calibrated.record;
    crate::note!(
        "preston calibrate: {} points ({} skipped), measured removal {:.3} nm RMS, fit residual {:.3} nm RMS, noise {:.3} nm RMS per map",
        r.points,
        r.skipped,
        r.measured_change_rms_nm,
        r.fit_rms_nm,
        r.noise_rms_nm
    );
    crate::note!(
        "  rate factor {:.4} +- {:.4}, width factor {:.4} +- {:.4}, offset ({:+.4} +- {:.4}, {:+.4} +- {:.4}) mm, drift {:+.4} +- {:.4} per hour",
        r.rate_factor,
        r.rate_factor_sigma,
        r.width_factor,
        r.width_factor_sigma,
        r.offset_x_mm,
        r.offset_x_mm_sigma,
        r.offset_y_mm,
        r.offset_y_mm_sigma,
        r.drift_per_hour,
        r.drift_per_hour_sigma
    );
    for h in &r.held {
        crate::note!("  {} {}", h.name, h.reason);
    }
    if let Some(m) = &r.map_shift {
        let rms = |v: Option<f64>| v.map_or("failed".to_string(), |v| format!("{v:.3} nm"));
        if m.kept {
            crate::note!(
                "  shift between the maps ({:+.4}, {:+.4}) mm kept: fit {} without it, {} with it",
                r.nuisance.map_shift_x_mm,
                r.nuisance.map_shift_y_mm,
                rms(m.fit_rms_without_nm),
                rms(m.fit_rms_with_nm)
            );
        } else {
            crate::note!(
                "  no shift between the maps: one would change the fit only from {} to {} (kept only where it lowers it by {:.0}% or more)",
                rms(m.fit_rms_without_nm),
                rms(m.fit_rms_with_nm),
                100.0 * MAP_SHIFT_MIN_GAIN
            );
        }
    }
    if let Some(f) = &r.freeform {
        crate::note!(
            "  free-form correction at {:.2} mm resolution ({:.1} effective parameters): fit {:.3} -> {:.3} nm RMS, {}",
            f.node_pitch_mm,
            f.effective_parameters,
            f.fit_rms_before_nm,
            f.fit_rms_after_nm,
            if f.applied { "applied" } else { "not applied (the data do not support it)" }
        );
    }
    crate::note!("  wrote {}", args.out.display());
    if args.output.json {
        print_json(&serde_json::json!({
            "command": "calibrate",
            "out": args.out,
            "calibration": r,
        }))?;
    }
    Ok(if calibrated.calibration.status.is_converged() {
        crate::EXIT_OK
    } else {
        EXIT_NOT_CONVERGED
    })
}
