//! The Gram matrix `G = R^T R` of the assembled influence matrix, for the normal products
//! `R^T R t` of the first-order solvers.
//!
//! A product `R^T (R t)` through `R` visits every non-zero of `R` twice; `G t` visits each
//! non-zero of `G` once. `G[j, k]` is non-zero only where the footprints of dwell points `j` and
//! `k` share a map point, so where `R` has many more rows than columns (a fine map under a
//! coarser dwell raster) `G` is several times smaller than `R` and every Hessian product is that
//! much cheaper. Forming `G` costs `W = sum_i k_i^2` multiply-adds (`k_i` the non-zeros of row
//! `i` of `R`), paid once; [`GramMatrix::worthwhile`] weighs it against the products a solve
//! takes at least.
//!
//! **Formation.** Column `j` of `G` is `R^T (R e_j)`: for every row `i` of column `j` (ascending),
//! every entry `(k, R[i, k])` of row `i` with `k >= j` adds `R[i, j] R[i, k]` to a dense
//! accumulator. Each entry `G[j, k]` is thus the sum over the shared rows in ascending row
//! order; the upper triangle is formed so and mirrored, so `G` is exactly symmetric, and columns
//! are formed independently, so it is bit-identical for any thread count. The column's entries
//! are read off the accumulator's span `j..=k_max` when that span is at most twice the
//! multiply-adds (neighbours numbered close, as along a raster: no per-entry bookkeeping in the
//! inner loop), else from the rows' sorted, deduplicated indices; entries that sum to exactly zero
//! are not stored.
//!
//! **Products.** `G t` is one dot product per row in a fixed order (outputs distributed over
//! threads): bit-identical for any thread count. It differs from `R^T (R t)` by rounding only.

use super::sparse::SparseOperator;
use super::LinearOperator;
use rayon::prelude::*;
use std::borrow::Cow;

/// Columns of `G` formed by one rayon task (each task holds one dense accumulator).
const COLUMNS_PER_TASK: usize = 64;
/// Minimum number of output entries of `G t` handed to one rayon task.
const MIN_TASK: usize = 128;
/// `G` is formed only when its pattern can hold at most this many times the non-zeros of `R`
/// (its memory then stays within what `R`'s row copy already takes).
const MAX_FILL_RATIO: f64 = 4.0;

/// `G = R^T R` in compressed rows (symmetric, both triangles stored).
#[derive(Debug, Clone)]
pub struct GramMatrix {
    n: usize,
    offsets: Vec<usize>,
    cols: Vec<u32>,
    vals: Vec<f64>,
}

impl GramMatrix {
    /// Whether forming `G` for `op` pays for a solve that takes at least `products` normal
    /// products: the `W = sum_i k_i^2` multiply-adds of the formation are at most the
    /// `2 nnz(R)` of each product times `products`, and `G`'s pattern is bounded by
    /// `MAX_FILL_RATIO nnz(R)` (bound per column: `min(n, sum over the column's rows of k_i)`).
    pub fn worthwhile(op: &SparseOperator<'_>, products: usize) -> bool {
        let (csc, csr) = (op.csc(), op.csr());
        let n = csc.ncols();
        let nnz = csc.nnz() as f64;
        if n == 0 || nnz == 0.0 || n > u32::MAX as usize {
            return false;
        }
        let row_len = |i: usize| (csr.row_offsets()[i + 1] - csr.row_offsets()[i]) as f64;
        let offsets = csc.col_offsets();
        let rows = csc.row_indices();
        let (mut work, mut fill) = (0.0, 0.0);
        for j in 0..n {
            let w: f64 = rows[offsets[j]..offsets[j + 1]]
                .iter()
                .map(|&i| row_len(i))
                .sum();
            work += w;
            fill += w.min(n as f64);
        }
        work <= 2.0 * nnz * products as f64 && fill <= MAX_FILL_RATIO * nnz
    }

