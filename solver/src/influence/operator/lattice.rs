//! The lattice plumbing of the FFT-based operators ([`super::fft`], [`super::complement`]): the
//! cells of points on a lattice, the real-to-complex row and complex column transforms with their
//! reused buffers, transform sizes with small prime factors, and lattice indices of coordinates
//! with the measured error of an off-lattice approximation.

use crate::error::{twelve_figures, Error, Result};
use rayon::prelude::*;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// Relative tolerance for a coordinate to count as on the lattice.
pub(super) const ON_LATTICE_TOL: f64 = 1e-6;

/// What an allocation failure of the lattice's buffers names.
pub(super) const LATTICE_WHAT: &str = "FFT lattice";

/// Points on a lattice `width` cells wide: their cells, the points ordered by cell with each
/// lattice row's range, and the rows holding a point (only those rows are transformed forward
/// when scattered from, and back when gathered into).
pub(super) struct Cells {
    pub(super) width: usize,
    pub(super) cells: Vec<usize>,
    pub(super) by_cell: Vec<usize>,
    pub(super) row_start: Vec<usize>,
    pub(super) rows: Vec<bool>,
}

impl Cells {
    pub(super) fn new(cells: Vec<usize>, width: usize, height: usize) -> Self {
        let mut by_cell: Vec<usize> = (0..cells.len()).collect();
        by_cell.sort_by_key(|&k| cells[k]);
        let mut row_start = vec![0; height + 1];
        for &c in &cells {
            row_start[c / width + 1] += 1;
        }
        for r in 0..height {
            row_start[r + 1] += row_start[r];
        }
        let rows = row_start.windows(2).map(|w| w[1] > w[0]).collect();
        Self {
            width,
            cells,
            by_cell,
            row_start,
            rows,
        }
    }

    pub(super) fn len(&self) -> usize {
        self.cells.len()
    }

    /// `row` = lattice row `r` holding `values` at the cells in it (summed where points share
    /// a cell, in a fixed order), zero elsewhere.
    pub(super) fn scatter_row(&self, r: usize, values: &[f64], row: &mut [f64]) {
        row.iter_mut().for_each(|v| *v = 0.0);
        let base = r * self.width;
        for &k in &self.by_cell[self.row_start[r]..self.row_start[r + 1]] {
            row[self.cells[k] - base] += values[k];
        }
    }

    /// Lattice row `r`: each cell holding points times `scale` and their number, the others zero
    /// (gathering the row at the points and scattering it back).
    pub(super) fn mask_row(&self, r: usize, scale: f64, row: &mut [f64]) {
        let base = r * self.width;
        let points = &self.by_cell[self.row_start[r]..self.row_start[r + 1]];
        let mut next = 0;
        for same in points.chunk_by(|&a, &b| self.cells[a] == self.cells[b]) {
            let c = self.cells[same[0]] - base;
            row[next..c].iter_mut().for_each(|v| *v = 0.0);
            row[c] *= same.len() as f64 * scale;
            next = c + 1;
        }
        row[next..].iter_mut().for_each(|v| *v = 0.0);
    }

    /// `out[k] = scale real[cells[k]]`.
    pub(super) fn gather(&self, real: &[f64], scale: f64, out: &mut [f64]) {
        out.par_iter_mut()
            .zip(self.cells.par_iter())
            .with_min_len(4096)
            .for_each(|(o, &c)| *o = real[c] * scale);
    }
}

/// The 2-D real transform: real-to-complex along x (`fx / 2 + 1` frequencies), complex along y.
pub(super) struct Transforms {
    pub(super) fx: usize,
    pub(super) fy: usize,
    pub(super) r2c_x: Arc<dyn RealToComplex<f64>>,
    pub(super) c2r_x: Arc<dyn ComplexToReal<f64>>,
    pub(super) fft_y: Arc<dyn Fft<f64>>,
    pub(super) ifft_y: Arc<dyn Fft<f64>>,
    /// Scratch length enough for every one of the four transforms.
    pub(super) scratch_len: usize,
}

/// Reused by every product: the real lattice (`fy` rows of `fx`), its row spectra (`fy` rows of
/// `fx / 2 + 1`) and their transpose (`fx / 2 + 1` rows of `fy`), where the y transforms run.
pub(super) struct Buffers {
    pub(super) real: Vec<f64>,
    pub(super) rows: Vec<Complex<f64>>,
    pub(super) columns: Vec<Complex<f64>>,
}

/// The smallest `k >= n` whose prime factors are all 2, 3, 5 or 7.
pub(crate) fn smooth_size(n: usize) -> usize {
    (n.max(1)..)
        .find(|&k| {
            let mut r = k;
            for p in [2, 3, 5, 7] {
                while r % p == 0 {
                    r /= p;
                }
            }
            r == 1
        })
        .unwrap_or(n)
}

