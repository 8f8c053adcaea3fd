//! A first-order solver for the contract: products with `R` and `R^T` only, on Jacobi-scaled
//! variables, with one of three iterations ([`FirstOrderMethod`]):
//!
//! * **Projected L-BFGS** (the default): limited-memory quasi-Newton directions (Nocedal 1980)
//!   on the free variables, as in Kim, Sra & Dhillon, SIAM J. Sci. Comput. 32 (2010), with an
//!   exact line search along the projected step. Steps at [`projected_lbfgs`].
//! * **FISTA** (Beck & Teboulle 2009) with gradient-based adaptive restart (O'Donoghue & Candes,
//!   "Adaptive restart for accelerated gradient schemes", 2015).
//! * **Projected Newton-CG**: Bertsekas, "Projected Newton methods for optimization problems with
//!   simple constraints", SIAM J. Control Optim. 20 (1982), with the Newton system solved by
//!   truncated conjugate gradients on the free variables (Lin & More, SIAM J. Optim. 9, 1999) and
//!   CG stopped when its steps stall (More & Toraldo, SIAM J. Optim. 1, 1991). Steps below.
//!
//! Chosen by measurement (docs/preconditioning.md): projected L-BFGS reaches a given objective in
//! the fewest products on every problem measured (the sample job, the generated 2e3, 2e4 and 2e5
//! problems, the off-lattice mirror); FISTA's KKT residual falls well before its objective does,
//! and Newton-CG is slow to bring its KKT residual down where dwell points outnumber map points.
//!
//! **Objective.** The free piston is eliminated analytically: for fixed `t` the best `c` is
//! `mean(R t - z)`, so with `P = I - 11'/m` the contract is
//! `f(t) = 0.5 ||P (R t - z)||^2 + rho 1't + 0.5 lambda ||D t||^2` over the box `l <= t <= u`, with
//! gradient `g = R^T P (R t - z) + rho 1 + lambda D^T D t`. The iterations evaluate it from the
//! normal equations, `R^T P (R t - z) = R^T R t - R^T z - ((c't - 1'z) / m) c` with `c = R^T 1`
//! and `R^T z` computed once, so that an operator can form `R^T R t` in one pass (the FFT
//! operator does, see [`crate::influence::fft`]); the certificate forms the residual itself.
//!
//! **Scaling.** `t = S w` with `S = diag(1 / sqrt(d_j))`, `d_j` the diagonal of the Hessian
//! `R^T P R + lambda D^T D` (Jacobi preconditioning); the box stays a box. `lambda_hat` is a
//! 60-step power-iteration estimate of the largest eigenvalue of the scaled Hessian (from below).
//! FISTA steps `1 / L` with `L = lambda_hat`, Beck & Teboulle's constant-step rule with the
//! estimate in place of the exact value; should the objective ever rise between checks, `L`
//! doubles and the momentum restarts. Newton-CG takes `L = 1.1 lambda_hat`, an upper bound with
//! margin, because its fallback step must decrease `f`. (FISTA with the 1.1 margin took 7,796
//! iterations on the generated 2e4 problem at tolerance 8e-8, without it 6,032 to the same
//! objective; 2,303 -> 2,258 at 2e3, 1,163 -> 1,119 at 2e5, 360 -> 340 at 1e6.)
//!
//! **Newton-CG steps.** At `w` with scaled gradient `q`: the binding set (variables that a
//! projected gradient step of length `1 / L` puts on a bound) takes that step; CG on the others
//! solves `H_FF d = -q_F` until the residual falls by `min(0.5, sqrt(kkt))` or a step gains less
//! than a quarter of the best step; `Proj(w + alpha d)` then halves `alpha` until the Armijo
//! condition `f(w_new) <= f(w) + 1e-4 q'(w_new - w)` holds (then along `-q`, and last a projected
//! gradient step of length `1 / L`, which always decreases an `L`-smooth `f`). Iterations count
//! products with the Hessian or gradient (two operator products each) and objective evaluations.
//!
//! **Certificate.** Every 10 FISTA iterations (every `it / 50` past 500; the time limit is checked
//! there too) or every Newton step, at the current feasible point `t`. L-BFGS carries its gradient
//! along the steps (`q + tau H p`) and takes the KKT residual of that gradient in the recursion's
//! first pass, every iteration; it forms the certificate when that residual meets the tolerance
//! (to confirm it; the carried gradient then restarts from the exact one), at the time limit, and,
//! where a gap bound can exist (`rho > 0` or every dwell point bounded above), also on FISTA's
//! schedule. So it stops at the first iteration whose exact residual meets the tolerance, not at
//! the next scheduled check. The certificate holds:
//! * KKT residual: `||w - Proj(w - grad_w f)||_2 / N(f)`, relative, in the scaled variables (zero
//!   exactly at the optimum); `N(f)` is `||S (R^T P z)||_2 + rho ||S 1||_2`, the scaled gradient at
//!   zero dwell, shrunk as `sqrt(f)` past a removal depth of 1e5 ([`KktNorm`]);
//! * gap bound, from Lagrangian duality: `0.5 ||a||^2 >= a'y - 0.5 ||y||^2` for every `y`, so with
//!   `y = alpha r` (`r = P(R t - z)`, the current residual) and `v = alpha D t` every feasible `s`
//!   has `f(s) >= d(alpha) = -alpha z'r - 0.5 alpha^2 (||r||^2 + lambda ||D t||^2) +
//!   sum_j min_{l_j <= s_j <= U_j} c_j s_j` with `c = alpha (R^T r + lambda D^T D t) + rho`.
//!   `U_j` is `u_j` or, when `rho > 0`, the level-set bound `l_j + (f(t) - rho 1'l) / rho` (every
//!   minimiser has `rho 1't* <= f(t*) <= f(t)`). `d` is maximised over a few `alpha` in `[0, 1]`
//!   and `f(t) - d` plus a rounding margin is reported ([`super::certificate`]). At `alpha = 1`
//!   this is the Frank-Wolfe gap; with `rho = 0` and no upper bound no finite bound exists unless
//!   every gradient entry is non-negative, and none is reported.
//!
//! The solve stops when the relative gap bound or the relative KKT residual is below the
//! tolerance, and says which ([`ConvergenceCriterion`]). Products with `R` and `R^T` are parallel with fixed-order sums, every other
//! reduction uses fixed chunks: the result is bit-identical for any thread count. No allocation
//! happens inside the iteration loop.

use super::certificate::{gap_bound, ConvergenceCriterion, DualInputs, GapBound};
use super::precond::{CirculantPreconditioner, DwellLattice};
use super::with_solver_operator;
use super::{
    DwellBounds, FirstOrderMethod, Preconditioner, Problem, Settings, Solution, SolverKind, Status,
};
use crate::error::{Error, Result};
use crate::influence::operator::{fill_and_sum, fixed_sum, lane_dot, LinearOperator, CHUNK};
use crate::observer::{IterationInfo, Observer, Stage};
use rayon::prelude::*;
use std::sync::OnceLock;
use std::time::Instant;

/// Iterations between certificate evaluations (each costs one extra `R t` and `R^T r`) at least;
/// past `CHECK_EVERY * CHECK_SPACING` iterations the gap grows to `it / CHECK_SPACING` (at most
/// 2% more iterations past the point the tolerance is met, against 10% extra products at a
/// fixed 10). L-BFGS reports its progress at the same spacing.
const CHECK_EVERY: usize = 10;
/// See [`CHECK_EVERY`].
const CHECK_SPACING: usize = 50;
/// When the iterations report their progress: every [`CHECK_EVERY`] iterations, spaced out as
/// the checks are where a report comes with a certificate.
struct Reports {
    /// The iteration last reported.
    last: usize,
    /// The iteration the next report is due at.
    next: usize,
}

impl Reports {
    fn new(it: usize) -> Self {
        Reports {
            last: it,
            next: it + CHECK_EVERY,
        }
    }

    fn due(&self, it: usize) -> bool {
        it >= self.next
    }

    /// Reports iteration `it` (objective, nm^2, and relative KKT residual) to `observer` and
    /// schedules the next report: `CHECK_EVERY` on, or `it / CHECK_SPACING` where longer and
    /// `spaced` (the certificates' schedule).
    fn report(
        &mut self,
        observer: &dyn Observer,
        it: usize,
        (objective, kkt): (f64, f64),
        spaced: bool,
    ) {
        observer.advance(Stage::Solve, (it - self.last) as u64);
        self.last = it;
        let gap = if spaced {
            CHECK_EVERY.max(it / CHECK_SPACING)
        } else {
            CHECK_EVERY
        };
        self.next = it + gap;
        observer.iteration(&IterationInfo {
            iteration: it,
            objective,
            kkt_residual: Some(kkt),
        });
    }
}

/// Power-iteration steps for the Lipschitz constant.
pub(crate) const POWER_STEPS: usize = 60;
/// Newton-CG's safety factor on the power-iteration estimate (it approaches the largest
/// eigenvalue from below); FISTA uses the estimate itself (see the module documentation).
const NEWTON_L_SAFETY: f64 = 1.1;

