//! The removal of a run as a lattice convolution: the contact motion's time density `ρ` on a
//! fine lattice, convolved with the footprint by FFT, read at the measured points.
//!
//! A run leaves `h(x) = Σ_k τ_k (1 + δ (t_k - t_mid) / 3600) f(x - p_k)` (samples `p_k` carrying
//! contact time `τ_k` at program time `t_k`; `δ` the rate's drift per hour). With the samples
//! spread bilinearly onto a lattice of pitch `h` into the densities `ρ0 = Σ τ_k` and
//! `ρ1 = Σ τ_k (t_k - t_mid) / 3600`, `h = f ⊛ ρ0 + δ f ⊛ ρ1`, each a discrete convolution with
//! the footprint sampled at the lattice offsets. The spreading smooths by a tent of width `h`; its
//! transform `sinc²` is divided out of the densities' spectra, so the residual error is the
//! bilinear interpolation's phase-dependent part, `O((h / rho)²)` of the removal with `rho` the
//! footprint's second-moment radius. Measured points on lattice nodes are read exactly; others
//! bilinearly.

use crate::error::{Error, Result};
use crate::tif::InfluenceFunction;
use rayon::prelude::*;
use realfft::RealFftPlanner;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::sync::Arc;

/// The program time at the middle of each dwell point's dwell, `Σ_{i<j} t_i + t_j / 2`, s, the
/// dwell points run in their order.
pub fn mid_times_s(dwell_s: &[f64]) -> Vec<f64> {
    let mut start = 0.0;
    dwell_s
        .iter()
        .map(|&t| {
            let at = start + t / 2.0;
            start += t;
            at
        })
        .collect()
}

/// The contact motion of a run: where the tool touched, for how long and when.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ContactMotion {
    /// x of every sample, mm.
    pub x_mm: Vec<f64>,
    /// y of every sample, mm.
    pub y_mm: Vec<f64>,
    /// Contact time of every sample, s.
    pub dwell_s: Vec<f64>,
    /// Program time at the middle of every sample, s from the program's start.
    pub time_s: Vec<f64>,
}

impl ContactMotion {
    /// Checks lengths, finiteness and that some time is spent in contact.
    pub fn validate(&self) -> Result<()> {
        let n = self.x_mm.len();
        for (what, len) in [
            ("contact y_mm", self.y_mm.len()),
            ("contact dwell_s", self.dwell_s.len()),
            ("contact time_s", self.time_s.len()),
        ] {
            if len != n {
                return Err(Error::LengthMismatch {
                    what,
                    got: len,
                    expected: n,
                });
            }
        }
        for k in 0..n {
            let (x, y, t, at) = (self.x_mm[k], self.y_mm[k], self.dwell_s[k], self.time_s[k]);
            if !(x.is_finite() && y.is_finite() && at.is_finite() && t.is_finite() && t >= 0.0) {
                return Err(Error::invalid(
                    "contact motion",
                    format!(
                        "sample {k} is not finite or has negative time ({x}, {y}, {t} s at {at} s)"
                    ),
                ));
            }
        }
        if self.contact_time_s() <= 0.0 {
            return Err(Error::invalid(
                "contact motion",
                "the run spends no time in contact",
            ));
        }
        Ok(())
    }

    /// Total contact time, s.
    pub fn contact_time_s(&self) -> f64 {
        self.dwell_s.iter().sum()
    }

    /// Program time from the first contact sample to the last, s.
    pub fn span_s(&self) -> f64 {
        let (lo, hi) = self
            .time_s
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &t| {
                (a.min(t), b.max(t))
            });
        if hi > lo {
            hi - lo
        } else {
            0.0
        }
    }

    /// Contact-time-weighted mean program time, s: the time at which a drift has no effect on
    /// the total removal.
    pub fn mid_time_s(&self) -> f64 {
        let t: f64 = self.contact_time_s();
        if t > 0.0 {
            self.dwell_s
                .iter()
                .zip(&self.time_s)
                .map(|(d, at)| d * at)
                .sum::<f64>()
                / t
        } else {
            0.0
        }
    }
}

