//! A circulant preconditioner for the normal matrix `R^T R` of a convolution operator, used by
//! the projected Newton-CG iteration ([`super::first_order`]).
//!
//! **Model.** Where the dwell points lie on a regular lattice (pitch `px`, `py`; lattice indices
//! `(a_j, b_j)`) and the TIF does not change over the part, `R^T R` is a block-Toeplitz matrix
//! with Toeplitz blocks (BTTB): `(R^T R)_{jk} = A(a_j - a_k, b_j - b_k)`, `A` the autocorrelation
//! of the TIF sampled at the dwell pitch, `A(d) = sum_x K(x) K(x + d)` over the map points. `A`
//! is read off one column of `R^T R` (one product with `R` and one with `R^T` at the lattice
//! point nearest the middle of the dwell area), embedded in a periodic `Nx x Ny` lattice large
//! enough that it does not wrap onto the dwell area (`Nx >= nx + 2 hx`, `hx` the stencil's
//! half-width), and diagonalised by the 2-D DFT: the circulant `C = F^* diag(A^) F` with
//! `A^ = F A` real (the stencil is symmetrised). The preconditioner is
//! `M^{-1} = E^T F^* diag(1 / (max(A^, 0) + mu)) F E`, `E` the embedding of the dwell points in the
//! periodic lattice (Chan, "An optimal circulant preconditioner for Toeplitz systems", SIAM J.
//! Sci. Stat. Comput. 9, 1988; Chan & Ng, "Conjugate gradient methods for Toeplitz systems",
//! SIAM Review 38, 1996, section 5 for the 2-D BTTB case). `M^{-1}` is the principal block of an
//! SPD matrix, so it is SPD for every `mu > 0`.
//!
//! **Regularisation.** The TIF's spectrum decays fast (a Gaussian's as `exp(-sigma^2 w^2)`), so
//! `A^` spans many decades; `mu = MU_REL * max A^` caps the preconditioner's gain at the
//! frequencies the removal cannot reach (they barely change the objective). The smoothing term
//! `lambda D^T D` enters as `2 lambda` (its diagonal) in the denominator.
//!
//! Applying `M^{-1}` costs two 2-D complex FFTs of the `Nx x Ny` lattice, run on the calling
//! thread with buffers allocated once: the result does not depend on the thread count and the
//! iteration allocates nothing.

use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// Relative tolerance for a coordinate to count as on the dwell lattice.
const ON_LATTICE_REL: f64 = 1e-6;
/// The dwell points must fill at least this share of their lattice's bounding box.
const MIN_FILL: f64 = 0.25;
/// Relative regularisation of the circulant model (see the module documentation). Chosen by
/// measurement among 1e-1, 1e-2, 1e-3 and 1e-4 (docs/preconditioning.md).
pub const MU_REL: f64 = 1e-3;

/// Dwell points on a regular lattice: `nx x ny` cells of pitch `px x py`, and each point's cell.
#[derive(Debug, Clone, PartialEq)]
pub struct DwellLattice {
    nx: usize,
    ny: usize,
    cells: Vec<(usize, usize)>,
}

impl DwellLattice {
    /// The lattice of the dwell points `(x, y)` (mm), when they lie on one: the pitch along each
    /// axis is the smallest step between distinct coordinates, every point within
    /// `1e-6` pitch of a lattice node, no two points in one cell, and the points filling at
    /// least a quarter of the lattice's bounding box. `None` otherwise.
    pub fn detect(x_mm: &[f64], y_mm: &[f64]) -> Option<Self> {
        let n = x_mm.len();
        if n < 2 || y_mm.len() != n {
            return None;
        }
        let axis = |v: &[f64]| -> Option<(f64, f64, usize)> {
            let mut s: Vec<f64> = v.to_vec();
            if s.iter().any(|a| !a.is_finite()) {
                return None;
            }
            s.sort_by(f64::total_cmp);
            let (lo, hi) = (s[0], s[s.len() - 1]);
            let span = hi - lo;
            let tol = 1e-9 * span.max(1.0);
            let pitch = s
                .windows(2)
                .map(|w| w[1] - w[0])
                .filter(|&d| d > tol)
                .fold(f64::INFINITY, f64::min);
            if !pitch.is_finite() {
                return Some((lo, 1.0, 1));
            }
            let cells = (span / pitch).round() + 1.0;
            if !(cells.is_finite() && cells <= 4.0 * n as f64 + 1.0) {
                return None;
            }
            Some((lo, pitch, cells as usize))
        };
        let (x0, px, nx) = axis(x_mm)?;
        let (y0, py, ny) = axis(y_mm)?;
        if (nx * ny) as f64 * MIN_FILL > n as f64 {
            return None;
        }
        let index = |v: f64, o: f64, p: f64| -> Option<usize> {
            let f = (v - o) / p;
            let k = f.round();
            ((f - k).abs() <= ON_LATTICE_REL && k >= 0.0).then_some(k as usize)
        };
        let mut seen = vec![false; nx * ny];
        let mut cells = Vec::with_capacity(n);
        for (&x, &y) in x_mm.iter().zip(y_mm) {
            let (a, b) = (index(x, x0, px)?, index(y, y0, py)?);
            if a >= nx || b >= ny || std::mem::replace(&mut seen[b * nx + a], true) {
                return None;
            }
            cells.push((a, b));
        }
        Some(Self { nx, ny, cells })
    }

