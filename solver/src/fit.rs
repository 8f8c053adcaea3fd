//! Fitting an XY-polynomial surface to measured points `(x, y, z)` (mm).
//!
//! With the conic base fixed the coefficients solve a linear least-squares problem in the
//! normalised monomials `(x/R)^m (y/R)^n`, `1 <= m + n <= order`: the rows are reduced by
//! tall-skinny QR, the columns scaled to unit norm and the small triangular factor solved by SVD
//! (whose singular values give the condition estimate). With the conic fitted too, the curvature
//! `c` and conic constant `k` enter nonlinearly and the whole parameter vector is found by
//! Levenberg-Marquardt (Nocedal & Wright, *Numerical Optimization*, 10.3) on the same machinery.

use crate::error::{Error, Result};
use crate::lstsq::{tsqr, Reduced};
use crate::status::Status;
use crate::surface::conic::{sag_parameter_derivs, sag_rho};
use crate::surface::xyp::{monomials, powers, XyPolynomial, XyTerm, MAX_ORDER};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Largest condition estimate of the column-scaled basis a fixed-base fit accepts: beyond it the
/// points do not determine the terms (too few, collinear, or too small an aperture).
pub const MAX_CONDITION: f64 = 1e13;
/// mm to nm.
const NM_PER_MM: f64 = 1e6;

/// How the conic base of the fitted surface is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "mode", rename_all = "snake_case", deny_unknown_fields)]
pub enum ConicBase {
    /// Held at the given values; the fit is linear.
    Fixed {
        /// Vertex curvature, 1/mm.
        curvature_per_mm: f64,
        /// Conic constant.
        conic: f64,
    },
    /// Fitted with the coefficients (nonlinear least squares). Where the polynomial has
    /// second-order terms, the conic and the polynomial overlap and the condition estimate shows it.
    Fitted,
}

impl Default for ConicBase {
    fn default() -> Self {
        ConicBase::Fixed {
            curvature_per_mm: 0.0,
            conic: 0.0,
        }
    }
}

/// Settings of [`fit_xy_polynomial`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitSettings {
    /// Highest total degree `m + n` of the fitted terms, 0..=10 (0: conic only).
    pub order: u32,
    /// Normalisation radius, mm; 0 chooses the largest `sqrt(x^2 + y^2)` of the points.
    pub norm_radius_mm: f64,
    /// Fixed or fitted conic base.
    pub base: ConicBase,
    /// Levenberg-Marquardt iterations at most (fitted base only).
    pub max_iterations: usize,
}

impl Default for FitSettings {
    fn default() -> Self {
        Self {
            order: MAX_ORDER,
            norm_radius_mm: 0.0,
            base: ConicBase::default(),
            max_iterations: 100,
        }
    }
}

impl FitSettings {
    /// Checks the order, the radius and the base values.
    pub fn validate(&self) -> Result<()> {
        if self.order > MAX_ORDER {
            return Err(Error::invalid(
                "order",
                format!("must be at most {MAX_ORDER}, got {}", self.order),
            ));
        }
        if !(self.norm_radius_mm.is_finite() && self.norm_radius_mm >= 0.0) {
            return Err(Error::invalid(
                "norm_radius_mm",
                format!(
                    "must be positive (or 0 for automatic), got {}",
                    self.norm_radius_mm
                ),
            ));
        }
        if let ConicBase::Fixed {
            curvature_per_mm,
            conic,
        } = self.base
        {
            if !(curvature_per_mm.is_finite() && conic.is_finite()) {
                return Err(Error::invalid(
                    "conic base",
                    format!("curvature_per_mm {curvature_per_mm} and conic {conic} must be finite"),
                ));
            }
        }
        if self.max_iterations == 0 {
            return Err(Error::invalid("max_iterations", "must be at least 1"));
        }
        Ok(())
    }
}

