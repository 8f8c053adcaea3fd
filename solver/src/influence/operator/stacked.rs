//! Stacked influence matrices. Several tools in one solve: `[R_1 / w_1, R_2 / w_2, ...]`, the
//! tools' matrices side by side over the same map points, each column block divided by the
//! tool's machining-time weight `w_k` (so that `rho sum(u)` with `u_k = w_k t_k` weighs tool `k`'s
//! time by `w_k`; `R_k t_k = (R_k / w_k) u_k`). Several scenarios of one path (the robust plan):
//! `[R_1; R_2; ...]`, one above the other over the same dwell points.

//!
//! [`StackedRows`] is the scenarios' stack without assembling it: matrix-free blocks (the
//! lattice operators with each scenario's kernel), each scaled by `a_s`,
//! `[a_1 R_1; ...; a_S R_S] t`, `R^T y = Σ a_s R_s^T y_s`, `R^T R t = Σ a_s² R_s^T R_s t`.

use super::matrix::InfluenceMatrix;
use super::{InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use nalgebra_sparse::CscMatrix;
use std::sync::{Arc, Mutex};

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

/// Matrix-free scenario blocks, shared by the stacks that scale them.
pub type ScenarioOperators = Arc<[Box<dyn InfluenceOperator>]>;

/// `[a_1 R_1; ...; a_S R_S]`: matrix-free blocks over the same map points and dwell points, one
/// above the other, block `s` scaled by `a_s` (module documentation). The blocks are shared, so
/// the same scenarios serve several scalings (the minimax rounds) without being built again.
pub struct StackedRows {
    blocks: ScenarioOperators,
    scales: Vec<f64>,
    /// Space for one block's `R_s^T y` (the products add the blocks' in a fixed order).
    column_scratch: Mutex<Vec<f64>>,
}

impl std::fmt::Debug for StackedRows {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StackedRows")
            .field("blocks", &self.blocks.len())
            .field("kind", &self.kind())
            .field("scales", &self.scales)
            .finish()
    }
}

impl StackedRows {
    /// The blocks `blocks` (at least one, all matrix-free and of one shape) scaled by `scales`
    /// (one per block, positive and finite).
    pub fn new(blocks: ScenarioOperators, scales: Vec<f64>) -> Result<Self> {
        let Some(first) = blocks.first() else {
            return Err(Error::invalid("robust", "no scenario"));
        };
        let shape = first.shape();
        if let Some(b) = blocks.iter().find(|b| b.shape() != shape) {
            return Err(Error::LengthMismatch {
                what: "scenario operator rows and columns",
                got: b.shape().0 * b.shape().1,
                expected: shape.0 * shape.1,
            });
        }
        if blocks
            .iter()
            .any(|b| b.downcast_ref::<InfluenceMatrix>().is_some())
        {
            return Err(Error::invalid(
                "robust",
                "the stacked operator takes matrix-free blocks (stack assembled ones with \
                 stack_rows)",
            ));
        }
        if scales.len() != blocks.len() {
            return Err(Error::LengthMismatch {
                what: "scenario scales",
                got: scales.len(),
                expected: blocks.len(),
            });
        }
        if let Some(a) = scales.iter().find(|a| !(a.is_finite() && **a > 0.0)) {
            return Err(Error::invalid(
                "scenario scale",
                format!("must be positive and finite, got {a}"),
            ));
        }
        Ok(Self {
            column_scratch: Mutex::new(vec![0.0; shape.1]),
            blocks,
            scales,
        })
    }

    /// Rows of one block (the map's rows).
    fn block_rows(&self) -> usize {
        self.blocks[0].shape().0
    }

