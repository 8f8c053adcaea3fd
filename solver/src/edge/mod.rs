//! Edge handling: a model for the dwell area beyond the measured map.
//!
//! A dwell raster reaches one TIF radius beyond the map so that the tool can work the map's rim,
//! but the dwell points out there are constrained only by the map points inside their footprint:
//! the optimiser is free to pile dwell on them. Edge handling adds *extension points* where the
//! map is not measured and gives them a target height, so that the residual there counts too:
//!
//! - [`EdgeMethod::ZeroBand`]: a zero-removal guard band ([`zero_band`]).
//! - [`EdgeMethod::Gaussian`]: Gaussian-weighted extrapolation ([`gaussian`]).
//! - [`EdgeMethod::Polynomial`]: local polynomial extrapolation ([`polynomial`]).
//! - [`EdgeMethod::GerchbergPapoulis`]: band-limited extension ([`gerchberg_papoulis`]).
//!
//! **Extension points** ([`extension_points`]): the nodes of a square lattice of the map's pitch
//! `p` (anchored at a map point, so a gridded map's own lattice), within the dwell points'
//! bounding box widened by the TIF reach, whose nearest map point is farther than `0.75 p` (no
//! map point in its cell) and nearer than `width_mm` (the band). The extension rows are appended
//! to the map rows of the problem with unit weight, like measured points; the report's figures
//! (RMS, PV, residual.csv) are on the measured map only.

pub mod gaussian;
pub mod gerchberg_papoulis;
pub mod polynomial;
pub mod zero_band;

use crate::error::{Error, Result};
use crate::machine::machinability::map_pitch_mm;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// How the dwell area beyond the map is modelled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum EdgeMethod {
    /// No extension: dwell points beyond the map are constrained only by the map points in their
    /// footprint (the default, and the sample job's).
    #[default]
    None,
    /// Zero-removal guard band: the extension points' target is the map's lowest height.
    ZeroBand,
    /// Gaussian-weighted extrapolation of the map.
    Gaussian,
    /// Local least-squares polynomial extrapolation of the map.
    Polynomial,
    /// Gerchberg-Papoulis band-limited extension (needs a map on a regular lattice).
    GerchbergPapoulis,
}

/// Edge handling settings (`[edge]` in a job file). Every field has a default.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeSettings {
    /// The model.
    pub method: EdgeMethod,
    /// Width of the band beyond the map that gets extension points, mm; absent: the TIF's
    /// nominal radius (as far as the generated raster reaches beyond the map).
    pub width_mm: Option<f64>,
    /// Gaussian extrapolation: the weight's standard deviation, mm.
    pub gaussian_sigma_mm: f64,
    /// Polynomial extrapolation: the degree (0 to 3).
    pub polynomial_degree: usize,
    /// Polynomial extrapolation: map points within this distance of the extension point's
    /// nearest map point are fitted, mm.
    pub polynomial_fit_radius_mm: f64,
    /// Gerchberg-Papoulis: highest spatial frequency kept, cycles/mm; absent: one over the TIF's
    /// footprint diameter (`1 / (2 r_nominal)`), the finest detail the tool can shape.
    pub band_limit_per_mm: Option<f64>,
    /// Gerchberg-Papoulis: iterations.
    pub iterations: usize,
}

impl Default for EdgeSettings {
    fn default() -> Self {
        Self {
            method: EdgeMethod::default(),
            width_mm: None,
            gaussian_sigma_mm: 1.0,
            polynomial_degree: 1,
            polynomial_fit_radius_mm: 2.0,
            band_limit_per_mm: None,
            iterations: 200,
        }
    }
}

impl EdgeSettings {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        if let Some(w) = self.width_mm {
            if !(w.is_finite() && w >= 0.0) {
                return Err(Error::invalid(
                    "edge width_mm",
                    format!("must be >= 0, got {w}"),
                ));
            }
        }
        for (name, v) in [
            ("edge gaussian_sigma_mm", self.gaussian_sigma_mm),
            (
                "edge polynomial_fit_radius_mm",
                self.polynomial_fit_radius_mm,
            ),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid(name, format!("must be positive, got {v}")));
            }
        }
        if self.polynomial_degree > 3 {
            return Err(Error::invalid(
                "edge polynomial_degree",
                format!("must be 0 to 3, got {}", self.polynomial_degree),
            ));
        }
        if let Some(b) = self.band_limit_per_mm {
            if !(b.is_finite() && b > 0.0) {
                return Err(Error::invalid(
                    "edge band_limit_per_mm",
                    format!("must be positive, got {b}"),
                ));
            }
        }
        if self.iterations == 0 {
            return Err(Error::invalid("edge iterations", "must be at least 1"));
        }
        Ok(())
    }
}

/// Extension points with their target heights.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Extension {
    /// x of each extension point, mm.
    pub x_mm: Vec<f64>,
    /// y of each extension point, mm.
    pub y_mm: Vec<f64>,
    /// Target height, nm.
    pub z_nm: Vec<f64>,
}