/// What the first-order iteration returns.
#[derive(Debug, Clone, PartialEq)]
pub struct FirstOrderResult {
    /// How the iteration ended.
    pub status: Status,
    /// Dwell times, s, inside the bounds.
    pub dwell_s: Vec<f64>,
    /// Iterations taken.
    pub iterations: usize,
    /// Full objective `f(t)` (with the `rho` and `lambda` terms), nm^2.
    pub full_objective: f64,
    /// Relative KKT residual (see the module documentation).
    pub kkt_residual: f64,
    /// Proven upper bound on `f(t) - min f` (nm^2), or why there is none.
    pub objective_gap_bound: GapBound,
    /// The test met, when the status is converged.
    pub converged_by: Option<ConvergenceCriterion>,
}

/// Solves the contract on `problem` with its operator (the assembled `R` or the FFT operator),
/// starting from `start` (projected
/// onto the bounds; default: the lower bounds).
pub fn solve(
    problem: &Problem,
    settings: &Settings,
    observer: &dyn Observer,
    start: Option<&[f64]>,
) -> Result<Solution> {
    settings.validate()?;
    solve_validated(problem, settings, observer, start)
}

/// As [`solve`], with `settings` already validated (by [`crate::setup::Choices::check`] or
/// [`super::solve_from`]).
pub(crate) fn solve_validated(
    problem: &Problem,
    settings: &Settings,
    observer: &dyn Observer,
    start: Option<&[f64]>,
) -> Result<Solution> {
    if settings.min_time {
        return Err(Error::invalid(
            "solver",
            "the minimum-time mode needs the QP solver (solver = \"qp\" or \"auto\")",
        ));
    }
    let t0 = Instant::now();
    let res = with_solver_operator(problem, POWER_STEPS, settings.first_order_tolerance, |op| {
        minimise_validated(
            op,
            problem.z_nm(),
            problem.bounds(),
            problem.rho(),
            problem.lambda(),
            settings,
            start,
            observer,
            problem.dwell_lattice(),
            Some(problem.scaled_hessian_norm()),
        )
    })?;
    let mut dwell_s = res.dwell_s;
    problem.bounds().project(&mut dwell_s);
    let eval = problem.evaluate(&dwell_s)?;
    Ok(Solution {
        status: res.status,
        solver: SolverKind::FirstOrder,
        dwell_s,
        piston_nm: eval.piston_nm,
        objective: eval.objective,
        iterations: res.iterations,
        solve_seconds: t0.elapsed().as_secs_f64(),
        kkt_residual: Some(res.kkt_residual),
        objective_gap_bound: res.objective_gap_bound.value(),
        gap_bound_reason: res.objective_gap_bound.reason(),
        converged_by: res.converged_by,
        min_time: None,
    })
}

/// Work vectors, allocated once.
pub(crate) struct Work {
    pub(crate) t: Vec<f64>,
    pub(crate) rt: Vec<f64>,
    pub(crate) g: Vec<f64>,
    pub(crate) partials: Vec<f64>,
}

/// The problem data the iteration needs.
pub(crate) struct Data<'a> {
    pub(crate) op: &'a dyn LinearOperator,
    pub(crate) z: &'a [f64],
    pub(crate) rho: f64,
    pub(crate) lambda: f64,
    /// `1'z`.
    pub(crate) sum_z: f64,
    /// `R^T z`.
    pub(crate) rtz: Vec<f64>,
    /// `c = R^T 1` (column sums).
    pub(crate) column_sums: Vec<f64>,
    /// Jacobi scale `S`.
    pub(crate) s: Vec<f64>,
    pub(crate) lo_w: Vec<f64>,
    pub(crate) hi_w: Vec<f64>,
}

impl Data<'_> {
    /// Gradient in the scaled variables at `w`: fills `work.t = S w`, `work.rt = P(R t - z)`,
    /// `work.g = grad_t f - rho` (i.e. `R^T r + lambda D^T D t`) and returns `(0.5||r||^2,
    /// 0.5 lambda ||D t||^2)`. The scaled gradient is `S (g + rho)`.
    pub(crate) fn gradient(&self, w: &[f64], work: &mut Work) -> (f64, f64) {
        let half_r2 = self.residual(w, work);
        let half_d2 = self.backward(work);
        (half_r2, half_d2)
    }

    /// `work.t = S w` and `work.g = R^T P (R t - z) + lambda D^T D t` (as [`Data::gradient`]
    /// leaves it) from the normal equations, with one pass over the lattice where the operator
    /// has one (`work.rt` is scratch): `R^T P (R t - z) = R^T R t - R^T z - mean c`,
    /// `c = R^T 1`, `mean = (c't - 1'z) / m`. `with_z = false` drops `z` (Hessian products).
    pub(crate) fn normal_gradient(&self, w: &[f64], with_z: bool, work: &mut Work) {
        let mean = self.raw_normal_product(w, with_z, work);
        let t = &work.t;
        work.g
            .par_iter_mut()
            .enumerate()
            .for_each(|(j, g)| *g = self.gradient_entry(*g, j, mean, with_z, t));
    }

    /// `work.t = S w` and `work.g = R^T R t`; returns `mean = (c't - 1'z) / m` (`1'z` only
    /// `with_z`), what [`Data::gradient_entry`] needs to finish the gradient.
    fn raw_normal_product(&self, w: &[f64], with_z: bool, work: &mut Work) -> f64 {
        let (c, s) = (&self.column_sums, &self.s);
        let ct = fill_and_sum(&mut work.t, &mut work.partials, |j| {
            let t = w[j] * s[j];
            (t, c[j] * t)
        });
        self.op.apply_normal(&work.t, &mut work.rt, &mut work.g);
        let sum_z = if with_z { self.sum_z } else { 0.0 };
        (ct - sum_z) / self.z.len() as f64
    }

    /// Entry `j` of `R^T P (R t - z) + lambda D^T D t` from entry `rtrt` of `R^T R t`:
    /// `rtrt - mean c_j - (R^T z)_j + lambda (D^T D t)_j` (`z` only `with_z`).
    #[inline(always)]
    fn gradient_entry(&self, rtrt: f64, j: usize, mean: f64, with_z: bool, t: &[f64]) -> f64 {
        let mut v = rtrt - mean * self.column_sums[j];
        if with_z {
            v -= self.rtz[j];
        }
        if self.lambda > 0.0 {
            v += self.lambda * dtd(t, j);
        }
        v
    }

    /// `work.t = S w`, `work.rt = P(R t - z)`; returns `0.5 ||rt||^2`.
    pub(crate) fn residual(&self, w: &[f64], work: &mut Work) -> f64 {
        let (m, z) = (self.z.len(), self.z);
        work.t
            .par_iter_mut()
            .zip(w.par_iter().zip(&self.s))
            .for_each(|(t, (w, s))| *t = w * s);
        self.op.apply(&work.t, &mut work.rt);
        let rt = &work.rt;
        let mean = fixed_sum(m, &mut work.partials, |i| rt[i] - z[i]) / m as f64;
        work.rt
            .par_iter_mut()
            .zip(z.par_iter())
            .for_each(|(r, z)| *r = *r - z - mean);
        let rt = &work.rt;
        0.5 * fixed_sum(rt.len(), &mut work.partials, |i| rt[i] * rt[i])
    }

    /// `0.5 lambda ||D t||^2` at `work.t`.
    fn half_smoothing(&self, work: &mut Work) -> f64 {
        if self.lambda <= 0.0 {
            return 0.0;
        }
        let t = &work.t;
        0.5 * self.lambda
            * fixed_sum(t.len().saturating_sub(1), &mut work.partials, |k| {
                (t[k + 1] - t[k]).powi(2)
            })
    }

    /// From `work.t` and `work.rt`: `work.g = R^T rt + lambda D^T D t`; returns
    /// `0.5 lambda ||D t||^2`.
    fn backward(&self, work: &mut Work) -> f64 {
        self.op.apply_transpose(&work.rt, &mut work.g);
        if self.lambda > 0.0 {
            let (t, lam) = (&work.t, self.lambda);
            work.g
                .par_iter_mut()
                .enumerate()
                .for_each(|(j, g)| *g += lam * dtd(t, j));
        }
        self.half_smoothing(work)
    }

    /// `||P z||^2`, the error to remove with its piston taken out (twice the objective at zero
    /// dwell without the `rho` and `lambda` terms); fixed-chunk sums.
    pub(crate) fn centred_z_norm_sq(&self, partials: &mut Vec<f64>) -> f64 {
        let (z, m) = (self.z, self.z.len());
        let mean = fixed_sum(m, partials, |i| z[i]) / m as f64;
        fixed_sum(m, partials, |i| (z[i] - mean).powi(2))
    }

    /// The full objective `f` at `w` (one product with `R`).
    pub(crate) fn objective(&self, w: &[f64], work: &mut Work) -> f64 {
        let half_r2 = self.residual(w, work);
        let half_d2 = self.half_smoothing(work);
        let t = &work.t;
        let sum_t = fixed_sum(t.len(), &mut work.partials, |j| t[j]);
        half_r2 + half_d2 + self.rho * sum_t
    }

    /// Scaled Hessian product `out = S (R^T P R + lambda D^T D) S v`.
    fn hessian_product(&self, v: &[f64], work: &mut Work, out: &mut [f64]) {
        self.hessian_product_dot(v, work, out);
    }

    /// [`Data::hessian_product`] that also returns `v'out`, finishing the product, scaling it and
    /// taking the dot product in one pass (`work.g` is left as scratch).
    fn hessian_product_dot(&self, v: &[f64], work: &mut Work, out: &mut [f64]) -> f64 {
        let mean = self.raw_normal_product(v, false, work);
        let (g, t, s) = (&work.g, &work.t, &self.s);
        fill_and_sum(out, &mut work.partials, |j| {
            let o = s[j] * self.gradient_entry(g[j], j, mean, false, t);
            (o, v[j] * o)
        })
    }

    pub(crate) fn project(&self, w: &mut [f64]) {
        w.par_iter_mut()
            .zip(self.lo_w.par_iter().zip(self.hi_w.par_iter()))
            .for_each(|(w, (lo, hi))| *w = w.max(*lo).min(*hi));
    }
}

