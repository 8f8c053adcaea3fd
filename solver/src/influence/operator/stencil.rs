//! Exact matrix-free products for map points on a regular lattice and dwell points off it whose
//! positions within a lattice cell take few distinct values: a raster whose pitch is a rational
//! multiple of the map's (1 mm over a 0.32 mm map has 8 x 8 such phases, 0.5 mm over 0.36 mm
//! 18 x 18).
//!
//! With the map lattice of pitch `h` through `(x0, y0)`, dwell point `j` at
//! `X_j = x0 + (b_j + f_j) h` (cell `b_j`, phase `f_j` in `[0, 1)`; likewise in y) and a map point
//! in cell `p`, `R[i, j] = TIF((p - b_j - f_j) h)` (zero beyond the support radius `r`): column `j`
//! is its phase's stencil `S_f[d] = TIF((d - f) h)`, `|d - f| h <= r`, placed at cell `b_j`. The
//! operator tabulates one stencil per distinct phase pair and never forms `R`:
//! - `R t` scatters: each dwell point adds `t_j S_f` to a dense image of the lattice, one
//!   contiguous stencil row at a time. The image is cut into strips of rows, each filled by one
//!   task from the dwell points in row order, so every cell sums its terms in one fixed order
//!   (bit-identical for any thread count); the removal is read at the map cells.
//! - `R^T y` gathers: `y` is summed onto the image, and each dwell point takes the dot product of
//!   its stencil with the window under it.
//! - `R^T R t` keeps `R t` on the image, weighted by the number of map points in each cell, and
//!   gathers from there.
//!
//! A product does the work of the assembled matrix's non-zeros (about `n pi r^2 / h^2`
//! multiply-adds each way) without an index per entry, over contiguous rows that vectorise, from
//! tables small enough to stay in cache. Stencil rows are stored and read in whole groups of
//! four entries (zeros past the row's span), so both kernels run in four-lane registers with no
//! scalar remainder; each dot product of the gather keeps sixteen running sums (four groups of
//! four lanes), so that its additions do not wait on one another. The scatter and gather run
//! under `pulp`'s run-time dispatch, compiled for the CPU's widest vector instructions with the
//! same operations in the same order (so with the same results as a scalar build).
//!
//! **Against the assembled `R`.** Phases are rounded to `1 / 2^24` of a cell, so each dwell point
//! moves by at most `h 2^-25 sqrt 2` (1.5e-8 mm at 0.36 mm) and each entry by at most the TIF's
//! slope times that; a pair within that distance of a step of the TIF (the support circle, a
//! truncated Gaussian's cut) may be kept by one and not the other. Everything else is the
//! assembled contract, entry for entry.

use super::lattice::{lattice_index, off_lattice_error};
use super::{ColumnStats, ColumnSums, InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use crate::tif::InfluenceFunction;
use rayon::prelude::*;
use std::collections::HashMap;
use std::sync::Mutex;

/// Phases are rounded to `1 / PHASE_STEPS` of a lattice cell.
const PHASE_STEPS: i64 = 1 << 24;
/// A dwell point farther than this many cells from the map's lowest corner is refused (the
/// rounded position `u 2^24` must stay well inside `i64`).
const MAX_CELL_OFFSET: f64 = 1e9;
/// Largest stencil radius, cells.
const MAX_REACH_CELLS: usize = 2048;
/// Largest image of the lattice (cells) the operator accepts.
const MAX_IMAGE_CELLS: usize = 400_000_000;
/// Bytes per image cell: the image and the map-point count.
const IMAGE_BYTES_PER_CELL: f64 = 16.0;
/// Lattice rows per strip of the scatter (one rayon task each).
const STRIP_ROWS: usize = 16;
/// Minimum number of dwell points per rayon task in the gather.
const GATHER_TASK: usize = 32;
/// Stencil rows are read in whole groups of this many entries (zero beyond the row's span), so
/// that the kernels' loops have no scalar remainder; the tables and the image carry the slack.
const LANE_GROUP: usize = 4;
/// Zero columns after each stencil row and each image row, for the last group of a row.
const ROW_SLACK: usize = LANE_GROUP - 1;

/// The phase-stencil operator (see the module documentation).
pub struct StencilOperator {
    /// Image width (the lattice's span and [`ROW_SLACK`] empty columns) and height, cells.
    nx: usize,
    ny: usize,
    /// Stencil side `2 w + 1`, cells (`w = ceil(r / h)`).
    side: usize,
    /// Length of a stored stencil row: `side` and [`ROW_SLACK`] zeros.
    stride: usize,
    /// The stencils, one block of `side` rows of `stride` entries per phase class.
    stencils: Vec<f64>,
    /// Per class and stencil row, the columns `[lo, hi)` read: the span that may be non-zero,
    /// lengthened with zeros to whole groups of [`LANE_GROUP`].
    spans: Vec<(usize, usize)>,
    /// Number of phase classes.
    classes: usize,
    /// Each dwell point's phase class.
    dwell_class: Vec<usize>,
    /// Each dwell point's stencil corner: image column and row of the stencil's entry `(0, 0)`.
    dwell_corner: Vec<(usize, usize)>,
    /// Dwell points ordered by stencil corner row (then index), and those rows.
    by_row: Vec<usize>,
    by_row_rows: Vec<usize>,
    /// Each map point's image cell.
    map_cells: Vec<usize>,
    /// Map points ordered by cell (then index), and those cells.
    by_cell: Vec<usize>,
    by_cell_cells: Vec<usize>,
    /// Map points per image cell.
    cell_count: Vec<f64>,
    /// Each column's sums over the map points (non-zeros, Jacobi scaling).
    columns: ColumnStats,
    /// The image every product works in.
    image: Mutex<Vec<f64>>,
    /// The widest vector instructions this CPU has, detected once: the kernels run compiled
    /// for them (the same operations in the same order, so the same results as without).
    arch: pulp::Arch,
}

impl std::fmt::Debug for StencilOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StencilOperator")
            .field("image", &(self.nx, self.ny))
            .field("side", &self.side)
            .field("classes", &self.classes)
            .field("m", &self.map_cells.len())
            .field("n", &self.dwell_class.len())
            .finish()
    }
}

