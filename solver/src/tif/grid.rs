//! A TIF sampled on a regular grid, evaluated by bilinear interpolation and zero outside the grid.

use super::InfluenceFunction;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Relative tolerance for deciding that sample coordinates lie on one grid line.
pub const GRID_COORD_REL_TOL: f64 = 1e-6;
/// An offset within this many grid cells outside the grid's edge is on the edge (wider than the
/// phase stencils' rounding of offsets, `2^-25` of a map cell, for maps up to 30 times coarser
/// than the grid).
const ON_EDGE_CELLS: f64 = 1e-6;

/// Removal rates on a regular grid of offsets from the tool centre.
///
/// Node `(ix, iy)` sits at `(x0_mm + ix * pitch_x_mm, y0_mm + iy * pitch_y_mm)`; `rates` is row-major
/// (`rates[iy * nx + ix]`). Between nodes the rate is bilinear; outside the grid it is zero.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "GridTifSpec")]
pub struct GridTif {
    x0_mm: f64,
    y0_mm: f64,
    pitch_x_mm: f64,
    pitch_y_mm: f64,
    nx: usize,
    ny: usize,
    rates_nm_per_s: Vec<f64>,
    #[serde(skip)]
    support_radius_mm: f64,
    #[serde(skip)]
    inv_pitch: (f64, f64),
}

impl GridTif {
    /// Builds the grid from its origin, pitches, shape and row-major rates.
    ///
    /// Needs at least 2 x 2 nodes, positive pitches, finite non-negative rates and at least one
    /// positive rate.
    pub fn new(
        x0_mm: f64,
        y0_mm: f64,
        pitch_x_mm: f64,
        pitch_y_mm: f64,
        nx: usize,
        ny: usize,
        rates_nm_per_s: Vec<f64>,
    ) -> Result<Self> {
        if nx < 2 || ny < 2 {
            return Err(Error::NotRegularGrid {
                what: "TIF",
                why: format!("needs at least 2 x 2 samples, got {nx} x {ny}"),
            });
        }
        if !(pitch_x_mm.is_finite()
            && pitch_x_mm > 0.0
            && pitch_y_mm.is_finite()
            && pitch_y_mm > 0.0)
        {
            return Err(Error::NotRegularGrid {
                what: "TIF",
                why: format!("pitches must be positive, got {pitch_x_mm} x {pitch_y_mm} mm"),
            });
        }
        if !(x0_mm.is_finite() && y0_mm.is_finite()) {
            return Err(Error::invalid("TIF grid origin", "not finite"));
        }
        let expected = nx
            .checked_mul(ny)
            .ok_or_else(|| Error::invalid("TIF grid", "too large"))?;
        if rates_nm_per_s.len() != expected {
            return Err(Error::LengthMismatch {
                what: "TIF rates",
                got: rates_nm_per_s.len(),
                expected,
            });
        }
        let mut any_positive = false;
        for (k, &v) in rates_nm_per_s.iter().enumerate() {
            if !v.is_finite() {
                return Err(Error::NonFinite {
                    what: "TIF",
                    index: k,
                    detail: format!("rate_nm_per_s={v}"),
                });
            }
            if v < 0.0 {
                return Err(Error::invalid(
                    "TIF rate_nm_per_s",
                    format!(
                        "negative rate {v} at x_mm={}, y_mm={}: a tool cannot add material",
                        x0_mm + (k % nx) as f64 * pitch_x_mm,
                        y0_mm + (k / nx) as f64 * pitch_y_mm
                    ),
                ));
            }
            any_positive |= v > 0.0;
        }
        if !any_positive {
            return Err(Error::invalid("TIF rate_nm_per_s", "all rates are zero"));
        }
        let mut g = Self {
            x0_mm,
            y0_mm,
            pitch_x_mm,
            pitch_y_mm,
            nx,
            ny,
            rates_nm_per_s,
            support_radius_mm: 0.0,
            inv_pitch: (1.0 / pitch_x_mm, 1.0 / pitch_y_mm),
        };
        g.support_radius_mm = g.compute_support_radius();
        Ok(g)
    }

