//! XY polynomial freeform: conic base plus `sum_j C_j (x/R)^m (y/R)^n`, `1 <= m + n <= 10`
//! (the "Extended polynomial" surface of optical design programs, with normalisation radius R).

use super::conic::sag_rho;
use super::SagDerivs;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Highest total degree `m + n` of a term.
pub const MAX_ORDER: u32 = 10;

/// One monomial term `coef_mm * (x/R)^m * (y/R)^n`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct XyTerm {
    /// Power of `x / R`.
    pub m: u32,
    /// Power of `y / R`.
    pub n: u32,
    /// Coefficient, mm.
    pub coef_mm: f64,
}

/// `z = c r^2 / (1 + sqrt(1 - (1+k) c^2 r^2)) + sum coef_mm (x/R)^m (y/R)^n`, lengths in mm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct XyPolynomial {
    /// Vertex curvature of the conic base, 1/mm.
    #[serde(default)]
    pub curvature_per_mm: f64,
    /// Conic constant of the base (dimensionless).
    #[serde(default)]
    pub conic: f64,
    /// Normalisation radius `R`, mm.
    pub norm_radius_mm: f64,
    /// The polynomial terms, `1 <= m + n <= 10`, each `(m, n)` at most once.
    #[serde(default)]
    pub terms: Vec<XyTerm>,
}

/// The monomials `(m, n)` of total degree 1..=order, by degree, then by falling `m`
/// (`x, y, x^2, xy, y^2, ...`): `order (order + 3) / 2` of them (65 for order 10).
pub fn monomials(order: u32) -> Vec<(u32, u32)> {
    let mut v = Vec::new();
    for d in 1..=order {
        for m in (0..=d).rev() {
            v.push((m, d - m));
        }
    }
    v
}

/// Powers `t^0 .. t^10`.
#[inline]
pub(crate) fn powers(t: f64) -> [f64; (MAX_ORDER + 1) as usize] {
    let mut p = [1.0; (MAX_ORDER + 1) as usize];
    for k in 1..p.len() {
        p[k] = p[k - 1] * t;
    }
    p
}

impl XyPolynomial {
    /// Checks finite parameters, a positive normalisation radius and valid, distinct terms.
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
        let mut seen = std::collections::HashSet::new();
        for (j, t) in self.terms.iter().enumerate() {
            let d = t.m.saturating_add(t.n);
            if !(1..=MAX_ORDER).contains(&d) {
                return Err(Error::invalid(
                    "terms",
                    format!("term {j} has m + n = {d}; it must be between 1 and {MAX_ORDER}"),
                ));
            }
            if !t.coef_mm.is_finite() {
                return Err(Error::invalid(
                    "terms",
                    format!("term {j} (m={}, n={}) has coef_mm {}", t.m, t.n, t.coef_mm),
                ));
            }
            if !seen.insert((t.m, t.n)) {
                return Err(Error::invalid(
                    "terms",
                    format!("the term m={}, n={} appears more than once", t.m, t.n),
                ));
            }
        }
        Ok(())
    }

    /// Highest `m + n` among the terms (0 when there are none).
    pub fn order(&self) -> u32 {
        self.terms.iter().map(|t| t.m + t.n).max().unwrap_or(0)
    }

    /// Sag and its first and second partial derivatives at `(x, y)`.
    #[inline]
    pub fn derivs(&self, x: f64, y: f64) -> Result<SagDerivs> {
        let rho = x * x + y * y;
        let g = sag_rho(self.curvature_per_mm, self.conic, rho)?;
        let mut d = SagDerivs::from_radial(x, y, g);
        let r = self.norm_radius_mm;
        let px = powers(x / r);
        let py = powers(y / r);
        let (mut z, mut zx, mut zy, mut zxx, mut zxy, mut zyy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for t in &self.terms {
            let (m, n) = (t.m as usize, t.n as usize);
            let (Some(&xm), Some(&yn)) = (px.get(m), py.get(n)) else {
                continue;
            };
            let c = t.coef_mm;
            z += c * xm * yn;
            if m >= 1 {
                let xm1 = px[m - 1];
                zx += c * m as f64 * xm1 * yn;
                if n >= 1 {
                    zxy += c * (m * n) as f64 * xm1 * py[n - 1];
                }
                if m >= 2 {
                    zxx += c * (m * (m - 1)) as f64 * px[m - 2] * yn;
                }
            }
            if n >= 1 {
                zy += c * n as f64 * xm * py[n - 1];
                if n >= 2 {
                    zyy += c * (n * (n - 1)) as f64 * xm * py[n - 2];
                }
            }
        }
        let (ir, ir2) = (1.0 / r, 1.0 / (r * r));
        d.z += z;
        d.zx += zx * ir;
        d.zy += zy * ir;
        d.zxx += zxx * ir2;
        d.zxy += zxy * ir2;
        d.zyy += zyy * ir2;
        Ok(d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn monomial_count_and_order() {
        assert_eq!(monomials(10).len(), 65);
        assert_eq!(monomials(2), vec![(1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]);
    }

    #[test]
    fn derivatives_match_central_differences() {
        let s = XyPolynomial {
            curvature_per_mm: 1.0 / 500.0,
            conic: -1.2,
            norm_radius_mm: 50.0,
            terms: monomials(10)
                .into_iter()
                .enumerate()
                .map(|(j, (m, n))| XyTerm {
                    m,
                    n,
                    coef_mm: 1e-3 * ((j as f64) * 0.7).sin(),
                })
                .collect(),
        };
        s.validate().unwrap();
        let (x, y, h) = (13.0, -21.0, 1e-4);
        let d = s.derivs(x, y).unwrap();
        let f = |x: f64, y: f64| s.derivs(x, y).unwrap();
        let tol = 1e-8;
        assert!(((f(x + h, y).z - f(x - h, y).z) / (2.0 * h) - d.zx).abs() < tol);
        assert!(((f(x, y + h).z - f(x, y - h).z) / (2.0 * h) - d.zy).abs() < tol);
        assert!(((f(x + h, y).zx - f(x - h, y).zx) / (2.0 * h) - d.zxx).abs() < tol);
        assert!(((f(x, y + h).zx - f(x, y - h).zx) / (2.0 * h) - d.zxy).abs() < tol);
        assert!(((f(x, y + h).zy - f(x, y - h).zy) / (2.0 * h) - d.zyy).abs() < tol);
        // A direct evaluation of the sum.
        let mut want = sag_rho(1.0 / 500.0, -1.2, x * x + y * y).unwrap().value;
        for t in &s.terms {
            want += t.coef_mm * (x / 50.0).powi(t.m as i32) * (y / 50.0).powi(t.n as i32);
        }
        assert!((d.z - want).abs() < 1e-14);
    }

    #[test]
    fn invalid_terms_rejected() {
        let mut s = XyPolynomial {
            curvature_per_mm: 0.0,
            conic: 0.0,
            norm_radius_mm: 1.0,
            terms: vec![XyTerm {
                m: 0,
                n: 0,
                coef_mm: 1.0,
            }],
        };
        assert!(s.validate().is_err());
        s.terms = vec![XyTerm {
            m: 6,
            n: 5,
            coef_mm: 1.0,
        }];
        assert!(s.validate().is_err());
        s.terms = vec![
            XyTerm {
                m: 1,
                n: 1,
                coef_mm: 1.0
            };
            2
        ];
        assert!(s.validate().is_err());
        s.terms.pop();
        s.norm_radius_mm = 0.0;
        assert!(s.validate().is_err());
    }
}
