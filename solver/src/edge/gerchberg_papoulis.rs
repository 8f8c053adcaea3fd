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

use crate::error::{Error, Result};
use crate::machine::machinability::map_pitch_mm;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

/// The iteration on a periodic `nx x ny` lattice of pitch `pitch_mm` (row-major, x fastest):
/// `values` at the `known` nodes are kept, the others are replaced by the band-limited
/// extension after `iterations` steps.
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
    let mut planner = FftPlanner::<f64>::new();
    let (fwd_x, inv_x) = (planner.plan_fft_forward(nx), planner.plan_fft_inverse(nx));
    let (fwd_y, inv_y) = (planner.plan_fft_forward(ny), planner.plan_fft_inverse(ny));
    let freq = |k: usize, len: usize| -> f64 {
        let s = if k <= len / 2 {
            k as f64
        } else {
            k as f64 - len as f64
        };
        s / (len as f64 * pitch_mm)
    };
    let keep: Vec<bool> = (0..n)
        .map(|i| {
            let (kx, ky) = (i % nx, i / nx);
            freq(kx, nx).powi(2) + freq(ky, ny).powi(2) <= band_limit_per_mm.powi(2)
        })
        .collect();
    let mut buf: Vec<Complex<f64>> = values.iter().map(|&v| Complex::new(v, 0.0)).collect();
    let mut column = vec![Complex::new(0.0, 0.0); ny];
    let scale = 1.0 / n as f64;
    for _ in 0..iterations {
        for row in buf.chunks_mut(nx) {
            fwd_x.process(row);
        }
        for kx in 0..nx {
            for (ky, c) in column.iter_mut().enumerate() {
                *c = buf[ky * nx + kx];
            }
            fwd_y.process(&mut column);
            for (ky, c) in column.iter_mut().enumerate() {
                if !keep[ky * nx + kx] {
                    *c = Complex::new(0.0, 0.0);
                }
            }
            inv_y.process(&mut column);
            for (ky, c) in column.iter().enumerate() {
                buf[ky * nx + kx] = *c;
            }
        }
        for row in buf.chunks_mut(nx) {
            inv_x.process(row);
        }
        for i in 0..n {
            buf[i] = if known[i] {
                Complex::new(values[i], 0.0)
            } else {
                Complex::new(buf[i].re * scale, 0.0)
            };
        }
    }
    for i in 0..n {
        if !known[i] {
            values[i] = buf[i].re;
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
                     {p} mm lattice"
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
