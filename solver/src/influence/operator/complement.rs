//! The normal product `R^T P R t` of the FFT operator through its complement, for maps that
//! cover most of the tool's reach.
//!
//! Row `c` of `R` on the lattice is `k_c = (K[c - q_j])_j` (kernel `K`, dwell cells `q_j`), and
//! `P` counts the map points in each cell, so `R^T P R = sum_c count_c k_c k_c^T`. Summed over
//! every cell of the unbounded lattice, `sum_c k_c k_c^T` is the kernel's autocorrelation
//! `A[q_j - q_k] = sum_c K[c] K[c + q_j - q_k]`: a convolution on the dwell (sub-)lattice, with
//! no map in it. Hence
//!
//! `R^T P R t = A * t - sum_{c in B} w_c k_c (k_c^T t)`,  `w_c = 1 - count_c`,
//!
//! `B` the band: the cells within the kernel's reach of a dwell point whose count is not one
//! (around the map's edge and its holes, and cells holding several points). `A * t` is one
//! forward and one inverse transform on the dwell lattice, padded by the autocorrelation's
//! radius (a quarter of the lattice's cells for a 1 mm raster over a 0.5 mm map), in place of
//! the direct route's two transforms on the map lattice and two on the dwell lattice. The band's
//! rows are summed directly: `u_c = k_c^T t` from a dense image of `t`, then `sum_c w_c u_c k_c`
//! gathered at the dwell points within reach of the band, from one table per position of a
//! lattice cell within the dwell sub-lattice's cell, in runs of consecutive image positions
//! (each tap's multiply-add taken over [`BLOCK`] outputs at once).
//!
//! Every output sums its terms in a fixed order, so results do not depend on the thread count.
//! They differ from the direct route by rounding relative to `||A|| ||t||`, as the direct
//! route's transforms do; where the map sees only the tail of a dwell point's footprint
//! (the outermost ring of an extended raster) the difference of the two terms loses the digits
//! of that ratio. [`super::FftOperator`] takes this route where its cost model says it is
//! cheaper.

use super::lattice::{smooth_size, Buffers, Cells, Fill, Spectrum, Transforms};
use rayon::prelude::*;
use realfft::RealFftPlanner;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::sync::Mutex;

/// Band cells (or dwell points) per rayon task.
const BAND_TASK: usize = 256;
/// Bytes per cell of the autocorrelation's transform lattice: a real buffer and two
/// half-spectrum complex ones, and `A`'s half spectrum.
const BYTES_PER_TRANSFORM_CELL: f64 = 40.0;
/// Outputs of a run summed together (each tap's multiply-add over `BLOCK` lanes).
const BLOCK: usize = 8;
/// Largest kernel (non-zero taps) whose autocorrelation is summed pair by pair (`taps^2` terms).
const MAX_AUTOCORRELATION_TAPS: usize = 10_000;

/// The lattice the operator works on, as [`super::FftOperator::new`] resolved it.
pub(super) struct LatticeGeometry<'a> {
    /// Dwell cells, lattice indices from the points' lowest corner.
    pub dwell_ij: &'a [(usize, usize)],
    /// Cells spanned by the points.
    pub nx: usize,
    /// Cells spanned by the points.
    pub ny: usize,
    /// Map points in each cell `(i, j)` of the span, row-major with row length `row`.
    pub map_count: &'a [u32],
    /// Row length of `map_count`.
    pub row: usize,
    /// The kernel's non-zero taps `(dx, dy, K)`, `|dx|, |dy| <= reach`.
    pub taps: &'a [(isize, isize, f64)],
    /// Kernel reach, cells.
    pub reach: usize,
    /// Dwell sub-lattice steps (1 on the lattice itself).
    pub step: (usize, usize),
    /// Dwell sub-lattice offset.
    pub offset: (usize, usize),
    /// Bytes the operator holds already (counted with the route's own against the budget).
    pub held_bytes: f64,
}

/// The complement route (see the module documentation).
pub(super) struct ComplementNormal {
    transforms: Transforms,
    /// Dwell points on the autocorrelation's lattice.
    dwell: Cells,
    /// `A`'s transform.
    a_hat: Vec<Complex<f64>>,
    scale: f64,
    buffers: Mutex<Buffers>,
    band: Band,
}