impl<'a> Data<'a> {
    /// The scaled problem for `op` with its work vectors and the KKT normalisation
    /// `||S (R^T P z)|| + rho ||S 1||` (floored; see [`KKT_FLOOR_NM`]). `z_nm` has `op`'s rows and
    /// `bounds` its columns (checked by the callers).
    pub(crate) fn prepare(
        op: &'a dyn LinearOperator,
        z_nm: &'a [f64],
        bounds: &DwellBounds,
        rho: f64,
        lambda: f64,
    ) -> (Self, Work, f64) {
        let (m, n) = (op.nrows(), op.ncols());
        // Jacobi scaling from the Hessian diagonal.
        let cn = op.centred_column_norms_sq();
        let s: Vec<f64> = cn
            .iter()
            .enumerate()
            .map(|(j, &c)| {
                let dd = if n == 1 {
                    0.0
                } else if j == 0 || j + 1 == n {
                    1.0
                } else {
                    2.0
                };
                let d = c + lambda * dd;
                if d > 0.0 && d.is_finite() {
                    1.0 / d.sqrt()
                } else {
                    1.0
                }
            })
            .collect();
        let lo_w: Vec<f64> = bounds
            .lower_s()
            .iter()
            .zip(&s)
            .map(|(l, s)| l / s)
            .collect();
        let hi_w: Vec<f64> = (0..n).map(|j| bounds.upper(j) / s[j]).collect();
        let mut work = Work {
            t: vec![0.0; n],
            rt: vec![0.0; m],
            g: vec![0.0; n],
            partials: Vec::with_capacity(m.max(n).div_ceil(4096) + 1),
        };
        // R^T z and R^T 1 for the gradient from the normal equations (`work.rt` holds the ones).
        let (mut rtz, mut column_sums) = (vec![0.0; n], vec![0.0; n]);
        op.apply_transpose(z_nm, &mut rtz);
        work.rt.iter_mut().for_each(|r| *r = 1.0);
        op.apply_transpose(&work.rt, &mut column_sums);
        let data = Data {
            op,
            z: z_nm,
            sum_z: z_nm.iter().sum(),
            rtz,
            column_sums,
            rho,
            lambda,
            s,
            lo_w,
            hi_w,
        };

        // Normalisation of the KKT residual: ||S (R^T P z)|| + rho ||S 1||, with
        // R^T P z = R^T z - (1'z / m) R^T 1.
        let kkt_scale = {
            let mean = data.sum_z / m as f64;
            let a: f64 = (0..n)
                .map(|j| ((data.rtz[j] - mean * data.column_sums[j]) * data.s[j]).powi(2))
                .sum::<f64>()
                .sqrt();
            let b: f64 = data.s.iter().map(|s| s * s).sum::<f64>().sqrt();
            // Floor: the scale of an error of KKT_FLOOR_NM over the map, so that a flat map (a and
            // rho both zero) gives a residual relative to a height far below any measurement
            // instead of rounding noise divided by the smallest float.
            let c: f64 = (0..n)
                .map(|j| (data.column_sums[j] * data.s[j]).powi(2))
                .sum::<f64>()
                .sqrt();
            (a + rho * b).max(KKT_FLOOR_NM * c).max(f64::MIN_POSITIVE)
        };

        (data, work, kkt_scale)
    }
}

/// `(D^T D t)_j` for the first-difference matrix `D` along the path.
pub(crate) fn dtd(t: &[f64], j: usize) -> f64 {
    let mut dd = 0.0;
    if j > 0 {
        dd += t[j] - t[j - 1];
    }
    if j + 1 < t.len() {
        dd -= t[j + 1] - t[j];
    }
    dd
}

/// Below this many rows plus columns the iteration runs on one thread: rayon's per-call cost
/// would dominate (the result is the same bits either way).
const SMALL_PROBLEM: usize = 5_000;

/// Minimises the contract objective for the operator `op` (see the module documentation).
#[allow(clippy::too_many_arguments)]
pub fn minimise(
    op: &dyn LinearOperator,
    z_nm: &[f64],
    bounds: &DwellBounds,
    rho: f64,
    lambda: f64,
    settings: &Settings,
    start: Option<&[f64]>,
    observer: &dyn Observer,
) -> Result<FirstOrderResult> {
    minimise_with(
        op, z_nm, bounds, rho, lambda, settings, start, observer, None,
    )
}

/// As [`minimise`], with the dwell points' lattice when they lie on one: Newton-CG then
/// preconditions its conjugate gradients with the circulant model of `R^T R`
/// ([`super::precond`]) unless the settings ask for Jacobi scaling only.
#[allow(clippy::too_many_arguments)]
pub fn minimise_with(
    op: &dyn LinearOperator,
    z_nm: &[f64],
    bounds: &DwellBounds,
    rho: f64,
    lambda: f64,
    settings: &Settings,
    start: Option<&[f64]>,
    observer: &dyn Observer,
    lattice: Option<&DwellLattice>,
) -> Result<FirstOrderResult> {
    settings.validate()?;
    minimise_validated(
        op, z_nm, bounds, rho, lambda, settings, start, observer, lattice, None,
    )
}

/// As [`minimise_with`], with `settings` already validated; the scaled Hessian's norm is taken
/// from `norm_cache` when it holds one and kept there otherwise ([`Problem`]'s cache).
#[allow(clippy::too_many_arguments)]
fn minimise_validated(
    op: &dyn LinearOperator,
    z_nm: &[f64],
    bounds: &DwellBounds,
    rho: f64,
    lambda: f64,
    settings: &Settings,
    start: Option<&[f64]>,
    observer: &dyn Observer,
    lattice: Option<&DwellLattice>,
    norm_cache: Option<&OnceLock<f64>>,
) -> Result<FirstOrderResult> {
    if op.nrows() + op.ncols() < SMALL_PROBLEM && rayon::current_num_threads() > 1 {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .map_err(|e| Error::Numerical {
                stage: "first-order thread pool",
                why: e.to_string(),
            })?;
        return pool.install(|| {
            minimise_here(
                op, z_nm, bounds, rho, lambda, settings, start, observer, lattice, norm_cache,
            )
        });
    }
    // Run on a worker of the pool: called from outside it, every parallel loop of the iteration
    // would be injected into the pool and waited for on a futex (a few microseconds each, and
    // one thread more than there are workers competing for the cores).
    rayon::scope(|_| {
        minimise_here(
            op, z_nm, bounds, rho, lambda, settings, start, observer, lattice, norm_cache,
        )
    })
}

