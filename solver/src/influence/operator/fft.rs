//! A matrix-free influence operator for map and dwell points on one regular lattice with a
//! shift-invariant TIF: `R t` and `R^T y` by zero-padded 2-D FFT convolution, so `R` is never
//! formed.
//!
//! Map points and dwell points must lie on a common lattice of pitch `h` (the map pitch; the
//! dwell pitch a multiple of it). With lattice indices `p_i` (map) and `q_j` (dwell),
//! `R[i, j] = K[p_i - q_j]`, `K[d] = TIF(d h)` for `|d| <= ceil(radius / h)`. `R t` scatters `t` onto
//! the lattice, convolves with `K` and gathers at the map points; `R^T y` scatters `y`, correlates
//! with `K` (multiplies by the conjugate transform) and gathers at the dwell points. The lattice
//! is padded so that the circular convolution equals the linear one on the points read (no
//! wrap-around: `f > max(c - q) + kr` and `f > max(q - c) + kr` over map cells `c` and dwell cells
//! `q`, so a map inset by the kernel radius in its dwell raster needs no padding), and further to
//! a size whose prime factors are 2, 3, 5 and 7.
//!
//! The transform is real-to-complex along x (realfft: `fx / 2 + 1` frequencies, half the work of
//! a complex transform) and complex along y (rustfft). Rows holding no input point are not
//! transformed forward, rows holding no output point not transformed back.
//!
//! When the dwell points lie on a coarser sub-lattice (steps `dx`, `dy`: a 1 mm raster on a
//! 0.5 mm map has `dx = dy = 2`), their side of each product runs on that sub-lattice: the
//! spectrum of `R t`'s input is the sub-lattice spectrum repeated (tiled), and `R^T y`, read only
//! on the sub-lattice, is transformed back there after its `dx dy` spectral aliases are summed
//! (folded) - the polyphase form of the convolution (e.g. Oppenheim & Schafer, "Discrete-Time
//! Signal Processing", sec. 4.7). The padded sizes are then multiples of the steps. With
//! `dx = dy = 2` this takes a quarter-size transform in place of a full one on each product.
//!
//! `R^T R t` (what a gradient step needs) does not return to the points between the products:
//! `R t` is transformed back along x one lattice row at a time, kept at the map cells (times
//! the number of map points in each: gathering and scattering in one) and transformed forward
//! again in the same pass. Every product runs as row passes (scatter or read a row, x transform)
//! and column passes (read a column of the row spectra, y transform, multiply, inverse), about
//! eight parallel loops for `R^T R t` against eighteen for `R t` and `R^T y` done one by one.
//!
//! Where the map covers most of the tool's reach, `R^T R t` takes the complement route instead
//! ([`super::complement`]): the kernel's autocorrelation convolved on the dwell lattice, less the
//! rows of the band of cells within reach whose map count is not one, summed directly. A cost
//! model counts both routes' work (`N log2 N` per transform of `N` cells against the band's
//! multiply-adds) and takes the cheaper.

use super::complement::{ComplementNormal, LatticeGeometry};
use super::lattice::{
    lattice_index, off_lattice_error, smooth_size, Buffers, Cells, Fill, Spectrum, Transforms,
    LATTICE_WHAT,
};
use super::{ColumnStats, ColumnSums, InfluenceOperator, LinearOperator, OperatorKind, Products};
use crate::error::{Error, Result};
use crate::tif::{lattice_reach, InfluenceFunction};
use realfft::RealFftPlanner;
use rustfft::num_complex::Complex;
use rustfft::FftPlanner;
use std::sync::Mutex;

/// Largest lattice (cells) the operator accepts: at about 32 bytes per cell (a real buffer and three
/// half-spectrum complex ones) 4e8 cells take ~13 GB.
const MAX_LATTICE_CELLS: usize = 400_000_000;
/// Bytes per lattice cell for the memory budget: the real buffer and three half-spectrum complex
/// ones (32), the dwell occupancy and map count masks (5), rounded up.
const LATTICE_BYTES_PER_CELL: f64 = 40.0;

/// Cost of a 2-D transform of `N` cells per `N log2 N`, in multiply-adds of the complement
/// route's band passes (the ratio of the two measured in `docs/largescale.md`, "The normal
/// product through the complement").
const FFT_WORK_PER_CELL_LOG2: f64 = 1.5;

/// The FFT convolution operator (see the module documentation).
pub struct FftOperator {
    fx: usize,
    fy: usize,
    /// The lattice pitch, mm, and the kernel's reach in cells (the padding).
    pitch_mm: f64,
    reach_cells: usize,
    kernel_hat: Vec<Complex<f64>>,
    /// Map cells on the lattice (shifted where the dwell points are on a sub-lattice).
    map: Cells,
    /// The dwell points: on the lattice, or on a sub-lattice coarser than it.
    dwell: DwellCells,
    /// Each column's sums over the map points (non-zeros, Jacobi scaling).
    columns: ColumnStats,
    transforms: Transforms,
    buffers: Mutex<Buffers>,
    /// The normal product through the kernel's autocorrelation and the band of cells whose map
    /// count is not one, where the cost model prefers it (see [`super::complement`]).
    complement: Option<ComplementNormal>,
}

/// How [`FftOperator`] forms `R^T P R t`.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum NormalRoute {
    /// By the cost model: the complement where it costs less than the direct route.
    Cheaper,
    /// `R t` on the lattice, masked, then `R^T` (tests).
    #[cfg_attr(not(test), allow(dead_code))]
    Direct,
    /// Through the complement wherever it can be built (tests).
    #[cfg_attr(not(test), allow(dead_code))]
    Complement,
}

/// Where the dwell side of each product runs.
enum DwellCells {
    /// Dwell cells on the lattice itself.
    Lattice(Cells),
    /// Dwell points on a coarser sub-lattice, with its own transforms and buffers.
    Sub(SubLattice),
}

/// Dwell points on the sub-lattice `o + (dx a, dy b)` of the lattice (a 1 mm raster on a 0.5 mm
/// map: `dx = dy = 2`). Their input to `R t` then has a spectrum that repeats `dx` times along x
/// and `dy` times along y, so it is computed on the `sx x sy` sub-lattice (`sx = fx / dx`) and
/// tiled; `R^T y` is read only on the sub-lattice, so its spectrum is folded (the `dx dy` aliases
/// summed) and transformed back on the sub-lattice. To keep the sub-lattice at the origin the map
/// side is shifted by `-o` (a circular shift, exact for the circular convolution).
struct SubLattice {
    dx: usize,
    dy: usize,
    sx: usize,
    sy: usize,
    transforms: Transforms,
    /// Dwell cells on the sub-lattice (`b * sx + a`).
    dwell: Cells,
    /// Locked after the lattice's buffers, never alone.
    buffers: Mutex<Buffers>,
}

impl std::fmt::Debug for FftOperator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FftOperator")
            .field("fx", &self.fx)
            .field("fy", &self.fy)
            .field("m", &self.map.len())
            .field("n", &self.ncols())
            .finish()
    }
}