    /// Builds the grid from scattered samples `(x_mm, y_mm, rate)` in any order.
    ///
    /// The distinct x and y values (to [`GRID_COORD_REL_TOL`] of the pitch) must be equally spaced
    /// and every grid node must be given exactly once.
    pub fn from_samples(x_mm: &[f64], y_mm: &[f64], rate_nm_per_s: &[f64]) -> Result<Self> {
        let n = x_mm.len();
        if y_mm.len() != n || rate_nm_per_s.len() != n {
            return Err(Error::LengthMismatch {
                what: "TIF samples",
                got: y_mm.len().min(rate_nm_per_s.len()),
                expected: n,
            });
        }
        for (i, (&x, &y)) in x_mm.iter().zip(y_mm).enumerate() {
            if !(x.is_finite() && y.is_finite()) {
                return Err(Error::NonFinite {
                    what: "TIF",
                    index: i,
                    detail: format!("x_mm={x}, y_mm={y}"),
                });
            }
        }
        let (x0, px, nx) = axis_of(x_mm, "x")?;
        let (y0, py, ny) = axis_of(y_mm, "y")?;
        if nx.checked_mul(ny) != Some(n) {
            return Err(Error::NotRegularGrid {
                what: "TIF",
                why: format!(
                    "{n} samples do not fill the {nx} x {ny} grid of their distinct coordinates"
                ),
            });
        }
        let mut rates = vec![f64::NAN; n];
        for (k, ((&x, &y), &v)) in x_mm.iter().zip(y_mm).zip(rate_nm_per_s).enumerate() {
            let ix = ((x - x0) / px).round() as usize;
            let iy = ((y - y0) / py).round() as usize;
            let slot = rates
                .get_mut(iy * nx + ix)
                .ok_or_else(|| Error::NotRegularGrid {
                    what: "TIF",
                    why: format!("sample {k} at ({x}, {y}) mm is off the grid"),
                })?;
            if !slot.is_nan() {
                return Err(Error::NotRegularGrid {
                    what: "TIF",
                    why: format!("sample {k} at ({x}, {y}) mm repeats a grid node"),
                });
            }
            *slot = v;
        }
        Self::new(x0, y0, px, py, nx, ny, rates)
    }

    /// Grid shape `(nx, ny)`.
    pub fn shape(&self) -> (usize, usize) {
        (self.nx, self.ny)
    }

    /// Grid pitches `(x, y)`, mm.
    pub fn pitch_mm(&self) -> (f64, f64) {
        (self.pitch_x_mm, self.pitch_y_mm)
    }

    /// Coordinates of node `(0, 0)`, mm.
    pub fn origin_mm(&self) -> (f64, f64) {
        (self.x0_mm, self.y0_mm)
    }

    /// Row-major rates, nm/s.
    pub fn rates_nm_per_s(&self) -> &[f64] {
        &self.rates_nm_per_s
    }

    /// The grid as the columns of its CSV: `(x_mm, y_mm, rate_nm_per_s)` of every node,
    /// row-major (x fastest), the order of [`GridTif::rates_nm_per_s`].
    pub fn columns(&self) -> (Vec<f64>, Vec<f64>, &[f64]) {
        let n = self.nx * self.ny;
        let mut x = Vec::with_capacity(n);
        let mut y = Vec::with_capacity(n);
        for iy in 0..self.ny {
            for ix in 0..self.nx {
                x.push(self.x0_mm + ix as f64 * self.pitch_x_mm);
                y.push(self.y0_mm + iy as f64 * self.pitch_y_mm);
            }
        }
        (x, y, &self.rates_nm_per_s)
    }

    /// Largest sampled rate, nm/s.
    pub fn peak_rate_nm_per_s(&self) -> f64 {
        self.rates_nm_per_s.iter().copied().fold(0.0, f64::max)
    }

