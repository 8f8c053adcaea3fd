//! Acceleration limits at scale: sequential convexification with an augmented Lagrangian on the
//! linearised chain constraints, accelerated projected-gradient subproblems that need only
//! products with `R` and `R^T`, and an exact feasibility repair.
//!
//! Same model as [`super::accel`]: along each line `|u_{j+1} - u_j| <= c_j` with the squared feed
//! `u_j = ds_j^2 / t_j^2` and `c_j = 2 a_max s_j`; connecting moves carry no constraint.
//!
//! **Outer loop** (iteration `k` at the dwell `t^k`). Each constrained segment's scaled
//! constraint `h_j(t) = (u_{j+1}(t) - u_j(t)) / c_j`, `-1 <= h_j <= 1`, is linearised at `t^k`
//! (`u_j' = -2 u_j / t_j`), and the convex subproblem
//! `min f(t) + sum_j (mu / 2) dist(h_j^lin(t) + y_j / mu, [-1, 1])^2` over the dwell box
//! intersected with the trust region `|t_j - t_j^k| <= tau t_j^k` is solved approximately. `f` is
//! the contract objective with the free piston eliminated, `f(t) = 0.5 ||P (R t - z)||^2 +
//! rho 1't + 0.5 lambda ||D t||^2`. The multipliers then take the augmented-Lagrangian update on
//! the true constraint, `y_j <- mu (w - clamp(w, -1, 1))` with `w = h_j(t^{k+1}) + y_j / mu`
//! (Powell-Hestenes-Rockafellar for two-sided constraints: Nocedal & Wright, *Numerical
//! Optimization*, 2nd ed., sec. 17.4), and `mu` grows tenfold when the largest violation did not
//! fall below a quarter of the previous one. The loop ends when the true constraint holds within
//! the tolerance and `f` changes by less than `objective_tolerance`, or after `max_iterations`.
//!
//! **Subproblems** are convex (a convex quadratic plus a convex penalty of affine functions), so
//! FISTA converges on them (Beck & Teboulle, SIAM J. Imaging Sci. 2, 2009), with the adaptive
//! restart of O'Donoghue & Candes (2015) and backtracking on the step. Variables are scaled by the
//! diagonal of the subproblem's (generalised) Hessian, `d_j = ||P R_j||^2 + lambda (D^T D)_jj +
//! mu sum (dh/dt_j)^2`: the penalty's curvature in `t` ranges over many decades (it scales as
//! `ds^2 / t^4`), and an iteration scaled by `R` alone stalls on it. Each iteration costs three
//! products with the operator (two for the gradient, one for the backtracking test); memory is
//! `O(m + n)` beyond the operator. Every subproblem is warm-started from the previous iterate.
//!
//! **Start and finish.** The feed-limited optimum (the first-order solver unless `qp` is asked
//! for) gives the reference; the loop starts from the feasible point of [`super::accel`] (interval
//! propagation of `u` along each line towards the feed-limited optimum). Its result is passed
//! through the same propagation, which moves `u` the least needed to satisfy every constraint
//! exactly; the better (in `f`) of that point and the start is returned, so the result always
//! meets the limit.
//!
//! **Why this method.** It needs nothing but operator products, so it runs with the assembled
//! sparse `R`, the matrix-free FFT operator and on curved parts alike, with memory linear in the
//! problem. The sequential QP ([`super::accel::solve_scp_qp`]) solves an interior-point QP with
//! `R` per iteration and does not reach 1e4 points. An augmented Lagrangian on the nonlinear
//! constraints in `t` with a spectral projected-gradient inner solver scaled by `R` alone was
//! tried and stalled (the penalty's curvature spread); linearising per outer iteration keeps each
//! subproblem convex, and the penalty-aware scaling keeps it well conditioned.