/// The fitted surface and the quality of the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitResult {
    /// The fitted surface (terms in the order of [`monomials`]).
    pub surface: XyPolynomial,
    /// Root mean square of the residual `z - z_fit`, nm.
    pub rms_nm: f64,
    /// Peak to valley of the residual, nm.
    pub pv_nm: f64,
    /// Condition estimate of the column-scaled least-squares matrix (`sigma_max / sigma_min`).
    pub condition_number: f64,
    /// Levenberg-Marquardt iterations (0 for a fixed base).
    pub iterations: usize,
    /// How the Levenberg-Marquardt iteration ended: [`Status::Converged`] when the cost stopped
    /// decreasing (relative change at most 1e-15, or no damped step decreases it: a stationary
    /// point to machine precision), [`Status::MaxIterations`] at the iteration limit; always
    /// converged for a fixed base (a linear least-squares solve).
    pub status: Status,
    /// Number of points fitted.
    pub points: usize,
    /// Residual `z - z_fit` of every point, nm.
    #[serde(skip)]
    pub residual_nm: Vec<f64>,
}

/// Fits `z = conic(x, y) + sum C (x/R)^m (y/R)^n` to the points (mm).
///
/// Errors: unequal lengths, non-finite values, fewer points than parameters, points that do not
/// determine the terms (condition estimate above [`MAX_CONDITION`] for a fixed base), points outside
/// the domain of a fixed conic.
pub fn fit_xy_polynomial(
    x_mm: &[f64],
    y_mm: &[f64],
    z_mm: &[f64],
    settings: &FitSettings,
) -> Result<FitResult> {
    settings.validate()?;
    let n = x_mm.len();
    if y_mm.len() != n || z_mm.len() != n {
        return Err(Error::LengthMismatch {
            what: "fit points",
            got: y_mm.len().min(z_mm.len()),
            expected: n,
        });
    }
    for i in 0..n {
        if !(x_mm[i].is_finite() && y_mm[i].is_finite() && z_mm[i].is_finite()) {
            return Err(Error::NonFinite {
                what: "fit",
                index: i,
                detail: format!("x_mm={}, y_mm={}, z_mm={}", x_mm[i], y_mm[i], z_mm[i]),
            });
        }
    }
    let mono = monomials(settings.order);
    let n_extra = usize::from(matches!(settings.base, ConicBase::Fitted)) * 2;
    if n < mono.len() + n_extra || n == 0 {
        return Err(Error::Geometry(format!(
            "{n} points cannot determine {} parameters (order {})",
            mono.len() + n_extra,
            settings.order
        )));
    }
    let norm = if settings.norm_radius_mm > 0.0 {
        settings.norm_radius_mm
    } else {
        let r = x_mm
            .iter()
            .zip(y_mm)
            .map(|(x, y)| x.hypot(*y))
            .fold(0.0, f64::max);
        if r > 0.0 {
            r
        } else {
            1.0
        }
    };
    let pts = Points {
        x: x_mm,
        y: y_mm,
        z: z_mm,
        mono: &mono,
        norm,
    };
    let (c, k, coefs, condition, iterations, status) = match settings.base {
        ConicBase::Fixed {
            curvature_per_mm,
            conic,
        } => {
            let (coefs, cond) = pts.linear_fit(curvature_per_mm, conic)?;
            if !(cond <= MAX_CONDITION) {
                return Err(Error::Geometry(format!(
                    "the points do not determine the order-{} terms (condition estimate {cond:.3e}); \
                     use a lower order or points that cover the aperture",
                    settings.order
                )));
            }
            (curvature_per_mm, conic, coefs, cond, 0, Status::Converged)
        }
        ConicBase::Fitted => pts.nonlinear_fit(settings.max_iterations)?,
    };
    let surface = XyPolynomial {
        curvature_per_mm: c,
        conic: k,
        norm_radius_mm: norm,
        terms: mono
            .iter()
            .zip(&coefs)
            .map(|(&(m, n), &coef_mm)| XyTerm { m, n, coef_mm })
            .collect(),
    };
    let residual_mm = pts.residuals(c, k, &coefs)?;
    let residual_nm: Vec<f64> = residual_mm.iter().map(|r| r * NM_PER_MM).collect();
    let ss: f64 = residual_nm.iter().map(|r| r * r).sum();
    let (lo, hi) = residual_nm
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &r| {
            (lo.min(r), hi.max(r))
        });
    Ok(FitResult {
        surface,
        rms_nm: (ss / n as f64).sqrt(),
        pv_nm: hi - lo,
        condition_number: condition,
        iterations,
        status,
        points: n,
        residual_nm,
    })
}

