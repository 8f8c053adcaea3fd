//! Acceleration limits at scale: an augmented Lagrangian with a spectral projected-gradient inner
//! solver, using only products with `R` and `R^T` (assembled or FFT operator).
//!
//! Same model as [`super::accel`]: along each line `|v_{j+1}^2 - v_j^2| <= 2 a_max s_j` with
//! `v_j = ds_j / t_j`, connecting moves free. Writing `u_j = ds_j^2 / t_j^2` and `c_j = 2 a_max
//! s_j`, each constrained segment gives the two scaled constraints
//! `h_j^+ = (u_{j+1} - u_j) / c_j - 1 <= 0` and `h_j^- = (u_j - u_{j+1}) / c_j - 1 <= 0`.
//!
//! **Augmented Lagrangian** (Powell-Hestenes-Rockafellar, for inequalities; Nocedal & Wright,
//! *Numerical Optimization*, 2nd ed., sec. 17.4): minimise over the dwell box
//! `L(t) = f(t) + (mu / 2) sum_k [max(0, h_k(t) + y_k / mu)^2 - (y_k / mu)^2]`, with `f` the
//! contract objective (free piston eliminated); then `y_k <- max(0, y_k + mu h_k)`, and `mu`
//! grows tenfold when the largest violation did not fall below a quarter of the previous one.
//! The outer loop stops once the largest violation is within a tenth of the constraint tolerance
//! after an inner solve at the final tolerance.
//!
//! **Inner solver**: spectral projected gradient (Birgin, Martinez & Raydan, "Nonmonotone
//! spectral projected gradient methods on convex sets", SIAM J. Optim. 10, 1196 (2000)) with
//! Barzilai-Borwein steps and a nonmonotone Armijo search over the last 10 values, in the
//! Jacobi-scaled variables of the first-order solver (`t = S w`, `S = diag(1/sqrt(d_j))`,
//! `d_j` the centred column norms of `R`). Each trial point costs one product with `R`, each
//! accepted point one with `R^T`; memory is `O(m + n)` beyond the operator. Stops when the
//! projected-gradient norm falls below the inner tolerance (relative to `||S R^T P z||`).
//!
//! **Start and finish.** It starts from the feasible point of [`super::accel`] (interval
//! propagation in `u` towards the feed-limited optimum) and ends with the same propagation
//! towards its result, which restores the limit exactly where the augmented Lagrangian left a
//! violation within tolerance; the better (in `f`) of that point and the start is returned.
//!
//! Why this method: the subproblems need nothing but operator products, so it runs on the FFT
//! operator and on curved parts alike, memory stays linear, and the warm start from the
//! feed-limited optimum means few outer iterations (docs/machine.md).

use super::accel::{self, AccelLimits, AccelReport, AccelSolution, Kinematics};
use super::operator::{LinearOperator, SparseOperator};
use super::{Problem, Settings, Solution, SolverKind, Status};
use crate::error::{Error, Result};
use crate::observer::{IterationInfo, Observer, Stage};
use crate::path::DwellPath;
use std::time::Instant;

/// Inner iterations per outer iteration, at most.
const MAX_INNER: usize = 3_000;
/// Nonmonotone memory of the line search.
const MEMORY: usize = 10;
/// Armijo constant.
const GAMMA: f64 = 1e-4;

/// The constraint side of the augmented Lagrangian.
struct Constraints<'a> {
    kin: &'a Kinematics,
    /// Constrained segment indices.
    seg: Vec<usize>,
}

impl Constraints<'_> {
    /// `(h^+, h^-)` of segment `j` at `t`.
    fn h(&self, j: usize, t: &[f64]) -> (f64, f64) {
        let c = self.kin.cap[j];
        let g = self.kin.v2(j + 1, t) - self.kin.v2(j, t);
        if c > 0.0 {
            (g / c - 1.0, -g / c - 1.0)
        } else {
            (g, -g)
        }
    }

    fn max_violation(&self, t: &[f64]) -> f64 {
        self.seg
            .iter()
            .map(|&j| {
                let (a, b) = self.h(j, t);
                a.max(b)
            })
            .fold(0.0, f64::max)
    }

    /// Adds the penalty's value to the return and its gradient (in `t`) to `grad`.
    fn penalty(&self, t: &[f64], y: &[f64], mu: f64, grad: Option<&mut [f64]>) -> f64 {
        let mut val = 0.0;
        let mut g = grad;
        for (k, &j) in self.seg.iter().enumerate() {
            let (hp, hm) = self.h(j, t);
            let c = self.kin.cap[j];
            let scale = if c > 0.0 { 1.0 / c } else { 1.0 };
            for (h, y, sign) in [(hp, y[2 * k], 1.0), (hm, y[2 * k + 1], -1.0)] {
                let a = (h + y / mu).max(0.0);
                val += 0.5 * mu * (a * a - (y / mu) * (y / mu));
                if a > 0.0 {
                    if let Some(g) = g.as_deref_mut() {
                        // d h / d t_{j+1} = sign * u'_{j+1} / c, d h / d t_j = -sign * u'_j / c,
                        // u'_i = -2 u_i / t_i.
                        let du = |i: usize| {
                            if self.kin.ds[i] == 0.0 || t[i] <= 0.0 {
                                0.0
                            } else {
                                -2.0 * self.kin.v2(i, t) / t[i]
                            }
                        };
                        g[j + 1] += mu * a * sign * scale * du(j + 1);
                        g[j] -= mu * a * sign * scale * du(j);
                    }
                }
            }
        }
        val
    }
}

