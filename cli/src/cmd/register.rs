//! `preston register`: installation error (ICP) and form error of measured points.

use anyhow::Context;
use preston_io::atomic::commit_all;
use preston_io::surface::{read_points, read_surface, stage_columns_csv, TransformFile};
use preston_io::writers::{stage_json, stage_map_csv};
use preston_solver::registration::{
    register, Dof, LockSource, RegisterSettings, Robust, INSTALLATION_RANGE_DEG,
    INSTALLATION_RANGE_MM,
};
use std::path::PathBuf;

use super::EXIT_NOT_CONVERGED;

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
    /// DOFs held at zero (design frame), e.g. `rz,tx,ty`.
    #[arg(long, value_enum, value_delimiter = ',', value_name = "LIST")]
    pub lock: Vec<Dof>,
    /// Prior bound on each rotation component, arcsec.
    #[arg(long, value_name = "A")]
    pub max_rotation_arcsec: Option<f64>,
    /// Prior bound on each translation component, um.
    #[arg(long, value_name = "T")]
    pub max_translation_um: Option<f64>,
    /// Range of the installation error's translations of the measured points' centroid, mm: a
    /// motion whose standard deviation (from the residual's scatter) exceeds its range is held,
    /// not estimated.
    #[arg(long, value_name = "MM", default_value_t = INSTALLATION_RANGE_MM)]
    pub installation_range_mm: f64,
    /// Range of the installation error's rotations about the measured points' centroid, degrees
    /// (see --installation-range-mm).
    #[arg(long, value_name = "DEG", default_value_t = INSTALLATION_RANGE_DEG)]
    pub installation_range_deg: f64,
    /// Output directory for transform.json, form_error.csv and registered_points.csv.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

/// Runs `preston register`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let surface = read_surface(&args.surface)?;
    let pts = read_points(&args.points)?;
    let mut lock = [false; 6];
    for d in &args.lock {
        lock[(*d).index()] = true;
    }
    let settings = RegisterSettings {
        max_iterations: args.max_iterations,
        robust: match args.robust {
            RobustArg::None => Robust::None,
            RobustArg::Huber => Robust::Huber { k: args.huber_k },
        },
        probe_radius_mm: args.probe_radius_mm,
        lock,
        installation_range_mm: args.installation_range_mm,
        installation_range_deg: args.installation_range_deg,
        max_rotation_arcsec: args.max_rotation_arcsec,
        max_translation_um: args.max_translation_um,
        ..RegisterSettings::default()
    };
    let reg = register(&surface, &pts.points(), &settings)
        .with_context(|| format!("registering {}", args.points.display()))?;
    // Motions the points and the surface leave exactly undetermined are refused unless the
    // user holds them; those the noise leaves undetermined are held with a warning.
    reg.refuse_undetermined("--lock")
        .with_context(|| args.points.display().to_string())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let tf = TransformFile::of(&reg, &settings);
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
    crate::errln!(
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
    let sg = tf.dof_sigma;
    crate::errln!(
        "  sigma [{:.3}, {:.3}, {:.3}] arcsec, [{:.3}, {:.3}, {:.3}] um; information eigenvalues \
         {:.3e} .. {:.3e}, condition number {}",
        sg[0],
        sg[1],
        sg[2],
        sg[3],
        sg[4],
        sg[5],
        tf.information_eigenvalues[0],
        tf.information_eigenvalues[5],
        tf.condition_number
            .map(|c| format!("{c:.3e}"))
            .unwrap_or_else(|| "infinite".into())
    );
    for l in &tf.locked {
        match l.source {
            LockSource::Weak => crate::errln!(
                "  warning: motion {} held: {}; its installation error is not recovered",
                l.label,
                l.reason
            ),
            LockSource::User => crate::errln!("  locked {} at zero", l.label),
            LockSource::Bound => crate::errln!("  {} held at its prior bound", l.label),
        }
    }
    if !reg.status.is_converged() {
        crate::errln!(
            "  warning: stopped before converging (status {}, {} iterations)",
            reg.status,
            reg.iterations
        );
        return Ok(EXIT_NOT_CONVERGED);
    }
    Ok(crate::EXIT_OK)
}