    /// `out = Σ_s w_s P_s`, with `product(s, part)` writing block `s`'s `P_s` into `part`, the
    /// blocks added in order (results independent of the thread count).
    fn weighted_sum(
        &self,
        out: &mut [f64],
        mut product: impl FnMut(usize, &mut [f64]),
        weight: impl Fn(usize) -> f64,
    ) {
        let mut guard = self
            .column_scratch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let tmp = guard.as_mut_slice();
        product(0, out);
        let w0 = weight(0);
        out.iter_mut().for_each(|v| *v *= w0);
        for s in 1..self.blocks.len() {
            product(s, tmp);
            let w = weight(s);
            out.iter_mut()
                .zip(tmp.iter())
                .for_each(|(o, v)| *o += w * v);
        }
    }
}

impl InfluenceOperator for StackedRows {
    fn kind(&self) -> OperatorKind {
        self.blocks[0].kind()
    }

    fn shape(&self) -> (usize, usize) {
        let (m, n) = self.blocks[0].shape();
        (m * self.blocks.len(), n)
    }

    fn nnz(&self) -> usize {
        self.blocks.iter().map(|b| b.nnz()).sum()
    }

    fn empty_columns(&self) -> Vec<usize> {
        let mut empty = self.blocks[0].empty_columns();
        for b in self.blocks.iter().skip(1) {
            let other = b.empty_columns();
            empty.retain(|j| other.binary_search(j).is_ok());
        }
        empty
    }

    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

impl LinearOperator for StackedRows {
    fn nrows(&self) -> usize {
        self.shape().0
    }

    fn ncols(&self) -> usize {
        self.shape().1
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        let m = self.block_rows();
        for ((b, a), o) in self.blocks.iter().zip(&self.scales).zip(out.chunks_mut(m)) {
            b.products(None).apply(t, o);
            o.iter_mut().for_each(|v| *v *= a);
        }
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        let m = self.block_rows();
        self.weighted_sum(
            out,
            |s, o| {
                self.blocks[s]
                    .products(None)
                    .apply_transpose(&y[s * m..(s + 1) * m], o)
            },
            |s| self.scales[s],
        );
    }

    fn apply_normal(&self, t: &[f64], scratch: &mut [f64], out: &mut [f64]) {
        let m = self.block_rows();
        // Each block's own (fused) normal product, with its part of `scratch`.
        self.weighted_sum(
            out,
            |s, o| {
                self.blocks[s]
                    .products(None)
                    .apply_normal(t, &mut scratch[s * m..(s + 1) * m], o)
            },
            |s| self.scales[s] * self.scales[s],
        );
    }

    fn products_cheap_per_dwell_point(&self) -> bool {
        self.blocks[0]
            .products(None)
            .products_cheap_per_dwell_point()
    }

    /// `Σ a_s² ||R_s,j||² - (Σ a_s 1'R_s,j)² / (S m)`, from each block's centred norms `N_s` and
    /// column sums: `||R_s,j||² = N_s + (1'R_s,j)² / m`.
    fn centred_column_norms_sq(&self) -> Vec<f64> {
        let (m, n) = self.blocks[0].shape();
        let ones = vec![1.0; m];
        let mut total = vec![0.0; n];
        let mut sum = vec![0.0; n];
        let mut col_sum = vec![0.0; n];
        let mf = m as f64;
        for (b, a) in self.blocks.iter().zip(&self.scales) {
            let products = b.products(None);
            let norms = products.centred_column_norms_sq();
            products.apply_transpose(&ones, &mut col_sum);
            // An empty column's sum is exactly zero (a matrix-free transposed product leaves
            // rounding there, which would make its norm a tiny positive one and its Jacobi scale
            // enormous).
            for j in b.empty_columns() {
                col_sum[j] = 0.0;
            }
            for j in 0..n {
                total[j] += a * a * (norms[j] + col_sum[j] * col_sum[j] / mf);
                sum[j] += a * col_sum[j];
            }
        }
        let rows = mf * self.blocks.len() as f64;
        total
            .iter()
            .zip(&sum)
            .map(|(t, s)| (t - s * s / rows).max(0.0))
            .collect()
    }
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