/// A dwell coordinate's cell and rounded phase (in `1 / PHASE_STEPS`) on the lattice of pitch
/// `pitch` through `origin`; `None` when not finite or too far out.
fn cell_and_phase(v: f64, origin: f64, pitch: f64) -> Option<(i64, i64)> {
    let u = (v - origin) / pitch;
    if !(u.is_finite() && u.abs() <= MAX_CELL_OFFSET) {
        return None;
    }
    let q = (u * PHASE_STEPS as f64).round() as i64;
    Some((q.div_euclid(PHASE_STEPS), q.rem_euclid(PHASE_STEPS)))
}

/// A dwell point's cell and rounded phase along x and y (see [`cell_and_phase`]) on the lattice
/// through `(x0, y0)`.
fn dwell_cell_and_phase(
    (x, y): (f64, f64),
    (x0, y0): (f64, f64),
    pitch: f64,
) -> Option<((i64, i64), (i64, i64))> {
    let (bx, fx) = cell_and_phase(x, x0, pitch)?;
    let (by, fy) = cell_and_phase(y, y0, pitch)?;
    Some(((bx, by), (fx, fy)))
}

/// The map's lowest x and y: the lattice runs through them.
pub(crate) fn lattice_origin(map_x_mm: &[f64], map_y_mm: &[f64]) -> (f64, f64) {
    (
        map_x_mm.iter().copied().fold(f64::INFINITY, f64::min),
        map_y_mm.iter().copied().fold(f64::INFINITY, f64::min),
    )
}

impl StencilOperator {
    /// The number of distinct phase pairs of the dwell points on the map's lattice of pitch
    /// `pitch_mm` (through the map's lowest x and y), or `None` once it passes `limit` or a dwell
    /// point is not finite: what the stencil tables would hold, counted without building them.
    pub fn phase_classes(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        limit: usize,
    ) -> Option<usize> {
        let origin = lattice_origin(map_x_mm, map_y_mm);
        let mut seen = std::collections::HashSet::new();
        for (&x, &y) in dwell_x_mm.iter().zip(dwell_y_mm) {
            let (_, phase) = dwell_cell_and_phase((x, y), origin, pitch_mm)?;
            seen.insert(phase);
            if seen.len() > limit {
                return None;
            }
        }
        Some(seen.len())
    }

