//! Gerchberg-Papoulis band-limited extension.
//!
//! The map is taken as a sample of a band-limited surface: heights with no spatial frequency
//! above `f_c` (cycles/mm). On a lattice holding the map and the extension points (padded so
//! that the periodic transform does not wrap the map onto itself), alternate the two
//! projections (Gerchberg, "Super-resolution through error energy reduction", Optica Acta 21,
//! 709 (1974); Papoulis, "A new algorithm in spectral analysis and band-limited
//! extrapolation", IEEE Trans. Circuits Syst. 22, 735 (1975)):
//!
//! 1. transform the lattice (2-D FFT) and zero every frequency with `fx^2 + fy^2 > f_c^2`;
//! 2. transform back and restore the measured heights at the known nodes.
//!
//! The unknown nodes start at the map's mean. Each step does not increase the distance to any
//! band-limited surface that fits the known samples (both steps are projections onto convex
//! sets), and when the band-limited fit is unique it converges to it.

use crate::error::{twelve_figures, Error, Result};
use crate::machine::machinability::map_pitch_mm;
use rayon::prelude::*;
use realfft::RealFftPlanner;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

/// The iteration on a periodic `nx x ny` lattice of pitch `pitch_mm` (row-major, x fastest):
/// `values` at the `known` nodes are kept, the others are replaced by the band-limited
/// extension after `iterations` steps.
///
/// The lattice is real, so its transform is Hermitian: rows go through a real-to-complex FFT
/// (`nx / 2 + 1` frequencies) and back. Only the columns `kx` holding a frequency inside the
/// band are transformed along y (a band of `f_c` keeps about `2 f_c nx p` of them); the others
/// are zeroed outright, which is what the mask would leave of them. Rows are transformed in
/// parallel, each the same way on any thread: the result is bit-identical for any thread count.
pub fn extend_on_lattice(
    values: &mut [f64],
    known: &[bool],
    nx: usize,
    ny: usize,
    pitch_mm: f64,
    band_limit_per_mm: f64,
    iterations: usize,
) -> Result<()> {
    let n = nx * ny;
    if values.len() != n || known.len() != n || n == 0 {
        return Err(Error::LengthMismatch {
            what: "Gerchberg-Papoulis lattice",
            got: values.len().min(known.len()),
            expected: n,
        });
    }
    let mut real_planner = RealFftPlanner::<f64>::new();
    let (r2c, c2r) = (
        real_planner.plan_fft_forward(nx),
        real_planner.plan_fft_inverse(nx),
    );
    let mut planner = FftPlanner::<f64>::new();
    let (fwd_y, inv_y) = (planner.plan_fft_forward(ny), planner.plan_fft_inverse(ny));
    let freq = |k: usize, len: usize| -> f64 {
        let s = if k <= len / 2 {
            k as f64
        } else {
            k as f64 - len as f64
        };
        s / (len as f64 * pitch_mm)
    };
    // Half spectrum: kx in 0..=nx/2 (non-negative x frequencies), all ky.
    let nh = nx / 2 + 1;
    let band2 = band_limit_per_mm.powi(2);
    let keep = |kx: usize, ky: usize| freq(kx, nx).powi(2) + freq(ky, ny).powi(2) <= band2;
    let active: Vec<usize> = (0..nh)
        .filter(|&kx| (0..ny).any(|ky| keep(kx, ky)))
        .collect();
    let column_mask: Vec<Vec<bool>> = active
        .iter()
        .map(|&kx| (0..ny).map(|ky| keep(kx, ky)).collect())
        .collect();
    let numerical = |e: realfft::FftError| Error::Numerical {
        stage: "Gerchberg-Papoulis extension",
        why: e.to_string(),
    };
    let zero = Complex::new(0.0, 0.0);
    let mut lattice = values.to_vec();
    let mut spectrum = vec![zero; nh * ny];
    let mut column = vec![zero; ny];
    let mut column_scratch = vec![
        zero;
        fwd_y
            .get_inplace_scratch_len()
            .max(inv_y.get_inplace_scratch_len())
    ];
    let row_scratch_len = r2c.get_scratch_len().max(c2r.get_scratch_len());
    let row_work = || (vec![0.0; nx], vec![zero; row_scratch_len]);
    let scale = 1.0 / n as f64;
    // A real input of even length has a real Nyquist bin as well as a real DC bin.
    let nyquist = nx.is_multiple_of(2).then_some(nh - 1);
    for _ in 0..iterations {
        lattice
            .par_chunks(nx)
            .zip(spectrum.par_chunks_mut(nh))
            .try_for_each_init(row_work, |(row, scratch), (values, out)| {
                row.copy_from_slice(values);
                r2c.process_with_scratch(row, out, scratch)
            })
            .map_err(numerical)?;
        let mut next = 0;
        for (a, mask) in active.iter().zip(&column_mask) {
            // Columns between the active ones hold only frequencies outside the band.
            for kx in next..*a {
                for ky in 0..ny {
                    spectrum[ky * nh + kx] = zero;
                }
            }
            next = a + 1;
            for (ky, c) in column.iter_mut().enumerate() {
                *c = spectrum[ky * nh + a];
            }
            fwd_y.process_with_scratch(&mut column, &mut column_scratch);
            for (c, keep) in column.iter_mut().zip(mask) {
                if !keep {
                    *c = zero;
                }
            }
            inv_y.process_with_scratch(&mut column, &mut column_scratch);
            for (ky, c) in column.iter().enumerate() {
                spectrum[ky * nh + a] = *c;
            }
        }
        for kx in next..nh {
            for ky in 0..ny {
                spectrum[ky * nh + kx] = zero;
            }
        }
        lattice
            .par_chunks_mut(nx)
            .zip(spectrum.par_chunks_mut(nh))
            .zip(values.par_chunks(nx).zip(known.par_chunks(nx)))
            .try_for_each_init(row_work, |(_, scratch), ((row, spec), (v, k))| {
                // The transform of a real lattice: DC and Nyquist bins are real up to rounding.
                spec[0].im = 0.0;
                if let Some(last) = nyquist {
                    spec[last].im = 0.0;
                }
                c2r.process_with_scratch(spec, row, scratch)?;
                for ((r, v), k) in row.iter_mut().zip(v).zip(k) {
                    *r = if *k { *v } else { *r * scale };
                }
                Ok(())
            })
            .map_err(numerical)?;
    }
    for ((v, l), k) in values.iter_mut().zip(&lattice).zip(known) {
        if !k {
            *v = *l;
        }
    }
    Ok(())
}

