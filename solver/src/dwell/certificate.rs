//! Optimality certificates: a proven bound on `f(t) - min f` at any feasible dwell vector, and
//! the vocabulary saying which test a converged solve met.
//!
//! **Gap bound** (Lagrangian duality). With `r = P(R t - z)` the piston-free residual at `t`,
//! `0.5 ||a||^2 >= a'y - 0.5 ||y||^2` for every `y`; taking `y = alpha r` (and `alpha D t` for
//! the smoothing term) every feasible `s` has
//! `f(s) >= d(alpha) = -alpha z'r - 0.5 alpha^2 (||r||^2 + lambda ||D t||^2) +
//! sum_j min_{l_j <= s_j <= U_j} c_j s_j`, `c = alpha (R^T r + lambda D^T D t) + rho`
//! (Boyd & Vandenberghe, *Convex Optimization*, 2004, sections 5.1-5.2). `U_j` is the dwell upper
//! bound `u_j` (from `v_min`) or, when `rho > 0`, the level-set bound `l_j + (f(t) - rho 1'l) /
//! rho` (every minimiser has `rho 1't* <= f(t*) <= f(t)`). `d` is maximised over a few `alpha`
//! in `(0, 1]`; `alpha = 1` is the Frank-Wolfe gap.
//!
//! **When there is none.** With `rho = 0` and no upper bound on some dwell point whose gradient
//! entry is negative, `d(alpha) = -inf` for every `alpha > 0`: only the trivial `f* >= rho 1'l`
//! remains, which is no certificate at all (with `rho = 0` it is `f* >= 0`, a "gap" equal to the
//! objective). The minimiser set may then be unbounded (a uniform layer of dwell is piston), so
//! no bound on the total dwell follows from the problem data either; the gap is reported as
//! absent with [`GapBoundReason::UnboundedDwellWithoutTimeWeight`], and the KKT residual is the
//! stopping test.

use super::with_operator;
use super::{DwellBounds, Problem};
use crate::error::{Error, Result};
use crate::influence::operator::{fixed_sum, LinearOperator};
use serde::{Deserialize, Serialize};
use std::fmt;

/// Why a solve reports no objective gap bound.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GapBoundReason {
    /// `rho = 0` and some dwell point has no upper bound (no `v_min`) where the gradient is
    /// negative: the dual function is `-inf` for every multiplier but zero.
    UnboundedDwellWithoutTimeWeight,
    /// The dual bound did not come out finite (overflowing data).
    NonFinite,
    /// The acceleration limit makes the problem non-convex in the dwell times: no Lagrangian
    /// dual bound applies.
    NonConvexAccelerationLimit,
}

impl fmt::Display for GapBoundReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            GapBoundReason::UnboundedDwellWithoutTimeWeight => {
                "rho = 0 and no dwell upper bound (v_min): no finite dual bound beyond f* >= 0; \
                 the KKT residual is the optimality test"
            }
            GapBoundReason::NonFinite => "the dual bound is not finite (overflow in the data)",
            GapBoundReason::NonConvexAccelerationLimit => {
                "the acceleration limit is not convex in the dwell times: no dual bound; the KKT \
                 residual of the limited problem is the stationarity test"
            }
        })
    }
}

/// Which test a converged solve met.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ConvergenceCriterion {
    /// The relative objective gap bound fell below the tolerance.
    ObjectiveGap,
    /// The relative KKT (projected-gradient) residual fell below the tolerance.
    KktResidual,
    /// The interior-point solver's own primal, dual and gap tolerances (Clarabel).
    InteriorPoint,
}

impl fmt::Display for ConvergenceCriterion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ConvergenceCriterion::ObjectiveGap => "objective gap bound",
            ConvergenceCriterion::KktResidual => "KKT residual",
            ConvergenceCriterion::InteriorPoint => "interior-point tolerances",
        })
    }
}

/// A proven bound on `f(t) - min f`, or why there is none.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GapBound {
    /// `f(t) - min f <= value`, nm^2.
    Bound(f64),
    /// No finite bound exists for this problem at this point.
    Unavailable(GapBoundReason),
}

impl GapBound {
    /// The bound, when there is one.
    pub fn value(self) -> Option<f64> {
        match self {
            GapBound::Bound(g) => Some(g),
            GapBound::Unavailable(_) => None,
        }
    }

    /// Why there is no bound, when there is none.
    pub fn reason(self) -> Option<GapBoundReason> {
        match self {
            GapBound::Bound(_) => None,
            GapBound::Unavailable(r) => Some(r),
        }
    }
}

/// The quantities at a feasible point `t` that the dual bound needs.
pub(crate) struct DualInputs<'a> {
    /// Full objective `f(t)`.
    pub f: f64,
    /// `z'r`.
    pub zr: f64,
    /// `||r||^2 + lambda ||D t||^2`.
    pub quad: f64,
    /// `R^T r + lambda D^T D t` (the gradient without `rho`).
    pub g: &'a [f64],
    /// `1't`.
    pub sum_t: f64,
    /// Weight of the total dwell.
    pub rho: f64,
}

