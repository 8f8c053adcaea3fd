//! Dense least squares for tall problems: tall-skinny QR (TSQR, Demmel et al., "Communication-
//! optimal parallel and sequential QR", 2012) over row blocks, then an SVD of the small
//! column-scaled triangular factor.
//!
//! For `min ||A x - b||`, the rows of `[A | b]` are generated block by block, each block is
//! reduced to its triangular factor by Householder QR (faer) in parallel, and the stacked factors
//! are reduced once more. Blocks are fixed and combined in order, so the answer does not depend on
//! the thread count.

use crate::error::{Error, Result};
use faer::linalg::solvers::{Qr, Svd};
use faer::Mat;
use rayon::prelude::*;

/// Rows per block.
const BLOCK_ROWS: usize = 4096;

/// The triangular factor of `[A | b]` (`(p + 1) x (p + 1)` when there are enough rows).
pub(crate) fn tsqr<F>(n_rows: usize, n_cols: usize, fill_row: F) -> Result<Mat<f64>>
where
    F: Fn(usize, &mut [f64]) -> Result<()> + Sync,
{
    let n_blocks = n_rows.div_ceil(BLOCK_ROWS);
    // Blocks in flight (one per thread) plus the stacked factors, each `rows x n_cols`.
    let block = BLOCK_ROWS.min(n_rows.max(1)) as f64 * n_cols as f64;
    let stacked = n_blocks as f64 * (n_cols.min(BLOCK_ROWS)) as f64 * n_cols as f64;
    crate::budget::check_f64s(
        "terms of the fit",
        &format!("a dense least-squares fit of {n_rows} points and {n_cols} columns"),
        block * rayon::current_num_threads() as f64 + stacked,
        1.0,
    )?;
    let factors: Vec<Mat<f64>> = (0..n_blocks)
        .into_par_iter()
        .map(|b| {
            let start = b * BLOCK_ROWS;
            let end = (start + BLOCK_ROWS).min(n_rows);
            let mut a = Mat::<f64>::zeros(end - start, n_cols);
            let mut row = vec![0.0; n_cols];
            for i in start..end {
                fill_row(i, &mut row)?;
                for (c, &v) in row.iter().enumerate() {
                    a[(i - start, c)] = v;
                }
            }
            Ok(triangular(&a))
        })
        .collect::<Result<_>>()?;
    let total: usize = factors.iter().map(|f| f.nrows()).sum();
    let mut stacked = Mat::<f64>::zeros(total, n_cols);
    let mut r0 = 0;
    for f in &factors {
        for c in 0..n_cols {
            for r in 0..f.nrows() {
                stacked[(r0 + r, c)] = f[(r, c)];
            }
        }
        r0 += f.nrows();
    }
    Ok(triangular(&stacked))
}

/// The upper-triangular factor of a matrix (`min(m, n) x n`).
fn triangular(a: &Mat<f64>) -> Mat<f64> {
    if a.nrows() == 0 {
        return Mat::zeros(0, a.ncols());
    }
    let qr = Qr::new(a.as_ref());
    let r = qr.thin_R();
    Mat::from_fn(
        r.nrows(),
        r.ncols(),
        |i, j| if j >= i { r[(i, j)] } else { 0.0 },
    )
}

/// The least-squares problem reduced to the triangular factor of `[A | b]`, with `A`'s columns
/// scaled to unit norm and the SVD of the scaled factor.
pub(crate) struct Reduced {
    /// Column norms of `A` (the scale factors).
    pub scale: Vec<f64>,
    /// `Q^T b` restricted to the first `p` rows.
    pub qb: Vec<f64>,
    /// Norm of the residual of the exact least-squares solution (`|R[p, p]|`).
    #[allow(dead_code)]
    pub residual_norm: f64,
    /// Singular values of the scaled factor.
    pub sigma: Vec<f64>,
    u: Mat<f64>,
    v: Mat<f64>,
}