/// The band's rows of `R` (see the module documentation), on images of the dwell sub-lattice
/// padded by twice the kernel's reach.
struct Band {
    /// Image row length.
    width: usize,
    side_x: usize,
    side_y: usize,
    /// Per phase (position within the sub-lattice's cell), `side_y` rows of `side_x` taps:
    /// entry `(ay, ax)` is `K` at the offset from the dwell point at window position `(ax, ay)`.
    tables: Vec<f64>,
    /// The tables turned by half a turn (the adjoint's windows), kept so that both passes read
    /// their taps left to right in the inner loop.
    flipped: Vec<f64>,
    /// Per phase and row, the span `[lo, hi)` of taps that may be non-zero.
    spans: Vec<(usize, usize)>,
    flipped_spans: Vec<(usize, usize)>,
    /// Band cells in run order: phase, image position (in the phase's image), weight `w_c`.
    cells: Vec<(usize, usize, f64)>,
    /// The forward pass: runs of band cells of one phase in consecutive image positions.
    forward: Runs,
    /// Dwell points within reach of the band in run order: index and image position.
    touched: Vec<(usize, usize)>,
    /// The adjoint pass: runs of touched dwell points in consecutive image positions.
    adjoint: Runs,
    image_len: usize,
    phases: usize,
    images: Mutex<BandImages>,
    arch: pulp::Arch,
}

/// Runs of outputs in consecutive image positions, none crossing a multiple of [`BAND_TASK`]
/// outputs, so that each task of `BAND_TASK` outputs takes whole runs.
struct Runs {
    /// Phase (forward) or 0, image position of the first output's window corner, length.
    runs: Vec<(usize, usize, usize)>,
    /// Runs of task `k`: `first[k]..first[k + 1]`.
    first: Vec<usize>,
}

impl Runs {
    /// Runs over outputs `(phase, position, corner)` sorted by phase and position.
    fn new(outputs: impl Iterator<Item = (usize, usize, usize)>) -> Self {
        let mut runs: Vec<(usize, usize, usize)> = Vec::new();
        let mut first = vec![0];
        let mut last: Option<(usize, usize)> = None;
        for (k, (phase, at, corner)) in outputs.enumerate() {
            if k > 0 && k % BAND_TASK == 0 {
                first.push(runs.len());
                last = None;
            }
            match (last, runs.last_mut()) {
                (Some((p, a)), Some(run)) if p == phase && a + 1 == at => run.2 += 1,
                _ => runs.push((phase, corner, 1)),
            }
            last = Some((phase, at));
        }
        first.push(runs.len());
        Self { runs, first }
    }

    fn tasks(&self) -> usize {
        self.first.len() - 1
    }
}

#[derive(Default)]
struct BandImages {
    /// `t` on the dwell image (written at the touched dwell points only).
    t: Vec<f64>,
    /// `w_c u_c` per phase image (written at the band cells only; zero elsewhere).
    v: Vec<f64>,
    u: Vec<f64>,
    s: Vec<f64>,
}

/// `mask` (rows of `w`) dilated by a box of half-widths `(rx, ry)`.
fn dilate(mask: &[bool], w: usize, rx: usize, ry: usize) -> Vec<bool> {
    let h = mask.len() / w.max(1);
    let mut across = vec![false; mask.len()];
    let mut prefix = vec![0u32; w + 1];
    for (row, out) in mask.chunks_exact(w).zip(across.chunks_exact_mut(w)) {
        for (x, &m) in row.iter().enumerate() {
            prefix[x + 1] = prefix[x] + u32::from(m);
        }
        for (x, o) in out.iter_mut().enumerate() {
            *o = prefix[(x + rx + 1).min(w)] > prefix[x.saturating_sub(rx)];
        }
    }
    let mut counts = vec![0u32; w];
    let mut out = vec![false; mask.len()];
    for y in 0..h + ry {
        if y < h {
            for (c, &m) in counts.iter_mut().zip(&across[y * w..(y + 1) * w]) {
                *c += u32::from(m);
            }
        }
        if y > 2 * ry {
            let gone = y - 2 * ry - 1;
            for (c, &m) in counts.iter_mut().zip(&across[gone * w..(gone + 1) * w]) {
                *c -= u32::from(m);
            }
        }
        // Rows `y - 2 ry ..= y` are counted: the window of row `y - ry`.
        if y >= ry {
            let r = y - ry;
            for (o, &c) in out[r * w..(r + 1) * w].iter_mut().zip(&counts) {
                *o = c > 0;
            }
        }
    }
    out
}

