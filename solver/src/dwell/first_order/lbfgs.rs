//! Projected L-BFGS (Kim, Sra & Dhillon 2010) with the two-loop recursion on the free variables
//! and an exact line search along the projected step, and its one-pass vector kernels.

use super::*;

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
pub(super) fn projected_lbfgs(it: Iteration<'_, '_>, mut x: Vec<f64>, mem: usize) -> Outcome {
    let Iteration {
        data,
        work,
        bounds,
        lip,
        limits,
        observer,
    } = it;
    let n = x.len();
    let rho = data.rho;
    let mut pairs = Pairs::new(n, mem);
    let mut v = Vectors::new(n);
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
    scaled_gradient(work, &mut v.q);
    let mut it = 1;
    let mut reports = Reports::new(it);
    // The iteration at which `q` and `cert` were last computed exactly.
    let mut exact_at = it;
    observer.iteration(&IterationInfo {
        iteration: it,
        objective: cert.f,
        kkt_residual: Some(cert.kkt),
    });
    if let Some(st) = stop_or_cancel(limits, observer, &cert, it) {
        return (st, x, it, cert);
    }
    while it < limits.max_it {
        let step = 1.0 / lip;
        // Two-loop recursion on the free variables; `d` stays zero on the binding ones, so its
        // dot products with the stored pairs are the restricted ones.
        let (dot, carried_kkt2) = free_gradient(
            data,
            &x,
            &v.q,
            step,
            pairs.newest_s(),
            &mut v.free,
            &mut v.d,
            &mut pair_partials,
        );
        if it != exact_at {
            // The carried gradient `q` follows the exact one to rounding (`q += tau S H S p`
            // each step), so its KKT residual tells when to form the certificate that decides.
            let carried_kkt = carried_kkt2.sqrt() / limits.kkt_norm.at(carried_f);
            let report = reports.due(it);
            let out_of_time =
                limits.began.elapsed().as_secs_f64() > limits.time_limit_s || observer.cancelled();
            if (carried_kkt <= limits.tol && limits.recheck_due(it))
                || (periodic && report)
                || out_of_time
            {
                cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
                scaled_gradient(work, &mut v.q);
                exact_at = it;
                carried_f = cert.f;
                reports.report(observer, it, (cert.f, cert.kkt), true);
                if let Some(st) = stop_or_cancel(limits, observer, &cert, it) {
                    status = st;
                    break;
                }
                // The next pass starts again from the exact gradient.
                continue;
            }
            if report {
                reports.report(observer, it, (carried_f, carried_kkt), false);
                if rho == 0.0 {
                    // Without a time term the carried objective is the fit: a point of its
                    // history between the certificates.
                    limits.record_fit(carried_f, it);
                }
            }
        }
        let qp = pairs.projected_step(data, &x, &mut v, step, dot, &mut work.partials);
        if !(qp < 0.0) {
            // No descent along the updated gradient: take the exact one, and stop if that
            // shows none either (stationary to rounding).
            cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
            scaled_gradient(work, &mut v.q);
            let fresh = it == exact_at;
            exact_at = it;
            carried_f = cert.f;
            if let Some(st) = stop_or_cancel(limits, observer, &cert, it) {
                status = st;
                break;
            }
            if fresh {
                // Stationary to rounding: no further step can lower the fit, so a KKT residual
                // within the tolerance is convergence whether or not the fit has settled.
                status = if cert.kkt <= limits.tol {
                    Status::Converged
                } else if cert.kkt <= limits.tol.sqrt() {
                    Status::AlmostConverged
                } else {
                    Status::NumericalError
                };
                break;
            }
            continue;
        }
        let php = data.hessian_product_dot(&v.p, work, &mut v.hp);
        it += 1;
        let tau = if php > 0.0 { (-qp / php).min(1.0) } else { 1.0 };
        carried_f += tau * qp + 0.5 * tau * tau * php;
        let yy = move_along(
            &mut x,
            &mut v.p,
            &mut v.hp,
            &mut v.q,
            tau,
            &mut work.partials,
        );
        pairs.push(&mut v, tau * tau * php, yy);
    }
    if it != exact_at {
        cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
        if status == Status::MaxIterations && limits.met(&cert, it).is_some() {
            status = Status::Converged;
        }
    }
    observer.advance(Stage::Solve, (it - reports.last) as u64);
    (status, x, it, cert)
}

/// The iteration's vectors of `n`: the scaled gradient `q`, the recursion's `d`, the step `p`,
/// its Hessian product `hp`, and the free-set mask.
struct Vectors {
    q: Vec<f64>,
    d: Vec<f64>,
    p: Vec<f64>,
    hp: Vec<f64>,
    free: Vec<bool>,
}

impl Vectors {
    fn new(n: usize) -> Self {
        Self {
            q: vec![0.0; n],
            d: vec![0.0; n],
            p: vec![0.0; n],
            hp: vec![0.0; n],
            free: vec![true; n],
        }
    }
}

/// The stored L-BFGS pairs `s = tau p`, `y = tau H p` in a ring of `mem`, newest at `newest`,
/// with `1 / s'y`, the scaling `gamma = s'y / y'y` of each and the first loop's coefficients.
struct Pairs {
    s: Vec<Vec<f64>>,
    y: Vec<Vec<f64>>,
    inv_sy: Vec<f64>,
    gamma_of: Vec<f64>,
    coef: Vec<f64>,
    stored: usize,
    newest: usize,
}

impl Pairs {
    fn new(n: usize, mem: usize) -> Self {
        Self {
            s: vec![vec![0.0; n]; mem],
            y: vec![vec![0.0; n]; mem],
            inv_sy: vec![0.0; mem],
            gamma_of: vec![0.0; mem],
            coef: vec![0.0; mem],
            stored: 0,
            newest: 0,
        }
    }