#[allow(clippy::too_many_arguments)]
fn minimise_here(
    op: &dyn LinearOperator,
    z_nm: &[f64],
    bounds: &DwellBounds,
    rho: f64,
    lambda: f64,
    settings: &Settings,
    start: Option<&[f64]>,
    observer: &dyn Observer,
    lattice: Option<&DwellLattice>,
    norm_cache: Option<&OnceLock<f64>>,
) -> Result<FirstOrderResult> {
    let (m, n) = (op.nrows(), op.ncols());
    if z_nm.len() != m {
        return Err(Error::LengthMismatch {
            what: "z_nm",
            got: z_nm.len(),
            expected: m,
        });
    }
    if bounds.len() != n {
        return Err(Error::LengthMismatch {
            what: "dwell bounds",
            got: bounds.len(),
            expected: n,
        });
    }
    if let Some(s) = start {
        if s.len() != n {
            return Err(Error::LengthMismatch {
                what: "warm start dwell_s",
                got: s.len(),
                expected: n,
            });
        }
    }
    if m == 0 || n == 0 {
        return Err(Error::invalid("problem", "has no map or no dwell points"));
    }
    let began = Instant::now();
    let (data, mut work, kkt_scale) = Data::prepare(op, z_nm, bounds, rho, lambda);

    let mut lambda_hat = scaled_hessian_norm(&data, &mut work, norm_cache);
    if !(lambda_hat.is_finite() && lambda_hat > 0.0) {
        lambda_hat = 1.0;
    }

    let mut x: Vec<f64> = match start {
        Some(t) => t.iter().zip(&data.s).map(|(t, s)| t / s).collect(),
        None => data.lo_w.clone(),
    };
    data.project(&mut x);
    let max_it = settings.first_order_max_iterations;
    observer.start(Stage::Solve, max_it as u64);
    let limits = Limits {
        tol: settings.first_order_tolerance,
        max_it,
        time_limit_s: settings.time_limit_s,
        began,
        kkt_norm: KktNorm {
            at_zero: kkt_scale,
            objective_at_zero: 0.5 * data.centred_z_norm_sq(&mut work.partials),
        },
    };
    let lattice = lattice.filter(|l| l.len() == n);
    let (status, x, it, cert) = match settings.first_order_method {
        FirstOrderMethod::Fista => {
            fista(&data, x, &mut work, bounds, lambda_hat, &limits, observer)
        }
        FirstOrderMethod::NewtonCg => {
            let lip = lambda_hat * NEWTON_L_SAFETY;
            let mut precond = match (settings.preconditioner, lattice) {
                (Preconditioner::Jacobi, _) | (_, None) => None,
                (Preconditioner::Circulant, Some(l)) => circulant(&data, l, &mut work),
            };
            newton_cg(
                &data,
                x,
                &mut work,
                bounds,
                lip,
                &limits,
                observer,
                precond.as_mut(),
            )
        }
        FirstOrderMethod::Lbfgs => {
            let mem = settings
                .lbfgs_memory
                .unwrap_or(if op.products_cheap_per_dwell_point() {
                    super::DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS
                } else {
                    super::DEFAULT_LBFGS_MEMORY
                });
            crate::budget::check_f64s(
                "lbfgs_memory",
                &format!(
                    "{mem} correction pairs: {} vectors of {n} dwell times",
                    2 * mem + 5
                ),
                n as f64,
                (2 * mem + 5) as f64,
            )?;
            projected_lbfgs(
                &data,
                x,
                mem,
                &mut work,
                bounds,
                lambda_hat * NEWTON_L_SAFETY,
                &limits,
                observer,
            )
        }
    };
    observer.finish(Stage::Solve);
    let dwell_s: Vec<f64> = x.iter().zip(&data.s).map(|(w, s)| w * s).collect();
    Ok(FirstOrderResult {
        status,
        dwell_s,
        iterations: it,
        full_objective: cert.f,
        kkt_residual: cert.kkt,
        objective_gap_bound: cert.gap,
        converged_by: match status {
            Status::Converged => limits.met(&cert),
            // Stalled at rounding level with the KKT residual below the square root of the
            // tolerance.
            Status::AlmostConverged => Some(ConvergenceCriterion::KktResidual),
            _ => None,
        },
    })
}

/// Height, nm, below which an error map counts as flat in the KKT normalisation (a femtometre).
const KKT_FLOOR_NM: f64 = 1e-6;

/// Removal depth `f(0) / f(t)` up to which the KKT residual is relative to the scaled gradient
/// at zero dwell alone ([`KktNorm`]).
const DEPTH_KNEE: f64 = 1e5;
/// Removal depth past which the KKT normalisation stops shrinking (a 10,000-fold RMS
/// reduction): beyond it the map is removed to rounding, and a share of what is left means little.
const DEPTH_CAP: f64 = 1e8;

/// The KKT residual's normalisation at objective `f`:
/// `N(f) = N0 sqrt(clamp(DEPTH_KNEE f / f(0), DEPTH_KNEE / DEPTH_CAP, 1))`, `N0 = ||S R^T P z|| +
/// rho ||S 1||` the scaled gradient at zero dwell and `f(0) = 0.5 ||P z||^2`.
///
/// Relative to `N0` alone, the excess `f - f*` left at a given tolerance grows in proportion to
/// the depth `f(0) / f*` (measured from 8e3 to 1.2e6, docs/preconditioning.md): near the
/// optimum `f - f* ~ ||g||^2 / (2 mu)` while `N0^2 ~ f(0)`. Deeper than `DEPTH_KNEE` the
/// normalisation follows `sqrt(f)`, so that the tolerance keeps meaning about the same share of
/// what is left.
#[derive(Debug, Clone, Copy)]
struct KktNorm {
    /// `N0`.
    at_zero: f64,
    /// `f(0)`, nm^2.
    objective_at_zero: f64,
}

impl KktNorm {
    /// `N(f)`; `N0` where the depth is not finite (a flat map).
    fn at(&self, f: f64) -> f64 {
        let share = DEPTH_KNEE * f / self.objective_at_zero;
        if share.is_finite() {
            self.at_zero * share.clamp(DEPTH_KNEE / DEPTH_CAP, 1.0).sqrt()
        } else {
            self.at_zero
        }
    }
}

/// Stopping rule shared by the iterations.
struct Limits {
    tol: f64,
    max_it: usize,
    time_limit_s: f64,
    began: Instant,
    kkt_norm: KktNorm,
}

impl Limits {
    /// The status the certificate earns, if the iteration should stop.
    fn stop(&self, cert: &Certificate) -> Option<Status> {
        if self.met(cert).is_some() {
            Some(Status::Converged)
        } else if self.began.elapsed().as_secs_f64() > self.time_limit_s {
            Some(Status::TimeLimit)
        } else {
            None
        }
    }
}

impl Limits {
    /// The test `cert` passes, if any: the relative gap bound first, then the relative KKT
    /// residual. Non-finite values pass nothing.
    fn met(&self, cert: &Certificate) -> Option<ConvergenceCriterion> {
        if !cert.f.is_finite() {
            return None;
        }
        if let GapBound::Bound(gap) = cert.gap {
            if gap / cert.f.abs().max(f64::MIN_POSITIVE) <= self.tol {
                return Some(ConvergenceCriterion::ObjectiveGap);
            }
        }
        (cert.kkt.is_finite() && cert.kkt <= self.tol).then_some(ConvergenceCriterion::KktResidual)
    }
}

/// What an iteration returns: status, scaled variables, iterations, the final certificate.
type Outcome = (Status, Vec<f64>, usize, Certificate);

/// FISTA with gradient-based adaptive restart from the feasible point `x`.
fn fista(
    data: &Data<'_>,
    mut x: Vec<f64>,
    work: &mut Work,
    bounds: &DwellBounds,
    mut lip: f64,
    limits: &Limits,
    observer: &dyn Observer,
) -> Outcome {
    let n = x.len();
    let rho = data.rho;
    let mut y = x.clone();
    let mut x_new = vec![0.0; n];
    let mut theta = 1.0_f64;
    let mut best_f = f64::INFINITY;
    let max_it = limits.max_it;
    let mut status = Status::MaxIterations;
    let mut cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
    let mut it = 0;
    let mut reports = Reports::new(0);
    while it < max_it {
        it += 1;
        // Projected gradient step from the extrapolated point y and, in the same pass, the
        // gradient-based restart test (y - x_new)'(x_new - x) > 0 (summed in fixed chunks).
        data.normal_gradient(&y, true, work);
        let step = 1.0 / lip;
        let restart_test = {
            let (g, sc, lo, hi) = (&work.g, &data.s, &data.lo_w, &data.hi_w);
            let (y, x) = (&y, &x);
            fill_and_sum(&mut x_new, &mut work.partials, |j| {
                let v = (y[j] - step * sc[j] * (g[j] + rho)).max(lo[j]).min(hi[j]);
                (v, (y[j] - v) * (v - x[j]))
            })
        };
        if restart_test > 0.0 {
            theta = 1.0;
            y.copy_from_slice(&x_new);
        } else {
            let theta_next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
            let beta = (theta - 1.0) / theta_next;
            y.par_iter_mut()
                .zip(x_new.par_iter().zip(x.par_iter()))
                .for_each(|(y, (xn, x))| *y = xn + beta * (xn - x));
            theta = theta_next;
        }
        std::mem::swap(&mut x, &mut x_new);

        if reports.due(it) || it == max_it {
            cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
            reports.report(observer, it, (cert.f, cert.kkt), true);
            if cert.f > best_f * (1.0 + 1e-12) + f64::MIN_POSITIVE {
                // The objective rose: the step was too long. Halve it and restart the momentum.
                lip *= 2.0;
                theta = 1.0;
                y.copy_from_slice(&x);
            }
            best_f = best_f.min(cert.f);
            if let Some(s) = limits.stop(&cert) {
                status = s;
                break;
            }
        }
    }
    if status == Status::MaxIterations && it != reports.last {
        cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
    }
    (status, x, it, cert)
}

