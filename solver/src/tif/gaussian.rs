//! Truncated Gaussian TIF: `rate(r) = peak * exp(-r^2 / (2 sigma^2))` for `r <= r_trunc`, else 0.
//!
//! The disc is closed up to rounding: an offset within [`ON_CIRCLE_REL`] of `r_trunc` outside it
//! is on the circle (4.5 nm at a 4.5 mm cut; wider than the phase stencils' rounding of offsets,
//! `2^-25` of a map cell). Lattices and rasters put whole families of map/dwell pairs exactly on the
//! cut circle (a 0.36 mm map and a 0.5 mm raster with a 4.5 mm cut, say), where the rate jumps
//! from `peak exp(-r_trunc^2 / 2 sigma^2)` to zero; without the closure the last bits of
//! `x - X` would decide which of them count, and operators that form the offsets differently
//! (assembled, phase stencils, FFT) would disagree.

use super::InfluenceFunction;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// A rotationally symmetric Gaussian removal footprint, cut to zero beyond a truncation radius.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GaussianTif {
    /// Standard deviation of the footprint, mm.
    pub sigma_mm: f64,
    /// Removal rate at the centre, nm/s.
    pub peak_rate_nm_per_s: f64,
    /// Radius beyond which the rate is zero, mm (3 sigma is customary).
    pub truncation_radius_mm: f64,
}

/// The customary truncation radius, in standard deviations, when none is given.
pub const DEFAULT_TRUNCATION_SIGMAS: f64 = 3.0;

/// An offset within this fraction of the truncation radius outside it is on the cut circle.
pub const ON_CIRCLE_REL: f64 = 1e-6;

impl GaussianTif {
    /// A validated Gaussian TIF: sigma, peak and truncation radius must be positive and finite.
    pub fn new(sigma_mm: f64, peak_rate_nm_per_s: f64, truncation_radius_mm: f64) -> Result<Self> {
        let g = Self {
            sigma_mm,
            peak_rate_nm_per_s,
            truncation_radius_mm,
        };
        g.validate()?;
        Ok(g)
    }

    /// A validated Gaussian TIF cut at `truncation_radius_mm`, or at
    /// [`DEFAULT_TRUNCATION_SIGMAS`] sigma when none is given.
    pub fn truncated(
        sigma_mm: f64,
        peak_rate_nm_per_s: f64,
        truncation_radius_mm: Option<f64>,
    ) -> Result<Self> {
        let cut = truncation_radius_mm.unwrap_or(DEFAULT_TRUNCATION_SIGMAS * sigma_mm);
        Self::new(sigma_mm, peak_rate_nm_per_s, cut)
    }

    /// Checks the parameters (all positive and finite).
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("gaussian sigma_mm", self.sigma_mm),
            ("gaussian peak_rate_nm_per_s", self.peak_rate_nm_per_s),
            ("gaussian truncation_radius_mm", self.truncation_radius_mm),
        ])?;
        Ok(())
    }

    /// Volumetric removal rate, mm^3/s: `2 pi sigma^2 peak (1 - exp(-r_t^2 / 2 sigma^2))`, nm -> mm.
    pub fn volume_rate_mm3_per_s(&self) -> f64 {
        let s2 = self.sigma_mm * self.sigma_mm;
        let cut = 1.0 - (-self.truncation_radius_mm.powi(2) / (2.0 * s2)).exp();
        2.0 * std::f64::consts::PI * s2 * self.peak_rate_nm_per_s * 1e-6 * cut
    }
}

impl InfluenceFunction for GaussianTif {
    #[inline]
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let r2 = dx_mm * dx_mm + dy_mm * dy_mm;
        let cut = self.support_radius_mm();
        if r2 > cut * cut {
            0.0
        } else {
            self.peak_rate_nm_per_s * (-r2 / (2.0 * self.sigma_mm * self.sigma_mm)).exp()
        }
    }

    /// The truncation radius closed up to rounding, `r_trunc (1 + ON_CIRCLE_REL)`.
    #[inline]
    fn support_radius_mm(&self) -> f64 {
        self.truncation_radius_mm * (1.0 + ON_CIRCLE_REL)
    }

    /// The closed truncation disc: the rate jumps from `peak exp(-r_trunc^2 / 2 sigma^2)` to
    /// zero on its circle.
    fn cut_disc_mm(&self) -> Option<(f64, f64, f64)> {
        Some((0.0, 0.0, self.support_radius_mm()))
    }

    /// The truncation radius itself: generated rasters reach exactly `r_trunc` past the map.
    fn nominal_radius_mm(&self) -> f64 {
        self.truncation_radius_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truncation_defaults_to_three_sigma_and_is_validated() {
        let g = GaussianTif::truncated(1.5, 7.0, None).unwrap();
        assert_eq!(g, GaussianTif::new(1.5, 7.0, 4.5).unwrap());
        let g = GaussianTif::truncated(1.5, 7.0, Some(2.0)).unwrap();
        assert_eq!(g.truncation_radius_mm, 2.0);
        assert!(GaussianTif::truncated(0.0, 7.0, None).is_err());
        assert!(GaussianTif::truncated(1.5, 7.0, Some(-1.0)).is_err());
    }

    #[test]
    fn gaussian_values() {
        let g = GaussianTif::new(2.0, 10.0, 6.0).unwrap();
        assert_eq!(g.rate_nm_per_s(0.0, 0.0), 10.0);
        // One sigma away: peak * e^{-1/2}.
        assert!((g.rate_nm_per_s(2.0, 0.0) - 10.0 * (-0.5f64).exp()).abs() < 1e-14);
        assert!((g.rate_nm_per_s(0.0, -2.0) - 10.0 * (-0.5f64).exp()).abs() < 1e-14);
        assert_eq!(g.rate_nm_per_s(6.01, 0.0), 0.0);
        assert!(GaussianTif::new(0.0, 1.0, 1.0).is_err());
        assert!(GaussianTif::new(1.0, -1.0, 1.0).is_err());
    }

    #[test]
    fn the_cut_circle_is_closed_up_to_rounding() {
        let g = GaussianTif::new(1.5, 20.0, 4.5).unwrap();
        let on_cut = 20.0 * (-4.5f64.powi(2) / (2.0 * 1.5 * 1.5)).exp();
        // A map point at 0.36 i and a raster point at -4 + 0.5 k, 4.5 mm apart (a 3-4-5 triangle):
        // the computed offset rounds to just outside the circle.
        let (dx, dy) = (
            0.36 * 5.0 - (-4.0 + 0.5 * 17.0),
            0.36 * 15.0 - (-4.0 + 0.5 * 26.0),
        );
        assert!(
            dx * dx + dy * dy > 4.5 * 4.5,
            "the offset must round outward"
        );
        assert!((g.rate_nm_per_s(dx, dy) / on_cut - 1.0).abs() < 1e-12);
        assert!((g.rate_nm_per_s(0.0, -4.5) / on_cut - 1.0).abs() < 1e-12);
        // Beyond the rounding margin the rate is zero; the raster reach stays the cut itself.
        assert_eq!(g.rate_nm_per_s(4.5 * (1.0 + 1e-5), 0.0), 0.0);
        assert_eq!(g.nominal_radius_mm(), 4.5);
        assert!(g.support_radius_mm() >= 4.5 && g.support_radius_mm() <= 4.5 * (1.0 + 2e-6));
    }
}
