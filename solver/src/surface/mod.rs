//! Analytic optical surfaces `z = f(x, y)` (mm): plane, conic, even asphere and XY polynomial.
//!
//! Every evaluation returns a `Result`: outside a surface's domain (a conic where
//! `1 - (1+k) c^2 r^2 <= 0`) it is an [`Error::Geometry`], never NaN. The unit normal points to
//! +z (`n = (-f_x, -f_y, 1) / sqrt(1 + f_x^2 + f_y^2)`), so a signed distance is positive where
//! material lies above the surface.

pub mod asphere;
pub mod closest;
pub mod conic;
pub mod xyp;

pub use asphere::EvenAsphere;
pub use closest::ClosestPoint;
pub use conic::Conic;
pub use xyp::{monomials, XyPolynomial, XyTerm, MAX_ORDER};

use crate::error::{Error, Result};
use conic::RhoDerivs;
use serde::{Deserialize, Serialize};

/// Sag `z` (mm) and its first and second partial derivatives at one point.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SagDerivs {
    /// Sag, mm.
    pub z: f64,
    /// `dz/dx` (dimensionless).
    pub zx: f64,
    /// `dz/dy`.
    pub zy: f64,
    /// `d2z/dx2`, 1/mm.
    pub zxx: f64,
    /// `d2z/dxdy`, 1/mm.
    pub zxy: f64,
    /// `d2z/dy2`, 1/mm.
    pub zyy: f64,
}

impl SagDerivs {
    /// Chain rule for a function of `rho = x^2 + y^2`: `z_x = 2 x g'`, `z_xx = 2 g' + 4 x^2 g''`,
    /// `z_xy = 4 x y g''`.
    #[inline]
    pub fn from_radial(x: f64, y: f64, g: RhoDerivs) -> Self {
        Self {
            z: g.value,
            zx: 2.0 * x * g.d1,
            zy: 2.0 * y * g.d1,
            zxx: 2.0 * g.d1 + 4.0 * x * x * g.d2,
            zxy: 4.0 * x * y * g.d2,
            zyy: 2.0 * g.d1 + 4.0 * y * y * g.d2,
        }
    }

    /// Unit normal towards +z: `(-z_x, -z_y, 1) / sqrt(1 + z_x^2 + z_y^2)`.
    #[inline]
    pub fn normal(&self) -> [f64; 3] {
        let w = (1.0 + self.zx * self.zx + self.zy * self.zy).sqrt();
        [-self.zx / w, -self.zy / w, 1.0 / w]
    }

    /// Principal curvatures `(k1, k2)`, 1/mm, `k1 >= k2`, positive where the surface bends
    /// towards its normal (a bowl opening to +z). From the fundamental forms of a graph
    /// (do Carmo, *Differential Geometry of Curves and Surfaces*, 3-3): the eigenvalues of the
    /// shape operator `I^-1 II` with `I = [[1+f_x^2, f_x f_y], [f_x f_y, 1+f_y^2]]` and
    /// `II = Hess f / sqrt(1 + f_x^2 + f_y^2)`.
    pub fn principal_curvatures(&self) -> (f64, f64) {
        // Eigenvalues of the shape operator S = I^-1 II, I = [[E, F], [F, G]],
        // II = [[f_xx, f_xy], [f_xy, f_yy]] / w, as (a + d)/2 +- sqrt(((a - d)/2)^2 + b c):
        // accurate also at umbilic points, where H^2 - K cancels.
        let (e, f, g) = (
            1.0 + self.zx * self.zx,
            self.zx * self.zy,
            1.0 + self.zy * self.zy,
        );
        let w = (1.0 + self.zx * self.zx + self.zy * self.zy).sqrt();
        let (l, m, n) = (self.zxx / w, self.zxy / w, self.zyy / w);
        let det = e * g - f * f;
        let a = (g * l - f * m) / det;
        let b = (g * m - f * n) / det;
        let c = (e * m - f * l) / det;
        let d = (e * n - f * m) / det;
        let half = 0.5 * (a - d);
        let disc = (half * half + b * c).max(0.0).sqrt();
        let mean = 0.5 * (a + d);
        (mean + disc, mean - disc)
    }
}

/// The plane `z = 0`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Plane {}

/// A design surface. JSON: `{"type": "plane" | "conic" | "even_asphere" | "xy_polynomial", ...}`
/// with the fields of the variant (lengths in mm).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Surface {
    /// `z = 0`.
    Plane(Plane),
    /// Conic of revolution.
    Conic(Conic),
    /// Conic plus even powers of `r`.
    EvenAsphere(EvenAsphere),
    /// Conic plus XY monomials.
    XyPolynomial(XyPolynomial),
}

impl Surface {
    /// Checks the parameters of the variant.
    pub fn validate(&self) -> Result<()> {
        match self {
            Surface::Plane(_) => Ok(()),
            Surface::Conic(c) => c.validate(),
            Surface::EvenAsphere(a) => a.validate(),
            Surface::XyPolynomial(p) => p.validate(),
        }
    }

    /// Sag and first and second derivatives at `(x_mm, y_mm)`; an [`Error::Geometry`] outside the
    /// surface's domain or for non-finite input.
    #[inline]
    pub fn derivs(&self, x_mm: f64, y_mm: f64) -> Result<SagDerivs> {
        if !(x_mm.is_finite() && y_mm.is_finite()) {
            return Err(Error::Geometry(format!(
                "surface evaluated at a non-finite point ({x_mm}, {y_mm}) mm"
            )));
        }
        match self {
            Surface::Plane(_) => Ok(SagDerivs::default()),
            Surface::Conic(c) => Ok(SagDerivs::from_radial(
                x_mm,
                y_mm,
                c.sag_rho(x_mm * x_mm + y_mm * y_mm)?,
            )),
            Surface::EvenAsphere(a) => Ok(SagDerivs::from_radial(
                x_mm,
                y_mm,
                a.sag_rho(x_mm * x_mm + y_mm * y_mm)?,
            )),
            Surface::XyPolynomial(p) => p.derivs(x_mm, y_mm),
        }
    }

