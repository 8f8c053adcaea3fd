//! A matrix-free influence operator for dwell points anywhere in the plane with a controlled
//! error: the non-uniform FFT construction (Dutt & Rokhlin 1993; Greengard & Lee 2004) with the
//! "exponential of semicircle" spreading kernel of Barnett, Magland & af Klinteberg, "A parallel
//! non-uniform fast Fourier transform library based on an 'exponential of semicircle' kernel",
//! SIAM J. Sci. Comput. 41 (2019) (FINUFFT).
//!
//! **The construction.** The map lies on a lattice of pitch `h` through `(x0, y0)`; the fine
//! lattice has pitch `h_f = h / s` (`s >= 1` an integer, so every map point is a fine node). In
//! units of fine cells a dwell point at `u_j = (X_j - x0) / h_f` is spread onto the `w x w` fine
//! nodes `c` around it by the tensor-product ES kernel
//!
//! `phi(z) = exp(beta (sqrt(1 - (2 z / w)^2) - 1))` for `|z| <= w / 2`, 0 outside,
//!
//! and the fine lattice is convolved by FFT with a deconvolved kernel `K`:
//!
//! `R~[i, j] = sum_c K(x_i - c) phi(c_x - u_jx) phi(c_y - u_jy)`, i.e. `R~ = K S`,
//! `R~^T = S^T K^T` (exact adjoint, one consistent linear map for the solvers).
//!
//! As a function of the dwell position `y` (continuous, in cells) the 1-D analogue
//! `sum_c K_c phi(c - y)` has the Fourier transform `K^(xi) phi^(xi)`, `K^` the (2 pi periodic)
//! transform of the lattice sequence `K_c` and `phi^(xi) = int phi(z) e^{-i xi z} dz`. The exact
//! contract `R[i, j] = TIF(x_i - X_j)` has `TIF^(xi)`. Choosing
//!
//! `K^(xi) = TIF_d^(xi) / phi^(xi)` for `|xi| <= pi / sigma`, 0 for `pi / sigma < |xi| <= pi`
//!
//! (per axis; `TIF_d` the TIF sampled on the fine lattice, `sigma` the upsampling factor) makes
//! the two agree on the band `|xi| <= pi / sigma`. What is left is (a) the TIF's content beyond
//! that band, which the operator drops (small when the TIF is resolved by `sigma h_f`: a
//! Gaussian of `sigma_g = 1.7 mm` at `h_f = 0.36 mm`, `sigma = 2` leaves `exp(-27)`), and (b) the
//! images `K^(xi - 2 pi m) phi^(xi)` at `|xi| >= 2 pi - pi / sigma`, relative size
//! `max phi^(xi) / min phi^(xi - 2 pi m)`, which the ES kernel makes about
//! `exp(-pi w sqrt(1 - 1 / sigma))` (Barnett et al., eq. 4.3 and sec. 4): the width follows the
//! tolerance `eps` as `w = ceil(ln(1 / eps) / (pi sqrt(1 - 1 / sigma)))` with
//! `beta = 0.97 pi (1 - 1 / (2 sigma)) w` (FINUFFT's choice; `w = 7` at `1e-6`, `sigma = 2`).
//! `K` is computed once on a periodic box around the TIF (deconvolution by direct DFT along
//! each axis) and kept over the TIF's reach plus `w` cells; `phi^` by quadrature after the
//! substitution `z = (w / 2) sin theta`, which removes the square root's edge singularity.
//!
//! A TIF with a discontinuity (a Gaussian cut where it is not zero) or kinks (a grid TIF,
//! bilinear between its samples) has content at every frequency, and the dropped band (a) then
//! sets the error, not `w`: the error actually incurred is measured, not assumed.
//! [`NufftOperator::estimated_error`] is the relative Frobenius error `||R~ - R||_F / ||R||_F`
//! over an evenly spaced sample of columns, each computed both ways entry by entry against the
//! exact contract.

use super::fft::FftOperator;
use super::lattice::off_lattice_error;
use super::{ColumnStats, ColumnSums, InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use crate::tif::{lattice_reach, InfluenceFunction};
use rayon::prelude::*;
use std::f64::consts::PI;
use std::sync::Mutex;

/// Relative tolerance for a map coordinate to count as on the lattice.
const ON_LATTICE_TOL: f64 = 1e-6;
/// Columns sampled for the error estimate (evenly spaced over the dwell points).
const ERROR_SAMPLE_COLUMNS: usize = 256;
/// Upsampling factor `sigma`: the band the deconvolution keeps is `|xi| <= pi / sigma` per fine
/// cell (FINUFFT's default, 2).
pub const UPSAMPLING: f64 = 2.0;
/// Largest refinement `s` (fine pitch `h / s`) [`NufftOperator::refinement_for`] tries.
pub const MAX_REFINEMENT: usize = 3;
/// Default tolerance on the estimated relative operator error (`||R~ - R||_F / ||R||_F`) within
/// which `operator = "auto"` may use the operator, and the ES kernel's design error.
pub const DEFAULT_NUFFT_TOLERANCE: f64 = 1e-6;
/// Relative error at refinement 1 above which [`NufftOperator::refinement_for`] tries no finer
/// lattice (a multiple of the tolerance).
const GIVE_UP: f64 = 1e3;
/// Fine-node rows per spreading task (each task writes its own rows: a fixed summation order).
const BAND_ROWS: usize = 16;

/// The exponential-of-semicircle kernel of width `w` fine cells (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EsKernel {
    /// Width `w` in fine cells (nodes per axis a point spreads onto).
    pub width: usize,
    /// Shape parameter `beta`.
    pub beta: f64,
}

