//! A matrix-free influence operator for map and dwell points on one regular lattice with a
//! shift-invariant TIF: `R t` and `R^T y` by zero-padded 2-D FFT convolution (rustfft), so `R` is
//! never formed.
//!
//! Map points and dwell points must lie on a common lattice of pitch `h` (the map pitch; the
//! dwell pitch a multiple of it). With lattice indices `p_i` (map) and `q_j` (dwell),
//! `R[i, j] = K[p_i - q_j]`, `K[d] = TIF(d h)` for `|d| <= ceil(radius / h)`. `R t` scatters `t` onto
//! the lattice, convolves with `K` and gathers at the map points; `R^T y` scatters `y`, correlates
//! with `K` (multiplies by the conjugate transform) and gathers at the dwell points. The lattice
//! is padded to `N + kr` per axis so the circular convolution equals the linear one on the points
//! read (no wrap-around).

use super::operator::LinearOperator;
use crate::error::{Error, Result};
use crate::tif::InfluenceFunction;
use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};
use std::sync::{Arc, Mutex};

/// Relative tolerance for a coordinate to count as on the lattice.
const ON_LATTICE_TOL: f64 = 1e-6;
/// Largest lattice (cells) the operator accepts: 4e8 cells of 16 bytes in three buffers is ~19 GB.
const MAX_LATTICE_CELLS: usize = 400_000_000;

/// The FFT convolution operator (see the module documentation).
pub struct FftOperator {
    fx: usize,
    fy: usize,
    kernel_hat: Vec<Complex<f64>>,
    map_cells: Vec<usize>,
    dwell_cells: Vec<usize>,
    /// `(k, k^2)` sums of each column over the map points, for the Jacobi scaling.
    col_sums: Vec<(f64, f64)>,
    /// Non-zero entries of each column of the implicit `R`.
    col_nnz: Vec<usize>,
    fft_x: Arc<dyn Fft<f64>>,
    ifft_x: Arc<dyn Fft<f64>>,
    fft_y: Arc<dyn Fft<f64>>,
    ifft_y: Arc<dyn Fft<f64>>,
    buffer: Mutex<Buffers>,
}

/// The lattice buffer and the transpose scratch, reused by every product.
type Buffers = (Vec<Complex<f64>>, Vec<Complex<f64>>);

impl std::fmt::Debug for FftOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FftOperator")
            .field("fx", &self.fx)
            .field("fy", &self.fy)
            .field("m", &self.map_cells.len())
            .field("n", &self.dwell_cells.len())
            .finish()
    }
}

/// Signed lattice index of `v` on the lattice of pitch `pitch` through `origin`.
fn lattice_index(v: f64, origin: f64, pitch: f64) -> Option<i64> {
    let u = (v - origin) / pitch;
    let k = u.round();
    ((u - k).abs() <= ON_LATTICE_TOL && k.abs() < 1e15).then_some(k as i64)
}

