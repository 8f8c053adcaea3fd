//! A matrix-free influence operator for dwell points anywhere in the plane (off the map's
//! lattice): each dwell point is spread onto an oversampled copy of the map lattice by bilinear
//! weights, and the lattice products run by FFT convolution ([`super::fft::FftOperator`]).
//!
//! With the map on a lattice of pitch `h` through `(x0, y0)` and an oversampling factor `s`, the
//! fine lattice has pitch `h_f = h / s` (every `s`-th fine node is a map node). A dwell point at
//! `X_j` lies in the fine cell with corners `q_c` and bilinear weights `w_jc` (`sum_c w_jc = 1`),
//! and the operator is
//!
//! `R~[i, j] = sum_c w_jc TIF(x_i - q_c)`,
//!
//! i.e. `R~ = K S` with `S` (fine nodes x dwell points) the spreading and `K` the lattice
//! convolution. `R~ t = K (S t)` and `R~^T y = S^T (K^T y)`, so the transpose is exact and the
//! solvers see one consistent linear map. `R~[i, j]` is the bilinear interpolant, in the tool's
//! position, of `TIF(x_i - .)` at the fine nodes around `X_j`, so for a TIF with bounded second
//! derivatives the entry error against the exact contract `R[i, j] = TIF(x_i - X_j)` is at most
//! `h_f^2 / 8 (max |TIF_xx| + max |TIF_yy|)` (the bilinear interpolation bound, e.g. Quarteroni,
//! Sacco & Saleri, "Numerical Mathematics", sec. 8.7): the relative operator error falls as
//! `O(s^-2)`. For a sampled (grid) TIF, itself bilinear between its samples, the same holds
//! within each grid cell, with first-order kinks at the grid lines. A TIF truncated where it is
//! not zero (a Gaussian cut at 3 sigma keeps a 1.1% step at its edge) adds entries within `h_f`
//! of the step that are off by up to the step: their share of `||R||_F^2` is `O(h_f)`, so that
//! part of the relative error falls only as `O(s^-1/2)` - the estimate below includes it.
//!
//! The error actually incurred is measured, not assumed: [`SpreadOperator::estimated_error`] is
//! the relative Frobenius error `||R~ - R||_F / ||R||_F` over a fixed, evenly spaced sample of
//! columns, each column computed both ways entry by entry.

use super::fft::FftOperator;
use super::lattice::off_lattice_error;
use super::{ColumnStats, ColumnSums, InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use crate::tif::{lattice_reach, InfluenceFunction};
use rayon::prelude::*;
use std::sync::Mutex;

/// Relative tolerance for a map coordinate to count as on the lattice.
const ON_LATTICE_TOL: f64 = 1e-6;
/// Columns sampled for the error estimate (evenly spaced over the dwell points).
const ERROR_SAMPLE_COLUMNS: usize = 256;
/// Largest oversampling factor [`SpreadOperator::with_tolerance`] tries.
pub const MAX_OVERSAMPLING: usize = 4;
/// Default tolerance on the estimated relative operator error (`||R~ - R||_F / ||R||_F`) below
/// which `operator = "auto"` may use the spreading operator: small enough that the default stays
/// the exact contract in practice (dwell points on a sub-lattice of the fine lattice); larger
/// tolerances are a user's explicit trade of accuracy for speed.
pub const DEFAULT_SPREAD_TOLERANCE: f64 = 1e-4;

/// A point's place in the fine lattice of pitch `fine` through `(x0, y0)`: the node `(i, j)`
/// below and left of it and its fractions `(fx, fy)` of the cell (a fraction within rounding of
/// a node snapped onto it: one node, not two).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Bilinear {
    pub(crate) i: i64,
    pub(crate) j: i64,
    pub(crate) fx: f64,
    pub(crate) fy: f64,
}

