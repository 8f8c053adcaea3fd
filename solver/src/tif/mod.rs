//! Tool influence functions (TIF): the removal rate, nm/s, at an offset from the tool centre.
//!
//! Preston's law gives the local removal rate `dz/dt = K p v` (Preston 1927); a TIF is that rate
//! integrated over the tool's contact patch for a tool held still, sampled or modelled in the
//! tool's frame.

pub mod bonnet;
pub mod gaussian;
pub mod grid;
pub mod hertz;
pub mod model;
pub mod perturbed;
pub mod spot;

pub use bonnet::{BonnetParams, BonnetTif};
pub use gaussian::GaussianTif;
pub use grid::GridTif;
pub use hertz::{HertzParams, HertzTif};
pub use model::{GridAdjustment, HertzPart, ProcessModel, SampledTif, TifModelKind, TifSummary};
pub use perturbed::{Perturbation, PerturbedTif};
pub use spot::SpotSummary;

use serde::{Deserialize, Serialize};

/// Whole lattice steps of `pitch_mm` that hold every integer offset within a support of radius
/// `radius_mm`: `ceil(radius / pitch)`, taken below the rounding margin by which supports are
/// closed ([`gaussian::ON_CIRCLE_REL`]), so closing a support does not widen a lattice kernel.
/// Integer offsets beyond it lie more than `radius_mm` out.
pub(crate) fn lattice_reach(radius_mm: f64, pitch_mm: f64) -> f64 {
    (radius_mm / pitch_mm * (1.0 - 2.0 * gaussian::ON_CIRCLE_REL)).ceil()
}

/// A removal footprint: rate in nm/s at offset `(dx_mm, dy_mm)` from the tool centre.
pub trait InfluenceFunction: Send + Sync {
    /// Removal rate, nm/s, at offset `(dx_mm, dy_mm)` = measurement point minus tool centre.
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64;

    /// Radius, mm, outside which the rate is exactly zero.
    fn support_radius_mm(&self) -> f64;

    /// The tool's nominal radius, mm, by which generated dwell rasters extend past the map: the
    /// half-width of a measured grid, the truncation radius of a model.
    fn nominal_radius_mm(&self) -> f64 {
        self.support_radius_mm()
    }

    /// Where the footprint is cut: the disc outside which the rate is zero, when the rate jumps
    /// to zero on its circle (a truncated Gaussian), `(centre_x_mm, centre_y_mm, radius_mm)`.
    /// `None` for a footprint that falls continuously to zero (the default): integrals of it
    /// along a path need no care at its edge.
    fn cut_disc_mm(&self) -> Option<(f64, f64, f64)> {
        None
    }
}

/// The TIF models a job can name.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Tif {
    /// Sampled on a regular grid, bilinear in between, zero outside.
    Grid(GridTif),
    /// Truncated Gaussian.
    Gaussian(GaussianTif),
}

impl Tif {
    /// The same TIF with its removal rate multiplied by `factor` (positive and finite): a
    /// Gaussian's peak, a grid's every sample.
    pub fn scaled(&self, factor: f64) -> crate::error::Result<Tif> {
        match self {
            Tif::Grid(g) => Ok(Tif::Grid(g.scaled(factor)?)),
            Tif::Gaussian(g) => Ok(Tif::Gaussian(GaussianTif::new(
                g.sigma_mm,
                g.peak_rate_nm_per_s * factor,
                g.truncation_radius_mm,
            )?)),
        }
    }
}

impl InfluenceFunction for Tif {
    #[inline]
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        match self {
            Tif::Grid(g) => g.rate_nm_per_s(dx_mm, dy_mm),
            Tif::Gaussian(g) => g.rate_nm_per_s(dx_mm, dy_mm),
        }
    }

    fn support_radius_mm(&self) -> f64 {
        match self {
            Tif::Grid(g) => g.support_radius_mm(),
            Tif::Gaussian(g) => g.support_radius_mm(),
        }
    }

    fn cut_disc_mm(&self) -> Option<(f64, f64, f64)> {
        match self {
            Tif::Grid(g) => g.cut_disc_mm(),
            Tif::Gaussian(g) => g.cut_disc_mm(),
        }
    }

    fn nominal_radius_mm(&self) -> f64 {
        match self {
            Tif::Grid(g) => g.nominal_radius_mm(),
            Tif::Gaussian(g) => g.nominal_radius_mm(),
        }
    }
}

/// A TIF with every rate multiplied by `factor` (a removal-rate error or a calibration):
/// `rate'(dx, dy) = factor * rate(dx, dy)`, same support.
#[derive(Debug, Clone, Copy)]
pub struct ScaledTif<'a, T: InfluenceFunction + ?Sized> {
    inner: &'a T,
    factor: f64,
}

impl<'a, T: InfluenceFunction + ?Sized> ScaledTif<'a, T> {
    /// `factor * inner`.
    pub fn new(inner: &'a T, factor: f64) -> Self {
        Self { inner, factor }
    }
}

impl<T: InfluenceFunction + ?Sized> InfluenceFunction for ScaledTif<'_, T> {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        self.factor * self.inner.rate_nm_per_s(dx_mm, dy_mm)
    }

    fn support_radius_mm(&self) -> f64 {
        self.inner.support_radius_mm()
    }

    fn cut_disc_mm(&self) -> Option<(f64, f64, f64)> {
        self.inner.cut_disc_mm()
    }

    fn nominal_radius_mm(&self) -> f64 {
        self.inner.nominal_radius_mm()
    }
}
