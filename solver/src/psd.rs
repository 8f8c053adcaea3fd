//! One-dimensional power spectral density of a height map along a lattice axis, the measure in
//! which the raster pitch's mid-spatial-frequency ripple shows as a peak.
//!
//! The map's points are put on their lattice (pitch `p`, see
//! [`crate::influence::operator::fft::FftOperator::lattice_pitch_mm`]); every line along the chosen axis is cut
//! into its runs of consecutive measured points, and each run into Welch segments of `L` points
//! (half-overlapping, `L` the largest power of two at most half the longest run, at least 8).
//! Each segment has its mean removed and a Hann window `w` applied; its one-sided periodogram is
//! `P(f_k) = c_k p |X_k|^2 / (L U)`, `f_k = k / (L p)` (1/mm), `U = mean(w^2)`, `c_k = 2` except
//! at `k = 0` and `k = L/2`, and the PSD is the mean over all segments (Welch 1967, IEEE Trans.
//! Audio Electroacoust. 15(2); ISO 10110-8 for the 1-D PSD of optical surfaces). Units: heights
//! in nm give nm^2 mm; `sum_k P(f_k) / (L p)` is the mean variance of the segments (Parseval).
//!
//! [`area_psd`] is the two-dimensional PSD of the whole map on its `nx x ny` lattice: the heights
//! less their mean, unmeasured cells zero, times a separable Hann window `w`, transformed by a 2-D
//! FFT; `P(fx_k, fy_l) = p^2 |X_kl|^2 / (nx ny U)` (nm^2 mm^2, two-sided), `U` the mean of `w^2`
//! over the lattice counting measured cells only, so `sum P dfx dfy` is the window-weighted variance
//! of the measured heights (Parseval; ISO 10110-8, prysm's `psd`). [`AreaPsd::azimuthal`] averages
//! it over annuli of `|f|` one frequency step wide (the coarser of `dfx`, `dfy`).

use crate::error::{twelve_figures, Error, Result};
use crate::influence::operator::fft::FftOperator;
use realfft::RealFftPlanner;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

/// Axis along which the lines run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LineAxis {
    /// Lines of constant y, along x.
    X,
    /// Lines of constant x, along y.
    Y,
}

/// A one-sided 1-D PSD.
#[derive(Debug, Clone, PartialEq)]
pub struct LinePsd {
    /// Spatial frequencies, 1/mm (`k / (L p)`, `k = 0..=L/2`).
    pub frequency_per_mm: Vec<f64>,
    /// PSD at each frequency, nm^2 mm.
    pub psd_nm2_mm: Vec<f64>,
    /// Segment length `L`, points.
    pub segment_points: usize,
    /// Lattice pitch `p`, mm.
    pub pitch_mm: f64,
    /// Segments averaged.
    pub segments: usize,
}

/// Shortest segment, points.
const MIN_SEGMENT: usize = 8;

/// The lattice of `x, y`: pitch, origin and index of every point.
struct Lattice {
    pitch_mm: f64,
    nx: usize,
    ny: usize,
    /// Per point `(ix, iy)`.
    cells: Vec<(usize, usize)>,
}

impl Lattice {
    fn of(x_mm: &[f64], y_mm: &[f64]) -> Result<Self> {
        let pitch_mm = FftOperator::lattice_pitch_mm(x_mm, y_mm)
            .ok_or_else(|| Error::invalid("psd", "the map has fewer than two distinct points"))?;
        let min = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
        let (x0, y0) = (min(x_mm), min(y_mm));
        let mut cells = Vec::with_capacity(x_mm.len());
        let (mut nx, mut ny) = (0, 0);
        for (i, (&x, &y)) in x_mm.iter().zip(y_mm).enumerate() {
            let (fx, fy) = ((x - x0) / pitch_mm, (y - y0) / pitch_mm);
            let (ix, iy) = (fx.round(), fy.round());
            if (fx - ix).abs() > 1e-3 || (fy - iy).abs() > 1e-3 {
                return Err(Error::invalid(
                    "psd",
                    format!(
                        "map point {} ({x} mm, {y} mm) is off the {} mm lattice",
                        i + 1,
                        twelve_figures(pitch_mm)
                    ),
                ));
            }
            let (ix, iy) = (ix as usize, iy as usize);
            nx = nx.max(ix + 1);
            ny = ny.max(iy + 1);
            cells.push((ix, iy));
        }
        let cells_total = nx.checked_mul(ny).filter(|&c| c <= 16 * x_mm.len().max(1));
        if cells_total.is_none() {
            return Err(Error::invalid(
                "psd",
                format!(
                    "the lattice ({nx} x {ny} at {pitch_mm} mm) is far larger than the map's {} points",
                    x_mm.len()
                ),
            ));
        }
        Ok(Lattice {
            pitch_mm,
            nx,
            ny,
            cells,
        })
    }
}

