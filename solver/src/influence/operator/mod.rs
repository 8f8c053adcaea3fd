//! How `R` is held and applied. Two traits, and their implementations in this folder:
//! - [`InfluenceOperator`]: `R` as a dwell problem holds it, whatever its form: its kind, shape,
//!   non-zeros, empty columns, removal `R t`, and the operator ready for products. A caller that
//!   needs one concrete form (the QP needs the assembled matrix) asks for it by type
//!   (`<dyn InfluenceOperator>::downcast_ref`);
//! - [`LinearOperator`]: the products `R t`, `R^T y`, `R^T R t` the first-order solvers take.
//!
//! The implementations:
//! - [`matrix`]: the assembled sparse matrix ([`sparse`]: its products by columns and rows;
//!   [`gram`]: the Gram matrix `R^T R` for the solvers' normal products);
//! - [`fft`]: matrix-free for map and dwell points on one lattice (FFT convolution); `complement`:
//!   its normal product through the kernel's autocorrelation on the dwell lattice, less the band
//!   of cells within reach that the map does not cover once; [`lattice`]: their lattice plumbing;
//! - [`spread`]: dwell points off the map lattice, spread bilinearly onto an oversampled lattice,
//!   then FFT convolution;
//! - [`nufft`]: dwell points anywhere with a controlled error (exponential-of-semicircle spreading
//!   onto a fine lattice, deconvolved FFT convolution);
//! - [`stencil`]: exact and matrix-free for dwell points at few distinct positions within a map
//!   cell (one tabulated stencil per position);
//! - [`expansion`]: dwell points anywhere with columns of their own shape (the swept model on a
//!   spiral or random path, a TIF cut at a radius): four spreading products, the TIF and its
//!   swept kernels' second-order terms in the stretch's direction, and an exact sparse correction
//!   where the expansion is poor (the cut circle, odd stretches), its error summed over every entry;
//! - [`stacked`]: several tools' operators side by side (one solve over all their dwell times).
//!
//! Every product is computed entry by entry in a fixed order (one dot product per output entry,
//! outputs distributed over threads), so results are bit-identical for any thread count.

mod complement;
pub mod expansion;
pub mod fft;
pub mod gram;
pub(crate) mod lattice;
pub mod matrix;
pub mod nufft;
pub mod sparse;
pub mod spread;
pub mod stacked;
pub mod stencil;

use crate::error::{Error, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How `R` is held: assembled, matrix-free on the map's lattice, or spread onto it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum OperatorKind {
    /// The assembled sparse matrix.
    #[default]
    Sparse,
    /// The matrix-free FFT convolution.
    Fft,
    /// Dwell points spread onto the map lattice, then FFT convolution.
    FftSpread,
    /// Matrix-free, one tabulated stencil per dwell position within a map cell (exact).
    Stencil,
    /// Dwell points spread by the exponential-of-semicircle kernel onto a fine lattice, then a
    /// deconvolved FFT convolution (non-uniform FFT; error measured against the exact `R`).
    Nufft,
    /// The TIF and its direction expansion spread from each stretch's centroid, with an exact
    /// sparse correction where the expansion is poor (error summed over every entry).
    Expansion,
}

/// The influence operator `R` (m x n, nm/s) as a dwell problem holds it. The assembled matrix,
/// the FFT operator and the spreading operator implement it; a problem holds one behind an
/// `Arc<dyn InfluenceOperator>` and asks it; only what needs one form (the QP needs the entries of
/// the assembled matrix) asks for that type ([`downcast_ref`](#method.downcast_ref)).
pub trait InfluenceOperator: std::fmt::Debug + Send + Sync + std::any::Any {
    /// How `R` is held.
    fn kind(&self) -> OperatorKind;

    /// `(m, n)`: measurement points (rows) and dwell points (columns).
    fn shape(&self) -> (usize, usize);

    /// Non-zero entries of `R` (stored, or implicit in a matrix-free operator: the number the
    /// assembled matrix would store).
    fn nnz(&self) -> usize;

    /// Dwell points whose column of `R` is empty (no measurement point in the tool's reach).
    fn empty_columns(&self) -> Vec<usize>;

    /// The operator ready for products. `normal_products`: `Some(k)` when the caller takes at
    /// least `k` normal products `R^T R t` and a formed Gram matrix may serve them (the
    /// assembled matrix forms one where [`gram::GramMatrix::worthwhile`] says it pays); `None`
    /// for products through `R` alone. The assembled matrix builds its row copy here, per call,
    /// so a caller that needs no product (the QP) never holds one.
    fn products(&self, normal_products: Option<usize>) -> Products<'_>;