/// The data of one fit.
struct Points<'a> {
    x: &'a [f64],
    y: &'a [f64],
    z: &'a [f64],
    mono: &'a [(u32, u32)],
    norm: f64,
}

impl Points<'_> {
    /// Writes the monomials at point `i` into `row[..mono.len()]`.
    #[inline]
    fn basis(&self, i: usize, row: &mut [f64]) {
        let px = powers(self.x[i] / self.norm);
        let py = powers(self.y[i] / self.norm);
        for (slot, &(m, n)) in row.iter_mut().zip(self.mono) {
            *slot = px[m as usize] * py[n as usize];
        }
    }

    fn polynomial(&self, i: usize, coefs: &[f64]) -> f64 {
        let px = powers(self.x[i] / self.norm);
        let py = powers(self.y[i] / self.norm);
        self.mono
            .iter()
            .zip(coefs)
            .map(|(&(m, n), c)| c * px[m as usize] * py[n as usize])
            .sum()
    }

    /// `z - conic - polynomial` for every point (mm).
    fn residuals(&self, c: f64, k: f64, coefs: &[f64]) -> Result<Vec<f64>> {
        (0..self.x.len())
            .into_par_iter()
            .map(|i| {
                let rho = self.x[i] * self.x[i] + self.y[i] * self.y[i];
                Ok(self.z[i] - sag_rho(c, k, rho)?.value - self.polynomial(i, coefs))
            })
            .collect()
    }

    fn cost(&self, c: f64, k: f64, coefs: &[f64]) -> f64 {
        match self.residuals(c, k, coefs) {
            Ok(r) => r.iter().map(|v| v * v).sum(),
            Err(_) => f64::INFINITY,
        }
    }

    /// Coefficients for a fixed conic, and the condition estimate.
    fn linear_fit(&self, c: f64, k: f64) -> Result<(Vec<f64>, f64)> {
        let p = self.mono.len();
        if p == 0 {
            // Conic only: nothing to fit, but the conic must be defined at every point.
            self.residuals(c, k, &[])?;
            return Ok((Vec::new(), 1.0));
        }
        let r = tsqr(self.x.len(), p + 1, |i, row| {
            self.basis(i, row);
            let rho = self.x[i] * self.x[i] + self.y[i] * self.y[i];
            row[p] = self.z[i] - sag_rho(c, k, rho)?.value;
            Ok(())
        })?;
        let red = Reduced::new(&r, p, "xy-polynomial fit")?;
        Ok((red.solve(0.0, 0.0), red.condition()))
    }

    /// A starting conic: `z ~ a + b x + c y + alpha rho + beta rho^2` gives `c0 = 2 alpha` and
    /// `(1 + k0) c0^3 / 8 = beta`; falls back to a paraboloid (defined everywhere) where the
    /// estimate leaves the conic's domain.
    fn initial_conic(&self) -> Result<(f64, f64)> {
        let r = tsqr(self.x.len(), 6, |i, row| {
            let rho = self.x[i] * self.x[i] + self.y[i] * self.y[i];
            let s = self.norm * self.norm;
            row.copy_from_slice(&[
                1.0,
                self.x[i],
                self.y[i],
                rho / s,
                (rho / s) * (rho / s),
                self.z[i],
            ]);
            Ok(())
        })?;
        let red = Reduced::new(&r, 5, "conic start")?;
        let sol = red.solve(0.0, 1e-13);
        let s = self.norm * self.norm;
        let c0 = 2.0 * sol[3] / s;
        let beta = sol[4] / (s * s);
        let mut k0 = if c0.abs() > 1e-12 {
            (8.0 * beta / (c0 * c0 * c0) - 1.0).clamp(-50.0, 50.0)
        } else {
            -1.0
        };
        let rho_max = self
            .x
            .iter()
            .zip(self.y)
            .map(|(x, y)| x * x + y * y)
            .fold(0.0, f64::max);
        if !(1.0 - (1.0 + k0) * c0 * c0 * rho_max > 1e-3) {
            k0 = -1.0;
        }
        Ok((c0, k0))
    }

    /// Levenberg-Marquardt on `[coefs, c, k]`; converged when an accepted step lowers the sum
    /// of squares by at most 1e-15 of it or to the data's round-off, or no step lowers it.
    /// Returns `(c, k, coefs, condition, iterations, status)`.
    fn nonlinear_fit(
        &self,
        max_iterations: usize,
    ) -> Result<(f64, f64, Vec<f64>, f64, usize, Status)> {
        let p = self.mono.len();
        let (mut c, mut k) = self.initial_conic()?;
        let mut coefs = if p > 0 {
            self.linear_fit(c, k)?.0
        } else {
            Vec::new()
        };
        let mut cost = self.cost(c, k, &coefs);
        // A sum of squares at the data's round-off (each residual within 64 ulps of the largest
        // height) is an exact fit: further steps only trade round-off.
        let z_max = self.z.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let round_off = self.x.len() as f64 * (64.0 * f64::EPSILON * z_max).powi(2);
        let mut lambda = 0.0;
        let mut condition = f64::INFINITY;
        let mut iterations = 0;
        let mut status = Status::MaxIterations;
        while iterations < max_iterations {
            iterations += 1;
            let r = tsqr(self.x.len(), p + 3, |i, row| {
                self.basis(i, &mut row[..p]);
                let rho = self.x[i] * self.x[i] + self.y[i] * self.y[i];
                let (dc, dk) = sag_parameter_derivs(c, k, rho)?;
                row[p] = dc;
                row[p + 1] = dk;
                row[p + 2] = self.z[i] - sag_rho(c, k, rho)?.value - self.polynomial(i, &coefs);
                Ok(())
            })?;
            let red = Reduced::new(&r, p + 2, "conic fit")?;
            condition = red.condition();
            let mut accepted = false;
            let mut converged = false;
            for _ in 0..30 {
                let step = red.solve(lambda, 1e-15);
                let nc = c + step[p];
                let nk = k + step[p + 1];
                let ncoefs: Vec<f64> = coefs.iter().zip(&step).map(|(a, d)| a + d).collect();
                let ncost = self.cost(nc, nk, &ncoefs);
                if ncost <= cost {
                    let small = (cost - ncost) <= 1e-15 * cost || ncost <= round_off;
                    c = nc;
                    k = nk;
                    coefs = ncoefs;
                    cost = ncost;
                    lambda *= 0.1;
                    accepted = true;
                    converged = small;
                    break;
                }
                lambda = if lambda == 0.0 { 1e-9 } else { lambda * 10.0 };
            }
            if !accepted || converged {
                status = Status::Converged;
                break;
            }
        }
        Ok((c, k, coefs, condition, iterations, status))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn too_few_and_collinear_points_are_errors() {
        let x = vec![0.0, 1.0, 2.0];
        let s = FitSettings {
            order: 2,
            norm_radius_mm: 1.0,
            ..FitSettings::default()
        };
        assert!(matches!(
            fit_xy_polynomial(&x, &x, &x, &s),
            Err(Error::Geometry(_))
        ));
        // 50 points on the line y = 0: the y terms have no effect.
        let x: Vec<f64> = (0..50).map(|i| i as f64).collect();
        let y = vec![0.0; 50];
        let e = fit_xy_polynomial(&x, &y, &x, &s).unwrap_err();
        assert!(matches!(e, Error::Geometry(_)), "{e}");
        // 50 points on the line y = x: x and y columns equal.
        let e = fit_xy_polynomial(&x, &x, &x, &s).unwrap_err();
        assert!(
            e.to_string().contains("condition") || e.to_string().contains("effect"),
            "{e}"
        );
    }

    #[test]
    fn plane_tilt_is_recovered() {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for i in 0..10 {
            for j in 0..10 {
                x.push(i as f64);
                y.push(j as f64);
            }
        }
        let z: Vec<f64> = x.iter().zip(&y).map(|(a, b)| 0.01 * a - 0.02 * b).collect();
        let s = FitSettings {
            order: 1,
            norm_radius_mm: 10.0,
            ..FitSettings::default()
        };
        let f = fit_xy_polynomial(&x, &y, &z, &s).unwrap();
        assert!((f.surface.terms[0].coef_mm - 0.1).abs() < 1e-14);
        assert!((f.surface.terms[1].coef_mm + 0.2).abs() < 1e-14);
        assert!(f.rms_nm < 1e-6);
    }
}