impl FftOperator {
    /// Builds the operator for map points `(x, y)` and dwell points `(X, Y)` (mm) on a lattice of
    /// pitch `pitch_mm`; an error when a point is off the lattice or two dwell points share a cell.
    pub fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        tif: &T,
    ) -> Result<Self> {
        if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
            return Err(Error::invalid("lattice pitch", format!("{pitch_mm}")));
        }
        if map_x_mm.is_empty() || dwell_x_mm.is_empty() {
            return Err(Error::invalid("FFT operator", "needs map and dwell points"));
        }
        // The lattice runs through the map's lowest x and y; dwell points must lie on it too.
        let x0 = map_x_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let y0 = map_y_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let idx = |xs: &[f64], ys: &[f64], what| -> Result<Vec<(i64, i64)>> {
            xs.iter()
                .zip(ys)
                .enumerate()
                .map(|(k, (&x, &y))| {
                    match (
                        lattice_index(x, x0, pitch_mm),
                        lattice_index(y, y0, pitch_mm),
                    ) {
                        (Some(i), Some(j)) => Ok((i, j)),
                        _ => Err(Error::invalid(
                            what,
                            format!(
                                "{k} at ({x}, {y}) mm is not on the map's {pitch_mm} mm lattice \
                                 through ({x0}, {y0}) mm"
                            ),
                        )),
                    }
                })
                .collect()
        };
        let map_signed = idx(map_x_mm, map_y_mm, "map point")?;
        let dwell_signed = idx(dwell_x_mm, dwell_y_mm, "dwell point")?;
        let (i0, j0) = map_signed
            .iter()
            .chain(&dwell_signed)
            .fold((i64::MAX, i64::MAX), |(a, b), p| (a.min(p.0), b.min(p.1)));
        let shift = |v: &[(i64, i64)]| -> Vec<(usize, usize)> {
            v.iter()
                .map(|&(i, j)| ((i - i0) as usize, (j - j0) as usize))
                .collect()
        };
        let (map_ij, dwell_ij) = (shift(&map_signed), shift(&dwell_signed));
        let nx = map_ij
            .iter()
            .chain(&dwell_ij)
            .map(|p| p.0)
            .max()
            .unwrap_or(0)
            + 1;
        let ny = map_ij
            .iter()
            .chain(&dwell_ij)
            .map(|p| p.1)
            .max()
            .unwrap_or(0)
            + 1;
        // A lattice too large to hold (points spread over a huge area) is an input error.
        if nx.saturating_mul(ny) > MAX_LATTICE_CELLS {
            return Err(Error::invalid(
                "FFT operator",
                format!(
                    "the points span {nx} x {ny} cells of {pitch_mm} mm, more than {MAX_LATTICE_CELLS}"
                ),
            ));
        }
        let kr = (tif.support_radius_mm() / pitch_mm).ceil() as usize;
        let (fx, fy) = (nx + kr + 1, ny + kr + 1);
        let cell = |(i, j): (usize, usize)| j * fx + i;
        let map_cells: Vec<usize> = map_ij.iter().map(|&p| cell(p)).collect();
        let dwell_cells: Vec<usize> = dwell_ij.iter().map(|&p| cell(p)).collect();
        let mut seen = vec![false; fx * fy];
        for (j, &c) in dwell_cells.iter().enumerate() {
            if std::mem::replace(&mut seen[c], true) {
                return Err(Error::invalid(
                    "dwell point",
                    format!("{j} shares a lattice cell with an earlier dwell point"),
                ));
            }
        }
        let mut planner = FftPlanner::<f64>::new();
        let fft_x = planner.plan_fft_forward(fx);
        let ifft_x = planner.plan_fft_inverse(fx);
        let fft_y = planner.plan_fft_forward(fy);
        let ifft_y = planner.plan_fft_inverse(fy);
        // Kernel K[d] = TIF(d h), wrapped.
        let k = kr as isize;
        let mut kernel = vec![Complex::new(0.0, 0.0); fx * fy];
        let mut taps: Vec<(isize, isize, f64)> = Vec::new();
        for dy in -k..=k {
            for dx in -k..=k {
                let v = tif.rate_nm_per_s(dx as f64 * pitch_mm, dy as f64 * pitch_mm);
                if v != 0.0 {
                    let ix = dx.rem_euclid(fx as isize) as usize;
                    let iy = dy.rem_euclid(fy as isize) as usize;
                    kernel[iy * fx + ix] = Complex::new(v, 0.0);
                    taps.push((dx, dy, v));
                }
            }
        }
        let mut scratch = vec![Complex::new(0.0, 0.0); fx * fy];
        fft2(&mut kernel, &mut scratch, fx, fy, &fft_x, &fft_y);
        // Column sums over the map points for the Jacobi scaling.
        let mut map_of = vec![false; fx * fy];
        for &c in &map_cells {
            map_of[c] = true;
        }
        let (col_sums, col_nnz): (Vec<(f64, f64)>, Vec<usize>) = dwell_ij
            .iter()
            .map(|&(i, j)| {
                let (mut s, mut s2, mut count) = (0.0, 0.0, 0usize);
                for &(dx, dy, v) in &taps {
                    let (a, b) = (i as isize + dx, j as isize + dy);
                    if a >= 0
                        && b >= 0
                        && (a as usize) < nx
                        && (b as usize) < ny
                        && map_of[b as usize * fx + a as usize]
                    {
                        s += v;
                        s2 += v * v;
                        count += 1;
                    }
                }
                ((s, s2), count)
            })
            .unzip();
        Ok(Self {
            fx,
            fy,
            kernel_hat: kernel,
            map_cells,
            dwell_cells,
            col_sums,
            col_nnz,
            fft_x,
            ifft_x,
            fft_y,
            ifft_y,
            buffer: Mutex::new((scratch, vec![Complex::new(0.0, 0.0); fx * fy])),
        })
    }

    /// Non-zero entries of the implicit matrix `R` (the number the sparse operator would store).
    pub fn nnz(&self) -> usize {
        self.col_nnz.iter().sum()
    }

    /// Dwell points whose column is empty: no map point lies in the tool's reach.
    pub fn empty_columns(&self) -> Vec<usize> {
        self.col_nnz
            .iter()
            .enumerate()
            .filter(|(_, &c)| c == 0)
            .map(|(j, _)| j)
            .collect()
    }

    /// The pitch, mm, of the lattice the map points lie on: the smallest step between distinct
    /// sorted x or y coordinates (steps below 1e-9 mm count as equal coordinates). `None` for
    /// fewer than two distinct coordinates on both axes. Whether every point (and every dwell
    /// point) is on that lattice is checked by [`FftOperator::new`].
    pub fn lattice_pitch_mm(map_x_mm: &[f64], map_y_mm: &[f64]) -> Option<f64> {
        let smallest_step = |v: &[f64]| -> f64 {
            let mut sorted: Vec<f64> = v.iter().copied().filter(|a| a.is_finite()).collect();
            sorted.sort_by(f64::total_cmp);
            sorted
                .windows(2)
                .map(|w| w[1] - w[0])
                .filter(|d| *d > 1e-9)
                .fold(f64::INFINITY, f64::min)
        };
        let pitch = smallest_step(map_x_mm).min(smallest_step(map_y_mm));
        pitch.is_finite().then_some(pitch)
    }

    /// Scatter `input` at `from`, multiply the transform by `K^` (or its conjugate), gather at `to`.
    fn convolve(&self, input: &[f64], from: &[usize], to: &[usize], conj: bool, out: &mut [f64]) {
        let mut guard = match self.buffer.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        let (buf, scratch) = &mut *guard;
        buf.par_iter_mut().for_each(|c| *c = Complex::new(0.0, 0.0));
        for (&c, &v) in from.iter().zip(input) {
            buf[c] = Complex::new(v, 0.0);
        }
        fft2(buf, scratch, self.fx, self.fy, &self.fft_x, &self.fft_y);
        buf.par_iter_mut()
            .zip(self.kernel_hat.par_iter())
            .for_each(|(b, k)| *b *= if conj { k.conj() } else { *k });
        fft2(buf, scratch, self.fx, self.fy, &self.ifft_x, &self.ifft_y);
        let scale = 1.0 / (self.fx * self.fy) as f64;
        for (o, &c) in out.iter_mut().zip(to) {
            *o = buf[c].re * scale;
        }
    }
}