impl EsKernel {
    /// FINUFFT's kernel for tolerance `eps` (clamped to `[1e-14, 1e-2]`) at upsampling `sigma`
    /// (> 1): `w = ceil(ln(1 / eps) / (pi sqrt(1 - 1 / sigma)))` (at least 2, at most 16),
    /// `beta = 0.97 pi (1 - 1 / (2 sigma)) w`.
    pub fn for_tolerance(eps: f64, sigma: f64) -> Self {
        let eps = if eps.is_finite() {
            eps.clamp(1e-14, 1e-2)
        } else {
            1e-2
        };
        let sigma = if sigma.is_finite() && sigma > 1.05 {
            sigma
        } else {
            2.0
        };
        let w = (-eps.ln() / (PI * (1.0 - 1.0 / sigma).sqrt())).ceil() as usize;
        let width = w.clamp(2, 16);
        Self {
            width,
            beta: 0.97 * PI * (1.0 - 0.5 / sigma) * width as f64,
        }
    }

    /// `phi(z)`, `z` in fine cells.
    #[inline]
    pub fn value(&self, z: f64) -> f64 {
        let a = 2.0 * z / self.width as f64;
        if a.abs() >= 1.0 {
            0.0
        } else {
            (self.beta * ((1.0 - a * a).sqrt() - 1.0)).exp()
        }
    }

    /// `phi^(xi) = int phi(z) cos(xi z) dz` (`phi` is even), `xi` in radians per fine cell:
    /// with `z = (w / 2) sin theta` the integrand `exp(beta (cos theta - 1)) cos(xi w / 2 sin
    /// theta) (w / 2) cos theta` is smooth on `[-pi / 2, pi / 2]`; composite Simpson on 2,048
    /// panels.
    pub fn fourier(&self, xi: f64) -> f64 {
        const PANELS: usize = 2048;
        let half = self.width as f64 / 2.0;
        let dt = PI / PANELS as f64;
        let f = |k: usize| {
            let t = -PI / 2.0 + k as f64 * dt;
            let (s, c) = t.sin_cos();
            (self.beta * (c - 1.0)).exp() * (xi * half * s).cos() * half * c
        };
        let mut sum = f(0) + f(PANELS);
        for k in 1..PANELS {
            sum += if k % 2 == 1 { 4.0 } else { 2.0 } * f(k);
        }
        sum * dt / 3.0
    }

    /// The first of the `w` fine nodes `u` spreads onto (`ceil(u - w / 2)`) and their weights.
    #[inline]
    fn weights(&self, u: f64, out: &mut [f64]) -> i64 {
        let first = (u - self.width as f64 / 2.0).ceil();
        for (a, o) in out.iter_mut().enumerate() {
            *o = self.value(first + a as f64 - u);
        }
        first as i64
    }
}

/// The deconvolved lattice kernel `K` of the module documentation, tabulated over
/// `|d_x|, |d_y| <= reach` fine cells and zero beyond the disc of that radius.
struct DeconvolvedKernel {
    pitch_mm: f64,
    reach: i64,
    values: Vec<f64>,
}

