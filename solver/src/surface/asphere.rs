//! Even asphere: conic plus `sum_i A_{2i} (r / R_norm)^{2i}` for `2i = 4, 6, ..., 20` (the
//! ISO 10110-12 even-asphere form, with a normalisation radius so every coefficient is in mm).

use super::conic::{sag_rho, RhoDerivs};
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// The largest number of aspheric coefficients (A4 .. A20).
pub const MAX_ASPHERE_COEFS: usize = 9;

fn one() -> f64 {
    1.0
}

/// `z = c r^2 / (1 + sqrt(1 - (1+k) c^2 r^2)) + sum_{i=0}^{8} coefs_mm[i] (r / R_norm)^(4 + 2 i)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvenAsphere {
    /// Vertex curvature, 1/mm.
    pub curvature_per_mm: f64,
    /// Conic constant (dimensionless).
    #[serde(default)]
    pub conic: f64,
    /// Normalisation radius `R_norm`, mm (1 mm when absent, which makes the coefficients the
    /// classical unnormalised `A4, A6, ...`).
    #[serde(default = "one")]
    pub norm_radius_mm: f64,
    /// `A4, A6, ..., A20` in mm, applied to `(r / R_norm)^4, (r / R_norm)^6, ...`; at most 9.
    #[serde(default)]
    pub coefs_mm: Vec<f64>,
}

impl EvenAsphere {
    /// Checks finiteness, a positive normalisation radius and at most 9 coefficients.
    pub fn validate(&self) -> Result<()> {
        super::conic::Conic {
            curvature_per_mm: self.curvature_per_mm,
            conic: self.conic,
        }
        .validate()?;
        if !(self.norm_radius_mm.is_finite() && self.norm_radius_mm > 0.0) {
            return Err(Error::invalid(
                "norm_radius_mm",
                format!("must be positive, got {}", self.norm_radius_mm),
            ));
        }
        if self.coefs_mm.len() > MAX_ASPHERE_COEFS {
            return Err(Error::invalid(
                "coefs_mm",
                format!(
                    "has {} entries; an even asphere has at most {MAX_ASPHERE_COEFS} (A4..A20)",
                    self.coefs_mm.len()
                ),
            ));
        }
        if let Some((i, a)) = self
            .coefs_mm
            .iter()
            .enumerate()
            .find(|(_, a)| !a.is_finite())
        {
            return Err(Error::invalid(
                "coefs_mm",
                format!("entry {i} (A{}) is {a}", 4 + 2 * i),
            ));
        }
        Ok(())
    }

    /// Sag and `rho`-derivatives: the conic's plus, with `u = rho / R^2`,
    /// `h = sum A_i u^i`, `h' = sum i A_i u^(i-1) / R^2`, `h'' = sum i (i-1) A_i u^(i-2) / R^4`.
    #[inline]
    pub fn sag_rho(&self, rho: f64) -> Result<RhoDerivs> {
        let base = sag_rho(self.curvature_per_mm, self.conic, rho)?;
        let r2 = self.norm_radius_mm * self.norm_radius_mm;
        let u = rho / r2;
        let (mut h, mut h1, mut h2) = (0.0, 0.0, 0.0);
        // Powers u^(i-2) for i = 2..=10 (the exponent of u for coefficient index k is k + 2).
        let mut p = 1.0; // u^(i-2)
        for (kk, &a) in self.coefs_mm.iter().enumerate() {
            let i = (kk + 2) as f64;
            h2 += i * (i - 1.0) * a * p;
            h1 += i * a * p * u;
            h += a * p * u * u;
            p *= u;
        }
        Ok(base.plus(RhoDerivs {
            value: h,
            d1: h1 / r2,
            d2: h2 / (r2 * r2),
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn asphere_terms_and_derivatives() {
        let a = EvenAsphere {
            curvature_per_mm: 1.0 / 200.0,
            conic: -0.5,
            norm_radius_mm: 25.0,
            coefs_mm: vec![1e-3, -2e-4, 5e-5],
        };
        a.validate().unwrap();
        let rho = 20.0f64 * 20.0;
        let u = rho / 625.0;
        let base = sag_rho(1.0 / 200.0, -0.5, rho).unwrap().value;
        let want = base + 1e-3 * u.powi(2) - 2e-4 * u.powi(3) + 5e-5 * u.powi(4);
        let got = a.sag_rho(rho).unwrap();
        assert!((got.value - want).abs() < 1e-14);
        let h = 1e-3;
        let n1 =
            (a.sag_rho(rho + h).unwrap().value - a.sag_rho(rho - h).unwrap().value) / (2.0 * h);
        let n2 = (a.sag_rho(rho + h).unwrap().d1 - a.sag_rho(rho - h).unwrap().d1) / (2.0 * h);
        assert!((n1 - got.d1).abs() < 1e-10);
        assert!((n2 - got.d2).abs() < 1e-10);
        let bad = EvenAsphere {
            coefs_mm: vec![0.0; 10],
            ..a
        };
        assert!(bad.validate().is_err());
    }
}