/// The span `[lo, hi)` of non-zero entries of `row` (`(0, 0)` when none).
fn span(row: &[f64]) -> (usize, usize) {
    match row.iter().position(|&v| v != 0.0) {
        Some(lo) => {
            let hi = row.iter().rposition(|&v| v != 0.0).map_or(lo, |h| h + 1);
            (lo, hi)
        }
        None => (0, 0),
    }
}

impl ComplementNormal {
    /// Builds the route for `g`; `None` when the kernel is too large for its autocorrelation to
    /// be summed pair by pair, when the route's arrays with the operator's would exceed the
    /// memory budget ([`crate::budget`]), or when `take(transform cells, band multiply-adds)`,
    /// asked once the band is known and before the transforms are planned, declines it (the
    /// direct route then serves).
    pub(super) fn new(
        g: &LatticeGeometry<'_>,
        take: impl FnOnce(f64, f64) -> bool,
    ) -> Option<Self> {
        if g.taps.len() > MAX_AUTOCORRELATION_TAPS || g.dwell_ij.is_empty() {
            return None;
        }
        let (dx, dy) = g.step;
        let (ox, oy) = g.offset;
        let sub: Vec<(usize, usize)> = g
            .dwell_ij
            .iter()
            .map(|&(i, j)| ((i - ox) / dx, (j - oy) / dy))
            .collect();
        let na = sub.iter().map(|p| p.0).max().unwrap_or(0) + 1;
        let nb = sub.iter().map(|p| p.1).max().unwrap_or(0) + 1;

        // A on the sub-lattice, radius (kax, kay) sub-lattice cells.
        let (kax, kay) = (2 * g.reach / dx, 2 * g.reach / dy);
        let (gx, gy) = (smooth_size(na + kax), smooth_size(nb + kay));
        let (kqx, kqy) = (g.reach.div_ceil(dx), g.reach.div_ceil(dy));
        let image_cells = ((na + 4 * kqx) * (nb + 4 * kqy)) as f64;
        let bytes = g.held_bytes
            + (gx * gy) as f64 * BYTES_PER_TRANSFORM_CELL
            + image_cells * ((1 + dx * dy) as f64 * crate::budget::F64_BYTES + 2.0)
            + ((g.nx + 2 * g.reach) * (g.ny + 2 * g.reach) * 2) as f64;
        crate::budget::check("FFT operator", "the complement route", bytes).ok()?;
        let mut band = Band::new(g, &sub, (na, nb));
        if !take((gx * gy) as f64, band.multiply_adds()) {
            return None;
        }
        band.allocate_images();
        let (awx, awy) = (2 * kax + 1, 2 * kay + 1);
        let mut a = vec![0.0; awx * awy];
        for &(x1, y1, v1) in g.taps {
            for &(x2, y2, v2) in g.taps {
                let (ex, ey) = (x2 - x1, y2 - y1);
                if ex.rem_euclid(dx as isize) == 0 && ey.rem_euclid(dy as isize) == 0 {
                    let ax = (ex / dx as isize + kax as isize) as usize;
                    let ay = (ey / dy as isize + kay as isize) as usize;
                    a[ay * awx + ax] += v1 * v2;
                }
            }
        }
        let mut planner = FftPlanner::<f64>::new();
        let mut real_planner = RealFftPlanner::<f64>::new();
        let transforms = Transforms::new(gx, gy, &mut planner, &mut real_planner);
        // Where the memory cannot be had the direct route serves.
        let mut buffers = Buffers::new(gx, gy).ok()?;
        for ay in 0..awy {
            for ax in 0..awx {
                let ix = (ax as isize - kax as isize).rem_euclid(gx as isize) as usize;
                let iy = (ay as isize - kay as isize).rem_euclid(gy as isize) as usize;
                buffers.real[iy * gx + ix] += a[ay * awx + ax];
            }
        }
        transforms.spectrum(&mut buffers, Fill::Ready, Spectrum::Keep);
        let a_hat = buffers.columns.clone();
        let dwell = Cells::new(sub.iter().map(|&(i, j)| j * gx + i).collect(), gx, gy);
        Some(Self {
            transforms,
            dwell,
            a_hat,
            scale: 1.0 / (gx * gy) as f64,
            buffers: Mutex::new(buffers),
            band,
        })
    }