    /// Sag `z(x, y)`, mm.
    pub fn sag_mm(&self, x_mm: f64, y_mm: f64) -> Result<f64> {
        Ok(self.derivs(x_mm, y_mm)?.z)
    }

    /// Gradient `(dz/dx, dz/dy)`.
    pub fn gradient(&self, x_mm: f64, y_mm: f64) -> Result<[f64; 2]> {
        let d = self.derivs(x_mm, y_mm)?;
        Ok([d.zx, d.zy])
    }

    /// Unit normal towards +z, see [`SagDerivs::normal`].
    pub fn normal(&self, x_mm: f64, y_mm: f64) -> Result<[f64; 3]> {
        Ok(self.derivs(x_mm, y_mm)?.normal())
    }

    /// Principal curvatures `(k1, k2)`, 1/mm, see [`SagDerivs::principal_curvatures`].
    pub fn principal_curvatures_per_mm(&self, x_mm: f64, y_mm: f64) -> Result<(f64, f64)> {
        Ok(self.derivs(x_mm, y_mm)?.principal_curvatures())
    }

    /// The point of the surface closest to `p` (mm), found by safeguarded Newton iteration
    /// started below `p`; see [`closest::closest_point`].
    pub fn closest_point(&self, p: [f64; 3]) -> Result<ClosestPoint> {
        closest::closest_point(self, p, [p[0], p[1]])
    }

    /// As [`Surface::closest_point`], started from the foot `(x, y)` of a nearby earlier answer.
    pub fn closest_point_from(&self, p: [f64; 3], start_xy_mm: [f64; 2]) -> Result<ClosestPoint> {
        closest::closest_point(self, p, start_xy_mm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_round_trip_and_interface_names() {
        let text = r#"{"type":"xy_polynomial","curvature_per_mm":0.001,"conic":-1,"norm_radius_mm":100,
            "terms":[{"m":1,"n":0,"coef_mm":0.5},{"m":2,"n":1,"coef_mm":-0.25}]}"#;
        let s: Surface = serde_json::from_str(text).unwrap();
        s.validate().unwrap();
        let z = s.sag_mm(10.0, 20.0).unwrap();
        let conic = 0.001 * 500.0 / (1.0 + (1.0f64 - 0.0).sqrt());
        let want = conic + 0.5 * 0.1 - 0.25 * 0.01 * 0.2;
        assert!((z - want).abs() < 1e-15);
        let back: Surface = serde_json::from_str(&serde_json::to_string(&s).unwrap()).unwrap();
        assert_eq!(back, s);
        let plane: Surface = serde_json::from_str(r#"{"type":"plane"}"#).unwrap();
        assert_eq!(plane.sag_mm(3.0, 4.0).unwrap(), 0.0);
        let c: Surface =
            serde_json::from_str(r#"{"type":"conic","curvature_per_mm":0.02,"conic":0}"#).unwrap();
        assert!(matches!(c.sag_mm(60.0, 0.0), Err(Error::Geometry(_))));
        assert!(serde_json::from_str::<Surface>(
            r#"{"type":"conic","curvature_per_mm":0.02,"k":0}"#
        )
        .is_err());
        let a: Surface = serde_json::from_str(
            r#"{"type":"even_asphere","curvature_per_mm":0.01,"conic":-0.5,"coefs_mm":[1e-7]}"#,
        )
        .unwrap();
        assert!(a.sag_mm(5.0, 0.0).unwrap() > 0.0);
    }

    #[test]
    fn sphere_curvatures_and_normal() {
        // Sphere of radius 80 mm: both principal curvatures 1/80 everywhere; normal towards centre.
        let r = 80.0;
        let s = Surface::Conic(Conic {
            curvature_per_mm: 1.0 / r,
            conic: 0.0,
        });
        for (x, y) in [(0.0, 0.0), (30.0, -20.0), (-50.0, 55.0)] {
            let (k1, k2) = s.principal_curvatures_per_mm(x, y).unwrap();
            assert!(
                (k1 - 1.0 / r).abs() < 1e-14 && (k2 - 1.0 / r).abs() < 1e-14,
                "{k1} {k2}"
            );
            let n = s.normal(x, y).unwrap();
            let z = s.sag_mm(x, y).unwrap();
            // Centre of the sphere is (0, 0, r): normal = (centre - p) / r.
            let want = [-x / r, -y / r, (r - z) / r];
            for k in 0..3 {
                assert!((n[k] - want[k]).abs() < 1e-14);
            }
        }
        // Saddle z = (x^2 - y^2) / (2 R) at the origin: curvatures +1/R and -1/R.
        let saddle = Surface::XyPolynomial(XyPolynomial {
            curvature_per_mm: 0.0,
            conic: 0.0,
            norm_radius_mm: 10.0,
            terms: vec![
                XyTerm {
                    m: 2,
                    n: 0,
                    coef_mm: 100.0 / 200.0,
                },
                XyTerm {
                    m: 0,
                    n: 2,
                    coef_mm: -100.0 / 200.0,
                },
            ],
        });
        let (k1, k2) = saddle.principal_curvatures_per_mm(0.0, 0.0).unwrap();
        assert!((k1 - 0.01).abs() < 1e-15 && (k2 + 0.01).abs() < 1e-15);
    }
}
