//! `preston simulate`: the removal a dwell program produces, discrete or continuous motion.

use super::map_input::{print_input_notes, MapInputArgs, PitchArg};
use super::tif_source::TifArgs;
use crate::progress::Bars;
use anyhow::Context;
use preston_io::simulation::{simulate, write_simulation};
use preston_solver::dwell::FeedLimits;
use preston_solver::simulate::Motion;
use std::path::PathBuf;
use std::process::ExitCode;

/// Motion model on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum MotionArg {
    /// The tool dwells at the points (the solver's model).
    Discrete,
    /// The tool sweeps the path at the scheduled feeds.
    Continuous,
}

/// Arguments of `preston simulate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Error map: CSV `x_mm,y_mm,z_nm` or any format of `preston map convert`.
    #[arg(long, value_name = "FILE")]
    pub map: PathBuf,
    #[command(flatten)]
    pub map_input: MapInputArgs,
    #[command(flatten)]
    pub map_pitch: PitchArg,
    #[command(flatten)]
    pub tif: TifArgs,
    /// Dwell program CSV `x_mm,y_mm,dwell_s` in path order (the dwell.csv of `preston solve`).
    #[arg(long, value_name = "dwell.csv")]
    pub dwell: PathBuf,
    /// Motion model.
    #[arg(long, value_enum, default_value = "discrete")]
    pub motion: MotionArg,
    /// Midpoint-rule samples per dwell point for continuous motion.
    #[arg(long, default_value_t = 8)]
    pub samples_per_point: usize,
    /// Fastest feed, mm/min: reports bound violations of the program (optional).
    #[arg(long = "v-max", value_name = "MM_PER_MIN")]
    pub v_max_mm_per_min: Option<f64>,
    /// Write PNG plots (error before, removal, residual) next to the CSVs.
    #[arg(long)]
    pub plots: bool,
    /// Output directory for residual.csv and report.json.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Runs `preston simulate`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let tif = args.tif.load()?;
    let motion = match args.motion {
        MotionArg::Discrete => Motion::Discrete,
        MotionArg::Continuous => Motion::Continuous {
            samples_per_point: args.samples_per_point,
        },
    };
    let limits = args.v_max_mm_per_min.map(|v| FeedLimits {
        v_max_mm_per_min: v,
        v_min_mm_per_min: 0.0,
    });
    let bars = Bars::new();
    let map = args
        .map_input
        .source(args.map.clone(), args.map_pitch.pitch_mm);
    let sim = simulate(&map, &tif, &args.dwell, motion, limits.as_ref(), &bars)?;
    write_simulation(&sim, &args.out, args.plots)
        .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let r = &sim.report;
    if let Some(input) = &r.map_input {
        print_input_notes(input);
    }
    eprintln!(
        "preston simulate ({}): {} map points, {} dwell points; RMS {:.3} -> {:.3} nm, PV {:.3} -> {:.3} nm, total dwell {:.2} s; wrote {}",
        r.solver,
        r.m,
        r.n,
        r.rms_before_nm,
        r.rms_after_nm,
        r.pv_before_nm,
        r.pv_after_nm,
        r.total_dwell_s,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