/// In-place 2-D transform of a row-major `fy x fx` buffer (rows, then columns via a transpose).
fn fft2(
    buf: &mut [Complex<f64>],
    scratch: &mut [Complex<f64>],
    fx: usize,
    fy: usize,
    fft_x: &Arc<dyn Fft<f64>>,
    fft_y: &Arc<dyn Fft<f64>>,
) {
    buf.par_chunks_mut(fx).for_each(|row| fft_x.process(row));
    // Transpose into scratch (fx rows of length fy).
    scratch.par_chunks_mut(fy).enumerate().for_each(|(i, col)| {
        for (j, c) in col.iter_mut().enumerate() {
            *c = buf[j * fx + i];
        }
    });
    scratch
        .par_chunks_mut(fy)
        .for_each(|col| fft_y.process(col));
    buf.par_chunks_mut(fx).enumerate().for_each(|(j, row)| {
        for (i, c) in row.iter_mut().enumerate() {
            *c = scratch[i * fy + j];
        }
    });
}

impl LinearOperator for FftOperator {
    fn nrows(&self) -> usize {
        self.map_cells.len()
    }

    fn ncols(&self) -> usize {
        self.dwell_cells.len()
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        self.convolve(t, &self.dwell_cells, &self.map_cells, false, out);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        self.convolve(y, &self.map_cells, &self.dwell_cells, true, out);
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        let m = self.map_cells.len().max(1) as f64;
        self.col_sums
            .iter()
            .map(|&(s, s2)| (s2 - s * s / m).max(0.0))
            .collect()
    }
}