impl FftOperator {
    /// Builds the operator for map points `(x, y)` and dwell points `(X, Y)` (mm) on a lattice of
    /// pitch `pitch_mm`; an error when a point is off the lattice or two dwell points share a cell.
    pub fn new<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        tif: &T,
    ) -> Result<Self> {
        Self::build(
            (map_x_mm, map_y_mm),
            (dwell_x_mm, dwell_y_mm),
            pitch_mm,
            tif,
            NormalRoute::Cheaper,
            true,
        )
    }

    /// As [`FftOperator::new`] for a few products (a removal `R t`): the normal product keeps
    /// its direct route, without the complement's set-up.
    pub fn for_products<T: InfluenceFunction + ?Sized>(
        map_x_mm: &[f64],
        map_y_mm: &[f64],
        dwell_x_mm: &[f64],
        dwell_y_mm: &[f64],
        pitch_mm: f64,
        tif: &T,
    ) -> Result<Self> {
        Self::build(
            (map_x_mm, map_y_mm),
            (dwell_x_mm, dwell_y_mm),
            pitch_mm,
            tif,
            NormalRoute::Direct,
            true,
        )
    }

    /// The lattice operator inside the NUFFT operator ([`super::nufft::NufftOperator`]), whose
    /// "dwell points" are every node of its fine lattice: its column sums (each node's taps
    /// over the map, `nodes x taps` work that on a 0.17 mm lattice under a 9 mm TIF dwarfs every
    /// product the solve takes) are not computed, since the NUFFT operator keeps its own over
    /// the real dwell points, and this operator's [`InfluenceOperator::nnz`],
    /// [`InfluenceOperator::empty_columns`] and [`LinearOperator::centred_column_norms_sq`] are
    /// then zero, empty and zero. The normal product's route is chosen by the cost model as in
    /// [`FftOperator::new`].
    pub(crate) fn for_nodes<T: InfluenceFunction + ?Sized>(
        map_mm: (&[f64], &[f64]),
        nodes_mm: (&[f64], &[f64]),
        pitch_mm: f64,
        tif: &T,
    ) -> Result<Self> {
        Self::build(map_mm, nodes_mm, pitch_mm, tif, NormalRoute::Cheaper, false)
    }

    /// As [`FftOperator::new`], with `R^T R t` through the direct route (`complement = false`)
    /// or the complement route wherever it can be built (tests of the solvers on either).
    #[cfg(test)]
    pub(crate) fn with_route<T: InfluenceFunction + ?Sized>(
        map_mm: (&[f64], &[f64]),
        dwell_mm: (&[f64], &[f64]),
        pitch_mm: f64,
        tif: &T,
        complement: bool,
    ) -> Result<Self> {
        let route = if complement {
            NormalRoute::Complement
        } else {
            NormalRoute::Direct
        };
        Self::build(map_mm, dwell_mm, pitch_mm, tif, route, true)
    }

    /// As [`FftOperator::new`], with the normal product's route chosen by `route`, and the
    /// column sums computed where `column_sums` (else zero: [`FftOperator::for_nodes`]).
    fn build<T: InfluenceFunction + ?Sized>(
        (map_x_mm, map_y_mm): (&[f64], &[f64]),
        (dwell_x_mm, dwell_y_mm): (&[f64], &[f64]),
        pitch_mm: f64,
        tif: &T,
        route: NormalRoute,
        column_sums: bool,
    ) -> Result<Self> {
        if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
            return Err(Error::invalid("lattice pitch", format!("{pitch_mm}")));
        }
        if map_x_mm.is_empty() || dwell_x_mm.is_empty() {
            return Err(Error::invalid("FFT operator", "needs map and dwell points"));
        }
        let OnLattice {
            map_ij,
            dwell_ij,
            nx,
            ny,
        } = OnLattice::index((map_x_mm, map_y_mm), (dwell_x_mm, dwell_y_mm), pitch_mm)?;
        let kr = lattice_reach(tif.support_radius_mm(), pitch_mm) as usize;
        let Padded {
            step: (dx, dy),
            offset: (ox, oy),
            size: (fx, fy),
        } = Padded::new(&map_ij, &dwell_ij, (nx, ny), kr, pitch_mm)?;
        let cell = |(i, j): (usize, usize)| j * fx + i;
        let map_cells: Vec<usize> = map_ij.iter().map(|&p| cell(p)).collect();
        let dwell_cells: Vec<usize> = dwell_ij.iter().map(|&p| cell(p)).collect();
        let mut seen = crate::budget::try_filled(LATTICE_WHAT, fx * fy, false)?;
        for (j, &c) in dwell_cells.iter().enumerate() {
            if std::mem::replace(&mut seen[c], true) {
                return Err(Error::invalid(
                    "dwell point",
                    format!("{j} shares a lattice cell with an earlier dwell point"),
                ));
            }
        }
        let mut planner = FftPlanner::<f64>::new();
        let mut real_planner = RealFftPlanner::<f64>::new();
        let transforms = Transforms::new(fx, fy, &mut planner, &mut real_planner);
        let mut buffers = Buffers::new(fx, fy)?;
        // Kernel K[d] = TIF(d h), wrapped, and its transform (in the transposed layout).
        let taps = kernel_taps(tif, kr, pitch_mm, &mut buffers.real, (fx, fy));
        transforms.spectrum(&mut buffers, Fill::Ready, Spectrum::Keep);
        let mut kernel_hat =
            crate::budget::try_filled(LATTICE_WHAT, buffers.columns.len(), Complex::new(0.0, 0.0))?;
        kernel_hat.copy_from_slice(&buffers.columns);
        // Column sums over the map points for the Jacobi scaling (a cell holding several map
        // points is several rows of R).
        let mut map_count = crate::budget::try_filled(LATTICE_WHAT, fx * fy, 0u32)?;
        for &c in &map_cells {
            map_count[c] += 1;
        }
        let sub = (dx * dy > 1)
            .then(|| -> Result<SubLattice> {
                let (sx, sy) = (fx / dx, fy / dy);
                let dwell_cells: Vec<usize> = dwell_ij
                    .iter()
                    .map(|&(i, j)| (j / dy) * sx + i / dx)
                    .collect();
                Ok(SubLattice {
                    dx,
                    dy,
                    sx,
                    sy,
                    transforms: Transforms::new(sx, sy, &mut planner, &mut real_planner),
                    dwell: Cells::new(dwell_cells, sx, sy),
                    buffers: Mutex::new(Buffers::new(sx, sy)?),
                })
            })
            .transpose()?;
        // With a sub-lattice the map side is shifted by -(ox, oy) (see `SubLattice`).
        let map_cells: Vec<usize> = if sub.is_some() {
            map_ij
                .iter()
                .map(|&(i, j)| cell(((i + fx - ox) % fx, (j + fy - oy) % fy)))
                .collect()
        } else {
            map_cells
        };
        let columns = if column_sums {
            self::column_sums(&dwell_ij, &taps, &map_count, (nx, ny), fx)
        } else {
            vec![ColumnSums::default(); dwell_ij.len()]
        };
        let complement = match route {
            NormalRoute::Direct => None,
            NormalRoute::Cheaper | NormalRoute::Complement => {
                let direct = match &sub {
                    Some(s) => direct_normal_work(fx * fy, s.sx * s.sy),
                    None => direct_normal_work(fx * fy, 0),
                };
                let geometry = LatticeGeometry {
                    dwell_ij: &dwell_ij,
                    nx,
                    ny,
                    map_count: &map_count,
                    row: fx,
                    taps: &taps,
                    reach: kr,
                    step: (dx, dy),
                    offset: (ox, oy),
                    held_bytes: fx as f64 * fy as f64 * LATTICE_BYTES_PER_CELL,
                };
                ComplementNormal::new(&geometry, |cells, band| {
                    route == NormalRoute::Complement || complement_normal_work(cells, band) < direct
                })
            }
        };
        Ok(Self {
            fx,
            fy,
            pitch_mm,
            reach_cells: kr,
            kernel_hat,
            map: Cells::new(map_cells, fx, fy),
            dwell: match sub {
                Some(sub) => DwellCells::Sub(sub),
                None => DwellCells::Lattice(Cells::new(dwell_cells, fx, fy)),
            },
            columns: ColumnStats::new(map_ij.len(), columns),
            transforms,
            buffers: Mutex::new(buffers),
            complement,
        })
    }

    /// The removals `R_k t` of the dwell `dwell_s` for each of `tifs` in place of the operator's
    /// own kernel, on the same lattice (one transform of each kernel and one convolution each:
    /// the removal of one plan under several TIFs). Each TIF's reach must be within the
    /// operator's (build it with the widest).
    pub fn removals_with(
        &self,
        dwell_s: &[f64],
        tifs: &[&dyn InfluenceFunction],
    ) -> Result<Vec<Vec<f64>>> {
        let (m, n) = (LinearOperator::nrows(self), LinearOperator::ncols(self));
        if dwell_s.len() != n {
            return Err(Error::LengthMismatch {
                what: "dwell_s",
                got: dwell_s.len(),
                expected: n,
            });
        }
        let mut out = Vec::with_capacity(tifs.len());
        for tif in tifs {
            let reach = lattice_reach(tif.support_radius_mm(), self.pitch_mm) as usize;
            if reach > self.reach_cells {
                return Err(Error::invalid(
                    "FFT kernel",
                    format!(
                        "reaches {reach} cells, beyond the operator's {}",
                        self.reach_cells
                    ),
                ));
            }
            let kernel_hat = {
                let mut guard = lock(&self.buffers);
                let buffers = &mut *guard;
                buffers.real.iter_mut().for_each(|v| *v = 0.0);
                kernel_taps(
                    *tif,
                    self.reach_cells,
                    self.pitch_mm,
                    &mut buffers.real,
                    (self.fx, self.fy),
                );
                self.transforms
                    .spectrum(buffers, Fill::Ready, Spectrum::Keep);
                buffers.columns.clone()
            };
            let mut h = vec![0.0; m];
            self.convolve_with(&kernel_hat, dwell_s, false, &mut h);
            out.push(h);
        }
        Ok(out)
    }

    /// Non-zero entries of the implicit matrix `R` (the number the sparse operator would store).
    pub fn nnz(&self) -> usize {
        self.columns.nnz()
    }

    /// Dwell points whose column is empty: no map point lies in the tool's reach.
    pub fn empty_columns(&self) -> Vec<usize> {
        self.columns.empty_columns()
    }

    /// The pitch, mm, of the lattice the map points lie on: the smallest step between distinct
    /// sorted x or y coordinates (steps below 1e-9 mm count as equal coordinates). `None` for
    /// fewer than two distinct coordinates on both axes. Whether every point (and every dwell
    /// point) is on that lattice is checked by [`FftOperator::new`].
    pub fn lattice_pitch_mm(map_x_mm: &[f64], map_y_mm: &[f64]) -> Option<f64> {
        let smallest_step = |v: &[f64]| -> f64 {
            let mut sorted: Vec<f64> = v.iter().copied().filter(|a| a.is_finite()).collect();
            sorted.sort_by(f64::total_cmp);
            sorted
                .windows(2)
                .map(|w| w[1] - w[0])
                .filter(|d| *d > 1e-9)
                .fold(f64::INFINITY, f64::min)
        };
        let pitch = smallest_step(map_x_mm).min(smallest_step(map_y_mm));
        pitch.is_finite().then_some(pitch)
    }

    /// `R t` (`conj = false`, from the dwell to the map cells) or `R^T y` (`conj = true`, from the
    /// map to the dwell cells): scatter, transform, multiply by `K^` (or its conjugate),
    /// transform back, gather; on the dwell sub-lattice where there is one (see [`SubLattice`]).
    /// Each step runs as few parallel passes as possible (a row pass scatters and transforms
    /// along x, a column pass reads its column of the row spectra and transforms along y).
    fn convolve(&self, input: &[f64], conj: bool, out: &mut [f64]) {
        self.convolve_with(&self.kernel_hat, input, conj, out);
    }

    /// [`FftOperator::convolve`] with the kernel spectrum `kernel_hat` (of this lattice).
    fn convolve_with(
        &self,
        kernel_hat: &[Complex<f64>],
        input: &[f64],
        conj: bool,
        out: &mut [f64],
    ) {
        let mut full_guard = lock(&self.buffers);
        let full = &mut *full_guard;
        let scale = self.scale();
        match &self.dwell {
            DwellCells::Sub(sub) if !conj => {
                let mut small = lock(&sub.buffers);
                self.tiled_spectrum(kernel_hat, sub, input, &mut small, full);
                self.transforms.to_real(full, &self.map.rows);
                self.map.gather(&full.real, scale, out);
            }
            DwellCells::Sub(sub) => {
                let mut small = lock(&sub.buffers);
                let small = &mut *small;
                self.transforms
                    .spectrum(full, Fill::Scatter(&self.map, input), Spectrum::Keep);
                self.fold_to_dwell(sub, full, small, out);
            }
            DwellCells::Lattice(dwell) => {
                let k = kernel_hat;
                let (from, to, after) = if conj {
                    (&self.map, dwell, Spectrum::Correlate(k))
                } else {
                    (dwell, &self.map, Spectrum::Convolve(k))
                };
                self.transforms
                    .spectrum(full, Fill::Scatter(from, input), after);
                self.transforms.to_real(full, &to.rows);
                to.gather(&full.real, scale, out);
            }
        }
    }

    /// `out = R^T R t` without leaving the lattice between the two products: `R t` transformed
    /// back along x row by row, kept at the map cells only (each times its number of map
    /// points, which is what gathering and scattering again would do) and transformed forward
    /// again in the same row pass.
    fn normal(&self, t: &[f64], out: &mut [f64]) {
        if let Some(c) = &self.complement {
            c.normal(t, out);
            return;
        }
        let mut full_guard = lock(&self.buffers);
        let full = &mut *full_guard;
        let scale = self.scale();
        let k = &self.kernel_hat;
        match &self.dwell {
            DwellCells::Sub(sub) => {
                let mut small = lock(&sub.buffers);
                let small = &mut *small;
                self.tiled_spectrum(&self.kernel_hat, sub, t, small, full);
                self.transforms
                    .spectrum(full, Fill::Masked(&self.map, scale), Spectrum::Keep);
                self.fold_to_dwell(sub, full, small, out);
            }
            DwellCells::Lattice(dwell) => {
                self.transforms
                    .spectrum(full, Fill::Scatter(dwell, t), Spectrum::Convolve(k));
                self.transforms.spectrum(
                    full,
                    Fill::Masked(&self.map, scale),
                    Spectrum::Correlate(k),
                );
                self.transforms.to_real(full, &dwell.rows);
                dwell.gather(&full.real, scale, out);
            }
        }
    }

    /// Normalisation of one forward and inverse transform pair on the lattice (the sub-lattice
    /// transforms are covered by it too: tiling and folding carry the rest).
    fn scale(&self) -> f64 {
        1.0 / (self.fx * self.fy) as f64
    }

    /// `full.columns` = the lattice transform of `K * t` for `t` on the sub-lattice, transformed
    /// back along y: `t`'s sub-lattice spectrum (in `small.columns`) tiled, times `K^`. The
    /// lattice spectrum of a signal on the sub-lattice through the origin is its sub-lattice
    /// spectrum repeated, `U[kx, ky] = S[kx mod sx, ky mod sy]`; `S` is stored for
    /// `kx <= sx / 2` only, the rest from `S[k] = conj(S[-k])`.
    fn tiled_spectrum(
        &self,
        kernel_hat: &[Complex<f64>],
        sub: &SubLattice,
        t: &[f64],
        small: &mut Buffers,
        full: &mut Buffers,
    ) {
        sub.transforms
            .spectrum(small, Fill::Scatter(&sub.dwell, t), Spectrum::Keep);
        let (fy, sx, sy) = (self.fy, sub.sx, sub.sy);
        let shx = sx / 2 + 1;
        let small = &small.columns;
        self.transforms
            .column_pass(&mut full.columns, |kx, column, scratch| {
                let kernel = &kernel_hat[kx * fy..(kx + 1) * fy];
                let kx = kx % sx;
                // `fy` is a multiple of `sy`: the column is `fy / sy` tiles of `from`.
                debug_assert_eq!(fy % sy, 0);
                let tiles = column.chunks_exact_mut(sy).zip(kernel.chunks_exact(sy));
                if kx < shx {
                    let from = &small[kx * sy..(kx + 1) * sy];
                    for (tile, k) in tiles {
                        for ((c, f), k) in tile.iter_mut().zip(from).zip(k) {
                            *c = f * k;
                        }
                    }
                } else {
                    // `S[-k]`: index `(sy - r) % sy` for `r = ky mod sy`.
                    let from = &small[(sx - kx) * sy..(sx - kx + 1) * sy];
                    for (tile, k) in tiles {
                        tile[0] = from[0].conj() * k[0];
                        for ((c, f), k) in tile[1..]
                            .iter_mut()
                            .zip(from[1..].iter().rev())
                            .zip(&k[1..])
                        {
                            *c = f.conj() * k;
                        }
                    }
                }
                self.transforms.ifft_y.process_with_scratch(column, scratch);
            });
    }

    /// `out` = `K^* y` read at the dwell points, from `y`'s lattice spectrum in `full.columns`:
    /// the lattice spectrum `V = conj(K^) Y` with its `dx dy` aliases summed (folded),
    /// `W[k] = sum_{p < dx, q < dy} V[kx + p sx, ky + q sy]` (`V[k] = conj(V[-k])` beyond the
    /// stored half, in a fixed order), transformed back on the sub-lattice and gathered.
    fn fold_to_dwell(
        &self,
        sub: &SubLattice,
        full: &Buffers,
        small: &mut Buffers,
        out: &mut [f64],
    ) {
        let (fx, fy, sx, sy) = (self.fx, self.fy, sub.sx, sub.sy);
        let hx = fx / 2 + 1;
        let (columns, kernel) = (&full.columns, &self.kernel_hat);
        let v = |kx: usize, ky: usize| -> Complex<f64> {
            if kx < hx {
                let i = kx * fy + ky;
                columns[i] * kernel[i].conj()
            } else {
                let i = (fx - kx) * fy + if ky == 0 { 0 } else { fy - ky };
                columns[i].conj() * kernel[i]
            }
        };
        sub.transforms
            .column_pass(&mut small.columns, |kx, column, scratch| {
                for (ky, w) in column.iter_mut().enumerate() {
                    let mut sum = Complex::new(0.0, 0.0);
                    for p in 0..sub.dx {
                        for q in 0..sub.dy {
                            sum += v(kx + p * sx, ky + q * sy);
                        }
                    }
                    *w = sum;
                }
                sub.transforms.ifft_y.process_with_scratch(column, scratch);
            });
        sub.transforms.to_real(small, &sub.dwell.rows);
        sub.dwell.gather(&small.real, self.scale(), out);
    }
}

