//! `preston register`: installation error (ICP) and form error of measured points.

use anyhow::Context;
use preston_io::atomic::commit_all;
use preston_io::surface::{read_points, read_surface, stage_columns_csv, TransformFile};
use preston_io::writers::{stage_json, stage_map_csv};
use preston_solver::registration::{register, RegisterSettings, Robust};
use std::path::PathBuf;
use std::process::ExitCode;

/// Exit code when the iteration limit was reached before a stopping test (outputs are written).
pub const EXIT_NOT_CONVERGED: u8 = 3;

/// Robust weighting on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum RobustArg {
    /// Plain least squares.
    None,
    /// Huber weights against outliers.
    Huber,
}

/// Arguments of `preston register`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Design surface JSON.
    #[arg(long, value_name = "S.json")]
    pub surface: PathBuf,
    /// Measured points CSV `x_mm,y_mm,z_mm` (probe tip centres with --probe-radius-mm).
    #[arg(long, value_name = "P.csv")]
    pub points: PathBuf,
    /// Radius of the contact probe's tip, mm: the points are tip centres and are compensated.
    #[arg(long, default_value_t = 0.0)]
    pub probe_radius_mm: f64,
    /// Robust weights.
    #[arg(long, value_enum, default_value_t = RobustArg::None)]
    pub robust: RobustArg,
    /// Huber threshold in robust standard deviations.
    #[arg(long, default_value_t = 1.345)]
    pub huber_k: f64,
    /// Gauss-Newton iterations at most.
    #[arg(long, default_value_t = 50)]
    pub max_iterations: usize,
    /// Output directory for transform.json, form_error.csv and registered_points.csv.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Runs `preston register`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let surface = read_surface(&args.surface)?;
    let pts = read_points(&args.points)?;
    let settings = RegisterSettings {
        max_iterations: args.max_iterations,
        robust: match args.robust {
            RobustArg::None => Robust::None,
            RobustArg::Huber => Robust::Huber { k: args.huber_k },
        },
        probe_radius_mm: args.probe_radius_mm,
        ..RegisterSettings::default()
    };
    let reg = register(&surface, &pts.points(), &settings)
        .with_context(|| format!("registering {}", args.points.display()))?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let tf = TransformFile::of(&reg, args.probe_radius_mm);
    let fx: Vec<f64> = reg.design_xy_mm.iter().map(|p| p[0]).collect();
    let fy: Vec<f64> = reg.design_xy_mm.iter().map(|p| p[1]).collect();
    let col = |k: usize| -> Vec<f64> { reg.surface_points_mm.iter().map(|p| p[k]).collect() };
    let (px, py, pz) = (col(0), col(1), col(2));
    commit_all(vec![
        stage_json(&args.out.join("transform.json"), &tf)?,
        stage_map_csv(
            &args.out.join("form_error.csv"),
            &fx,
            &fy,
            &reg.form_error_nm,
        )?,
        stage_columns_csv(
            &args.out.join("registered_points.csv"),
            &["x_mm", "y_mm", "z_mm", "weight"],
            &[&px, &py, &pz, &reg.weights],
        )?,
    ])
    .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let r = tf.rotation_arcsec;
    let t = tf.translation_um;
    eprintln!(
        "preston register: {} points, {} iterations; rotation [{:.3}, {:.3}, {:.3}] arcsec, \
         translation [{:.3}, {:.3}, {:.3}] um, form error RMS {:.3} nm; wrote {}",
        tf.points,
        tf.iterations,
        r[0],
        r[1],
        r[2],
        t[0],
        t[1],
        t[2],
        tf.rms_nm,
        args.out.display()
    );
    if !reg.converged {
        eprintln!(
            "  warning: stopped at the iteration limit ({}) before converging",
            reg.iterations
        );
        return Ok(ExitCode::from(EXIT_NOT_CONVERGED));
    }
    Ok(ExitCode::SUCCESS)
}
