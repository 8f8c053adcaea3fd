//! The swept model on the lattice operators, exact at every dwell point.
//!
//! The FFT, stencil, NUFFT and spreading operators apply one shift-invariant kernel: the TIF
//! averaged along the dominant stretch ([`super::swept::Stretches::dominant`], on a serpentine
//! raster the interior stretch along the lines). The dwell points whose stretch differs (the
//! row ends' L-shaped stretches, the path's ends) have columns `R_j = R~_j + D_j` with `D_j` the
//! difference of their exact swept column and the kernel's. With `E` the `n x k` selection of
//! those `k` columns,
//!
//! `R = R~ + D E^T`, `R^T y = R~^T y + E D^T y`,
//! `R^T R = R~^T R~ + C E^T + E C^T + E (D^T D) E^T`, `C = R~^T D` (`n x k`),
//!
//! so the normal product keeps the inner operator's own (fused) one and adds sparse terms, or,
//! where those would cost more than fusing saves ([`UNFUSED_ENTRIES_PER_DWELL_POINT`]), is
//! `R^T (R t)` through the two corrected products. `D`
//! is assembled directly (`k` columns over the map points in reach), `C` by transposed products
//! of the inner operator at set-up, one per batch of corrected points far enough apart that
//! their columns of `C` do not meet, `D^T D` over the pairs of columns whose reaches meet. The centred column norms (Jacobi scaling) of the corrected columns follow from the
//! inner operator's: `||R~_j + D_j||² - (1'R~_j + 1'D_j)² / m` with `||R~_j||² = N~_j + s_j² / m`,
//! `s = R~^T 1`, and `R~_j' D_j = C[j, k]`.

use crate::error::{Error, Result};
use crate::influence::model::swept::Stretches;
use crate::influence::operator::matrix::InfluenceMatrix;
use crate::influence::operator::{InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::tif::InfluenceFunction;
use rayon::prelude::*;
use std::sync::Mutex;

/// Fewest outputs of the sparse normal-product terms per rayon task.
const SPARSE_TASK: usize = 1024;

/// Entries of `C = R~^T D` below this share of the column's largest are the inner operator's
/// rounding (FFT products leave about 1e-16 of the peak everywhere) and are not kept.
const C_DROP_TOLERANCE: f64 = 1e-14;
/// The reach within which a corrected column meets another column, as a multiple of the sum of
/// their supports' radii (a margin for the spreading operators' kernels, which reach a few fine
/// cells beyond the TIF's support).
const SUPPORT_MARGIN: f64 = 1.1;

/// The normal product is the inner operator's fused one plus the sparse terms `C` and `D^T D`
/// until those exceed the unfused passes' (`D E^T t`, `D^T y`) by this many entries per dwell
/// point; beyond it, `R^T (R t)` through the corrected `R` and `R^T`. Unfusing an FFT product
/// costs 12-28% of a product of 30-50 ns per dwell point (`docs/benchmarks.md`), a sparse entry
/// about 2 ns: on the generated 2e4 raster (6.8 entries per point) unfused is 22% faster a
/// product, on the 2e5 one (2.0) 25% slower. Where the row ends lie off the map, `D` holds
/// little and `C` (its columns' every dwell point in reach) far more.
const UNFUSED_ENTRIES_PER_DWELL_POINT: f64 = 4.0;

/// A lattice operator with the swept model's exact columns for the dwell points whose stretch
/// is not the kernel's (module documentation).
pub struct SweptCorrected {
    inner: Box<dyn InfluenceOperator>,
    /// The corrected columns `j` (ascending).
    columns: Vec<usize>,
    /// `D`: m x k, column `k` the exact swept column of `columns[k]` less the kernel's.
    d: InfluenceMatrix,
    /// `C = R~^T D`: for each corrected column, the dwell points `j` and values kept.
    c: Vec<Vec<(usize, f64)>>,
    /// `D^T D` over the pairs `(a, b)` whose reaches meet (both orders listed).
    dtd: Vec<Vec<(usize, f64)>>,
    /// `C` by rows: the dwell points `r` with an entry (ascending), where each one's entries
    /// start, and the entries `(k, C[r, k])`, ascending in `k` within a row.
    c_by_row: (Vec<usize>, Vec<usize>, Vec<(usize, f64)>),
    /// Space for the sparse terms' sums: one per row of `C`, then one per corrected column.
    sparse_sums: Mutex<Vec<f64>>,
    /// Centred squared column norms of `R~ + D E^T`.
    norms: Vec<f64>,
    /// Normal products as `R^T (R t)` through the corrected `R` and `R^T` (rather than the inner
    /// operator's fused one plus `C` and `D^T D`), where `C` holds far more than `D`
    /// ([`UNFUSED_ENTRIES_PER_DWELL_POINT`]).
    unfused: bool,
}

impl std::fmt::Debug for SweptCorrected {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SweptCorrected")
            .field("inner", &self.inner)
            .field("corrected_columns", &self.columns.len())
            .finish()
    }
}

