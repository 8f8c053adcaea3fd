//! Truncated Gaussian TIF: `rate(r) = peak * exp(-r^2 / (2 sigma^2))` for `r <= r_trunc`, else 0.

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
        if r2 > self.truncation_radius_mm * self.truncation_radius_mm {
            0.0
        } else {
            self.peak_rate_nm_per_s * (-r2 / (2.0 * self.sigma_mm * self.sigma_mm)).exp()
        }
    }

    fn support_radius_mm(&self) -> f64 {
        self.truncation_radius_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
