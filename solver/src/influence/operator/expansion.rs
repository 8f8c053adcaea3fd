//! A matrix-free operator for dwell points anywhere whose columns each have their own shape: the
//! swept model on a spiral or a random path, where each dwell point's stretch turns with the path,
//! and a TIF cut at a radius (a jump no smooth spreading resolves).
//!
//! **The expansion.** Column `j` of the swept `R` is the TIF averaged over the stretch's measure
//! `mu_j` (its pieces, uniform along each). About the measure's centroid `c_j`, with second central
//! moment `M_j` (2 x 2), a smooth kernel's column is to second order
//!
//! `R_j(x) ~ K(x - c_j) + 1/2 (M_xx K_xx + 2 M_xy K_xy + M_yy K_yy)(x - c_j)`
//!
//! (a straight stretch of length `ds` in direction `theta` has `M = ds^2/12 (c^2, cs, s^2)`: the
//! `K + ds^2/24 (c^2 K_xx + 2cs K_xy + s^2 K_yy)` of the swept kernel's expansion). The derivative
//! kernels are not differentiated: they are the exact swept kernels ([`swept_rate`], a cut
//! circle's pieces integrated exactly) along three directions of one reference length `L`, less
//! the TIF: `D_xx = K_0 - K ~ L^2/24 K_xx`, `D_yy = K_90 - K`, `D_xy = K_45 - (K_0 + K_90)/2 ~
//! L^2/24 K_xy`; a measured grid TIF serves as a model one does. Each of the four kernels is
//! applied by the bilinear spreading operator ([`SpreadOperator`]) at the centroids, and the
//! spreading's own second-order error, `+1/2 h^2 (a_x (1 - a_x) K_xx + a_y (1 - a_y) K_yy)` for a
//! point at fractions `a` of its fine cell of pitch `h`, is taken off the same derivative terms.
//! So
//!
//! `R~ t = K*(S t) + D_xx*(S (w_xx t)) + D_xy*(S (w_xy t)) + D_yy*(S (w_yy t)) + C t`,
//!
//! `w_xx = 12 (M_xx - h^2 a_x (1 - a_x)) / L^2`, `w_xy = 24 M_xy / L^2`, `w_yy` as `w_xx`: four
//! lattice convolutions, the transpose exact likewise (`R~^T y = sum_k w_k S^T (K_k^T y) + C^T y`).
//!
//! **The exact correction `C`.** Where the expansion is poor (entries near a cut circle, whose jump
//! no Taylor series follows; odd stretches: the path's ends, the spiral's first turns, a random
//! path's corners) `C` holds `R - (expansion)` entry by entry. The build assembles the exact `R`
//! once (a column each, as the sparse operator does), takes every entry's difference, and keeps
//! the largest ones: all but a set whose squared sum is within `tolerance^2 ||R||_F^2`. The
//! error reported ([`ExpansionOperator::estimated_error`]) is that dropped sum over every entry of
//! every column, not a sample: `||R~ - R||_F / ||R||_F` up to the FFT's rounding (about 1e-13).
//! The build costs one assembly of `R` and the products cost four spreading products and a pass
//! over `C` (its share of `R`'s non-zeros is [`ExpansionOperator::correction_share`]).
//!
//! Every product is computed entry by entry in a fixed order, so results are bit-identical for any
//! thread count; the choice of `C` sums its histogram in fixed chunks of columns.

use super::spread::{bilinear_nodes, SpreadOperator};
use super::{ColumnStats, ColumnSums, InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use crate::influence::model::swept::{swept_rate, Stretches};
use crate::influence::operator::matrix::InfluenceMatrix;
use crate::tif::{lattice_reach, InfluenceFunction};
use rayon::prelude::*;
use std::sync::Mutex;

/// Bins of the squared differences' histogram per octave.
const BINS_PER_OCTAVE: f64 = 4.0;
/// Histogram bins (squared differences from `2^-600` to `2^600`).
const BINS: usize = 4800;
/// Columns per fixed chunk of the histogram's sums.
const HISTOGRAM_CHUNK: usize = 64;

/// A coefficient and a stretch's midpoint samples `(dx, dy, weight)` and piece halves.
type Part = (f64, Vec<[f64; 3]>, Vec<[f64; 2]>);

/// One of the three derivative kernels: the TIF's exact swept kernels along straight stretches,
/// combined with coefficients (`(coefficient, direction in radians)`).
struct DirectionKernel<'a, T: ?Sized> {
    tif: &'a T,
    parts: Vec<Part>,
    reach_mm: f64,
}

