//! The point influence model: `R[i, j] = f(x_i - X_j, y_i - Y_j)`, the TIF `f` (nm/s) at the offset
//! between measurement point `i` and dwell point `j` (Preston's law with the tool held at the
//! dwell point), assembled as the sparse [`InfluenceMatrix`].
//!
//! Assembly visits, for every dwell point, only the measurement points inside the TIF's support
//! radius, found with a strip index over the map. Two parallel passes (rayon): the first counts
//! the points inside each dwell point's disc, which sizes the arrays once; the second fills every
//! column in place. The matrix is identical for any thread count.

use crate::error::{Error, Result};
use crate::influence::operator::matrix::{InfluenceMatrix, NNZ_BYTES};
use crate::observer::{Observer, Stage};
use crate::tif::InfluenceFunction;
use nalgebra_sparse::CscMatrix;
use rayon::prelude::*;

/// Dwell columns handled by one rayon task.
const COLUMNS_PER_TASK: usize = 64;

impl InfluenceMatrix {
    /// Assembles `R[i, j] = tif(x_i - X_j, y_i - Y_j)` for map points `(x_i, y_i)` and dwell points
    /// `(X_j, Y_j)`, keeping only non-zero entries.
    pub fn assemble<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        tif: &T,
        observer: &dyn Observer,
    ) -> Result<Self> {
        Self::assemble_with(
            map_x_mm,
            map_y_mm,
            dwell_x_mm,
            dwell_y_mm,
            tif.support_radius_mm(),
            |_j, _i, dx, dy| tif.rate_nm_per_s(dx, dy),
            observer,
        )
    }

    /// Assembles with a general kernel `rate(j, i, dx_mm, dy_mm)` (nm/s) for dwell point `j` and
    /// measurement point `i` at plan offset `(dx, dy) = (x_i - X_j, y_i - Y_j)`; only pairs within
    /// `search_radius_mm` in the plan are visited. Per-dwell-point TIFs and tangent-frame offsets on
    /// curved parts use this entry point.
    pub fn assemble_with<K>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        search_radius_mm: f64,
        kernel: K,
        observer: &dyn Observer,
    ) -> Result<Self>
    where
        K: Fn(usize, usize, f64, f64) -> f64 + Sync,
    {
        let m = map_x_mm.len();
        let n = dwell_x_mm.len();
        if map_y_mm.len() != m {
            return Err(Error::LengthMismatch {
                what: "map y_mm",
                got: map_y_mm.len(),
                expected: m,
            });
        }
        if dwell_y_mm.len() != n {
            return Err(Error::LengthMismatch {
                what: "dwell y_mm",
                got: dwell_y_mm.len(),
                expected: n,
            });
        }
        if !(search_radius_mm.is_finite() && search_radius_mm > 0.0) {
            return Err(Error::invalid(
                "TIF support radius",
                format!("must be positive and finite, got {search_radius_mm} mm"),
            ));
        }
        let index = StripIndex::new(map_x_mm, map_y_mm, search_radius_mm);
        observer.start(Stage::Assembly, n as u64);
        let r2 = search_radius_mm * search_radius_mm;

        // Pass 1: count the map points inside each dwell point's disc (an upper bound on the
        // column's non-zeros), so the matrix is allocated once and filled in place.
        let candidates: Vec<usize> = (0..n)
            .into_par_iter()
            .with_min_len(COLUMNS_PER_TASK)
            .map(|j| {
                let (cx, cy) = (dwell_x_mm[j], dwell_y_mm[j]);
                let mut count = 0usize;
                index.for_each_near(cx, cy, search_radius_mm, |_, px, py| {
                    let (dx, dy) = (px - cx, py - cy);
                    count += usize::from(dx * dx + dy * dy <= r2);
                });
                count
            })
            .collect();
        let mut bound_offsets = Vec::with_capacity(n + 1);
        bound_offsets.push(0usize);
        for &c in &candidates {
            bound_offsets.push(bound_offsets[bound_offsets.len() - 1] + c);
        }
        let capacity = bound_offsets[n];
        crate::budget::check(
            "influence matrix R",
            &format!(
                "{capacity} candidate non-zeros ({n} dwell points, map points within \
                 {search_radius_mm} mm of each) x {NNZ_BYTES} bytes (CSC and its row-major copy)"
            ),
            capacity as f64 * NNZ_BYTES,
        )?;

        // Pass 2: every task fills its own slice of the arrays (zeroed pages are touched first by
        // the thread that writes them); entries equal to zero are dropped, so a column may end
        // before its bound.
        let mut row_indices = vec![0usize; capacity];
        let mut values = vec![0.0f64; capacity];
        let mut tasks = Vec::with_capacity(n.div_ceil(COLUMNS_PER_TASK));
        {
            let (mut rows_rest, mut values_rest) = (&mut row_indices[..], &mut values[..]);
            let mut first = 0;
            while first < n {
                let last = (first + COLUMNS_PER_TASK).min(n);
                let len = bound_offsets[last] - bound_offsets[first];
                let (rows_here, rows_next) = std::mem::take(&mut rows_rest).split_at_mut(len);
                let (values_here, values_next) = std::mem::take(&mut values_rest).split_at_mut(len);
                tasks.push((first..last, rows_here, values_here));
                rows_rest = rows_next;
                values_rest = values_next;
                first = last;
            }
        }
        let column_lengths: Vec<Vec<usize>> = tasks
            .into_par_iter()
            .map(|(columns, rows, vals)| {
                let count = columns.len();
                // Cancelled: the remaining columns are left empty, and no matrix is returned.
                if observer.cancelled() {
                    return vec![0; count];
                }
                let lengths = fill_columns(
                    &index,
                    dwell_x_mm,
                    dwell_y_mm,
                    columns,
                    &bound_offsets,
                    search_radius_mm,
                    &kernel,
                    rows,
                    vals,
                );
                observer.advance(Stage::Assembly, count as u64);
                lengths
            })
            .collect();
        crate::observer::check_cancelled(observer)?;

        // Close the gaps left by dropped zeros (none for a Gaussian inside its truncation radius).
        let mut col_offsets = Vec::with_capacity(n + 1);
        col_offsets.push(0usize);
        let mut end = 0usize;
        for (j, len) in column_lengths.into_iter().flatten().enumerate() {
            let from = bound_offsets[j];
            if from != end {
                row_indices.copy_within(from..from + len, end);
                values.copy_within(from..from + len, end);
            }
            end += len;
            col_offsets.push(end);
        }
        row_indices.truncate(end);
        values.truncate(end);
        observer.finish(Stage::Assembly);
        let csc =
            CscMatrix::try_from_csc_data(m, n, col_offsets, row_indices, values).map_err(|e| {
                Error::Numerical {
                    stage: "influence assembly",
                    why: e.to_string(),
                }
            })?;
        Ok(Self::from_csc(csc))
    }
}