impl Extension {
    /// Number of extension points.
    pub fn len(&self) -> usize {
        self.x_mm.len()
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.x_mm.is_empty()
    }
}

/// Extends the map `(x, y, z)` into the dwell area of the points `(dwell_x, dwell_y)` with
/// `settings`; `tif_radius_mm` is the TIF's nominal radius (default band width and band limit),
/// `reach_mm` its support radius (how far beyond a dwell point the tool removes material).
#[allow(clippy::too_many_arguments)]
pub fn extend(
    settings: &EdgeSettings,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    map_z_nm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    tif_radius_mm: f64,
    reach_mm: f64,
) -> Result<Extension> {
    settings.validate()?;
    if settings.method == EdgeMethod::None || map_x_mm.len() < 2 || dwell_x_mm.is_empty() {
        return Ok(Extension::default());
    }
    let width = settings.width_mm.unwrap_or(tif_radius_mm);
    let (x, y) = extension_points(map_x_mm, map_y_mm, dwell_x_mm, dwell_y_mm, reach_mm, width)?;
    let z = match settings.method {
        EdgeMethod::None => Vec::new(),
        EdgeMethod::ZeroBand => zero_band::extend(map_z_nm, x.len()),
        EdgeMethod::Gaussian => gaussian::extend(
            map_x_mm,
            map_y_mm,
            map_z_nm,
            &x,
            &y,
            settings.gaussian_sigma_mm,
        )?,
        EdgeMethod::Polynomial => polynomial::extend(
            map_x_mm,
            map_y_mm,
            map_z_nm,
            &x,
            &y,
            settings.polynomial_degree,
            settings.polynomial_fit_radius_mm,
        )?,
        EdgeMethod::GerchbergPapoulis => gerchberg_papoulis::extend(
            map_x_mm,
            map_y_mm,
            map_z_nm,
            &x,
            &y,
            settings
                .band_limit_per_mm
                .unwrap_or(1.0 / (2.0 * tif_radius_mm.max(f64::MIN_POSITIVE))),
            settings.iterations,
        )?,
    };
    Ok(Extension {
        x_mm: x,
        y_mm: y,
        z_nm: z,
    })
}

/// Points bucketed on a square grid of cell `h` (mm), for radius queries.
pub(crate) struct Buckets {
    h: f64,
    cells: HashMap<(i64, i64), Vec<u32>>,
}

impl Buckets {
    pub(crate) fn new(x: &[f64], y: &[f64], h: f64) -> Self {
        let mut cells: HashMap<(i64, i64), Vec<u32>> = HashMap::with_capacity(x.len());
        for (i, (&px, &py)) in x.iter().zip(y).enumerate() {
            cells
                .entry(((px / h).floor() as i64, (py / h).floor() as i64))
                .or_default()
                .push(i as u32);
        }
        Self { h, cells }
    }

    /// Calls `f(i, d)` for every point `i` at distance `d <= r` from `(px, py)`.
    pub(crate) fn within(
        &self,
        x: &[f64],
        y: &[f64],
        px: f64,
        py: f64,
        r: f64,
        mut f: impl FnMut(usize, f64),
    ) {
        let k = (r / self.h).ceil() as i64;
        let (cx, cy) = ((px / self.h).floor() as i64, (py / self.h).floor() as i64);
        for dx in -k..=k {
            for dy in -k..=k {
                if let Some(v) = self.cells.get(&(cx + dx, cy + dy)) {
                    for &i in v {
                        let i = i as usize;
                        let d = (x[i] - px).hypot(y[i] - py);
                        if d <= r {
                            f(i, d);
                        }
                    }
                }
            }
        }
    }

    /// Whether some point lies at distance `d <= r` from `(px, py)` (stops at the first).
    pub(crate) fn any_within(&self, x: &[f64], y: &[f64], px: f64, py: f64, r: f64) -> bool {
        let k = (r / self.h).ceil() as i64;
        let (cx, cy) = ((px / self.h).floor() as i64, (py / self.h).floor() as i64);
        for dx in -k..=k {
            for dy in -k..=k {
                if let Some(v) = self.cells.get(&(cx + dx, cy + dy)) {
                    if v.iter().any(|&i| {
                        let i = i as usize;
                        (x[i] - px).hypot(y[i] - py) <= r
                    }) {
                        return true;
                    }
                }
            }
        }
        false
    }

    /// The nearest point within `r_max` of `(px, py)` and its distance, by growing rings.
    pub(crate) fn nearest(
        &self,
        x: &[f64],
        y: &[f64],
        px: f64,
        py: f64,
        r_max: f64,
    ) -> Option<(usize, f64)> {
        let mut r = self.h;
        loop {
            let mut best: Option<(usize, f64)> = None;
            self.within(x, y, px, py, r.min(r_max), |i, d| {
                if best.is_none_or(|(_, b)| d < b) {
                    best = Some((i, d));
                }
            });
            if best.is_some() || r >= r_max {
                return best;
            }
            r *= 2.0;
        }
    }
}