use super::accel::{
    feasible_start, finish, forward_reachable, speed_boxes, AccelLimits, AccelSolution, Finished,
    Kinematics,
};
use super::first_order::dtd;
use super::{with_operator, DwellBounds, Problem, Settings, SolverChoice, SolverKind, Status};
use crate::error::{Error, Result};
use crate::influence::operator::LinearOperator;
use crate::observer::{IterationInfo, Observer, Stage};
use crate::path::DwellPath;
use std::time::Instant;

/// FISTA iterations per subproblem, at most.
const MAX_INNER: usize = 400;
/// A subproblem ends when its scaled projected-gradient norm falls below this fraction of the
/// first one.
const INNER_REDUCTION: f64 = 1e-3;
/// Largest penalty weight relative to the first.
const MAX_MU_GROWTH: f64 = 1e10;

/// Solves the dwell problem with the acceleration limit by the first-order method (see the
/// module documentation): the feed-limited optimum first ([`super::solve`]), then the outer loop.
pub fn solve(
    problem: &Problem,
    path: &DwellPath,
    limits: &AccelLimits,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<AccelSolution> {
    limits.validate()?;
    settings.validate()?;
    let started = Instant::now();
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
    let (lo_u, hi_u) = speed_boxes(&kin, bounds)?;
    let reachable = forward_reachable(&kin, &lo_u, &hi_u, limits)?;
    // The reference only starts the loop and prices the limit: `auto` takes the first-order
    // solver for it at any size (an explicit `qp` is kept).
    let mut reference_settings = settings.clone();
    if reference_settings.solver == SolverChoice::Auto {
        reference_settings.solver = SolverChoice::FirstOrder;
    }
    let reference = super::solve(problem, &reference_settings, observer)?;
    let tol = limits.constraint_tolerance;
    let done = |dwell_s, iterations, inner, status, reference| {
        finish(
            problem,
            path,
            limits,
            &kin,
            Finished {
                reference,
                dwell_s,
                iterations,
                inner_iterations: inner,
                status,
                solver: SolverKind::FirstOrder,
                started,
            },
        )
    };
    if kin.violation(&reference.dwell_s) <= tol {
        let (t, st, it) = (reference.dwell_s.clone(), reference.status, reference.iterations);
        return done(t, 0, it, st, reference);
    }
    let start = feasible_start(&kin, &reachable, &reference.dwell_s, bounds);
    let segments: Vec<usize> = (0..kin.cap.len())
        .filter(|&j| kin.constrained[j] && kin.cap[j] > 0.0)
        .collect();
    let outcome = with_operator(problem, |op| {
        let mut al = Loop {
            op,
            z: problem.z_nm(),
            rho: problem.rho(),
            lambda: problem.lambda(),
            cn: op.centred_column_norms_sq(),
            kin: &kin,
            segments: &segments,
            r: vec![0.0; op.nrows()],
        };
        al.run(&start, bounds, limits, settings, observer, started)
    })?;
    let repaired = feasible_start(&kin, &reachable, &outcome.dwell_s, bounds);
    let f_rep = problem.evaluate(&repaired)?.full_objective;
    let f_start = problem.evaluate(&start)?.full_objective;
    let best = if f_rep <= f_start { repaired } else { start };
    let inner = reference.iterations + outcome.inner_iterations;
    done(best, outcome.iterations, inner, outcome.status, reference)
}

/// What the outer loop ends with.
struct Outcome {
    dwell_s: Vec<f64>,
    iterations: usize,
    inner_iterations: usize,
    status: Status,
}

/// The pieces of the augmented-Lagrangian loop.
struct Loop<'a> {
    op: &'a dyn LinearOperator,
    z: &'a [f64],
    rho: f64,
    lambda: f64,
    /// Centred column norms of `R` (the diagonal of `R^T P R`).
    cn: Vec<f64>,
    kin: &'a Kinematics,
    /// Constrained segments with a positive cap.
    segments: &'a [usize],
    /// Residual buffer, `m`.
    r: Vec<f64>,
}