    /// Tasks of the band's forward and adjoint passes (tests).
    #[cfg(test)]
    pub(super) fn band_runs(&self) -> (usize, usize) {
        (self.band.forward.tasks(), self.band.adjoint.tasks())
    }

    /// `out = R^T P R t`.
    pub(super) fn normal(&self, t: &[f64], out: &mut [f64]) {
        {
            let mut guard = self.buffers.lock().unwrap_or_else(|e| e.into_inner());
            let b = &mut *guard;
            self.transforms.spectrum(
                b,
                Fill::Scatter(&self.dwell, t),
                Spectrum::Convolve(&self.a_hat),
            );
            self.transforms.to_real(b, &self.dwell.rows);
            self.dwell.gather(&b.real, self.scale, out);
        }
        self.band.subtract(t, out);
    }
}

impl Band {
    fn new(g: &LatticeGeometry<'_>, sub: &[(usize, usize)], (na, nb): (usize, usize)) -> Self {
        let (dx, dy) = g.step;
        let (ox, oy) = g.offset;
        let kr = g.reach;
        let (kqx, kqy) = (kr.div_ceil(dx), kr.div_ceil(dy));
        let (side_x, side_y) = (2 * kqx + 1, 2 * kqy + 1);
        let (padx, pady) = (2 * kqx, 2 * kqy);
        let width = na + 4 * kqx;
        let image_len = width * (nb + 4 * kqy);
        let phases = dx * dy;

        // Tables: phase (fx, fy), window entry (ax, ay) -> K at ((kqx - ax) dx + fx, ...).
        let kw = 2 * kr + 1;
        let mut kernel = vec![0.0; kw * kw];
        for &(x, y, v) in g.taps {
            kernel[(y + kr as isize) as usize * kw + (x + kr as isize) as usize] = v;
        }
        let k_at = |x: isize, y: isize| -> f64 {
            if x.unsigned_abs() > kr || y.unsigned_abs() > kr {
                0.0
            } else {
                kernel[(y + kr as isize) as usize * kw + (x + kr as isize) as usize]
            }
        };
        let block = side_x * side_y;
        let mut tables = vec![0.0; phases * block];
        let mut flipped = vec![0.0; phases * block];
        for fy in 0..dy {
            for fx in 0..dx {
                let p = fy * dx + fx;
                for ay in 0..side_y {
                    for ax in 0..side_x {
                        let ex = (kqx as isize - ax as isize) * dx as isize + fx as isize;
                        let ey = (kqy as isize - ay as isize) * dy as isize + fy as isize;
                        let v = k_at(ex, ey);
                        tables[p * block + ay * side_x + ax] = v;
                        flipped[p * block + (side_y - 1 - ay) * side_x + (side_x - 1 - ax)] = v;
                    }
                }
            }
        }
        let spans = tables.chunks_exact(side_x).map(span).collect();
        let flipped_spans = flipped.chunks_exact(side_x).map(span).collect();

        // Cells within reach of a dwell point (a box of the kernel's reach), on the lattice
        // padded by the reach on every side.
        let (wx, wy) = (g.nx + 2 * kr, g.ny + 2 * kr);
        let mut occupied = vec![false; wx * wy];
        for &(i, j) in g.dwell_ij {
            occupied[(j + kr) * wx + i + kr] = true;
        }
        let reach = dilate(&occupied, wx, kr, kr);
        drop(occupied);
        let mut cells: Vec<(usize, usize, usize, f64)> = Vec::new();
        let mut marked = vec![false; image_len];
        for py in 0..wy {
            for px in 0..wx {
                if !reach[py * wx + px] {
                    continue;
                }
                let (cx, cy) = (px as isize - kr as isize, py as isize - kr as isize);
                let inside = cx >= 0 && cy >= 0 && (cx as usize) < g.nx && (cy as usize) < g.ny;
                let count = if inside {
                    g.map_count[cy as usize * g.row + cx as usize]
                } else {
                    0
                };
                if count == 1 {
                    continue;
                }
                let (rx, ry) = (cx - ox as isize, cy - oy as isize);
                let (qx, fx) = (rx.div_euclid(dx as isize), rx.rem_euclid(dx as isize));
                let (qy, fy) = (ry.div_euclid(dy as isize), ry.rem_euclid(dy as isize));
                // Reach keeps `qx >= -kqx`, so the image indices below are non-negative.
                let ix = (qx + padx as isize) as usize;
                let iy = (qy + pady as isize) as usize;
                let at = iy * width + ix;
                marked[at] = true;
                let corner = (iy - kqy) * width + ix - kqx;
                cells.push((
                    fy as usize * dx + fx as usize,
                    at,
                    corner,
                    1.0 - f64::from(count),
                ));
            }
        }
        drop(reach);
        cells.sort_by_key(|c| (c.0, c.1));
        let forward = Runs::new(cells.iter().map(|c| (c.0, c.1, c.2)));
        let near = dilate(&marked, width, kqx, kqy);
        let mut touched: Vec<(usize, usize, usize)> = sub
            .iter()
            .enumerate()
            .filter_map(|(j, &(a, b))| {
                let at = (b + pady) * width + a + padx;
                near[at].then(|| (j, at, (b + pady - kqy) * width + a + padx - kqx))
            })
            .collect();
        touched.sort_by_key(|d| d.1);
        let adjoint = Runs::new(touched.iter().map(|d| (0, d.1, d.2)));
        Self {
            width,
            side_x,
            side_y,
            tables,
            flipped,
            spans,
            flipped_spans,
            cells: cells.iter().map(|c| (c.0, c.1, c.3)).collect(),
            forward,
            touched: touched.iter().map(|d| (d.0, d.1)).collect(),
            adjoint,
            image_len,
            phases,
            images: Mutex::new(BandImages::default()),
            arch: pulp::Arch::new(),
        }
    }