impl Bilinear {
    /// The four corner nodes and their bilinear weights.
    pub(crate) fn nodes(&self) -> [((i64, i64), f64); 4] {
        let (i, j, fx, fy) = (self.i, self.j, self.fx, self.fy);
        [
            ((i, j), (1.0 - fx) * (1.0 - fy)),
            ((i + 1, j), fx * (1.0 - fy)),
            ((i, j + 1), (1.0 - fx) * fy),
            ((i + 1, j + 1), fx * fy),
        ]
    }
}

/// The bilinear cell of `(x, y)` on the fine lattice of pitch `fine` through `(x0, y0)`; `None`
/// when the point is too far away (or not finite). The spreading operator's weights, shared with
/// [`super::expansion`].
pub(crate) fn bilinear_nodes(x: f64, y: f64, x0: f64, y0: f64, fine: f64) -> Option<Bilinear> {
    let (u, v) = ((x - x0) / fine, (y - y0) / fine);
    if !(u.is_finite() && v.is_finite() && u.abs() < 1e9 && v.abs() < 1e9) {
        return None;
    }
    let (i, j) = (u.floor(), v.floor());
    let snap = |f: f64| {
        if f < ON_LATTICE_TOL {
            0.0
        } else if f > 1.0 - ON_LATTICE_TOL {
            1.0
        } else {
            f
        }
    };
    Some(Bilinear {
        i: i as i64,
        j: j as i64,
        fx: snap(u - i),
        fy: snap(v - j),
    })
}

/// The spreading operator (see the module documentation).
pub struct SpreadOperator {
    inner: FftOperator,
    oversampling: usize,
    fine_pitch_mm: f64,
    /// For each dwell point, its up to four fine nodes (indices into the inner operator's
    /// dwell points) and weights; unused slots have weight 0.
    stencil: Vec<[(u32, f64); 4]>,
    /// Transpose of `stencil` (CSR by node): the dwell points spread onto each node.
    node_start: Vec<usize>,
    node_entries: Vec<(u32, f64)>,
    /// Each column's sums of `R~` over the map points (non-zeros, Jacobi scaling).
    columns: ColumnStats,
    estimated_error: f64,
    m: usize,
    /// Node-space work vectors for the products.
    work: Mutex<(Vec<f64>, Vec<f64>)>,
}

impl std::fmt::Debug for SpreadOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SpreadOperator")
            .field("oversampling", &self.oversampling)
            .field("fine_pitch_mm", &self.fine_pitch_mm)
            .field("m", &self.m)
            .field("n", &self.stencil.len())
            .field("nodes", &self.node_start.len().saturating_sub(1))
            .field("estimated_error", &self.estimated_error)
            .finish()
    }
}

/// The geometry shared by the error estimate and the operator: map cells on the coarse lattice,
/// each dwell point's fine nodes and weights, and the fine kernel.
struct Layout {
    pitch_mm: f64,
    s: usize,
    x0: f64,
    y0: f64,
    /// Map points' coarse lattice indices.
    map_ij: Vec<(i64, i64)>,
    /// Coarse lattice box of the map: origin and size, and the first map point in each cell
    /// (`u32::MAX` for none) with the number of map points in it.
    box_i0: i64,
    box_j0: i64,
    box_w: usize,
    box_h: usize,
    cell_count: Vec<u32>,
    /// Each dwell point's fine nodes `(i, j)` and weights.
    nodes: Vec<[((i64, i64), f64); 4]>,
    /// Kernel `K[d] = TIF(d h_f)`, `|d_x|, |d_y| <= kr`, row-major `(2 kr + 1)^2`.
    kr: i64,
    kernel: Vec<f64>,
}