/// Fills the columns `columns` into `rows` / `vals`, the slices of the matrix arrays that start
/// at `bound_offsets[columns.start]`; column `j` starts at `bound_offsets[j]` and may hold up to
/// `bound_offsets[j + 1] - bound_offsets[j]` entries. Returns each column's number of non-zeros.
#[allow(clippy::too_many_arguments)]
fn fill_columns<K>(
    index: &StripIndex,
    dwell_x: &[f64],
    dwell_y: &[f64],
    columns: std::ops::Range<usize>,
    bound_offsets: &[usize],
    radius: f64,
    kernel: &K,
    rows: &mut [usize],
    vals: &mut [f64],
) -> Vec<usize>
where
    K: Fn(usize, usize, f64, f64) -> f64 + Sync,
{
    let base = bound_offsets[columns.start];
    let mut lengths = Vec::with_capacity(columns.len());
    let mut order: Vec<usize> = Vec::new();
    let mut sorted_rows: Vec<usize> = Vec::new();
    let mut sorted_values: Vec<f64> = Vec::new();
    let r2 = radius * radius;
    for j in columns {
        let (cx, cy) = (dwell_x[j], dwell_y[j]);
        let (start, stop) = (bound_offsets[j] - base, bound_offsets[j + 1] - base);
        let column_rows = &mut rows[start..stop];
        let column_vals = &mut vals[start..stop];
        let mut len = 0usize;
        index.for_each_near(cx, cy, radius, |i, px, py| {
            let dx = px - cx;
            let dy = py - cy;
            if dx * dx + dy * dy <= r2 {
                let v = kernel(j, i, dx, dy);
                if v != 0.0 {
                    if let (Some(r), Some(x)) = (column_rows.get_mut(len), column_vals.get_mut(len))
                    {
                        *r = i;
                        *x = v;
                        len += 1;
                    }
                }
            }
        });
        // Rows come out ascending for a row-major map; sort the column otherwise.
        let (column_rows, column_vals) = (&mut column_rows[..len], &mut column_vals[..len]);
        if !column_rows.windows(2).all(|w| w[0] < w[1]) {
            order.clear();
            order.extend(0..len);
            order.sort_unstable_by_key(|&e| column_rows[e]);
            sorted_rows.clear();
            sorted_values.clear();
            sorted_rows.extend(order.iter().map(|&e| column_rows[e]));
            sorted_values.extend(order.iter().map(|&e| column_vals[e]));
            column_rows.copy_from_slice(&sorted_rows);
            column_vals.copy_from_slice(&sorted_values);
        }
        lengths.push(len);
    }
    lengths
}

