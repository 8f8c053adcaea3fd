//! Conic base sag `z = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2))` (the standard optical conic,
//! e.g. Malacara, *Optical Shop Testing*, ch. 18) and its derivatives with respect to `rho = r^2`.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Value and first two derivatives of a function of `rho = r^2` (mm, 1, 1/mm^...).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RhoDerivs {
    /// The value, mm.
    pub value: f64,
    /// First derivative with respect to `rho`, 1/mm.
    pub d1: f64,
    /// Second derivative with respect to `rho`, 1/mm^3.
    pub d2: f64,
}

impl RhoDerivs {
    /// Sum of two functions of `rho`.
    pub fn plus(self, o: Self) -> Self {
        Self {
            value: self.value + o.value,
            d1: self.d1 + o.d1,
            d2: self.d2 + o.d2,
        }
    }
}

/// A conic of revolution about the z axis: vertex curvature `c` (1/mm, the reciprocal of the
/// vertex radius) and conic constant `k` (0 sphere, -1 paraboloid, < -1 hyperboloid).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Conic {
    /// Vertex curvature `c = 1 / R_vertex`, 1/mm. Positive: concave towards +z.
    pub curvature_per_mm: f64,
    /// Conic constant `k` (dimensionless).
    #[serde(default)]
    pub conic: f64,
}

impl Conic {
    /// Checks that both parameters are finite.
    pub fn validate(&self) -> Result<()> {
        if !self.curvature_per_mm.is_finite() {
            return Err(Error::invalid(
                "curvature_per_mm",
                format!("must be finite, got {}", self.curvature_per_mm),
            ));
        }
        if !self.conic.is_finite() {
            return Err(Error::invalid(
                "conic",
                format!("must be finite, got {}", self.conic),
            ));
        }
        Ok(())
    }

    /// Sag and derivatives in `rho = r^2`: with `s = sqrt(1 - (1+k) c^2 rho)`,
    /// `g = c rho / (1 + s)`, `g' = c / (2 s)`, `g'' = (1+k) c^3 / (4 s^3)`.
    ///
    /// Outside the conic's domain (`1 - (1+k) c^2 rho <= 0`: the surface has turned vertical or
    /// does not exist) this is an [`Error::Geometry`].
    #[inline]
    pub fn sag_rho(&self, rho: f64) -> Result<RhoDerivs> {
        sag_rho(self.curvature_per_mm, self.conic, rho)
    }
}

/// See [`Conic::sag_rho`].
#[inline]
pub fn sag_rho(c: f64, k: f64, rho: f64) -> Result<RhoDerivs> {
    if c == 0.0 {
        return Ok(RhoDerivs::default());
    }
    let arg = 1.0 - (1.0 + k) * c * c * rho;
    if !(arg > 0.0) {
        return Err(Error::Geometry(format!(
            "conic (c = {c} 1/mm, k = {k}) is not defined at r = {} mm: 1 - (1+k) c^2 r^2 = {arg} <= 0",
            rho.max(0.0).sqrt()
        )));
    }
    let s = arg.sqrt();
    Ok(RhoDerivs {
        value: c * rho / (1.0 + s),
        d1: c / (2.0 * s),
        d2: (1.0 + k) * c * c * c / (4.0 * s * s * s),
    })
}

/// Partial derivatives of the conic sag `g(rho; c, k)` with respect to `c` and `k`:
/// `dg/dc = rho / (1+s) + (1+k) c^2 rho^2 / (s (1+s)^2)`, `dg/dk = c^3 rho^2 / (2 s (1+s)^2)`.
pub fn sag_parameter_derivs(c: f64, k: f64, rho: f64) -> Result<(f64, f64)> {
    let arg = 1.0 - (1.0 + k) * c * c * rho;
    if !(arg > 0.0) {
        return Err(Error::Geometry(format!(
            "conic (c = {c} 1/mm, k = {k}) is not defined at r = {} mm",
            rho.max(0.0).sqrt()
        )));
    }
    let s = arg.sqrt();
    let q = 1.0 + s;
    let dc = rho / q + (1.0 + k) * c * c * rho * rho / (s * q * q);
    let dk = c * c * c * rho * rho / (2.0 * s * q * q);
    Ok((dc, dk))
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOL: f64 = 1e-12;

    #[test]
    fn sphere_sag_matches_closed_form() {
        // Sphere of radius 50 mm: z = R - sqrt(R^2 - r^2).
        let r_v = 50.0;
        let c = Conic {
            curvature_per_mm: 1.0 / r_v,
            conic: 0.0,
        };
        for r in [0.0, 1.0, 10.0, 30.0, 49.0] {
            let g = c.sag_rho(r * r).unwrap();
            let exact = r_v - (r_v * r_v - r * r).sqrt();
            assert!((g.value - exact).abs() < TOL * r_v, "r={r}");
            // dz/dr = r / sqrt(R^2 - r^2) = 2 r g'.
            let slope = r / (r_v * r_v - r * r).sqrt();
            assert!((2.0 * r * g.d1 - slope).abs() < TOL * (1.0 + slope));
        }
        assert!(matches!(c.sag_rho(51.0 * 51.0), Err(Error::Geometry(_))));
        assert!(matches!(c.sag_rho(50.0 * 50.0), Err(Error::Geometry(_))));
    }

    #[test]
    fn paraboloid_is_quadratic_and_derivs_match_differences() {
        let g = sag_rho(0.01, -1.0, 1234.0).unwrap();
        assert!((g.value - 0.01 * 1234.0 / 2.0).abs() < TOL);
        let (c, k, rho, h) = (1.0 / 80.0, -0.6, 900.0, 1e-3);
        let f = |r: f64| sag_rho(c, k, r).unwrap();
        let num1 = (f(rho + h).value - f(rho - h).value) / (2.0 * h);
        let num2 = (f(rho + h).d1 - f(rho - h).d1) / (2.0 * h);
        assert!((num1 - f(rho).d1).abs() < 1e-9);
        assert!((num2 - f(rho).d2).abs() < 1e-9);
        let (dc, dk) = sag_parameter_derivs(c, k, rho).unwrap();
        let hc = 1e-7;
        let ndc = (sag_rho(c + hc, k, rho).unwrap().value - sag_rho(c - hc, k, rho).unwrap().value)
            / (2.0 * hc);
        let ndk = (sag_rho(c, k + 1e-5, rho).unwrap().value
            - sag_rho(c, k - 1e-5, rho).unwrap().value)
            / 2e-5;
        assert!((ndc - dc).abs() < 1e-6 * dc.abs());
        assert!((ndk - dk).abs() < 1e-6 * dk.abs());
    }
}
