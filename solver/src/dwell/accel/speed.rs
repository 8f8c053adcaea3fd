//! Acceleration limits at scale: accelerated projected gradient in squared speed.
//!
//! In the squared speed `u_j = v_j^2 = (ds_j / t_j)^2` the limit along a line is a bounded
//! difference, `|u_{j+1} - u_j| <= 2 a_max s_j`, and the feed limits are a box: the feasible set
//! `C` is a polyhedron made of one chain per line, onto which [`super::chain`] projects exactly in
//! linear time. The objective is the contract's quadratic in the dwell times `t`, so the method
//! works in `t` (Jacobi-scaled, `t = S w`, as [`crate::dwell::first_order`]) and maps each step
//! into squared speed to project:
//!
//! ```text
//! w_hat = y - grad_w f(y) / L                            gradient step from the extrapolated y
//! z_hat = u(y) + J (w_hat - y),   J = du/dw = -2 u S / t  squared speed, linearised at y
//! z     = argmin_{z in C_y} sum_j (z_j - z_hat_j)^2 / J_j^2   exact chain projection
//! w_new = y + (z - u(y)) / J
//! ```
//!
//! `C_y` is `C` with the feed box replaced by its image under the linearisation (so `w_new` stays
//! inside the dwell bounds). This is the projection of `w_hat`, in the scaled Euclidean metric,
//! onto the constraint set linearised at `y`: the projected gradient method of sequential
//! linearisation (the gradient-projection form of SQP, Bertsekas, *Nonlinear Programming*, 3rd ed.,
//! §2.3 and §4.3); its fixed points are exactly the KKT points of the limited problem, and the
//! violation of the true constraint is second order in the step. Momentum is FISTA's (Beck &
//! Teboulle 2009), monotone: a step that raises `f` is refused, the momentum restarts, and if the
//! step had no momentum `L` doubles. The iteration stops when the relative KKT residual
//! `||w - P_{C_w}(w - grad_w f)|| / (||S R^T P z|| q)` is below the tolerance, with
//! `q = ||P r|| / ||P z||` the residual left over the error to remove (`r = R t - z`), clamped to
//! `[Q_MIN, 1]`:
//! the gradient's scale shrinks with the residual, so a map corrected a hundredfold is solved to
//! the same relative accuracy as one corrected twofold. The result is then
//! moved onto the true `C` by the exact projection of `u(t)` in the same metric (a change of the
//! order of the remaining violation), so the written dwell times meet the limit exactly.
//!
//! Each iteration costs one normal product `R^T R t` (the gradient of the new iterate; the
//! gradient is affine in `t`, so the extrapolated point's is the same combination of gradients
//! unless the bounds clip it) and one chain projection (`O(n)`, parallel over lines). A step is
//! accepted when `f(t_new) - f(t) = (t_new - t)' (g + g_new) / 2 <= 0`, exact for the quadratic
//! and free of the cancellation a difference of two objective values suffers; the objective
//! itself is evaluated through `R` only at the KKT checks. Normal products go through the Gram
//! matrix where the assembled `R` has one ([`crate::influence::GramMatrix`]), through one pass
//! over the lattice for the FFT operator, and as `R^T (R t)` otherwise, so the assembled, FFT and
//! spreading operators and curved parts all serve.

use super::chain::{project_chain, Chain, ChainScratch};
use super::LineCaps;
use crate::dwell::first_order::{scaled_hessian_norm, Data, Work};
use crate::dwell::Status;
use crate::influence::operator::{fill_and_sum, fixed_sum};
use crate::observer::{IterationInfo, Observer, Stage};
use rayon::prelude::*;
use std::sync::OnceLock;
use std::time::Instant;

/// Iterations between KKT checks.
const CHECK_EVERY: usize = 10;

/// Smallest residual-to-error ratio `q` in the KKT residual's scale (module documentation): a
/// residual below 1% of the error is solved to 100 times the tolerance's accuracy, not more.
const Q_MIN: f64 = 0.01;

/// Stopping rule of the iteration.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SpeedLimits {
    /// Relative KKT residual to reach.
    pub tolerance: f64,
    /// Gradient steps at most.
    pub max_steps: usize,
    /// Wall-clock limit, s.
    pub time_limit_s: f64,
}

/// What the iteration returns.
#[derive(Debug, Clone)]
pub(crate) struct SpeedResult {
    /// How it ended.
    pub status: Status,
    /// Dwell times, s, meeting the limit.
    pub dwell_s: Vec<f64>,
    /// Gradient steps taken.
    pub iterations: usize,
    /// The last relative KKT residual.
    pub kkt_residual: f64,
}