/// Map and dwell points as indices on the lattice of `pitch_mm` through the map's lowest x and
/// y, shifted so that the lowest index is 0; `nx` x `ny` cells hold them all.
struct OnLattice {
    map_ij: Vec<(usize, usize)>,
    dwell_ij: Vec<(usize, usize)>,
    nx: usize,
    ny: usize,
}

impl OnLattice {
    /// The indices, or an input error naming a point off the lattice or a lattice too large to
    /// hold.
    fn index(
        (map_x_mm, map_y_mm): (&[f64], &[f64]),
        (dwell_x_mm, dwell_y_mm): (&[f64], &[f64]),
        pitch_mm: f64,
    ) -> Result<Self> {
        // The lattice runs through the map's lowest x and y; dwell points must lie on it too.
        let x0 = map_x_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let y0 = map_y_mm.iter().copied().fold(f64::INFINITY, f64::min);
        let idx = |xs: &[f64], ys: &[f64], what| -> Result<Vec<(i64, i64)>> {
            xs.iter()
                .zip(ys)
                .enumerate()
                .map(|(k, (&x, &y))| {
                    match (
                        lattice_index(x, x0, pitch_mm),
                        lattice_index(y, y0, pitch_mm),
                    ) {
                        (Some(i), Some(j)) => Ok((i, j)),
                        _ => Err(off_lattice_error(what, k, (x, y), pitch_mm, (x0, y0))),
                    }
                })
                .collect()
        };
        let map_signed = idx(map_x_mm, map_y_mm, "map point")?;
        let dwell_signed = idx(dwell_x_mm, dwell_y_mm, "dwell point")?;
        let (i0, j0) = map_signed
            .iter()
            .chain(&dwell_signed)
            .fold((i64::MAX, i64::MAX), |(a, b), p| (a.min(p.0), b.min(p.1)));
        let shift = |v: &[(i64, i64)]| -> Vec<(usize, usize)> {
            v.iter()
                .map(|&(i, j)| ((i - i0) as usize, (j - j0) as usize))
                .collect()
        };
        let (map_ij, dwell_ij) = (shift(&map_signed), shift(&dwell_signed));
        let nx = map_ij
            .iter()
            .chain(&dwell_ij)
            .map(|p| p.0)
            .max()
            .unwrap_or(0)
            + 1;
        let ny = map_ij
            .iter()
            .chain(&dwell_ij)
            .map(|p| p.1)
            .max()
            .unwrap_or(0)
            + 1;
        // A lattice too large to hold (points spread over a huge area) is an input error.
        if nx.saturating_mul(ny) > MAX_LATTICE_CELLS {
            return Err(Error::invalid(
                "FFT operator",
                format!(
                    "the points span {nx} x {ny} cells of {pitch_mm} mm, more than {MAX_LATTICE_CELLS}"
                ),
            ));
        }
        Ok(Self {
            map_ij,
            dwell_ij,
            nx,
            ny,
        })
    }
}