impl SweptCorrected {
    /// `inner` (a lattice operator over the rows `(x, y)` and the dwell points of `path`, with
    /// the kernel `kernel`: `tif` swept along the dominant stretch) corrected at the dwell points
    /// `columns` whose stretch in `stretches` differs from the dominant one
    /// ([`Stretches::outside_dominant`], ascending). `Err(inner)`, the operator unchanged, when
    /// there are none (nothing to correct).
    #[allow(clippy::too_many_arguments)]
    pub fn new<T: InfluenceFunction + ?Sized, K: InfluenceFunction + ?Sized>(
        inner: Box<dyn InfluenceOperator>,
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        path: &DwellPath,
        stretches: &Stretches,
        columns: Vec<usize>,
        tif: &T,
        kernel: &K,
        observer: &dyn Observer,
    ) -> Result<std::result::Result<Self, Box<dyn InfluenceOperator>>> {
        Self::build(
            inner,
            (map_x_mm, map_y_mm),
            path,
            stretches,
            columns,
            (tif, kernel),
            UNFUSED_ENTRIES_PER_DWELL_POINT,
            observer,
        )
    }

    /// [`SweptCorrected::new`] with the fused normal product kept while its sparse terms exceed
    /// the unfused passes' by at most `unfused_above` entries per dwell point.
    #[allow(clippy::too_many_arguments)]
    fn build<T: InfluenceFunction + ?Sized, K: InfluenceFunction + ?Sized>(
        inner: Box<dyn InfluenceOperator>,
        (map_x_mm, map_y_mm): (&[f64], &[f64]),
        path: &DwellPath,
        stretches: &Stretches,
        columns: Vec<usize>,
        (tif, kernel): (&T, &K),
        unfused_above: f64,
        observer: &dyn Observer,
    ) -> Result<std::result::Result<Self, Box<dyn InfluenceOperator>>> {
        let (m, n) = inner.shape();
        if stretches.len() != n || path.len() != n || map_x_mm.len() != m {
            return Err(Error::LengthMismatch {
                what: "swept correction: stretches, path and operator",
                got: stretches.len(),
                expected: n,
            });
        }
        if columns.windows(2).any(|w| w[0] >= w[1]) || columns.last().is_some_and(|&j| j >= n) {
            return Err(Error::invalid(
                "swept correction columns",
                format!("must be ascending dwell indices below {n}"),
            ));
        }
        if columns.is_empty() {
            return Ok(Err(inner));
        }
        let (cx, cy): (Vec<f64>, Vec<f64>) = columns
            .iter()
            .map(|&j| (path.x_mm()[j], path.y_mm()[j]))
            .unzip();
        let radius = stretches.reach_of(tif).max(kernel.support_radius_mm());
        let d = InfluenceMatrix::assemble_with(
            map_x_mm,
            map_y_mm,
            &cx,
            &cy,
            radius,
            |k, _i, dx, dy| {
                let exact = stretches.rate_nm_per_s(columns[k], tif, dx, dy);
                exact - kernel.rate_nm_per_s(dx, dy)
            },
            observer,
        )?;
        let k_count = columns.len();
        let products = inner.products(None);
        // C = R~^T D. Column k is non-zero only at the dwell points within `reach` of point k
        // (where `R~_j` and `D_k` can meet), so corrected points more than `2 reach` apart share
        // one transposed product: batches formed greedily, their members' parts told apart by
        // distance.
        let reach = SUPPORT_MARGIN * (kernel.support_radius_mm() + radius);
        let cell = reach;
        let cell_of = |x: f64, y: f64| ((x / cell).floor() as i64, (y / cell).floor() as i64);
        let mut grid: std::collections::HashMap<(i64, i64), Vec<usize>> =
            std::collections::HashMap::new();
        for (j, (&x, &y)) in path.x_mm().iter().zip(path.y_mm()).enumerate() {
            grid.entry(cell_of(x, y)).or_default().push(j);
        }
        let near = |k: usize| -> Vec<usize> {
            let (px, py) = (cx[k], cy[k]);
            let (ci, cj) = cell_of(px, py);
            let mut out = Vec::new();
            for a in -1..=1 {
                for b in -1..=1 {
                    if let Some(js) = grid.get(&(ci + a, cj + b)) {
                        out.extend(js.iter().copied().filter(|&j| {
                            let (dx, dy) = (path.x_mm()[j] - px, path.y_mm()[j] - py);
                            dx * dx + dy * dy <= reach * reach
                        }));
                    }
                }
            }
            out.sort_unstable();
            out
        };
        let apart2 = (2.0 * reach) * (2.0 * reach);
        let mut batches: Vec<Vec<usize>> = Vec::new();
        for k in 0..k_count {
            let fits = |batch: &Vec<usize>| {
                batch.iter().all(|&o| {
                    let (dx, dy) = (cx[o] - cx[k], cy[o] - cy[k]);
                    dx * dx + dy * dy > apart2
                })
            };
            match batches.iter_mut().find(|b| fits(b)) {
                Some(b) => b.push(k),
                None => batches.push(vec![k]),
            }
        }
        let mut dense = vec![0.0; m];
        let mut out = vec![0.0; n];
        let mut c = vec![Vec::new(); k_count];
        let mut d_sums = Vec::with_capacity(k_count);
        let mut d_norms = Vec::with_capacity(k_count);
        for k in 0..k_count {
            let col = d.csc().col(k);
            d_sums.push(col.values().iter().sum::<f64>());
            d_norms.push(col.values().iter().map(|v| v * v).sum::<f64>());
        }
        for batch in &batches {
            dense.iter_mut().for_each(|v| *v = 0.0);
            for &k in batch {
                let col = d.csc().col(k);
                for (&i, &v) in col.row_indices().iter().zip(col.values()) {
                    dense[i] += v;
                }
            }
            products.apply_transpose(&dense, &mut out);
            for &k in batch {
                let js = near(k);
                let peak = js.iter().fold(0.0f64, |a, &j| a.max(out[j].abs()));
                c[k] = js
                    .into_iter()
                    .filter(|&j| out[j].abs() > C_DROP_TOLERANCE * peak)
                    .map(|j| (j, out[j]))
                    .collect();
            }
        }
        // D^T D over the pairs whose reaches meet.
        let reach2 = (2.0 * radius) * (2.0 * radius);
        let mut dtd = vec![Vec::new(); k_count];
        dense.iter_mut().for_each(|v| *v = 0.0);
        for a in 0..k_count {
            let ca = d.csc().col(a);
            for (&i, &v) in ca.row_indices().iter().zip(ca.values()) {
                dense[i] = v;
            }
            for b in 0..k_count {
                let (dx, dy) = (cx[a] - cx[b], cy[a] - cy[b]);
                if dx * dx + dy * dy > reach2 {
                    continue;
                }
                let cb = d.csc().col(b);
                let v: f64 = cb
                    .row_indices()
                    .iter()
                    .zip(cb.values())
                    .map(|(&i, &w)| dense[i] * w)
                    .sum();
                if v != 0.0 {
                    dtd[a].push((b, v));
                }
            }
            for &i in ca.row_indices() {
                dense[i] = 0.0;
            }
        }
        // Centred norms of the corrected columns from the inner operator's.
        let mut norms = products.centred_column_norms_sq();
        let ones = vec![1.0; m];
        let mut s = vec![0.0; n];
        products.apply_transpose(&ones, &mut s);
        let mf = m as f64;
        for (k, &j) in columns.iter().enumerate() {
            if d.csc().col(k).nnz() == 0 {
                // The column is the inner operator's: its norm stays as it is (an empty column's
                // exact zero too, which the transposed products' rounding would otherwise make
                // a tiny positive norm and an enormous Jacobi scale).
                continue;
            }
            let cross = c[k]
                .iter()
                .find(|(jj, _)| *jj == j)
                .map_or(0.0, |&(_, v)| v);
            let plain = norms[j] + s[j] * s[j] / mf;
            let sum = s[j] + d_sums[k];
            norms[j] = (plain + 2.0 * cross + d_norms[k] - sum * sum / mf).max(0.0);
        }
        drop(products);
        let c_entries: usize = c.iter().map(Vec::len).sum();
        let dtd_entries: usize = dtd.iter().map(Vec::len).sum();
        let unfused =
            (2 * c_entries + dtd_entries) as f64 - (2 * d.nnz()) as f64 > unfused_above * n as f64;
        let (c, dtd) = if unfused {
            (Vec::new(), Vec::new())
        } else {
            (c, dtd)
        };
        let c_by_row = transpose_lists(&c, n);
        let sums = c_by_row.0.len() + columns.len();
        Ok(Ok(Self {
            inner,
            columns,
            d,
            c,
            dtd,
            c_by_row,
            sparse_sums: Mutex::new(vec![0.0; sums]),
            norms,
            unfused,
        }))
    }
    /// The dwell points whose columns are corrected.
    pub fn corrected_columns(&self) -> usize {
        self.columns.len()
    }
}