/// A 2-D real FFT of a fixed size: rows by `realfft`, then columns by `rustfft`.
struct Fft2 {
    nx: usize,
    ny: usize,
    row_fwd: Arc<dyn realfft::RealToComplex<f64>>,
    row_inv: Arc<dyn realfft::ComplexToReal<f64>>,
    col_fwd: Arc<dyn rustfft::Fft<f64>>,
    col_inv: Arc<dyn rustfft::Fft<f64>>,
}

impl std::fmt::Debug for Fft2 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Fft2({} x {})", self.nx, self.ny)
    }
}

impl Fft2 {
    fn new(nx: usize, ny: usize) -> Self {
        let mut real = RealFftPlanner::<f64>::new();
        let mut complex = FftPlanner::<f64>::new();
        Self {
            nx,
            ny,
            row_fwd: real.plan_fft_forward(nx),
            row_inv: real.plan_fft_inverse(nx),
            col_fwd: complex.plan_fft_forward(ny),
            col_inv: complex.plan_fft_inverse(ny),
        }
    }

    /// Half-spectrum columns: `nx / 2 + 1`.
    fn half(&self) -> usize {
        self.nx / 2 + 1
    }

    /// The spectrum of a row-major `ny x nx` real grid, column-major (`c * ny + j`).
    fn forward(&self, mut grid: Vec<f64>) -> Vec<Complex<f64>> {
        let (nx, ny, half) = (self.nx, self.ny, self.half());
        let mut rows = vec![Complex::new(0.0, 0.0); ny * half];
        grid.par_chunks_mut(nx)
            .zip(rows.par_chunks_mut(half))
            .for_each(|(row, out)| {
                // Lengths match the plan: the only error realfft reports.
                let _ = self.row_fwd.process(row, out);
            });
        let mut cols = vec![Complex::new(0.0, 0.0); half * ny];
        cols.par_chunks_mut(ny).enumerate().for_each(|(c, col)| {
            for (j, v) in col.iter_mut().enumerate() {
                *v = rows[j * half + c];
            }
            self.col_fwd.process(col);
        });
        cols
    }

    /// The row-major real grid of a column-major half spectrum, scaled by `1 / (nx ny)`.
    fn inverse(&self, mut cols: Vec<Complex<f64>>) -> Vec<f64> {
        let (nx, ny, half) = (self.nx, self.ny, self.half());
        cols.par_chunks_mut(ny)
            .for_each(|col| self.col_inv.process(col));
        let scale = 1.0 / (nx * ny) as f64;
        let mut grid = vec![0.0; nx * ny];
        grid.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
            let mut spec: Vec<Complex<f64>> = (0..half).map(|c| cols[c * ny + j]).collect();
            // The DC and Nyquist bins of a real signal's spectrum are real.
            spec[0].im = 0.0;
            if nx % 2 == 0 {
                spec[half - 1].im = 0.0;
            }
            let _ = self.row_inv.process(&mut spec, row);
            for v in row.iter_mut() {
                *v *= scale;
            }
        });
        grid
    }
}

/// The removal of one contact motion at a fixed set of points for any footprint: the module's
/// lattice convolution, with the motion's densities transformed once.
#[derive(Debug)]
pub struct LatticeRemoval {
    pitch_mm: f64,
    origin_mm: (f64, f64),
    reach_cells: usize,
    fft: Fft2,
    density_hat: [Vec<Complex<f64>>; 2],
    /// Every point's cell `(ix, iy)` and fractions within it.
    points: Vec<(usize, usize, f64, f64)>,
    mid_time_s: f64,
}

/// Most lattice nodes a calibration's convolution may use.
pub const MAX_LATTICE_NODES: f64 = 64.0e6;