    /// Volumetric removal rate of the bilinear interpolant, mm^3/s (trapezoid rule is exact for it).
    pub fn volume_rate_mm3_per_s(&self) -> f64 {
        // The integral of a bilinear interpolant over a cell is the mean of its corners times the
        // cell area; summing cells gives the 2-D trapezoid rule with weights 1/4, 1/2, 1.
        let mut s = 0.0;
        for iy in 0..self.ny {
            let wy = if iy == 0 || iy + 1 == self.ny {
                0.5
            } else {
                1.0
            };
            for ix in 0..self.nx {
                let wx = if ix == 0 || ix + 1 == self.nx {
                    0.5
                } else {
                    1.0
                };
                s += wx * wy * self.node(ix, iy);
            }
        }
        s * self.pitch_x_mm * self.pitch_y_mm * 1e-6
    }

    /// Rate-weighted centroid of the nodes `(sum r x / sum r, sum r y / sum r)`, mm.
    pub fn centroid_mm(&self) -> (f64, f64) {
        let (mut sx, mut sy, mut s) = (0.0, 0.0, 0.0);
        for iy in 0..self.ny {
            for ix in 0..self.nx {
                let v = self.node(ix, iy);
                sx += v * (self.x0_mm + ix as f64 * self.pitch_x_mm);
                sy += v * (self.y0_mm + iy as f64 * self.pitch_y_mm);
                s += v;
            }
        }
        (sx / s, sy / s)
    }

    /// The same samples with the origin moved so that the rate-weighted centroid is at the tool
    /// centre `(0, 0)` (a pure shift of the coordinates, no interpolation).
    pub fn recentred(&self) -> Result<Self> {
        let (cx, cy) = self.centroid_mm();
        Self::new(
            self.x0_mm - cx,
            self.y0_mm - cy,
            self.pitch_x_mm,
            self.pitch_y_mm,
            self.nx,
            self.ny,
            self.rates_nm_per_s.clone(),
        )
    }

