//! Local polynomial extrapolation.
//!
//! For each extension point `q`, with `p*` its nearest map point, a polynomial of total degree
//! `d` (`sum_{a+b<=d} c_ab u^a v^b` in coordinates centred at `p*` and scaled by the fit radius
//! `R`) is fitted by least squares to the map points within `R` of `p*` and evaluated at `q`
//! (local polynomial regression: Cleveland, J. Am. Stat. Assoc. 74, 829 (1979), here
//! unweighted and evaluated beyond the data). Rank-deficient neighbourhoods (a
//! single line of points) get the minimum-norm least-squares fit. A map that is itself a
//! polynomial of degree `<= d` is extended exactly.

use super::Buckets;
use crate::error::{Error, Result};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

/// Heights at `(x, y)` extrapolated by local fits of degree `degree` over radius `fit_radius_mm`.
pub fn extend(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    map_z_nm: &[f64],
    x_mm: &[f64],
    y_mm: &[f64],
    degree: usize,
    fit_radius_mm: f64,
) -> Result<Vec<f64>> {
    if map_x_mm.is_empty() {
        return Err(Error::invalid("map", "has no points"));
    }
    let b = Buckets::new(map_x_mm, map_y_mm, fit_radius_mm);
    let powers: Vec<(i32, i32)> = (0..=degree as i32)
        .flat_map(|t| (0..=t).map(move |a| (a, t - a)))
        .collect();
    x_mm.par_iter()
        .zip(y_mm)
        .map(|(&px, &py)| {
            let Some((near, _)) = b.nearest(map_x_mm, map_y_mm, px, py, f64::INFINITY) else {
                return Ok(0.0);
            };
            let (cx, cy) = (map_x_mm[near], map_y_mm[near]);
            let mut idx = Vec::new();
            b.within(map_x_mm, map_y_mm, cx, cy, fit_radius_mm, |i, _| {
                idx.push(i)
            });
            let k = powers.len();
            let row = |x: f64, y: f64| -> Vec<f64> {
                let (u, v) = ((x - cx) / fit_radius_mm, (y - cy) / fit_radius_mm);
                powers.iter().map(|&(a, c)| u.powi(a) * v.powi(c)).collect()
            };
            let mut a = DMatrix::<f64>::zeros(idx.len(), k);
            let mut rhs = DVector::<f64>::zeros(idx.len());
            for (r, &i) in idx.iter().enumerate() {
                for (c, v) in row(map_x_mm[i], map_y_mm[i]).into_iter().enumerate() {
                    a[(r, c)] = v;
                }
                rhs[r] = map_z_nm[i];
            }
            let coef = a
                .svd(true, true)
                .solve(&rhs, 1e-10)
                .map_err(|why| Error::Numerical {
                    stage: "polynomial edge extrapolation",
                    why: why.to_string(),
                })?;
            Ok(row(px, py)
                .into_iter()
                .zip(coef.iter())
                .map(|(t, c)| t * c)
                .sum())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::super::tests::grid_map;
    use super::*;

    #[test]
    fn reproduces_polynomials_of_its_degree() {
        let quad =
            |a: f64, b: f64| 3.0 + 0.5 * a - 2.0 * b + 0.1 * a * a - 0.3 * a * b + 0.2 * b * b;
        let (x, y, z) = grid_map(quad);
        let (qx, qy) = ([-2.0, 12.5, 5.0, 11.0], [1.0, 3.0, -2.5, 6.0]);
        let e = extend(&x, &y, &z, &qx, &qy, 2, 3.0).unwrap();
        for k in 0..qx.len() {
            let want = quad(qx[k], qy[k]);
            assert!(
                (e[k] - want).abs() < 1e-8 * want.abs().max(1.0),
                "{} vs {want}",
                e[k]
            );
        }
        // Degree 1 reproduces a plane but not the quadratic.
        let plane = |a: f64, b: f64| 1.0 + 0.25 * a - 0.75 * b;
        let (x, y, z) = grid_map(plane);
        let e = extend(&x, &y, &z, &qx, &qy, 1, 2.0).unwrap();
        for k in 0..qx.len() {
            assert!((e[k] - plane(qx[k], qy[k])).abs() < 1e-9);
        }
        let (x, y, z) = grid_map(quad);
        let e = extend(&x, &y, &z, &qx, &qy, 1, 2.0).unwrap();
        assert!((0..qx.len()).any(|k| (e[k] - quad(qx[k], qy[k])).abs() > 1e-3));
    }
}