impl LatticeRemoval {
    /// The lattice of pitch `pitch_mm` over the points `(x_mm, y_mm)` and every footprint of
    /// radius up to `reach_mm`, with `motion` spread onto it. The lattice's origin is the points'
    /// lowest x and y less a whole number of cells, so points on a grid whose pitch is a multiple
    /// of `pitch_mm` sit on nodes.
    pub fn new(
        motion: &ContactMotion,
        x_mm: &[f64],
        y_mm: &[f64],
        reach_mm: f64,
        pitch_mm: f64,
    ) -> Result<Self> {
        motion.validate()?;
        if x_mm.len() != y_mm.len() || x_mm.is_empty() {
            return Err(Error::invalid(
                "calibration points",
                format!(
                    "{} x and {} y: need as many, and at least one",
                    x_mm.len(),
                    y_mm.len()
                ),
            ));
        }
        if !(pitch_mm.is_finite() && pitch_mm > 0.0 && reach_mm.is_finite() && reach_mm > 0.0) {
            return Err(Error::invalid(
                "calibration lattice",
                format!("pitch {pitch_mm} mm and reach {reach_mm} mm must be positive"),
            ));
        }
        let bbox = crate::map::BoundingBox::of_points(x_mm, y_mm)
            .ok_or_else(|| Error::invalid("calibration points", "not finite"))?;
        let reach_cells = (reach_mm / pitch_mm).ceil() as usize + 1;
        let origin_mm = (
            bbox.x_min_mm - reach_cells as f64 * pitch_mm,
            bbox.y_min_mm - reach_cells as f64 * pitch_mm,
        );
        let span_x =
            ((bbox.x_max_mm - bbox.x_min_mm) / pitch_mm).ceil() + 2.0 * reach_cells as f64 + 2.0;
        let span_y =
            ((bbox.y_max_mm - bbox.y_min_mm) / pitch_mm).ceil() + 2.0 * reach_cells as f64 + 2.0;
        // The density lattice, plus the kernel's reach so the circular convolution does not wrap
        // onto the points.
        let (gx, gy) = (span_x + reach_cells as f64, span_y + reach_cells as f64);
        if !(gx * gy <= MAX_LATTICE_NODES) {
            return Err(Error::invalid(
                "calibration lattice",
                format!(
                    "{gx:.0} x {gy:.0} nodes at {pitch_mm} mm is more than {MAX_LATTICE_NODES:.0}: use a coarser --lattice-pitch-mm"
                ),
            ));
        }
        crate::budget::check_f64s(
            "calibration lattice",
            &format!("a {gx:.0} x {gy:.0} lattice"),
            gx * gy,
            10.0,
        )?;
        let nx = crate::influence::operator::lattice::smooth_size(gx as usize);
        let ny = crate::influence::operator::lattice::smooth_size(gy as usize);
        let (sx, sy) = (span_x as usize, span_y as usize);
        let mid_time_s = motion.mid_time_s();
        let mut dens = [vec![0.0; nx * ny], vec![0.0; nx * ny]];
        for k in 0..motion.x_mm.len() {
            let fx = (motion.x_mm[k] - origin_mm.0) / pitch_mm;
            let fy = (motion.y_mm[k] - origin_mm.1) / pitch_mm;
            if !(fx >= 0.0 && fy >= 0.0 && fx < (sx - 1) as f64 && fy < (sy - 1) as f64) {
                continue; // beyond every point's reach
            }
            let (ix, iy) = (fx as usize, fy as usize);
            let (ax, ay) = (fx - ix as f64, fy - iy as f64);
            let w0 = motion.dwell_s[k];
            let w1 = w0 * (motion.time_s[k] - mid_time_s) / 3600.0;
            for (d, w) in dens.iter_mut().zip([w0, w1]) {
                d[iy * nx + ix] += w * (1.0 - ax) * (1.0 - ay);
                d[iy * nx + ix + 1] += w * ax * (1.0 - ay);
                d[(iy + 1) * nx + ix] += w * (1.0 - ax) * ay;
                d[(iy + 1) * nx + ix + 1] += w * ax * ay;
            }
        }
        let fft = Fft2::new(nx, ny);
        // The tent's transform along each axis: sinc²(π k / n).
        let tent = |k: usize, n: usize| {
            let f = k.min(n - k) as f64 / n as f64;
            let a = std::f64::consts::PI * f;
            if a == 0.0 {
                1.0
            } else {
                (a.sin() / a).powi(2)
            }
        };
        let [d0, d1] = dens;
        let density_hat = [d0, d1].map(|d| {
            let mut hat = fft.forward(d);
            for c in 0..fft.half() {
                let tx = tent(c, nx);
                for j in 0..ny {
                    hat[c * ny + j] /= tx * tent(j, ny);
                }
            }
            hat
        });
        let points = x_mm
            .iter()
            .zip(y_mm)
            .map(|(&x, &y)| {
                let fx = (x - origin_mm.0) / pitch_mm;
                let fy = (y - origin_mm.1) / pitch_mm;
                let (ix, iy) = (fx.floor() as usize, fy.floor() as usize);
                (ix, iy, fx - ix as f64, fy - iy as f64)
            })
            .collect();
        Ok(Self {
            pitch_mm,
            origin_mm,
            reach_cells,
            fft,
            density_hat,
            points,
            mid_time_s,
        })
    }

