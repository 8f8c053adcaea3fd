"""Does a good start, or fixing an edge band, cut projected L-BFGS's products to 0.1%?

The experiment behind docs/preconditioning.md, "Where the products go". numpy only:

    python docs/experiments/start_and_bands.py [n_dwell]     (default 2000; about 10 minutes)

The problem of `active_set_oracle.py` (the `preston bench` family, products by FFT). A numpy
projected L-BFGS that follows `solver/src/dwell/first_order.rs` (Jacobi-scaled variables, memory 5,
free-set two-loop recursion, exact minimiser along the projected step) runs
  * from the lower bounds (as Preston starts), and from an inverse-filter start: the Tikhonov
    deconvolution of the map on the map lattice, `t = F^-1[conj(K) Z / (|K|^2 + mu)]`, four times
    over (the raster holds a quarter of the lattice's points), clipped onto the bounds;
  * then, at the iterates 10%, 1% and 0.1% above the best value found (12,000 products), it puts
    the best point's dwell into one band of dwell points at a time (by distance from the map's
    edge, inside negative) and reports the objective's excess: if the excess lived in a band,
    fixing that band would remove it.
"""
import numpy as np

import active_set_oracle as p


def lbfgs_from(t0, products, m=5, every=10):
    """Projected L-BFGS from `t0`; returns the last iterate and (products, objective) every `every`."""
    dmask, Ls = p.dmask, p.Ls
    s_ = np.sqrt(np.where(dmask, p.diag, 1.0))
    lx = np.where(dmask, p.l * s_, 0)
    x = np.where(dmask, np.maximum(lx, t0 * s_), 0)
    hess = lambda v: np.where(dmask, p.H(np.where(dmask, v / s_, 0)) / s_, 0)
    q = np.where(dmask, p.grad(x / s_) / s_, 0)
    S, Y, hist = [], [], []
    for it in range(1, products + 1):
        bind = dmask & (x - q / Ls <= lx)
        free = dmask & ~bind
        d = np.where(free, -q, 0.0)
        stack = []
        for si, yi in reversed(list(zip(S, Y))):
            sy = yi[free] @ si[free]
            rho = 1.0 / sy if sy > 0 else 0.0
            a = rho * (si[free] @ d[free])
            stack.append((a, rho, si, yi))
            d = d - a * np.where(free, yi, 0)
        sy = Y[-1][free] @ S[-1][free] if S else 0.0
        yy = Y[-1][free] @ Y[-1][free] if S else 0.0
        d = d * (sy / yy if sy > 0 and yy > 0 else 1.0 / Ls)
        for a, rho, si, yi in reversed(stack):
            d = d + (a - rho * (yi[free] @ d[free])) * np.where(free, si, 0)
        d = np.where(bind, -q / Ls, d)
        step = np.where(dmask, np.maximum(lx, x + d), 0) - x
        if q[dmask] @ step[dmask] >= 0:
            S, Y = [], []
            step = np.where(dmask, np.maximum(lx, x - q / Ls), 0) - x
        hstep = hess(step)
        php = step[dmask] @ hstep[dmask]
        tau = min(1.0, -(q[dmask] @ step[dmask]) / php) if php > 0 else 1.0
        x = x + tau * step
        q_new = q + tau * hstep
        S.append(tau * step)
        Y.append(q_new - q)
        S, Y, q = S[-m:], Y[-m:], q_new
        if it % every == 0:
            hist.append((it, p.objective(x / s_)))
    return x / s_, hist


def first(hist, fstar, tol):
    return next((i for i, o in hist if o <= fstar * (1 + tol)), None)


def main():
    t_ref, _ = lbfgs_from(p.lo, 12000, every=500)
    fstar = p.objective(t_ref)
    print(f"best objective {fstar:.6f} nm^2 (L-BFGS, 12,000 products); at the lower bounds {p.objective(p.lo):.4e}")

    _, h_lo = lbfgs_from(p.lo, 8000)
    fstar = min(fstar, min(o for _, o in h_lo))
    bz = np.where(p.mask, p.b - p.b[p.mask].mean(), 0.0)
    for mu_rel in (1e-3, 1e-2):
        mu = mu_rel * np.abs(p.Kh).max() ** 2
        tt = np.fft.irfft2(np.conj(p.Kh) * np.fft.rfft2(bz) / (np.abs(p.Kh) ** 2 + mu), s=(p.N, p.N))
        t0 = np.where(p.dmask, np.maximum(p.l, 4 * tt), 0)
        _, h = lbfgs_from(t0, 8000)
        print(f"inverse-filter start, mu = {mu_rel:g} max|K|^2: objective {p.objective(t0):.4e}; products to 1%:"
              f" {first(h, fstar, 1e-2)}, to 0.1%: {first(h, fstar, 1e-3)}")
    print(f"lower-bound start: products to 1%: {first(h_lo, fstar, 1e-2)}, to 0.1%: {first(h_lo, fstar, 1e-3)}")

    ii, jj = np.nonzero(p.dmask)
    lo_ix, hi_ix = p.kr, p.kr + p.k - 1
    outside = np.maximum(np.maximum(np.maximum(lo_ix - ii, ii - hi_ix), 0),
                         np.maximum(np.maximum(lo_ix - jj, jj - hi_ix), 0)) * p.h
    inside = np.minimum(np.minimum(ii - lo_ix, hi_ix - ii), np.minimum(jj - lo_ix, hi_ix - jj)) * p.h
    signed = np.where(outside > 0, outside, -inside)
    bands = ((-1e9, -12), (-12, -6), (-6, -3), (-3, 0), (0, 3), (3, 6.1))
    for target in (1e-1, 1e-2, 1e-3):
        it = first(h_lo, fstar, target)
        t, _ = lbfgs_from(p.lo, it, every=10 ** 9)
        excess = p.objective(t) - fstar
        row = []
        for a, b in bands:
            sel = (signed > a) & (signed <= b)
            fixed = t.copy()
            fixed[ii[sel], jj[sel]] = t_ref[ii[sel], jj[sel]]
            row.append(f"({a:g}, {b:g}] mm: {p.objective(fixed) - fstar:.4g}")
        print(f"{100 * target:g}% above (product {it}), excess {excess:.4g} nm^2; excess with one band fixed: " + "; ".join(row))


if __name__ == "__main__":
    main()