    /// Removal `h = R t`, nm, for dwell times `t` (s); `t.len() == n`.
    fn removal_nm(&self, dwell_s: &[f64]) -> Result<Vec<f64>> {
        let (m, n) = self.shape();
        if dwell_s.len() != n {
            return Err(Error::LengthMismatch {
                what: "dwell_s",
                got: dwell_s.len(),
                expected: n,
            });
        }
        let mut h = vec![0.0; m];
        self.products(None).apply(dwell_s, &mut h);
        Ok(h)
    }
}

impl dyn InfluenceOperator {
    /// The operator as its concrete type `T`, where it is one (the QP asks for the assembled
    /// [`matrix::InfluenceMatrix`]); `None` otherwise.
    pub fn downcast_ref<T: InfluenceOperator>(&self) -> Option<&T> {
        (self as &dyn std::any::Any).downcast_ref::<T>()
    }
}

/// An [`InfluenceOperator`] ready for products ([`InfluenceOperator::products`]): derefs to the
/// [`LinearOperator`] the solvers use.
pub enum Products<'a> {
    /// A matrix-free operator, used as it is.
    Direct(&'a dyn LinearOperator),
    /// An operator built for the products (the assembled matrix with its row copy, and its Gram
    /// matrix where normal products go through `G`).
    Built(Box<dyn LinearOperator + 'a>),
}

impl<'a> std::ops::Deref for Products<'a> {
    type Target = dyn LinearOperator + 'a;

    fn deref(&self) -> &Self::Target {
        match self {
            Products::Direct(op) => *op,
            Products::Built(op) => op.as_ref(),
        }
    }
}

/// A linear map `R` from `n` dwell times (s) to `m` removals (nm), with its transpose.
pub trait LinearOperator: Sync {
    /// Number of measurement points `m` (rows).
    fn nrows(&self) -> usize;
    /// Number of dwell points `n` (columns).
    fn ncols(&self) -> usize;
    /// `out = R t`; `t.len() == n`, `out.len() == m`.
    fn apply(&self, t: &[f64], out: &mut [f64]);
    /// `out = R^T y`; `y.len() == m`, `out.len() == n`.
    fn apply_transpose(&self, y: &[f64], out: &mut [f64]);
    /// `out = R^T R t`; `scratch.len() == m` (space for `R t`, which an operator may bypass).
    fn apply_normal(&self, t: &[f64], scratch: &mut [f64], out: &mut [f64]) {
        self.apply(t, scratch);
        self.apply_transpose(scratch, out);
    }
    /// Whether [`LinearOperator::apply_normal`] is much cheaper than `R t` and `R^T y` (a
    /// formed Gram matrix): the first-order solvers' power iteration then takes Hessian
    /// products through it alone. Objective, residual and certificate always go through `R`:
    /// the quadratic form `t'R^T R t - 2 t'R^T z + z'z` loses the relative accuracy of a small
    /// residual to cancellation.
    fn prefers_normal_products(&self) -> bool {
        false
    }
    /// Whether a product costs about as little per dwell point as a few passes over a vector of
    /// dwell times (tens of nanoseconds: FFT convolutions), rather than far more (an assembled
    /// matrix's or the phase stencils' hundreds of multiply-adds a column). Iterations that keep
    /// more vectors then lose to their own passes; the projected L-BFGS keeps fewer pairs.
    fn products_cheap_per_dwell_point(&self) -> bool {
        false
    }
    /// Squared norms of the centred columns, `||R_j||^2 - (1' R_j)^2 / m` (the diagonal of
    /// `R^T P R` with `P = I - 11'/m`), used for the Jacobi scaling.
    fn centred_column_norms_sq(&self) -> Vec<f64>;
}

/// One column's sums over the map points, as a matrix-free operator accumulates them entry by
/// entry: the sum and sum of squares of its entries and its non-zeros (an entry held by `k` map
/// points, several measurements in one lattice cell, counts `k` times).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct ColumnSums {
    sum: f64,
    sum_sq: f64,
    nnz: usize,
}

impl ColumnSums {
    /// Adds entry `v` held by `count` map points (a zero entry or count adds nothing).
    #[inline]
    pub(crate) fn add(&mut self, count: u32, v: f64) {
        if v != 0.0 && count > 0 {
            let c = f64::from(count);
            self.sum += c * v;
            self.sum_sq += c * v * v;
            self.nnz += count as usize;
        }
    }
}

/// A matrix-free operator's column whose norm is below this fraction of the largest column's is
/// held as empty. Its products carry rounding relative to the largest entries (about 1e-13 for
/// the FFT), so such a column's share of `R^T y` is rounding, and the Jacobi scaling
/// (`1 / ||P R_j||`) would blow that rounding up past every real gradient: a hard-cut grid TIF
/// reaching a map point only through a bilinear weight of 1e-13 at its cut made a column of
/// norm 1e-26 whose scaled noise passed the start as converged. A column this weak removes
/// nothing a plan can use.
pub(crate) const UNRESOLVED_COLUMN_REL: f64 = 1e-10;