/// One segment's linearised scaled constraint: `h = o + p t_{j+1} + q t_j`.
#[derive(Clone, Copy)]
struct Row {
    j: usize,
    o: f64,
    p: f64,
    q: f64,
}

impl Loop<'_> {
    /// `f(t)`; with `grad`, also its gradient. Leaves the centred residual in `self.r`.
    fn objective(&mut self, t: &[f64], grad: Option<&mut [f64]>) -> f64 {
        let mut rt = std::mem::take(&mut self.r);
        self.op.apply(t, &mut rt);
        let f = self.value(&rt, t, grad);
        f
    }

    /// `f(t)` from `R t`; with `grad`, also its gradient. Leaves the centred residual in
    /// `self.r`.
    fn value(&mut self, rt: &[f64], t: &[f64], grad: Option<&mut [f64]>) -> f64 {
        let m = rt.len() as f64;
        self.r.resize(rt.len(), 0.0);
        let mut mean = 0.0;
        for ((r, z), a) in self.r.iter_mut().zip(self.z).zip(rt) {
            *r = a - z;
            mean += *r;
        }
        mean /= m;
        let mut f = 0.0;
        for r in self.r.iter_mut() {
            *r -= mean;
            f += *r * *r;
        }
        f *= 0.5;
        f += self.rho * t.iter().sum::<f64>();
        f += 0.5 * self.lambda * t.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum::<f64>();
        if let Some(g) = grad {
            self.op.apply_transpose(&self.r, g);
            for (j, gj) in g.iter_mut().enumerate() {
                *gj += self.rho + self.lambda * dtd(t, j);
            }
        }
        f
    }

    /// True scaled constraint of segment `j` at `t`.
    fn h(&self, j: usize, t: &[f64]) -> f64 {
        (self.kin.v2(j + 1, t) - self.kin.v2(j, t)) / self.kin.cap[j]
    }

    /// `u_j'(t_j) = -2 u_j / t_j`.
    fn du(&self, j: usize, t: &[f64]) -> f64 {
        if self.kin.ds[j] == 0.0 || t[j] <= 0.0 {
            0.0
        } else {
            -2.0 * self.kin.v2(j, t) / t[j]
        }
    }

    fn linearise(&self, t: &[f64]) -> Vec<Row> {
        self.segments
            .iter()
            .map(|&j| {
                let c = self.kin.cap[j];
                let (p, q) = (self.du(j + 1, t) / c, -self.du(j, t) / c);
                Row {
                    j,
                    o: self.h(j, t) - p * t[j + 1] - q * t[j],
                    p,
                    q,
                }
            })
            .collect()
    }

    /// Penalty value at `t`; with `grad`, adds its gradient.
    fn penalty(rows: &[Row], y: &[f64], mu: f64, t: &[f64], grad: Option<&mut [f64]>) -> f64 {
        let mut val = 0.0;
        let mut g = grad;
        for (row, &yk) in rows.iter().zip(y) {
            let w = row.o + row.p * t[row.j + 1] + row.q * t[row.j] + yk / mu;
            let e = w - w.clamp(-1.0, 1.0);
            if e != 0.0 {
                val += 0.5 * mu * e * e;
                if let Some(g) = g.as_deref_mut() {
                    g[row.j + 1] += mu * e * row.p;
                    g[row.j] += mu * e * row.q;
                }
            }
        }
        val
    }

    fn run(
        &mut self,
        start: &[f64],
        bounds: &DwellBounds,
        limits: &AccelLimits,
        settings: &Settings,
        observer: &dyn Observer,
        started: Instant,
    ) -> Result<Outcome> {
        let n = start.len();
        let mut t = start.to_vec();
        let mut f = self.objective(&t, None);
        let ns = self.segments.len().max(1) as f64;
        let mu0 = 10.0 * f.abs().max(1e-12) / ns;
        let mut mu = mu0;
        let mut y = vec![0.0; self.segments.len()];
        let tol = limits.constraint_tolerance;
        let settle_scale = 1e-12 * 0.5 * self.z.iter().map(|z| z * z).sum::<f64>();
        let mut prev_viol = self.kin.violation(&t).max(0.0) + 1.0;
        let mut lip: f64 = 1.0;
        let mut inner_total = 0;
        let mut status = Status::MaxIterations;
        let mut iterations = 0;
        let mut best: Option<(f64, Vec<f64>)> = None;
        let tau = limits.trust_region;
        // Buffers.
        let (mut x, mut x_prev, mut yv) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        let (mut g, mut trial) = (vec![0.0; n], vec![0.0; n]);
        let m = self.z.len();
        let (mut rx, mut rx_prev) = (vec![0.0; m], vec![0.0; m]);
        let (mut ry, mut rtrial) = (vec![0.0; m], vec![0.0; m]);
        let mut d = vec![0.0; n];
        let (mut lo, mut hi) = (vec![0.0; n], vec![0.0; n]);
        observer.start(Stage::Loop, limits.max_iterations as u64);
        while iterations < limits.max_iterations {
            if started.elapsed().as_secs_f64() > settings.time_limit_s {
                status = Status::TimeLimit;
                break;
            }
            iterations += 1;
            let rows = self.linearise(&t);
            for j in 0..n {
                lo[j] = bounds.lower_s()[j].max(t[j] * (1.0 - tau));
                hi[j] = bounds.upper(j).min(t[j] * (1.0 + tau)).max(lo[j]);
                let dd = if n == 1 {
                    0.0
                } else if j == 0 || j + 1 == n {
                    1.0
                } else {
                    2.0
                };
                d[j] = self.cn[j] + self.lambda * dd;
            }
            for row in &rows {
                d[row.j + 1] += mu * row.p * row.p;
                d[row.j] += mu * row.q * row.q;
            }
            for dj in d.iter_mut() {
                if !(*dj > 0.0 && dj.is_finite()) {
                    *dj = 1.0;
                }
            }
            // FISTA on the subproblem, scaled metric d. `R x`, `R x_prev` and `R trial` are
            // kept, so that `R` at the extrapolated point is their combination: one product with
            // `R` (the backtracking test) and one with `R^T` (the gradient) per iteration.
            x.copy_from_slice(&t);
            x_prev.copy_from_slice(&t);
            self.op.apply(&x, &mut rx);
            rx_prev.copy_from_slice(&rx);
            let mut theta: f64 = 1.0;
            let mut beta = 0.0;
            let mut phi_x = f64::INFINITY;
            let mut first_pg = None;
            lip = (0.5 * lip).max(1e-6);
            for _ in 0..MAX_INNER {
                inner_total += 1;
                for j in 0..n {
                    yv[j] = x[j] + beta * (x[j] - x_prev[j]);
                }
                for i in 0..ry.len() {
                    ry[i] = rx[i] + beta * (rx[i] - rx_prev[i]);
                }
                let phi_y = self.value(&ry, &yv, Some(&mut g))
                    + Self::penalty(&rows, &y, mu, &yv, Some(&mut g));
                // Projected-gradient norm (scaled) at yv.
                let pg: f64 = (0..n)
                    .map(|j| {
                        let s = (yv[j] - g[j] / d[j]).clamp(lo[j], hi[j]) - yv[j];
                        d[j] * s * s
                    })
                    .sum::<f64>()
                    .sqrt();
                let first = *first_pg.get_or_insert(pg);
                if pg <= INNER_REDUCTION * first || pg == 0.0 {
                    if beta != 0.0 {
                        std::mem::swap(&mut x, &mut yv);
                        std::mem::swap(&mut rx, &mut ry);
                    }
                    break;
                }
                // Backtracking step.
                let phi_t = loop {
                    for j in 0..n {
                        trial[j] = (yv[j] - g[j] / (lip * d[j])).clamp(lo[j], hi[j]);
                    }
                    self.op.apply(&trial, &mut rtrial);
                    let phi_t = self.value(&rtrial, &trial, None)
                        + Self::penalty(&rows, &y, mu, &trial, None);
                    let (mut lin, mut quad) = (0.0, 0.0);
                    for j in 0..n {
                        let s = trial[j] - yv[j];
                        lin += g[j] * s;
                        quad += d[j] * s * s;
                    }
                    if phi_t <= phi_y + lin + 0.5 * lip * quad + 1e-12 * phi_y.abs()
                        || lip > 1e12
                    {
                        break phi_t;
                    }
                    lip *= 2.0;
                };
                if phi_t > phi_x {
                    // Adaptive restart: drop the momentum, stay at x.
                    theta = 1.0;
                    beta = 0.0;
                    continue;
                }
                let theta_next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
                beta = (theta - 1.0) / theta_next;
                theta = theta_next;
                std::mem::swap(&mut x_prev, &mut x);
                std::mem::swap(&mut x, &mut trial);
                std::mem::swap(&mut rx_prev, &mut rx);
                std::mem::swap(&mut rx, &mut rtrial);
                phi_x = phi_t;
            }
            // Subproblem solution x: the new iterate.
            t.copy_from_slice(&x);
            let f_new = self.objective(&t, None);
            let viol = self.kin.violation(&t).max(0.0);
            for (row, yk) in rows.iter().zip(y.iter_mut()) {
                let w = self.h(row.j, &t) + *yk / mu;
                *yk = mu * (w - w.clamp(-1.0, 1.0));
            }
            if viol > 0.25 * prev_viol && mu < MAX_MU_GROWTH * mu0 {
                mu *= 10.0;
            }
            prev_viol = viol;
            observer.iteration(&IterationInfo {
                iteration: iterations,
                objective: f_new,
                kkt_residual: Some(viol),
            });
            observer.advance(Stage::Loop, 1);
            let feasible = viol <= tol;
            let settled =
                (f_new - f).abs() <= limits.objective_tolerance * f_new.abs().max(settle_scale);
            f = f_new;
            if feasible && best.as_ref().is_none_or(|(bf, _)| f_new < *bf) {
                best = Some((f_new, t.clone()));
            }
            if feasible && settled {
                status = Status::Converged;
                break;
            }
        }
        observer.finish(Stage::Loop);
        let dwell_s = match best {
            Some((_, b)) if status != Status::Converged => b,
            _ => t,
        };
        Ok(Outcome {
            dwell_s,
            iterations,
            inner_iterations: inner_total,
            status,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwell::accel::{self, max_acceleration_mm_per_s2, AccelMethod};
    use crate::dwell::FeedLimits;
    use crate::influence::InfluenceMatrix;
    use crate::map::BoundingBox;
    use crate::observer::Silent;
    use crate::path::raster::{serpentine, RasterAxis};
    use crate::tif::GaussianTif;

    /// A `nx x ny` map at `pitch` mm with smooth bumps and a trench on a 50 nm base, a
    /// serpentine raster at `raster_mm` over it, a Gaussian TIF of `sigma` mm and `v_max`.
    pub(crate) fn raster_case(
        nx: usize,
        ny: usize,
        pitch: f64,
        raster_mm: f64,
        sigma: f64,
        v_max: f64,
    ) -> (Problem, DwellPath) {
        let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
        let (w, h) = ((nx - 1) as f64 * pitch, (ny - 1) as f64 * pitch);
        for iy in 0..ny {
            for ix in 0..nx {
                let (px, py) = (ix as f64 * pitch, iy as f64 * pitch);
                x.push(px);
                y.push(py);
                z.push(
                    50.0 + 300.0 * (-(px - 0.5 * w).powi(2) / 8.0).exp()
                        + 40.0 * (px / 7.0).sin() * (py / 5.0).cos()
                        + 20.0 * (py / h.max(1.0)),
                );
            }
        }
        let bbox = BoundingBox::of_points(&x, &y).unwrap();
        let path = serpentine(&bbox, raster_mm, RasterAxis::X).unwrap();
        let tif = GaussianTif::new(sigma, 100.0, 3.0).unwrap();
        let r =
            InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
        let lim = FeedLimits {
            v_max_mm_per_min: v_max,
            v_min_mm_per_min: 0.0,
        };
        let b = DwellBounds::from_feeds(&path.ds_mm(), &lim).unwrap();
        (Problem::new(r, z, b, 0.0, 0.0).unwrap(), path)
    }

    /// Relative objective tolerance against the SCP-QP reference on small cases.
    const OBJECTIVE_VS_REFERENCE: f64 = 0.01;

    /// Both methods on one case; the first-order result meets the limit within the tolerance and
    /// its objective is within 1% of the reference's (or below it).
    fn compare_with_reference(problem: &Problem, path: &DwellPath, fraction_of_free: f64) {
        let settings = Settings::default();
        let free = crate::dwell::solve(problem, &settings, &Silent).unwrap();
        let a_free = max_acceleration_mm_per_s2(path, &free.dwell_s, 60.0);
        let mut limits = AccelLimits::new(fraction_of_free * a_free);
        let fo = solve(problem, path, &limits, &settings, &Silent).unwrap();
        limits.method = AccelMethod::ScpQp;
        limits.max_iterations = 200;
        let qp = accel::solve(problem, path, &limits, &settings, &Silent).unwrap();
        assert_eq!(qp.solution.status, Status::Converged, "{:?}", qp.report);
        let a = max_acceleration_mm_per_s2(path, &fo.solution.dwell_s, 60.0);
        assert!(
            a <= limits.a_max_mm_per_s2 * (1.0 + limits.constraint_tolerance),
            "{a} > {}",
            limits.a_max_mm_per_s2
        );
        assert!(problem.bounds().max_violation_s(&fo.solution.dwell_s) < 1e-12);
        assert!(fo.report.binding_segments > 0, "{:?}", fo.report);
        let (f, f_ref) = (fo.solution.objective, qp.solution.objective);
        assert!(
            f <= f_ref * (1.0 + OBJECTIVE_VS_REFERENCE),
            "first-order {f} vs SCP-QP {f_ref} ({:?})",
            fo.report
        );
    }

    #[test]
    fn matches_reference_on_a_line() {
        let (problem, path) = raster_case(81, 1, 0.25, 0.5, 1.0, 600.0);
        assert!(problem.n() <= 500);
        compare_with_reference(&problem, &path, 0.2);
    }

    #[test]
    fn matches_reference_on_a_small_raster() {
        let (problem, path) = raster_case(41, 17, 0.5, 1.0, 1.0, 600.0);
        assert!(problem.n() <= 500, "{}", problem.n());
        compare_with_reference(&problem, &path, 0.1);
    }

    #[test]
    #[ignore]
    fn issue_case_figures() {
        let (problem, path) = raster_case(120, 70, 0.5, 0.8, 1.5, 2000.0);
        eprintln!("m {} n {} nnz {}", problem.m(), problem.n(), problem.nnz());
        let settings = Settings::default();
        let limits = AccelLimits::new(20.0);
        let t0 = Instant::now();
        let out = solve(&problem, &path, &limits, &settings, &Silent).unwrap();
        eprintln!(
            "fo: {:.2} s (reference {:.2} s, {} inner) {:?}",
            t0.elapsed().as_secs_f64(),
            out.reference.solve_seconds,
            out.solution.iterations,
            out.report
        );
        let a = max_acceleration_mm_per_s2(&path, &out.solution.dwell_s, 60.0);
        eprintln!("max a {a}");
        if std::env::var("SCP").is_ok() {
            let mut l = limits.clone();
            l.method = AccelMethod::ScpQp;
            l.max_iterations = 200;
            let t0 = Instant::now();
            let r = accel::solve(&problem, &path, &l, &settings, &Silent).unwrap();
            eprintln!("scp: {:.2} s {:?}", t0.elapsed().as_secs_f64(), r.report);
        }
    }
}