/// Map points bucketed into horizontal strips; within a strip sorted by x (then by index), so a
/// disc query is one binary search per strip. For a row-major map (y-major, x ascending) the
/// visited indices come out ascending and need no sort.
pub(crate) struct StripIndex {
    y0: f64,
    strip_height: f64,
    strip_start: Vec<usize>,
    xs: Vec<f64>,
    ys: Vec<f64>,
    ids: Vec<usize>,
}

impl StripIndex {
    pub(crate) fn new(x: &[f64], y: &[f64], radius: f64) -> Self {
        let m = x.len();
        let (y_lo, y_hi) = y
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let (x_lo, x_hi) = x
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        if m == 0 || y_hi.is_nan() || y_hi < y_lo {
            return Self {
                y0: 0.0,
                strip_height: 1.0,
                strip_start: vec![0, 0],
                xs: Vec::new(),
                ys: Vec::new(),
                ids: Vec::new(),
            };
        }
        // Strip height near the mean point spacing, between radius/64 and radius.
        let area = ((x_hi - x_lo).max(radius) * (y_hi - y_lo).max(radius)).max(f64::MIN_POSITIVE);
        let spacing = (area / m as f64).sqrt();
        let strip_height = spacing.clamp(radius / 64.0, radius);
        let n_strips = (((y_hi - y_lo) / strip_height).floor() as usize).saturating_add(1);
        let strip_of = |v: f64| -> usize {
            (((v - y_lo) / strip_height).floor().max(0.0) as usize).min(n_strips - 1)
        };
        let mut counts = vec![0usize; n_strips + 1];
        for &v in y {
            counts[strip_of(v) + 1] += 1;
        }
        for s in 0..n_strips {
            counts[s + 1] += counts[s];
        }
        let strip_start = counts.clone();
        let mut fill = counts;
        let mut ids = vec![0usize; m];
        for (i, &v) in y.iter().enumerate() {
            let s = strip_of(v);
            ids[fill[s]] = i;
            fill[s] += 1;
        }
        for s in 0..n_strips {
            ids[strip_start[s]..strip_start[s + 1]]
                .sort_by(|&a, &b| x[a].total_cmp(&x[b]).then(a.cmp(&b)));
        }
        let xs = ids.iter().map(|&i| x[i]).collect();
        let ys = ids.iter().map(|&i| y[i]).collect();
        Self {
            y0: y_lo,
            strip_height,
            strip_start,
            xs,
            ys,
            ids,
        }
    }