/// Conjugate-gradient steps per Newton step at most.
const MAX_CG_STEPS: usize = 200;
/// CG stops when a step gains less than this fraction of its best step's model decrease (the
/// face is then explored enough; More & Toraldo 1991 use the same test). Chosen by measurement on
/// the sample job among 0.01, 0.03, 0.1, 0.25 and 0.5 (fewest products to a KKT residual of 1e-6).
const CG_STALL: f64 = 0.25;
/// Armijo constant of the projected line search.
const ARMIJO: f64 = 1e-4;
/// Halvings of the projected line search at most.
const MAX_HALVINGS: usize = 40;

/// The circulant preconditioner for `data`'s operator on `lattice`, from the column of `R^T R`
/// at the lattice's central point (one product with `R` and one with `R^T`).
fn circulant(
    data: &Data<'_>,
    lattice: &DwellLattice,
    work: &mut Work,
) -> Option<CirculantPreconditioner> {
    let c = CirculantPreconditioner::probe_point(lattice);
    work.t.iter_mut().for_each(|t| *t = 0.0);
    *work.t.get_mut(c)? = 1.0;
    data.op.apply(&work.t, &mut work.rt);
    data.op.apply_transpose(&work.rt, &mut work.g);
    CirculantPreconditioner::new(lattice, &work.g, data.lambda)
}

/// Projected Newton-CG from the feasible point `x` (the steps are in the module documentation),
/// its conjugate gradients preconditioned by `precond` when given.
#[allow(clippy::too_many_arguments)]
fn newton_cg(
    data: &Data<'_>,
    mut x: Vec<f64>,
    work: &mut Work,
    bounds: &DwellBounds,
    lip: f64,
    limits: &Limits,
    observer: &dyn Observer,
    mut precond: Option<&mut CirculantPreconditioner>,
) -> Outcome {
    let n = x.len();
    let rho = data.rho;
    let inv_s: Vec<f64> = data.s.iter().map(|s| 1.0 / s).collect();
    let mut grad = vec![0.0; n];
    let mut free = vec![true; n];
    let mut d = vec![0.0; n];
    let mut r = vec![0.0; n];
    let mut zr = vec![0.0; n];
    let mut p = vec![0.0; n];
    let mut hp = vec![0.0; n];
    let mut x_new = vec![0.0; n];
    let mut status = Status::MaxIterations;
    let mut it = 1;
    let mut cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
    while it < limits.max_it {
        let it_before = it;
        observer.iteration(&IterationInfo {
            iteration: it,
            objective: cert.f,
            kkt_residual: Some(cert.kkt),
        });
        if let Some(s) = limits.stop(&cert) {
            status = s;
            break;
        }
        // Scaled gradient (certificate() left g = grad_t f - rho in work.g).
        grad.par_iter_mut()
            .zip(work.g.par_iter().zip(&data.s))
            .for_each(|(gw, (g, s))| *gw = s * (g + rho));
        // The binding set: variables a projected-gradient step of length 1 / L puts on a bound.
        // They take that step (to the bound); the others the Newton-CG step (Bertsekas 1982).
        let (lo, hi) = (&data.lo_w, &data.hi_w);
        let step = 1.0 / lip;
        free.par_iter_mut().enumerate().for_each(|(j, f)| {
            *f = !binds(grad[j], x[j], lo[j], hi[j], step);
        });
        // Truncated CG on the free variables.
        d.iter_mut().for_each(|v| *v = 0.0);
        r.par_iter_mut()
            .zip(grad.par_iter().zip(free.par_iter()))
            .for_each(|(r, (g, f))| *r = if *f { -g } else { 0.0 });
        let mut precondition = |r: &[f64], zr: &mut [f64]| match precond.as_deref_mut() {
            Some(m) => m.apply_scaled(r, &inv_s, &free, zr),
            None => zr.copy_from_slice(r),
        };
        precondition(&r, &mut zr);
        p.copy_from_slice(&zr);
        let mut rs = fixed_sum(n, &mut work.partials, |j| r[j] * r[j]);
        let mut rz = fixed_sum(n, &mut work.partials, |j| r[j] * zr[j]);
        let target = rs.sqrt() * cert.kkt.sqrt().min(0.5);
        let mut best_decrease = 0.0_f64;
        for _ in 0..MAX_CG_STEPS {
            if rs.sqrt() <= target || it >= limits.max_it {
                break;
            }
            data.hessian_product(&p, work, &mut hp);
            it += 1;
            hp.par_iter_mut().zip(free.par_iter()).for_each(|(h, f)| {
                if !*f {
                    *h = 0.0;
                }
            });
            let php = fixed_sum(n, &mut work.partials, |j| p[j] * hp[j]);
            if !(php > 0.0 && rz > 0.0) {
                break;
            }
            let a = rz / php;
            // Model decrease of this step: 0.5 a r'z (More & Toraldo 1991: stop CG when a step
            // gains less than a fraction of the best step).
            let decrease = 0.5 * a * rz;
            best_decrease = best_decrease.max(decrease);
            d.par_iter_mut()
                .zip(p.par_iter())
                .for_each(|(d, p)| *d += a * p);
            r.par_iter_mut()
                .zip(hp.par_iter())
                .for_each(|(r, h)| *r -= a * h);
            rs = fixed_sum(n, &mut work.partials, |j| r[j] * r[j]);
            if decrease <= CG_STALL * best_decrease {
                break;
            }
            precondition(&r, &mut zr);
            let rz_new = fixed_sum(n, &mut work.partials, |j| r[j] * zr[j]);
            let beta = rz_new / rz;
            rz = rz_new;
            p.par_iter_mut()
                .zip(zr.par_iter())
                .for_each(|(p, z)| *p = z + beta * *p);
        }
        d.par_iter_mut()
            .zip(grad.par_iter().zip(free.par_iter()))
            .for_each(|(d, (g, f))| {
                if !*f {
                    *d = -step * g;
                }
            });
        // Projected line search along d, then along -grad; a projected gradient step of length
        // 1 / L (a guaranteed decrease for an L-smooth f) if both fail.
        let mut accepted = false;
        for direction in [Direction::Newton, Direction::Gradient] {
            if direction == Direction::Gradient {
                d.par_iter_mut()
                    .zip(grad.par_iter())
                    .for_each(|(d, g)| *d = -g);
            }
            let mut alpha = 1.0;
            for _ in 0..MAX_HALVINGS {
                trial(data, &x, &d, alpha, &mut x_new);
                let decrease = fixed_sum(n, &mut work.partials, |j| grad[j] * (x_new[j] - x[j]));
                if !(decrease < 0.0) {
                    break;
                }
                let f_new = data.objective(&x_new, work);
                it += 1;
                if f_new <= cert.f + ARMIJO * decrease {
                    accepted = true;
                    break;
                }
                alpha *= 0.5;
            }
            if accepted {
                break;
            }
        }
        if !accepted {
            trial(data, &x, &d, 1.0 / lip, &mut x_new);
            let f_new = data.objective(&x_new, work);
            it += 1;
            if !(f_new < cert.f) {
                // No descent left at rounding level: the point cannot be improved here.
                status = if cert.kkt <= limits.tol.sqrt() {
                    Status::AlmostConverged
                } else {
                    Status::NumericalError
                };
                break;
            }
        }
        std::mem::swap(&mut x, &mut x_new);
        cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
        it += 1;
        observer.advance(Stage::Solve, (it - it_before) as u64);
    }
    (status, x, it, cert)
}