    /// Builds the operator for map points `(x, y)` on the lattice of pitch `pitch_mm` through
    /// their lowest x and y, dwell points `(X, Y)` anywhere, and `tif`; an error naming the point
    /// when a map point is off the lattice, and when the image or the tables would exceed the
    /// memory limit.
    pub fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        tif: &T,
    ) -> Result<Self> {
        if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
            return Err(Error::invalid("lattice pitch", format!("{pitch_mm}")));
        }
        for (what, got, expected) in [
            ("map y_mm", map_y_mm.len(), map_x_mm.len()),
            ("dwell y_mm", dwell_y_mm.len(), dwell_x_mm.len()),
        ] {
            if got != expected {
                return Err(Error::LengthMismatch {
                    what,
                    got,
                    expected,
                });
            }
        }
        if map_x_mm.is_empty() || dwell_x_mm.is_empty() {
            return Err(Error::invalid(
                "stencil operator",
                "needs map and dwell points",
            ));
        }
        let radius = tif.support_radius_mm();
        let w = stencil_reach(radius, pitch_mm)?;
        let side = 2 * w + 1;
        let (x0, y0) = lattice_origin(map_x_mm, map_y_mm);
        let map_ij = map_indices((map_x_mm, map_y_mm), (x0, y0), pitch_mm)?;
        let PhaseClasses {
            phases,
            dwell_class,
            dwell_base,
        } = PhaseClasses::of((dwell_x_mm, dwell_y_mm), (x0, y0), pitch_mm)?;
        let classes = phases.len();
        crate::budget::check_f64s(
            "dwell points (stencil operator)",
            &format!(
                "{classes} distinct positions within a {pitch_mm} mm cell, a stencil of \
                 {side} x {side} cells each"
            ),
            classes as f64 * (side * side) as f64,
            1.0,
        )?;
        let wi = w as i64;
        let ((lo_x, lo_y), (nx, ny)) = image_extent(&map_ij, &dwell_base, w, pitch_mm)?;

        // One stencil per phase class: S_f[b][a] = TIF(((a - w) - fx) h, ((b - w) - fy) h).
        let stride = side + ROW_SLACK;
        let (stencils, spans) = tabulate_stencils(tif, &phases, w, pitch_mm);

        let cell_of = |(a, b): (i64, i64)| (b - lo_y) as usize * nx + (a - lo_x) as usize;
        let map_cells: Vec<usize> = map_ij.iter().map(|&p| cell_of(p)).collect();
        let mut cell_count = vec![0.0; nx * ny];
        for &c in &map_cells {
            cell_count[c] += 1.0;
        }
        let mut by_cell: Vec<usize> = (0..map_cells.len()).collect();
        by_cell.sort_by_key(|&i| map_cells[i]);
        let by_cell_cells: Vec<usize> = by_cell.iter().map(|&i| map_cells[i]).collect();
        let dwell_corner: Vec<(usize, usize)> = dwell_base
            .iter()
            .map(|&(a, b)| ((a - wi - lo_x) as usize, (b - wi - lo_y) as usize))
            .collect();
        let mut by_row: Vec<usize> = (0..dwell_corner.len()).collect();
        by_row.sort_by_key(|&j| dwell_corner[j].1);
        let by_row_rows: Vec<usize> = by_row.iter().map(|&j| dwell_corner[j].1).collect();

        let mut op = Self {
            nx,
            ny,
            side,
            stride,
            stencils,
            spans,
            classes,
            dwell_class,
            dwell_corner,
            by_row,
            by_row_rows,
            map_cells,
            by_cell,
            by_cell_cells,
            cell_count,
            columns: ColumnStats::default(),
            image: Mutex::new(vec![0.0; nx * ny]),
            arch: pulp::Arch::new(),
        };
        op.columns = ColumnStats::new(
            op.map_cells.len(),
            (0..op.dwell_class.len())
                .into_par_iter()
                .map(|j| op.column_sums(j))
                .collect(),
        );
        Ok(op)
    }

    /// Number of distinct phase pairs (stencils tabulated).
    pub fn phase_class_count(&self) -> usize {
        self.classes
    }

    /// Non-zero entries of the implicit matrix `R` (the number the sparse operator would store).
    pub fn nnz(&self) -> usize {
        self.columns.nnz()
    }

    /// Dwell points whose column is empty: no map point lies in the tool's reach.
    pub fn empty_columns(&self) -> Vec<usize> {
        self.columns.empty_columns()
    }

    /// Stencil row `b` of class `k`: its span start and its non-zero span of values.
    #[inline(always)]
    fn stencil_row(&self, k: usize, b: usize) -> (usize, &[f64]) {
        let (lo, hi) = self.spans[k * self.side + b];
        let start = (k * self.side + b) * self.stride;
        (lo, &self.stencils[start + lo..start + hi])
    }

    /// Column `j`'s sums over the map points.
    fn column_sums(&self, j: usize) -> ColumnSums {
        let (cx, cy) = self.dwell_corner[j];
        let mut sums = ColumnSums::default();
        for b in 0..self.side {
            let (lo, row) = self.stencil_row(self.dwell_class[j], b);
            let start = (cy + b) * self.nx + cx + lo;
            for (&v, &c) in row.iter().zip(&self.cell_count[start..start + row.len()]) {
                // Counts are small whole numbers, exact in both types.
                sums.add(c as u32, v);
            }
        }
        sums
    }

    /// `image = R t` on every cell, times the cell's map-point count when `weighted`: strips of
    /// rows filled by one task each from the dwell points in row order.
    fn scatter(&self, t: &[f64], image: &mut [f64], weighted: bool) {
        image
            .par_chunks_mut(STRIP_ROWS * self.nx)
            .enumerate()
            .for_each(|(s, strip)| {
                self.arch.dispatch(ScatterStrip {
                    op: self,
                    t,
                    r0: s * STRIP_ROWS,
                    strip,
                    weighted,
                })
            });
    }

    /// The strip of `image` from row `r0` (see [`Self::scatter`]).
    #[inline(always)]
    fn scatter_strip<S: pulp::Simd>(
        &self,
        simd: S,
        t: &[f64],
        r0: usize,
        strip: &mut [f64],
        weighted: bool,
    ) {
        let (nx, side) = (self.nx, self.side);
        strip.fill(0.0);
        let r1 = r0 + strip.len() / nx;
        let first = self.by_row_rows.partition_point(|&c| c + side <= r0);
        let last = self.by_row_rows.partition_point(|&c| c < r1);
        for &j in &self.by_row[first..last] {
            let tj = t[j];
            if tj == 0.0 {
                continue;
            }
            let (cx, cy) = self.dwell_corner[j];
            for b in r0.saturating_sub(cy)..(r1 - cy).min(side) {
                let (lo, row) = self.stencil_row(self.dwell_class[j], b);
                let start = (cy + b - r0) * nx + cx + lo;
                add_scaled(simd, tj, row, &mut strip[start..start + row.len()]);
            }
        }
        if weighted {
            let counts = &self.cell_count[r0 * nx..r1 * nx];
            for (o, &c) in strip.iter_mut().zip(counts) {
                *o *= c;
            }
        }
    }

    /// `image[c] = sum of y_i` over the map points in cell `c` (in index order), by strips.
    fn fill_from_map(&self, y: &[f64], image: &mut [f64]) {
        let nx = self.nx;
        image
            .par_chunks_mut(STRIP_ROWS * nx)
            .enumerate()
            .for_each(|(s, strip)| {
                strip.fill(0.0);
                let (c0, c1) = (s * STRIP_ROWS * nx, s * STRIP_ROWS * nx + strip.len());
                let first = self.by_cell_cells.partition_point(|&c| c < c0);
                let last = self.by_cell_cells.partition_point(|&c| c < c1);
                for (&i, &c) in self.by_cell[first..last]
                    .iter()
                    .zip(&self.by_cell_cells[first..last])
                {
                    strip[c - c0] += y[i];
                }
            });
    }

    /// `out[j]` = stencil `j` dotted with the image under it (rows in order).
    fn gather(&self, image: &[f64], out: &mut [f64]) {
        out.par_chunks_mut(GATHER_TASK)
            .enumerate()
            .for_each(|(c, chunk)| {
                self.arch.dispatch(GatherChunk {
                    op: self,
                    image,
                    first: c * GATHER_TASK,
                    out: chunk,
                })
            });
    }

    /// `out[k]` for dwell point `first + k` (see [`Self::gather`]).
    #[inline(always)]
    fn gather_chunk<S: pulp::Simd>(&self, simd: S, image: &[f64], first: usize, out: &mut [f64]) {
        for (k, o) in out.iter_mut().enumerate() {
            let j = first + k;
            let (cx, cy) = self.dwell_corner[j];
            let class = self.dwell_class[j];
            let mut acc = Lanes::new(simd);
            for b in 0..self.side {
                let (lo, row) = self.stencil_row(class, b);
                let start = (cy + b) * self.nx + cx + lo;
                acc.add_products(row, &image[start..start + row.len()]);
            }
            *o = acc.sum();
        }
    }

    fn lock_image(&self) -> std::sync::MutexGuard<'_, Vec<f64>> {
        // A panic in another product cannot leave the image inconsistent: every product
        // overwrites all of it first.
        self.image.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The stencil's half-width in cells for a TIF of support `radius` mm on the lattice of