/// The best dual bound over a few multipliers; `partials` is scratch for the fixed-order sums.
pub(crate) fn gap_bound(
    inputs: &DualInputs<'_>,
    bounds: &DwellBounds,
    partials: &mut Vec<f64>,
) -> GapBound {
    let DualInputs {
        f,
        zr,
        quad,
        g,
        sum_t,
        rho,
    } = *inputs;
    let n = g.len();
    let lower = bounds.lower_s();
    let sum_l = fixed_sum(n, partials, |j| lower[j]);
    let level = if rho > 0.0 {
        ((f - rho * sum_l) / rho).max(0.0)
    } else {
        f64::INFINITY
    };
    let upper_of = |j: usize| bounds.upper(j).min(lower[j] + level);
    let dual = |alpha: f64, partials: &mut Vec<f64>| -> f64 {
        let lin = fixed_sum(n, partials, |j| {
            let c = alpha * g[j] + rho;
            if c >= 0.0 {
                c * lower[j]
            } else {
                let u = upper_of(j);
                if u.is_finite() {
                    c * u
                } else {
                    f64::NEG_INFINITY
                }
            }
        });
        -alpha * zr - 0.5 * alpha * alpha * quad + lin
    };
    let mut alphas = vec![1.0, 0.999, 0.99, 0.9, 0.5, 0.1];
    if rho > 0.0 {
        let worst = g.iter().fold(0.0_f64, |a, &gj| a.max(-gj));
        if worst > 0.0 {
            alphas.push((rho / worst).min(1.0));
        }
    }
    let mut best = f64::NEG_INFINITY;
    for a in alphas {
        let d = dual(a, partials);
        if d > best {
            best = d;
        }
    }
    if rho > 0.0 {
        // alpha = 0: f* >= rho 1'l, finite and sometimes the best.
        best = best.max(rho * sum_l);
    }
    if best == f64::NEG_INFINITY {
        return GapBound::Unavailable(GapBoundReason::UnboundedDwellWithoutTimeWeight);
    }
    // Rounding margin: a few ulps of the magnitudes that cancel.
    let margin = 1e-12 * (f.abs() + zr.abs() + quad + rho * sum_t.abs());
    let gap = (f - best).max(0.0) + margin;
    if gap.is_finite() {
        GapBound::Bound(gap)
    } else {
        GapBound::Unavailable(GapBoundReason::NonFinite)
    }
}

/// The gap bound of `problem` at the feasible dwell vector `dwell_s` (one product with `R` and
/// one with `R^T`).
pub fn certify(problem: &Problem, dwell_s: &[f64]) -> Result<GapBound> {
    let n = problem.n();
    if dwell_s.len() != n {
        return Err(Error::LengthMismatch {
            what: "dwell_s",
            got: dwell_s.len(),
            expected: n,
        });
    }
    with_operator(problem, |op| Ok(gap_bound_with(problem, op, dwell_s)))
}

/// [`certify`] with the operator in hand.
fn gap_bound_with(problem: &Problem, op: &dyn LinearOperator, dwell_s: &[f64]) -> GapBound {
    let n = problem.n();
    let z = problem.z_nm();
    let m = z.len();
    let mut partials = Vec::new();
    let mut r = vec![0.0; m];
    op.apply(dwell_s, &mut r);
    let mean = fixed_sum(m, &mut partials, |i| r[i] - z[i]) / m as f64;
    r.iter_mut().zip(z).for_each(|(r, z)| *r = *r - z - mean);
    let mut g = vec![0.0; n];
    op.apply_transpose(&r, &mut g);
    let lambda = problem.lambda();
    let mut half_d2 = 0.0;
    if lambda > 0.0 {
        for (j, gj) in g.iter_mut().enumerate() {
            *gj += lambda * super::dtd(dwell_s, j);
        }
        half_d2 = 0.5
            * lambda
            * fixed_sum(n.saturating_sub(1), &mut partials, |k| {
                (dwell_s[k + 1] - dwell_s[k]).powi(2)
            });
    }
    let r2 = fixed_sum(m, &mut partials, |i| r[i] * r[i]);
    let zr = fixed_sum(m, &mut partials, |i| z[i] * r[i]);
    let sum_t = fixed_sum(n, &mut partials, |j| dwell_s[j]);
    let rho = problem.rho();
    let inputs = DualInputs {
        f: 0.5 * r2 + half_d2 + rho * sum_t,
        zr,
        quad: r2 + 2.0 * half_d2,
        g: &g,
        sum_t,
        rho,
    };
    gap_bound(&inputs, problem.bounds(), &mut partials)
}