/// The 1-D PSD of the heights `z_nm` at lattice points `(x_mm, y_mm)` along `axis`.
pub fn line_psd(x_mm: &[f64], y_mm: &[f64], z_nm: &[f64], axis: LineAxis) -> Result<LinePsd> {
    let n = z_nm.len();
    if x_mm.len() != n || y_mm.len() != n {
        return Err(Error::LengthMismatch {
            what: "psd coordinates",
            got: x_mm.len().min(y_mm.len()),
            expected: n,
        });
    }
    let lattice = Lattice::of(x_mm, y_mm)?;
    let (along, lines) = match axis {
        LineAxis::X => (lattice.nx, lattice.ny),
        LineAxis::Y => (lattice.ny, lattice.nx),
    };
    // Dense grid, NaN where nothing was measured; line-major along the axis.
    let mut grid = vec![f64::NAN; along * lines];
    for (&(ix, iy), &z) in lattice.cells.iter().zip(z_nm) {
        let (a, l) = match axis {
            LineAxis::X => (ix, iy),
            LineAxis::Y => (iy, ix),
        };
        grid[l * along + a] = z;
    }
    // Runs of finite heights.
    let mut runs: Vec<(usize, usize)> = Vec::new();
    for l in 0..lines {
        let row = &grid[l * along..(l + 1) * along];
        let mut a = 0;
        while a < along {
            if !row[a].is_finite() {
                a += 1;
                continue;
            }
            let start = a;
            while a < along && row[a].is_finite() {
                a += 1;
            }
            runs.push((l * along + start, a - start));
        }
    }
    let longest = runs.iter().map(|r| r.1).max().unwrap_or(0);
    if longest < 2 * MIN_SEGMENT {
        return Err(Error::invalid(
            "psd",
            format!(
                "the longest line of measured points along the axis has {longest} points; at least {} are needed",
                2 * MIN_SEGMENT
            ),
        ));
    }
    let seg = prev_power_of_two(longest / 2).max(MIN_SEGMENT);
    let hann: Vec<f64> = (0..seg)
        .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / seg as f64).cos())
        .collect();
    let u = hann.iter().map(|w| w * w).sum::<f64>() / seg as f64;
    let mut planner = RealFftPlanner::<f64>::new();
    let fft = planner.plan_fft_forward(seg);
    let mut input = fft.make_input_vec();
    let mut spectrum = fft.make_output_vec();
    let mut scratch = fft.make_scratch_vec();
    let bins = seg / 2 + 1;
    let mut sum = vec![0.0; bins];
    let mut segments = 0usize;
    let p = lattice.pitch_mm;
    for &(start, len) in &runs {
        let mut s = 0;
        while s + seg <= len {
            let data = &grid[start + s..start + s + seg];
            let mean = data.iter().sum::<f64>() / seg as f64;
            for ((slot, &z), &w) in input.iter_mut().zip(data).zip(&hann) {
                *slot = (z - mean) * w;
            }
            fft.process_with_scratch(&mut input, &mut spectrum, &mut scratch)
                .map_err(|e| Error::Numerical {
                    stage: "psd",
                    why: e.to_string(),
                })?;
            for (k, (acc, c)) in sum.iter_mut().zip(&spectrum).enumerate() {
                let one_sided = if k == 0 || 2 * k == seg { 1.0 } else { 2.0 };
                *acc += one_sided * p * c.norm_sqr() / (seg as f64 * u);
            }
            segments += 1;
            s += seg / 2;
        }
    }
    let psd_nm2_mm: Vec<f64> = sum.iter().map(|v| v / segments.max(1) as f64).collect();
    let frequency_per_mm = (0..bins).map(|k| k as f64 / (seg as f64 * p)).collect();
    Ok(LinePsd {
        frequency_per_mm,
        psd_nm2_mm,
        segment_points: seg,
        pitch_mm: p,
        segments,
    })
}

/// A two-sided 2-D PSD on the map's lattice, frequencies in FFT-shifted order (ascending).
#[derive(Debug, Clone, PartialEq)]
pub struct AreaPsd {
    /// Frequencies along x, 1/mm (`k / (nx p)`, `k = -floor(nx/2) .. ceil(nx/2) - 1`).
    pub fx_per_mm: Vec<f64>,
    /// Frequencies along y, 1/mm.
    pub fy_per_mm: Vec<f64>,
    /// PSD, nm^2 mm^2, row-major in y: `psd[l * nx + k]` at `(fx[k], fy[l])`.
    pub psd_nm2_mm2: Vec<f64>,
    /// Lattice pitch, mm.
    pub pitch_mm: f64,
}