/// Points of a line weighing more than this times its lightest point are fixed at their target
/// in the projection: the exact projection would move them by at most about `1 / PIN_RATIO` of
/// the lightest point's move, and keeping them in would cost the chain projection its precision
/// ([`super::chain`]). They are the slow points, whose squared speed is tiny. Two fixed points
/// may be further apart than the caps between them allow (a slow point a few segments from one
/// at the fastest feed, which is heavy too when the line's lightest point barely reaches the
/// map): the exact projection then moves the lighter of the two, so that one is freed (its
/// weight capped at `PIN_RATIO` times the lightest) and the line projected again, until no
/// fixed points conflict.
const PIN_RATIO: f64 = 1e10;

/// One line's chain projection: its index range and scratch (kept between iterations).
struct Line {
    start: usize,
    end: usize,
    scratch: ChainScratch,
    out: Vec<f64>,
    pinned: Vec<bool>,
    weight: Vec<f64>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    cuts: usize,
}

/// The chain data of every point, refilled at each projection.
struct Projection {
    lines: Vec<Line>,
    target: Vec<f64>,
    weight: Vec<f64>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    z: Vec<f64>,
    cap: Vec<f64>,
    linked: Vec<bool>,
}

impl Projection {
    fn new(kin: &LineCaps) -> Self {
        let n = kin.ds.len();
        let mut lines = Vec::new();
        let mut start = 0;
        for j in 0..n {
            let last = j + 1 == n || !kin.constrained[j];
            if last {
                lines.push(Line {
                    start,
                    end: j + 1,
                    scratch: ChainScratch::default(),
                    out: vec![0.0; j + 1 - start],
                    pinned: Vec::with_capacity(j + 1 - start),
                    weight: vec![0.0; j + 1 - start],
                    lower: vec![0.0; j + 1 - start],
                    upper: vec![0.0; j + 1 - start],
                    cuts: 0,
                });
                start = j + 1;
            }
        }
        Self {
            lines,
            target: vec![0.0; n],
            weight: vec![0.0; n],
            lower: vec![0.0; n],
            upper: vec![0.0; n],
            z: vec![0.0; n],
            cap: kin.cap.clone(),
            linked: kin.constrained.clone(),
        }
    }

    /// Fills each point's target, weight and box from `f(j)`; a point with a zero-length stretch
    /// has no speed and enters its chain fixed at `u = 0`.
    fn fill(&mut self, ds: &[f64], f: impl Fn(usize) -> (f64, f64, f64, f64) + Sync) {
        self.target
            .par_iter_mut()
            .zip(self.weight.par_iter_mut())
            .zip(self.lower.par_iter_mut().zip(self.upper.par_iter_mut()))
            .enumerate()
            .for_each(|(j, ((tg, wt), (l, h)))| {
                (*tg, *wt, *l, *h) = if ds[j] == 0.0 {
                    (0.0, 1.0, 0.0, 0.0)
                } else {
                    f(j)
                };
            });
    }

    /// Projects `target` (weights, boxes filled) onto the chains into `self.z`; returns cuts.
    fn run(&mut self) -> usize {
        let (target, weight, lower, upper, cap, linked) = (
            &self.target,
            &self.weight,
            &self.lower,
            &self.upper,
            &self.cap,
            &self.linked,
        );
        self.lines.par_iter_mut().for_each(|line| {
            let (a, b) = (line.start, line.end);
            let lightest = weight[a..b].iter().copied().fold(f64::INFINITY, f64::min);
            let heaviest = PIN_RATIO * lightest;
            line.pinned.clear();
            line.pinned
                .extend(weight[a..b].iter().map(|&w| w > heaviest));
            // Each round frees at least one fixed point, so the rounds end.
            loop {
                for k in 0..b - a {
                    let (w, l, h) = (weight[a + k], lower[a + k], upper[a + k]);
                    if line.pinned[k] {
                        let fixed = target[a + k].max(l).min(h);
                        line.weight[k] = lightest;
                        line.lower[k] = fixed;
                        line.upper[k] = fixed;
                    } else {
                        line.weight[k] = w.min(heaviest);
                        line.lower[k] = l;
                        line.upper[k] = h;
                    }
                }
                let chain = Chain {
                    target: &target[a..b],
                    weight: &line.weight,
                    lower: &line.lower,
                    upper: &line.upper,
                    cap: &cap[a..b.saturating_sub(1).max(a)],
                    linked: &linked[a..b.saturating_sub(1).max(a)],
                };
                line.cuts = project_chain(&chain, &mut line.scratch, &mut line.out);
                if line.cuts == 0 {
                    break;
                }
                // At each cut `k -> k + 1`: the fixed point there and the last one before it
                // conflict; the lighter is freed.
                let mut freed = false;
                for k in line.scratch.cut_segments() {
                    let after = Some(k + 1).filter(|&i| line.pinned[i]);
                    let before = (0..=k).rev().find(|&i| line.pinned[i]);
                    let lighter = match (before, after) {
                        (Some(i), Some(j)) => {
                            Some(if weight[a + i] <= weight[a + j] { i } else { j })
                        }
                        (i, j) => i.or(j),
                    };
                    if let Some(i) = lighter {
                        freed |= std::mem::replace(&mut line.pinned[i], false);
                    }
                }
                if !freed {
                    break;
                }
            }
        });
        let mut cuts = 0;
        for line in &self.lines {
            self.z[line.start..line.end].copy_from_slice(&line.out);
            cuts += line.cuts;
        }
        cuts
    }
}