/// `pitch_mm`, or an input error when it is not finite, not positive or too wide.
fn stencil_reach(radius: f64, pitch_mm: f64) -> Result<usize> {
    let reach = (radius / pitch_mm).ceil();
    if !(radius.is_finite() && radius > 0.0 && reach <= MAX_REACH_CELLS as f64) {
        return Err(Error::invalid(
            "stencil operator",
            format!(
                "the TIF's support radius {radius} mm spans more than {MAX_REACH_CELLS} cells \
                 of {pitch_mm} mm"
            ),
        ));
    }
    Ok(reach as usize)
}

/// The lattice index of each map point, or an error naming the first point off the lattice.
fn map_indices(
    (map_x_mm, map_y_mm): (&[f64], &[f64]),
    (x0, y0): (f64, f64),
    pitch_mm: f64,
) -> Result<Vec<(i64, i64)>> {
    map_x_mm
        .iter()
        .zip(map_y_mm)
        .enumerate()
        .map(|(i, (&x, &y))| {
            match (
                lattice_index(x, x0, pitch_mm),
                lattice_index(y, y0, pitch_mm),
            ) {
                (Some(a), Some(b)) => Ok((a, b)),
                _ => Err(off_lattice_error(
                    "map point",
                    i,
                    (x, y),
                    pitch_mm,
                    (x0, y0),
                )),
            }
        })
        .collect::<Result<_>>()
}

/// The dwell points' phase classes: the distinct positions within a lattice cell (in
/// `PHASE_STEPS` per cell, in order of first appearance), each point's class and its base cell.
struct PhaseClasses {
    phases: Vec<(i64, i64)>,
    dwell_class: Vec<usize>,
    dwell_base: Vec<(i64, i64)>,
}

impl PhaseClasses {
    fn of(
        (dwell_x_mm, dwell_y_mm): (&[f64], &[f64]),
        origin: (f64, f64),
        pitch_mm: f64,
    ) -> Result<Self> {
        let mut class_of: HashMap<(i64, i64), usize> = HashMap::new();
        let mut phases: Vec<(i64, i64)> = Vec::new();
        let mut dwell_class = Vec::with_capacity(dwell_x_mm.len());
        let mut dwell_base = Vec::with_capacity(dwell_x_mm.len());
        for (j, (&x, &y)) in dwell_x_mm.iter().zip(dwell_y_mm).enumerate() {
            let Some((base, phase)) = dwell_cell_and_phase((x, y), origin, pitch_mm) else {
                return Err(Error::invalid(
                    "dwell point",
                    format!(
                        "{j} at ({x}, {y}) mm is not finite or more than {MAX_CELL_OFFSET:e} cells \
                         from the map"
                    ),
                ));
            };
            let class = *class_of.entry(phase).or_insert_with(|| {
                phases.push(phase);
                phases.len() - 1
            });
            dwell_class.push(class);
            dwell_base.push(base);
        }
        Ok(Self {
            phases,
            dwell_class,
            dwell_base,
        })
    }
}

/// The image's lowest cell and its size `(nx, ny)` (with the row slack): it spans the map cells
/// and every stencil of half-width `w`, so no product clips; refused when too large or beyond
/// the memory budget.
fn image_extent(
    map_ij: &[(i64, i64)],
    dwell_base: &[(i64, i64)],
    w: usize,
    pitch_mm: f64,
) -> Result<((i64, i64), (usize, usize))> {
    let wi = w as i64;
    let (mut lo_x, mut lo_y, mut hi_x, mut hi_y) = (i64::MAX, i64::MAX, i64::MIN, i64::MIN);
    for &(a, b) in map_ij {
        (lo_x, lo_y, hi_x, hi_y) = (lo_x.min(a), lo_y.min(b), hi_x.max(a), hi_y.max(b));
    }
    for &(a, b) in dwell_base {
        (lo_x, lo_y) = (lo_x.min(a - wi), lo_y.min(b - wi));
        (hi_x, hi_y) = (hi_x.max(a + wi), hi_y.max(b + wi));
    }
    let (span_x, span_y) = ((hi_x - lo_x + 1) as f64, (hi_y - lo_y + 1) as f64);
    if span_x * span_y > MAX_IMAGE_CELLS as f64 {
        return Err(Error::invalid(
            "stencil operator",
            format!(
                "map and dwell points span {span_x} x {span_y} cells of {pitch_mm} mm, more \
                 than {MAX_IMAGE_CELLS}"
            ),
        ));
    }
    crate::budget::check(
        "map and dwell points (stencil operator)",
        &format!(
            "an image of {span_x} x {span_y} cells of {pitch_mm} mm at \
             {IMAGE_BYTES_PER_CELL} bytes each"
        ),
        (span_x + ROW_SLACK as f64) * span_y * IMAGE_BYTES_PER_CELL,
    )?;
    Ok(((lo_x, lo_y), (span_x as usize + ROW_SLACK, span_y as usize)))
}