/// The midpoint samples and piece halves of a straight stretch of length `length_mm` in
/// direction `theta`, centred on the point, in pieces of at most 1/64 of the support radius (the
/// swept model's rule).
fn straight(length_mm: f64, theta: f64, support_mm: f64) -> (Vec<[f64; 3]>, Vec<[f64; 2]>) {
    let pieces = ((length_mm / (support_mm / 64.0)).ceil() as usize).clamp(1, 256);
    let (c, s) = (theta.cos(), theta.sin());
    let piece = length_mm / pieces as f64;
    let samples = (0..pieces)
        .map(|k| {
            let t = -0.5 * length_mm + (k as f64 + 0.5) * piece;
            [t * c, t * s, 1.0 / pieces as f64]
        })
        .collect();
    let halves = vec![[0.5 * piece * c, 0.5 * piece * s]; pieces];
    (samples, halves)
}

impl<'a, T: InfluenceFunction + ?Sized> DirectionKernel<'a, T> {
    /// `sum_k coefficient_k K_{theta_k}` for stretches of length `length_mm`.
    fn new(tif: &'a T, length_mm: f64, terms: &[(f64, f64)]) -> Self {
        let support = tif.support_radius_mm();
        Self {
            tif,
            parts: terms
                .iter()
                .map(|&(coef, theta)| {
                    let (samples, halves) = straight(length_mm, theta, support);
                    (coef, samples, halves)
                })
                .collect(),
            reach_mm: support + 0.5 * length_mm,
        }
    }
}

impl<T: InfluenceFunction + ?Sized> InfluenceFunction for DirectionKernel<'_, T> {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        self.parts
            .iter()
            .map(|(c, s, h)| c * swept_rate(self.tif, s, h, dx_mm, dy_mm))
            .sum()
    }

    fn support_radius_mm(&self) -> f64 {
        self.reach_mm
    }
}

/// The TIF's point kernel as the first term (a newtype so the four terms share one type).
struct PointKernel<'a, T: ?Sized>(&'a T);

impl<T: InfluenceFunction + ?Sized> InfluenceFunction for PointKernel<'_, T> {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        self.0.rate_nm_per_s(dx_mm, dy_mm)
    }

    fn support_radius_mm(&self) -> f64 {
        self.0.support_radius_mm()
    }
}

/// A kernel tabulated on the fine lattice's offsets, as the spreading operator samples it.
struct Table {
    kr: i64,
    values: Vec<f64>,
}

impl Table {
    fn new(kernel: &dyn InfluenceFunction, fine: f64) -> Self {
        let kr = lattice_reach(kernel.support_radius_mm(), fine) as i64;
        let side = (2 * kr + 1) as usize;
        let values = (0..side * side)
            .map(|k| {
                let (dx, dy) = ((k % side) as i64 - kr, (k / side) as i64 - kr);
                kernel.rate_nm_per_s(dx as f64 * fine, dy as f64 * fine)
            })
            .collect();
        Self { kr, values }
    }

    #[inline]
    fn at(&self, dx: i64, dy: i64) -> f64 {
        if dx.abs() > self.kr || dy.abs() > self.kr {
            return 0.0;
        }
        let side = 2 * self.kr + 1;
        self.values[((dy + self.kr) * side + dx + self.kr) as usize]
    }
}

/// Where each dwell point's column sits and how it bends: the centroid of its stretch and the
/// stretch's second central moment `(M_xx, M_xy, M_yy)` (zero for the point model).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColumnShape {
    /// Centroid, mm.
    pub centre_mm: (f64, f64),
    /// Second central moment of the stretch's measure, mm^2.
    pub moment_mm2: [f64; 3],
}