    /// Allocates the images the passes work on (left empty by [`Band::new`] until the route is
    /// taken).
    fn allocate_images(&mut self) {
        let images = self.images.get_mut().unwrap_or_else(|e| e.into_inner());
        *images = BandImages {
            t: vec![0.0; self.image_len + BLOCK],
            v: vec![0.0; self.phases * self.image_len + BLOCK],
            u: vec![0.0; self.cells.len()],
            s: vec![0.0; self.touched.len()],
        };
    }

    fn multiply_adds(&self) -> f64 {
        let taps = |spans: &[(usize, usize)], p: usize| -> usize {
            spans[p * self.side_y..(p + 1) * self.side_y]
                .iter()
                .map(|(lo, hi)| hi - lo)
                .sum()
        };
        let forward: usize = self.cells.iter().map(|c| taps(&self.spans, c.0)).sum();
        let per_dwell: usize = (0..self.phases).map(|p| taps(&self.flipped_spans, p)).sum();
        (forward + self.touched.len() * per_dwell) as f64
    }

    /// `out -= sum_{c in B} w_c k_c (k_c^T t)`.
    fn subtract(&self, t: &[f64], out: &mut [f64]) {
        let mut guard = self.images.lock().unwrap_or_else(|e| e.into_inner());
        let BandImages { t: image, v, u, s } = &mut *guard;
        for &(j, at) in &self.touched {
            image[at] = t[j];
        }
        self.run(false, image, u);
        for (&(phase, at, weight), &u) in self.cells.iter().zip(u.iter()) {
            v[phase * self.image_len + at] = weight * u;
        }
        self.run(true, v, s);
        for (&(j, _), &s) in self.touched.iter().zip(s.iter()) {
            out[j] -= s;
        }
    }

