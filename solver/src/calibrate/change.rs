//! The measured change of a run: the map before, resampled at the points of the map after.
//!
//! The map measured before is held on its own lattice (an interferometer's pixels, dropouts
//! allowed) and read at the after map's points, moved by the shift `s` between the two
//! measurements: `d_i(s) = B(x_i + s) - A(x_i)`, bicubically where the sixteen nodes around are
//! present, bilinearly otherwise, extrapolated linearly up to one pixel beyond the edge. A point counts
//! only where it lies inside the before map and the before map is defined around `x_i + s` for
//! every shift up to one before-pixel, so the set of points does not change while the shift is
//! fitted; the others (dropouts, points outside) are skipped and counted.

use crate::error::{Error, Result};
use crate::map::HeightMap;

/// Relative distance from a lattice node within which a coordinate counts as on it.
const ON_NODE_REL: f64 = 1e-4;

/// A map on a regular lattice, missing nodes as NaN.
#[derive(Debug, Clone, PartialEq)]
pub struct GriddedMap {
    origin_mm: (f64, f64),
    pitch_mm: (f64, f64),
    nx: usize,
    ny: usize,
    z_nm: Vec<f64>,
}

impl GriddedMap {
    /// The lattice of `map`: along each axis the smallest step between distinct coordinates,
    /// every point on a node.
    ///
    /// Errors: a map whose points do not lie on one lattice, or whose lattice would be more than
    /// sixteen times its point count.
    pub fn of(map: &HeightMap, what: &str) -> Result<Self> {
        let axis = |v: &[f64]| -> (f64, f64, usize) {
            let mut s: Vec<f64> = v.to_vec();
            s.sort_by(f64::total_cmp);
            let (lo, hi) = (s[0], s[s.len() - 1]);
            let tol = 1e-9 * (hi - lo).max(1.0);
            let pitch = s
                .windows(2)
                .map(|w| w[1] - w[0])
                .filter(|&d| d > tol)
                .fold(f64::INFINITY, f64::min);
            if pitch.is_finite() {
                (lo, pitch, ((hi - lo) / pitch).round() as usize + 1)
            } else {
                (lo, 1.0, 1)
            }
        };
        if map.len() < 4 {
            return Err(Error::invalid(what, "needs at least four points"));
        }
        let (x0, px, nx) = axis(map.x_mm());
        let (y0, py, ny) = axis(map.y_mm());
        if nx < 2 || ny < 2 || (nx as f64) * (ny as f64) > 16.0 * map.len() as f64 {
            return Err(Error::NotRegularGrid {
                what: "calibration map",
                why: format!(
                    "{what}: its points do not fill a regular grid ({nx} x {ny} nodes for {} points)",
                    map.len()
                ),
            });
        }
        let mut z = vec![f64::NAN; nx * ny];
        for (k, ((&x, &y), &v)) in map
            .x_mm()
            .iter()
            .zip(map.y_mm())
            .zip(map.z_nm())
            .enumerate()
        {
            let (fx, fy) = ((x - x0) / px, (y - y0) / py);
            let (ix, iy) = (fx.round(), fy.round());
            if (fx - ix).abs() > ON_NODE_REL || (fy - iy).abs() > ON_NODE_REL {
                return Err(Error::NotRegularGrid {
                    what: "calibration map",
                    why: format!(
                        "{what}: point {k} at ({x}, {y}) mm is off the grid of pitch {px} x {py} mm"
                    ),
                });
            }
            z[iy as usize * nx + ix as usize] = v;
        }
        Ok(Self {
            origin_mm: (x0, y0),
            pitch_mm: (px, py),
            nx,
            ny,
            z_nm: z,
        })
    }

    /// Pitch along x and y, mm.
    pub fn pitch_mm(&self) -> (f64, f64) {
        self.pitch_mm
    }