    /// Forms `G = R^T R` from the operator's column and row storage (see the module
    /// documentation): the upper triangle column by column, then its mirror.
    pub fn new(op: &SparseOperator<'_>) -> Self {
        let (csc, csr) = (op.csc(), op.csr());
        let n = csc.ncols();
        let (c_off, c_rows, c_vals) = (csc.col_offsets(), csc.row_indices(), csc.values());
        let (r_off, r_cols, r_vals) = (csr.row_offsets(), csr.col_indices(), csr.values());
        let starts: Vec<usize> = (0..n).step_by(COLUMNS_PER_TASK).collect();
        // Each task: its columns' upper-triangle lengths, indices `k >= j` and values.
        type Block = (Vec<usize>, Vec<u32>, Vec<f64>);
        let blocks: Vec<Block> = starts
            .par_iter()
            .map_init(
                || (vec![0.0; n], Vec::new()),
                |(acc, touched): &mut (Vec<f64>, Vec<u32>), &start| {
                    let end = (start + COLUMNS_PER_TASK).min(n);
                    let (mut lens, mut cols, mut vals) = (Vec::new(), Vec::new(), Vec::new());
                    // The rows of column j from its entry at j on (their columns are sorted).
                    let upper = |j: usize, p: usize| {
                        let i = c_rows[p];
                        let row = r_off[i]..r_off[i + 1];
                        let from = row.start + r_cols[row.clone()].partition_point(|&k| k < j);
                        from..row.end
                    };
                    for j in start..end {
                        let (mut last, mut work) = (j, 0usize);
                        let column = c_off[j]..c_off[j + 1];
                        for (p, &a) in column.clone().zip(&c_vals[column]) {
                            let part = upper(j, p);
                            if let Some(&k) = r_cols[part.clone()].last() {
                                last = last.max(k);
                            }
                            work += part.len();
                            for (&k, &v) in r_cols[part.clone()].iter().zip(&r_vals[part]) {
                                acc[k] += a * v;
                            }
                        }
                        let before = cols.len();
                        if last - j < 2 * work {
                            // Read the span j..=last off the accumulator: at most twice the
                            // accumulation's cost (a path whose neighbours are numbered close).
                            for (k, a) in acc.iter_mut().enumerate().take(last + 1).skip(j) {
                                if *a != 0.0 {
                                    cols.push(k as u32);
                                    vals.push(*a);
                                    *a = 0.0;
                                }
                            }
                        } else {
                            // Neighbours numbered far apart: collect the indices the rows hold.
                            touched.clear();
                            for p in c_off[j]..c_off[j + 1] {
                                touched.extend(r_cols[upper(j, p)].iter().map(|&k| k as u32));
                            }
                            touched.sort_unstable();
                            touched.dedup();
                            for &k in touched.iter() {
                                let a = &mut acc[k as usize];
                                if *a != 0.0 {
                                    cols.push(k);
                                    vals.push(*a);
                                }
                                *a = 0.0;
                            }
                        }
                        lens.push(cols.len() - before);
                    }
                    (lens, cols, vals)
                },
            )
            .collect();
        // The upper triangle by rows.
        let mut up_off = Vec::with_capacity(n + 1);
        up_off.push(0);
        let total: usize = blocks.iter().map(|b| b.1.len()).sum();
        let (mut up_cols, mut up_vals) = (Vec::with_capacity(total), Vec::with_capacity(total));
        for (lens, c, v) in blocks {
            for len in lens {
                let last = *up_off.last().unwrap_or(&0);
                up_off.push(last + len);
            }
            up_cols.extend_from_slice(&c);
            up_vals.extend_from_slice(&v);
        }
        // Both triangles: row j holds the mirrored entries (k, j), k < j, then its upper row.
        let mut len = vec![0usize; n];
        for j in 0..n {
            len[j] += up_off[j + 1] - up_off[j];
            for &k in &up_cols[up_off[j]..up_off[j + 1]] {
                if k as usize != j {
                    len[k as usize] += 1;
                }
            }
        }
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0);
        for l in &len {
            let last = *offsets.last().unwrap_or(&0);
            offsets.push(last + l);
        }
        let nnz = *offsets.last().unwrap_or(&0);
        let (mut cols, mut vals) = (vec![0u32; nnz], vec![0.0; nnz]);
        let mut next: Vec<usize> = offsets[..n].to_vec();
        for j in 0..n {
            for p in up_off[j]..up_off[j + 1] {
                let k = up_cols[p] as usize;
                if k != j {
                    // Entry (k, j) of the lower triangle, appended to row k in ascending j.
                    cols[next[k]] = j as u32;
                    vals[next[k]] = up_vals[p];
                    next[k] += 1;
                }
            }
            // Row j's own upper part follows its mirrored entries (all at columns < j, and
            // every one of them is placed by the rows before j).
            let (a, b) = (up_off[j], up_off[j + 1]);
            let at = next[j];
            cols[at..at + (b - a)].copy_from_slice(&up_cols[a..b]);
            vals[at..at + (b - a)].copy_from_slice(&up_vals[a..b]);
            next[j] += b - a;
        }
        Self {
            n,
            offsets,
            cols,
            vals,
        }
    }

    /// Order `n` (the dwell points).
    pub fn n(&self) -> usize {
        self.n
    }

    /// Stored non-zeros (both triangles).
    pub fn nnz(&self) -> usize {
        self.vals.len()
    }

    /// `out = G t`.
    pub fn apply(&self, t: &[f64], out: &mut [f64]) {
        let (offsets, cols, vals) = (&self.offsets, &self.cols, &self.vals);
        out.par_iter_mut()
            .enumerate()
            .with_min_len(MIN_TASK)
            .for_each(|(j, o)| {
                let (a, b) = (offsets[j], offsets[j + 1]);
                *o = cols[a..b]
                    .iter()
                    .zip(&vals[a..b])
                    .map(|(&k, &v)| v * t.get(k as usize).copied().unwrap_or(0.0))
                    .sum();
            });
    }
}