    /// The lattice restricted to the listed dwell points (indices into this lattice's points).
    pub fn subset(&self, kept: &[usize]) -> Option<Self> {
        let cells = kept
            .iter()
            .map(|&j| self.cells.get(j).copied())
            .collect::<Option<Vec<_>>>()?;
        Some(Self {
            nx: self.nx,
            ny: self.ny,
            cells,
        })
    }

    /// Number of dwell points.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    /// True when there are no dwell points.
    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// Lattice size `(nx, ny)`, cells.
    pub fn size(&self) -> (usize, usize) {
        (self.nx, self.ny)
    }

    /// The dwell point nearest the middle of the lattice.
    fn central_point(&self) -> usize {
        let (cx, cy) = (self.nx as f64 / 2.0, self.ny as f64 / 2.0);
        let mut best = (f64::INFINITY, 0);
        for (j, &(a, b)) in self.cells.iter().enumerate() {
            let d = (a as f64 - cx).powi(2) + (b as f64 - cy).powi(2);
            if d < best.0 {
                best = (d, j);
            }
        }
        best.1
    }
}

/// Smallest `2^a 3^b 5^c` at least `n`.
fn smooth_size(n: usize) -> usize {
    let mut k = n.max(1);
    loop {
        let mut r = k;
        for p in [2, 3, 5] {
            while r.is_multiple_of(p) {
                r /= p;
            }
        }
        if r == 1 {
            return k;
        }
        k += 1;
    }
}

/// The circulant preconditioner (module documentation), with its buffers.
pub struct CirculantPreconditioner {
    fx: usize,
    fy: usize,
    /// Lattice cell of each dwell point in the periodic `fx x fy` lattice (row-major, `b fx + a`).
    cell: Vec<usize>,
    /// `1 / (max(A^, 0) + mu)` in the transposed layout (`kx fy + ky`).
    inv_eig: Vec<f64>,
    fft_x: Arc<dyn Fft<f64>>,
    ifft_x: Arc<dyn Fft<f64>>,
    fft_y: Arc<dyn Fft<f64>>,
    ifft_y: Arc<dyn Fft<f64>>,
    buf: Vec<Complex<f64>>,
    buf_t: Vec<Complex<f64>>,
    scratch: Vec<Complex<f64>>,
}

impl std::fmt::Debug for CirculantPreconditioner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CirculantPreconditioner")
            .field("fx", &self.fx)
            .field("fy", &self.fy)
            .finish()
    }
}