/// Projected L-BFGS from the feasible point `x`, in the scaled variables. At `x` with scaled
/// gradient `q`, the binding variables (those a projected gradient step of length `1 / L` puts on
/// a bound) take that step; the others `d_F = -H q_F`, `H` the L-BFGS inverse Hessian (Nocedal,
/// Math. Comp. 35, 1980: two-loop recursion) on the stored pairs restricted to the free set
/// (Kim, Sra & Dhillon, "Tackling box-constrained optimization via a new projected quasi-Newton
/// approach", SIAM J. Sci. Comput. 32, 2010). The step `p = Proj(x + d) - x` and one Hessian
/// product `H p` give, the objective being quadratic, the exact minimiser along the segment
/// `x + tau p`, `tau = min(1, -q'p / p'Hp)`, and the new gradient `q + tau H p` without further
/// products (recomputed exactly at every check). Should `p` not descend, the memory is cleared
/// and the projected gradient step taken instead. Memory: `2 mem + 5` vectors of `n` (`mem`
/// pairs) and a free-set mask. The recursion's first pass carries the binding test, the first
/// loop's last update the scaling by `gamma`, and the projection the second loop's last update,
/// so an iteration makes `2 mem + 2` passes over `n`-vectors besides the Hessian product.
#[allow(clippy::too_many_arguments)]
fn projected_lbfgs(
    data: &Data<'_>,
    mut x: Vec<f64>,
    mem: usize,
    work: &mut Work,
    bounds: &DwellBounds,
    lip: f64,
    limits: &Limits,
    observer: &dyn Observer,
) -> Outcome {
    let n = x.len();
    let rho = data.rho;
    let mut s_mem = vec![vec![0.0; n]; mem];
    let mut y_mem = vec![vec![0.0; n]; mem];
    let mut inv_sy = vec![0.0; mem];
    let mut gamma_of = vec![0.0; mem];
    let mut coef = vec![0.0; mem];
    let (mut stored, mut newest) = (0usize, 0usize);
    let mut q = vec![0.0; n];
    let mut d = vec![0.0; n];
    let mut p = vec![0.0; n];
    let mut hp = vec![0.0; n];
    let mut free = vec![true; n];
    let mut pair_partials = Vec::new();
    let mut status = Status::MaxIterations;
    let mut cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
    // Without `rho` or dwell upper bounds there is no gap bound to stop on (see
    // `super::certificate`), so the certificate is formed only when the carried gradient's KKT
    // residual says the tolerance is met, to confirm it.
    let periodic = rho > 0.0 || data.hi_w.iter().all(|h| h.is_finite());
    // The objective carried along the steps, `f + tau q'p + 0.5 tau^2 p'Hp` (exact for the
    // quadratic up to rounding), for the progress reports between certificates.
    let mut carried_f = cert.f;
    let scaled_gradient = |work: &Work, q: &mut [f64]| {
        q.par_iter_mut()
            .zip(work.g.par_iter().zip(&data.s))
            .for_each(|(q, (g, s))| *q = s * (g + rho));
    };
    scaled_gradient(work, &mut q);
    let mut it = 1;
    let mut reports = Reports::new(it);
    // The iteration at which `q` and `cert` were last computed exactly.
    let mut exact_at = it;
    observer.iteration(&IterationInfo {
        iteration: it,
        objective: cert.f,
        kkt_residual: Some(cert.kkt),
    });
    if let Some(st) = limits.stop(&cert) {
        return (st, x, it, cert);
    }
    while it < limits.max_it {
        let step = 1.0 / lip;
        // Two-loop recursion on the free variables; `d` stays zero on the binding ones, so its
        // dot products with the stored pairs are the restricted ones.
        let order = |k: usize| (newest + mem - k) % mem;
        let (mut dot, carried_kkt2) = {
            let newest_s = (stored > 0).then(|| s_mem[order(0)].as_slice());
            free_gradient(
                data,
                &x,
                &q,
                step,
                newest_s,
                &mut free,
                &mut d,
                &mut pair_partials,
            )
        };
        if it != exact_at {
            // The carried gradient `q` follows the exact one to rounding (`q += tau S H S p`
            // each step), so its KKT residual tells when to form the certificate that decides.
            let carried_kkt = carried_kkt2.sqrt() / limits.kkt_norm.at(carried_f);
            let report = reports.due(it);
            let out_of_time = limits.began.elapsed().as_secs_f64() > limits.time_limit_s;
            if carried_kkt <= limits.tol || (periodic && report) || out_of_time {
                cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
                scaled_gradient(work, &mut q);
                exact_at = it;
                carried_f = cert.f;
                reports.report(observer, it, (cert.f, cert.kkt), true);
                if let Some(st) = limits.stop(&cert) {
                    status = st;
                    break;
                }
                // The next pass starts again from the exact gradient.
                continue;
            }
            if report {
                reports.report(observer, it, (carried_f, carried_kkt), false);
            }
        }
        let gamma = if stored > 0 && gamma_of[order(0)] > 0.0 {
            gamma_of[order(0)]
        } else {
            step
        };
        // The first loop's last update also scales `d` by `gamma` and takes the second loop's
        // first dot product (one pass for the two).
        for k in 0..stored {
            let i = order(k);
            let a = inv_sy[i] * dot;
            coef[i] = a;
            let (next, scale) = if k + 1 < stored {
                (s_mem[order(k + 1)].as_slice(), None)
            } else {
                (y_mem[order(k)].as_slice(), Some(gamma))
            };
            dot = masked_axpy_dot(
                &mut d,
                -a,
                &y_mem[i],
                &free,
                scale,
                Some(next),
                &mut work.partials,
            );
        }
        if stored == 0 {
            scale(&mut d, gamma);
        }
        // The second loop's last update is left to the projection's pass: `(c, i)`.
        let mut last_update = None;
        for k in (0..stored).rev() {
            let i = order(k);
            let c = coef[i] - inv_sy[i] * dot;
            if k == 0 {
                last_update = Some((c, i));
                break;
            }
            let next = Some(y_mem[order(k - 1)].as_slice());
            dot = masked_axpy_dot(&mut d, c, &s_mem[i], &free, None, next, &mut work.partials);
        }
        // The projected step, and the projected gradient step when it does not descend.
        // The direction is `-d` on the free variables (`d` the recursion's `H q`, finished here
        // by its last update) and the gradient step on the binding ones.
        let mut qp = match last_update {
            Some((c, i)) => {
                let s_last = &s_mem[i];
                project_along(data, &x, &mut p, &q, &mut work.partials, |j| {
                    if free[j] {
                        -(d[j] + c * s_last[j])
                    } else {
                        -step * q[j]
                    }
                })
            }
            None => project_along(data, &x, &mut p, &q, &mut work.partials, |j| {
                if free[j] {
                    -d[j]
                } else {
                    -step * q[j]
                }
            }),
        };
        if !(qp < 0.0) {
            stored = 0;
            qp = project_along(data, &x, &mut p, &q, &mut work.partials, |j| -step * q[j]);
        }
        if !(qp < 0.0) {
            // No descent along the updated gradient: take the exact one, and stop if that
            // shows none either (stationary to rounding).
            cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
            scaled_gradient(work, &mut q);
            let fresh = it == exact_at;
            exact_at = it;
            carried_f = cert.f;
            if let Some(st) = limits.stop(&cert) {
                status = st;
                break;
            }
            if fresh {
                status = if cert.kkt <= limits.tol.sqrt() {
                    Status::AlmostConverged
                } else {
                    Status::NumericalError
                };
                break;
            }
            continue;
        }
        let php = data.hessian_product_dot(&p, work, &mut hp);
        it += 1;
        let tau = if php > 0.0 { (-qp / php).min(1.0) } else { 1.0 };
        carried_f += tau * qp + 0.5 * tau * tau * php;
        let yy = move_along(&mut x, &mut p, &mut hp, &mut q, tau, &mut work.partials);
        // The new pair: s = tau p, y = tau H p (exact for the quadratic). `p` and `hp` are
        // overwritten in full by the next step, so the pair's vectors are swapped in.
        let sy = tau * tau * php;
        if sy > 0.0 && sy.is_finite() {
            newest = (newest + 1) % mem;
            std::mem::swap(&mut s_mem[newest], &mut p);
            std::mem::swap(&mut y_mem[newest], &mut hp);
            inv_sy[newest] = 1.0 / sy;
            gamma_of[newest] = if yy > 0.0 { sy / yy } else { 0.0 };
            stored = (stored + 1).min(mem);
        }
    }
    if it != exact_at {
        cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
        if status == Status::MaxIterations && limits.met(&cert).is_some() {
            status = Status::Converged;
        }
    }
    observer.advance(Stage::Solve, (it - reports.last) as u64);
    (status, x, it, cert)
}

/// The start of the two-loop recursion, in one pass over fixed chunks: `free[j]` = whether a
/// projected gradient step of length `step` leaves variable `j` off its bounds ([`binds`]),
/// `d = q` on the free variables and 0 on the binding ones. Returns `sum_j w[j] d[j]` (0 without
/// `w`) and the squared projected-gradient norm `sum_j (x_j - Proj(x_j - q_j))^2` at the scaled
/// gradient `q` the iteration carries, the KKT residual's numerator (see [`certificate`]).
#[allow(clippy::too_many_arguments)]
fn free_gradient(
    data: &Data<'_>,
    x: &[f64],
    q: &[f64],
    step: f64,
    w: Option<&[f64]>,
    free: &mut [bool],
    d: &mut [f64],
    partials: &mut Vec<[f64; 2]>,
) -> (f64, f64) {
    let (lo, hi) = (&data.lo_w, &data.hi_w);
    d.par_chunks_mut(CHUNK)
        .zip(free.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(c, (d_chunk, free_chunk))| {
            let (mut acc, mut kkt2) = (0.0, 0.0);
            for (k, (d, fr)) in d_chunk.iter_mut().zip(free_chunk).enumerate() {
                let j = c * CHUNK + k;
                *fr = !binds(q[j], x[j], lo[j], hi[j], step);
                *d = if *fr { q[j] } else { 0.0 };
                if let Some(w) = w {
                    acc += w[j] * *d;
                }
                let moved = x[j] - (x[j] - q[j]).max(lo[j]).min(hi[j]);
                kkt2 += moved * moved;
            }
            [acc, kkt2]
        })
        .collect_into_vec(partials);
    partials
        .iter()
        .fold((0.0, 0.0), |(a, k), p| (a + p[0], k + p[1]))
}

