//! `preston tif spot`: a measured TIF from maps before and after a stationary dwell.

use super::map_input::{print_input_notes, MapInputArgs, PitchArg};
use anyhow::{bail, Context};
use preston_solver::modal::FormTerm;
use preston_solver::tif::spot::{fit_gaussian, tif_from_spot, SpotOptions, SpotSummary};
use std::path::{Path, PathBuf};

/// Fitted model on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum FitArg {
    /// Elliptical Gaussian (Levenberg-Marquardt): sigma_x, sigma_y, peak, centre.
    Gaussian,
}

/// Arguments of `preston tif spot`.
#[derive(Debug, clap::Args)]
pub struct SpotArgs {
    /// Map measured before the spot (any map format; same grid as --after).
    #[arg(long, value_name = "FILE")]
    pub before: PathBuf,
    /// Map measured after the spot.
    #[arg(long, value_name = "FILE")]
    pub after: PathBuf,
    /// Format and units of both maps (their --remove is not used: see --remove below).
    #[command(flatten)]
    pub input: MapInputArgs,
    #[command(flatten)]
    pub pitch: PitchArg,
    /// Dwell time of the spot, s.
    #[arg(long)]
    pub dwell_s: f64,
    /// Radius about the spot that holds the TIF, mm (default 0.4 of the grid's smaller side);
    /// the background is fitted outside it and everything outside it is zero.
    #[arg(long, value_name = "MM")]
    pub crop_radius_mm: Option<f64>,
    /// Move the origin to the rate-weighted centroid.
    #[arg(long)]
    pub recentre: bool,
    /// Fit a model and report its parameters.
    #[arg(long, value_enum)]
    pub fit: Option<FitArg>,
    /// Output TIF CSV `x_mm,y_mm,rate_nm_per_s`.
    #[arg(long, value_name = "TIF.csv")]
    pub out: PathBuf,
}

/// Runs `preston tif spot`.
pub fn run(a: SpotArgs) -> anyhow::Result<u8> {
    let remove = a
        .input
        .remove
        .as_ref()
        .map(|r| r.0.clone())
        .unwrap_or_default();
    if let Some(t) = remove
        .iter()
        .find(|t| !matches!(t, FormTerm::Piston | FormTerm::Tilt))
    {
        bail!(
            "tif spot --remove takes piston and tilt (the background plane), not {}",
            t.name()
        );
    }
    let mut input = a.input.clone();
    input.remove = None;
    let read = |f: &Path| -> anyhow::Result<_> {
        let r = input.source(f.to_path_buf(), a.pitch.pitch_mm).read()?;
        print_input_notes(&r.input);
        Ok(r.map)
    };
    let before = read(&a.before)?;
    let after = read(&a.after)?;
    let spot = tif_from_spot(
        &before,
        &after,
        &SpotOptions {
            dwell_s: a.dwell_s,
            crop_radius_mm: a.crop_radius_mm,
            remove_tilt: remove.contains(&FormTerm::Tilt),
            recentre: a.recentre,
        },
    )
    .with_context(|| format!("spot from {} and {}", a.before.display(), a.after.display()))?;
    let g = &spot.tif;
    let fit = match a.fit {
        Some(FitArg::Gaussian) => Some(fit_gaussian(g)?),
        None => None,
    };
    super::tif::write_grid(&a.out, g)?;
    let summary = SpotSummary::of(&spot, fit.as_ref());
    let (nx, ny) = (summary.nx, summary.ny);
    crate::outln!("{}", serde_json::to_string_pretty(&summary)?);
    crate::errln!(
        "preston tif spot: {nx} x {ny} grid, peak {:.4} nm/s, FWHM {:.4} mm; wrote {}",
        summary.peak_rate_nm_per_s,
        summary.fwhm_mm,
        a.out.display()
    );
    Ok(crate::EXIT_OK)
}