/// The padded periodic lattice of the transforms and the dwell points' sub-lattice on it.
struct Padded {
    /// Steps of the dwell points' sub-lattice (gcd of their index differences).
    step: (usize, usize),
    /// Offset of the sub-lattice (the first dwell point's index modulo the step).
    offset: (usize, usize),
    /// Cells of the padded lattice along x and y.
    size: (usize, usize),
}

impl Padded {
    /// Padded so that no wrap-around reaches an output (`wrap_free_size`), then up to a
    /// multiple of the step whose prime factors are 2, 3, 5 and 7 only, whose transforms are
    /// fastest (a prime factor such as 227 in 908 sends the transform to Rader's or
    /// Bluestein's algorithm); refused when the memory budget cannot hold it.
    fn new(
        map_ij: &[(usize, usize)],
        dwell_ij: &[(usize, usize)],
        (nx, ny): (usize, usize),
        kr: usize,
        pitch_mm: f64,
    ) -> Result<Self> {
        let (dx, dy) = (
            sub_lattice_step(dwell_ij.iter().map(|p| p.0)),
            sub_lattice_step(dwell_ij.iter().map(|p| p.1)),
        );
        let (ox, oy) = (dwell_ij[0].0 % dx, dwell_ij[0].1 % dy);
        let (need_x, need_y) = (
            wrap_free_size(map_ij.iter().map(|p| p.0), dwell_ij.iter().map(|p| p.0), kr),
            wrap_free_size(map_ij.iter().map(|p| p.1), dwell_ij.iter().map(|p| p.1), kr),
        );
        let (fx, fy) = (
            dx * smooth_size(need_x.max(nx).div_ceil(dx)),
            dy * smooth_size(need_y.max(ny).div_ceil(dy)),
        );
        crate::budget::check(
            "map and dwell points (FFT operator)",
            &format!(
                "the points span {nx} x {ny} cells of {pitch_mm} mm; an FFT lattice of {fx} x {fy} \
                 cells at {LATTICE_BYTES_PER_CELL} bytes each"
            ),
            fx as f64 * fy as f64 * LATTICE_BYTES_PER_CELL,
        )?;
        Ok(Self {
            step: (dx, dy),
            offset: (ox, oy),
            size: (fx, fy),
        })
    }
}