    /// Bilinear resampling onto a square grid of pitch `pitch_mm` with nodes at `k * pitch`
    /// covering this grid's extent.
    pub fn resampled(&self, pitch_mm: f64) -> Result<Self> {
        if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
            return Err(Error::invalid(
                "TIF resampling pitch_mm",
                format!("must be positive, got {pitch_mm}"),
            ));
        }
        let x1 = self.x0_mm + (self.nx - 1) as f64 * self.pitch_x_mm;
        let y1 = self.y0_mm + (self.ny - 1) as f64 * self.pitch_y_mm;
        let k = |v: f64, up: bool| {
            let f = v / pitch_mm;
            if up {
                (f - 1e-9).ceil()
            } else {
                (f + 1e-9).floor()
            }
        };
        let (kx0, kx1, ky0, ky1) = (
            k(self.x0_mm, true),
            k(x1, false),
            k(self.y0_mm, true),
            k(y1, false),
        );
        let (nx, ny) = (kx1 - kx0 + 1.0, ky1 - ky0 + 1.0);
        if !(nx >= 2.0 && ny >= 2.0) || nx * ny > 1e8 {
            return Err(Error::invalid(
                "TIF resampling pitch_mm",
                format!("{pitch_mm} mm gives a {nx} x {ny} grid"),
            ));
        }
        let (nx, ny) = (nx as usize, ny as usize);
        let mut rates = Vec::with_capacity(nx * ny);
        for iy in 0..ny {
            for ix in 0..nx {
                let x = (kx0 + ix as f64) * pitch_mm;
                let y = (ky0 + iy as f64) * pitch_mm;
                rates.push(self.rate_nm_per_s(x, y));
            }
        }
        Self::new(
            kx0 * pitch_mm,
            ky0 * pitch_mm,
            pitch_mm,
            pitch_mm,
            nx,
            ny,
            rates,
        )
    }

    /// The grid with every rate multiplied by `factor` (positive and finite).
    pub fn scaled(&self, factor: f64) -> Result<Self> {
        if !(factor.is_finite() && factor > 0.0) {
            return Err(Error::invalid(
                "TIF scale factor",
                format!("must be positive, got {factor}"),
            ));
        }
        Self::new(
            self.x0_mm,
            self.y0_mm,
            self.pitch_x_mm,
            self.pitch_y_mm,
            self.nx,
            self.ny,
            self.rates_nm_per_s.iter().map(|v| v * factor).collect(),
        )
    }

    /// Scaled so that the largest node is `peak_nm_per_s`.
    pub fn scaled_to_peak(&self, peak_nm_per_s: f64) -> Result<Self> {
        self.scaled(peak_nm_per_s / self.peak_rate_nm_per_s())
    }

    /// Scaled so that [`GridTif::volume_rate_mm3_per_s`] is `volume_mm3_per_s`.
    pub fn scaled_to_volume(&self, volume_mm3_per_s: f64) -> Result<Self> {
        self.scaled(volume_mm3_per_s / self.volume_rate_mm3_per_s())
    }

    /// Equivalent-circle full width at half maximum, mm: the diameter of the disc whose area is
    /// that of the nodes at or above half the peak (node count times cell area), `2 sqrt(A / pi)`.
    /// For a Gaussian this is `2 sqrt(2 ln 2) sigma` to within about a pitch.
    pub fn fwhm_mm(&self) -> f64 {
        let half = 0.5 * self.peak_rate_nm_per_s();
        let count = self.rates_nm_per_s.iter().filter(|&&v| v >= half).count();
        let area = count as f64 * self.pitch_x_mm * self.pitch_y_mm;
        2.0 * (area / std::f64::consts::PI).sqrt()
    }

    #[inline]
    fn node(&self, ix: usize, iy: usize) -> f64 {
        self.rates_nm_per_s
            .get(iy * self.nx + ix)
            .copied()
            .unwrap_or(0.0)
    }

    /// Farthest point from the tool centre of any cell with a non-zero corner.
    fn compute_support_radius(&self) -> f64 {
        let mut r2 = 0.0_f64;
        for iy in 0..self.ny - 1 {
            for ix in 0..self.nx - 1 {
                let nonzero = self.node(ix, iy) != 0.0
                    || self.node(ix + 1, iy) != 0.0
                    || self.node(ix, iy + 1) != 0.0
                    || self.node(ix + 1, iy + 1) != 0.0;
                if nonzero {
                    for (cx, cy) in [(ix, iy), (ix + 1, iy), (ix, iy + 1), (ix + 1, iy + 1)] {
                        let x = self.x0_mm + cx as f64 * self.pitch_x_mm;
                        let y = self.y0_mm + cy as f64 * self.pitch_y_mm;
                        r2 = r2.max(x * x + y * y);
                    }
                }
            }
        }
        r2.sqrt()
    }
}

/// The serialised form of a [`GridTif`]; deserialising validates it through [`GridTif::new`].
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct GridTifSpec {
    x0_mm: f64,
    y0_mm: f64,
    pitch_x_mm: f64,
    pitch_y_mm: f64,
    nx: usize,
    ny: usize,
    rates_nm_per_s: Vec<f64>,
}

impl TryFrom<GridTifSpec> for GridTif {
    type Error = Error;
    fn try_from(s: GridTifSpec) -> Result<Self> {
        GridTif::new(
            s.x0_mm,
            s.y0_mm,
            s.pitch_x_mm,
            s.pitch_y_mm,
            s.nx,
            s.ny,
            s.rates_nm_per_s,
        )
    }
}