impl DeconvolvedKernel {
    fn new<T: InfluenceFunction + ?Sized>(tif: &T, pitch_mm: f64, es: &EsKernel) -> Self {
        let w = es.width as i64;
        let kr = lattice_reach(tif.support_radius_mm(), pitch_mm) as i64;
        let reach = kr + w;
        // Periodic box: the TIF's support, the kept reach and a margin for the band cut's ripple.
        let p = (2 * (reach + 2 * w) + 1) as usize;
        let c0 = (p / 2) as i64;
        let mut boxed = vec![0.0; p * p];
        for b in 0..p {
            for a in 0..p {
                let (dx, dy) = (a as i64 - c0, b as i64 - c0);
                if dx.abs() <= kr && dy.abs() <= kr {
                    boxed[b * p + a] =
                        tif.rate_nm_per_s(dx as f64 * pitch_mm, dy as f64 * pitch_mm);
                }
            }
        }
        // The 1-D filter f[n] = (1/p) sum_k g(k) cos(2 pi k n / p), g = 1 / phi^ on the band.
        let band = PI / UPSAMPLING;
        let half = (p as i64 - 1) / 2;
        let gains: Vec<(f64, f64)> = (-half..=half)
            .filter_map(|k| {
                let xi = 2.0 * PI * k as f64 / p as f64;
                (xi.abs() <= band).then(|| (xi, 1.0 / es.fourier(xi)))
            })
            .collect();
        let filter: Vec<f64> = (0..p)
            .map(|n| {
                gains
                    .iter()
                    .map(|&(xi, g)| g * (xi * n as f64).cos())
                    .sum::<f64>()
                    / p as f64
            })
            .collect();
        let convolve = |line: &[f64], out: &mut [f64]| {
            for (n, o) in out.iter_mut().enumerate() {
                *o = line
                    .iter()
                    .enumerate()
                    .map(|(m, &v)| v * filter[(n + p - m) % p])
                    .sum();
            }
        };
        // Along x (rows), then along y (columns).
        let mut rows = vec![0.0; p * p];
        rows.par_chunks_mut(p)
            .zip(boxed.par_chunks(p))
            .for_each(|(o, l)| convolve(l, o));
        let mut transposed = vec![0.0; p * p];
        for b in 0..p {
            for a in 0..p {
                transposed[a * p + b] = rows[b * p + a];
            }
        }
        let mut cols = vec![0.0; p * p];
        cols.par_chunks_mut(p)
            .zip(transposed.par_chunks(p))
            .for_each(|(o, l)| convolve(l, o));
        let side = (2 * reach + 1) as usize;
        let mut values = vec![0.0; side * side];
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                if dx * dx + dy * dy > reach * reach {
                    continue;
                }
                let (a, b) = ((c0 + dx) as usize, (c0 + dy) as usize);
                values[(dy + reach) as usize * side + (dx + reach) as usize] = cols[a * p + b];
            }
        }
        Self {
            pitch_mm,
            reach,
            values,
        }
    }

    #[inline]
    fn at(&self, dx: i64, dy: i64) -> f64 {
        if dx.abs() > self.reach || dy.abs() > self.reach {
            return 0.0;
        }
        let side = 2 * self.reach + 1;
        self.values[((dy + self.reach) * side + dx + self.reach) as usize]
    }
}

impl InfluenceFunction for DeconvolvedKernel {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let (a, b) = (
            (dx_mm / self.pitch_mm).round(),
            (dy_mm / self.pitch_mm).round(),
        );
        if a.abs() > 1e9 || b.abs() > 1e9 {
            return 0.0;
        }
        self.at(a as i64, b as i64)
    }

    fn support_radius_mm(&self) -> f64 {
        self.reach as f64 * self.pitch_mm
    }
}

/// Geometry and weights shared by the error estimate and the operator.
struct Layout {
    pitch_mm: f64,
    s: i64,
    x0: f64,
    y0: f64,
    es: EsKernel,
    /// Map cells (coarse lattice) and the map points in each.
    box_w: usize,
    box_h: usize,
    cell_count: Vec<u32>,
    m: usize,
    /// Each dwell point's first fine node `(i, j)` (absolute fine indices).
    first: Vec<(i64, i64)>,
    /// Each dwell point's `w` weights along x, then `w` along y.
    weights: Vec<f64>,
    kernel: DeconvolvedKernel,
}