impl ColumnShape {
    /// The shapes of every dwell point: each stretch's centroid and moment (its pieces uniform
    /// along their length), or the points themselves with no moment (point model).
    pub fn of(dwell_x_mm: &[f64], dwell_y_mm: &[f64], stretches: Option<&Stretches>) -> Vec<Self> {
        (0..dwell_x_mm.len())
            .map(|j| {
                let (x, y) = (dwell_x_mm[j], dwell_y_mm[j]);
                let Some(st) = stretches else {
                    return Self {
                        centre_mm: (x, y),
                        moment_mm2: [0.0; 3],
                    };
                };
                let samples = st.of(j);
                let halves = st.pieces_of(j);
                let (mut cx, mut cy, mut w) = (0.0, 0.0, 0.0);
                for s in samples {
                    cx += s[2] * s[0];
                    cy += s[2] * s[1];
                    w += s[2];
                }
                if w > 0.0 {
                    cx /= w;
                    cy /= w;
                }
                let mut m = [0.0; 3];
                for (k, s) in samples.iter().enumerate() {
                    let (u, v) = (s[0] - cx, s[1] - cy);
                    let h = halves.get(k).copied().unwrap_or([0.0, 0.0]);
                    let q = s[2] / w.max(f64::MIN_POSITIVE);
                    m[0] += q * (u * u + h[0] * h[0] / 3.0);
                    m[1] += q * (u * v + h[0] * h[1] / 3.0);
                    m[2] += q * (v * v + h[1] * h[1] / 3.0);
                }
                Self {
                    centre_mm: (x + cx, y + cy),
                    moment_mm2: m,
                }
            })
            .collect()
    }
}

/// The sparse exact correction `C`, by columns and by rows.
#[derive(Debug, Default)]
struct Correction {
    col_start: Vec<usize>,
    col_rows: Vec<u32>,
    col_vals: Vec<f64>,
    row_start: Vec<usize>,
    row_cols: Vec<u32>,
    row_vals: Vec<f64>,
}

/// The direction-expansion operator (module documentation).
pub struct ExpansionOperator {
    /// `K`, `D_xx`, `D_xy`, `D_yy`, each spread from the centroids.
    terms: Vec<SpreadOperator>,
    /// Per dwell point weights of `D_xx`, `D_xy`, `D_yy`.
    weights: [Vec<f64>; 3],
    correction: Correction,
    columns: ColumnStats,
    estimated_error: f64,
    reference_mm: f64,
    oversampling: usize,
    exact_nnz: usize,
    m: usize,
    work: Mutex<(Vec<f64>, Vec<f64>)>,
}

impl std::fmt::Debug for ExpansionOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExpansionOperator")
            .field("m", &self.m)
            .field("n", &self.weights[0].len())
            .field("oversampling", &self.oversampling)
            .field("reference_mm", &self.reference_mm)
            .field("correction_nnz", &self.correction.col_vals.len())
            .field("estimated_error", &self.estimated_error)
            .finish()
    }
}