/// One stencil per phase class, `S_f[b][a] = TIF(((a - w) - fx) h, ((b - w) - fy) h)` inside
/// the TIF's support, rows of `2 w + 1 + ROW_SLACK`; and each row's span of non-zeros widened
/// to whole lane groups.
fn tabulate_stencils<T: InfluenceFunction + ?Sized>(
    tif: &T,
    phases: &[(i64, i64)],
    w: usize,
    pitch_mm: f64,
) -> (Vec<f64>, Vec<(usize, usize)>) {
    let radius = tif.support_radius_mm();
    let r2 = radius * radius;
    let side = 2 * w + 1;
    let stride = side + ROW_SLACK;
    let mut stencils = vec![0.0; phases.len() * side * stride];
    stencils
        .par_chunks_mut(side * stride)
        .zip(phases)
        .for_each(|(block, &(fx, fy))| {
            let (px, py) = (
                fx as f64 / PHASE_STEPS as f64,
                fy as f64 / PHASE_STEPS as f64,
            );
            for (b, row) in block.chunks_mut(stride).enumerate() {
                let dy = ((b as f64 - w as f64) - py) * pitch_mm;
                for (a, v) in row[..side].iter_mut().enumerate() {
                    let dx = ((a as f64 - w as f64) - px) * pitch_mm;
                    if dx * dx + dy * dy <= r2 {
                        *v = tif.rate_nm_per_s(dx, dy);
                    }
                }
            }
        });
    let spans: Vec<(usize, usize)> = stencils
        .chunks(stride)
        .map(|row| match row.iter().position(|&v| v != 0.0) {
            Some(lo) => {
                let hi = stride - row.iter().rev().position(|&v| v != 0.0).unwrap_or(0);
                (lo, lo + (hi - lo).next_multiple_of(LANE_GROUP))
            }
            None => (0, 0),
        })
        .collect();
    (stencils, spans)
}

/// Whether `S` holds [`LANE_GROUP`] `f64` lanes: the kernels then take a group per
/// instruction; otherwise they take the same operations one lane at a time.
#[inline(always)]
fn group_wide<S: pulp::Simd>() -> bool {
    std::mem::size_of::<S::f64s>() == LANE_GROUP * std::mem::size_of::<f64>()
}

/// `out[k] += t v[k]` (a multiply, then an add: the same result in every lane width); the
/// lengths are equal multiples of [`LANE_GROUP`].
#[inline(always)]
fn add_scaled<S: pulp::Simd>(simd: S, t: f64, v: &[f64], out: &mut [f64]) {
    if group_wide::<S>() {
        let (out, _) = S::as_mut_simd_f64s(out);
        let (v, _) = S::as_simd_f64s(v);
        let t = simd.splat_f64s(t);
        for (o, &v) in out.iter_mut().zip(v) {
            *o = simd.add_f64s(*o, simd.mul_f64s(t, v));
        }
    } else {
        for (o, &v) in out.iter_mut().zip(v) {
            *o += t * v;
        }
    }
}

/// Sixteen running sums of products for the gather's dot products, four groups of
/// [`LANE_GROUP`]: enough independent additions in flight to hide their latency. Group `g` of a
/// row (its entries `4 g .. 4 g + 4` from the row's first column read) goes to sums
/// `g mod 4`; [`Lanes::sum`] combines the sums in a fixed order, so every lane width gives the
/// same result.
struct Lanes<S: pulp::Simd> {
    simd: S,
    wide: [S::f64s; 4],
    narrow: [[f64; LANE_GROUP]; 4],
}

impl<S: pulp::Simd> Lanes<S> {
    #[inline(always)]
    fn new(simd: S) -> Self {
        Self {
            simd,
            wide: [simd.splat_f64s(0.0); 4],
            narrow: [[0.0; LANE_GROUP]; 4],
        }
    }

    /// Adds `a[k] b[k]` for every `k`; `a` and `b` have the same length, a multiple of
    /// [`LANE_GROUP`].
    #[inline(always)]
    fn add_products(&mut self, a: &[f64], b: &[f64]) {
        if group_wide::<S>() {
            let simd = self.simd;
            let (a, _) = S::as_simd_f64s(a);
            let (b, _) = S::as_simd_f64s(b);
            let (whole_a, whole_b) = (a.chunks_exact(4), b.chunks_exact(4));
            let (rest_a, rest_b) = (whole_a.remainder(), whole_b.remainder());
            let [s0, s1, s2, s3] = &mut self.wide;
            for (x, y) in whole_a.zip(whole_b) {
                *s0 = simd.add_f64s(*s0, simd.mul_f64s(x[0], y[0]));
                *s1 = simd.add_f64s(*s1, simd.mul_f64s(x[1], y[1]));
                *s2 = simd.add_f64s(*s2, simd.mul_f64s(x[2], y[2]));
                *s3 = simd.add_f64s(*s3, simd.mul_f64s(x[3], y[3]));
            }
            for (s, (&x, &y)) in [s0, s1, s2].into_iter().zip(rest_a.iter().zip(rest_b)) {
                *s = simd.add_f64s(*s, simd.mul_f64s(x, y));
            }
        } else {
            let (whole_a, whole_b) = (
                a.chunks_exact(4 * LANE_GROUP),
                b.chunks_exact(4 * LANE_GROUP),
            );
            let (rest_a, rest_b) = (whole_a.remainder(), whole_b.remainder());
            for (x, y) in whole_a.zip(whole_b) {
                for (g, s) in self.narrow.iter_mut().enumerate() {
                    for (l, s) in s.iter_mut().enumerate() {
                        *s += x[g * LANE_GROUP + l] * y[g * LANE_GROUP + l];
                    }
                }
            }
            for (g, s) in self
                .narrow
                .iter_mut()
                .take(rest_a.len() / LANE_GROUP)
                .enumerate()
            {
                for (l, s) in s.iter_mut().enumerate() {
                    *s += rest_a[g * LANE_GROUP + l] * rest_b[g * LANE_GROUP + l];
                }
            }
        }
    }