/// Squared speed `u = (ds / t)^2` and its derivative with respect to the scaled variable,
/// `du/dw = -2 u s / t`, at `t = s w`.
fn speed_and_slope(ds: f64, s: f64, w: f64) -> (f64, f64) {
    let t = s * w;
    let u = (ds / t) * (ds / t);
    (u, -2.0 * u * s / t)
}

/// State of the iteration beyond [`Data`].
struct Iteration<'a> {
    data: &'a Data<'a>,
    kin: &'a LineCaps,
    proj: Projection,
}

impl Iteration<'_> {
    /// Projects `w_hat` onto the constraint set linearised at `y` (scaled variables), into `out`.
    fn project_linearised(&mut self, y: &[f64], w_hat: &[f64], out: &mut [f64]) {
        let (ds, s, lo, hi) = (&self.kin.ds, &self.data.s, &self.data.lo_w, &self.data.hi_w);
        let p = &mut self.proj;
        p.fill(ds, |j| {
            let (u, d) = speed_and_slope(ds[j], s[j], y[j]);
            // d < 0: the upper dwell bound gives the lower squared speed.
            (
                u + d * (w_hat[j] - y[j]),
                (1.0 / (d * d)).min(1e300),
                u + d * (hi[j] - y[j]),
                u + d * (lo[j] - y[j]),
            )
        });
        p.run();
        let z = &p.z;
        out.par_iter_mut().enumerate().for_each(|(j, o)| {
            *o = if ds[j] == 0.0 {
                w_hat[j]
            } else {
                let (u, d) = speed_and_slope(ds[j], s[j], y[j]);
                y[j] + (z[j] - u) / d
            }
            .max(lo[j])
            .min(hi[j]);
        });
    }

    /// Moves `w` onto the true constraint set: the exact projection of `u(t)` onto `C` in the
    /// metric of the linearisation at `w` (boxes `[(ds / t_max)^2, (ds / t_min)^2]`).
    fn retract(&mut self, w: &mut [f64]) {
        let (ds, s, lo, hi) = (&self.kin.ds, &self.data.s, &self.data.lo_w, &self.data.hi_w);
        let p = &mut self.proj;
        {
            let w = &*w;
            p.fill(ds, |j| {
                let (u, d) = speed_and_slope(ds[j], s[j], w[j]);
                let t_max = s[j] * hi[j];
                let l = if t_max.is_finite() {
                    (ds[j] / t_max).powi(2)
                } else {
                    0.0
                };
                (
                    u,
                    (1.0 / (d * d)).min(1e300),
                    l,
                    (ds[j] / (s[j] * lo[j])).powi(2),
                )
            });
        }
        p.run();
        let z = &p.z;
        w.par_iter_mut().enumerate().for_each(|(j, wj)| {
            if ds[j] > 0.0 {
                let floor = (ds[j] / (s[j] * *wj) * 1e-3).powi(2);
                let t = ds[j] / z[j].max(floor).sqrt();
                *wj = (t / s[j]).max(lo[j]).min(hi[j]);
            }
        });
    }
}

/// The gradient `grad_t f = R^T P (R t - z) + lambda D^T D t + rho` at the scaled point `w`
/// (`t = S w`) into `g`, from one normal product ([`Data::normal_gradient`]: through the Gram
/// matrix where the operator holds one).
fn gradient(data: &Data<'_>, w: &[f64], work: &mut Work, g: &mut [f64]) {
    data.normal_gradient(w, true, work);
    let rho = data.rho;
    g.par_iter_mut()
        .zip(work.g.par_iter())
        .for_each(|(g, wg)| *g = wg + rho);
}