    /// Calls `f(index, x, y)` for every point whose strip and x-range can lie within `radius` of
    /// `(cx, cy)` (a superset of the disc; callers test the distance).
    #[inline]
    pub(crate) fn for_each_near(
        &self,
        cx: f64,
        cy: f64,
        radius: f64,
        mut f: impl FnMut(usize, f64, f64),
    ) {
        let n_strips = self.strip_start.len() - 1;
        let lo = ((cy - radius - self.y0) / self.strip_height).floor();
        let hi = ((cy + radius - self.y0) / self.strip_height).floor();
        if lo.is_nan() || hi.is_nan() || hi < 0.0 || lo >= n_strips as f64 || lo > hi {
            return;
        }
        let s0 = lo.max(0.0) as usize;
        let s1 = (hi as usize).min(n_strips - 1);
        for s in s0..=s1 {
            let band_lo = self.y0 + s as f64 * self.strip_height;
            let band_hi = band_lo + self.strip_height;
            let dy = if cy < band_lo {
                band_lo - cy
            } else if cy > band_hi {
                cy - band_hi
            } else {
                0.0
            };
            if dy > radius {
                continue;
            }
            let half = (radius * radius - dy * dy).max(0.0).sqrt();
            let (a, b) = (self.strip_start[s], self.strip_start[s + 1]);
            let xs = &self.xs[a..b];
            let first = xs.partition_point(|&x| x < cx - half);
            let last = xs.partition_point(|&x| x <= cx + half);
            for k in a + first..a + last {
                f(self.ids[k], self.xs[k], self.ys[k]);
            }
        }
    }
}

/// Map points summed by one rayon task in the direct sums ([`sum_near`]).
pub(crate) const POINTS_PER_TASK: usize = 256;

/// The map's y, the dwell points' y and the dwell times against the `m` map and `n` dwell x.
pub(crate) fn check_lengths(
    m: usize,
    n: usize,
    map_y_mm: &[f64],
    dwell_y_mm: &[f64],
    dwell_s: &[f64],
) -> Result<()> {
    for (what, got, expected) in [
        ("map y_mm", map_y_mm.len(), m),
        ("dwell y_mm", dwell_y_mm.len(), n),
        ("dwell_s", dwell_s.len(), n),
    ] {
        if got != expected {
            return Err(Error::LengthMismatch {
                what,
                got,
                expected,
            });
        }
    }
    Ok(())
}