    /// The sum of every product added: the four sums of each lane pairwise, then the lanes
    /// pairwise.
    #[inline(always)]
    fn sum(&self) -> f64 {
        let mut groups = self.narrow;
        if group_wide::<S>() {
            for (g, w) in groups.iter_mut().zip(&self.wide) {
                g.copy_from_slice(pulp::bytemuck::cast_slice::<S::f64s, f64>(
                    std::slice::from_ref(w),
                ));
            }
        }
        let [s0, s1, s2, s3] = groups;
        let l: [f64; LANE_GROUP] = std::array::from_fn(|k| (s0[k] + s1[k]) + (s2[k] + s3[k]));
        (l[0] + l[1]) + (l[2] + l[3])
    }
}

/// One strip of the scatter, run by [`pulp::Arch::dispatch`] so that its loops are compiled for
/// the CPU's widest vector instructions.
struct ScatterStrip<'a> {
    op: &'a StencilOperator,
    t: &'a [f64],
    r0: usize,
    strip: &'a mut [f64],
    weighted: bool,
}

impl pulp::WithSimd for ScatterStrip<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        self.op
            .scatter_strip(simd, self.t, self.r0, self.strip, self.weighted)
    }
}

/// One chunk of the gather, run as [`ScatterStrip`].
struct GatherChunk<'a> {
    op: &'a StencilOperator,
    image: &'a [f64],
    first: usize,
    out: &'a mut [f64],
}

impl pulp::WithSimd for GatherChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        self.op.gather_chunk(simd, self.image, self.first, self.out)
    }
}

impl LinearOperator for StencilOperator {
    fn nrows(&self) -> usize {
        self.map_cells.len()
    }

    fn ncols(&self) -> usize {
        self.dwell_class.len()
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        let mut image = self.lock_image();
        self.scatter(t, &mut image, false);
        let image = &*image;
        out.par_iter_mut()
            .zip(&self.map_cells)
            .with_min_len(4 * GATHER_TASK)
            .for_each(|(o, &c)| *o = image[c]);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        let mut image = self.lock_image();
        self.fill_from_map(y, &mut image);
        self.gather(&image, out);
    }

    fn apply_normal(&self, t: &[f64], _scratch: &mut [f64], out: &mut [f64]) {
        let mut image = self.lock_image();
        self.scatter(t, &mut image, true);
        self.gather(&image, out);
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.columns.centred_norms_sq()
    }
}

impl InfluenceOperator for StencilOperator {
    fn kind(&self) -> OperatorKind {
        OperatorKind::Stencil
    }

    fn shape(&self) -> (usize, usize) {
        (LinearOperator::nrows(self), LinearOperator::ncols(self))
    }

    fn nnz(&self) -> usize {
        StencilOperator::nnz(self)
    }

    fn empty_columns(&self) -> Vec<usize> {
        StencilOperator::empty_columns(self)
    }

    /// The operator itself: its products need no copy.
    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::{InfluenceMatrix, SparseOperator};
    use crate::observer::Silent;

    /// Products of dwell points on a rational raster equal the assembled ones within this
    /// relative tolerance (the rounded phases are exact there; only the order of sums differs).
    const EXACT_REL_TOL: f64 = 1e-12;
    /// For dwell points anywhere, the phase rounding (`h 2^-25 sqrt 2`) times the TIF's slope.
    const ROUNDED_REL_TOL: f64 = 1e-7;

    /// The gather's sums against their definition (entry `k` of a row into sum `(k / 4) mod 4`,
    /// lane `k mod 4`; then each lane's four sums pairwise, then the lanes pairwise), bit for
    /// bit, one lane at a time (`Scalar`), four lanes portably (`Scalar256b`), eight (which
    /// take the one-lane path) and, where the CPU has them, in AVX2 registers. Rows of every
    /// length up to 40 in steps of 4, so each count of remainder groups is met; `add_scaled`
    /// likewise against `out[k] += t v[k]`.
    #[test]
    fn kernels_give_the_definition_in_every_lane_width() {
        let value = |k: usize| ((k * 7919) % 1009) as f64 / 97.0 - 5.0;
        let rows: Vec<(Vec<f64>, Vec<f64>)> = (0..=10)
            .map(|g| {
                let n = 4 * g;
                let a = (0..n).map(|k| value(k + 13 * g)).collect();
                let b = (0..n).map(|k| value(3 * k + 101 * g + 1) * 1e-3).collect();
                (a, b)
            })
            .collect();
        let mut sums = [[0.0f64; 4]; 4];
        for (a, b) in &rows {
            for (k, (x, y)) in a.iter().zip(b).enumerate() {
                sums[(k / 4) % 4][k % 4] += x * y;
            }
        }
        let lane = |k: usize| (sums[0][k] + sums[1][k]) + (sums[2][k] + sums[3][k]);
        let expected = (lane(0) + lane(1)) + (lane(2) + lane(3));
        fn run<S: pulp::Simd>(simd: S, rows: &[(Vec<f64>, Vec<f64>)]) -> (f64, Vec<f64>) {
            let mut lanes = Lanes::new(simd);
            let mut scaled = Vec::new();
            for (a, b) in rows {
                lanes.add_products(a, b);
                let mut out = b.clone();
                add_scaled(simd, -0.37, a, &mut out);
                scaled.extend(out);
            }
            (lanes.sum(), scaled)
        }
        let scaled: Vec<f64> = rows
            .iter()
            .flat_map(|(a, b)| a.iter().zip(b).map(|(x, y)| y + -0.37 * x))
            .collect();
        let mut widths = vec![
            ("one lane", run(pulp::Scalar::new(), &rows)),
            ("four lanes", run(pulp::Scalar256b, &rows)),
            ("eight lanes", run(pulp::Scalar512b, &rows)),
        ];
        #[cfg(target_arch = "x86_64")]
        if let Some(v3) = pulp::x86::V3::try_new() {
            widths.push(("AVX2", run(v3, &rows)));
        }
        for (name, (got, got_scaled)) in widths {
            assert_eq!(
                got.to_bits(),
                expected.to_bits(),
                "{name}: {got} != {expected}"
            );
            assert!(
                got_scaled
                    .iter()
                    .zip(&scaled)
                    .all(|(g, e)| g.to_bits() == e.to_bits()),
                "{name}"
            );
        }
        assert!(
            expected.abs() > 1e-3,
            "the sum is not a cancellation to nothing"
        );
    }

