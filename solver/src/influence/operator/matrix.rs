//! The assembled influence matrix `R` (m x n, nm/s), stored by columns, as an
//! [`InfluenceOperator`]: its products through the row copy ([`super::sparse`]) and, where the
//! caller takes enough normal products, through the Gram matrix `R^T R` ([`super::gram`]). The
//! influence models assemble it ([`crate::influence::model::point`] and the swept and surface
//! models).

use super::gram::{GramMatrix, GramOperator};
use super::sparse::SparseOperator;
use super::{InfluenceOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use nalgebra_sparse::{CscMatrix, CsrMatrix};
use rayon::prelude::*;
use std::sync::OnceLock;

/// Bytes held per non-zero of `R` through a solve: row index and value in the CSC matrix, and
/// again in the row-major copy the products use.
pub const NNZ_BYTES: f64 = 32.0;

/// The sparse influence matrix, stored by columns (one column per dwell point), with the row
/// copy and Gram matrix its products take, each built at the first call that needs it
/// ([`InfluenceOperator::products`]) and kept for the next (a solve followed by another on the
/// same matrix, as the acceleration-limited stage does, builds them once).
#[derive(Debug, Clone)]
pub struct InfluenceMatrix {
    csc: CscMatrix<f64>,
    rows: OnceLock<CsrMatrix<f64>>,
    gram: OnceLock<GramMatrix>,
}

impl PartialEq for InfluenceMatrix {
    /// Equal entries (the kept copies are derived from them).
    fn eq(&self, other: &Self) -> bool {
        self.csc == other.csc
    }
}

impl InfluenceMatrix {
    /// The Gram matrix `R^T R` where [`InfluenceOperator::products`] has formed it.
    pub fn formed_gram(&self) -> Option<&GramMatrix> {
        self.gram.get()
    }

    /// Wraps an existing CSC matrix (m measurement points x n dwell points).
    pub fn from_csc(csc: CscMatrix<f64>) -> Self {
        Self {
            csc,
            rows: OnceLock::new(),
            gram: OnceLock::new(),
        }
    }

    /// The matrix in compressed sparse column form.
    pub fn csc(&self) -> &CscMatrix<f64> {
        &self.csc
    }

    /// Number of measurement points (rows).
    pub fn nrows(&self) -> usize {
        self.csc.nrows()
    }

    /// Number of dwell points (columns).
    pub fn ncols(&self) -> usize {
        self.csc.ncols()
    }

    /// Number of stored non-zero entries.
    pub fn nnz(&self) -> usize {
        self.csc.nnz()
    }

    /// Dwell points whose column is empty: no measurement point lies in the tool's reach.
    pub fn empty_columns(&self) -> Vec<usize> {
        self.csc
            .col_offsets()
            .windows(2)
            .enumerate()
            .filter(|(_, w)| matches!(w, [a, b] if a == b))
            .map(|(j, _)| j)
            .collect()
    }

    /// Removal `h = R t`, nm, for dwell times `t` (s). Sequential, so bit-identical for any
    /// thread count.
    pub fn removal_nm(&self, dwell_s: &[f64]) -> Result<Vec<f64>> {
        if dwell_s.len() != self.ncols() {
            return Err(Error::LengthMismatch {
                what: "dwell_s",
                got: dwell_s.len(),
                expected: self.ncols(),
            });
        }
        let mut h = vec![0.0; self.nrows()];
        for (col, &t) in self.csc.col_iter().zip(dwell_s) {
            for (&i, &r) in col.row_indices().iter().zip(col.values()) {
                if let Some(hi) = h.get_mut(i) {
                    *hi += r * t;
                }
            }
        }
        Ok(h)
    }

    /// `g = R^T y`, one dot product per column (in parallel; each entry is summed in a fixed order).
    pub fn transpose_mul(&self, y: &[f64]) -> Result<Vec<f64>> {
        if y.len() != self.nrows() {
            return Err(Error::LengthMismatch {
                what: "R^T y input",
                got: y.len(),
                expected: self.nrows(),
            });
        }
        let offsets = self.csc.col_offsets();
        let rows = self.csc.row_indices();
        let vals = self.csc.values();
        Ok((0..self.ncols())
            .into_par_iter()
            .map(|j| {
                let (a, b) = (offsets[j], offsets[j + 1]);
                rows[a..b]
                    .iter()
                    .zip(&vals[a..b])
                    .map(|(&i, &v)| v * y.get(i).copied().unwrap_or(0.0))
                    .sum()
            })
            .collect())
    }
}

impl InfluenceOperator for InfluenceMatrix {
    fn kind(&self) -> OperatorKind {
        OperatorKind::Sparse
    }

    fn shape(&self) -> (usize, usize) {
        (self.csc.nrows(), self.csc.ncols())
    }

    fn nnz(&self) -> usize {
        self.csc.nnz()
    }

    fn empty_columns(&self) -> Vec<usize> {
        InfluenceMatrix::empty_columns(self)
    }

    /// The CSC matrix with its CSR copy (`R t` by rows), and with its Gram matrix where the
    /// caller takes normal products and it is formed already or forming it pays; both are built
    /// once and kept.
    fn products(&self, normal_products: Option<usize>) -> Products<'_> {
        let csr = self.rows.get_or_init(|| CsrMatrix::from(&self.csc));
        let op = SparseOperator::with_rows(&self.csc, csr);
        let gram = match normal_products {
            Some(k) => match self.gram.get() {
                Some(g) => Some(g),
                None if GramMatrix::worthwhile(&op, k) => {
                    Some(self.gram.get_or_init(|| GramMatrix::new(&op)))
                }
                None => None,
            },
            None => None,
        };
        match gram {
            Some(g) => Products::Built(Box::new(GramOperator::with_gram(op, g))),
            None => Products::Built(Box::new(op)),
        }
    }

    /// The sequential column sweep of [`InfluenceMatrix::removal_nm`] (no row copy).
    fn removal_nm(&self, dwell_s: &[f64]) -> Result<Vec<f64>> {
        InfluenceMatrix::removal_nm(self, dwell_s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::test_support::scattered;
    use crate::tif::GaussianTif;

    #[test]
    fn removal_is_linear_and_adjoint_holds() {
        let (mx, my) = scattered(300, 3);
        let (dx, dy) = scattered(40, 4);
        let tif = GaussianTif::new(1.5, 2.0, 4.5).unwrap();
        let r = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        let t1: Vec<f64> = (0..40).map(|j| 1.0 + j as f64 * 0.1).collect();
        let t2: Vec<f64> = (0..40).map(|j| (j as f64).sin().abs()).collect();
        let h1 = r.removal_nm(&t1).unwrap();
        let h2 = r.removal_nm(&t2).unwrap();
        let sum: Vec<f64> = t1.iter().zip(&t2).map(|(a, b)| 2.0 * a + 3.0 * b).collect();
        let hs = r.removal_nm(&sum).unwrap();
        for i in 0..300 {
            assert!((hs[i] - (2.0 * h1[i] + 3.0 * h2[i])).abs() <= 1e-12 * hs[i].abs().max(1.0));
        }
        let y: Vec<f64> = (0..300).map(|i| (i as f64 * 0.37).cos()).collect();
        let g = r.transpose_mul(&y).unwrap();
        let lhs: f64 = h1.iter().zip(&y).map(|(a, b)| a * b).sum();
        let rhs: f64 = g.iter().zip(&t1).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(1.0));
    }

    /// The row copy and Gram matrix are built once and kept: a second call borrows the same
    /// ones, and its products equal the first call's and the CSC matrix's own (`R t` by rows,
    /// `G t` against `R^T (R t)`: rounding only).
    #[test]
    fn products_build_the_row_copy_and_gram_matrix_once() {
        let (mx, my) = scattered(400, 5);
        let (dx, dy) = scattered(60, 6);
        let tif = GaussianTif::new(1.5, 2.0, 4.5).unwrap();
        let r = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        let t: Vec<f64> = (0..60).map(|j| 0.5 + (j % 7) as f64 * 0.2).collect();
        // Without normal products: the row copy, no Gram matrix.
        let plain = r.products(None);
        assert!(r.formed_gram().is_none());
        let first = r.products(Some(10_000));
        let formed: *const GramMatrix = r
            .formed_gram()
            .expect("a Gram matrix pays for 10,000 normal products here");
        let second = r.products(Some(10_000));
        assert!(std::ptr::eq(formed, r.formed_gram().unwrap()));
        drop(first);
        let (mut h_rows, mut h_normal, mut h_gram) = (vec![0.0; 400], vec![0.0; 60], vec![0.0; 60]);
        plain.apply(&t, &mut h_rows);
        let h_cols = r.removal_nm(&t).unwrap();
        let scale = h_cols.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
        for (x, y) in h_rows.iter().zip(&h_cols) {
            assert!((x - y).abs() <= 1e-13 * scale);
        }
        plain.apply_transpose(&h_rows, &mut h_normal);
        second.apply_normal(&t, &mut vec![0.0; 400], &mut h_gram);
        let scale = h_normal.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
        for (x, y) in h_gram.iter().zip(&h_normal) {
            assert!((x - y).abs() <= 1e-12 * scale);
        }
    }
}