impl Layout {
    #[allow(clippy::too_many_arguments)]
    fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        s: usize,
        tolerance: f64,
        tif: &T,
    ) -> Result<Self> {
        if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
            return Err(Error::invalid("lattice pitch", format!("{pitch_mm}")));
        }
        if s == 0 {
            return Err(Error::invalid("refinement", "must be at least 1"));
        }
        if map_x_mm.is_empty() || dwell_x_mm.is_empty() {
            return Err(Error::invalid(
                "NUFFT operator",
                "needs map and dwell points",
            ));
        }
        let x0 = map_x_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let y0 = map_y_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let index = |v: f64, o: f64| -> Option<i64> {
            let u = (v - o) / pitch_mm;
            let k = u.round();
            ((u - k).abs() <= ON_LATTICE_TOL && k.abs() < 1e9).then_some(k as i64)
        };
        let map_ij = map_x_mm
            .iter()
            .zip(map_y_mm)
            .enumerate()
            .map(|(k, (&x, &y))| match (index(x, x0), index(y, y0)) {
                (Some(i), Some(j)) => Ok((i, j)),
                _ => Err(off_lattice_error(
                    "map point",
                    k,
                    (x, y),
                    pitch_mm,
                    (x0, y0),
                )),
            })
            .collect::<Result<Vec<_>>>()?;
        let box_w = map_ij.iter().map(|p| p.0).max().unwrap_or(0) as usize + 1;
        let box_h = map_ij.iter().map(|p| p.1).max().unwrap_or(0) as usize + 1;
        crate::budget::check(
            "map points (NUFFT operator)",
            &format!("a map lattice of {box_w} x {box_h} cells of {pitch_mm} mm"),
            box_w as f64 * box_h as f64 * 4.0,
        )?;
        let mut cell_count = vec![0u32; box_w * box_h];
        for &(i, j) in &map_ij {
            cell_count[j as usize * box_w + i as usize] += 1;
        }
        let es = EsKernel::for_tolerance(tolerance, UPSAMPLING);
        let w = es.width;
        let fine = pitch_mm / s as f64;
        let mut first = Vec::with_capacity(dwell_x_mm.len());
        let mut weights = vec![0.0; 2 * w * dwell_x_mm.len()];
        for (k, ((&x, &y), wk)) in dwell_x_mm
            .iter()
            .zip(dwell_y_mm)
            .zip(weights.chunks_mut(2 * w))
            .enumerate()
        {
            let (u, v) = ((x - x0) / fine, (y - y0) / fine);
            if !(u.is_finite() && v.is_finite() && u.abs() < 1e9 && v.abs() < 1e9) {
                return Err(Error::invalid(
                    "dwell point",
                    format!("{k} at ({x}, {y}) mm is too far from the map"),
                ));
            }
            let (wx, wy) = wk.split_at_mut(w);
            let i = es.weights(u, wx);
            let j = es.weights(v, wy);
            first.push((i, j));
        }
        let kernel = DeconvolvedKernel::new(tif, fine, &es);
        Ok(Self {
            pitch_mm,
            s: s as i64,
            x0,
            y0,
            es,
            box_w,
            box_h,
            cell_count,
            m: map_ij.len(),
            first,
            weights,
            kernel,
        })
    }

    /// Calls `f(cell, count, R~ entry)` for every occupied map cell in reach of dwell point `j`.
    fn for_each_entry(&self, j: usize, mut f: impl FnMut(usize, u32, f64)) {
        let w = self.es.width;
        let (fi, fj) = self.first[j];
        let (wx, wy) = self.weights[2 * w * j..2 * w * (j + 1)].split_at(w);
        let (s, r) = (self.s, self.kernel.reach);
        let a0 = (fi - r).div_euclid(s).max(0);
        let a1 = (fi + w as i64 - 1 + r)
            .div_euclid(s)
            .min(self.box_w as i64 - 1);
        let b0 = (fj - r).div_euclid(s).max(0);
        let b1 = (fj + w as i64 - 1 + r)
            .div_euclid(s)
            .min(self.box_h as i64 - 1);
        for b in b0..=b1 {
            for a in a0..=a1 {
                let cell = b as usize * self.box_w + a as usize;
                let count = self.cell_count[cell];
                if count == 0 {
                    continue;
                }
                let mut value = 0.0;
                for (q, &wyq) in wy.iter().enumerate() {
                    let mut row = 0.0;
                    for (p, &wxp) in wx.iter().enumerate() {
                        row += wxp * self.kernel.at(a * s - fi - p as i64, b * s - fj - q as i64);
                    }
                    value += wyq * row;
                }
                f(cell, count, value);
            }
        }
    }

    /// `(||R~_j - R_j||^2, ||R_j||^2)` against the exact contract `R[i, j] = TIF(x_i - X_j)`.
    fn column_error<T: InfluenceFunction + ?Sized>(
        &self,
        j: usize,
        x: f64,
        y: f64,
        tif: &T,
    ) -> (f64, f64) {
        let (mut err, mut norm) = (0.0, 0.0);
        self.for_each_entry(j, |cell, count, v| {
            let a = (cell % self.box_w) as f64;
            let b = (cell / self.box_w) as f64;
            let exact = tif.rate_nm_per_s(
                self.x0 + a * self.pitch_mm - x,
                self.y0 + b * self.pitch_mm - y,
            );
            let c = f64::from(count);
            err += c * (v - exact) * (v - exact);
            norm += c * exact * exact;
        });
        // Map cells the exact column reaches and the operator's does not are within its reach
        // by construction (the kept kernel covers the TIF's support plus the spreading width).
        (err, norm)
    }

    fn estimated_error<T: InfluenceFunction + ?Sized>(
        &self,
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        tif: &T,
    ) -> f64 {
        let n = self.first.len();
        let samples = n.min(ERROR_SAMPLE_COLUMNS);
        let parts: Vec<(f64, f64)> = (0..samples)
            .into_par_iter()
            .map(|k| {
                let j = k * n / samples;
                self.column_error(j, dwell_x_mm[j], dwell_y_mm[j], tif)
            })
            .collect();
        let (err, norm) = parts
            .iter()
            .fold((0.0, 0.0), |(e, n), p| (e + p.0, n + p.1));
        if norm > 0.0 {
            (err / norm).sqrt()
        } else if err > 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    }

    /// Column `j`'s sums of the exact contract over the map points (non-zeros, Jacobi scaling):
    /// `R~` agrees with it to the operator's error, and its support is the TIF's.
    fn exact_column_sums<T: InfluenceFunction + ?Sized>(
        &self,
        x: f64,
        y: f64,
        tif: &T,
    ) -> ColumnSums {
        let mut sums = ColumnSums::default();
        let r = tif.support_radius_mm();
        let span = |c: f64, o: f64, len: usize| {
            let lo = ((c - r - o) / self.pitch_mm).floor().max(0.0);
            let hi = ((c + r - o) / self.pitch_mm).ceil().min(len as f64 - 1.0);
            (lo as i64, hi as i64)
        };
        let (a0, a1) = span(x, self.x0, self.box_w);
        let (b0, b1) = span(y, self.y0, self.box_h);
        for b in b0..=b1 {
            for a in a0..=a1 {
                let count = self.cell_count[b as usize * self.box_w + a as usize];
                if count > 0 {
                    sums.add(
                        count,
                        tif.rate_nm_per_s(
                            self.x0 + a as f64 * self.pitch_mm - x,
                            self.y0 + b as f64 * self.pitch_mm - y,
                        ),
                    );
                }
            }
        }
        sums
    }
}