    /// The lattice cell of `(x, y)` and its fractions, when inside.
    /// The lattice cell of `(x, y)` and its fractions; up to one pixel beyond the grid's edge the
    /// edge cell, its fraction outside `[0, 1]` (so a shifted read of an edge point stays
    /// defined, extrapolated linearly).
    fn cell(&self, x: f64, y: f64) -> Option<(usize, usize, f64, f64)> {
        let (max_x, max_y) = ((self.nx - 1) as f64, (self.ny - 1) as f64);
        let fx = (x - self.origin_mm.0) / self.pitch_mm.0;
        let fy = (y - self.origin_mm.1) / self.pitch_mm.1;
        if !(fx >= -1.0 && fy >= -1.0 && fx <= max_x + 1.0 && fy <= max_y + 1.0) {
            return None;
        }
        // Beyond the edge the edge cell's bilinear form extrapolates linearly.
        let (ix, iy) = (
            (fx.max(0.0).floor() as usize).min(self.nx.saturating_sub(2)),
            (fy.max(0.0).floor() as usize).min(self.ny.saturating_sub(2)),
        );
        Some((ix, iy, fx - ix as f64, fy - iy as f64))
    }

    /// Whether the sixteen nodes of the bicubic read at `(x, y)` are all present.
    pub fn has_stencil(&self, x: f64, y: f64) -> bool {
        let Some((ix, iy, _, _)) = self.cell(x, y) else {
            return false;
        };
        if ix == 0 || iy == 0 || ix + 2 >= self.nx || iy + 2 >= self.ny {
            return false;
        }
        (iy - 1..=iy + 2).all(|j| (ix - 1..=ix + 2).all(|i| self.z_nm[j * self.nx + i].is_finite()))
    }

    /// The height at `(x, y)`: Catmull-Rom bicubic over the sixteen nodes around it where they
    /// are all present (exact for quadratics, error `O(h⁴)` for smooth maps, so a fine ripple a
    /// shift moves across a pixel is not smoothed away), bilinear between the four around it
    /// otherwise; `None` where one of those four is missing or the point is outside.
    pub fn at(&self, x: f64, y: f64) -> Option<f64> {
        self.read(x, y).map(|(v, _)| v)
    }

    /// [`GriddedMap::at`] and the sum of the squared interpolation weights: the factor by which
    /// the read scales the variance of white noise on the nodes.
    pub fn read(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let (ix, iy, ax, ay) = self.cell(x, y)?;
        let z = |i: usize, j: usize| self.z_nm[j * self.nx + i];
        let bilinear = (1.0 - ay) * ((1.0 - ax) * z(ix, iy) + ax * z(ix + 1, iy))
            + ay * ((1.0 - ax) * z(ix, iy + 1) + ax * z(ix + 1, iy + 1));
        if !bilinear.is_finite() {
            return None;
        }
        let bilinear_gain = ((1.0 - ax).powi(2) + ax * ax) * ((1.0 - ay).powi(2) + ay * ay);
        if ix == 0 || iy == 0 || ix + 2 >= self.nx || iy + 2 >= self.ny {
            return Some((bilinear, bilinear_gain));
        }
        // Catmull-Rom weights of the four nodes at offsets -1, 0, 1, 2 for fraction t.
        let weights = |t: f64| {
            let (t2, t3) = (t * t, t * t * t);
            [
                0.5 * (-t3 + 2.0 * t2 - t),
                0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
                0.5 * (-3.0 * t3 + 4.0 * t2 + t),
                0.5 * (t3 - t2),
            ]
        };
        let (wx, wy) = (weights(ax), weights(ay));
        let mut v = 0.0;
        for (b, wyb) in wy.iter().enumerate() {
            for (a, wxa) in wx.iter().enumerate() {
                v += wyb * wxa * z(ix + a - 1, iy + b - 1);
            }
        }
        let gain = wx.iter().map(|w| w * w).sum::<f64>() * wy.iter().map(|w| w * w).sum::<f64>();
        Some(if v.is_finite() {
            (v, gain)
        } else {
            (bilinear, bilinear_gain)
        })
    }
}

