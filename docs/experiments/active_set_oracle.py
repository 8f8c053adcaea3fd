"""How many products would an active-set Krylov method need if it knew the optimal active set?

The experiment behind docs/preconditioning.md, "What would 10x fewer products take?". numpy only:

    python docs/experiments/active_set_oracle.py [n_dwell]     (default 5000; about 5 minutes)

A problem of the `preston bench` family (square map at 0.5 mm with eight random cosine modes, Gaussian TIF
sigma 2 mm, peak 10 nm/s, truncated at 6 mm, 1 mm dwell raster over the map extended by 6 mm, lower
bound from v_max = 2000 mm/min, free piston), products by FFT on one periodic lattice. It compares, in
products with R^T P R to reach 1% / 0.1% / 0.01% above the best objective found:
  * Jacobi-scaled FISTA from the lower bounds (step 1 / lambda_max of the scaled Hessian);
  * conjugate gradients, Jacobi-preconditioned, on the free variables of that best point (an oracle
    active set) from the lower bounds, objective taken at the iterate clipped onto the bounds;
  * the same CG preconditioned by the circulant (BTTB) model of R^T R, plain and Jacobi-scaled;
  * ADMM with every subproblem exact by FFT (v = C t on the lattice, s = t with s >= l).
"""
import sys
import numpy as np

rng = np.random.default_rng(1)
n_target = int(sys.argv[1]) if len(sys.argv) > 1 else 5000
h, sig, peak, rad, vmax = 0.5, 2.0, 10.0, 6.0, 2000 / 60
map_side = np.sqrt(n_target) - 2 * rad
k = int(round(map_side / h)) + 1
kr = int(round(rad / h))
nd = int(round(map_side + 2 * rad)) + 1
span = (nd - 1) * 2 + 1
N = int(np.ceil((span + 2 * kr) / 64) * 64)
xs = np.arange(k) * h
X, Y = np.meshgrid(xs, xs)
Z = 0
for _ in range(8):
    wl = 8 + max(map_side - 8, 0) * rng.random()
    ang, kk = 2 * np.pi * rng.random(), 2 * np.pi / wl
    Z = Z + (20 + 40 * rng.random()) * np.cos(kk * np.cos(ang) * X + kk * np.sin(ang) * Y + 6 * rng.random())
b = np.zeros((N, N)); mask = np.zeros((N, N), bool)
b[kr:kr + k, kr:kr + k] = Z; mask[kr:kr + k, kr:kr + k] = True
dmask = np.zeros((N, N), bool); dmask[0:span:2, 0:span:2] = True
d = np.arange(-kr, kr + 1) * h
KX, KY = np.meshgrid(d, d)
K = peak * np.exp(-(KX ** 2 + KY ** 2) / (2 * sig ** 2)); K[KX ** 2 + KY ** 2 > rad ** 2] = 0
Kfull = np.zeros((N, N))
Kfull[np.ix_(np.arange(-kr, kr + 1) % N, np.arange(-kr, kr + 1) % N)] = K
Kh = np.fft.rfft2(Kfull)
C = lambda t: np.fft.irfft2(Kh * np.fft.rfft2(t), s=(N, N))
Ct = lambda y: np.fft.irfft2(np.conj(Kh) * np.fft.rfft2(y), s=(N, N))
l = 1.0 / vmax
lo = np.where(dmask, l, 0.0)
print(f"lattice {N}x{N}, map points {mask.sum()}, dwell points {dmask.sum()}")


def objective(t):
    r = (C(t) - b)[mask]; r -= r.mean(); return 0.5 * r @ r


def grad(t):
    r = C(t) - b; r = np.where(mask, r - r[mask].mean(), 0); return np.where(dmask, Ct(r), 0)


def H(x, F=dmask):
    r = C(x); r = np.where(mask, r - r[mask].mean(), 0); return np.where(F, Ct(r), 0)


diag = np.fft.irfft2(np.conj(np.fft.rfft2(Kfull ** 2)) * np.fft.rfft2(mask.astype(float)), s=(N, N))
diag = np.where(dmask, np.maximum(diag, 1e-12), 1.0)
Dinv = np.where(dmask, 1 / diag, 0)
v = np.where(dmask, rng.random((N, N)), 0)
for _ in range(50):
    w = np.sqrt(Dinv) * H(np.sqrt(Dinv) * v); Ls = np.linalg.norm(w) / np.linalg.norm(v); v = w / np.linalg.norm(w)