impl InfluenceOperator for SweptCorrected {
    fn kind(&self) -> OperatorKind {
        self.inner.kind()
    }

    fn shape(&self) -> (usize, usize) {
        self.inner.shape()
    }

    fn nnz(&self) -> usize {
        self.inner.nnz()
    }

    fn empty_columns(&self) -> Vec<usize> {
        let mut empty = self.inner.empty_columns();
        empty.retain(|j| match self.columns.binary_search(j) {
            Ok(k) => self.d.csc().col(k).nnz() == 0,
            Err(_) => true,
        });
        empty
    }

    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

impl LinearOperator for SweptCorrected {
    fn nrows(&self) -> usize {
        self.inner.shape().0
    }

    fn ncols(&self) -> usize {
        self.inner.shape().1
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        self.inner.products(None).apply(t, out);
        for (k, &j) in self.columns.iter().enumerate() {
            let tj = t[j];
            if tj != 0.0 {
                let col = self.d.csc().col(k);
                for (&i, &v) in col.row_indices().iter().zip(col.values()) {
                    out[i] += v * tj;
                }
            }
        }
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        self.inner.products(None).apply_transpose(y, out);
        for (k, &j) in self.columns.iter().enumerate() {
            let col = self.d.csc().col(k);
            out[j] += col
                .row_indices()
                .iter()
                .zip(col.values())
                .map(|(&i, &v)| v * y[i])
                .sum::<f64>();
        }
    }