/// Signed lattice index of `v` on the lattice of pitch `pitch` through `origin`.
pub(crate) fn lattice_index(v: f64, origin: f64, pitch: f64) -> Option<i64> {
    let u = (v - origin) / pitch;
    let k = u.round();
    ((u - k).abs() <= ON_LATTICE_TOL && k.abs() < 1e15).then_some(k as i64)
}

/// The error for point `k` of `what` at `(x, y)` mm, off the lattice of pitch `pitch_mm` mm
/// through `origin` (numbers to [`twelve_figures`]).
pub(crate) fn off_lattice_error(
    what: &str,
    k: usize,
    (x, y): (f64, f64),
    pitch_mm: f64,
    (x0, y0): (f64, f64),
) -> Error {
    let f = twelve_figures;
    Error::invalid(
        what,
        format!(
            "{k} at ({}, {}) mm is not on the map's {} mm lattice through ({}, {}) mm",
            f(x),
            f(y),
            f(pitch_mm),
            f(x0),
            f(y0)
        ),
    )
}

impl Buffers {
    /// The zeroed buffers of an `fx` x `fy` lattice; an error where the memory cannot be had.
    pub(super) fn new(fx: usize, fy: usize) -> Result<Self> {
        let hx = fx / 2 + 1;
        let zero = Complex::new(0.0, 0.0);
        Ok(Self {
            real: crate::budget::try_filled(LATTICE_WHAT, fx * fy, 0.0)?,
            rows: crate::budget::try_filled(LATTICE_WHAT, hx * fy, zero)?,
            columns: crate::budget::try_filled(LATTICE_WHAT, hx * fy, zero)?,
        })
    }
}

/// How a row pass fills a row of the real lattice before its forward transform along x.
#[derive(Clone, Copy)]
pub(super) enum Fill<'a> {
    /// The row is already in `real` (every row is transformed).
    Ready,
    /// The points' values scattered onto the row (summed where points share a cell); rows
    /// holding no point are zero and not transformed.
    Scatter(&'a Cells, &'a [f64]),
    /// The row of the signal whose spectrum (transformed back along y) is in `columns`,
    /// transformed back along x and kept at the points' cells only, times the number of points
    /// in the cell and `scale`: gathering at the points and scattering back, in one pass.
    Masked(&'a Cells, f64),
}