/// The contract objective and its gradient through the operator.
struct Smooth<'a> {
    op: &'a dyn LinearOperator,
    z: &'a [f64],
    rho: f64,
    lambda: f64,
    r: Vec<f64>,
}

impl Smooth<'_> {
    /// `f(t)`; leaves the centred residual in `self.r`.
    fn value(&mut self, t: &[f64]) -> f64 {
        self.op.apply(t, &mut self.r);
        let m = self.r.len() as f64;
        let mean = self.r.iter().zip(self.z).map(|(a, b)| a - b).sum::<f64>() / m;
        let mut s = 0.0;
        for (r, z) in self.r.iter_mut().zip(self.z) {
            *r = *r - z - mean;
            s += *r * *r;
        }
        let smooth: f64 = t.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
        0.5 * s + self.rho * t.iter().sum::<f64>() + 0.5 * self.lambda * smooth
    }

    /// Gradient at the `t` of the last [`Smooth::value`] call.
    fn gradient(&self, t: &[f64], g: &mut [f64]) {
        self.op.apply_transpose(&self.r, g);
        let n = t.len();
        for j in 0..n {
            let mut dd = 0.0;
            if j > 0 {
                dd += t[j] - t[j - 1];
            }
            if j + 1 < n {
                dd -= t[j + 1] - t[j];
            }
            g[j] += self.rho + self.lambda * dd;
        }
    }
}