    fn apply_normal(&self, t: &[f64], scratch: &mut [f64], out: &mut [f64]) {
        if self.unfused {
            self.apply(t, scratch);
            self.apply_transpose(scratch, out);
            return;
        }
        // The sparse terms' sums, each in ascending index order (the same for any thread
        // count): (C E^T t)_r for each row r of C, then (C^T t + D^T D E^T t)_k for each
        // corrected column k; computed beside the inner operator's product and added to it.
        let mut guard = self
            .sparse_sums
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let (row_sums, column_sums) = guard.split_at_mut(self.c_by_row.0.len());
        let (rows, starts, entries) = &self.c_by_row;
        let sparse = || {
            row_sums
                .par_iter_mut()
                .with_min_len(SPARSE_TASK)
                .enumerate()
                .for_each(|(row, sum)| {
                    *sum = entries[starts[row]..starts[row + 1]]
                        .iter()
                        .map(|&(k, v)| v * t[self.columns[k]])
                        .sum();
                });
            column_sums
                .par_iter_mut()
                .with_min_len(SPARSE_TASK)
                .enumerate()
                .for_each(|(k, sum)| {
                    let ct: f64 = self.c[k].iter().map(|&(r, v)| v * t[r]).sum();
                    let dd: f64 = self.dtd[k]
                        .iter()
                        .map(|&(b, v)| v * t[self.columns[b]])
                        .sum();
                    *sum = ct + dd;
                });
        };
        rayon::join(
            || self.inner.products(None).apply_normal(t, scratch, out),
            sparse,
        );
        for (&r, v) in rows.iter().zip(row_sums.iter()) {
            out[r] += v;
        }
        for (&j, v) in self.columns.iter().zip(column_sums.iter()) {
            out[j] += v;
        }
    }