/// What a column pass does after the forward transform along y.
#[derive(Clone, Copy)]
pub(super) enum Spectrum<'a> {
    /// Keeps the spectrum.
    Keep,
    /// Multiplies by the kernel's spectrum (column-major) and transforms back along y.
    Convolve(&'a [Complex<f64>]),
    /// Multiplies by the conjugate of the kernel's spectrum and transforms back along y.
    Correlate(&'a [Complex<f64>]),
}

impl Transforms {
    pub(super) fn new(
        fx: usize,
        fy: usize,
        planner: &mut FftPlanner<f64>,
        real_planner: &mut RealFftPlanner<f64>,
    ) -> Self {
        let (r2c_x, c2r_x) = (
            real_planner.plan_fft_forward(fx),
            real_planner.plan_fft_inverse(fx),
        );
        let (fft_y, ifft_y) = (planner.plan_fft_forward(fy), planner.plan_fft_inverse(fy));
        let scratch_len = r2c_x
            .get_scratch_len()
            .max(c2r_x.get_scratch_len())
            .max(fft_y.get_inplace_scratch_len())
            .max(ifft_y.get_inplace_scratch_len());
        Self {
            fx,
            fy,
            r2c_x,
            c2r_x,
            fft_y,
            ifft_y,
            scratch_len,
        }
    }

    /// Every row `r` of `real` (`fx` long) and of the row spectra `rows` (`fx / 2 + 1` long) to
    /// `body(r, real_row, spectrum_row, scratch)`, in parallel.
    pub(super) fn row_pass<F>(&self, real: &mut [f64], rows: &mut [Complex<f64>], body: F)
    where
        F: Fn(usize, &mut [f64], &mut [Complex<f64>], &mut [Complex<f64>]) + Sync,
    {
        let (fx, hx) = (self.fx, self.fx / 2 + 1);
        real.par_chunks_mut(fx)
            .zip(rows.par_chunks_mut(hx))
            .enumerate()
            .for_each_init(
                || vec![Complex::new(0.0, 0.0); self.scratch_len],
                |scratch, (r, (real_row, spectrum_row))| body(r, real_row, spectrum_row, scratch),
            );
    }

    /// Every column `kx` (`fy` long) of `columns` to `body(kx, column, scratch)`, in parallel.
    pub(super) fn column_pass<F>(&self, columns: &mut [Complex<f64>], body: F)
    where
        F: Fn(usize, &mut [Complex<f64>], &mut [Complex<f64>]) + Sync,
    {
        columns.par_chunks_mut(self.fy).enumerate().for_each_init(
            || vec![Complex::new(0.0, 0.0); self.scratch_len],
            |scratch, (kx, column)| body(kx, column, scratch),
        );
    }

    /// `spectrum_row` = row `r` of the column-major spectrum `columns` (a strided read: rayon
    /// hands each thread a contiguous range of rows, so the cache lines read for one row mostly
    /// serve the next ones too).
    pub(super) fn read_row(
        &self,
        columns: &[Complex<f64>],
        r: usize,
        spectrum_row: &mut [Complex<f64>],
    ) {
        for (kx, s) in spectrum_row.iter_mut().enumerate() {
            *s = columns[kx * self.fy + r];
        }
    }

    /// `column` = column `kx` of the row-major spectrum `rows` (a strided read, as in
    /// [`Transforms::read_row`]).
    pub(super) fn read_column(
        &self,
        rows: &[Complex<f64>],
        kx: usize,
        column: &mut [Complex<f64>],
    ) {
        let hx = self.fx / 2 + 1;
        for (ky, c) in column.iter_mut().enumerate() {
            *c = rows[ky * hx + kx];
        }
    }

    /// `spectrum_row` = the x transform of `real_row` (used as scratch).
    pub(super) fn r2c(
        &self,
        real_row: &mut [f64],
        spectrum_row: &mut [Complex<f64>],
        scratch: &mut [Complex<f64>],
    ) {
        // Lengths match the plan by construction; the only error is a length one.
        let _ = self
            .r2c_x
            .process_with_scratch(real_row, spectrum_row, scratch);
    }

    /// `real_row` = the inverse x transform of `spectrum_row` (used as scratch).
    pub(super) fn c2r(
        &self,
        spectrum_row: &mut [Complex<f64>],
        real_row: &mut [f64],
        scratch: &mut [Complex<f64>],
    ) {
        // The spectrum of a real signal has real DC (and Nyquist) terms; clear the rounding left
        // in their imaginary parts, which the transform ignores.
        let hx = spectrum_row.len();
        spectrum_row[0].im = 0.0;
        if 2 * (hx - 1) == self.fx {
            spectrum_row[hx - 1].im = 0.0;
        }
        let _ = self
            .c2r_x
            .process_with_scratch(spectrum_row, real_row, scratch);
    }

    /// Forward transform (unnormalised) of the lattice filled by `fill` into `b.columns`, then
    /// `after`: one row pass (fill, x transform) and one column pass (read the column, y
    /// transform, and for a convolution the multiplication and the inverse y transform).
    /// `b.real` and `b.rows` are left as scratch.
    pub(super) fn spectrum(&self, b: &mut Buffers, fill: Fill<'_>, after: Spectrum<'_>) {
        let fy = self.fy;
        let Buffers {
            real,
            rows,
            columns,
        } = b;
        let zero = |s: &mut [Complex<f64>]| s.iter_mut().for_each(|c| *c = Complex::new(0.0, 0.0));
        let read_from = &*columns;
        self.row_pass(
            real,
            rows,
            |r, real_row, spectrum_row, scratch| match fill {
                Fill::Ready => self.r2c(real_row, spectrum_row, scratch),
                Fill::Scatter(cells, _) | Fill::Masked(cells, _) if !cells.rows[r] => {
                    zero(spectrum_row)
                }
                Fill::Scatter(cells, values) => {
                    cells.scatter_row(r, values, real_row);
                    self.r2c(real_row, spectrum_row, scratch);
                }
                Fill::Masked(cells, scale) => {
                    self.read_row(read_from, r, spectrum_row);
                    self.c2r(spectrum_row, real_row, scratch);
                    cells.mask_row(r, scale, real_row);
                    self.r2c(real_row, spectrum_row, scratch);
                }
            },
        );
        let rows = &*rows;
        self.column_pass(columns, |kx, column, scratch| {
            self.read_column(rows, kx, column);
            self.fft_y.process_with_scratch(column, scratch);
            let (k, conj) = match after {
                Spectrum::Keep => return,
                Spectrum::Convolve(k) => (&k[kx * fy..(kx + 1) * fy], false),
                Spectrum::Correlate(k) => (&k[kx * fy..(kx + 1) * fy], true),
            };
            if conj {
                column.iter_mut().zip(k).for_each(|(c, k)| *c *= k.conj());
            } else {
                column.iter_mut().zip(k).for_each(|(c, k)| *c *= k);
            }
            self.ifft_y.process_with_scratch(column, scratch);
        });
    }

    /// `b.real` = the inverse x transform, for the rows marked in `rows_wanted` (others left as
    /// they were), of the signal whose spectrum transformed back along y is in `b.columns`
    /// (unnormalised; one row pass). `b.rows` is left as scratch.
    pub(super) fn to_real(&self, b: &mut Buffers, rows_wanted: &[bool]) {
        let Buffers {
            real,
            rows,
            columns,
        } = b;
        let read_from = &*columns;
        self.row_pass(real, rows, |r, real_row, spectrum_row, scratch| {
            if rows_wanted[r] {
                self.read_row(read_from, r, spectrum_row);
                self.c2r(spectrum_row, real_row, scratch);
            }
        });
    }
}