/// The measured change of a run at the points where both maps have data.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasuredChange {
    /// x of the points used, mm.
    pub x_mm: Vec<f64>,
    /// y of the points used, mm.
    pub y_mm: Vec<f64>,
    /// The map after the run at the points, nm.
    pub after_nm: Vec<f64>,
    /// The map before the run on its lattice.
    pub before: GriddedMap,
    /// Points of the after map skipped: a dropout or the edge of the before map within one pixel.
    pub skipped: usize,
}

impl MeasuredChange {
    /// The change between `before` and `after` (module documentation).
    ///
    /// Errors: a before map not on a regular grid; fewer than 16 points in common.
    pub fn new(before: &HeightMap, after: &HeightMap) -> Result<Self> {
        let grid = GriddedMap::of(before, "the map before the run")?;
        let (px, py) = grid.pitch_mm();
        let mut out = Self {
            x_mm: Vec::with_capacity(after.len()),
            y_mm: Vec::with_capacity(after.len()),
            after_nm: Vec::with_capacity(after.len()),
            before: grid,
            skipped: 0,
        };
        for ((&x, &y), &z) in after.x_mm().iter().zip(after.y_mm()).zip(after.z_nm()) {
            let (fx, fy) = (
                (x - out.before.origin_mm.0) / px,
                (y - out.before.origin_mm.1) / py,
            );
            let inside = fx >= -ON_NODE_REL
                && fy >= -ON_NODE_REL
                && fx <= (out.before.nx - 1) as f64 + ON_NODE_REL
                && fy <= (out.before.ny - 1) as f64 + ON_NODE_REL;
            let covered = inside
                && [-1.0, 0.0, 1.0].iter().all(|&sx| {
                    [-1.0, 0.0, 1.0]
                        .iter()
                        .all(|&sy| out.before.at(x + sx * px, y + sy * py).is_some())
                });
            if covered && z.is_finite() {
                out.x_mm.push(x);
                out.y_mm.push(y);
                out.after_nm.push(z);
            } else {
                out.skipped += 1;
            }
        }
        if out.x_mm.len() < 16 {
            return Err(Error::invalid(
                "calibration maps",
                format!(
                    "only {} points of the map after the run lie inside the map before it (away from its edges and dropouts): are they of the same part and frame?",
                    out.x_mm.len()
                ),
            ));
        }
        Ok(out)
    }

    /// The measured change `B(x + s) - A(x)` at the points, nm, for a shift `s` of at most one
    /// before-pixel.
    pub fn change_nm(&self, shift_mm: (f64, f64)) -> Vec<f64> {
        self.weighted_change_nm(shift_mm).0
    }

    /// [`MeasuredChange::change_nm`] and each point's weight `sqrt(2 / (1 + g))`, `g` the
    /// interpolation's noise gain: with equal white noise on both maps the weighted change has
    /// the same noise variance at every shift, so the fit of the shift is not drawn to the
    /// fractions of a pixel where interpolation smooths the noise most.
    pub fn weighted_change_nm(&self, shift_mm: (f64, f64)) -> (Vec<f64>, Vec<f64>) {
        self.x_mm
            .iter()
            .zip(&self.y_mm)
            .zip(&self.after_nm)
            .map(|((&x, &y), &a)| {
                self.before
                    .read(x + shift_mm.0, y + shift_mm.1)
                    .map_or((0.0, 0.0), |(b, g)| (b - a, (2.0 / (1.0 + g)).sqrt()))
            })
            .unzip()
    }

    /// Number of points used.
    pub fn len(&self) -> usize {
        self.x_mm.len()
    }

    /// True when no point is used.
    pub fn is_empty(&self) -> bool {
        self.x_mm.is_empty()
    }
}
