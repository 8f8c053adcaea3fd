//! Stacked influence matrices. Several tools in one solve: `[R_1 / w_1, R_2 / w_2, ...]`, the
//! tools' matrices side by side over the same map points, each column block divided by the
//! tool's machining-time weight `w_k` (so that `rho sum(u)` with `u_k = w_k t_k` weighs tool `k`'s
//! time by `w_k`; `R_k t_k = (R_k / w_k) u_k`). Several scenarios of one path (the robust plan):
//! `[R_1; R_2; ...]`, one above the other over the same dwell points.

use super::matrix::InfluenceMatrix;
use crate::error::{Error, Result};
use nalgebra_sparse::CscMatrix;

/// `[R_1 / w_1, R_2 / w_2, ...]`; every block must have the same rows and every weight be
/// positive and finite.
pub fn stack_scaled(blocks: &[(&InfluenceMatrix, f64)]) -> Result<InfluenceMatrix> {
    let m = blocks.first().map_or(0, |(r, _)| r.nrows());
    let (mut offsets, mut rows, mut vals) = (vec![0usize], Vec::new(), Vec::new());
    for (k, &(r, w)) in blocks.iter().enumerate() {
        if r.nrows() != m {
            return Err(Error::LengthMismatch {
                what: "stacked influence matrix rows",
                got: r.nrows(),
                expected: m,
            });
        }
        if !(w.is_finite() && w > 0.0) {
            return Err(Error::invalid(
                "time_weight",
                format!("tool {}: must be positive, got {w}", k + 1),
            ));
        }
        for col in r.csc().col_iter() {
            rows.extend_from_slice(col.row_indices());
            vals.extend(col.values().iter().map(|v| v / w));
            offsets.push(rows.len());
        }
    }
    let n = offsets.len() - 1;
    let csc =
        CscMatrix::try_from_csc_data(m, n, offsets, rows, vals).map_err(|e| Error::Numerical {
            stage: "stacked influence matrix",
            why: e.to_string(),
        })?;
    Ok(InfluenceMatrix::from_csc(csc))
}

/// `[R_1; R_2; ...]`: the blocks one above the other (same columns), as the robust plan's
/// scenarios ([`crate::setup::robust`]).
pub fn stack_rows(blocks: &[InfluenceMatrix]) -> Result<InfluenceMatrix> {
    let Some(first) = blocks.first() else {
        return Err(Error::invalid("robust", "no scenario"));
    };
    let (m, n) = (first.csc().nrows(), first.csc().ncols());
    if let Some(b) = blocks
        .iter()
        .find(|b| b.csc().ncols() != n || b.csc().nrows() != m)
    {
        return Err(Error::LengthMismatch {
            what: "scenario influence matrix",
            got: b.csc().ncols(),
            expected: n,
        });
    }
    let nnz: usize = blocks.iter().map(|b| b.csc().nnz()).sum();
    let (mut offsets, mut rows, mut vals) = (
        Vec::with_capacity(n + 1),
        Vec::with_capacity(nnz),
        Vec::with_capacity(nnz),
    );
    offsets.push(0);
    for j in 0..n {
        for (k, b) in blocks.iter().enumerate() {
            let col = b.csc().col(j);
            rows.extend(col.row_indices().iter().map(|i| i + k * m));
            vals.extend_from_slice(col.values());
        }
        offsets.push(rows.len());
    }
    let csc =
        CscMatrix::try_from_csc_data(m * blocks.len(), n, offsets, rows, vals).map_err(|e| {
            Error::Numerical {
                stage: "stacked scenario matrix",
                why: e.to_string(),
            }
        })?;
    Ok(InfluenceMatrix::from_csc(csc))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    #[test]
    fn stacked_product_is_the_weighted_sum_of_the_tools_products() {
        let (mx, my): (Vec<f64>, Vec<f64>) =
            (0..100).map(|k| ((k % 10) as f64, (k / 10) as f64)).unzip();
        let big = GaussianTif::new(2.0, 1.0, 6.0).unwrap();
        let small = GaussianTif::new(0.5, 3.0, 1.5).unwrap();
        let (d1x, d1y) = (vec![2.0, 5.0, 8.0], vec![2.0, 5.0, 8.0]);
        let (d2x, d2y) = (vec![1.5, 4.5, 6.5, 9.0], vec![3.0, 1.0, 7.5, 9.0]);
        let r1 = InfluenceMatrix::assemble(&mx, &my, &d1x, &d1y, &big, &Silent).unwrap();
        let r2 = InfluenceMatrix::assemble(&mx, &my, &d2x, &d2y, &small, &Silent).unwrap();
        let (w1, w2) = (1.0, 4.0);
        let s = stack_scaled(&[(&r1, w1), (&r2, w2)]).unwrap();
        assert_eq!((s.nrows(), s.ncols()), (100, 7));
        let t1 = [1.0, 2.0, 0.5];
        let t2 = [0.3, 0.0, 2.0, 1.0];
        let u: Vec<f64> = t1
            .iter()
            .map(|t| t * w1)
            .chain(t2.iter().map(|t| t * w2))
            .collect();
        let h = s.removal_nm(&u).unwrap();
        let h1 = r1.removal_nm(&t1).unwrap();
        let h2 = r2.removal_nm(&t2).unwrap();
        for i in 0..100 {
            assert!((h[i] - h1[i] - h2[i]).abs() <= 1e-12 * (h1[i] + h2[i]).abs().max(1.0));
        }
        assert!(stack_scaled(&[(&r1, 1.0), (&r2, 0.0)]).is_err());
    }
}