impl Layout {
    fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        s: usize,
        tif: &T,
    ) -> Result<Self> {
        if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
            return Err(Error::invalid("lattice pitch", format!("{pitch_mm}")));
        }
        if s == 0 {
            return Err(Error::invalid("oversampling factor", "must be at least 1"));
        }
        if map_x_mm.is_empty() || dwell_x_mm.is_empty() {
            return Err(Error::invalid(
                "spreading operator",
                "needs map and dwell points",
            ));
        }
        let x0 = map_x_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let y0 = map_y_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let index = |v: f64, o: f64| -> Option<i64> {
            let u = (v - o) / pitch_mm;
            let k = u.round();
            ((u - k).abs() <= ON_LATTICE_TOL && k.abs() < 1e9).then_some(k as i64)
        };
        let map_ij = map_x_mm
            .iter()
            .zip(map_y_mm)
            .enumerate()
            .map(|(k, (&x, &y))| match (index(x, x0), index(y, y0)) {
                (Some(i), Some(j)) => Ok((i, j)),
                _ => Err(off_lattice_error(
                    "map point",
                    k,
                    (x, y),
                    pitch_mm,
                    (x0, y0),
                )),
            })
            .collect::<Result<Vec<_>>>()?;
        let (box_i0, box_j0) = (0, 0);
        let box_w = map_ij.iter().map(|p| p.0).max().unwrap_or(0) as usize + 1;
        let box_h = map_ij.iter().map(|p| p.1).max().unwrap_or(0) as usize + 1;
        crate::budget::check(
            "map points (spreading operator)",
            &format!("a map lattice of {box_w} x {box_h} cells of {pitch_mm} mm"),
            box_w as f64 * box_h as f64 * 4.0,
        )?;
        let mut cell_count = vec![0u32; box_w * box_h];
        for &(i, j) in &map_ij {
            cell_count[j as usize * box_w + i as usize] += 1;
        }
        let fine = pitch_mm / s as f64;
        let nodes = dwell_x_mm
            .iter()
            .zip(dwell_y_mm)
            .enumerate()
            .map(|(k, (&x, &y))| {
                bilinear_nodes(x, y, x0, y0, fine)
                    .map(|b| b.nodes())
                    .ok_or_else(|| {
                        Error::invalid(
                            "dwell point",
                            format!("{k} at ({x}, {y}) mm is too far from the map"),
                        )
                    })
            })
            .collect::<Result<Vec<_>>>()?;
        let kr = lattice_reach(tif.support_radius_mm(), fine) as i64;
        let side = (2 * kr + 1) as usize;
        let kernel = (0..side * side)
            .map(|k| {
                let (dx, dy) = ((k % side) as i64 - kr, (k / side) as i64 - kr);
                tif.rate_nm_per_s(dx as f64 * fine, dy as f64 * fine)
            })
            .collect();
        Ok(Self {
            pitch_mm,
            s,
            x0,
            y0,
            map_ij,
            box_i0,
            box_j0,
            box_w,
            box_h,
            cell_count,
            nodes,
            kr,
            kernel,
        })
    }

    /// Calls `f(cell index, cell count, value of R~)` for every occupied map cell in reach of
    /// dwell point `j`'s nodes (value may be zero).
    fn for_each_entry(&self, j: usize, mut f: impl FnMut(usize, u32, f64)) {
        let nodes = &self.nodes[j];
        let s = self.s as i64;
        let (qi, qj) = nodes[0].0;
        let side = 2 * self.kr + 1;
        // Coarse cells a with a s in [qi - kr, qi + 1 + kr].
        let a0 = (qi - self.kr).div_euclid(s).max(self.box_i0);
        let a1 = (qi + 1 + self.kr)
            .div_euclid(s)
            .min(self.box_i0 + self.box_w as i64 - 1);
        let b0 = (qj - self.kr).div_euclid(s).max(self.box_j0);
        let b1 = (qj + 1 + self.kr)
            .div_euclid(s)
            .min(self.box_j0 + self.box_h as i64 - 1);
        for b in b0..=b1 {
            for a in a0..=a1 {
                let cell = (b - self.box_j0) as usize * self.box_w + (a - self.box_i0) as usize;
                let count = self.cell_count[cell];
                if count == 0 {
                    continue;
                }
                let mut value = 0.0;
                for &((ni, nj), w) in nodes {
                    if w == 0.0 {
                        continue;
                    }
                    let (dx, dy) = (a * s - ni, b * s - nj);
                    if dx.abs() <= self.kr && dy.abs() <= self.kr {
                        value += w * self.kernel[((dy + self.kr) * side + dx + self.kr) as usize];
                    }
                }
                f(cell, count, value);
            }
        }
    }

    /// Column `j`'s sums of `R~` over the map points.
    fn column_sums(&self, j: usize) -> ColumnSums {
        let mut sums = ColumnSums::default();
        self.for_each_entry(j, |_, count, v| sums.add(count, v));
        sums
    }

    /// `(||R~_j - R_j||^2, ||R_j||^2)` for column `j`, against the exact contract
    /// `R[i, j] = TIF(x_i - X_j)`.
    fn column_error<T: InfluenceFunction + ?Sized>(
        &self,
        j: usize,
        x: f64,
        y: f64,
        tif: &T,
    ) -> (f64, f64) {
        let (mut err, mut norm) = (0.0, 0.0);
        self.for_each_entry(j, |cell, count, v| {
            let a = (cell % self.box_w) as i64 + self.box_i0;
            let b = (cell / self.box_w) as i64 + self.box_j0;
            let (mx, my) = (
                self.x0 + a as f64 * self.pitch_mm,
                self.y0 + b as f64 * self.pitch_mm,
            );
            let exact = tif.rate_nm_per_s(mx - x, my - y);
            let c = f64::from(count);
            err += c * (v - exact) * (v - exact);
            norm += c * exact * exact;
        });
        (err, norm)
    }

    /// Relative Frobenius error of `R~` over an evenly spaced sample of columns.
    fn estimated_error<T: InfluenceFunction + ?Sized>(
        &self,
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        tif: &T,
    ) -> f64 {
        let n = self.nodes.len();
        let samples = n.min(ERROR_SAMPLE_COLUMNS);
        let parts: Vec<(f64, f64)> = (0..samples)
            .into_par_iter()
            .map(|k| {
                let j = k * n / samples;
                self.column_error(j, dwell_x_mm[j], dwell_y_mm[j], tif)
            })
            .collect();
        let (err, norm) = parts
            .iter()
            .fold((0.0, 0.0), |(e, n), p| (e + p.0, n + p.1));
        if norm > 0.0 {
            (err / norm).sqrt()
        } else if err > 0.0 {
            f64::INFINITY
        } else {
            0.0
        }
    }
}