    /// The forward (`u`) or adjoint (`s`) pass over `image`, one task per [`BAND_TASK`] outputs.
    fn run(&self, adjoint: bool, image: &[f64], out: &mut [f64]) {
        let runs = if adjoint {
            &self.adjoint
        } else {
            &self.forward
        };
        out.par_chunks_mut(BAND_TASK)
            .zip(0..runs.tasks())
            .for_each(|(chunk, k)| {
                self.arch.dispatch(Pass {
                    band: self,
                    adjoint,
                    image,
                    runs: &runs.runs[runs.first[k]..runs.first[k + 1]],
                    out: chunk,
                })
            });
    }

    /// The outputs of `runs` (consecutive in `out`): forward, `u_c = sum_r sum_a T[a] K[c - a]`
    /// over the table of the run's phase; adjoint, `s_q = sum_p sum_r sum_a V_p[a] K[a - q]`
    /// over the turned tables of every phase. Each output sums its taps row by row, left to
    /// right, whatever run it falls in; a run takes each tap once for all its outputs (a
    /// contiguous multiply-add that vectorises).
    #[inline(always)]
    fn pass(&self, adjoint: bool, image: &[f64], runs: &[(usize, usize, usize)], out: &mut [f64]) {
        let (tables, spans) = if adjoint {
            (&self.flipped, &self.flipped_spans)
        } else {
            (&self.tables, &self.spans)
        };
        let mut next = 0;
        for &(phase, corner, len) in runs {
            let phases = if adjoint {
                0..self.phases
            } else {
                phase..phase + 1
            };
            for b in (0..len).step_by(BLOCK) {
                let mut acc = [0.0; BLOCK];
                for p in phases.clone() {
                    // The image runs on past the phase's into the next phase's and a slack of
                    // `BLOCK`: the lanes beyond the run read there and are dropped.
                    let image = if adjoint {
                        &image[p * self.image_len..]
                    } else {
                        image
                    };
                    for r in 0..self.side_y {
                        let (lo, hi) = spans[p * self.side_y + r];
                        let taps = &tables[(p * self.side_y + r) * self.side_x..][lo..hi];
                        let row = corner + r * self.width + lo + b;
                        for (a, &k) in taps.iter().enumerate() {
                            let from = &image[row + a..][..BLOCK];
                            acc.iter_mut().zip(from).for_each(|(v, x)| *v += k * x);
                        }
                    }
                }
                let take = BLOCK.min(len - b);
                out[next + b..next + b + take].copy_from_slice(&acc[..take]);
            }
            next += len;
        }
    }
}

/// One task of a band pass, run by [`pulp::Arch::dispatch`] so that its loops are compiled for
/// the CPU's widest vector instructions.
struct Pass<'a> {
    band: &'a Band,
    adjoint: bool,
    image: &'a [f64],
    runs: &'a [(usize, usize, usize)],
    out: &'a mut [f64],
}

impl pulp::WithSimd for Pass<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        self.band
            .pass(self.adjoint, self.image, self.runs, self.out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The separable box dilation against the definition: a cell is set when any cell within
    /// `rx` columns and `ry` rows of it is, at the corners and edges of the mask too.
    #[test]
    fn dilation_is_the_box_maximum() {
        let (w, h) = (13, 9);
        let mask: Vec<bool> = (0..w * h).map(|k| (k * 7919) % 23 == 0).collect();
        for (rx, ry) in [(0, 0), (1, 2), (3, 1), (20, 20)] {
            let got = dilate(&mask, w, rx, ry);
            for y in 0..h {
                for x in 0..w {
                    let want = (y.saturating_sub(ry)..(y + ry + 1).min(h)).any(|b| {
                        (x.saturating_sub(rx)..(x + rx + 1).min(w)).any(|a| mask[b * w + a])
                    });
                    assert_eq!(got[y * w + x], want, "({x}, {y}) with ({rx}, {ry})");
                }
            }
        }
    }
}
