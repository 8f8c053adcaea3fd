//! `preston fit`: fit an XY-polynomial surface to measured points.

use anyhow::Context;
use preston_io::atomic::commit_all;
use preston_io::surface::{read_points, stage_columns_csv, stage_surface, FitSummary};
use preston_solver::fit::{fit_xy_polynomial, ConicBase, FitSettings};
use preston_solver::surface::Surface;
use std::path::PathBuf;

use super::EXIT_NOT_CONVERGED;

/// Arguments of `preston fit`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Points CSV `x_mm,y_mm,z_mm`.
    #[arg(long, value_name = "P.csv")]
    pub points: PathBuf,
    /// Highest total degree m + n of the XY terms (0 to 10).
    #[arg(long, default_value_t = 10)]
    pub order: u32,
    /// Normalisation radius, mm (default: the largest sqrt(x^2 + y^2) of the points).
    #[arg(long)]
    pub norm_radius_mm: Option<f64>,
    /// Vertex curvature of the fixed conic base, 1/mm.
    #[arg(
        long,
        default_value_t = 0.0,
        conflicts_with = "fit_conic",
        allow_negative_numbers = true
    )]
    pub curvature_per_mm: f64,
    /// Conic constant of the fixed conic base.
    #[arg(
        long,
        default_value_t = 0.0,
        conflicts_with = "fit_conic",
        allow_negative_numbers = true
    )]
    pub conic: f64,
    /// Fit the curvature and conic constant too (nonlinear least squares).
    #[arg(long)]
    pub fit_conic: bool,
    /// Write the fitted surface (JSON) here.
    #[arg(long, value_name = "surface.json")]
    pub out: Option<PathBuf>,
    /// Write the fit residual per point here (`x_mm,y_mm,residual_nm`).
    #[arg(long, value_name = "R.csv")]
    pub residuals: Option<PathBuf>,
}

/// Runs `preston fit`: prints the summary JSON (`rms_nm`, `pv_nm`, `terms`, ...) on stdout.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let pts = read_points(&args.points)?;
    let settings = FitSettings {
        order: args.order,
        norm_radius_mm: args.norm_radius_mm.unwrap_or(0.0),
        base: if args.fit_conic {
            ConicBase::Fitted
        } else {
            ConicBase::Fixed {
                curvature_per_mm: args.curvature_per_mm,
                conic: args.conic,
            }
        },
        ..FitSettings::default()
    };
    let fit = fit_xy_polynomial(&pts.x_mm, &pts.y_mm, &pts.z_mm, &settings)
        .with_context(|| format!("fitting {}", args.points.display()))?;
    let mut staged = Vec::new();
    if let Some(out) = &args.out {
        staged.push(stage_surface(
            out,
            &Surface::XyPolynomial(fit.surface.clone()),
        )?);
    }
    if let Some(r) = &args.residuals {
        staged.push(stage_columns_csv(
            r,
            &["x_mm", "y_mm", "residual_nm"],
            &[&pts.x_mm, &pts.y_mm, &fit.residual_nm],
        )?);
    }
    commit_all(staged)?;
    crate::outln!("{}", serde_json::to_string_pretty(&FitSummary::of(&fit))?);
    crate::errln!(
        "preston fit: {} points, order {}, RMS {:.3} nm, PV {:.3} nm, condition {:.3e}",
        fit.points,
        args.order,
        fit.rms_nm,
        fit.pv_nm,
        fit.condition_number
    );
    if args.fit_conic && fit.condition_number > preston_solver::fit::MAX_CONDITION {
        crate::errln!(
            "  warning: condition estimate {:.3e}: the data do not determine the curvature, the \
             conic constant and the polynomial's terms separately (they overlap over this \
             aperture); the surface is fitted, its split into conic and polynomial is not \
             determined separately (fix the conic with --curvature-per-mm and --conic to pin it)",
            fit.condition_number
        );
    }
    if !fit.status.is_converged() {
        crate::errln!(
            "  warning: the conic fit stopped before converging (status {}, {} iterations); \
             outputs hold the last iterate",
            fit.status,
            fit.iterations
        );
        return Ok(EXIT_NOT_CONVERGED);
    }
    Ok(crate::EXIT_OK)
}