impl CirculantPreconditioner {
    /// Builds the preconditioner for `lattice` from `column`, the column of the Hessian
    /// (`R^T R`, in dwell time) at [`CirculantPreconditioner::probe_point`], and the smoothing
    /// weight `lambda`. `None` when the stencil is empty or not finite.
    pub fn new(lattice: &DwellLattice, column: &[f64], lambda: f64) -> Option<Self> {
        if column.len() != lattice.len() || lattice.is_empty() {
            return None;
        }
        let c = lattice.central_point();
        let (ca, cb) = lattice.cells[c];
        let (mut hx, mut hy) = (0usize, 0usize);
        let peak = column.iter().fold(0.0_f64, |a, &v| a.max(v.abs()));
        if !(peak > 0.0 && peak.is_finite()) {
            return None;
        }
        for (&(a, b), &v) in lattice.cells.iter().zip(column) {
            if v != 0.0 {
                hx = hx.max(a.abs_diff(ca));
                hy = hy.max(b.abs_diff(cb));
            }
        }
        let fx = smooth_size(lattice.nx + 2 * hx);
        let fy = smooth_size(lattice.ny + 2 * hy);
        let len = fx * fy;
        // Symmetrised stencil A(d) = (A(d) + A(-d)) / 2, wrapped onto the periodic lattice.
        let wrap = |d: i64, f: usize| -> usize { d.rem_euclid(f as i64) as usize };
        let mut stencil = vec![Complex::new(0.0, 0.0); len];
        for (&(a, b), &v) in lattice.cells.iter().zip(column) {
            let (dx, dy) = (a as i64 - ca as i64, b as i64 - cb as i64);
            for (sx, sy) in [(dx, dy), (-dx, -dy)] {
                stencil[wrap(sy, fy) * fx + wrap(sx, fx)].re += 0.5 * v;
            }
        }
        let mut planner = FftPlanner::<f64>::new();
        let fft_x = planner.plan_fft_forward(fx);
        let ifft_x = planner.plan_fft_inverse(fx);
        let fft_y = planner.plan_fft_forward(fy);
        let ifft_y = planner.plan_fft_inverse(fy);
        let scratch_len = [&fft_x, &ifft_x, &fft_y, &ifft_y]
            .iter()
            .map(|f| f.get_inplace_scratch_len())
            .max()
            .unwrap_or(0);
        let cell = lattice
            .cells
            .iter()
            .map(|&(a, b)| b * fx + a)
            .collect::<Vec<_>>();
        let mut p = Self {
            fx,
            fy,
            cell,
            inv_eig: vec![0.0; len],
            fft_x,
            ifft_x,
            fft_y,
            ifft_y,
            buf: stencil,
            buf_t: vec![Complex::new(0.0, 0.0); len],
            scratch: vec![Complex::new(0.0, 0.0); scratch_len],
        };
        p.forward();
        let max_eig = p.buf_t.iter().fold(0.0_f64, |a, v| a.max(v.re));
        if !(max_eig > 0.0 && max_eig.is_finite()) {
            return None;
        }
        let mu = MU_REL * max_eig + 2.0 * lambda;
        for (e, v) in p.inv_eig.iter_mut().zip(&p.buf_t) {
            *e = 1.0 / (v.re.max(0.0) + mu);
        }
        Some(p)
    }

    /// The dwell point whose Hessian column [`CirculantPreconditioner::new`] needs.
    pub fn probe_point(lattice: &DwellLattice) -> usize {
        lattice.central_point()
    }

    /// `buf` (row-major) -> its 2-D DFT in `buf_t` (transposed, `kx fy + ky`).
    fn forward(&mut self) {
        let (fx, fy) = (self.fx, self.fy);
        self.fft_x
            .process_with_scratch(&mut self.buf, &mut self.scratch);
        transpose(&self.buf, &mut self.buf_t, fx, fy);
        self.fft_y
            .process_with_scratch(&mut self.buf_t, &mut self.scratch);
    }

    /// `out = D M^{-1} D v` on the points where `mask` holds (the free dwell points; the others
    /// are read as and set to 0), `D = diag(scale)`: with variables `t = S w`, the preconditioner
    /// of the scaled Hessian `S H S` is `S^{-1} M^{-1} S^{-1}`, so `scale = 1 / s`.
    pub fn apply_scaled(&mut self, v: &[f64], scale: &[f64], mask: &[bool], out: &mut [f64]) {
        let s = scale;
        self.buf.fill(Complex::new(0.0, 0.0));
        for (j, &c) in self.cell.iter().enumerate() {
            if mask[j] {
                self.buf[c].re = v[j] * s[j];
            }
        }
        self.forward();
        for (b, e) in self.buf_t.iter_mut().zip(&self.inv_eig) {
            *b *= *e;
        }
        let (fx, fy) = (self.fx, self.fy);
        self.ifft_y
            .process_with_scratch(&mut self.buf_t, &mut self.scratch);
        transpose(&self.buf_t, &mut self.buf, fy, fx);
        self.ifft_x
            .process_with_scratch(&mut self.buf, &mut self.scratch);
        let norm = 1.0 / (fx * fy) as f64;
        for (j, &c) in self.cell.iter().enumerate() {
            out[j] = if mask[j] {
                self.buf[c].re * norm * s[j]
            } else {
                0.0
            };
        }
    }
}