/// Distinct sorted values of one coordinate: `(first, pitch, count)`; they must be equally spaced.
fn axis_of(v: &[f64], name: &str) -> Result<(f64, f64, usize)> {
    let mut s: Vec<f64> = v.to_vec();
    s.sort_by(f64::total_cmp);
    let (lo, hi) = match (s.first(), s.last()) {
        (Some(&lo), Some(&hi)) => (lo, hi),
        _ => {
            return Err(Error::NotRegularGrid {
                what: "TIF",
                why: "no samples".into(),
            })
        }
    };
    let span = hi - lo;
    let tol = GRID_COORD_REL_TOL * span.max(f64::MIN_POSITIVE);
    let mut distinct: Vec<f64> = Vec::new();
    for &a in &s {
        match distinct.last() {
            Some(&d) if (a - d).abs() <= tol => {}
            _ => distinct.push(a),
        }
    }
    let count = distinct.len();
    if count < 2 {
        return Err(Error::NotRegularGrid {
            what: "TIF",
            why: format!("only one distinct {name} value"),
        });
    }
    let pitch = span / (count - 1) as f64;
    for (k, &d) in distinct.iter().enumerate() {
        let expected = lo + k as f64 * pitch;
        if (d - expected).abs() > GRID_COORD_REL_TOL * pitch.max(span) + 1e-3 * pitch {
            return Err(Error::NotRegularGrid {
                what: "TIF",
                why: format!(
                    "{name} values are not equally spaced: {name}={d} mm where {expected} mm was expected (pitch {pitch} mm)"
                ),
            });
        }
    }
    Ok((lo, pitch, count))
}