    /// Lattice pitch, mm.
    pub fn pitch_mm(&self) -> f64 {
        self.pitch_mm
    }

    /// The motion's contact-time-weighted mean program time, s (`t_mid`).
    pub fn mid_time_s(&self) -> f64 {
        self.mid_time_s
    }

    /// The footprint sampled at the lattice offsets within its reach, wrapped onto the FFT grid.
    fn kernel_grid(&self, tif: &dyn InfluenceFunction) -> Vec<f64> {
        let (nx, ny) = (self.fft.nx, self.fft.ny);
        let r = self.reach_cells as i64;
        let h = self.pitch_mm;
        let mut k = vec![0.0; nx * ny];
        for dy in -r..=r {
            let jy = dy.rem_euclid(ny as i64) as usize;
            for dx in -r..=r {
                let jx = dx.rem_euclid(nx as i64) as usize;
                k[jy * nx + jx] = tif.rate_nm_per_s(dx as f64 * h, dy as f64 * h);
            }
        }
        k
    }

    /// `(f ⊛ ρ0, f ⊛ ρ1)` at the points, nm and nm per unit drift per hour: the removal at the
    /// footprint's rate and the change of it per unit `δ`.
    pub fn removal_parts(&self, tif: &dyn InfluenceFunction) -> [Vec<f64>; 2] {
        let kernel_hat = self.fft.forward(self.kernel_grid(tif));
        let nx = self.fft.nx;
        self.density_hat.each_ref().map(|dens| {
            let product: Vec<Complex<f64>> =
                kernel_hat.iter().zip(dens).map(|(k, d)| k * d).collect();
            let grid = self.fft.inverse(product);
            self.points
                .iter()
                .map(|&(ix, iy, ax, ay)| {
                    let at = |i: usize, j: usize| grid.get(j * nx + i).copied().unwrap_or(0.0);
                    (1.0 - ay) * ((1.0 - ax) * at(ix, iy) + ax * at(ix + 1, iy))
                        + ay * ((1.0 - ax) * at(ix, iy + 1) + ax * at(ix + 1, iy + 1))
                })
                .collect()
        })
    }

    /// `(f ⊛ ρ0, f ⊛ ρ1)` on the whole lattice, row-major.
    pub(super) fn convolved_grids(&self, tif: &dyn InfluenceFunction) -> [Vec<f64>; 2] {
        let kernel_hat = self.fft.forward(self.kernel_grid(tif));
        self.density_hat.each_ref().map(|dens| {
            let product: Vec<Complex<f64>> =
                kernel_hat.iter().zip(dens).map(|(k, d)| k * d).collect();
            self.fft.inverse(product)
        })
    }