/// The kernel `K[d] = TIF(d h)` within the reach `kr`, written wrapped into `real` (a
/// `fx` x `fy` lattice, row-major), and its non-zero taps `(dx, dy, rate)`.
fn kernel_taps<T: InfluenceFunction + ?Sized>(
    tif: &T,
    kr: usize,
    pitch_mm: f64,
    real: &mut [f64],
    (fx, fy): (usize, usize),
) -> Vec<(isize, isize, f64)> {
    let k = kr as isize;
    let mut taps: Vec<(isize, isize, f64)> = Vec::new();
    for dy in -k..=k {
        for dx in -k..=k {
            let v = tif.rate_nm_per_s(dx as f64 * pitch_mm, dy as f64 * pitch_mm);
            if v != 0.0 {
                let ix = dx.rem_euclid(fx as isize) as usize;
                let iy = dy.rem_euclid(fy as isize) as usize;
                real[iy * fx + ix] = v;
                taps.push((dx, dy, v));
            }
        }
    }
    taps
}

/// Column sums of `R` for each dwell point over the map points it reaches (`map_count`: map
/// points per cell of the lattice of row length `fx`; the points lie within `nx` x `ny`).
fn column_sums(
    dwell_ij: &[(usize, usize)],
    taps: &[(isize, isize, f64)],
    map_count: &[u32],
    (nx, ny): (usize, usize),
    fx: usize,
) -> Vec<ColumnSums> {
    use rayon::prelude::*;
    // Each dwell point's sums on their own, in parallel (the same sums as in series).
    dwell_ij
        .par_iter()
        .map(|&(i, j)| {
            let mut sums = ColumnSums::default();
            for &(dx, dy, v) in taps {
                let (a, b) = (i as isize + dx, j as isize + dy);
                if a >= 0 && b >= 0 && (a as usize) < nx && (b as usize) < ny {
                    sums.add(map_count[b as usize * fx + a as usize], v);
                }
            }
            sums
        })
        .collect()
}

/// Work of the direct normal product (in units of one multiply-add of the band's passes): two
/// transforms on the lattice of `full` cells and two on the dwell sub-lattice's `sub` cells (four
/// on the lattice where there is no sub-lattice), `FFT_WORK_PER_CELL_LOG2 N log2 N` each.
fn direct_normal_work(full: usize, sub: usize) -> f64 {
    let fft = |n: usize| {
        let n = n as f64;
        FFT_WORK_PER_CELL_LOG2 * n * n.max(2.0).log2()
    };
    if sub == 0 {
        4.0 * fft(full)
    } else {
        2.0 * fft(full) + 2.0 * fft(sub)
    }
}

/// Work of the complement route in the same units: two transforms on its lattice of `cells`
/// cells and the band's `band` multiply-adds.
fn complement_normal_work(cells: f64, band: f64) -> f64 {
    2.0 * FFT_WORK_PER_CELL_LOG2 * cells * cells.max(2.0).log2() + band
}

/// The buffers behind `m` (a panic elsewhere leaves them as scratch, still usable).
fn lock(m: &Mutex<Buffers>) -> std::sync::MutexGuard<'_, Buffers> {
    match m.lock() {
        Ok(g) => g,
        Err(p) => p.into_inner(),
    }
}

