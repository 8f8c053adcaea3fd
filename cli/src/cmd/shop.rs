//! `preston shop`: a virtual shop to rehearse the loop. It keeps the part's true surface, runs a
//! program with the tool it really has (rate, width, offset, shape and drift off the spot test)
//! and reads the part with an interferometer that adds noise and drops piston and tilt.

use super::shop_tool_args::ShopToolArgs;
use super::tif_source::TifArgs;
use crate::summary_output::{print_json, OutputArgs};
use anyhow::Context;
use preston_io::shop::{visit, write_visit, ShopInputs};
use preston_solver::iterate::shop::Interferometer;
use preston_solver::machine::gcode::motion::Kinematics;
use std::path::PathBuf;

/// Arguments of `preston shop`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The part's true surface before the run, CSV `x_mm,y_mm,z_nm` (the surface_after.csv of
    /// the previous visit).
    #[arg(long, value_name = "FILE")]
    pub surface: PathBuf,
    /// The program to run (without it the shop only measures the part).
    #[arg(long, value_name = "program.nc")]
    pub program: Option<PathBuf>,
    /// The program's dialect (default: the one its header names, else iso).
    #[arg(long, value_enum)]
    pub dialect: Option<preston_solver::machine::gcode::dialect::Dialect>,
    #[command(flatten)]
    pub tif: TifArgs,
    /// The controller's path acceleration, mm/s^2 (default: every block at its feed).
    #[arg(long, value_name = "MM_PER_S2")]
    pub a_max_mm_per_s2: Option<f64>,
    /// Turn angle above which the tool stops, degrees.
    #[arg(long, value_name = "DEG", default_value_t = 60.0)]
    pub corner_angle_deg: f64,
    #[command(flatten)]
    pub tool: ShopToolArgs,
    /// The interferometer's noise per pixel, nm RMS.
    #[arg(long, default_value_t = 0.3)]
    pub noise_rms_nm: f64,
    /// Seed of the noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output directory: surface_after.csv, measured.csv, shop.json.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// Runs `preston shop`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    args.output.apply();
    let inputs = ShopInputs {
        surface: preston_io::metrology::MapSource {
            file: Some(args.surface.clone()),
            ..Default::default()
        },
        program: args.program.clone(),
        dialect: args.dialect,
        tif: args.tif.load()?,
        kinematics: Kinematics::of_limit(args.a_max_mm_per_s2, args.corner_angle_deg)?,
        tool: args.tool.tool()?,
        interferometer: Interferometer {
            noise_rms_nm: args.noise_rms_nm,
        },
        seed: args.seed,
    };
    let v = visit(&inputs)?;
    write_visit(&v, &args.out)
        .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let r = &v.record;
    crate::note!(
        "preston shop: true surface {:.3} -> {:.3} nm RMS (piston and tilt removed), measured {:.3} nm RMS; {:.0} s of program; the tool's footprint: rate {:.4}, width {:.4}, centroid ({:+.4}, {:+.4}) mm; wrote {}",
        r.true_rms_before_nm,
        r.true_rms_after_nm,
        r.measured_rms_nm,
        r.program_time_s,
        r.tool_figures.rate_factor,
        r.tool_figures.width_factor,
        r.tool_figures.offset_x_mm,
        r.tool_figures.offset_y_mm,
        args.out.display()
    );
    if args.output.json {
        print_json(&serde_json::json!({"command": "shop", "out": args.out, "shop": r}))?;
    }
    Ok(crate::EXIT_OK)
}