    /// The ring index of the `k`-th newest pair.
    fn order(&self, k: usize) -> usize {
        let mem = self.s.len();
        (self.newest + mem - k) % mem
    }

    /// The newest `s`, when a pair is stored.
    fn newest_s(&self) -> Option<&[f64]> {
        (self.stored > 0).then(|| self.s[self.order(0)].as_slice())
    }

    /// Stores the pair `(p, hp)` of `s'y = sy` and `y'y = yy` when `sy` is positive and
    /// finite. `p` and `hp` are overwritten in full by the next step, so the pair's vectors
    /// are swapped in.
    fn push(&mut self, v: &mut Vectors, sy: f64, yy: f64) {
        if sy > 0.0 && sy.is_finite() {
            let mem = self.s.len();
            self.newest = (self.newest + 1) % mem;
            let newest = self.newest;
            std::mem::swap(&mut self.s[newest], &mut v.p);
            std::mem::swap(&mut self.y[newest], &mut v.hp);
            self.inv_sy[newest] = 1.0 / sy;
            self.gamma_of[newest] = if yy > 0.0 { sy / yy } else { 0.0 };
            self.stored = (self.stored + 1).min(mem);
        }
    }

    /// The two-loop recursion on `v.d` (started by [`free_gradient`], `dot` its first dot
    /// product) and the projected step along it into `v.p`; the projected gradient step (the
    /// memory cleared) when it does not descend. Returns `q'p`.
    fn projected_step(
        &mut self,
        data: &Data<'_>,
        x: &[f64],
        v: &mut Vectors,
        step: f64,
        mut dot: f64,
        partials: &mut Vec<f64>,
    ) -> f64 {
        let Vectors { q, d, p, free, .. } = v;
        let stored = self.stored;
        let gamma = if stored > 0 && self.gamma_of[self.order(0)] > 0.0 {
            self.gamma_of[self.order(0)]
        } else {
            step
        };
        // The first loop's last update also scales `d` by `gamma` and takes the second loop's
        // first dot product (one pass for the two).
        for k in 0..stored {
            let i = self.order(k);
            let a = self.inv_sy[i] * dot;
            self.coef[i] = a;
            let (next, scale) = if k + 1 < stored {
                (self.s[self.order(k + 1)].as_slice(), None)
            } else {
                (self.y[self.order(k)].as_slice(), Some(gamma))
            };
            dot = masked_axpy_dot(d, -a, &self.y[i], free, scale, Some(next), partials);
        }
        if stored == 0 {
            scale(d, gamma);
        }
        // The second loop's last update is left to the projection's pass: `(c, i)`.
        let mut last_update = None;
        for k in (0..stored).rev() {
            let i = self.order(k);
            let c = self.coef[i] - self.inv_sy[i] * dot;
            if k == 0 {
                last_update = Some((c, i));
                break;
            }
            let next = Some(self.y[self.order(k - 1)].as_slice());
            dot = masked_axpy_dot(d, c, &self.s[i], free, None, next, partials);
        }
        // The projected step, and the projected gradient step when it does not descend.
        // The direction is `-d` on the free variables (`d` the recursion's `H q`, finished here
        // by its last update) and the gradient step on the binding ones.
        let mut qp = match last_update {
            Some((c, i)) => {
                let s_last = &self.s[i];
                project_along(data, x, p, q, partials, |j| {
                    select(free[j], -(d[j] + c * s_last[j]), -step * q[j])
                })
            }
            None => project_along(data, x, p, q, partials, |j| {
                select(free[j], -d[j], -step * q[j])
            }),
        };
        if !(qp < 0.0) {
            self.stored = 0;
            qp = project_along(data, x, p, q, partials, |j| -step * q[j]);
        }
        qp
    }
}

/// The start of the two-loop recursion, in one pass over fixed chunks: `free[j]` = whether a
/// projected gradient step of length `step` leaves variable `j` off its bounds ([`binds`]),
/// `d = q` on the free variables and 0 on the binding ones. Returns `sum_j w[j] d[j]` (0 without
/// `w`) and the squared projected-gradient norm `sum_j (x_j - Proj(x_j - q_j))^2` at the scaled
/// gradient `q` the iteration carries, the KKT residual's numerator (see [`certificate`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn free_gradient(
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
                *d = masked(q[j], *fr);
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
pub(super) fn masked_axpy_dot(
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
            // The masked term without a branch: `a v` where the mask is set, `+0.0` elsewhere
            // (its bits and-ed with all ones or with zero), the same bits as the select.
            match scale {
                None => {
                    for ((d, v), &m) in chunk.iter_mut().zip(v).zip(mask) {
                        *d += masked(a * v, m);
                    }
                }
                Some(g) => {
                    for ((d, v), &m) in chunk.iter_mut().zip(v).zip(mask) {
                        *d = (*d + masked(a * v, m)) * g;
                    }
                }
            }
            w.map_or(0.0, |w| lane_dot(chunk, &w[base..end]))
        })
        .collect_into_vec(partials);
    partials.iter().sum()
}

/// `v` where `keep`, `+0.0` elsewhere, without a branch (so that the loops around it vectorise):
/// the bits of `v` and-ed with all ones or with zero.
#[inline(always)]
pub(super) fn masked(v: f64, keep: bool) -> f64 {
    f64::from_bits(v.to_bits() & u64::from(keep).wrapping_neg())
}

/// `a` where `first`, else `b`, without a branch: the bits of the one chosen.
#[inline(always)]
pub(super) fn select(first: bool, a: f64, b: f64) -> f64 {
    let m = u64::from(first).wrapping_neg();
    f64::from_bits((a.to_bits() & m) | (b.to_bits() & !m))
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
pub(super) fn project_along<F>(
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