    /// A lattice grid read bilinearly at point `i` moved by `(-cells_x, -cells_y)` whole cells:
    /// the convolution with a kernel shifted by that many cells.
    pub(super) fn read_shifted(&self, grid: &[f64], i: usize, cells_x: i64, cells_y: i64) -> f64 {
        let nx = self.fft.nx as i64;
        let ny = self.fft.ny as i64;
        let (ix, iy, ax, ay) = self.points[i];
        let (ix, iy) = (ix as i64 - cells_x, iy as i64 - cells_y);
        let at = |i: i64, j: i64| {
            if i < 0 || j < 0 || i >= nx || j >= ny {
                0.0
            } else {
                grid[(j * nx + i) as usize]
            }
        };
        (1.0 - ay) * ((1.0 - ax) * at(ix, iy) + ax * at(ix + 1, iy))
            + ay * ((1.0 - ax) * at(ix, iy + 1) + ax * at(ix + 1, iy + 1))
    }

    /// Number of points the removal is read at.
    pub fn points(&self) -> usize {
        self.points.len()
    }

    /// The removal at the points with the footprint `tif` drifting by `drift_per_hour`, nm.
    pub fn removal_nm(&self, tif: &dyn InfluenceFunction, drift_per_hour: f64) -> Vec<f64> {
        let [a, b] = self.removal_parts(tif);
        a.iter()
            .zip(&b)
            .map(|(a, b)| a + drift_per_hour * b)
            .collect()
    }

    /// The lattice origin, mm.
    pub fn origin_mm(&self) -> (f64, f64) {
        self.origin_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tif::GaussianTif;

    /// The lattice removal against the direct sum over the samples, relative to the peak.
    const LATTICE_REL_TOL: f64 = 2e-3;

    #[test]
    fn lattice_removal_matches_the_direct_sum_with_drift() {
        let tif = GaussianTif::new(1.2, 10.0, 5.0).expect("gaussian");
        // A serpentine of samples over 20 x 10 mm, times in program order.
        let mut motion = ContactMotion::default();
        let mut t = 0.0;
        for row in 0..21 {
            for col in 0..81 {
                let x = if row % 2 == 0 { col } else { 80 - col } as f64 * 0.25 - 10.0;
                let y = row as f64 * 0.5 - 5.0;
                let d = 0.5 + 0.4 * (0.3 * x).sin() * (0.5 * y).cos();
                motion.x_mm.push(x);
                motion.y_mm.push(y);
                motion.dwell_s.push(d);
                motion.time_s.push(t + d / 2.0);
                t += d;
            }
        }
        let (px, py): (Vec<f64>, Vec<f64>) = (0..400)
            .map(|k| (-8.0 + (k % 20) as f64 * 0.8, -4.0 + (k / 20) as f64 * 0.4))
            .unzip();
        let lattice = LatticeRemoval::new(&motion, &px, &py, 5.0, 0.1).expect("lattice");
        let drift = 0.3;
        let h = lattice.removal_nm(&tif, drift);
        let mid = motion.mid_time_s();
        let mut peak: f64 = 0.0;
        let direct: Vec<f64> = px
            .iter()
            .zip(&py)
            .map(|(&x, &y)| {
                let s: f64 = (0..motion.x_mm.len())
                    .map(|k| {
                        motion.dwell_s[k]
                            * (1.0 + drift * (motion.time_s[k] - mid) / 3600.0)
                            * tif.rate_nm_per_s(x - motion.x_mm[k], y - motion.y_mm[k])
                    })
                    .sum();
                peak = peak.max(s.abs());
                s
            })
            .collect();
        for (i, (a, b)) in h.iter().zip(&direct).enumerate() {
            assert!(
                (a - b).abs() <= LATTICE_REL_TOL * peak,
                "point {i}: lattice {a} against direct {b}"
            );
        }
    }
}
