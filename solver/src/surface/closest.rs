//! Closest point on a surface `z = f(x, y)` to a point `p`: minimise
//! `F(u, v) = |p - (u, v, f(u, v))|^2 / 2` by Newton's method with safeguards.
//!
//! Gradient `g = (e_x + e_z f_u, e_y + e_z f_v)` with `e = S(u, v) - p`; Hessian
//! `H = J^T J + e_z Hess f` with `J^T J = [[1 + f_u^2, f_u f_v], [f_u f_v, 1 + f_v^2]]` (always
//! positive definite). Safeguards: where `H` is not positive definite (saddles, points far on the
//! concave side) the Gauss-Newton matrix `J^T J` is used instead; every step is backtracked until
//! `F` decreases (Armijo) and the surface is defined at the new foot.

use super::{SagDerivs, Surface};
use crate::error::{Error, Result};

/// Newton iterations before giving up.
const MAX_ITERATIONS: usize = 100;
/// Halvings of a step in the line search.
const MAX_HALVINGS: usize = 60;
/// Converged when the step is below this times `1 + |foot|` (mm).
const STEP_TOL: f64 = 1e-14;

/// The closest surface point to a query point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClosestPoint {
    /// The foot on the surface `(x, y, z)`, mm.
    pub point_mm: [f64; 3],
    /// Unit normal at the foot, towards +z.
    pub normal: [f64; 3],
    /// `n . (p - foot)`, mm: positive when the query point is on the +z (normal) side.
    pub signed_distance_mm: f64,
    /// Newton iterations used.
    pub iterations: usize,
}