/// The NUFFT-style spreading operator (see the module documentation).
pub struct NufftOperator {
    inner: FftOperator,
    refinement: usize,
    fine_pitch_mm: f64,
    es: EsKernel,
    /// Each dwell point's first node relative to the node rectangle `(column, row)`.
    first: Vec<(u32, u32)>,
    weights: Vec<f64>,
    /// Node rectangle width (columns) and height (rows).
    width: usize,
    height: usize,
    /// For each band of [`BAND_ROWS`] node rows, the dwell points that touch it, ascending.
    band_points: Vec<Vec<u32>>,
    columns: ColumnStats,
    estimated_error: f64,
    tolerance: f64,
    m: usize,
    work: Mutex<(Vec<f64>, Vec<f64>)>,
}

impl std::fmt::Debug for NufftOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NufftOperator")
            .field("refinement", &self.refinement)
            .field("fine_pitch_mm", &self.fine_pitch_mm)
            .field("es", &self.es)
            .field("m", &self.m)
            .field("n", &self.first.len())
            .field("nodes", &(self.width * self.height))
            .field("estimated_error", &self.estimated_error)
            .finish()
    }
}

impl NufftOperator {
    /// Estimated relative operator error `||R~ - R||_F / ||R||_F` (over a sample of columns) of
    /// the operator with refinement `s` and kernel design tolerance `tolerance`, without
    /// building it.
    #[allow(clippy::too_many_arguments)]
    pub fn estimate_error<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        s: usize,
        tolerance: f64,
        tif: &T,
    ) -> Result<f64> {
        let layout = Layout::new(
            map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, pitch_mm, s, tolerance, tif,
        )?;
        Ok(layout.estimated_error(dwell_x_mm, dwell_y_mm, tif))
    }

    /// The smallest refinement `s` in `1..=MAX_REFINEMENT` whose estimated error is within
    /// `tolerance`, with that error; otherwise (`Err`) the refinement with the smallest error
    /// and that error. Stops early when a refinement gains less than a factor 2 on the one
    /// before (the TIF's own content beyond the band, not the lattice, then sets the error), or
    /// when the error at `s = 1` exceeds the tolerance a thousandfold.
    pub fn refinement_for<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        tif: &T,
        tolerance: f64,
    ) -> Result<std::result::Result<(usize, f64), (usize, f64)>> {
        let mut best = (1, f64::INFINITY);
        for s in 1..=MAX_REFINEMENT {
            let e = Self::estimate_error(
                map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, pitch_mm, s, tolerance, tif,
            )?;
            if e <= tolerance {
                return Ok(Ok((s, e)));
            }
            // A finer lattice widens the band kept; a TIF whose error at the map's own band is
            // more than `GIVE_UP` times the tolerance has content (steps, kinks, noise) far
            // beyond it, and the further estimates would cost more than they could find.
            let stalled = e > 0.5 * best.1 || (s == 1 && e > GIVE_UP * tolerance);
            if e < best.1 {
                best = (s, e);
            }
            if stalled {
                break;
            }
        }
        Ok(Err(best))
    }

    /// Builds the operator for map points on a lattice of pitch `pitch_mm` (through their lowest
    /// x and y) and dwell points anywhere: fine pitch `pitch_mm / s`, ES kernel designed for
    /// `tolerance`.
    #[allow(clippy::too_many_arguments)]
    pub fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        s: usize,
        tolerance: f64,
        tif: &T,
    ) -> Result<Self> {
        let layout = Layout::new(
            map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, pitch_mm, s, tolerance, tif,
        )?;
        let estimated_error = layout.estimated_error(dwell_x_mm, dwell_y_mm, tif);
        let w = layout.es.width;
        let i0 = layout.first.iter().map(|p| p.0).min().unwrap_or(0);
        let j0 = layout.first.iter().map(|p| p.1).min().unwrap_or(0);
        let i1 = layout.first.iter().map(|p| p.0).max().unwrap_or(0) + w as i64;
        let j1 = layout.first.iter().map(|p| p.1).max().unwrap_or(0) + w as i64;
        let (width, height) = ((i1 - i0) as usize, (j1 - j0) as usize);
        crate::budget::check(
            "dwell points (NUFFT operator)",
            &format!("a fine lattice of {width} x {height} nodes"),
            width as f64 * height as f64 * 48.0,
        )?;
        let fine = pitch_mm / s as f64;
        let mut node_x = Vec::with_capacity(width * height);
        let mut node_y = Vec::with_capacity(width * height);
        for r in 0..height {
            for c in 0..width {
                node_x.push(layout.x0 + (i0 + c as i64) as f64 * fine);
                node_y.push(layout.y0 + (j0 + r as i64) as f64 * fine);
            }
        }
        // The fine lattice's operator over every node: this operator keeps the column sums
        // over the dwell points itself and asks only products of it.
        let inner = FftOperator::for_nodes(
            (map_x_mm, map_y_mm),
            (&node_x, &node_y),
            fine,
            &layout.kernel,
        )?;
        let first: Vec<(u32, u32)> = layout
            .first
            .iter()
            .map(|&(i, j)| ((i - i0) as u32, (j - j0) as u32))
            .collect();
        let bands = height.div_ceil(BAND_ROWS);
        let mut band_points = vec![Vec::new(); bands];
        for (k, &(_, r)) in first.iter().enumerate() {
            let (lo, hi) = (r as usize / BAND_ROWS, (r as usize + w - 1) / BAND_ROWS);
            for b in band_points.iter_mut().take(hi + 1).skip(lo) {
                b.push(k as u32);
            }
        }
        let columns = ColumnStats::new(
            layout.m,
            dwell_x_mm
                .par_iter()
                .zip(dwell_y_mm.par_iter())
                .map(|(&x, &y)| layout.exact_column_sums(x, y, tif))
                .collect(),
        );
        let nodes = width * height;
        Ok(Self {
            inner,
            refinement: s,
            fine_pitch_mm: fine,
            es: layout.es,
            first,
            weights: layout.weights,
            width,
            height,
            band_points,
            columns,
            estimated_error,
            tolerance,
            m: layout.m,
            work: Mutex::new((vec![0.0; nodes], vec![0.0; nodes])),
        })
    }

    /// The refinement `s` (fine lattice pitch = map pitch / `s`).
    pub fn refinement(&self) -> usize {
        self.refinement
    }

    /// Pitch of the fine lattice, mm.
    pub fn fine_pitch_mm(&self) -> f64 {
        self.fine_pitch_mm
    }

    /// The spreading kernel.
    pub fn kernel(&self) -> EsKernel {
        self.es
    }

    /// The tolerance the kernel was designed for.
    pub fn tolerance(&self) -> f64 {
        self.tolerance
    }

    /// Estimated relative operator error `||R~ - R||_F / ||R||_F` against the exact contract,
    /// over an evenly spaced sample of columns.
    pub fn estimated_error(&self) -> f64 {
        self.estimated_error
    }

    /// Non-zero entries of the exact `R` (over the map points).
    pub fn nnz(&self) -> usize {
        self.columns.nnz()
    }

    /// Dwell points whose exact column is empty: no map point in the tool's reach.
    pub fn empty_columns(&self) -> Vec<usize> {
        self.columns.empty_columns()
    }

    /// `nodes = S t`: band by band, each band's dwell points in ascending order.
    fn spread(&self, t: &[f64], nodes: &mut [f64]) {
        let (w, width) = (self.es.width, self.width);
        nodes
            .par_chunks_mut(BAND_ROWS * width)
            .zip(self.band_points.par_iter())
            .enumerate()
            .for_each(|(band, (rows, points))| {
                rows.fill(0.0);
                let r0 = band * BAND_ROWS;
                let r1 = r0 + rows.len() / width;
                for &k in points {
                    let k = k as usize;
                    let (c, r) = (self.first[k].0 as usize, self.first[k].1 as usize);
                    let (wx, wy) = self.weights[2 * w * k..2 * w * (k + 1)].split_at(w);
                    let tk = t[k];
                    for (q, &wyq) in wy.iter().enumerate() {
                        let row = r + q;
                        if row < r0 || row >= r1 {
                            continue;
                        }
                        let f = tk * wyq;
                        let dst = &mut rows[(row - r0) * width + c..(row - r0) * width + c + w];
                        for (d, &wxp) in dst.iter_mut().zip(wx) {
                            *d += f * wxp;
                        }
                    }
                }
            });
    }

    /// `out = S^T nodes`.
    fn gather(&self, nodes: &[f64], out: &mut [f64]) {
        let (w, width) = (self.es.width, self.width);
        out.par_iter_mut()
            .enumerate()
            .with_min_len(256)
            .for_each(|(k, o)| {
                let (c, r) = (self.first[k].0 as usize, self.first[k].1 as usize);
                let (wx, wy) = self.weights[2 * w * k..2 * w * (k + 1)].split_at(w);
                let mut sum = 0.0;
                for (q, &wyq) in wy.iter().enumerate() {
                    let src = &nodes[(r + q) * width + c..(r + q) * width + c + w];
                    let row: f64 = src.iter().zip(wx).map(|(a, b)| a * b).sum();
                    sum += wyq * row;
                }
                *o = sum;
            });
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Vec<f64>, Vec<f64>)> {
        // A panic while holding the work vectors leaves them merely stale: they are overwritten
        // before every use.
        self.work.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl LinearOperator for NufftOperator {
    fn nrows(&self) -> usize {
        self.m
    }

    fn products_cheap_per_dwell_point(&self) -> bool {
        true
    }

    fn ncols(&self) -> usize {
        self.first.len()
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (a, _) = &mut *work;
        self.spread(t, a);
        self.inner.apply(a, out);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (_, b) = &mut *work;
        self.inner.apply_transpose(y, b);
        self.gather(b, out);
    }

    fn apply_normal(&self, t: &[f64], scratch: &mut [f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (a, b) = &mut *work;
        self.spread(t, a);
        self.inner.apply_normal(a, scratch, b);
        self.gather(b, out);
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.columns.centred_norms_sq()
    }
}

impl InfluenceOperator for NufftOperator {
    fn kind(&self) -> OperatorKind {
        OperatorKind::Nufft
    }

    fn shape(&self) -> (usize, usize) {
        (LinearOperator::nrows(self), LinearOperator::ncols(self))
    }

    fn nnz(&self) -> usize {
        NufftOperator::nnz(self)
    }

    fn empty_columns(&self) -> Vec<usize> {
        NufftOperator::empty_columns(self)
    }

    /// The operator itself: its products need no copy, and it has no Gram matrix.
    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::InfluenceMatrix;
    use crate::observer::Silent as NoopObserver;
    use crate::rng::SplitMix64 as Rng;
    use crate::tif::GaussianTif;

    /// A 61 x 41 map at 0.4 mm with a round hole, and dwell points on a 0.55 mm raster at an
    /// arbitrary phase against the map lattice.
    fn case() -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut mx, mut my) = (Vec::new(), Vec::new());
        for j in 0..41 {
            for i in 0..61 {
                let (x, y) = (i as f64 * 0.4, j as f64 * 0.4);
                if (x - 12.0).powi(2) + (y - 8.0).powi(2) < 9.0 {
                    continue;
                }
                mx.push(x);
                my.push(y);
            }
        }
        let (mut dx, mut dy) = (Vec::new(), Vec::new());
        for j in 0..30 {
            for i in 0..44 {
                dx.push(0.1371 + i as f64 * 0.55);
                dy.push(0.2619 + j as f64 * 0.55);
            }
        }
        (mx, my, dx, dy)
    }

    /// A smooth Gaussian (cut at 8 sigma, where its step is 1.3e-14 of the peak).
    fn smooth() -> GaussianTif {
        GaussianTif::new(1.5, 10.0, 12.0).unwrap()
    }

    fn rel(a: &[f64], b: &[f64]) -> f64 {
        let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
        let n: f64 = b.iter().map(|y| y * y).sum();
        (d / n).sqrt()
    }

    /// Relative errors of `R~ t` and `R~^T r` against the assembled `R` for random `t`, `r`.
    fn product_errors<T: InfluenceFunction>(op: &NufftOperator, tif: &T) -> (f64, f64) {
        let (mx, my, dx, dy) = case();
        let exact = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, tif, &NoopObserver).unwrap();
        let csc = exact.csc();
        let mut rng = Rng::new(7);
        let t: Vec<f64> = (0..dx.len()).map(|_| rng.uniform()).collect();
        let r: Vec<f64> = (0..mx.len()).map(|_| rng.uniform() - 0.5).collect();
        let mut rt = vec![0.0; mx.len()];
        let mut rtr = vec![0.0; dx.len()];
        for (j, col) in csc.col_iter().enumerate() {
            for (&i, &v) in col.row_indices().iter().zip(col.values()) {
                rt[i] += v * t[j];
                rtr[j] += v * r[i];
            }
        }
        let mut a = vec![0.0; mx.len()];
        op.apply(&t, &mut a);
        let mut b = vec![0.0; dx.len()];
        op.apply_transpose(&r, &mut b);
        (rel(&a, &rt), rel(&b, &rtr))
    }

    #[test]
    fn es_kernel_width_follows_the_tolerance() {
        // FINUFFT's widths at sigma = 2: ceil(log10(1 / eps)) + 1 to within one.
        for (eps, w) in [(1e-6, 7), (1e-9, 10)] {
            let k = EsKernel::for_tolerance(eps, 2.0);
            assert!((k.width as i64 - w).abs() <= 1, "{eps}: {}", k.width);
        }
        // phi^ against a plain Riemann sum of the definition.
        let k = EsKernel::for_tolerance(1e-6, 2.0);
        for xi in [0.0, 0.7, 1.5] {
            let n = 200_000;
            let h = k.width as f64 / n as f64;
            let riemann: f64 = (0..n)
                .map(|i| {
                    let z = -(k.width as f64) / 2.0 + (i as f64 + 0.5) * h;
                    k.value(z) * (xi * z).cos() * h
                })
                .sum();
            assert!((k.fourier(xi) - riemann).abs() < 1e-8 * k.fourier(0.0));
        }
    }

    #[test]
    fn products_match_the_assembled_matrix_within_the_tolerance() {
        let (mx, my, dx, dy) = case();
        let tif = smooth();
        // At 1e-9 the Gaussian's content beyond the band of the map pitch (2.8e-8 of its peak
        // at pi / (2 h)) needs a finer lattice: the refinement is chosen from the estimate.
        for (tol, expect_s) in [(1e-6, 1), (1e-9, 2)] {
            let (s, _) = NufftOperator::refinement_for(&mx, &my, &dx, &dy, 0.4, &tif, tol)
                .unwrap()
                .unwrap();
            assert_eq!(s, expect_s, "tol {tol}");
            let op = NufftOperator::new(&mx, &my, &dx, &dy, 0.4, s, tol, &tif).unwrap();
            let (e_apply, e_transpose) = product_errors(&op, &tif);
            assert!(e_apply < tol, "tol {tol}: R t error {e_apply:.2e}");
            assert!(
                e_transpose < tol,
                "tol {tol}: R^T r error {e_transpose:.2e}"
            );
            assert!(op.estimated_error() < tol, "{:.2e}", op.estimated_error());
        }
    }

    #[test]
    fn products_match_the_swept_kernel_within_the_tolerance() {
        use crate::influence::SweptTif;
        // The Gaussian averaged over a 0.55 mm stretch along x (nine samples).
        let samples: Vec<[f64; 3]> = (0..9)
            .map(|k| [-0.275 + k as f64 * 0.55 / 8.0, 0.0, 1.0 / 9.0])
            .collect();
        let tif = SweptTif::new(smooth(), samples);
        let (mx, my, dx, dy) = case();
        let tol = 1e-6;
        let op = NufftOperator::new(&mx, &my, &dx, &dy, 0.4, 1, tol, &tif).unwrap();
        let (e_apply, e_transpose) = product_errors(&op, &tif);
        assert!(e_apply < tol, "R t error {e_apply:.2e}");
        assert!(e_transpose < tol, "R^T r error {e_transpose:.2e}");
    }

    #[test]
    fn transpose_is_the_adjoint_and_normal_is_the_product() {
        let (mx, my, dx, dy) = case();
        let op = NufftOperator::new(&mx, &my, &dx, &dy, 0.4, 2, 1e-6, &smooth()).unwrap();
        let mut rng = Rng::new(3);
        let t: Vec<f64> = (0..dx.len()).map(|_| rng.uniform()).collect();
        let y: Vec<f64> = (0..mx.len()).map(|_| rng.uniform() - 0.5).collect();
        let mut rt = vec![0.0; mx.len()];
        op.apply(&t, &mut rt);
        let mut rty = vec![0.0; dx.len()];
        op.apply_transpose(&y, &mut rty);
        let lhs: f64 = rt.iter().zip(&y).map(|(a, b)| a * b).sum();
        let rhs: f64 = t.iter().zip(&rty).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() <= 1e-10 * lhs.abs().max(rhs.abs()));
        let mut scratch = vec![0.0; mx.len()];
        let mut normal = vec![0.0; dx.len()];
        op.apply_normal(&t, &mut scratch, &mut normal);
        let mut two = vec![0.0; dx.len()];
        op.apply_transpose(&rt, &mut two);
        assert!(rel(&normal, &two) < 1e-10);
    }

    #[test]
    fn a_kinked_tif_shows_its_error_in_the_estimate() {
        // A Gaussian cut at 2 sigma keeps a 13.5% step: its content beyond the band is large,
        // and the estimate (and the product error) say so, far above the design tolerance.
        let tif = GaussianTif::new(1.5, 10.0, 3.0).unwrap();
        let (mx, my, dx, dy) = case();
        let op = NufftOperator::new(&mx, &my, &dx, &dy, 0.4, 1, 1e-6, &tif).unwrap();
        let (e_apply, _) = product_errors(&op, &tif);
        assert!(op.estimated_error() > 1e-3, "{:.2e}", op.estimated_error());
        assert!(e_apply > 1e-5, "{e_apply:.2e}");
    }
}
