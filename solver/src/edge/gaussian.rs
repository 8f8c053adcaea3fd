//! Gaussian-weighted extrapolation.
//!
//! The height at an extension point `q` is the Gaussian-weighted mean of the map heights,
//! `z(q) = sum_i w_i z_i / sum_i w_i`, `w_i = exp(-|q - p_i|^2 / (2 sigma^2))` (Nadaraya-Watson
//! kernel regression: Nadaraya, Theory Probab. Appl. 9, 141 (1964); Watson, Sankhya A 26, 359
//! (1964)), over the map points within `d_0 + 3 sigma` of `q`, where `d_0` is the distance to
//! the nearest map point (the weights are computed relative to that point's, which leaves the
//! ratio unchanged and keeps them representable far from the map). The extension is a convex
//! combination of measured heights: it never leaves the map's range, reproduces a constant map
//! exactly, and far beyond `sigma` it follows the rim's heights.

use super::Buckets;
use crate::error::{Error, Result};
use rayon::prelude::*;

/// Heights at `(x, y)` extrapolated from the map with standard deviation `sigma_mm`, nm.
pub fn extend(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    map_z_nm: &[f64],
    x_mm: &[f64],
    y_mm: &[f64],
    sigma_mm: f64,
) -> Result<Vec<f64>> {
    if map_x_mm.is_empty() {
        return Err(Error::invalid("map", "has no points"));
    }
    let b = Buckets::new(map_x_mm, map_y_mm, sigma_mm);
    let two_s2 = 2.0 * sigma_mm * sigma_mm;
    Ok(x_mm
        .par_iter()
        .zip(y_mm)
        .map(|(&px, &py)| {
            let Some((_, d0)) = b.nearest(map_x_mm, map_y_mm, px, py, f64::INFINITY) else {
                return 0.0;
            };
            let (mut sw, mut swz) = (0.0, 0.0);
            b.within(map_x_mm, map_y_mm, px, py, d0 + 3.0 * sigma_mm, |i, d| {
                let w = (-(d * d - d0 * d0) / two_s2).exp();
                sw += w;
                swz += w * map_z_nm[i];
            });
            swz / sw
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::super::tests::grid_map;
    use super::*;

    #[test]
    fn constant_map_extends_exactly() {
        let (x, y, z) = grid_map(|_, _| 42.5);
        let e = extend(&x, &y, &z, &[-2.0, 13.0, 5.0], &[-1.0, 2.0, 9.0], 1.0).unwrap();
        for v in e {
            assert!((v - 42.5).abs() < 1e-12, "{v}");
        }
    }

    #[test]
    fn extension_stays_in_the_map_range_and_matches_a_slow_sum() {
        let (x, y, z) = grid_map(|a, b| (0.7 * a).sin() * 10.0 + b * b);
        let (lo, hi) = z
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let (qx, qy) = ([-1.5, 11.0, 4.0], [2.0, 5.5, -3.0]);
        let sigma = 1.3;
        let e = extend(&x, &y, &z, &qx, &qy, sigma).unwrap();
        for k in 0..3 {
            assert!(e[k] >= lo && e[k] <= hi);
            // Slow reference: every map point (the truncated tail is below exp(-4.5) relative
            // to the nearest point's weight, times at most m points).
            let (mut sw, mut swz) = (0.0, 0.0);
            for i in 0..x.len() {
                let d2 = (x[i] - qx[k]).powi(2) + (y[i] - qy[k]).powi(2);
                let w = (-d2 / (2.0 * sigma * sigma)).exp();
                sw += w;
                swz += w * z[i];
            }
            let slow = swz / sw;
            assert!((e[k] - slow).abs() < 0.05 * (hi - lo), "{} vs {slow}", e[k]);
        }
    }
}