/// An azimuthally averaged 2-D PSD.
#[derive(Debug, Clone, PartialEq)]
pub struct AzimuthalPsd {
    /// Annulus centres `k df`, 1/mm.
    pub frequency_per_mm: Vec<f64>,
    /// Mean of the 2-D PSD over the annulus, nm^2 mm^2.
    pub psd_nm2_mm2: Vec<f64>,
    /// Lattice frequencies in each annulus.
    pub cells: Vec<usize>,
}

impl AreaPsd {
    /// Frequency steps `(dfx, dfy)`, 1/mm.
    pub fn steps_per_mm(&self) -> (f64, f64) {
        let step = |n: usize| 1.0 / (n as f64 * self.pitch_mm);
        (step(self.fx_per_mm.len()), step(self.fy_per_mm.len()))
    }

    /// `sum P dfx dfy`: the window-weighted variance of the heights, nm^2.
    pub fn variance_nm2(&self) -> f64 {
        let (dx, dy) = self.steps_per_mm();
        self.psd_nm2_mm2.iter().sum::<f64>() * dx * dy
    }

    /// The mean over annuli `|f| in [(k - 1/2) df, (k + 1/2) df)`, `df` the coarser step, up to
    /// the Nyquist frequency of the lattice `1 / (2 p)`.
    pub fn azimuthal(&self) -> AzimuthalPsd {
        let (dx, dy) = self.steps_per_mm();
        let df = dx.max(dy);
        let bins = (0.5 / self.pitch_mm / df).floor() as usize + 1;
        let mut sum = vec![0.0; bins];
        let mut cells = vec![0usize; bins];
        let nx = self.fx_per_mm.len();
        for (l, fy) in self.fy_per_mm.iter().enumerate() {
            for (k, fx) in self.fx_per_mm.iter().enumerate() {
                let b = ((fx * fx + fy * fy).sqrt() / df).round() as usize;
                if b < bins {
                    sum[b] += self.psd_nm2_mm2[l * nx + k];
                    cells[b] += 1;
                }
            }
        }
        let keep: Vec<usize> = (0..bins).filter(|&b| cells[b] > 0).collect();
        AzimuthalPsd {
            frequency_per_mm: keep.iter().map(|&b| b as f64 * df).collect(),
            psd_nm2_mm2: keep.iter().map(|&b| sum[b] / cells[b] as f64).collect(),
            cells: keep.iter().map(|&b| cells[b]).collect(),
        }
    }
}

/// Hann window of `n` points, zero at both ends' outer neighbours (`sin^2(pi (k + 1/2) / n)`), so
/// every point has weight.
fn hann_midpoint(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| {
            (std::f64::consts::PI * (k as f64 + 0.5) / n as f64)
                .sin()
                .powi(2)
        })
        .collect()
}