/// Solves the dwell problem with the acceleration limit by the augmented Lagrangian (module
/// documentation): the feed-limited optimum first ([`super::solve`]), then the outer loop.
pub fn solve(
    problem: &Problem,
    path: &DwellPath,
    limits: &AccelLimits,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<AccelSolution> {
    limits.validate()?;
    settings.validate()?;
    let start = Instant::now();
    let n = problem.n();
    if path.len() != n {
        return Err(Error::LengthMismatch {
            what: "dwell path",
            got: path.len(),
            expected: n,
        });
    }
    let kin = Kinematics::new(path, limits);
    let bounds = problem.bounds();
    let (lo_u, hi_u) = accel::speed_boxes(&kin, bounds)?;
    let reachable = accel::forward_reachable(&kin, &lo_u, &hi_u, limits)?;
    let reference = super::solve(problem, settings, observer)?;
    let tol = limits.constraint_tolerance;

    let sparse;
    let op: &dyn LinearOperator = match (problem.influence(), problem.fft_operator()) {
        (Some(r), _) => {
            sparse = SparseOperator::new(r.csc());
            &sparse
        }
        (None, Some(f)) => f,
        (None, None) => {
            return Err(Error::invalid("problem", "has neither a matrix nor an operator"));
        }
    };
    let cons = Constraints {
        kin: &kin,
        seg: (0..kin.cap.len()).filter(|&j| kin.constrained[j]).collect(),
    };
    let mut smooth = Smooth {
        op,
        z: problem.z_nm(),
        rho: problem.rho(),
        lambda: problem.lambda(),
        r: vec![0.0; problem.m()],
    };

    let t_start = accel::feasible_start(&kin, &reachable, &reference.dwell_s, bounds);
    let mut outer = 0;
    let mut inner_total = 0;
    let mut status = Status::MaxIterations;
    let best_t;
    if kin.violation(&reference.dwell_s) <= tol {
        best_t = reference.dwell_s.clone();
        status = reference.status;
    } else {
        // Jacobi scaling.
        let mut d = op.centred_column_norms_sq();
        let lam = problem.lambda();
        for (j, dj) in d.iter_mut().enumerate() {
            // Diagonal of lambda D^T D: 1 at the path's ends, 2 inside.
            *dj += lam * ([j > 0, j + 1 < n].iter().filter(|&&b| b).count() as f64);
        }
        let mut pos: Vec<f64> = d.iter().copied().filter(|&v| v > 0.0).collect();
        pos.sort_by(f64::total_cmp);
        let fill = pos.get(pos.len() / 2).copied().unwrap_or(1.0);
        let s: Vec<f64> = d
            .iter()
            .map(|&v| 1.0 / if v > 0.0 { v } else { fill }.sqrt())
            .collect();
        let lo_w: Vec<f64> = (0..n).map(|j| bounds.lower_s()[j] / s[j]).collect();
        let hi_w: Vec<f64> = (0..n).map(|j| bounds.upper(j) / s[j]).collect();
        // Gradient scale of the KKT test: ||S R^T P z||.
        let gscale = {
            let zero = vec![0.0; n];
            smooth.value(&zero);
            let mut g = vec![0.0; n];
            smooth.gradient(&zero, &mut g);
            g.iter()
                .zip(&s)
                .map(|(g, s)| (g * s).powi(2))
                .sum::<f64>()
                .sqrt()
                .max(f64::MIN_POSITIVE)
        };
        let mut w: Vec<f64> = (0..n).map(|j| t_start[j] / s[j]).collect();
        let mut y = vec![0.0; 2 * cons.seg.len()];
        let f0 = smooth.value(&t_start).max(1e-300);
        // A unit violation on every segment weighs about ten times the start's objective.
        let mut mu = 10.0 * f0 / (cons.seg.len().max(1) as f64);
        let mut prev_viol = f64::INFINITY;
        let final_tol = settings.first_order_tolerance.min(1e-5);
        let mut inner_tol = 1e-3_f64.max(final_tol);
        let max_outer = limits.max_iterations.max(1);
        observer.start(Stage::Loop, max_outer as u64);
        let mut t = t_start.clone();
        while outer < max_outer {
            outer += 1;
            let (it, _pg) = spg(
                &mut smooth, &cons, &y, mu, &s, &lo_w, &hi_w, &mut w, inner_tol * gscale,
            );
            inner_total += it;
            for j in 0..n {
                t[j] = s[j] * w[j];
            }
            let viol = cons.max_violation(&t);
            eprintln!("DBG outer {outer} inner {it} pg {:.3e} tol {:.3e} viol {viol:.3e} f {:.6e} mu {mu:.3e}", _pg, inner_tol * gscale, smooth.value(&t));
            observer.advance(Stage::Loop, 1);
            observer.iteration(&IterationInfo {
                iteration: outer,
                objective: smooth.value(&t),
                kkt_residual: Some(viol),
            });
            if viol <= 0.1 * tol && inner_tol <= final_tol {
                status = Status::Converged;
                break;
            }
            for (k, &j) in cons.seg.iter().enumerate() {
                let (hp, hm) = cons.h(j, &t);
                y[2 * k] = (y[2 * k] + mu * hp).max(0.0);
                y[2 * k + 1] = (y[2 * k + 1] + mu * hm).max(0.0);
            }
            if viol > 0.25 * prev_viol {
                mu *= 10.0;
            }
            prev_viol = viol;
            inner_tol = (inner_tol * 0.1).max(final_tol);
        }
        observer.finish(Stage::Loop);
        // Restore the limit exactly, then keep the better of that and the feasible start.
        let repaired = accel::feasible_start(&kin, &reachable, &t, bounds);
        let f_rep = smooth.value(&repaired);
        let f_start = smooth.value(&t_start);
        eprintln!("DBG f_rep {f_rep:.6e} f_start {f_start:.6e}");
        best_t = if f_rep <= f_start { repaired } else { t_start };
    }
    finish(
        problem, path, limits, &kin, reference, best_t, outer, inner_total, status, start,
    )
}

/// The spectral projected gradient on the augmented Lagrangian in scaled variables; returns
/// (iterations, final projected-gradient norm).
#[allow(clippy::too_many_arguments)]
fn spg(
    smooth: &mut Smooth<'_>,
    cons: &Constraints<'_>,
    y: &[f64],
    mu: f64,
    s: &[f64],
    lo: &[f64],
    hi: &[f64],
    w: &mut [f64],
    tol: f64,
) -> (usize, f64) {
    let n = w.len();
    let mut t: Vec<f64> = (0..n).map(|j| s[j] * w[j]).collect();
    let eval = |smooth: &mut Smooth<'_>, t: &[f64]| smooth.value(t) + cons.penalty(t, y, mu, None);
    let grad = |smooth: &Smooth<'_>, t: &[f64], g: &mut [f64]| {
        smooth.gradient(t, g);
        cons.penalty(t, y, mu, Some(g));
        for j in 0..n {
            g[j] *= s[j];
        }
    };
    let mut f = eval(smooth, &t);
    let mut g = vec![0.0; n];
    grad(smooth, &t, &mut g);
    let mut hist = vec![f; 1];
    let pg_norm = |w: &[f64], g: &[f64]| -> f64 {
        (0..n)
            .map(|j| ((w[j] - g[j]).clamp(lo[j], hi[j]) - w[j]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let mut alpha = {
        let gi = g.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
        if gi > 0.0 {
            1.0 / gi
        } else {
            1.0
        }
    };
    let (mut w_new, mut g_new, mut dir) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let mut it = 0;
    let mut pg = pg_norm(w, &g);
    while it < MAX_INNER && pg > tol {
        it += 1;
        for j in 0..n {
            dir[j] = (w[j] - alpha * g[j]).clamp(lo[j], hi[j]) - w[j];
        }
        let gd: f64 = (0..n).map(|j| g[j] * dir[j]).sum();
        if gd >= 0.0 {
            break;
        }
        let fmax = hist.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mut lam = 1.0;
        let mut f_new;
        loop {
            for j in 0..n {
                w_new[j] = w[j] + lam * dir[j];
                t[j] = s[j] * w_new[j];
            }
            f_new = eval(smooth, &t);
            if f_new <= fmax + GAMMA * lam * gd || lam < 1e-12 {
                break;
            }
            // Safeguarded quadratic backtracking.
            let q = -0.5 * lam * lam * gd / (f_new - f - lam * gd);
            lam = if q >= 0.1 * lam && q <= 0.5 * lam {
                q
            } else {
                0.5 * lam
            };
        }
        if !(f_new <= fmax + GAMMA * lam * gd) {
            // No decrease found: restore and stop.
            for j in 0..n {
                t[j] = s[j] * w[j];
            }
            smooth.value(&t);
            break;
        }
        grad(smooth, &t, &mut g_new);
        let (mut ss, mut sy) = (0.0, 0.0);
        for j in 0..n {
            let sj = w_new[j] - w[j];
            ss += sj * sj;
            sy += sj * (g_new[j] - g[j]);
        }
        alpha = if sy > 0.0 {
            (ss / sy).clamp(1e-12, 1e12)
        } else {
            1e12_f64.min(alpha * 10.0)
        };
        w.copy_from_slice(&w_new);
        g.copy_from_slice(&g_new);
        f = f_new;
        hist.push(f);
        if hist.len() > MEMORY {
            hist.remove(0);
        }
        pg = pg_norm(w, &g);
    }
    (it, pg)
}

/// Builds the solution and report (shared layout with the SCP).
#[allow(clippy::too_many_arguments)]
fn finish(
    problem: &Problem,
    path: &DwellPath,
    limits: &AccelLimits,
    kin: &Kinematics,
    reference: Solution,
    best_t: Vec<f64>,
    outer: usize,
    inner: usize,
    status: Status,
    start: Instant,
) -> Result<AccelSolution> {
    let eval = problem.evaluate(&best_t)?;
    let m = problem.m() as f64;
    let accels = accel::segment_accelerations_mm_per_s2(path, &best_t, limits.corner_angle_deg);
    let report = AccelReport {
        a_max_mm_per_s2: limits.a_max_mm_per_s2,
        max_accel_mm_per_s2: accels.iter().flatten().fold(0.0, |a, &b| f64::max(a, b)),
        max_accel_reference_mm_per_s2: accel::max_acceleration_mm_per_s2(
            path,
            &reference.dwell_s,
            limits.corner_angle_deg,
        ),
        scp_iterations: outer,
        constrained_segments: kin.constrained.iter().filter(|&&c| c).count(),
        binding_segments: accels
            .iter()
            .flatten()
            .filter(|&&a| a >= 0.99 * limits.a_max_mm_per_s2)
            .count(),
        rms_after_nm: (2.0 * eval.objective / m).max(0.0).sqrt(),
        rms_after_reference_nm: (2.0 * reference.objective / m).max(0.0).sqrt(),
        objective: eval.objective,
        objective_reference: reference.objective,
        objective_gap: eval.objective - reference.objective,
        status,
    };
    let solution = Solution {
        status,
        solver: SolverKind::FirstOrder,
        piston_nm: eval.piston_nm,
        objective: eval.objective,
        dwell_s: best_t,
        iterations: reference.iterations + inner,
        solve_seconds: start.elapsed().as_secs_f64(),
        kkt_residual: None,
        objective_gap_bound: None,
        min_time: reference.min_time,
    };
    Ok(AccelSolution {
        solution,
        report,
        reference,
    })
}