impl SpreadOperator {
    /// Estimated relative operator error `||R~ - R||_F / ||R||_F` (over a sample of columns) of
    /// the spreading operator with oversampling factor `s`, without building it.
    pub fn estimate_error<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        s: usize,
        tif: &T,
    ) -> Result<f64> {
        let layout = Layout::new(map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, pitch_mm, s, tif)?;
        Ok(layout.estimated_error(dwell_x_mm, dwell_y_mm, tif))
    }

    /// The smallest oversampling factor `s` in `1..=MAX_OVERSAMPLING` whose estimated error is at
    /// most `tolerance`, with that error; `None` when none is.
    pub fn oversampling_for<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        tif: &T,
        tolerance: f64,
    ) -> Result<Option<(usize, f64)>> {
        for s in 1..=MAX_OVERSAMPLING {
            let e =
                Self::estimate_error(map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, pitch_mm, s, tif)?;
            if e <= tolerance {
                return Ok(Some((s, e)));
            }
        }
        Ok(None)
    }

    /// Builds the operator for map points on a lattice of pitch `pitch_mm` (through their lowest
    /// x and y) and dwell points anywhere, with oversampling factor `s >= 1`.
    pub fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        s: usize,
        tif: &T,
    ) -> Result<Self> {
        let layout = Layout::new(map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, pitch_mm, s, tif)?;
        let estimated_error = layout.estimated_error(dwell_x_mm, dwell_y_mm, tif);
        // The fine nodes touched, numbered in (j, i) order.
        let mut touched: Vec<(i64, i64)> = layout
            .nodes
            .iter()
            .flat_map(|n| {
                n.iter()
                    .filter(|(_, w)| *w != 0.0)
                    .map(|(ij, _)| (ij.1, ij.0))
            })
            .collect();
        touched.sort_unstable();
        touched.dedup();
        let node_index = |i: i64, j: i64| -> u32 {
            // Every node looked up was collected above.
            touched.binary_search(&(j, i)).unwrap_or(0) as u32
        };
        let stencil: Vec<[(u32, f64); 4]> = layout
            .nodes
            .iter()
            .map(|n| {
                n.map(|((i, j), w)| {
                    if w == 0.0 {
                        (0, 0.0)
                    } else {
                        (node_index(i, j), w)
                    }
                })
            })
            .collect();
        let mut node_start = vec![0usize; touched.len() + 1];
        for st in &stencil {
            for &(k, w) in st {
                if w != 0.0 {
                    node_start[k as usize + 1] += 1;
                }
            }
        }
        for k in 0..touched.len() {
            node_start[k + 1] += node_start[k];
        }
        let mut fill = node_start.clone();
        let mut node_entries = vec![(0u32, 0.0); node_start[touched.len()]];
        for (j, st) in stencil.iter().enumerate() {
            for &(k, w) in st {
                if w != 0.0 {
                    node_entries[fill[k as usize]] = (j as u32, w);
                    fill[k as usize] += 1;
                }
            }
        }
        let fine = pitch_mm / s as f64;
        let node_x: Vec<f64> = touched
            .iter()
            .map(|&(_, i)| layout.x0 + i as f64 * fine)
            .collect();
        let node_y: Vec<f64> = touched
            .iter()
            .map(|&(j, _)| layout.y0 + j as f64 * fine)
            .collect();
        let inner = FftOperator::new(map_x_mm, map_y_mm, &node_x, &node_y, fine, tif)?;
        let columns = ColumnStats::new(
            layout.map_ij.len(),
            (0..layout.nodes.len())
                .into_par_iter()
                .map(|j| layout.column_sums(j))
                .collect(),
        );
        let nodes = touched.len();
        Ok(Self {
            inner,
            oversampling: s,
            fine_pitch_mm: fine,
            stencil,
            node_start,
            node_entries,
            columns,
            estimated_error,
            m: layout.map_ij.len(),
            work: Mutex::new((vec![0.0; nodes], vec![0.0; nodes])),
        })
    }

    /// The oversampling factor `s` (fine lattice pitch = map pitch / `s`).
    pub fn oversampling(&self) -> usize {
        self.oversampling
    }

    /// Pitch of the fine lattice, mm.
    pub fn fine_pitch_mm(&self) -> f64 {
        self.fine_pitch_mm
    }

    /// Estimated relative operator error `||R~ - R||_F / ||R||_F` against the exact contract,
    /// over an evenly spaced sample of columns.
    pub fn estimated_error(&self) -> f64 {
        self.estimated_error
    }

    /// Non-zero entries of `R~` (over the map points).
    pub fn nnz(&self) -> usize {
        self.columns.nnz()
    }

    /// Dwell points whose column is empty: no map point in the tool's reach.
    pub fn empty_columns(&self) -> Vec<usize> {
        self.columns.empty_columns()
    }

    /// Fine nodes the dwell points spread onto.
    pub fn nodes(&self) -> usize {
        self.node_start.len() - 1
    }

    /// `nodes = S t`: each node's dwell points times their weights, in a fixed order.
    fn spread(&self, t: &[f64], nodes: &mut [f64]) {
        nodes
            .par_iter_mut()
            .enumerate()
            .with_min_len(1024)
            .for_each(|(k, o)| {
                *o = self.node_entries[self.node_start[k]..self.node_start[k + 1]]
                    .iter()
                    .map(|&(j, w)| w * t[j as usize])
                    .sum();
            });
    }

    /// `out = S^T nodes`.
    fn gather(&self, nodes: &[f64], out: &mut [f64]) {
        out.par_iter_mut()
            .zip(self.stencil.par_iter())
            .with_min_len(1024)
            .for_each(|(o, st)| {
                *o = st.iter().map(|&(k, w)| w * nodes[k as usize]).sum();
            });
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Vec<f64>, Vec<f64>)> {
        // A panic while holding the work vectors leaves them merely stale: they are overwritten
        // before every use.
        self.work.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl LinearOperator for SpreadOperator {
    fn nrows(&self) -> usize {
        self.m
    }

    fn products_cheap_per_dwell_point(&self) -> bool {
        true
    }

    fn ncols(&self) -> usize {
        self.stencil.len()
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (a, _) = &mut *work;
        self.spread(t, a);
        self.inner.apply(a, out);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (_, b) = &mut *work;
        self.inner.apply_transpose(y, b);
        self.gather(b, out);
    }

    fn apply_normal(&self, t: &[f64], scratch: &mut [f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (a, b) = &mut *work;
        self.spread(t, a);
        self.inner.apply_normal(a, scratch, b);
        self.gather(b, out);
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.columns.centred_norms_sq()
    }
}

impl InfluenceOperator for SpreadOperator {
    fn kind(&self) -> OperatorKind {
        OperatorKind::FftSpread
    }

    fn shape(&self) -> (usize, usize) {
        (LinearOperator::nrows(self), LinearOperator::ncols(self))
    }

    fn nnz(&self) -> usize {
        SpreadOperator::nnz(self)
    }

    fn empty_columns(&self) -> Vec<usize> {
        SpreadOperator::empty_columns(self)
    }

    /// The operator itself: its products need no copy, and it has no Gram matrix.
    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::InfluenceMatrix;
    use crate::observer::Silent as NoopObserver;
    use crate::tif::GaussianTif;

    /// A 41 x 31 map at 0.4 mm and dwell points on a 0.55 mm raster, off the map lattice.
    fn case() -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut mx, mut my, mut dx, mut dy) = (vec![], vec![], vec![], vec![]);
        for j in 0..31 {
            for i in 0..41 {
                mx.push(-3.0 + 0.4 * i as f64);
                my.push(1.0 + 0.4 * j as f64);
            }
        }
        for j in 0..20 {
            for i in 0..28 {
                dx.push(-3.3 + 0.55 * i as f64 + 0.013 * j as f64);
                dy.push(0.7 + 0.55 * j as f64);
            }
        }
        (mx, my, dx, dy)
    }

    /// Truncated at 4.5 sigma, where the jump (4e-5 of the peak) is below the interpolation
    /// error studied.
    fn tif() -> GaussianTif {
        GaussianTif::new(1.2, 1.0, 5.4).unwrap()
    }

    /// Relative Frobenius error over every column, from the assembled exact `R` and `R~ e_j`.
    fn full_error(op: &SpreadOperator, exact: &InfluenceMatrix) -> f64 {
        let (m, n) = (op.nrows(), op.ncols());
        let dense = exact.csc();
        let (mut err, mut norm) = (0.0, 0.0);
        let mut e = vec![0.0; n];
        let mut col = vec![0.0; m];
        for j in 0..n {
            e[j] = 1.0;
            op.apply(&e, &mut col);
            e[j] = 0.0;
            let mut exact_col = vec![0.0; m];
            let c = dense.col(j);
            for (&i, &v) in c.row_indices().iter().zip(c.values()) {
                exact_col[i] = v;
            }
            for i in 0..m {
                err += (col[i] - exact_col[i]).powi(2);
                norm += exact_col[i].powi(2);
            }
        }
        (err / norm).sqrt()
    }

    #[test]
    fn transpose_is_the_adjoint_and_normal_is_the_product() {
        let (mx, my, dx, dy) = case();
        let op = SpreadOperator::new(&mx, &my, &dx, &dy, 0.4, 2, &tif()).unwrap();
        let t: Vec<f64> = (0..op.ncols())
            .map(|j| ((j * 7919) % 13) as f64 * 0.1)
            .collect();
        let y: Vec<f64> = (0..op.nrows())
            .map(|i| ((i * 104729) % 17) as f64 - 8.0)
            .collect();
        let mut rt = vec![0.0; op.nrows()];
        let mut rty = vec![0.0; op.ncols()];
        op.apply(&t, &mut rt);
        op.apply_transpose(&y, &mut rty);
        let lhs: f64 = rt.iter().zip(&y).map(|(a, b)| a * b).sum();
        let rhs: f64 = rty.iter().zip(&t).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() <= 1e-10 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
        let mut normal = vec![0.0; op.ncols()];
        let mut scratch = vec![0.0; op.nrows()];
        op.apply_normal(&t, &mut scratch, &mut normal);
        let mut two = vec![0.0; op.ncols()];
        op.apply_transpose(&rt, &mut two);
        for (a, b) in normal.iter().zip(&two) {
            assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0));
        }
    }

    #[test]
    fn error_falls_as_the_square_of_the_fine_pitch_and_matches_the_estimate() {
        let (mx, my, dx, dy) = case();
        let tif = tif();
        let exact = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &NoopObserver).unwrap();
        let errors: Vec<f64> = [1, 2, 4]
            .iter()
            .map(|&s| {
                let op = SpreadOperator::new(&mx, &my, &dx, &dy, 0.4, s, &tif).unwrap();
                let full = full_error(&op, &exact);
                // The sampled estimate tracks the full error (same columns structure).
                assert!(
                    (op.estimated_error() / full - 1.0).abs() < 0.35,
                    "s = {s}: estimate {} vs full {full}",
                    op.estimated_error()
                );
                full
            })
            .collect();
        // O(h_f^2): doubling s divides the error by about 4.
        for w in errors.windows(2) {
            let ratio = w[0] / w[1];
            assert!((3.0..5.0).contains(&ratio), "ratio {ratio} ({errors:?})");
        }
        // The closed-form bound for a Gaussian (|f_xx| <= A / sigma^2): relative to the entries'
        // RMS this is loose, so check the absolute entry error instead.
        assert!(errors[0] < 0.05, "{errors:?}");
    }

    #[test]
    fn dwell_points_on_the_lattice_reproduce_the_exact_matrix() {
        let (mx, my, _, _) = case();
        let (dx, dy): (Vec<f64>, Vec<f64>) = (0..60)
            .map(|k| {
                (
                    -3.0 + 0.4 * (k % 10) as f64 * 2.0,
                    1.0 + 0.4 * (k / 10) as f64 * 3.0,
                )
            })
            .unzip();
        let tif = tif();
        let exact = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &NoopObserver).unwrap();
        let op = SpreadOperator::new(&mx, &my, &dx, &dy, 0.4, 1, &tif).unwrap();
        assert!(full_error(&op, &exact) < 1e-12);
        assert!(op.estimated_error() < 1e-12);
        assert_eq!(op.nnz(), exact.nnz());
    }

    #[test]
    fn centred_norms_match_the_applied_columns() {
        let (mx, my, dx, dy) = case();
        let op = SpreadOperator::new(&mx, &my, &dx, &dy, 0.4, 2, &tif()).unwrap();
        let norms = op.centred_column_norms_sq();
        let mut e = vec![0.0; op.ncols()];
        let mut col = vec![0.0; op.nrows()];
        for j in (0..op.ncols()).step_by(37) {
            e[j] = 1.0;
            op.apply(&e, &mut col);
            e[j] = 0.0;
            let m = col.len() as f64;
            let (s, s2) = col
                .iter()
                .fold((0.0, 0.0), |(s, s2), v| (s + v, s2 + v * v));
            let want = s2 - s * s / m;
            assert!((norms[j] - want).abs() <= 1e-9 * want.max(1e-12), "{j}");
        }
    }
}