/// The contract's value at the scaled point `w` from one product with `R`, and `||P r||`
/// (`r = R t - z`).
fn exact_value(data: &Data<'_>, w: &[f64], work: &mut Work) -> (f64, f64) {
    let f = data.objective(w, work);
    let r = &work.rt;
    let pr = fixed_sum(r.len(), &mut work.partials, |i| r[i] * r[i]).sqrt();
    (f, pr)
}

/// `f(b) - f(a)` of the quadratic contract from the gradients at both ends:
/// `(t_b - t_a)' (g_a + g_b) / 2`, exact for a quadratic (scaled points, `t = S w`). Its rounding
/// is relative to the change, not to `f`.
fn change(
    s: &[f64],
    (wa, ga): (&[f64], &[f64]),
    (wb, gb): (&[f64], &[f64]),
    partials: &mut Vec<f64>,
) -> f64 {
    0.5 * fixed_sum(s.len(), partials, |j| {
        s[j] * (wb[j] - wa[j]) * (ga[j] + gb[j])
    })
}

/// Minimises the contract under the acceleration limit from `start` (dwell times, s, inside the
/// bounds); see the module documentation. The step's Lipschitz constant comes from `norm_cache`
/// when an earlier solve on the same problem left it there.
#[allow(clippy::too_many_arguments)]
pub(crate) fn minimise(
    data: &Data<'_>,
    work: &mut Work,
    kkt_scale: f64,
    kin: &LineCaps,
    start: &[f64],
    limits: &SpeedLimits,
    observer: &dyn Observer,
    norm_cache: Option<&OnceLock<f64>>,
) -> SpeedResult {
    let began = Instant::now();
    let n = start.len();
    let mut it_state = Iteration {
        data,
        kin,
        proj: Projection::new(kin),
    };
    let mut lip = scaled_hessian_norm(data, work, norm_cache);
    if !(lip.is_finite() && lip > 0.0) {
        lip = 1.0;
    }
    let s = &data.s;
    // Scaled start on the true set.
    let mut x: Vec<f64> = start.iter().zip(s).map(|(t, s)| t / s).collect();
    data.project(&mut x);
    it_state.retract(&mut x);
    let pz_norm = data.centred_z_norm_sq(&mut work.partials).sqrt();
    let mut g_x = vec![0.0; n];
    gradient(data, &x, work, &mut g_x);
    let mut x_prev = x.clone();
    let mut g_prev = g_x.clone();
    let mut y = x.clone();
    let mut g_y = vec![0.0; n];
    let mut w_hat = vec![0.0; n];
    let mut x_new = vec![0.0; n];
    let mut g_new = vec![0.0; n];
    let mut theta = 1.0_f64;
    let mut beta = 0.0_f64;
    let mut kkt = f64::INFINITY;
    let mut status = Status::MaxIterations;
    let mut it = 0;
    observer.start(Stage::Loop, limits.max_steps as u64);
    while it < limits.max_steps {
        it += 1;
        // Extrapolated point, clipped to the bounds, and its gradient (affine in the point).
        let clipped = {
            let (x, xp, lo, hi) = (&x, &x_prev, &data.lo_w, &data.hi_w);
            fill_and_sum(&mut y, &mut work.partials, |j| {
                let raw = x[j] + beta * (x[j] - xp[j]);
                let v = raw.max(lo[j]).min(hi[j]);
                (v, (v - raw).abs())
            }) > 0.0
        };
        if beta == 0.0 {
            g_y.copy_from_slice(&g_x);
        } else if clipped {
            gradient(data, &y, work, &mut g_y);
        } else {
            g_y.par_iter_mut()
                .zip(g_x.par_iter().zip(g_prev.par_iter()))
                .for_each(|(g, (a, b))| *g = a + beta * (a - b));
        }
        let step = 1.0 / lip;
        w_hat
            .par_iter_mut()
            .zip(y.par_iter().zip(g_y.par_iter().zip(s.par_iter())))
            .for_each(|(wh, (y, (g, s)))| *wh = y - step * s * g);
        it_state.project_linearised(&y, &w_hat, &mut x_new);
        gradient(data, &x_new, work, &mut g_new);
        let df = change(s, (&x, &g_x), (&x_new, &g_new), &mut work.partials);
        if df <= 0.0 {
            std::mem::swap(&mut x_prev, &mut x);
            std::mem::swap(&mut x, &mut x_new);
            std::mem::swap(&mut g_prev, &mut g_x);
            std::mem::swap(&mut g_x, &mut g_new);
            let theta_next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
            beta = (theta - 1.0) / theta_next;
            theta = theta_next;
        } else {
            // Refused: restart the momentum; without momentum the step was too long.
            if beta == 0.0 {
                lip *= 2.0;
            }
            beta = 0.0;
            theta = 1.0;
            x_prev.copy_from_slice(&x);
            g_prev.copy_from_slice(&g_x);
        }
        if it % CHECK_EVERY == 0 || it == limits.max_steps {
            // The value through R and the residual's share of the error.
            let (fx, pr_norm) = exact_value(data, &x, work);
            let q = if pz_norm > 0.0 {
                (pr_norm / pz_norm).clamp(Q_MIN, 1.0)
            } else {
                1.0
            };
            kkt = kkt_residual(&mut it_state, &x, &g_x, &mut w_hat, &mut x_new, work)
                / (kkt_scale * q);
            observer.advance(Stage::Loop, CHECK_EVERY as u64);
            observer.iteration(&IterationInfo {
                iteration: it,
                objective: fx,
                kkt_residual: Some(kkt),
            });
            if kkt <= limits.tolerance {
                status = Status::Converged;
                break;
            }
            if began.elapsed().as_secs_f64() > limits.time_limit_s {
                status = Status::TimeLimit;
                break;
            }
            // Cancelled: the caller returns `Error::Cancelled`, not this result.
            if observer.cancelled() {
                status = Status::Stalled;
                break;
            }
        }
    }
    observer.finish(Stage::Loop);
    it_state.retract(&mut x);
    let dwell_s: Vec<f64> = x.iter().zip(s).map(|(w, s)| w * s).collect();
    SpeedResult {
        status,
        dwell_s,
        iterations: it,
        kkt_residual: kkt,
    }
}