    /// An asymmetric TIF (off-centre, tilted Gaussian, cut at 2.1 mm), so that a mirrored stencil
    /// or a phase taken with the wrong sign cannot pass.
    struct Lopsided;

    impl InfluenceFunction for Lopsided {
        fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
            let (u, v) = (dx_mm - 0.3, dy_mm + 0.2);
            if dx_mm * dx_mm + dy_mm * dy_mm > 2.1 * 2.1 {
                return 0.0;
            }
            (1.0 + 0.2 * dx_mm - 0.1 * dy_mm) * (-(u * u + 2.0 * v * v) / 1.5).exp()
        }

        fn support_radius_mm(&self) -> f64 {
            2.1
        }
    }

    /// A round map (radius 5 mm) on a 0.4 mm lattice, one point measured twice.
    fn round_map() -> (Vec<f64>, Vec<f64>) {
        let (mut x, mut y) = (vec![], vec![]);
        for j in -13..=13 {
            for i in -13..=13 {
                let (a, b) = (0.4 * i as f64 + 0.1, 0.4 * j as f64 - 0.3);
                if (a - 0.1).hypot(b + 0.3) <= 5.0 {
                    x.push(a);
                    y.push(b);
                }
            }
        }
        x.push(x[40]);
        y.push(y[40]);
        (x, y)
    }

    /// A 0.5 mm raster (5/4 of the map pitch: 4 x 4 phases) reaching 1.5 mm past the map.
    fn raster() -> (Vec<f64>, Vec<f64>) {
        (0..27 * 27)
            .map(|k| (-6.4 + 0.5 * (k % 27) as f64, -6.55 + 0.5 * (k / 27) as f64))
            .unzip()
    }

    fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
        let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
        let n: f64 = b.iter().map(|y| y * y).sum();
        (d / n).sqrt()
    }

    /// `R t` and `R^T y` of the stencil operator and of the assembled matrix, and the largest
    /// entry-wise difference relative to the largest entry.
    fn compare(dx: &[f64], dy: &[f64]) -> (StencilOperator, f64, f64) {
        let (mx, my) = round_map();
        let op = StencilOperator::new(&mx, &my, dx, dy, 0.4, &Lopsided).unwrap();
        let exact = InfluenceMatrix::assemble(&mx, &my, dx, dy, &Lopsided, &Silent).unwrap();
        let sparse = SparseOperator::new(exact.csc());
        let t: Vec<f64> = (0..dx.len())
            .map(|j| ((j * 7919) % 13) as f64 * 0.1)
            .collect();
        let y: Vec<f64> = (0..mx.len())
            .map(|i| ((i * 104729) % 17) as f64 - 8.0)
            .collect();
        let (mut a, mut b) = (vec![0.0; mx.len()], vec![0.0; mx.len()]);
        op.apply(&t, &mut a);
        sparse.apply(&t, &mut b);
        let forward = rel_diff(&a, &b);
        let (mut a, mut b) = (vec![0.0; dx.len()], vec![0.0; dx.len()]);
        op.apply_transpose(&y, &mut a);
        sparse.apply_transpose(&y, &mut b);
        (op, forward, rel_diff(&a, &b))
    }

    #[test]
    fn products_on_a_rational_raster_equal_the_assembled_matrix() {
        let (dx, dy) = raster();
        let (op, forward, transpose) = compare(&dx, &dy);
        assert_eq!(op.phase_class_count(), 16);
        assert!(forward < EXACT_REL_TOL, "R t off by {forward:e}");
        assert!(transpose < EXACT_REL_TOL, "R^T y off by {transpose:e}");
        let (mx, my) = round_map();
        let exact = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &Lopsided, &Silent).unwrap();
        assert_eq!(op.nnz(), exact.nnz());
        assert_eq!(op.empty_columns(), exact.empty_columns());
        assert!(
            !op.empty_columns().is_empty(),
            "the raster reaches past the TIF"
        );
        let want = SparseOperator::new(exact.csc()).centred_column_norms_sq();
        let got = op.centred_column_norms_sq();
        assert!(rel_diff(&got, &want) < EXACT_REL_TOL);
    }

    /// A 0.36 mm map and a 0.5 mm raster (18 x 18 phases, rounded) put families of pairs
    /// exactly 4.5 mm apart, on the cut circle, some of whose computed offsets round outward:
    /// the stencils and the assembled `R` count the same pairs.
    #[test]
    fn pairs_on_a_gaussian_cut_circle_count_in_both_operators() {
        let tif = crate::tif::GaussianTif::new(1.5, 20.0, 4.5).unwrap();
        let (mx, my): (Vec<f64>, Vec<f64>) = (0..60 * 40)
            .map(|k| (0.36 * (k % 60) as f64, 0.36 * (k / 60) as f64))
            .unzip();
        let (dx, dy): (Vec<f64>, Vec<f64>) = (0..60 * 46)
            .map(|k| (-4.0 + 0.5 * (k % 60) as f64, -4.0 + 0.5 * (k / 60) as f64))
            .unzip();
        let op = StencilOperator::new(&mx, &my, &dx, &dy, 0.36, &tif).unwrap();
        let exact = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        assert_eq!(op.nnz(), exact.nnz());
        let sparse = SparseOperator::new(exact.csc());
        let t: Vec<f64> = (0..dx.len())
            .map(|j| 0.1 + ((j * 7919) % 13) as f64)
            .collect();
        let (mut a, mut b) = (vec![0.0; mx.len()], vec![0.0; mx.len()]);
        op.apply(&t, &mut a);
        sparse.apply(&t, &mut b);
        let forward = rel_diff(&a, &b);
        assert!(forward < ROUNDED_REL_TOL, "R t off by {forward:e}");
    }

    #[test]
    fn products_at_scattered_dwell_points_equal_the_assembled_matrix_to_the_rounding() {
        // Every dwell point its own phase.
        let (dx, dy): (Vec<f64>, Vec<f64>) = (0..300)
            .map(|k| {
                let (a, b) = (k as f64 * 0.618_033_988_75, k as f64 * 0.414_213_562_37);
                (-6.0 + 12.0 * a.fract(), -6.0 + 12.0 * b.fract())
            })
            .unzip();
        let (op, forward, transpose) = compare(&dx, &dy);
        assert!(op.phase_class_count() > 290);
        assert!(forward < ROUNDED_REL_TOL, "R t off by {forward:e}");
        assert!(transpose < ROUNDED_REL_TOL, "R^T y off by {transpose:e}");
    }

    #[test]
    fn normal_product_is_the_transpose_of_the_product_and_adjoint_holds() {
        let (mx, my) = round_map();
        let (dx, dy) = raster();
        let op = StencilOperator::new(&mx, &my, &dx, &dy, 0.4, &Lopsided).unwrap();
        let t: Vec<f64> = (0..dx.len()).map(|j| 1.0 + ((j * 31) % 7) as f64).collect();
        let y: Vec<f64> = (0..mx.len()).map(|i| ((i * 13) % 5) as f64 - 2.0).collect();
        let (mut rt, mut rty) = (vec![0.0; mx.len()], vec![0.0; dx.len()]);
        op.apply(&t, &mut rt);
        op.apply_transpose(&y, &mut rty);
        let lhs: f64 = rt.iter().zip(&y).map(|(a, b)| a * b).sum();
        let rhs: f64 = rty.iter().zip(&t).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() <= EXACT_REL_TOL * lhs.abs(),
            "{lhs} vs {rhs}"
        );
        let (mut normal, mut two) = (vec![0.0; dx.len()], vec![0.0; dx.len()]);
        op.apply_normal(&t, &mut vec![0.0; mx.len()], &mut normal);
        op.apply_transpose(&rt, &mut two);
        assert!(rel_diff(&normal, &two) < EXACT_REL_TOL);
    }

    #[test]
    fn products_do_not_depend_on_the_thread_count() {
        let (mx, my) = round_map();
        let (dx, dy) = raster();
        let op = StencilOperator::new(&mx, &my, &dx, &dy, 0.4, &Lopsided).unwrap();
        let t: Vec<f64> = (0..dx.len()).map(|j| ((j * 17) % 11) as f64).collect();
        let run = |threads: usize| {
            crate::test_support::on_threads(threads, || {
                let (mut rt, mut normal) = (vec![0.0; mx.len()], vec![0.0; dx.len()]);
                op.apply(&t, &mut rt);
                op.apply_normal(&t, &mut vec![0.0; mx.len()], &mut normal);
                (rt, normal)
            })
        };
        let one = run(1);
        for threads in [2, 3, 5] {
            assert!(run(threads) == one, "{threads} threads");
        }
    }

    /// The kernels compiled for the CPU's vector instructions do the same operations in the same
    /// order as the scalar build: bit-identical products.
    #[test]
    fn vector_and_scalar_kernels_give_the_same_bits() {
        let (mx, my) = round_map();
        let (dx, dy) = raster();
        let mut op = StencilOperator::new(&mx, &my, &dx, &dy, 0.4, &Lopsided).unwrap();
        let t: Vec<f64> = (0..dx.len())
            .map(|j| 0.3 + ((j * 29) % 13) as f64)
            .collect();
        let y: Vec<f64> = (0..mx.len()).map(|i| ((i * 7) % 9) as f64 - 4.0).collect();
        let run = |op: &StencilOperator| {
            let (mut rt, mut rty, mut normal) = (
                vec![0.0; mx.len()],
                vec![0.0; dx.len()],
                vec![0.0; dx.len()],
            );
            op.apply(&t, &mut rt);
            op.apply_transpose(&y, &mut rty);
            op.apply_normal(&t, &mut vec![0.0; mx.len()], &mut normal);
            (rt, rty, normal)
        };
        let detected = run(&op);
        op.arch = pulp::Arch::Scalar;
        assert!(run(&op) == detected);
    }

    #[test]
    fn phase_classes_are_counted_and_bounded() {
        let (mx, my) = round_map();
        let (dx, dy) = raster();
        assert_eq!(
            StencilOperator::phase_classes(&mx, &my, &dx, &dy, 0.4, 100),
            Some(16)
        );
        assert_eq!(
            StencilOperator::phase_classes(&mx, &my, &dx, &dy, 0.4, 15),
            None
        );
        // A raster on the map lattice has one phase.
        let (lx, ly): (Vec<f64>, Vec<f64>) = (0..50)
            .map(|k| (0.1 + 0.8 * (k % 10) as f64, -0.3 + 0.4 * (k / 10) as f64))
            .unzip();
        assert_eq!(
            StencilOperator::phase_classes(&mx, &my, &lx, &ly, 0.4, 100),
            Some(1)
        );
    }

    #[test]
    fn a_map_point_off_the_lattice_is_refused_by_index() {
        let (mut mx, my) = round_map();
        mx[7] += 0.13;
        let (dx, dy) = raster();
        let e = StencilOperator::new(&mx, &my, &dx, &dy, 0.4, &Lopsided).unwrap_err();
        assert!(e.to_string().contains("map point: 7 at"), "{e}");
    }
}