/// The traversal of the pairs the direct sums share (the removal of a motion summed without
/// assembling `R`, [`crate::simulate::direct`], and on a curved part
/// [`super::surface::removals_on_surface_with`]): for every map point `i`, each dwell point
/// `j` within `search_radius_mm` of it in plan, in the strip index's fixed order, calls
/// `add(i, j, x_i - X_j, y_i - Y_j, sums)` with map point `i`'s `kernels` sums. Each map point is
/// summed by one task, so the sums do not depend on the thread count. Returns the sums kernel by
/// kernel. Lengths are the caller's to check. Once `observer` asks for a stop the remaining map
/// points are skipped: the caller then returns [`Error::Cancelled`], not the sums.
#[allow(clippy::too_many_arguments)]
pub(crate) fn sum_near<F>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    kernels: usize,
    search_radius_mm: f64,
    observer: &dyn Observer,
    add: F,
) -> Vec<Vec<f64>>
where
    F: Fn(usize, usize, f64, f64, &mut [f64]) + Sync,
{
    let (m, n, k) = (map_x_mm.len(), dwell_x_mm.len(), kernels);
    if k == 0 {
        return Vec::new();
    }
    observer.start(Stage::Assembly, n as u64);
    let index = StripIndex::new(dwell_x_mm, dwell_y_mm, search_radius_mm);
    // Point-major: the k sums of map point i at i * k.
    let mut h = vec![0.0; m * k];
    h.par_chunks_mut(POINTS_PER_TASK * k)
        .enumerate()
        .for_each(|(c, chunk)| {
            if observer.cancelled() {
                return;
            }
            for (p, sums) in chunk.chunks_mut(k).enumerate() {
                let i = c * POINTS_PER_TASK + p;
                let (px, py) = (map_x_mm[i], map_y_mm[i]);
                index.for_each_near(px, py, search_radius_mm, |j, cx, cy| {
                    add(i, j, px - cx, py - cy, sums);
                });
            }
        });
    observer.advance(Stage::Assembly, n as u64);
    observer.finish(Stage::Assembly);
    (0..k)
        .map(|t| h.iter().skip(t).step_by(k).copied().collect())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::test_support::scattered;
    use crate::tif::{GaussianTif, GridTif};

    #[test]
    fn entries_equal_direct_tif_and_nnz_matches_brute_force() {
        let (mx, my) = scattered(700, 1);
        let (dx, dy) = scattered(90, 2);
        let tif = GaussianTif::new(1.0, 5.0, 2.5).unwrap();
        let r = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        let mut brute = 0;
        for j in 0..dx.len() {
            for i in 0..mx.len() {
                let v = tif.rate_nm_per_s(mx[i] - dx[j], my[i] - dy[j]);
                if v != 0.0 {
                    brute += 1;
                }
                let got = r
                    .csc()
                    .get_entry(i, j)
                    .map(|e| e.into_value())
                    .unwrap_or(0.0);
                assert_eq!(got, v, "entry ({i},{j})");
            }
        }
        assert_eq!(r.nnz(), brute);
        assert!(brute > 1000);
    }

    #[test]
    fn grid_tif_on_grid_map_matches_brute_force() {
        // Row-major 41 x 21 map at 0.5 mm, a 5 x 5 pyramid-ish TIF at pitch 0.7 mm.
        let mut mx = Vec::new();
        let mut my = Vec::new();
        for iy in 0..21 {
            for ix in 0..41 {
                mx.push(ix as f64 * 0.5);
                my.push(iy as f64 * 0.5);
            }
        }
        let rates: Vec<f64> = (0..25)
            .map(|k| {
                let (ix, iy) = ((k % 5) as f64 - 2.0, (k / 5) as f64 - 2.0);
                (3.0 - ix.abs() - iy.abs()).max(0.0)
            })
            .collect();
        let tif = GridTif::new(-1.4, -1.4, 0.7, 0.7, 5, 5, rates).unwrap();
        let (dx, dy) = scattered(60, 7);
        let r = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        let mut brute = 0;
        for j in 0..dx.len() {
            for i in 0..mx.len() {
                let v = tif.rate_nm_per_s(mx[i] - dx[j], my[i] - dy[j]);
                brute += usize::from(v != 0.0);
                let got = r
                    .csc()
                    .get_entry(i, j)
                    .map(|e| e.into_value())
                    .unwrap_or(0.0);
                assert_eq!(got, v);
            }
        }
        assert_eq!(r.nnz(), brute);
    }

    #[test]
    fn far_dwell_points_give_empty_columns() {
        let mx = vec![0.0, 1.0];
        let my = vec![0.0, 0.0];
        let tif = GaussianTif::new(1.0, 1.0, 3.0).unwrap();
        let r =
            InfluenceMatrix::assemble(&mx, &my, &[0.5, 100.0], &[0.0, 0.0], &tif, &Silent).unwrap();
        assert_eq!(r.empty_columns(), vec![1]);
    }
}