/// The column sums of a matrix-free operator over its `m` map points: its non-zeros, empty
/// columns and the centred column norms of the Jacobi scaling, read the same way by every
/// matrix-free operator.
#[derive(Debug, Clone, Default)]
pub(crate) struct ColumnStats {
    columns: Vec<ColumnSums>,
    m: usize,
}

impl ColumnStats {
    /// The statistics of `columns` over `m` map points.
    pub(crate) fn new(m: usize, columns: Vec<ColumnSums>) -> Self {
        Self { columns, m }
    }

    /// Non-zero entries of the implicit matrix (the number the sparse operator would store).
    pub(crate) fn nnz(&self) -> usize {
        self.columns.iter().map(|c| c.nnz).sum()
    }

    /// Columns with no non-zero entry (dwell points with no map point in the tool's reach), or
    /// whose norm is below [`UNRESOLVED_COLUMN_REL`] of the largest column's: the matrix-free
    /// products cannot resolve them, and they are held as empty.
    pub(crate) fn empty_columns(&self) -> Vec<usize> {
        let floor = self.resolved_floor_sq();
        self.columns
            .iter()
            .enumerate()
            .filter(|(_, c)| c.nnz == 0 || c.sum_sq < floor)
            .map(|(j, _)| j)
            .collect()
    }

    /// `||R_j||^2 - (1' R_j)^2 / m` for every column (see
    /// [`LinearOperator::centred_column_norms_sq`]); zero for a column held as empty
    /// ([`ColumnStats::empty_columns`]).
    pub(crate) fn centred_norms_sq(&self) -> Vec<f64> {
        let m = self.m.max(1) as f64;
        let floor = self.resolved_floor_sq();
        self.columns
            .iter()
            .map(|c| {
                if c.sum_sq < floor {
                    0.0
                } else {
                    (c.sum_sq - c.sum * c.sum / m).max(0.0)
                }
            })
            .collect()
    }

    /// The squared norm below which a column is not resolved by the products
    /// ([`UNRESOLVED_COLUMN_REL`] of the largest column's norm, squared).
    fn resolved_floor_sq(&self) -> f64 {
        let largest = self.columns.iter().map(|c| c.sum_sq).fold(0.0, f64::max);
        largest * UNRESOLVED_COLUMN_REL * UNRESOLVED_COLUMN_REL
    }
}

/// Length of the fixed chunks of [`fixed_sum`]: the chunking does not depend on the thread count.
pub(crate) const CHUNK: usize = 4096;

/// Sum of `f(k)` for `k` in `0..len`, in fixed chunks summed in parallel and then in order:
/// bit-identical for any thread count. `partials` is reused scratch space.
pub(crate) fn fixed_sum<F>(len: usize, partials: &mut Vec<f64>, f: F) -> f64
where
    F: Fn(usize) -> f64 + Sync,
{
    let chunks = len.div_ceil(CHUNK);
    (0..chunks)
        .into_par_iter()
        .map(|c| {
            let end = ((c + 1) * CHUNK).min(len);
            (c * CHUNK..end).map(&f).sum::<f64>()
        })
        .collect_into_vec(partials);
    partials.iter().sum()
}

/// Sets `out[j]` and sums `term` over `j`, from `(out[j], term) = f(j)`, in the fixed chunks of
/// [`fixed_sum`] (one pass; bit-identical for any thread count). `partials` is reused scratch.
pub(crate) fn fill_and_sum<F>(out: &mut [f64], partials: &mut Vec<f64>, f: F) -> f64
where
    F: Fn(usize) -> (f64, f64) + Sync,
{
    out.par_chunks_mut(CHUNK)
        .enumerate()
        .map(|(c, chunk)| {
            let mut acc = 0.0;
            for (k, o) in chunk.iter_mut().enumerate() {
                let (value, term) = f(c * CHUNK + k);
                *o = value;
                acc += term;
            }
            acc
        })
        .collect_into_vec(partials);
    partials.iter().sum()
}

/// `sum_j a[j] b[j]` with four running sums, combined in a fixed order (so bit-identical for
/// any thread count; the independent sums let the additions overlap).
#[inline(always)]
pub(crate) fn lane_dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

#[cfg(test)]
mod tests {
    use super::lane_dot;

    /// `sum_{j<n} j (j + 1) = (n - 1) n (n + 1) / 3`, exact in `f64` at these sizes, for every
    /// length modulo the four running sums.
    #[test]
    fn lane_dot_is_the_inner_product_for_every_remainder() {
        for n in 0..=13usize {
            let a: Vec<f64> = (0..n).map(|j| j as f64).collect();
            let b: Vec<f64> = (0..n).map(|j| (j + 1) as f64).collect();
            let expected = if n == 0 {
                0.0
            } else {
                ((n - 1) * n * (n + 1)) as f64 / 3.0
            };
            assert_eq!(lane_dot(&a, &b), expected, "length {n}");
        }
    }
}