/// `d[j] += a v[j]` on the free variables (`mask`), then `d[j] *= scale` where there is one,
/// then `sum_j w[j] d[j]` (0 without `w`), in one pass over fixed chunks (bit-identical for any
/// thread count, and to the update and [`scale`] one after the other).
fn masked_axpy_dot(
    d: &mut [f64],
    a: f64,
    v: &[f64],
    mask: &[bool],
    scale: Option<f64>,
    w: Option<&[f64]>,
    partials: &mut Vec<f64>,
) -> f64 {
    d.par_chunks_mut(CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let base = c * CHUNK;
            let end = base + chunk.len();
            let (v, mask) = (&v[base..end], &mask[base..end]);
            match scale {
                None => {
                    for ((d, v), &m) in chunk.iter_mut().zip(v).zip(mask) {
                        *d += if m { a * v } else { 0.0 };
                    }
                }
                Some(g) => {
                    for ((d, v), &m) in chunk.iter_mut().zip(v).zip(mask) {
                        *d = (*d + if m { a * v } else { 0.0 }) * g;
                    }
                }
            }
            w.map_or(0.0, |w| lane_dot(chunk, &w[base..end]))
        })
        .collect_into_vec(partials);
    partials.iter().sum()
}

/// `d *= a`.
fn scale(d: &mut [f64], a: f64) {
    d.par_iter_mut().for_each(|d| *d *= a);
}

/// `p *= tau`, `hp *= tau`, `x += p`, `q += hp`; returns `||hp||^2` after the scaling (one pass,
/// fixed chunks).
fn move_along(
    x: &mut [f64],
    p: &mut [f64],
    hp: &mut [f64],
    q: &mut [f64],
    tau: f64,
    partials: &mut Vec<f64>,
) -> f64 {
    x.par_chunks_mut(CHUNK)
        .zip(p.par_chunks_mut(CHUNK))
        .zip(hp.par_chunks_mut(CHUNK).zip(q.par_chunks_mut(CHUNK)))
        .map(|((x, p), (h, q))| {
            let mut acc = 0.0;
            for (((x, p), h), q) in x.iter_mut().zip(p.iter_mut()).zip(h.iter_mut()).zip(q) {
                *p *= tau;
                *h *= tau;
                *x += *p;
                *q += *h;
                acc += *h * *h;
            }
            acc
        })
        .collect_into_vec(partials);
    partials.iter().sum()
}

/// `p = Proj(x + direction) - x`, the direction given entry by entry (so that it is assembled
/// in the projection's pass); returns `q'p`.
fn project_along<F>(
    data: &Data<'_>,
    x: &[f64],
    p: &mut [f64],
    q: &[f64],
    partials: &mut Vec<f64>,
    direction: F,
) -> f64
where
    F: Fn(usize) -> f64 + Sync,
{
    let (lo, hi) = (&data.lo_w, &data.hi_w);
    fill_and_sum(p, partials, |j| {
        let v = (x[j] + direction(j)).max(lo[j]).min(hi[j]) - x[j];
        (v, q[j] * v)
    })
}

/// Whether a projected gradient step of length `step` from `x` along the scaled gradient `g`
/// puts the variable on its bound `lo` or `hi` (the binding set of Bertsekas 1982).
fn binds(g: f64, x: f64, lo: f64, hi: f64, step: f64) -> bool {
    (g > 0.0 && x - lo <= step * g) || (g < 0.0 && hi - x <= -step * g)
}

/// Search directions of a Newton-CG step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Direction {
    Newton,
    Gradient,
}

/// `out = Proj(x + alpha d)`.
fn trial(data: &Data<'_>, x: &[f64], d: &[f64], alpha: f64, out: &mut [f64]) {
    out.par_iter_mut()
        .zip(x.par_iter().zip(d.par_iter()))
        .for_each(|(o, (x, d))| *o = x + alpha * d);
    data.project(out);
}

/// The largest eigenvalue of the scaled Hessian: `cache`'s value when it holds one, else
/// [`power_iteration`]'s (then kept in `cache`).
pub(crate) fn scaled_hessian_norm(
    data: &Data<'_>,
    work: &mut Work,
    cache: Option<&OnceLock<f64>>,
) -> f64 {
    match cache {
        Some(c) => *c.get_or_init(|| power_iteration(data, work)),
        None => power_iteration(data, work),
    }
}

/// Largest eigenvalue of the scaled Hessian `S (R^T P R + lambda D^T D) S` by power iteration
/// (the `rho` term and `z` do not enter: the gradient is affine, so differences are taken).
pub(crate) fn power_iteration(data: &Data<'_>, work: &mut Work) -> f64 {
    let n = data.s.len();
    // A deterministic start with every component present.
    let mut v: Vec<f64> = (0..n)
        .map(|j| 1.0 + 0.5 * (((j * 7919) % 13) as f64 / 13.0))
        .collect();
    let zero = vec![0.0; n];
    let via_normal = data.op.prefers_normal_products();
    // The gradient is H t + b (with S scaling); b from the zero point.
    let b: Vec<f64> = if via_normal {
        zero.clone()
    } else {
        data.gradient(&zero, work);
        work.g.clone()
    };
    let mut est = 0.0;
    let mut hv = vec![0.0; n];
    for _ in 0..POWER_STEPS {
        let norm = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        if norm <= 0.0 || !norm.is_finite() {
            return 0.0;
        }
        v.iter_mut().for_each(|a| *a /= norm);
        if via_normal {
            // Hv (scaled) from the normal product alone.
            data.hessian_product(&v, work, &mut hv);
        } else {
            data.gradient(&v, work);
            // Hv (scaled) = S (g(v) - g(0)).
            hv.iter_mut()
                .enumerate()
                .for_each(|(j, h)| *h = data.s[j] * (work.g[j] - b[j]));
        }
        est = v.iter().zip(&hv).map(|(a, b)| a * b).sum::<f64>();
        std::mem::swap(&mut v, &mut hv);
    }
    est
}

/// The certificate at a feasible point.
#[derive(Debug, Clone, Copy)]
struct Certificate {
    f: f64,
    kkt: f64,
    gap: GapBound,
}