def fista(products, every=50):
    t = lo.copy(); y = t.copy(); th = 1.0; hist = []
    for it in range(1, products + 1):
        tn = np.where(dmask, np.maximum(l, y - Dinv * grad(y) / Ls), 0)
        thn = (1 + np.sqrt(1 + 4 * th * th)) / 2; y = tn + (th - 1) / thn * (tn - t); t, th = tn, thn
        if it % every == 0: hist.append((it, objective(t)))
    return t, hist


def pcg(F, Minv, products, every=25):
    x = lo.copy(); r = np.where(F, -grad(x), 0); z = Minv(r); p = z.copy(); rz = (r * z).sum(); hist = []
    for it in range(1, products + 1):
        Hp = H(p, F); a = rz / (p * Hp).sum(); x = x + a * p; r = r - a * Hp
        z = Minv(r); rzn = (r * z).sum(); p = z + rzn / rz * p; rz = rzn
        if it % every == 0: hist.append((it, objective(np.where(dmask, np.maximum(l, x), 0))))
    return hist


def admm(iters, rho1, rho2, every=50):
    t = lo.copy(); s = t.copy(); v = C(t); u1 = np.zeros((N, N)); u2 = np.zeros((N, N))
    den = rho1 * np.abs(Kh) ** 2 + rho2; hist = []
    for it in range(1, iters + 1):
        th_ = (rho1 * np.conj(Kh) * np.fft.rfft2(v - u1) + rho2 * np.fft.rfft2(s - u2)) / den
        t = np.fft.irfft2(th_, s=(N, N)); Ctv = np.fft.irfft2(Kh * th_, s=(N, N)); q = Ctv + u1
        c = (q - b)[mask].mean()
        v = np.where(mask, (b + c + rho1 * q) / (1 + rho1), q)
        s = np.where(dmask, np.maximum(l, t + u2), 0)
        u1 += Ctv - v; u2 += t - s
        if it % every == 0: hist.append((it, objective(s)))
    return hist


if __name__ == "__main__":
    t_ref, h_f = fista(20000)
    fstar = min(o for _, o in h_f)
    F = dmask & (t_ref > l * (1 + 1e-6))
    print(f"best objective {fstar:.6f} nm^2 (Jacobi-FISTA, 20,000 products); free at it {F.sum()}")
    first = lambda hist, tol: next((i for i, o in hist if o <= fstar * (1 + tol)), None)
    runs = {"Jacobi-FISTA": h_f, "oracle CG, Jacobi": pcg(F, lambda r: Dinv * r, 4000)}
    col = Ct(C(np.roll(np.roll((np.arange(N)[:, None] == 0) & (np.arange(N)[None, :] == 0), 0, 0), 0, 1).astype(float)))
    Ah = np.real(np.fft.fft2(col[::2, ::2]))
    sc = np.where(dmask, np.sqrt(diag / col.max()), 1.0)
    for mu in (1e-4, 1e-2):
        den = np.maximum(Ah, 0) + mu * Ah.max()
        for scaled in (False, True):
            def Minv(r, den=den, scaled=scaled):
                u = (r / sc if scaled else r)[::2, ::2]
                out = np.zeros_like(r); out[::2, ::2] = np.real(np.fft.ifft2(np.fft.fft2(u) / den))
                return np.where(F, out / sc if scaled else out, 0)
            runs[f"oracle CG, circulant mu={mu:g}{' Jacobi-scaled' if scaled else ''}"] = pcg(F, Minv, 1000)
    for rho1, rho2 in ((0.01, 1e3), (0.01, 1e2), (0.1, 1e3)):
        runs[f"ADMM rho1={rho1:g} rho2={rho2:g}"] = admm(2000, rho1, rho2)
    for name, hist in runs.items():
        last_i, last_o = hist[-1]
        print(f"{name:45s} to 1%: {first(hist, 1e-2)}, 0.1%: {first(hist, 1e-3)}, 0.01%: {first(hist, 1e-4)};"
              f" after {last_i}: {100 * (last_o / fstar - 1):+.3f}%")