/// The 2-D PSD of the heights `z_nm` at lattice points `(x_mm, y_mm)` (see the module's
/// documentation). The lattice needs at least 4 points along each axis.
pub fn area_psd(x_mm: &[f64], y_mm: &[f64], z_nm: &[f64]) -> Result<AreaPsd> {
    let n = z_nm.len();
    if x_mm.len() != n || y_mm.len() != n {
        return Err(Error::LengthMismatch {
            what: "psd coordinates",
            got: x_mm.len().min(y_mm.len()),
            expected: n,
        });
    }
    let lattice = Lattice::of(x_mm, y_mm)?;
    let (nx, ny, p) = (lattice.nx, lattice.ny, lattice.pitch_mm);
    if nx < 4 || ny < 4 {
        return Err(Error::invalid(
            "psd",
            format!("the lattice is {nx} x {ny} points; a 2-D PSD needs at least 4 x 4"),
        ));
    }
    let finite: Vec<bool> = z_nm.iter().map(|z| z.is_finite()).collect();
    let count = finite.iter().filter(|f| **f).count();
    if count == 0 {
        return Err(Error::invalid("psd", "no finite height"));
    }
    let mean = z_nm.iter().filter(|z| z.is_finite()).sum::<f64>() / count as f64;
    let (wx, wy) = (hann_midpoint(nx), hann_midpoint(ny));
    let mut grid = vec![Complex::new(0.0, 0.0); nx * ny];
    let mut u = 0.0;
    for ((&(ix, iy), &z), &ok) in lattice.cells.iter().zip(z_nm).zip(&finite) {
        if ok {
            let w = wx[ix] * wy[iy];
            grid[iy * nx + ix] = Complex::new((z - mean) * w, 0.0);
            u += w * w;
        }
    }
    let u = u / (nx * ny) as f64;
    let mut planner = FftPlanner::<f64>::new();
    let (fx, fy) = (planner.plan_fft_forward(nx), planner.plan_fft_forward(ny));
    for row in grid.chunks_exact_mut(nx) {
        fx.process(row);
    }
    let mut column = vec![Complex::new(0.0, 0.0); ny];
    for k in 0..nx {
        for (l, c) in column.iter_mut().enumerate() {
            *c = grid[l * nx + k];
        }
        fy.process(&mut column);
        for (l, c) in column.iter().enumerate() {
            grid[l * nx + k] = *c;
        }
    }
    // Shifted order: index 0 is the most negative frequency.
    let shifted = |n: usize, i: usize| (i + n - n / 2) % n;
    let freq = |n: usize| -> Vec<f64> {
        (0..n)
            .map(|i| (i as f64 - (n / 2) as f64) / (n as f64 * p))
            .collect()
    };
    let scale = p * p / ((nx * ny) as f64 * u);
    let mut psd = vec![0.0; nx * ny];
    for l in 0..ny {
        for k in 0..nx {
            psd[l * nx + k] = scale * grid[shifted(ny, l) * nx + shifted(nx, k)].norm_sqr();
        }
    }
    Ok(AreaPsd {
        fx_per_mm: freq(nx),
        fy_per_mm: freq(ny),
        psd_nm2_mm2: psd,
        pitch_mm: p,
    })
}