    /// Relative tolerance of matrix-free products against the assembled ones (the same sums,
    /// FFT rounding).
    const STACK_TOL: f64 = 1e-10;

    #[test]
    fn scaled_matrix_free_rows_are_the_scaled_stacked_matrices() {
        // Two FFT blocks (different TIFs) over one lattice with dwell points off the map at the
        // corner (empty columns in both), scales 0.5 and 2: every product and the centred
        // norms are those of `[0.5 R_1; 2 R_2]` assembled.
        let (mx, my): (Vec<f64>, Vec<f64>) =
            (0..400).map(|k| ((k % 20) as f64, (k / 20) as f64)).unzip();
        let (dx, dy): (Vec<f64>, Vec<f64>) = (0..24 * 24)
            .map(|k| ((k % 24) as f64 - 2.0, (k / 24) as f64 - 2.0))
            .chain([(40.0, 40.0)])
            .unzip();
        let tifs = [
            GaussianTif::new(1.5, 2.0, 4.5).unwrap(),
            GaussianTif::new(1.0, 3.0, 3.0).unwrap(),
        ];
        let scales = [0.5, 2.0];
        let blocks: Vec<Box<dyn InfluenceOperator>> = tifs
            .iter()
            .map(|t| {
                Box::new(super::super::fft::FftOperator::new(&mx, &my, &dx, &dy, 1.0, t).unwrap())
                    as Box<dyn InfluenceOperator>
            })
            .collect();
        let op = StackedRows::new(Arc::from(blocks), scales.to_vec()).unwrap();
        // Block `s` assembled with its TIF's peak scaled by `a_s`: `a_s R_s` to rounding.
        let mats: Vec<InfluenceMatrix> = tifs
            .iter()
            .zip(scales)
            .map(|(t, a)| {
                let scaled =
                    GaussianTif::new(t.sigma_mm, a * t.peak_rate_nm_per_s, t.truncation_radius_mm)
                        .unwrap();
                InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &scaled, &Silent).unwrap()
            })
            .collect();
        let stacked = stack_rows(&mats).unwrap();
        let reference = stacked.products(None);
        let n = dx.len();
        assert_eq!(op.shape(), (800, n));
        let t: Vec<f64> = (0..n).map(|j| 1.0 + (0.3 * j as f64).sin()).collect();
        let y: Vec<f64> = (0..800).map(|i| (0.11 * i as f64).cos()).collect();
        let close = |a: &[f64], b: &[f64], what: &str| {
            let peak = a.iter().fold(0.0f64, |p, v| p.max(v.abs()));
            for (k, (u, v)) in a.iter().zip(b).enumerate() {
                assert!((u - v).abs() <= STACK_TOL * peak, "{what} {k}: {u} vs {v}");
            }
        };
        let (mut h, mut h_ref) = (vec![0.0; 800], vec![0.0; 800]);
        op.apply(&t, &mut h);
        reference.apply(&t, &mut h_ref);
        close(&h_ref, &h, "R t");
        let (mut g, mut g_ref) = (vec![0.0; n], vec![0.0; n]);
        op.apply_transpose(&y, &mut g);
        reference.apply_transpose(&y, &mut g_ref);
        close(&g_ref, &g, "R^T y");
        op.apply_normal(&t, &mut h, &mut g);
        reference.apply_normal(&t, &mut h_ref, &mut g_ref);
        close(&g_ref, &g, "R^T R t");
        let norms = op.centred_column_norms_sq();
        close(
            &reference.centred_column_norms_sq(),
            &norms,
            "centred norms",
        );
        // The far dwell point reaches nothing in either block: empty, with an exact zero norm.
        assert_eq!(op.empty_columns(), vec![n - 1]);
        assert_eq!(norms[n - 1], 0.0);
        assert!(StackedRows::new(Arc::clone(&op.blocks), vec![1.0]).is_err());
        assert!(StackedRows::new(Arc::clone(&op.blocks), vec![1.0, 0.0]).is_err());
    }
}