/// The extension points (see the module documentation): lattice nodes of the map's pitch within
/// `reach_mm` of the dwell points' bounding box, with no map point within `0.75 p` and one
/// within `width_mm`.
pub fn extension_points(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    reach_mm: f64,
    width_mm: f64,
) -> Result<(Vec<f64>, Vec<f64>)> {
    let p = map_pitch_mm(map_x_mm, map_y_mm)
        .filter(|p| p.is_finite() && *p > 0.0)
        .ok_or_else(|| Error::invalid("map", "edge handling needs at least two distinct points"))?;
    let bounds = |v: &[f64]| {
        v.iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &t| {
                (a.min(t), b.max(t))
            })
    };
    let (mx0, mx1) = bounds(map_x_mm);
    let (my0, my1) = bounds(map_y_mm);
    let (dx0, dx1) = bounds(dwell_x_mm);
    let (dy0, dy1) = bounds(dwell_y_mm);
    let x0 = (dx0 - reach_mm).max(mx0 - width_mm);
    let x1 = (dx1 + reach_mm).min(mx1 + width_mm);
    let y0 = (dy0 - reach_mm).max(my0 - width_mm);
    let y1 = (dy1 + reach_mm).min(my1 + width_mm);
    if !(x1 >= x0 && y1 >= y0) {
        return Ok((Vec::new(), Vec::new()));
    }
    // Lattice anchored at the first map point.
    let (ax, ay) = (map_x_mm[0], map_y_mm[0]);
    let i0 = ((x0 - ax) / p).ceil() as i64;
    let i1 = ((x1 - ax) / p).floor() as i64;
    let j0 = ((y0 - ay) / p).ceil() as i64;
    let j1 = ((y1 - ay) / p).floor() as i64;
    let count = (i1 - i0 + 1).max(0) as f64 * (j1 - j0 + 1).max(0) as f64;
    if count > 1e8 {
        return Err(Error::invalid(
            "edge",
            format!("the extension lattice would hold {count:.3e} nodes (pitch {p} mm)"),
        ));
    }
    let buckets = Buckets::new(map_x_mm, map_y_mm, p.max(width_mm / 4.0));
    let covered = 0.75 * p;
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for j in j0..=j1 {
        for i in i0..=i1 {
            let (px, py) = (ax + i as f64 * p, ay + j as f64 * p);
            // The nearest map point is farther than `covered` and within the band.
            if !buckets.any_within(map_x_mm, map_y_mm, px, py, covered)
                && buckets.any_within(map_x_mm, map_y_mm, px, py, width_mm)
            {
                xs.push(px);
                ys.push(py);
            }
        }
    }
    Ok((xs, ys))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1 mm grid map over [0, 10] x [0, 4].
    pub(crate) fn grid_map(f: impl Fn(f64, f64) -> f64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..=4 {
            for i in 0..=10 {
                let (px, py) = (i as f64, j as f64);
                x.push(px);
                y.push(py);
                z.push(f(px, py));
            }
        }
        (x, y, z)
    }

    #[test]
    fn extension_points_fill_the_band_only() {
        let (x, y, _) = grid_map(|_, _| 0.0);
        // Dwell points over the map widened by 3 mm; band 2 mm.
        let (ex, ey) = extension_points(&x, &y, &[-3.0, 13.0], &[-3.0, 7.0], 0.0, 2.0).unwrap();
        // The lattice [-2, 12] x [-2, 6] less the 11 x 5 map, less the corner nodes farther than
        // 2 mm from the map (the four corners of each 2 x 2 corner block beyond sqrt 2 ... 2).
        for (&px, &py) in ex.iter().zip(&ey) {
            let dx = (0.0 - px).max(px - 10.0).max(0.0);
            let dy = (0.0 - py).max(py - 4.0).max(0.0);
            let d = dx.hypot(dy);
            assert!(d > 0.75 && d <= 2.0 + 1e-12, "({px}, {py}) at {d}");
        }
        // Every lattice node at distance (0.75, 2] is present.
        let mut want = 0;
        for j in -2..=6 {
            for i in -2..=12 {
                let (px, py) = (i as f64, j as f64);
                let d = (0.0 - px)
                    .max(px - 10.0)
                    .max(0.0)
                    .hypot((0.0 - py).max(py - 4.0).max(0.0));
                if d > 0.75 && d <= 2.0 {
                    want += 1;
                }
            }
        }
        assert_eq!(ex.len(), want);
    }

    #[test]
    fn none_adds_nothing() {
        let (x, y, z) = grid_map(|a, b| a + b);
        let s = EdgeSettings {
            method: EdgeMethod::None,
            ..EdgeSettings::default()
        };
        let e = extend(&s, &x, &y, &z, &[-3.0, 13.0], &[-3.0, 7.0], 2.0, 2.0).unwrap();
        assert!(e.is_empty());
    }

    #[test]
    fn bad_settings_are_named() {
        let s = EdgeSettings {
            polynomial_degree: 7,
            ..EdgeSettings::default()
        };
        assert!(s
            .validate()
            .unwrap_err()
            .to_string()
            .contains("polynomial_degree"));
    }
}