impl InfluenceFunction for GridTif {
    #[inline]
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let max_x = (self.nx - 1) as f64;
        let max_y = (self.ny - 1) as f64;
        let fx = (dx_mm - self.x0_mm) * self.inv_pitch.0;
        let fy = (dy_mm - self.y0_mm) * self.inv_pitch.1;
        // Outside the grid (this also rejects NaN). The grid is closed: an offset on its edge up
        // to rounding (a dwell raster placed one grid half-width off the map puts whole rows of
        // pairs there) is on it, so rounding does not decide whether the edge samples count.
        let e = ON_EDGE_CELLS;
        if !(fx >= -e && fx <= max_x + e && fy >= -e && fy <= max_y + e) {
            return 0.0;
        }
        let (fx, fy) = (fx.clamp(0.0, max_x), fy.clamp(0.0, max_y));
        // Cell index, clamped so the far edge uses the last cell with weight 1 on its far nodes
        // (truncation is the floor here: fx, fy >= 0).
        let ix = (fx as usize).min(self.nx - 2);
        let iy = (fy as usize).min(self.ny - 2);
        let ax = fx - ix as f64;
        let ay = fy - iy as f64;
        let base = iy * self.nx + ix;
        let r = &self.rates_nm_per_s;
        let (v00, v10, v01, v11) = match (
            r.get(base),
            r.get(base + 1),
            r.get(base + self.nx),
            r.get(base + self.nx + 1),
        ) {
            (Some(a), Some(b), Some(c), Some(d)) => (*a, *b, *c, *d),
            _ => return 0.0,
        };
        (1.0 - ay) * ((1.0 - ax) * v00 + ax * v10) + ay * ((1.0 - ax) * v01 + ax * v11)
    }

    fn support_radius_mm(&self) -> f64 {
        self.support_radius_mm
    }

    /// Half-width of the grid: the largest |coordinate| of its edges.
    fn nominal_radius_mm(&self) -> f64 {
        let x1 = self.x0_mm + (self.nx - 1) as f64 * self.pitch_x_mm;
        let y1 = self.y0_mm + (self.ny - 1) as f64 * self.pitch_y_mm;
        [self.x0_mm, x1, self.y0_mm, y1]
            .iter()
            .fold(0.0, |a: f64, v| a.max(v.abs()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 3 x 2 grid at pitch (1, 2) mm from (-1, 0):
    /// row y=0: 0 1 2 ; row y=2: 4 5 6.
    fn small() -> GridTif {
        GridTif::new(
            -1.0,
            0.0,
            1.0,
            2.0,
            3,
            2,
            vec![0.0, 1.0, 2.0, 4.0, 5.0, 6.0],
        )
        .unwrap()
    }

    #[test]
    fn columns_are_the_nodes_row_major_and_read_back_to_the_grid() {
        let g = small();
        let (x, y, r) = g.columns();
        assert_eq!(x, vec![-1.0, 0.0, 1.0, -1.0, 0.0, 1.0]);
        assert_eq!(y, vec![0.0, 0.0, 0.0, 2.0, 2.0, 2.0]);
        assert_eq!(r, g.rates_nm_per_s());
        // Each node's rate is the grid's rate there, and the columns read back to the grid.
        for k in 0..r.len() {
            assert_eq!(g.rate_nm_per_s(x[k], y[k]), r[k]);
        }
        assert_eq!(GridTif::from_samples(&x, &y, r).unwrap(), g);
    }

    #[test]
    fn bilinear_matches_hand_values() {
        let g = small();
        // Nodes are reproduced exactly.
        assert_eq!(g.rate_nm_per_s(-1.0, 0.0), 0.0);
        assert_eq!(g.rate_nm_per_s(0.0, 0.0), 1.0);
        assert_eq!(g.rate_nm_per_s(1.0, 2.0), 6.0);
        // Centre of the first cell: mean of 0, 1, 4, 5 = 2.5.
        assert!((g.rate_nm_per_s(-0.5, 1.0) - 2.5).abs() < 1e-14);
        // (0.25, 0.5): cell ix=1, ax=0.25, ay=0.25:
        // 0.75*(0.75*1 + 0.25*2) + 0.25*(0.75*5 + 0.25*6) = 0.75*1.25 + 0.25*5.25 = 2.25.
        assert!((g.rate_nm_per_s(0.25, 0.5) - 2.25).abs() < 1e-14);
        // Outside: zero.
        assert_eq!(g.rate_nm_per_s(1.0001, 1.0), 0.0);
        assert_eq!(g.rate_nm_per_s(0.0, -0.001), 0.0);
        assert_eq!(g.rate_nm_per_s(f64::NAN, 0.0), 0.0);
    }

    /// An offset on the grid's edge up to rounding is on it: `x - X` for a map point and a dwell
    /// point one grid half-width apart lands a few ulps either side of the edge, and both sides
    /// give the edge value; a step of 1e-6 cell beyond it is outside.
    #[test]
    fn the_edge_is_on_the_grid_up_to_rounding() {
        let g = small();
        for (dx, dy, edge) in [
            (1.0, 1.0, 4.0),
            (-1.0, 1.0, 2.0),
            (0.0, 2.0, 5.0),
            (0.5, 0.0, 1.5),
        ] {
            for ulps in [-3.0, 0.0, 3.0] {
                let (x, y) = (dx + ulps * f64::EPSILON, dy + ulps * f64::EPSILON);
                assert!((g.rate_nm_per_s(x, y) - edge).abs() < 1e-12, "({x}, {y})");
            }
        }
        // 0.3 - 0.2 - 0.1 rounds to -2.8e-17: on the edge at y = 0.
        assert_eq!(g.rate_nm_per_s(0.0, 0.3 - 0.2 - 0.1), 1.0);
        assert_eq!(g.rate_nm_per_s(1.0 + 1e-5, 1.0), 0.0);
        assert_eq!(g.rate_nm_per_s(0.0, -2e-5), 0.0);
    }

    #[test]
    fn scattered_samples_any_order() {
        let xs = [1.0, -1.0, 0.0, 0.0, 1.0, -1.0];
        let ys = [2.0, 0.0, 0.0, 2.0, 0.0, 2.0];
        let vs = [6.0, 0.0, 1.0, 5.0, 2.0, 4.0];
        let g = GridTif::from_samples(&xs, &ys, &vs).unwrap();
        assert_eq!(g, small());
    }

    #[test]
    fn rejects_irregular_and_bad_values() {
        // Unequal spacing in x.
        let xs = [0.0, 1.0, 3.0, 0.0, 1.0, 3.0];
        let ys = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0];
        let vs = [1.0; 6];
        assert!(matches!(
            GridTif::from_samples(&xs, &ys, &vs),
            Err(Error::NotRegularGrid { .. })
        ));
        // A missing node.
        assert!(GridTif::from_samples(&xs[..5], &ys[..5], &vs[..5]).is_err());
        // Negative and all-zero rates.
        assert!(GridTif::new(0.0, 0.0, 1.0, 1.0, 2, 2, vec![1.0, -1.0, 0.0, 0.0]).is_err());
        assert!(GridTif::new(0.0, 0.0, 1.0, 1.0, 2, 2, vec![0.0; 4]).is_err());
    }

    #[test]
    fn resample_recentre_scale_fwhm() {
        use crate::tif::{GaussianTif, InfluenceFunction};
        // A Gaussian sampled off-centre at (0.7, -0.4) mm.
        let g = GaussianTif::new(1.5, 8.0, 6.0).unwrap();
        let (n, h) = (81usize, 0.15);
        let x0 = -6.0;
        let mut r = Vec::new();
        for iy in 0..n {
            for ix in 0..n {
                let (x, y) = (x0 + ix as f64 * h, x0 + iy as f64 * h);
                r.push(g.rate_nm_per_s(x - 0.7, y + 0.4));
            }
        }
        let grid = GridTif::new(x0, x0, h, h, n, n, r).unwrap();
        let (cx, cy) = grid.centroid_mm();
        // The truncated Gaussian is symmetric about its centre, but the grid clips it: tolerance
        // is the clipped mass fraction times the span.
        assert!(
            (cx - 0.7).abs() < 2e-3 && (cy + 0.4).abs() < 2e-3,
            "{cx} {cy}"
        );
        let c = grid.recentred().unwrap();
        let (ux, uy) = c.centroid_mm();
        assert!(ux.abs() < 1e-12 && uy.abs() < 1e-12);
        assert_eq!(c.rates_nm_per_s(), grid.rates_nm_per_s());
        // Resampling onto a finer grid keeps the bilinear values at the old nodes' positions.
        let fine = grid.resampled(0.05).unwrap();
        for (x, y) in [(0.75, -0.45), (-1.2, 2.1), (3.0, 0.0)] {
            assert!((fine.rate_nm_per_s(x, y) - grid.rate_nm_per_s(x, y)).abs() < 1e-9);
        }
        assert!(
            (fine.volume_rate_mm3_per_s() - grid.volume_rate_mm3_per_s()).abs()
                < 1e-3 * grid.volume_rate_mm3_per_s()
        );
        let p = grid.scaled_to_peak(20.0).unwrap();
        assert!((p.peak_rate_nm_per_s() - 20.0).abs() < 1e-12);
        let v = grid.scaled_to_volume(0.01).unwrap();
        assert!((v.volume_rate_mm3_per_s() - 0.01).abs() < 1e-15);
        // FWHM of a Gaussian: 2 sqrt(2 ln 2) sigma, within the node area quantisation (a pitch).
        let want = 2.0 * (2.0 * 2f64.ln()).sqrt() * 1.5;
        assert!(
            (grid.fwhm_mm() - want).abs() < h,
            "{} {want}",
            grid.fwhm_mm()
        );
        assert!(grid.scaled(0.0).is_err() && grid.resampled(-1.0).is_err());
    }

    #[test]
    fn volume_of_bilinear_pyramid() {
        // 3 x 3 grid, pitch 1, centre node 1, others 0: a pyramid of base 2 x 2 whose bilinear
        // volume is 4 cells * (1/4 * 1) = 1 (nm mm^2), i.e. 1e-6 mm^3/s.
        let mut r = vec![0.0; 9];
        r[4] = 1.0;
        let g = GridTif::new(-1.0, -1.0, 1.0, 1.0, 3, 3, r).unwrap();
        assert!((g.volume_rate_mm3_per_s() - 1e-6).abs() < 1e-18);
        assert!((g.support_radius_mm() - 2f64.sqrt()).abs() < 1e-15);
    }
}