fn certificate(
    data: &Data<'_>,
    w: &[f64],
    work: &mut Work,
    bounds: &DwellBounds,
    kkt_norm: &KktNorm,
) -> Certificate {
    let (half_r2, half_d2) = data.gradient(w, work);
    let n = w.len();
    let rho = data.rho;
    let t = &work.t;
    let g = &work.g;
    let sum_t = fixed_sum(n, &mut work.partials, |j| t[j]);
    let f = half_r2 + half_d2 + rho * sum_t;
    // KKT residual in the scaled variables.
    let kkt2 = fixed_sum(n, &mut work.partials, |j| {
        let gw = data.s[j] * (g[j] + rho);
        let p = (w[j] - gw).max(data.lo_w[j]).min(data.hi_w[j]);
        (w[j] - p).powi(2)
    });
    let kkt = kkt2.sqrt() / kkt_norm.at(f);
    // Dual bound: needs z'r.
    let z = data.z;
    let rt = &work.rt;
    let zr = fixed_sum(z.len(), &mut work.partials, |i| z[i] * rt[i]);
    let inputs = DualInputs {
        f,
        zr,
        quad: 2.0 * (half_r2 + half_d2),
        g,
        sum_t,
        rho,
    };
    let gap = gap_bound(&inputs, bounds, &mut work.partials);
    Certificate { f, kkt, gap }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::operator::SparseOperator;
    use crate::observer::Silent;
    use crate::rng::SplitMix64;
    use nalgebra_sparse::{CooMatrix, CscMatrix};

    /// Agreement of the fused passes with their definitions: rounding of a few terms.
    const FUSED_REL_TOL: f64 = 1e-12;

    /// A dense random `R` (m x n, entries in [0, 1)) as a CSC matrix, and its rows.
    fn random_r(m: usize, n: usize, seed: u64) -> (CscMatrix<f64>, Vec<Vec<f64>>) {
        let mut rng = SplitMix64::new(seed);
        let rows: Vec<Vec<f64>> = (0..m)
            .map(|_| (0..n).map(|_| rng.uniform()).collect())
            .collect();
        let mut coo = CooMatrix::new(m, n);
        for (i, row) in rows.iter().enumerate() {
            for (j, &v) in row.iter().enumerate() {
                coo.push(i, j, v);
            }
        }
        (CscMatrix::from(&coo), rows)
    }

    /// The Hessian product's one fused pass gives `S (R^T P R + lambda D^T D) S v` and `v'out`,
    /// against the product formed entry by entry (`P = I - 11'/m`, `D` the first differences).
    #[test]
    fn the_fused_hessian_product_is_the_scaled_hessian() {
        let (m, n, lambda) = (9, 6, 0.3);
        let (csc, rows) = random_r(m, n, 7);
        let op = SparseOperator::new(&csc);
        let z: Vec<f64> = (0..m).map(|i| (i as f64).sin()).collect();
        let bounds = DwellBounds::new(vec![0.0; n], None).unwrap();
        let (data, mut work, _) = Data::prepare(&op, &z, &bounds, 0.0, lambda);
        let v: Vec<f64> = (0..n).map(|j| 1.0 - 0.2 * j as f64).collect();
        let mut out = vec![0.0; n];
        let vho = data.hessian_product_dot(&v, &mut work, &mut out);
        // Reference: t = S v, r = P R t, h = R^T r + lambda D^T D t, out = S h.
        let t: Vec<f64> = (0..n).map(|j| data.s[j] * v[j]).collect();
        let rt: Vec<f64> = rows
            .iter()
            .map(|row| row.iter().zip(&t).map(|(a, b)| a * b).sum())
            .collect();
        let mean = rt.iter().sum::<f64>() / m as f64;
        let mut expected_vho = 0.0;
        for j in 0..n {
            let h: f64 =
                (0..m).map(|i| rows[i][j] * (rt[i] - mean)).sum::<f64>() + lambda * dtd(&t, j);
            let o = data.s[j] * h;
            assert!(
                (out[j] - o).abs() <= FUSED_REL_TOL * o.abs().max(1.0),
                "{j}"
            );
            expected_vho += v[j] * o;
        }
        assert!((vho - expected_vho).abs() <= FUSED_REL_TOL * expected_vho.abs());
        // The gradient of the normal equations without `z`, scaled, is the same product.
        data.normal_gradient(&v, false, &mut work);
        for ((s, g), o) in data.s.iter().zip(&work.g).zip(&out) {
            assert_eq!(s * g, *o);
        }
    }

    /// The KKT normalisation is the gradient at zero dwell down to the knee's depth, shrinks as
    /// `sqrt(f)` past it, and stops shrinking at the cap; a flat map keeps `N0`.
    #[test]
    fn the_kkt_normalisation_follows_what_is_left_past_the_knee() {
        const REL: f64 = 1e-15;
        let norm = KktNorm {
            at_zero: 2.0,
            objective_at_zero: 1e6,
        };
        let at_knee = 1e6 / DEPTH_KNEE;
        assert_eq!(norm.at(2e6), 2.0);
        assert_eq!(norm.at(1e6), 2.0);
        assert_eq!(norm.at(at_knee), 2.0);
        // 100 times deeper: a tenth of the normalisation.
        assert!((norm.at(at_knee / 100.0) - 0.2).abs() <= REL * 0.2);
        let floor = 2.0 * (DEPTH_KNEE / DEPTH_CAP).sqrt();
        for f in [1e6 / DEPTH_CAP, 1e6 / DEPTH_CAP / 10.0, 0.0] {
            assert!((norm.at(f) - floor).abs() <= REL * floor, "{f}");
        }
        let flat = KktNorm {
            at_zero: 2.0,
            objective_at_zero: 0.0,
        };
        assert_eq!(flat.at(0.0), 2.0);
        assert_eq!(flat.at(1.0), 2.0);
    }

    /// Without a gap bound (`rho = 0`, no `v_min`) projected L-BFGS forms its certificate only
    /// when the KKT residual of the gradient it carries meets the tolerance: it stops at the first
    /// iteration whose exact residual does. That iteration is found by running the same
    /// (deterministic) iteration for 1, 2, ... steps, each run ending with an exact certificate.
    #[test]
    fn lbfgs_stops_at_the_first_certified_iteration() {
        const TOL: f64 = 1e-10;
        let (m, n) = (90, 40);
        let (csc, _) = random_r(m, n, 5);
        let op = SparseOperator::new(&csc);
        let mut rng = SplitMix64::new(9);
        let z: Vec<f64> = (0..m).map(|_| 5.0 + rng.normal()).collect();
        let bounds = DwellBounds::new(vec![0.0; n], None).unwrap();
        let run = |max_it| {
            let settings = Settings {
                first_order_tolerance: TOL,
                first_order_max_iterations: max_it,
                ..Settings::default()
            };
            minimise(&op, &z, &bounds, 0.0, 0.0, &settings, None, &Silent).unwrap()
        };
        let full = run(100_000);
        assert_eq!(full.status, Status::Converged);
        assert!(full.kkt_residual <= TOL, "{}", full.kkt_residual);
        assert!(matches!(full.objective_gap_bound, GapBound::Unavailable(_)));
        let first = (1..=full.iterations)
            .find(|&k| run(k).kkt_residual <= TOL)
            .unwrap();
        assert_eq!(full.iterations, first);
        // Not a case the former fixed spacing of certificates would have met by chance.
        assert!(
            first > CHECK_EVERY + 1 && (first - 1) % CHECK_EVERY != 0,
            "{first}"
        );
    }

    /// The recursion's first pass marks as binding exactly what [`binds`] says and starts from
    /// `q` on the free set; the projection of a direction given entry by entry is
    /// `min(max(x + d, lo), hi) - x`, and its returned dot product `q'p`.
    #[test]
    fn the_fused_recursion_passes_follow_their_definitions() {
        let n = 3 * CHUNK + 17;
        let (csc, _) = random_r(2, n, 11);
        let op = SparseOperator::new(&csc);
        let z = [1.0, -1.0];
        let upper: Vec<f64> = (0..n).map(|j| 1.0 + (j % 5) as f64).collect();
        let bounds = DwellBounds::new(vec![0.0; n], Some(upper)).unwrap();
        let (data, mut work, _) = Data::prepare(&op, &z, &bounds, 0.0, 0.0);
        let mut rng = SplitMix64::new(3);
        // Points on a bound, near one and inside; gradients of both signs.
        let x: Vec<f64> = (0..n)
            .map(|j| match j % 4 {
                0 => data.lo_w[j],
                1 => data.hi_w[j],
                2 => data.lo_w[j] + 1e-3 * rng.uniform(),
                _ => 0.5 * (data.lo_w[j] + data.hi_w[j]),
            })
            .collect();
        let q: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
        let w: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
        let step = 0.01;
        let (mut free, mut d) = (vec![false; n], vec![f64::NAN; n]);
        let mut pairs = Vec::new();
        let (dot, kkt2) =
            free_gradient(&data, &x, &q, step, Some(&w), &mut free, &mut d, &mut pairs);
        let (mut expected_dot, mut expected_kkt2) = (0.0, 0.0);
        for j in 0..n {
            let (lo, hi) = (data.lo_w[j], data.hi_w[j]);
            let binding = binds(q[j], x[j], lo, hi, step);
            assert_eq!(free[j], !binding, "{j}");
            assert_eq!(d[j], if binding { 0.0 } else { q[j] }, "{j}");
            expected_dot += w[j] * d[j];
            // The projected gradient: the full step, or the distance to the bound it hits.
            let moved = if q[j] > 0.0 {
                q[j].min(x[j] - lo)
            } else {
                q[j].max(x[j] - hi)
            };
            expected_kkt2 += moved * moved;
        }
        assert!(free.contains(&true) && free.contains(&false));
        assert!((dot - expected_dot).abs() <= FUSED_REL_TOL * expected_dot.abs());
        assert!((kkt2 - expected_kkt2).abs() <= FUSED_REL_TOL * expected_kkt2);
        let hq: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
        let direction = |j: usize| if free[j] { -hq[j] } else { -step * q[j] };
        let mut p = vec![0.0; n];
        let qp = project_along(&data, &x, &mut p, &q, &mut work.partials, direction);
        let (mut expected_qp, mut clipped) = (0.0, 0);
        for j in 0..n {
            let (lo, hi) = (data.lo_w[j], data.hi_w[j]);
            let inside = (x[j] + direction(j)).clamp(lo, hi);
            assert_eq!(p[j], inside - x[j], "{j}");
            clipped += usize::from(inside != x[j] + direction(j));
            expected_qp += q[j] * p[j];
        }
        assert!(clipped > 0 && clipped < n);
        assert!((qp - expected_qp).abs() <= FUSED_REL_TOL * expected_qp.abs());
        // The masked update with the scaling folded in: the same bits as the update, then the
        // scaling, then the dot product, one after the other.
        let (a, gamma) = (-0.37, 1.9);
        let mut fused = d.clone();
        let fused_dot = masked_axpy_dot(
            &mut fused,
            a,
            &hq,
            &free,
            Some(gamma),
            Some(&w),
            &mut work.partials,
        );
        let mut apart = d.clone();
        masked_axpy_dot(&mut apart, a, &hq, &free, None, None, &mut work.partials);
        scale(&mut apart, gamma);
        for j in 0..n {
            let want = if free[j] {
                (d[j] + a * hq[j]) * gamma
            } else {
                d[j] * gamma
            };
            assert_eq!(fused[j].to_bits(), apart[j].to_bits(), "{j}");
            assert_eq!(fused[j], want, "{j}");
        }
        let apart_dot = masked_axpy_dot(
            &mut apart,
            0.0,
            &hq,
            &free,
            None,
            Some(&w),
            &mut work.partials,
        );
        assert_eq!(fused_dot.to_bits(), apart_dot.to_bits());
    }
}