fn objective(p: [f64; 3], u: f64, v: f64, d: &SagDerivs) -> f64 {
    let e = [u - p[0], v - p[1], d.z - p[2]];
    0.5 * (e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
}

/// Solves the symmetric 2x2 system `[[a, b], [b, c]] x = r`; `None` if not positive definite.
#[inline]
fn solve_spd2(a: f64, b: f64, c: f64, r: [f64; 2]) -> Option<[f64; 2]> {
    let det = a * c - b * b;
    if !(a > 0.0 && det > 1e-300 * a.abs().max(c.abs()).max(1.0)) {
        return None;
    }
    Some([(c * r[0] - b * r[1]) / det, (a * r[1] - b * r[0]) / det])
}

/// The closest point of `surface` to `p`, Newton started at the foot `start = (u, v)`.
///
/// Errors: the start is outside the surface's domain, or the iteration does not converge.
pub fn closest_point(surface: &Surface, p: [f64; 3], start: [f64; 2]) -> Result<ClosestPoint> {
    if !p.iter().all(|c| c.is_finite()) {
        return Err(Error::Geometry(format!(
            "closest point requested for a non-finite point {p:?}"
        )));
    }
    let (mut u, mut v) = (start[0], start[1]);
    let mut d = match surface.derivs(u, v) {
        Ok(d) => d,
        Err(_) if start != [p[0], p[1]] => {
            u = p[0];
            v = p[1];
            surface.derivs(u, v)?
        }
        Err(e) => return Err(e),
    };
    let mut f = objective(p, u, v, &d);
    for it in 1..=MAX_ITERATIONS {
        let e = [u - p[0], v - p[1], d.z - p[2]];
        let g = [e[0] + e[2] * d.zx, e[1] + e[2] * d.zy];
        let (ga, gb, gc) = (1.0 + d.zx * d.zx, d.zx * d.zy, 1.0 + d.zy * d.zy);
        let newton = solve_spd2(
            ga + e[2] * d.zxx,
            gb + e[2] * d.zxy,
            gc + e[2] * d.zyy,
            [-g[0], -g[1]],
        );
        let step = match newton {
            Some(s) => s,
            None => solve_spd2(ga, gb, gc, [-g[0], -g[1]]).ok_or_else(|| {
                Error::Geometry(format!(
                    "closest point to {p:?}: singular Gauss-Newton matrix"
                ))
            })?,
        };
        let scale = 1.0 + u.abs().max(v.abs());
        let slope = g[0] * step[0] + g[1] * step[1];
        let mut t = 1.0;
        let mut accepted = None;
        for _ in 0..MAX_HALVINGS {
            let (un, vn) = (u + t * step[0], v + t * step[1]);
            if let Ok(dn) = surface.derivs(un, vn) {
                let fn_ = objective(p, un, vn, &dn);
                let small = t * step[0].abs().max(step[1].abs()) <= STEP_TOL * scale * 1e3;
                if fn_ <= f + 1e-4 * t * slope || (small && fn_ <= f * (1.0 + 1e-12) + 1e-30) {
                    accepted = Some((un, vn, dn, fn_));
                    break;
                }
            }
            t *= 0.5;
        }
        let Some((un, vn, dn, fn_)) = accepted else {
            // No decrease possible at working precision: the current foot is the answer.
            return Ok(finish(p, u, v, &d, it));
        };
        let moved = (un - u).abs().max((vn - v).abs());
        u = un;
        v = vn;
        d = dn;
        f = fn_;
        if moved <= STEP_TOL * scale {
            return Ok(finish(p, u, v, &d, it));
        }
    }
    Err(Error::Geometry(format!(
        "closest point to ({}, {}, {}) mm did not converge in {MAX_ITERATIONS} iterations",
        p[0], p[1], p[2]
    )))
}

fn finish(p: [f64; 3], u: f64, v: f64, d: &SagDerivs, iterations: usize) -> ClosestPoint {
    let n = d.normal();
    let sd = n[0] * (p[0] - u) + n[1] * (p[1] - v) + n[2] * (p[2] - d.z);
    ClosestPoint {
        point_mm: [u, v, d.z],
        normal: n,
        signed_distance_mm: sd,
        iterations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::{Conic, XyPolynomial, XyTerm};

    /// Distance tolerance of the closest point, mm.
    const DIST_TOL: f64 = 1e-11;

    #[test]
    fn sphere_closest_point_is_radial() {
        let r = 100.0;
        let s = Surface::Conic(Conic {
            curvature_per_mm: 1.0 / r,
            conic: 0.0,
        });
        let centre = [0.0, 0.0, r];
        for p in [
            [10.0, 20.0, 5.0],
            [60.0, -30.0, -40.0],
            [0.0, 0.0, -3.0],
            [50.0, 50.0, 60.0],
        ] {
            let cp = s.closest_point(p).unwrap();
            let dv = [p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]];
            let len = (dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]).sqrt();
            for k in 0..3 {
                let want = centre[k] + r * dv[k] / len;
                assert!((cp.point_mm[k] - want).abs() < DIST_TOL, "{p:?} {cp:?}");
            }
            // Outside the sphere (len > r) is below the bowl: negative distance.
            assert!((cp.signed_distance_mm - (r - len)).abs() < DIST_TOL);
        }
    }

    #[test]
    fn saddle_closest_point_is_stationary() {
        let s = Surface::XyPolynomial(XyPolynomial {
            curvature_per_mm: 0.0,
            conic: 0.0,
            norm_radius_mm: 10.0,
            terms: vec![
                XyTerm {
                    m: 2,
                    n: 0,
                    coef_mm: 2.0,
                },
                XyTerm {
                    m: 0,
                    n: 2,
                    coef_mm: -2.0,
                },
            ],
        });
        for p in [[0.0, 0.0, 5.0], [1.0, -2.0, -4.0], [7.0, 3.0, 0.5]] {
            let cp = s.closest_point(p).unwrap();
            // p - foot is parallel to the normal.
            let e = [
                p[0] - cp.point_mm[0],
                p[1] - cp.point_mm[1],
                p[2] - cp.point_mm[2],
            ];
            let cross = [
                e[1] * cp.normal[2] - e[2] * cp.normal[1],
                e[2] * cp.normal[0] - e[0] * cp.normal[2],
                e[0] * cp.normal[1] - e[1] * cp.normal[0],
            ];
            assert!(cross.iter().all(|c| c.abs() < 1e-10), "{p:?} {cp:?}");
        }
    }
}