    fn products_cheap_per_dwell_point(&self) -> bool {
        self.inner.products(None).products_cheap_per_dwell_point()
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.norms.clone()
    }
}

/// Lists `lists[k] = [(r, v), ...]` (each `r < n`) by `r`: the rows `r` with an entry,
/// ascending, the start of each row's entries (one more than the rows), and the entries
/// `(k, v)`, ascending in `k` within a row.
fn transpose_lists(
    lists: &[Vec<(usize, f64)>],
    n: usize,
) -> (Vec<usize>, Vec<usize>, Vec<(usize, f64)>) {
    let mut count = vec![0usize; n];
    for list in lists {
        for &(r, _) in list {
            count[r] += 1;
        }
    }
    let rows: Vec<usize> = (0..n).filter(|&r| count[r] > 0).collect();
    let mut starts = Vec::with_capacity(rows.len() + 1);
    let mut next = vec![0usize; n];
    let mut total = 0;
    for &r in &rows {
        starts.push(total);
        next[r] = total;
        total += count[r];
    }
    starts.push(total);
    let mut entries = vec![(0usize, 0.0f64); total];
    for (k, list) in lists.iter().enumerate() {
        for &(r, v) in list {
            entries[next[r]] = (k, v);
            next[r] += 1;
        }
    }
    (rows, starts, entries)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::model::swept::assemble_swept;
    use crate::influence::operator::fft::FftOperator;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    /// Products of the corrected operator against the assembled swept `R`, relative to the
    /// largest entry of the exact product: both sum the same entries, in different orders.
    const PRODUCT_TOL: f64 = 1e-11;

    /// A 15 x 10 mm map and a serpentine raster on its 0.5 mm lattice whose row ends lie a
    /// millimetre outside it, well within the TIF's reach: the FFT operator with the dominant
    /// stretch's kernel misses the row ends' L-shaped stretches; corrected, its `R t`, `R^T y`,
    /// `R^T R t` and centred column norms are the assembled swept `R`'s, with the normal product
    /// fused (the inner operator's plus `C` and `D^T D`) and unfused (`R^T (R t)`).
    #[test]
    fn the_corrected_lattice_operator_is_the_assembled_swept_matrix() {
        corrected_against_assembled(1, f64::INFINITY);
        corrected_against_assembled(1, 0.0);
    }

    /// The same with the map on a lattice twice as fine as the raster's (the FFT operator's
    /// dwell points on a sub-lattice).
    #[test]
    fn the_corrected_lattice_operator_is_the_assembled_swept_matrix_on_a_finer_map() {
        corrected_against_assembled(2, f64::INFINITY);
        corrected_against_assembled(2, 0.0);
    }

    fn corrected_against_assembled(refine: usize, unfused_above: f64) {
        let (mut mx, mut my) = (Vec::new(), Vec::new());
        let h = 0.5 / refine as f64;
        for j in 0..(20 * refine + 1) {
            for i in 0..(30 * refine + 1) {
                mx.push(i as f64 * h);
                my.push(j as f64 * h);
            }
        }
        // Rows from 5 mm below to 5 mm above the map, each from 1 mm before to 1 mm beyond it:
        // the row ends of the outer rows reach no map point (empty columns), the others do.
        let (mut dx, mut dy) = (Vec::new(), Vec::new());
        for row in 0..41 {
            for k in 0..35 {
                let i = if row % 2 == 0 { k } else { 34 - k };
                dx.push(-1.0 + 0.5 * i as f64);
                dy.push(-5.0 + 0.5 * row as f64);
            }
        }
        let path = DwellPath::new(dx.clone(), dy.clone()).unwrap();
        let tif = GaussianTif::new(1.0, 5.0, 3.0).unwrap();
        let stretches = Stretches::of_path(&path, 0.05).unwrap();
        let kernel = stretches.dominant_kernel(tif.clone());
        let fft = FftOperator::new(&mx, &my, &dx, &dy, h, &kernel).unwrap();
        let exact = assemble_swept(&mx, &my, &path, &stretches, &tif, &Silent).unwrap();
        let plain_t: Vec<f64> = (0..dx.len())
            .map(|j| 1.0 + 0.3 * ((j as f64) * 0.37).sin())
            .collect();
        let plain = fft.removal_nm(&plain_t).unwrap();
        let want = exact.removal_nm(&plain_t).unwrap();
        let peak = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let worst = plain
            .iter()
            .zip(&want)
            .fold(0.0f64, |a, (p, w)| a.max((p - w).abs()));
        assert!(
            worst > 1e-4 * peak,
            "the uncorrected kernel should miss the row ends"
        );
        let corrected = match SweptCorrected::build(
            Box::new(fft),
            (&mx, &my),
            &path,
            &stretches,
            stretches.outside_dominant(),
            (&tif, &kernel),
            unfused_above,
            &Silent,
        )
        .unwrap()
        {
            Ok(c) => c,
            Err(_) => panic!("the row ends differ from the dominant stretch"),
        };
        assert_eq!(corrected.unfused, unfused_above == 0.0);
        assert_eq!(
            corrected.corrected_columns(),
            stretches.outside_dominant().len()
        );
        // Both ends of every row but the path's own two, which are mirrored straight.
        assert_eq!(corrected.corrected_columns(), 2 * 41 - 2);
        let close = |got: &[f64], want: &[f64]| {
            let peak = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() <= PRODUCT_TOL * peak, "{g} against {w}");
            }
        };
        let (m, n) = (mx.len(), dx.len());
        let ep = exact.products(None);
        let cp = corrected.products(None);
        let mut a = vec![0.0; m];
        let mut b = vec![0.0; m];
        cp.apply(&plain_t, &mut a);
        ep.apply(&plain_t, &mut b);
        close(&a, &b);
        let y: Vec<f64> = (0..m).map(|i| ((i as f64) * 0.11).cos()).collect();
        let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
        cp.apply_transpose(&y, &mut a);
        ep.apply_transpose(&y, &mut b);
        close(&a, &b);
        let (mut s1, mut s2) = (vec![0.0; m], vec![0.0; m]);
        cp.apply_normal(&plain_t, &mut s1, &mut a);
        ep.apply_normal(&plain_t, &mut s2, &mut b);
        close(&a, &b);
        let (mine, exact) = (cp.centred_column_norms_sq(), ep.centred_column_norms_sq());
        close(&mine, &exact);
        // An empty column's norm is exactly zero (the Jacobi scale divides by its root).
        let empty = exact.iter().filter(|&&e| e == 0.0).count();
        assert!(empty > 0);
        for (g, e) in mine.iter().zip(&exact) {
            if *e == 0.0 {
                assert_eq!(*g, 0.0);
            }
        }
    }
}