/// Heights at `(x, y)` by band-limited extension of the map (which must lie on a regular
/// lattice: every map point within a quarter pitch of a node).
pub fn extend(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    map_z_nm: &[f64],
    x_mm: &[f64],
    y_mm: &[f64],
    band_limit_per_mm: f64,
    iterations: usize,
) -> Result<Vec<f64>> {
    if x_mm.is_empty() {
        return Ok(Vec::new());
    }
    let p = map_pitch_mm(map_x_mm, map_y_mm)
        .filter(|p| p.is_finite() && *p > 0.0)
        .ok_or_else(|| Error::invalid("map", "needs at least two distinct points"))?;
    let fold = |a: &[f64], b: &[f64]| {
        a.iter()
            .chain(b)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            })
    };
    let (x0, x1) = fold(map_x_mm, x_mm);
    let (y0, y1) = fold(map_y_mm, y_mm);
    // Pad by the extension's reach beyond the map on each side, so the wrap-around of the
    // periodic lattice lands in a pad and not on the map's far edge.
    let (mx0, mx1) = fold(map_x_mm, &[]);
    let (my0, my1) = fold(map_y_mm, &[]);
    let pad = ((mx0 - x0).max(x1 - mx1).max(my0 - y0).max(y1 - my1) / p).ceil() as usize + 1;
    let nx = ((x1 - x0) / p).round() as usize + 1 + 2 * pad;
    let ny = ((y1 - y0) / p).round() as usize + 1 + 2 * pad;
    if (nx as f64) * (ny as f64) > 1e8 {
        return Err(Error::invalid(
            "edge gerchberg-papoulis",
            format!("the lattice would hold {nx} x {ny} nodes"),
        ));
    }
    let (ox, oy) = (x0 - pad as f64 * p, y0 - pad as f64 * p);
    let node = |x: f64, y: f64| -> Option<usize> {
        let (fi, fj) = ((x - ox) / p, (y - oy) / p);
        let (i, j) = (fi.round(), fj.round());
        ((fi - i).abs() <= 0.25 && (fj - j).abs() <= 0.25 && i >= 0.0 && j >= 0.0)
            .then(|| j as usize * nx + i as usize)
            .filter(|&k| k < nx * ny)
    };
    let mean = map_z_nm.iter().sum::<f64>() / map_z_nm.len() as f64;
    let mut values = vec![0.0; nx * ny];
    let mut known = vec![false; nx * ny];
    for (k, ((&x, &y), &z)) in map_x_mm.iter().zip(map_y_mm).zip(map_z_nm).enumerate() {
        let i = node(x, y).ok_or_else(|| {
            Error::invalid(
                "edge gerchberg-papoulis",
                format!(
                    "needs a map on a regular lattice: map point {k} ({x}, {y}) is off the \
                     {} mm lattice",
                    twelve_figures(p)
                ),
            )
        })?;
        values[i] = z - mean;
        known[i] = true;
    }
    extend_on_lattice(
        &mut values,
        &known,
        nx,
        ny,
        p,
        band_limit_per_mm,
        iterations,
    )?;
    x_mm.iter()
        .zip(y_mm)
        .map(|(&x, &y)| {
            node(x, y).map(|i| values[i] + mean).ok_or_else(|| {
                Error::invalid("edge gerchberg-papoulis", "extension point off the lattice")
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::TAU;

    /// A band-limited periodic surface on a 64 x 64 lattice of 0.5 mm: harmonics (2, 0), (1, 3)
    /// and (-2, 1) of the 32 mm period, all below 0.125 cycles/mm.
    fn surface(i: usize, j: usize) -> f64 {
        let (u, v) = (i as f64 / 64.0, j as f64 / 64.0);
        20.0 * (TAU * 2.0 * u).cos() + 8.0 * (TAU * (u + 3.0 * v)).sin()
            - 5.0 * (TAU * (-2.0 * u + v) + 0.3).cos()
    }

    #[test]
    fn recovers_a_band_limited_surface() {
        let (nx, ny) = (64, 64);
        let truth: Vec<f64> = (0..nx * ny).map(|k| surface(k % nx, k / nx)).collect();
        // Unknown: a 10-node strip across the lattice and a 12 x 12 block.
        let known: Vec<bool> = (0..nx * ny)
            .map(|k| {
                let (i, j) = (k % nx, k / nx);
                !((50..60).contains(&i) || ((5..17).contains(&i) && (20..32).contains(&j)))
            })
            .collect();
        let mut v: Vec<f64> = truth
            .iter()
            .zip(&known)
            .map(|(&t, &k)| if k { t } else { 0.0 })
            .collect();
        let before = truth
            .iter()
            .zip(&v)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        extend_on_lattice(&mut v, &known, nx, ny, 0.5, 0.125, 300).unwrap();
        let err = truth
            .iter()
            .zip(&v)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        // Stated tolerance: 1e-6 of the surface's 33 nm amplitude after 300 iterations.
        assert!(err < 1e-6 * 33.0, "max error {err} (from {before})");
        // The known samples are untouched.
        for k in 0..nx * ny {
            if known[k] {
                assert_eq!(v[k], truth[k]);
            }
        }
    }

    /// A band-limited surface periodic on an odd `nx x ny` lattice (no Nyquist bin along x):
    /// harmonics (1, 0), (2, 1) and (-1, 1) of the lattice periods.
    fn odd_surface(i: usize, j: usize, nx: usize, ny: usize) -> f64 {
        let (u, v) = (i as f64 / nx as f64, j as f64 / ny as f64);
        12.0 * (TAU * u + 0.4).cos() + 6.0 * (TAU * (2.0 * u + v)).sin()
            - 3.0 * (TAU * (-u + v)).cos()
    }

    #[test]
    fn recovers_a_band_limited_surface_on_an_odd_lattice_for_any_thread_count() {
        let (nx, ny) = (63, 50);
        let pitch = 0.5;
        // Band limit just above the surface's highest frequency, |(2 / 31.5, 1 / 25)| = 0.075
        // cycles/mm.
        let band = 0.08;
        let truth: Vec<f64> = (0..nx * ny)
            .map(|k| odd_surface(k % nx, k / nx, nx, ny))
            .collect();
        let known: Vec<bool> = (0..nx * ny)
            .map(|k| {
                let (i, j) = (k % nx, k / nx);
                !((20..26).contains(&i) && (10..30).contains(&j))
            })
            .collect();
        let start: Vec<f64> = truth
            .iter()
            .zip(&known)
            .map(|(&t, &k)| if k { t } else { 0.0 })
            .collect();
        let run = |threads: usize| {
            let mut v = start.clone();
            crate::test_support::on_threads(threads, || {
                extend_on_lattice(&mut v, &known, nx, ny, pitch, band, 300)
            })
            .unwrap();
            v
        };
        let v = run(1);
        let err = truth
            .iter()
            .zip(&v)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        // Stated tolerance: 1e-6 of the surface's 21 nm amplitude after 300 iterations.
        assert!(err < 1e-6 * 21.0, "max error {err}");
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&v), bits(&run(2)));
    }

    #[test]
    fn map_level_extension_of_a_constant_is_that_constant() {
        let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..10 {
            for i in 0..20 {
                x.push(i as f64 * 0.5);
                y.push(j as f64 * 0.5);
                z.push(7.25);
            }
        }
        let e = extend(&x, &y, &z, &[-1.0, 11.0], &[2.0, 6.0], 0.1, 20).unwrap();
        for v in e {
            assert!((v - 7.25).abs() < 1e-9, "{v}");
        }
        // Off-lattice maps are refused with the point named.
        x[3] += 0.2;
        let err = extend(&x, &y, &z, &[-1.0], &[2.0], 0.1, 20).unwrap_err();
        assert!(err.to_string().contains("map point 3"), "{err}");
    }
}