/// Smallest transform length along one axis for which the circular convolution with a kernel of
/// radius `kr` equals the linear one at every output: an input `q` reaches an output `c` only
/// through `c - q` itself, never through `c - q -+ f`, when `f > max(c - q) + kr` and
/// `f > max(q - c) + kr` over map cells `c` and dwell cells `q` (both directions of the product).
/// A map inset by the kernel radius inside the dwell points needs no padding beyond the points.
fn wrap_free_size(
    map: impl Iterator<Item = usize> + Clone,
    dwell: impl Iterator<Item = usize> + Clone,
    kr: usize,
) -> usize {
    let range = |v: &mut dyn Iterator<Item = usize>| {
        v.fold((usize::MAX, 0), |(lo, hi), i| (lo.min(i), hi.max(i)))
    };
    let ((map_lo, map_hi), (dwell_lo, dwell_hi)) =
        (range(&mut map.clone()), range(&mut dwell.clone()));
    map_hi
        .saturating_sub(dwell_lo)
        .max(dwell_hi.saturating_sub(map_lo))
        + kr
        + 1
}

/// Step of the sub-lattice holding the indices `v` along one axis: the gcd of their differences
/// from the first (1 when all are equal).
fn sub_lattice_step(mut v: impl Iterator<Item = usize>) -> usize {
    let Some(first) = v.next() else { return 1 };
    let gcd = |mut a: usize, mut b: usize| {
        while b != 0 {
            (a, b) = (b, a % b);
        }
        a
    };
    v.fold(0, |g, i| gcd(g, i.abs_diff(first))).max(1)
}

impl LinearOperator for FftOperator {
    fn nrows(&self) -> usize {
        self.map.len()
    }

    fn products_cheap_per_dwell_point(&self) -> bool {
        true
    }

    fn ncols(&self) -> usize {
        match &self.dwell {
            DwellCells::Lattice(cells) => cells.len(),
            DwellCells::Sub(sub) => sub.dwell.len(),
        }
    }

    fn apply(&self, t: &[f64], out: &mut [f64]) {
        self.convolve(t, false, out);
    }

    fn apply_transpose(&self, y: &[f64], out: &mut [f64]) {
        self.convolve(y, true, out);
    }

    fn apply_normal(&self, t: &[f64], _scratch: &mut [f64], out: &mut [f64]) {
        self.normal(t, out);
    }

    fn centred_column_norms_sq(&self) -> Vec<f64> {
        self.columns.centred_norms_sq()
    }
}

impl InfluenceOperator for FftOperator {
    fn kind(&self) -> OperatorKind {
        OperatorKind::Fft
    }

    fn shape(&self) -> (usize, usize) {
        (LinearOperator::nrows(self), LinearOperator::ncols(self))
    }

    fn nnz(&self) -> usize {
        FftOperator::nnz(self)
    }

    fn empty_columns(&self) -> Vec<usize> {
        FftOperator::empty_columns(self)
    }

    /// The operator itself: its products need no copy, and it has no Gram matrix.
    fn products(&self, _normal_products: Option<usize>) -> Products<'_> {
        Products::Direct(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Products equal the brute-force sums within this relative tolerance.
    const BRUTE_REL_TOL: f64 = 1e-11;

    /// A deliberately asymmetric TIF (off-centre, tilted Gaussian), so that a mirrored or
    /// conjugated kernel cannot pass.
    struct Lopsided;

    impl InfluenceFunction for Lopsided {
        fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
            let (u, v) = (dx_mm - 0.3, dy_mm + 0.2);
            if dx_mm * dx_mm + dy_mm * dy_mm > 2.6 * 2.6 {
                return 0.0;
            }
            (1.0 + 0.2 * dx_mm - 0.1 * dy_mm) * (-(u * u + 2.0 * v * v) / 1.5).exp()
        }

        fn support_radius_mm(&self) -> f64 {
            2.6
        }
    }