impl ExpansionOperator {
    /// Builds the operator for map points on a lattice of pitch `pitch_mm` (through their lowest
    /// x and y), dwell points anywhere with the column shapes `shapes` ([`ColumnShape::of`]), the
    /// exact `R` (`exact`, assembled with the same model: swept along the stretches the shapes
    /// came from, or the point model), the fine lattice at `oversampling` and the error budget
    /// `tolerance` (relative Frobenius).
    #[allow(clippy::too_many_arguments)]
    pub fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        shapes: &[ColumnShape],
        exact: &InfluenceMatrix,
        pitch_mm: f64,
        oversampling: usize,
        tif: &T,
        tolerance: f64,
    ) -> Result<Self> {
        let (m, n) = (map_x_mm.len(), shapes.len());
        if exact.csc().nrows() != m || exact.csc().ncols() != n {
            return Err(Error::invalid(
                "expansion operator",
                "the exact R does not match the map and dwell points",
            ));
        }
        if !(tolerance.is_finite() && tolerance >= 0.0) {
            return Err(Error::invalid(
                "expansion tolerance",
                format!("{tolerance}"),
            ));
        }
        if oversampling == 0 || map_x_mm.is_empty() || shapes.is_empty() {
            return Err(Error::invalid(
                "expansion operator",
                "needs map and dwell points and an oversampling of at least 1",
            ));
        }
        let fine = pitch_mm / oversampling as f64;
        // Reference length: the median stretch length (sqrt(12 trace M) for a straight one), at
        // least the fine pitch (the point model's derivative terms).
        let mut lengths: Vec<f64> = shapes
            .iter()
            .map(|s| (12.0 * (s.moment_mm2[0] + s.moment_mm2[2])).sqrt())
            .collect();
        lengths.sort_by(f64::total_cmp);
        let reference_mm = lengths[lengths.len() / 2].max(fine);
        let quarter = std::f64::consts::FRAC_PI_4;
        let kernel0 = PointKernel(tif);
        let dxx = DirectionKernel::new(tif, reference_mm, &[(1.0, 0.0)]).minus_point();
        let dyy = DirectionKernel::new(tif, reference_mm, &[(1.0, 2.0 * quarter)]).minus_point();
        let dxy = DirectionKernel::new(
            tif,
            reference_mm,
            &[(1.0, quarter), (-0.5, 0.0), (-0.5, 2.0 * quarter)],
        );
        let kernels: [&dyn InfluenceFunction; 4] = [&kernel0, &dxx, &dxy, &dyy];
        let x0 = map_x_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let y0 = map_y_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let (cx, cy): (Vec<f64>, Vec<f64>) = shapes.iter().map(|s| s.centre_mm).unzip();
        let cells = cx
            .iter()
            .zip(&cy)
            .enumerate()
            .map(|(k, (&x, &y))| {
                bilinear_nodes(x, y, x0, y0, fine).ok_or_else(|| {
                    Error::invalid(
                        "dwell point",
                        format!("{k} at ({x}, {y}) mm is too far from the map"),
                    )
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let scale = 1.0 / (reference_mm * reference_mm);
        let mut weights = [vec![0.0; n], vec![0.0; n], vec![0.0; n]];
        for (j, (s, b)) in shapes.iter().zip(&cells).enumerate() {
            let h2 = fine * fine;
            weights[0][j] = 12.0 * (s.moment_mm2[0] - h2 * b.fx * (1.0 - b.fx)) * scale;
            weights[1][j] = 24.0 * s.moment_mm2[1] * scale;
            weights[2][j] = 12.0 * (s.moment_mm2[2] - h2 * b.fy * (1.0 - b.fy)) * scale;
        }
        let terms = kernels
            .iter()
            .map(|k| SpreadOperator::new(map_x_mm, map_y_mm, &cx, &cy, pitch_mm, oversampling, *k))
            .collect::<Result<Vec<_>>>()?;
        let tables: Vec<Table> = kernels.iter().map(|k| Table::new(*k, fine)).collect();
        let kr = tables.iter().map(|t| t.kr).max().unwrap_or(0);

        // Map points by coarse lattice cell (several points may share one).
        let index = |v: f64, o: f64| ((v - o) / pitch_mm).round() as i64;
        let map_ij: Vec<(i64, i64)> = map_x_mm
            .iter()
            .zip(map_y_mm)
            .map(|(&x, &y)| (index(x, x0), index(y, y0)))
            .collect();
        let box_w = map_ij.iter().map(|p| p.0).max().unwrap_or(0) as usize + 1;
        let box_h = map_ij.iter().map(|p| p.1).max().unwrap_or(0) as usize + 1;
        let mut cell_start = vec![0usize; box_w * box_h + 1];
        for &(i, j) in &map_ij {
            cell_start[j as usize * box_w + i as usize + 1] += 1;
        }
        for k in 0..box_w * box_h {
            cell_start[k + 1] += cell_start[k];
        }
        let mut fill = cell_start.clone();
        let mut cell_rows = vec![0u32; m];
        for (r, &(i, j)) in map_ij.iter().enumerate() {
            let c = j as usize * box_w + i as usize;
            cell_rows[fill[c]] = r as u32;
            fill[c] += 1;
        }
        let s = oversampling as i64;
        let csc = exact.csc();
        let weights_ref = &weights;
        // Column j's entries `(row, exact, expansion)` over the union of both supports.
        let entries = |j: usize, pos: &mut Vec<u32>| -> Vec<(u32, f64, f64)> {
            let b = &cells[j];
            let nodes = b.nodes();
            let w = [1.0, weights_ref[0][j], weights_ref[1][j], weights_ref[2][j]];
            let mut out: Vec<(u32, f64, f64)> = Vec::new();
            let a0 = (b.i - kr).div_euclid(s).max(0);
            let a1 = (b.i + 1 + kr).div_euclid(s).min(box_w as i64 - 1);
            let b0 = (b.j - kr).div_euclid(s).max(0);
            let b1 = (b.j + 1 + kr).div_euclid(s).min(box_h as i64 - 1);
            for cb in b0..=b1 {
                for ca in a0..=a1 {
                    let cell = cb as usize * box_w + ca as usize;
                    let rows = &cell_rows[cell_start[cell]..cell_start[cell + 1]];
                    if rows.is_empty() {
                        continue;
                    }
                    let mut v = 0.0;
                    for (k, table) in tables.iter().enumerate() {
                        if w[k] == 0.0 {
                            continue;
                        }
                        let mut tk = 0.0;
                        for &((ni, nj), wn) in &nodes {
                            if wn != 0.0 {
                                tk += wn * table.at(ca * s - ni, cb * s - nj);
                            }
                        }
                        v += w[k] * tk;
                    }
                    for &r in rows {
                        pos[r as usize] = out.len() as u32;
                        out.push((r, 0.0, v));
                    }
                }
            }
            let col = csc.col(j);
            for (&r, &e) in col.row_indices().iter().zip(col.values()) {
                let p = pos[r];
                if p != u32::MAX {
                    out[p as usize].1 = e;
                } else {
                    out.push((r as u32, e, 0.0));
                }
            }
            for &(r, _, _) in &out {
                pos[r as usize] = u32::MAX;
            }
            out.sort_unstable_by_key(|e| e.0);
            out
        };
        let bin_of = |d2: f64| -> usize {
            if d2 <= 0.0 {
                return 0;
            }
            let b = (BINS_PER_OCTAVE * d2.log2()).floor() + (BINS / 2) as f64;
            b.clamp(1.0, (BINS - 1) as f64) as usize
        };
        // Pass 1: the squared differences' histogram and `||R||_F^2`, in fixed chunks.
        let chunks = n.div_ceil(HISTOGRAM_CHUNK);
        let parts: Vec<(Vec<f64>, f64)> = (0..chunks)
            .into_par_iter()
            .map_init(
                || vec![u32::MAX; m],
                |pos, c| {
                    let mut hist = vec![0.0; BINS];
                    let mut norm = 0.0;
                    for j in c * HISTOGRAM_CHUNK..((c + 1) * HISTOGRAM_CHUNK).min(n) {
                        for (_, e, v) in entries(j, pos) {
                            let d2 = (e - v) * (e - v);
                            hist[bin_of(d2)] += d2;
                            norm += e * e;
                        }
                    }
                    (hist, norm)
                },
            )
            .collect();
        let mut hist = vec![0.0; BINS];
        let mut norm_sq = 0.0;
        for (h, nrm) in &parts {
            for (a, b) in hist.iter_mut().zip(h) {
                *a += b;
            }
            norm_sq += nrm;
        }
        let budget = tolerance * tolerance * norm_sq;
        // Keep the bins from `keep_from` up: the lowest bins whose sum is within the budget are
        // dropped (bin 0 holds the exact zeros).
        let (mut keep_from, mut dropped) = (0usize, 0.0);
        for (b, &h) in hist.iter().enumerate() {
            if dropped + h > budget {
                break;
            }
            dropped += h;
            keep_from = b + 1;
        }
        // Pass 2: the kept differences and each column's sums of `R~`.
        let kept: Vec<(Vec<(u32, f64)>, ColumnSums)> = (0..n)
            .into_par_iter()
            .map_init(
                || vec![u32::MAX; m],
                |pos, j| {
                    let mut c = Vec::new();
                    let mut sums = ColumnSums::default();
                    for (r, e, v) in entries(j, pos) {
                        let d = e - v;
                        if bin_of(d * d) >= keep_from {
                            c.push((r, d));
                            sums.add(1, e);
                        } else {
                            sums.add(1, v);
                        }
                    }
                    (c, sums)
                },
            )
            .collect();
        let mut correction = Correction {
            col_start: Vec::with_capacity(n + 1),
            ..Default::default()
        };
        correction.col_start.push(0);
        let mut column_sums = Vec::with_capacity(n);
        for (c, sums) in kept {
            for (r, d) in c {
                correction.col_rows.push(r);
                correction.col_vals.push(d);
            }
            correction.col_start.push(correction.col_rows.len());
            column_sums.push(sums);
        }
        // The row copy for `C t`.
        let mut row_start = vec![0usize; m + 1];
        for &r in &correction.col_rows {
            row_start[r as usize + 1] += 1;
        }
        for k in 0..m {
            row_start[k + 1] += row_start[k];
        }
        let mut fill = row_start.clone();
        let total = correction.col_rows.len();
        let (mut row_cols, mut row_vals) = (vec![0u32; total], vec![0.0; total]);
        for j in 0..n {
            for k in correction.col_start[j]..correction.col_start[j + 1] {
                let r = correction.col_rows[k] as usize;
                row_cols[fill[r]] = j as u32;
                row_vals[fill[r]] = correction.col_vals[k];
                fill[r] += 1;
            }
        }
        correction.row_start = row_start;
        correction.row_cols = row_cols;
        correction.row_vals = row_vals;
        let estimated_error = if norm_sq > 0.0 {
            (dropped / norm_sq).sqrt()
        } else {
            0.0
        };
        Ok(Self {
            terms,
            weights,
            correction,
            columns: ColumnStats::new(m, column_sums),
            estimated_error,
            reference_mm,
            oversampling,
            exact_nnz: exact.nnz(),
            m,
            work: Mutex::new((vec![0.0; n], vec![0.0; m.max(n)])),
        })
    }

    /// Relative operator error `||R~ - R||_F / ||R||_F` over every entry (the differences the
    /// correction dropped; within the build's tolerance).
    pub fn estimated_error(&self) -> f64 {
        self.estimated_error
    }

    /// Entries of the exact correction `C`.
    pub fn correction_nnz(&self) -> usize {
        self.correction.col_vals.len()
    }

    /// `C`'s entries over the exact `R`'s non-zeros.
    pub fn correction_share(&self) -> f64 {
        self.correction_nnz() as f64 / self.exact_nnz.max(1) as f64
    }

    /// The reference stretch length of the derivative kernels, mm.
    pub fn reference_mm(&self) -> f64 {
        self.reference_mm
    }

    /// The spreading operators' oversampling.
    pub fn oversampling(&self) -> usize {
        self.oversampling
    }

    /// Fine lattice nodes of one spreading operator (its FFT size is the cost model's).
    pub fn nodes(&self) -> usize {
        self.terms[0].nodes()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, (Vec<f64>, Vec<f64>)> {
        self.work.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl<'a, T: InfluenceFunction + ?Sized> DirectionKernel<'a, T> {
    /// The kernel less the TIF itself (an empty stretch).
    fn minus_point(mut self) -> Self {
        self.parts.push((-1.0, vec![[0.0, 0.0, 1.0]], Vec::new()));
        self
    }
}

impl LinearOperator for ExpansionOperator {
    fn nrows(&self) -> usize {
        self.m
    }

    fn ncols(&self) -> usize {
        self.weights[0].len()
    }

    fn products_cheap_per_dwell_point(&self) -> bool {
        true
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (wt, part) = &mut *work;
        let part = &mut part[..self.m];
        self.terms[0].apply(t, out);
        for k in 0..3 {
            wt.par_iter_mut()
                .zip(t.par_iter().zip(self.weights[k].par_iter()))
                .with_min_len(4096)
                .for_each(|(o, (a, b))| *o = a * b);
            self.terms[k + 1].apply(wt, part);
            out.par_iter_mut()
                .zip(part.par_iter())
                .with_min_len(4096)
                .for_each(|(o, p)| *o += p);
        }
        let c = &self.correction;
        add_compressed_product(&c.row_start, &c.row_cols, &c.row_vals, t, out, 1024);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        let mut work = self.lock();
        let (part, _) = &mut *work;
        self.terms[0].apply_transpose(y, out);
        for k in 0..3 {
            self.terms[k + 1].apply_transpose(y, part);
            out.par_iter_mut()
                .zip(part.par_iter().zip(self.weights[k].par_iter()))
                .with_min_len(4096)
                .for_each(|(o, (p, w))| *o += w * p);
        }
        let c = &self.correction;
        add_compressed_product(&c.col_start, &c.col_rows, &c.col_vals, y, out, 256);
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.columns.centred_norms_sq()
    }
}

/// `out[k] += Σ_e vals[e] x[index[e]]` over the entries `e` in `start[k]..start[k + 1]`: the
/// correction's product by rows (CSR) or, with its columns, its transpose (CSC).
fn add_compressed_product(
    start: &[usize],
    index: &[u32],
    vals: &[f64],
    x: &[f64],
    out: &mut [f64],
    min_len: usize,
) {
    out.par_iter_mut()
        .enumerate()
        .with_min_len(min_len)
        .for_each(|(k, o)| {
            let range = start[k]..start[k + 1];
            let acc: f64 = vals[range.clone()]
                .iter()
                .zip(&index[range])
                .map(|(v, &i)| v * x[i as usize])
                .sum();
            *o += acc;
        });
}

impl InfluenceOperator for ExpansionOperator {
    fn kind(&self) -> OperatorKind {
        OperatorKind::Expansion
    }

    fn shape(&self) -> (usize, usize) {
        (self.m, self.weights[0].len())
    }

    fn nnz(&self) -> usize {
        self.exact_nnz
    }

    fn empty_columns(&self) -> Vec<usize> {
        self.columns.empty_columns()
    }

    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::assemble_swept;
    use crate::observer::Silent;
    use crate::path::DwellPath;
    use crate::tif::GaussianTif;

    /// A 30 mm disc at 0.5 mm and a spiral of pitch 1 mm to 18 mm, off the lattice.
    fn case() -> (Vec<f64>, Vec<f64>, DwellPath) {
        let (mut mx, mut my) = (vec![], vec![]);
        for j in -30..=30 {
            for i in -30..=30 {
                let (x, y) = (0.5 * i as f64, 0.5 * j as f64);
                if x * x + y * y <= 225.0 {
                    mx.push(x);
                    my.push(y);
                }
            }
        }
        let (mut px, mut py) = (vec![0.013], vec![-0.021]);
        let (pitch, step) = (1.0, 1.0);
        let mut theta: f64 = 0.5;
        loop {
            let r = pitch * theta / std::f64::consts::TAU;
            if r > 18.0 {
                break;
            }
            px.push(0.013 + r * theta.cos());
            py.push(-0.021 + r * theta.sin());
            theta += step / r.max(step);
        }
        (mx, my, DwellPath::new(px, py).unwrap())
    }

    fn dense_error(op: &ExpansionOperator, exact: &InfluenceMatrix) -> f64 {
        let (m, n) = (op.nrows(), op.ncols());
        let (mut err, mut norm) = (0.0, 0.0);
        let mut e = vec![0.0; n];
        let mut col = vec![0.0; m];
        for j in 0..n {
            e[j] = 1.0;
            op.apply(&e, &mut col);
            e[j] = 0.0;
            let mut want = vec![0.0; m];
            let c = exact.csc().col(j);
            for (&i, &v) in c.row_indices().iter().zip(c.values()) {
                want[i] = v;
            }
            for i in 0..m {
                err += (col[i] - want[i]).powi(2);
                norm += want[i].powi(2);
            }
        }
        (err / norm).sqrt()
    }

    fn build(cut_sigmas: f64, tolerance: f64) -> (ExpansionOperator, InfluenceMatrix) {
        let (mx, my, path) = case();
        let tif = GaussianTif::new(3.0, 10.0, 3.0 * cut_sigmas).unwrap();
        let stretches = Stretches::of_path(&path, tif.support_radius_mm() / 64.0).unwrap();
        let exact = assemble_swept(&mx, &my, &path, &stretches, &tif, &Silent).unwrap();
        let shapes = ColumnShape::of(path.x_mm(), path.y_mm(), Some(&stretches));
        let op =
            ExpansionOperator::new(&mx, &my, &shapes, &exact, 0.5, 1, &tif, tolerance).unwrap();
        (op, exact)
    }

    /// Products and transpose products against the exact swept `R` on a small spiral, with a
    /// Gaussian cut at 3 sigma (a 1.1% jump): the reported error bounds the measured one.
    #[test]
    fn products_match_the_exact_swept_matrix_within_the_reported_error() {
        for tolerance in [1e-3, 1e-4, 1e-6] {
            let (op, exact) = build(3.0, tolerance);
            let measured = dense_error(&op, &exact);
            assert!(
                op.estimated_error() <= tolerance,
                "{}",
                op.estimated_error()
            );
            assert!(
                measured <= op.estimated_error() * 1.0001 + 1e-12,
                "tolerance {tolerance}: measured {measured} above the reported {}",
                op.estimated_error()
            );
            // Transpose: y' (R~ t) = (R~^T y)' t, and R~^T y against the exact R^T y.
            let (m, n) = (op.nrows(), op.ncols());
            let t: Vec<f64> = (0..n).map(|j| ((j * 7919) % 13) as f64 * 0.1).collect();
            let y: Vec<f64> = (0..m).map(|i| ((i * 104729) % 17) as f64 - 8.0).collect();
            let (mut rt, mut rty) = (vec![0.0; m], vec![0.0; n]);
            op.apply(&t, &mut rt);
            op.apply_transpose(&y, &mut rty);
            let lhs: f64 = rt.iter().zip(&y).map(|(a, b)| a * b).sum();
            let rhs: f64 = rty.iter().zip(&t).map(|(a, b)| a * b).sum();
            assert!(
                (lhs - rhs).abs() <= 1e-10 * lhs.abs().max(1.0),
                "{lhs} vs {rhs}"
            );
            let mut want = vec![0.0; n];
            let csc = exact.csc();
            for (j, w) in want.iter_mut().enumerate() {
                let c = csc.col(j);
                *w = c
                    .row_indices()
                    .iter()
                    .zip(c.values())
                    .map(|(&i, v)| v * y[i])
                    .sum();
            }
            let diff: f64 = want.iter().zip(&rty).map(|(a, b)| (a - b).powi(2)).sum();
            let size: f64 = want.iter().map(|a| a * a).sum();
            assert!((diff / size).sqrt() < 10.0 * tolerance.max(1e-9));
        }
    }

    /// The expansion itself carries a smooth TIF: with a Gaussian cut where it is negligible, few
    /// entries need the correction at the default tolerance.
    #[test]
    fn a_smooth_tif_needs_few_corrections() {
        let (op, exact) = build(5.0, 1e-4);
        assert!(dense_error(&op, &exact) <= 1e-4);
        assert!(op.correction_share() < 0.1, "{}", op.correction_share());
        let (cut, _) = build(3.0, 1e-4);
        assert!(cut.correction_share() > op.correction_share());
    }

    /// Bit-identical products for any thread count.
    #[test]
    fn products_do_not_depend_on_the_thread_count() {
        let (op, _) = build(3.0, 1e-4);
        let t: Vec<f64> = (0..op.ncols()).map(|j| (j % 7) as f64).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut out = vec![0.0; op.nrows()];
                op.apply(&t, &mut out);
                let mut back = vec![0.0; op.ncols()];
                op.apply_transpose(&out, &mut back);
                (out, back)
            })
        };
        assert_eq!(run(1), run(3));
    }
}
