//! The TIF flags shared by `simulate` and `iterate`: a grid file or a Gaussian model.

use anyhow::{bail, Context};
use preston_io::readers::read_tif;
use preston_solver::tif::{GaussianTif, Tif};
use std::path::PathBuf;

/// Where the TIF comes from.
#[derive(Debug, clap::Args)]
pub struct TifArgs {
    /// Gridded TIF CSV `x_mm,y_mm,rate_nm_per_s` (one tool here; several tools in one plan are
    /// for `preston solve`).
    #[arg(long, value_name = "T.csv", conflicts_with = "gaussian_sigma_mm", action = clap::ArgAction::Append)]
    pub tif: Vec<PathBuf>,
    /// Gaussian TIF instead of a file: sigma, mm.
    #[arg(long, requires = "gaussian_peak_nm_per_s")]
    pub gaussian_sigma_mm: Option<f64>,
    /// Gaussian TIF peak removal rate, nm/s.
    #[arg(long, requires = "gaussian_sigma_mm")]
    pub gaussian_peak_nm_per_s: Option<f64>,
    /// Gaussian TIF truncation radius, mm (default 3 sigma).
    #[arg(long, requires = "gaussian_sigma_mm")]
    pub gaussian_truncation_mm: Option<f64>,
}

impl TifArgs {
    /// The Gaussian model the flags give, if they give one (truncation default 3 sigma).
    pub fn gaussian(&self) -> anyhow::Result<Option<GaussianTif>> {
        match (self.gaussian_sigma_mm, self.gaussian_peak_nm_per_s) {
            (Some(sigma), Some(peak)) => Ok(Some(
                GaussianTif::truncated(sigma, peak, self.gaussian_truncation_mm)
                    .context("Gaussian TIF")?,
            )),
            _ => Ok(None),
        }
    }

    /// Whether the flags name a TIF.
    pub fn given(&self) -> bool {
        !self.tif.is_empty() || self.gaussian_sigma_mm.is_some()
    }

    /// The TIF the flags name.
    pub fn load(&self) -> anyhow::Result<Tif> {
        match self.tif.as_slice() {
            [] => {}
            [f] => return Ok(Tif::Grid(read_tif(f)?)),
            _ => bail!("one --tif only here (several tools are for `preston solve`)"),
        }
        match self.gaussian()? {
            Some(g) => Ok(Tif::Gaussian(g)),
            None => bail!(
                "no TIF: give --tif T.csv or --gaussian-sigma-mm and --gaussian-peak-nm-per-s"
            ),
        }
    }
}