/// The assembled `R` with its Gram matrix: `R t` and `R^T y` through `R`, `R^T R t` through
/// `G` (one pass over `G`'s non-zeros).
#[derive(Debug, Clone)]
pub struct GramOperator<'a> {
    op: SparseOperator<'a>,
    gram: Cow<'a, GramMatrix>,
}

impl<'a> GramOperator<'a> {
    /// Forms the Gram matrix of `op`.
    pub fn new(op: SparseOperator<'a>) -> Self {
        let gram = Cow::Owned(GramMatrix::new(&op));
        Self { op, gram }
    }

    /// `op` with its Gram matrix `gram`, formed once by the caller ([`GramMatrix::new`] of the
    /// same matrix).
    pub fn with_gram(op: SparseOperator<'a>, gram: &'a GramMatrix) -> Self {
        Self {
            op,
            gram: Cow::Borrowed(gram),
        }
    }

    /// The Gram matrix.
    pub fn gram(&self) -> &GramMatrix {
        &self.gram
    }
}

impl LinearOperator for GramOperator<'_> {
    fn nrows(&self) -> usize {
        self.op.nrows()
    }

    fn ncols(&self) -> usize {
        self.op.ncols()
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        self.op.apply(t, out);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        self.op.apply_transpose(y, out);
    }

    /// `out = G t`; `scratch` is not used.
    fn apply_normal(&self, t: &[f64], _scratch: &mut [f64], out: &mut [f64]) {
        self.gram.apply(t, out);
    }

    fn prefers_normal_products(&self) -> bool {
        true
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.op.centred_column_norms_sq()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra_sparse::{CooMatrix, CscMatrix};

    /// A 7 x 5 matrix with empty rows and columns and overlapping column patterns.
    fn matrix() -> CscMatrix<f64> {
        let entries = [
            (0, 0, 1.5),
            (1, 0, -2.0),
            (1, 1, 0.5),
            (2, 1, 3.0),
            (2, 3, 1.25),
            (4, 3, -0.75),
            (4, 4, 2.0),
            (5, 0, 0.25),
            (5, 4, 1.0),
            (6, 1, -1.0),
        ];
        let mut coo = CooMatrix::new(7, 5);
        for (i, j, v) in entries {
            coo.push(i, j, v);
        }
        CscMatrix::from(&coo)
    }

    /// Relative tolerance of a product through `G` against the same product through `R`
    /// (different rounding order of the same terms).
    const PRODUCT_RTOL: f64 = 1e-14;

    #[test]
    fn gram_matrix_is_r_transpose_r_entry_by_entry_and_symmetric() {
        let csc = matrix();
        let op = SparseOperator::new(&csc);
        let g = GramMatrix::new(&op);
        let dense = nalgebra::DMatrix::from(&csc);
        let reference = dense.transpose() * &dense;
        let n = csc.ncols();
        let mut stored = nalgebra::DMatrix::<f64>::zeros(n, n);
        for j in 0..n {
            for p in g.offsets[j]..g.offsets[j + 1] {
                stored[(j, g.cols[p] as usize)] = g.vals[p];
            }
        }
        for j in 0..n {
            for k in 0..n {
                assert!(
                    (stored[(j, k)] - reference[(j, k)]).abs() <= 1e-15,
                    "G[{j},{k}] = {} against {}",
                    stored[(j, k)],
                    reference[(j, k)]
                );
                assert_eq!(stored[(j, k)], stored[(k, j)]);
            }
        }
        // Column 2 of R is empty: so is row 2 of G; columns 0 and 3 share no row.
        assert_eq!(g.offsets[3] - g.offsets[2], 0);
        assert!(!g.cols[g.offsets[0]..g.offsets[1]].contains(&3));
    }

    /// Both ways of reading a column off the accumulator (its span, for neighbours numbered
    /// close; the rows' indices, for neighbours numbered far apart) give `R^T R`: a banded matrix
    /// whose columns are numbered in order, and the same with the columns shuffled so that a row's
    /// four entries lie far apart (column `j` then spans far more than twice its multiply-adds).
    #[test]
    fn gram_matrix_is_r_transpose_r_for_close_and_far_numbering() {
        let (m, n) = (400, 300);
        let shuffled: Vec<usize> = (0..n).map(|j| (j * 7) % n).collect();
        for perm in [(0..n).collect::<Vec<usize>>(), shuffled] {
            let mut coo = CooMatrix::new(m, n);
            for i in 0..m {
                for c in 0..4 {
                    let v = 1.0 + ((i * 5 + c * 3) % 11) as f64 * 0.25;
                    coo.push(i, perm[(i + c) % n], v);
                }
            }
            let csc = CscMatrix::from(&coo);
            let g = GramMatrix::new(&SparseOperator::new(&csc));
            let dense = nalgebra::DMatrix::from(&csc);
            let reference = dense.transpose() * &dense;
            let mut stored = nalgebra::DMatrix::<f64>::zeros(n, n);
            for j in 0..n {
                for p in g.offsets[j]..g.offsets[j + 1] {
                    stored[(j, g.cols[p] as usize)] = g.vals[p];
                }
            }
            let count = (0..n * n).filter(|&e| reference[e] != 0.0).count();
            assert_eq!(g.nnz(), count);
            for e in 0..n * n {
                assert!((stored[e] - reference[e]).abs() <= 1e-13 * reference[e].abs().max(1.0));
            }
        }
    }

    #[test]
    fn normal_product_through_gram_matches_r_then_r_transpose() {
        let csc = matrix();
        let op = SparseOperator::new(&csc);
        let t = [0.3, -1.7, 2.0, 0.9, 1.1];
        let (mut scratch, mut via_r, mut via_g) = (vec![0.0; 7], vec![0.0; 5], vec![0.0; 5]);
        op.apply_normal(&t, &mut scratch, &mut via_r);
        let gop = GramOperator::new(op);
        gop.apply_normal(&t, &mut scratch, &mut via_g);
        let scale = via_r.iter().fold(0.0_f64, |a, v| a.max(v.abs()));
        for (a, b) in via_r.iter().zip(&via_g) {
            assert!((a - b).abs() <= PRODUCT_RTOL * scale, "{a} against {b}");
        }
    }

    #[test]
    fn gram_is_identical_for_one_and_two_threads() {
        // Enough columns for several formation tasks.
        let (m, n) = (400, 300);
        let mut coo = CooMatrix::new(m, n);
        for j in 0..n {
            for d in 0..9 {
                let i = (j * 4 / 3 + d * 3) % m;
                coo.push(i, j, 1.0 + ((i * 31 + j * 17) % 23) as f64 / 7.0);
            }
        }
        let csc = CscMatrix::from(&coo);
        let run = |threads: usize| {
            crate::test_support::on_threads(threads, || {
                let g = GramMatrix::new(&SparseOperator::new(&csc));
                let t: Vec<f64> = (0..n).map(|j| (j as f64 * 0.37).sin()).collect();
                let mut out = vec![0.0; n];
                g.apply(&t, &mut out);
                (g.offsets.clone(), g.cols.clone(), g.vals.clone(), out)
            })
        };
        assert_eq!(run(1), run(2));
    }

    #[test]
    fn worthwhile_weighs_formation_against_products() {
        let csc = matrix();
        let op = SparseOperator::new(&csc);
        // W = sum_i k_i^2 = 1 + 4 + 4 + 0 + 4 + 4 + 1 = 18 against 2 nnz = 20 per product.
        assert!(GramMatrix::worthwhile(&op, 1));
        // A dense row makes the formation cost its square.
        let mut coo = CooMatrix::new(2, 40);
        for j in 0..40 {
            coo.push(0, j, 1.0);
        }
        coo.push(1, 0, 1.0);
        let dense_row = CscMatrix::from(&coo);
        let op = SparseOperator::new(&dense_row);
        // W = 1601 > 2 * 41 * 10; and G's pattern (1,600 entries) is far above 4 nnz(R).
        assert!(!GramMatrix::worthwhile(&op, 10));
    }
}