/// Unnormalised KKT residual at `x` with gradient `g_x` (unscaled):
/// `||x - P_x(x - S g_x)||`, with `P_x` the projection onto the constraint set linearised at
/// `x`; the caller divides by `kkt_scale q` (module documentation).
fn kkt_residual(
    state: &mut Iteration<'_>,
    x: &[f64],
    g_x: &[f64],
    w_hat: &mut [f64],
    out: &mut [f64],
    work: &mut Work,
) -> f64 {
    let s = &state.data.s;
    w_hat
        .par_iter_mut()
        .zip(x.par_iter().zip(g_x.par_iter().zip(s.par_iter())))
        .for_each(|(wh, (x, (g, s)))| *wh = x - s * g);
    state.project_linearised(x, w_hat, out);
    fixed_sum(x.len(), &mut work.partials, |j| (x[j] - out[j]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative rounding allowed on a cap the projection holds.
    const CAP_ROUNDING: f64 = 1e-12;

    /// A point at the fastest feed next to a slow one, both far heavier than the line's lightest
    /// point (one that barely reaches the map): fixing both at their targets would leave them out
    /// of each other's reach. The exact projection moves the lighter of the two onto the cap and
    /// keeps the heavier where it is; the line is projected without a cut.
    #[test]
    fn heavy_points_out_of_each_others_reach_are_projected_onto_the_cap() {
        const CAP: f64 = 2000.0;
        const FAST: f64 = 2500.0;
        let kin = LineCaps {
            ds: vec![1.0; 4],
            cap: vec![CAP; 3],
            constrained: vec![true; 3],
        };
        let mut proj = Projection::new(&kin);
        // (target, weight, lower, upper) per point: the lightest, two at the fastest feed
        // (one heavy), the slow point (heaviest).
        let points = [
            (FAST, 1e-30, 0.0, FAST),
            (FAST, 1e-12, 0.0, FAST),
            (FAST, 1.0, 0.0, FAST),
            (1e-8, 1e20, 0.0, FAST),
        ];
        proj.fill(&kin.ds, |j| points[j]);
        let cuts = proj.run();
        let z = &proj.z;
        assert_eq!(cuts, 0, "{z:?}");
        for (j, w) in z.windows(2).enumerate() {
            assert!(
                (w[1] - w[0]).abs() <= CAP * (1.0 + CAP_ROUNDING),
                "segment {j}: {z:?}"
            );
        }
        for (j, &(_, _, l, h)) in points.iter().enumerate() {
            assert!(z[j] >= l && z[j] <= h, "point {j}: {z:?}");
        }
        // The heaviest point keeps its target; its neighbour lands on the cap from it.
        assert_eq!(z[3], points[3].0);
        assert!(
            (z[2] - (points[3].0 + CAP)).abs() <= CAP * CAP_ROUNDING,
            "{z:?}"
        );
    }
}
