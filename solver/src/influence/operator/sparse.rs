//! The assembled influence matrix as a [`LinearOperator`]: its CSC arrays for `R^T y` (one dot
//! product per column) and a CSR copy for `R t` (one dot product per row), each output entry
//! one dot product in a fixed order, so results are bit-identical for any thread count.

use super::LinearOperator;
use nalgebra_sparse::{CscMatrix, CsrMatrix};
use rayon::prelude::*;
use std::borrow::Cow;

/// The sparse influence matrix as an operator: CSC for `R^T y` (one dot product per column) and a
/// CSR copy for `R t` (one dot product per row). Memory: about twice the matrix.
#[derive(Debug, Clone)]
pub struct SparseOperator<'a> {
    csc: &'a CscMatrix<f64>,
    csr: Cow<'a, CsrMatrix<f64>>,
}

impl<'a> SparseOperator<'a> {
    /// Wraps a CSC matrix and builds its CSR copy.
    pub fn new(csc: &'a CscMatrix<f64>) -> Self {
        Self {
            csc,
            csr: Cow::Owned(CsrMatrix::from(csc)),
        }
    }

    /// Wraps a CSC matrix and its CSR copy `csr` (the same matrix by rows, built once by the
    /// caller).
    pub fn with_rows(csc: &'a CscMatrix<f64>, csr: &'a CsrMatrix<f64>) -> Self {
        Self {
            csc,
            csr: Cow::Borrowed(csr),
        }
    }

    /// The matrix by columns.
    pub fn csc(&self) -> &CscMatrix<f64> {
        self.csc
    }

    /// The matrix by rows.
    pub fn csr(&self) -> &CsrMatrix<f64> {
        &self.csr
    }
}

/// Minimum number of output entries handed to one rayon task.
const MIN_TASK: usize = 512;

impl LinearOperator for SparseOperator<'_> {
    fn nrows(&self) -> usize {
        self.csc.nrows()
    }

    fn ncols(&self) -> usize {
        self.csc.ncols()
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        let offsets = self.csr.row_offsets();
        let cols = self.csr.col_indices();
        let vals = self.csr.values();
        out.par_iter_mut()
            .enumerate()
            .with_min_len(MIN_TASK)
            .for_each(|(i, o)| {
                let (a, b) = (offsets[i], offsets[i + 1]);
                *o = cols[a..b]
                    .iter()
                    .zip(&vals[a..b])
                    .map(|(&j, &v)| v * t.get(j).copied().unwrap_or(0.0))
                    .sum();
            });
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        let offsets = self.csc.col_offsets();
        let rows = self.csc.row_indices();
        let vals = self.csc.values();
        out.par_iter_mut()
            .enumerate()
            .with_min_len(MIN_TASK / 4)
            .for_each(|(j, o)| {
                let (a, b) = (offsets[j], offsets[j + 1]);
                *o = rows[a..b]
                    .iter()
                    .zip(&vals[a..b])
                    .map(|(&i, &v)| v * y.get(i).copied().unwrap_or(0.0))
                    .sum();
            });
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        let m = self.csc.nrows().max(1) as f64;
        self.csc
            .col_iter()
            .map(|c| {
                let (s, s2) = c
                    .values()
                    .iter()
                    .fold((0.0, 0.0), |(s, s2), &v| (s + v, s2 + v * v));
                (s2 - s * s / m).max(0.0)
            })
            .collect()
    }
}
