//! Projected Newton-CG (Bertsekas 1982) with truncated, optionally circulant-preconditioned
//! conjugate gradients on the free variables and a projected Armijo line search; the steps are
//! in [`super`]'s documentation.

use super::*;

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
pub(super) fn circulant(
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
pub(super) fn newton_cg(
    it: Iteration<'_, '_>,
    mut x: Vec<f64>,
    mut precond: Option<&mut CirculantPreconditioner>,
) -> Outcome {
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
    let mut v = CgVectors::new(data, n);
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
        if let Some(s) = stop_or_cancel(limits, observer, &cert, it) {
            status = s;
            break;
        }
        // Scaled gradient (certificate() left g = grad_t f - rho in work.g).
        v.grad
            .par_iter_mut()
            .zip(work.g.par_iter().zip(&data.s))
            .for_each(|(gw, (g, s))| *gw = s * (g + rho));
        // The binding set: variables a projected-gradient step of length 1 / L puts on a bound.
        // They take that step (to the bound); the others the Newton-CG step (Bertsekas 1982).
        let (lo, hi) = (&data.lo_w, &data.hi_w);
        let step = 1.0 / lip;
        let grad = &v.grad;
        v.free.par_iter_mut().enumerate().for_each(|(j, f)| {
            *f = !binds(grad[j], x[j], lo[j], hi[j], step);
        });
        // Truncated CG on the free variables.
        let kkt = cert.kkt;
        truncated_cg(
            data,
            work,
            &mut v,
            precond.as_deref_mut(),
            kkt,
            (&mut it, limits.max_it),
        );
        let CgVectors { d, grad, free, .. } = &mut v;
        d.par_iter_mut()
            .zip(grad.par_iter().zip(free.par_iter()))
            .for_each(|(d, (g, f))| {
                if !*f {
                    *d = -step * g;
                }
            });
        // Projected line search along d, then along -grad; a projected gradient step of length
        // 1 / L (a guaranteed decrease for an L-smooth f) if both fail.
        let accepted = line_search(data, work, &x, &mut v, cert.f, &mut it);
        if !accepted {
            trial(data, &x, &v.d, 1.0 / lip, &mut v.x_new);
            let f_new = data.objective(&v.x_new, work);
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
        std::mem::swap(&mut x, &mut v.x_new);
        cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
        it += 1;
        observer.advance(Stage::Solve, (it - it_before) as u64);
    }
    (status, x, it, cert)
}

/// The vectors of `n` a Newton-CG iteration works in: the scaled gradient, the free set, the
/// step `d`, the CG residual `r`, its preconditioned `zr`, direction `p` and product `hp`, the
/// trial point and the inverse scaling.
struct CgVectors {
    grad: Vec<f64>,
    free: Vec<bool>,
    d: Vec<f64>,
    r: Vec<f64>,
    zr: Vec<f64>,
    p: Vec<f64>,
    hp: Vec<f64>,
    x_new: Vec<f64>,
    inv_s: Vec<f64>,
}

impl CgVectors {
    fn new(data: &Data<'_>, n: usize) -> Self {
        Self {
            inv_s: data.s.iter().map(|s| 1.0 / s).collect(),
            grad: vec![0.0; n],
            free: vec![true; n],
            d: vec![0.0; n],
            r: vec![0.0; n],
            zr: vec![0.0; n],
            p: vec![0.0; n],
            hp: vec![0.0; n],
            x_new: vec![0.0; n],
        }
    }
}

/// Truncated CG on the free variables for `d` (`H_FF d_F = -grad_F`), preconditioned by
/// `precond` when given: to a residual of `min(sqrt(kkt), 0.5)` of its start, a stalling step
/// (More & Toraldo 1991) or the iteration limit; `it` counts the Hessian products.
fn truncated_cg(
    data: &Data<'_>,
    work: &mut Work,
    v: &mut CgVectors,
    mut precond: Option<&mut CirculantPreconditioner>,
    kkt: f64,
    (it, max_it): (&mut usize, usize),
) {
    let CgVectors {
        grad,
        free,
        d,
        r,
        zr,
        p,
        hp,
        inv_s,
        ..
    } = v;
    let n = d.len();
    d.iter_mut().for_each(|v| *v = 0.0);
    r.par_iter_mut()
        .zip(grad.par_iter().zip(free.par_iter()))
        .for_each(|(r, (g, f))| *r = if *f { -g } else { 0.0 });
    let mut precondition = |r: &[f64], zr: &mut [f64]| match precond.as_deref_mut() {
        Some(m) => m.apply_scaled(r, inv_s, free, zr),
        None => zr.copy_from_slice(r),
    };
    precondition(r, zr);
    p.copy_from_slice(zr);
    let mut rs = fixed_sum(n, &mut work.partials, |j| r[j] * r[j]);
    let mut rz = fixed_sum(n, &mut work.partials, |j| r[j] * zr[j]);
    let target = rs.sqrt() * kkt.sqrt().min(0.5);
    let mut best_decrease = 0.0_f64;
    for _ in 0..MAX_CG_STEPS {
        if rs.sqrt() <= target || *it >= max_it {
            break;
        }
        data.hessian_product(p, work, hp);
        *it += 1;
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
        precondition(r, zr);
        let rz_new = fixed_sum(n, &mut work.partials, |j| r[j] * zr[j]);
        let beta = rz_new / rz;
        rz = rz_new;
        p.par_iter_mut()
            .zip(zr.par_iter())
            .for_each(|(p, z)| *p = z + beta * *p);
    }
}

/// Projected line search (Armijo, halving) from `x` of objective `f0` along `v.d`, then along
/// `-grad`; the accepted point in `v.x_new`. Returns whether one was accepted; `it` counts the
/// objective evaluations.
fn line_search(
    data: &Data<'_>,
    work: &mut Work,
    x: &[f64],
    v: &mut CgVectors,
    f0: f64,
    it: &mut usize,
) -> bool {
    let CgVectors { grad, d, x_new, .. } = v;
    let n = x.len();
    for direction in [Direction::Newton, Direction::Gradient] {
        if direction == Direction::Gradient {
            d.par_iter_mut()
                .zip(grad.par_iter())
                .for_each(|(d, g)| *d = -g);
        }
        let mut alpha = 1.0;
        for _ in 0..MAX_HALVINGS {
            trial(data, x, d, alpha, x_new);
            let decrease = fixed_sum(n, &mut work.partials, |j| grad[j] * (x_new[j] - x[j]));
            if !(decrease < 0.0) {
                break;
            }
            let f_new = data.objective(x_new, work);
            *it += 1;
            if f_new <= f0 + ARMIJO * decrease {
                return true;
            }
            alpha *= 0.5;
        }
    }
    false
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