impl Reduced {
    /// Reduces the triangular factor `r_aug` of `[A | b]` with `p` columns in `A`.
    pub fn new(r_aug: &Mat<f64>, p: usize, what: &str) -> Result<Self> {
        if r_aug.nrows() < p {
            return Err(Error::Geometry(format!(
                "{what}: {} points cannot determine {p} parameters",
                r_aug.nrows()
            )));
        }
        let mut scale = vec![0.0; p];
        for (c, s) in scale.iter_mut().enumerate() {
            let mut ss = 0.0;
            for r in 0..=c {
                ss += r_aug[(r, c)] * r_aug[(r, c)];
            }
            *s = ss.sqrt();
            if !(*s > 0.0) || !s.is_finite() {
                return Err(Error::Geometry(format!(
                    "{what}: parameter {c} has no effect on the points (all its basis values are zero)"
                )));
            }
        }
        let rs = Mat::from_fn(p, p, |i, j| {
            if j >= i {
                r_aug[(i, j)] / scale[j]
            } else {
                0.0
            }
        });
        let qb: Vec<f64> = (0..p).map(|i| r_aug[(i, p)]).collect();
        let residual_norm = if r_aug.nrows() > p {
            r_aug[(p, p)].abs()
        } else {
            0.0
        };
        let svd = Svd::new(rs.as_ref()).map_err(|e| Error::Numerical {
            stage: "least-squares SVD",
            why: format!("{e:?}"),
        })?;
        let s = svd.S().column_vector();
        let sigma: Vec<f64> = (0..p).map(|k| s[k]).collect();
        Ok(Self {
            scale,
            qb,
            residual_norm,
            sigma,
            u: svd.U().to_owned(),
            v: svd.V().to_owned(),
        })
    }

    /// Condition estimate of the column-scaled problem: `sigma_max / sigma_min`.
    pub fn condition(&self) -> f64 {
        let max = self.sigma.iter().copied().fold(0.0, f64::max);
        let min = self.sigma.iter().copied().fold(f64::INFINITY, f64::min);
        if min > 0.0 {
            max / min
        } else {
            f64::INFINITY
        }
    }

    /// Solution `x` (unscaled) of the damped problem `min ||A x - b||^2 + lambda ||D x||^2` with
    /// `D` the column norms: `y = V diag(s / (s^2 + lambda)) U^T Q^T b`, `x = y / scale`. Singular
    /// values below `rcond * sigma_max` are dropped (minimum-norm solution).
    pub fn solve(&self, lambda: f64, rcond: f64) -> Vec<f64> {
        let p = self.scale.len();
        let smax = self.sigma.iter().copied().fold(0.0, f64::max);
        let mut coef = vec![0.0; p];
        for (k, (c, &s)) in coef.iter_mut().zip(&self.sigma).enumerate() {
            if !(s > rcond * smax) {
                continue;
            }
            let mut utb = 0.0;
            for i in 0..p {
                utb += self.u[(i, k)] * self.qb[i];
            }
            *c = utb * s / (s * s + lambda);
        }
        (0..p)
            .map(|j| {
                let mut y = 0.0;
                for (k, c) in coef.iter().enumerate() {
                    y += self.v[(j, k)] * c;
                }
                y / self.scale[j]
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tsqr_solves_a_known_line_fit() {
        // z = 3 + 2 t + noise-free, 10_000 rows over several blocks.
        let n = 10_000;
        let r = tsqr(n, 3, |i, row| {
            let t = i as f64 / n as f64;
            row[0] = 1.0;
            row[1] = t;
            // The pattern + - - + is orthogonal to 1 and t.
            row[2] = 3.0 + 2.0 * t + if i % 4 == 0 || i % 4 == 3 { 0.5 } else { -0.5 };
            Ok(())
        })
        .unwrap();
        let red = Reduced::new(&r, 2, "test").unwrap();
        let x = red.solve(0.0, 1e-15);
        assert!(
            (x[0] - 3.0).abs() < 1e-10 && (x[1] - 2.0).abs() < 1e-10,
            "{x:?}"
        );
        // Residual norm = sqrt(n * 0.25).
        assert!((red.residual_norm - (n as f64 * 0.25).sqrt()).abs() < 1e-8);
        assert!(red.condition() > 1.0 && red.condition() < 10.0);
    }
}