/// `dst` (`cols` rows of `rows`) = transpose of `src` (`rows` rows of `cols`).
fn transpose(src: &[Complex<f64>], dst: &mut [Complex<f64>], cols: usize, rows: usize) {
    const B: usize = 32;
    for r0 in (0..rows).step_by(B) {
        for c0 in (0..cols).step_by(B) {
            for r in r0..(r0 + B).min(rows) {
                for c in c0..(c0 + B).min(cols) {
                    dst[c * rows + r] = src[r * cols + c];
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lattice_detection_finds_a_serpentine_raster_and_rejects_scatter() {
        // A 5 x 4 raster at 1.5 mm in serpentine order, shifted.
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for b in 0..4 {
            for k in 0..5 {
                let a = if b % 2 == 0 { k } else { 4 - k };
                x.push(10.0 + 1.5 * a as f64);
                y.push(-3.0 + 1.5 * b as f64);
            }
        }
        let l = DwellLattice::detect(&x, &y).expect("a lattice");
        assert_eq!(l.size(), (5, 4));
        assert_eq!(l.cells[5], (4, 1));
        x[3] += 0.3;
        assert!(DwellLattice::detect(&x, &y).is_none());
    }

    /// On a full periodic lattice with a circulant Hessian, `M^{-1}` (mu -> 0) inverts it: the
    /// product with the Hessian gives the identity up to the regularisation.
    #[test]
    fn the_circulant_model_inverts_a_convolution_hessian() {
        let (nx, ny) = (12usize, 10usize);
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for b in 0..ny {
            for a in 0..nx {
                x.push(a as f64);
                y.push(b as f64);
            }
        }
        let lattice = DwellLattice::detect(&x, &y).unwrap();
        // Stencil of a 1-D-separable positive definite convolution: [0.25, 1, 0.25] squared.
        let k = |d: i64| match d.abs() {
            0 => 1.0,
            1 => 0.25,
            _ => 0.0,
        };
        let c = CirculantPreconditioner::probe_point(&lattice);
        let (ca, cb) = lattice.cells[c];
        let column: Vec<f64> = lattice
            .cells
            .iter()
            .map(|&(a, b)| k(a as i64 - ca as i64) * k(b as i64 - cb as i64))
            .collect();
        let mut p = CirculantPreconditioner::new(&lattice, &column, 0.0).unwrap();
        // A smooth vector well inside the lattice: H (M^{-1} v) should be close to v there.
        let n = nx * ny;
        let v: Vec<f64> = lattice
            .cells
            .iter()
            .map(|&(a, b)| {
                let (u, w) = (a as f64 - 5.5, b as f64 - 4.5);
                (-(u * u + w * w) / 4.0).exp()
            })
            .collect();
        let s = vec![1.0; n];
        let mask = vec![true; n];
        let mut mv = vec![0.0; n];
        p.apply_scaled(&v, &s, &mask, &mut mv);
        let hv: Vec<f64> = (0..n)
            .map(|j| {
                let (a, b) = lattice.cells[j];
                (0..n)
                    .map(|i| {
                        let (c, d) = lattice.cells[i];
                        k(a as i64 - c as i64) * k(b as i64 - d as i64) * mv[i]
                    })
                    .sum()
            })
            .collect();
        let err = hv
            .iter()
            .zip(&v)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        // Truncation at the lattice edge (v is 1e-4 of its peak there) and mu = 1e-3 max A^.
        assert!(err < 5e-3, "max |H M^-1 v - v| = {err}");
        // Symmetric: u' M^{-1} v == v' M^{-1} u.
        let u: Vec<f64> = (0..n).map(|j| ((j * 37) % 11) as f64 - 5.0).collect();
        let mut mu = vec![0.0; n];
        p.apply_scaled(&u, &s, &mask, &mut mu);
        let a: f64 = u.iter().zip(&mv).map(|(a, b)| a * b).sum();
        let b: f64 = v.iter().zip(&mu).map(|(a, b)| a * b).sum();
        assert!((a - b).abs() <= 1e-12 * a.abs().max(1.0), "{a} vs {b}");
    }
}