    /// A map with x pitch 0.2 mm and y pitch 0.3 mm is refused with the pitch as written, not as
    /// the coordinates' differences round it.
    #[test]
    fn an_anisotropic_map_is_refused_with_its_pitch_as_written() {
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for j in 0..4 {
            for i in 0..5 {
                x.push(0.1 + i as f64 * 0.2);
                y.push(j as f64 * 0.3);
            }
        }
        let pitch = FftOperator::lattice_pitch_mm(&x, &y).unwrap();
        assert_ne!(pitch, 0.2);
        let err = FftOperator::new(&x, &y, &x, &y, pitch, &Lopsided)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            err.contains(
                "5 at (0.1, 0.3) mm is not on the map's 0.2 mm lattice through (0.1, 0) mm"
            ),
            "{err}"
        );
    }

    /// `R t` and `R^T y` against `R[i, j] = TIF(p_i - q_j)` summed directly, for dwell points on
    /// the whole lattice and on sub-lattices with several steps and offsets.
    /// Lattice pitch of the sub-lattice test cases, mm.
    const CASE_PITCH_MM: f64 = 0.5;
    /// The test map's size, cells.
    const CASE_MAP_CELLS: (usize, usize) = (17, 13);
    /// (steps, offsets, margin): dwell points from `margin` cells before the map to `margin`
    /// after it (the kernel radius is 6 cells), or inside it for a negative margin.
    const SUB_LATTICE_CASES: [(usize, usize, usize, usize, i64); 8] = [
        (1, 1, 0, 0, 6),
        (2, 2, 0, 0, 6),
        (2, 2, 1, 1, 6),
        (3, 2, 2, 1, 6),
        (1, 3, 0, 2, 6),
        (2, 2, 1, 0, 9),
        (1, 1, 0, 0, -4),
        (2, 2, 0, 1, -3),
    ];

    /// The test map: every cell of `CASE_MAP_CELLS`, one point measured twice (two rows of `R`,
    /// summed in `R^T y`).
    fn case_map() -> Vec<(f64, f64)> {
        let (h, (mx, my)) = (CASE_PITCH_MM, CASE_MAP_CELLS);
        let mut map: Vec<(f64, f64)> = (0..my)
            .flat_map(|j| (0..mx).map(move |i| (i as f64 * h, j as f64 * h)))
            .collect();
        map.push(map[40]);
        map
    }

    /// The dwell raster of one of `SUB_LATTICE_CASES`.
    fn case_dwell((dx, dy, ox, oy, margin): (usize, usize, usize, usize, i64)) -> Vec<(f64, f64)> {
        let (h, (mx, my)) = (CASE_PITCH_MM, CASE_MAP_CELLS);
        let (ax, ay) = (
            (mx as i64 + 2 * margin) as usize,
            (my as i64 + 2 * margin) as usize,
        );
        (0..ay / dy)
            .flat_map(|b| {
                (0..ax / dx).map(move |a| {
                    (
                        ((a * dx + ox) as f64 - margin as f64) * h,
                        ((b * dy + oy) as f64 - margin as f64) * h,
                    )
                })
            })
            .collect()
    }

    #[test]
    fn products_equal_the_direct_sums_on_every_sub_lattice() {
        let h = CASE_PITCH_MM;
        let map = case_map();
        for case in SUB_LATTICE_CASES {
            let (dx, dy, ox, oy, margin) = case;
            let dwell = case_dwell(case);
            let (x, y): (Vec<f64>, Vec<f64>) = map.iter().copied().unzip();
            let (qx, qy): (Vec<f64>, Vec<f64>) = dwell.iter().copied().unzip();
            let op = FftOperator::new(&x, &y, &qx, &qy, h, &Lopsided).unwrap();
            assert_eq!(matches!(op.dwell, DwellCells::Sub(_)), dx * dy > 1);
            let (m, n) = (map.len(), dwell.len());
            let t: Vec<f64> = (0..n).map(|j| 1.0 + ((j * 37) % 11) as f64 * 0.3).collect();
            let w: Vec<f64> = (0..m).map(|i| ((i * 13) % 7) as f64 - 3.0).collect();
            let r = |i: usize, j: usize| Lopsided.rate_nm_per_s(x[i] - qx[j], y[i] - qy[j]);
            let (mut rt, mut rtw) = (vec![0.0; m], vec![0.0; n]);
            op.apply(&t, &mut rt);
            op.apply_transpose(&w, &mut rtw);
            let scale = (0..m).map(|i| (0..n).map(|j| (r(i, j) * t[j]).abs()).sum::<f64>());
            for (i, s) in scale.enumerate() {
                let direct: f64 = (0..n).map(|j| r(i, j) * t[j]).sum();
                assert!(
                    (rt[i] - direct).abs() <= BRUTE_REL_TOL * s.max(1.0),
                    "steps ({dx}, {dy}) offset ({ox}, {oy}) margin {margin}: (R t)[{i}] {} vs {direct}",
                    rt[i]
                );
            }
            let norms = op.centred_column_norms_sq();
            for (j, got) in norms.iter().enumerate() {
                let (s1, s2) =
                    (0..m).fold((0.0, 0.0), |(a, b), i| (a + r(i, j), b + r(i, j).powi(2)));
                let direct = s2 - s1 * s1 / m as f64;
                assert!(
                    (got - direct).abs() <= BRUTE_REL_TOL * s2.max(1.0),
                    "margin {margin}: centred column norm {j} {got} vs {direct}"
                );
            }
            for (j, got) in rtw.iter().enumerate() {
                let direct: f64 = (0..m).map(|i| r(i, j) * w[i]).sum();
                let s: f64 = (0..m).map(|i| (r(i, j) * w[i]).abs()).sum();
                assert!(
                    (got - direct).abs() <= BRUTE_REL_TOL * s.max(1.0),
                    "steps ({dx}, {dy}) offset ({ox}, {oy}) margin {margin}: (R^T y)[{j}] {got} vs {direct}"
                );
            }
            // R^T R t in one pass over the lattice (the repeated map point counts twice).
            let mut rtrt = vec![0.0; n];
            op.apply_normal(&t, &mut rt, &mut rtrt);
            let direct_rt: Vec<f64> = (0..m)
                .map(|i| (0..n).map(|j| r(i, j) * t[j]).sum())
                .collect();
            let abs_rt: Vec<f64> = (0..m)
                .map(|i| (0..n).map(|j| (r(i, j) * t[j]).abs()).sum())
                .collect();
            for (j, got) in rtrt.iter().enumerate() {
                let direct: f64 = (0..m).map(|i| r(i, j) * direct_rt[i]).sum();
                let s: f64 = (0..m).map(|i| r(i, j).abs() * abs_rt[i]).sum();
                assert!(
                    (got - direct).abs() <= BRUTE_REL_TOL * s.max(1.0),
                    "steps ({dx}, {dy}) offset ({ox}, {oy}) margin {margin}: (R^T R t)[{j}] {got} vs {direct}"
                );
            }
        }
    }

    /// Another kernel's removal on the same lattice: `removals_with` gives, for the operator's
    /// own TIF and a shifted, narrower one, the direct sums `sum_j K(x_i - q_j) t_j` on every
    /// sub-lattice case; a kernel reaching beyond the operator's padding is refused.
    #[test]
    fn removals_with_other_kernels_are_their_direct_sums() {
        struct Shifted;
        impl InfluenceFunction for Shifted {
            fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
                Lopsided.rate_nm_per_s((dx_mm - 0.05) / 0.9, dy_mm / 0.9) / 0.81
            }
            fn support_radius_mm(&self) -> f64 {
                0.9 * 2.6 + 0.05
            }
        }
        let h = CASE_PITCH_MM;
        let map = case_map();
        let (x, y): (Vec<f64>, Vec<f64>) = map.iter().copied().unzip();
        for case in SUB_LATTICE_CASES {
            let dwell = case_dwell(case);
            let (qx, qy): (Vec<f64>, Vec<f64>) = dwell.iter().copied().unzip();
            let op = FftOperator::for_products(&x, &y, &qx, &qy, h, &Lopsided).unwrap();
            let t: Vec<f64> = (0..dwell.len())
                .map(|j| 1.0 + ((j * 37) % 11) as f64 * 0.3)
                .collect();
            let got = op.removals_with(&t, &[&Lopsided, &Shifted]).unwrap();
            let tifs: [&dyn InfluenceFunction; 2] = [&Lopsided, &Shifted];
            for (k, tif) in tifs.iter().enumerate() {
                for i in 0..map.len() {
                    let terms = (0..dwell.len())
                        .map(|j| tif.rate_nm_per_s(x[i] - qx[j], y[i] - qy[j]) * t[j]);
                    let (direct, scale) = terms.fold((0.0, 0.0), |(a, b), v| (a + v, b + v.abs()));
                    assert!(
                        (got[k][i] - direct).abs() <= BRUTE_REL_TOL * scale.max(1.0),
                        "{case:?} kernel {k} point {i}: {} vs {direct}",
                        got[k][i]
                    );
                }
            }
        }
        struct Wide;
        impl InfluenceFunction for Wide {
            fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
                Lopsided.rate_nm_per_s(dx_mm / 2.0, dy_mm / 2.0)
            }
            fn support_radius_mm(&self) -> f64 {
                5.2
            }
        }
        let dwell = case_dwell(SUB_LATTICE_CASES[0]);
        let (qx, qy): (Vec<f64>, Vec<f64>) = dwell.iter().copied().unzip();
        let op = FftOperator::for_products(&x, &y, &qx, &qy, h, &Lopsided).unwrap();
        assert!(op.removals_with(&vec![1.0; dwell.len()], &[&Wide]).is_err());
    }

    /// `R^T P R t` through the lattice and through the complement (the kernel's autocorrelation
    /// less the band of cells whose map count is not one) against the sums over the map points,
    /// on every sub-lattice case and on three dwell points (fewer dwell columns than the
    /// autocorrelation's radius), for the full map (one cell counted twice) and for the map with
    /// a hole. The complement's rounding is relative to the sums over every cell of the
    /// unbounded lattice, which the tolerance takes.
    #[test]
    fn both_normal_routes_equal_the_direct_sums() {
        let h = CASE_PITCH_MM;
        let full = case_map();
        let holed: Vec<(f64, f64)> = full
            .iter()
            .copied()
            .filter(|&(x, y)| (x - 4.0).powi(2) + (y - 3.0).powi(2) > 1.2 * 1.2)
            .collect();
        assert!(holed.len() + 15 < full.len());
        let reach = (Lopsided.support_radius_mm() / h).ceil() as i64;
        for map in [&full, &holed] {
            let (x, y): (Vec<f64>, Vec<f64>) = map.iter().copied().unzip();
            let few = vec![(2.0, 2.0), (2.5, 2.0), (2.0, 3.5)];
            let rasters = SUB_LATTICE_CASES.map(|c| (format!("{c:?}"), case_dwell(c)));
            for (case, dwell) in rasters.into_iter().chain([("few".to_string(), few)]) {
                let (qx, qy): (Vec<f64>, Vec<f64>) = dwell.iter().copied().unzip();
                let (m, n) = (map.len(), dwell.len());
                let t: Vec<f64> = (0..n).map(|j| 1.0 + ((j * 37) % 11) as f64 * 0.3).collect();
                let k = |ex: f64, ey: f64| Lopsided.rate_nm_per_s(ex, ey);
                let r = |i: usize, j: usize| k(x[i] - qx[j], y[i] - qy[j]);
                let rt: Vec<f64> = (0..m)
                    .map(|i| (0..n).map(|j| r(i, j) * t[j]).sum())
                    .collect();
                // Scale: sum over every cell within reach of `|K| (|K| |t|)`.
                let cell = |v: f64| (v / h).round() as i64;
                let lo = |v: &[f64]| v.iter().map(|&a| cell(a)).min().unwrap_or(0) - reach;
                let hi = |v: &[f64]| v.iter().map(|&a| cell(a)).max().unwrap_or(0) + reach;
                let cells: Vec<(f64, f64)> = (lo(&qy)..=hi(&qy))
                    .flat_map(|cy| {
                        (lo(&qx)..=hi(&qx)).map(move |cx| (cx as f64 * h, cy as f64 * h))
                    })
                    .collect();
                let abs_rt: Vec<f64> = cells
                    .iter()
                    .map(|&(cx, cy)| {
                        (0..n)
                            .map(|j| (k(cx - qx[j], cy - qy[j]) * t[j]).abs())
                            .sum()
                    })
                    .collect();
                for route in [NormalRoute::Direct, NormalRoute::Complement] {
                    let op = FftOperator::build((&x, &y), (&qx, &qy), h, &Lopsided, route, true)
                        .unwrap();
                    assert_eq!(op.complement.is_some(), route == NormalRoute::Complement);
                    let mut got = vec![0.0; n];
                    op.apply_normal(&t, &mut vec![0.0; m], &mut got);
                    for (j, got) in got.iter().enumerate() {
                        let direct: f64 = (0..m).map(|i| r(i, j) * rt[i]).sum();
                        let s: f64 = cells
                            .iter()
                            .zip(&abs_rt)
                            .map(|(&(cx, cy), a)| k(cx - qx[j], cy - qy[j]).abs() * a)
                            .sum();
                        assert!(
                            (got - direct).abs() <= BRUTE_REL_TOL * s.max(1.0),
                            "{route:?}, case {case}, {m} map points: (R^T R t)[{j}] {got} vs {direct}"
                        );
                    }
                }
            }
        }
    }

    /// The complement route's band passes split their outputs into tasks of whole runs, each
    /// output summing its taps in one order: the product is the same to the bit for any number
    /// of threads, on a map with a hole whose band spans many tasks.
    #[test]
    fn the_complement_route_does_not_depend_on_the_thread_count() {
        let h = CASE_PITCH_MM;
        let map: Vec<(f64, f64)> = (0..70)
            .flat_map(|j| (0..90).map(move |i| (i as f64 * h, j as f64 * h)))
            .filter(|&(x, y)| (x - 20.0).powi(2) + (y - 15.0).powi(2) > 16.0)
            .collect();
        let dwell: Vec<(f64, f64)> = (0..41)
            .flat_map(|b| {
                (0..51).map(move |a| ((2 * a) as f64 * h - 3.0, (2 * b) as f64 * h - 3.0))
            })
            .collect();
        let (x, y): (Vec<f64>, Vec<f64>) = map.iter().copied().unzip();
        let (qx, qy): (Vec<f64>, Vec<f64>) = dwell.iter().copied().unzip();
        let op = FftOperator::build(
            (&x, &y),
            (&qx, &qy),
            h,
            &Lopsided,
            NormalRoute::Complement,
            true,
        )
        .unwrap();
        let band = &op.complement.as_ref().unwrap().band_runs();
        assert!(band.0 > 4 && band.1 > 4, "band tasks {band:?}");
        let t: Vec<f64> = (0..dwell.len()).map(|j| ((j * 17) % 11) as f64).collect();
        let run = |threads: usize| {
            crate::test_support::on_threads(threads, || {
                let mut normal = vec![0.0; dwell.len()];
                op.apply_normal(&t, &mut vec![0.0; map.len()], &mut normal);
                normal
            })
        };
        let one = run(1);
        for threads in [2, 3, 5] {
            assert!(run(threads) == one, "{threads} threads");
        }
    }

    #[test]
    fn wrap_free_size_covers_both_directions() {
        // Map cells 12..=271 inset by the radius 12 in dwell cells 0..=283: 284 = 271 - 0 + 13.
        assert_eq!(wrap_free_size(12..=271, (0..=283).step_by(2), 12), 284);
        // Dwell points inside the map: offsets -60..=59 (the lattice must still hold all 100).
        assert_eq!(wrap_free_size(0..=99, 40..=60, 5), 66);
        assert_eq!(wrap_free_size(0..=9, 0..=9, 0), 10);
    }

    #[test]
    fn sub_lattice_steps_are_the_gcd_of_the_index_differences() {
        assert_eq!(sub_lattice_step([4usize, 6, 10].into_iter()), 2);
        assert_eq!(sub_lattice_step([3usize, 9, 21, 6].into_iter()), 3);
        assert_eq!(sub_lattice_step([5usize, 5].into_iter()), 1);
        assert_eq!(sub_lattice_step([2usize, 7].into_iter()), 5);
        assert_eq!(sub_lattice_step(std::iter::empty()), 1);
    }

    #[test]
    fn smooth_sizes_have_only_small_prime_factors() {
        // 908 = 4 x 227 and 2014 = 2 x 19 x 53; 945 = 3^3 x 5 x 7, 2016 = 2^5 x 3^2 x 7.
        assert_eq!(smooth_size(908), 945);
        assert_eq!(smooth_size(2014), 2016);
        assert_eq!(smooth_size(11), 12);
        assert_eq!(smooth_size(64), 64);
        assert_eq!(smooth_size(1), 1);
        for n in 1..2000 {
            let k = smooth_size(n);
            assert!(k >= n && k < n + n / 4 + 2, "{n} -> {k}");
        }
    }
}