fn prev_power_of_two(v: usize) -> usize {
    if v == 0 {
        0
    } else {
        1 << (usize::BITS - 1 - v.leading_zeros())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative tolerance of the Parseval and peak checks (window leakage and averaging).
    const PSD_REL_TOL: f64 = 0.02;

    fn lattice(nx: usize, ny: usize, pitch: f64, f: impl Fn(f64, f64) -> f64) -> [Vec<f64>; 3] {
        let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..ny {
            for i in 0..nx {
                let (a, b) = (i as f64 * pitch, j as f64 * pitch);
                x.push(a);
                y.push(b);
                z.push(f(a, b));
            }
        }
        [x, y, z]
    }

    /// A sinusoid of amplitude A on a bin: the PSD peaks at its frequency and integrates to its
    /// variance `A^2 / 2` (Parseval), along either axis.
    #[test]
    fn a_sinusoid_peaks_at_its_frequency_with_its_variance() {
        let (pitch, amp) = (0.25, 7.0);
        // Segment 64 points (longest run 128): bin 8 is 8 / (64 * 0.25) = 0.5 /mm.
        let f0 = 0.5;
        for axis in [LineAxis::X, LineAxis::Y] {
            let [x, y, z] = lattice(128, 128, pitch, |a, b| {
                let s = if axis == LineAxis::X { a } else { b };
                amp * (2.0 * std::f64::consts::PI * f0 * s + 0.3).sin()
            });
            let psd = line_psd(&x, &y, &z, axis).unwrap();
            assert_eq!(psd.segment_points, 64);
            let peak = (0..psd.psd_nm2_mm.len())
                .max_by(|&a, &b| psd.psd_nm2_mm[a].total_cmp(&psd.psd_nm2_mm[b]))
                .unwrap();
            assert!((psd.frequency_per_mm[peak] - f0).abs() < 1e-12);
            let df = 1.0 / (psd.segment_points as f64 * pitch);
            let variance: f64 = psd.psd_nm2_mm.iter().sum::<f64>() * df;
            assert!(
                (variance / (amp * amp / 2.0) - 1.0).abs() < PSD_REL_TOL,
                "{axis:?}: {variance}"
            );
        }
    }

    /// Lines across the other axis do not leak into the PSD: a map varying only in y is flat
    /// along x.
    #[test]
    fn variation_across_the_lines_is_not_seen() {
        let [x, y, z] = lattice(64, 40, 0.5, |_, b| 30.0 * (b / 3.0).sin());
        let psd = line_psd(&x, &y, &z, LineAxis::X).unwrap();
        assert!(psd.psd_nm2_mm.iter().all(|&v| v < 1e-20), "{psd:?}");
    }

    /// The 2-D PSD equals an independent estimate, the periodogram summed term by term as a
    /// discrete Fourier transform (no FFT), on an irregular map with a hole; a sinusoid's power
    /// sits at its frequency and integrates to its variance (Parseval); the azimuthal average
    /// peaks at `|f|`.
    #[test]
    fn area_psd_matches_a_direct_dft_and_parseval() {
        let (nx, ny, pitch) = (24usize, 18usize, 0.4);
        let [mut x, mut y, mut z] = lattice(nx, ny, pitch, |a, b| {
            3.0 * (a * 1.7).sin() + 2.0 * (b * 0.9 + a * 0.4).cos() + 0.1 * a * b
        });
        // A hole: cells dropped.
        let drop: Vec<usize> = (0..x.len()).filter(|&i| (i * 7) % 23 == 0).collect();
        for &i in drop.iter().rev() {
            x.remove(i);
            y.remove(i);
            z.remove(i);
        }
        let psd = area_psd(&x, &y, &z).unwrap();
        let mean = z.iter().sum::<f64>() / z.len() as f64;
        let (wx, wy) = (hann_midpoint(nx), hann_midpoint(ny));
        let cells: Vec<(usize, usize)> = x
            .iter()
            .zip(&y)
            .map(|(a, b)| ((a / pitch).round() as usize, (b / pitch).round() as usize))
            .collect();
        let u: f64 = cells
            .iter()
            .map(|&(i, j)| (wx[i] * wy[j]).powi(2))
            .sum::<f64>()
            / (nx * ny) as f64;
        let tau = 2.0 * std::f64::consts::PI;
        let mut worst = 0.0f64;
        let peak = psd.psd_nm2_mm2.iter().cloned().fold(0.0, f64::max);
        for (l, fy) in psd.fy_per_mm.iter().enumerate() {
            for (k, fx) in psd.fx_per_mm.iter().enumerate() {
                let (mut re, mut im) = (0.0, 0.0);
                for (q, &(i, j)) in cells.iter().enumerate() {
                    let v = (z[q] - mean) * wx[i] * wy[j];
                    let phase = -tau * (fx * i as f64 * pitch + fy * j as f64 * pitch);
                    re += v * phase.cos();
                    im += v * phase.sin();
                }
                let direct = pitch * pitch * (re * re + im * im) / ((nx * ny) as f64 * u);
                worst = worst.max((direct - psd.psd_nm2_mm2[l * nx + k]).abs() / peak);
            }
        }
        assert!(worst < 1e-10, "largest difference {worst} of the peak");
        // A sinusoid on a bin of a full lattice: Parseval and the peak.
        let (nx, ny, pitch, amp) = (64usize, 32usize, 0.5, 5.0);
        let (f0x, f0y) = (8.0 / (nx as f64 * pitch), 4.0 / (ny as f64 * pitch));
        let [x, y, z] = lattice(nx, ny, pitch, |a, b| {
            amp * (tau * (f0x * a + f0y * b) + 0.2).sin()
        });
        let psd = area_psd(&x, &y, &z).unwrap();
        let var = psd.variance_nm2();
        assert!((var / (amp * amp / 2.0) - 1.0).abs() < PSD_REL_TOL, "{var}");
        let top = (0..psd.psd_nm2_mm2.len())
            .max_by(|&a, &b| psd.psd_nm2_mm2[a].total_cmp(&psd.psd_nm2_mm2[b]))
            .unwrap();
        let (fx, fy) = (psd.fx_per_mm[top % nx], psd.fy_per_mm[top / nx]);
        assert!((fx.abs() - f0x).abs() < 1e-12 && (fy.abs() - f0y).abs() < 1e-12);
        let az = psd.azimuthal();
        let best = (0..az.psd_nm2_mm2.len())
            .max_by(|&a, &b| az.psd_nm2_mm2[a].total_cmp(&az.psd_nm2_mm2[b]))
            .unwrap();
        let (dx, dy) = psd.steps_per_mm();
        let f0 = (f0x * f0x + f0y * f0y).sqrt();
        assert!((az.frequency_per_mm[best] - f0).abs() <= 0.5 * dx.max(dy) + 1e-12);
        assert!(az.cells.iter().sum::<usize>() <= nx * ny);
    }

    /// Points off the lattice and lines too short are refused with the point or size named.
    #[test]
    fn off_lattice_and_short_maps_are_refused() {
        let [mut x, y, z] = lattice(64, 4, 1.0, |a, _| a);
        x[5] += 0.37;
        let e = line_psd(&x, &y, &z, LineAxis::X).unwrap_err().to_string();
        assert!(e.contains("off the"), "{e}");
        let [x, y, z] = lattice(10, 4, 1.0, |a, _| a);
        assert!(line_psd(&x, &y, &z, LineAxis::X).is_err());
    }
}
