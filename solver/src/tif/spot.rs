//! A measured TIF from a removal spot: two maps of the same part on the same grid, one before
//! and one after the tool dwelt at one place for a known time.
//!
//! Steps: the removal `before - after` at the grid nodes both maps hold, divided by the dwell
//! (nm/s); the spot centre estimated at the largest 3 x 3 mean; a background (piston, and tilt
//! when asked) fitted by least squares to the nodes outside the crop radius and subtracted
//! everywhere; every node outside the crop set to zero (NaN there too), negative rates inside
//! clipped to zero (NaN inside the crop is an error); optionally shifted so that the
//! rate-weighted centroid is the tool centre. An elliptical Gaussian
//! `A exp(-(x - x0)^2 / (2 sx^2) - (y - y0)^2 / (2 sy^2))` can be fitted to the crop by
//! Levenberg-Marquardt (Marquardt 1963), as the open dwell codes characterise spots.

use crate::error::{Error, Result};
use crate::map::HeightMap;
use crate::tif::{GridTif, TifModelKind};
use nalgebra::{Matrix3, Matrix5, Vector3, Vector5};
use serde::{Deserialize, Serialize};

/// How to turn a removal spot into a TIF.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpotOptions {
    /// Dwell time of the spot, s.
    pub dwell_s: f64,
    /// Radius about the spot centre that holds the TIF, mm (default: 0.4 of the grid's smaller
    /// side).
    pub crop_radius_mm: Option<f64>,
    /// Remove a background tilt (as well as piston) fitted outside the crop.
    pub remove_tilt: bool,
    /// Shift the coordinates so that the rate-weighted centroid is the tool centre.
    pub recentre: bool,
}

/// A fitted elliptical Gaussian.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GaussianFit {
    /// Peak rate, nm/s.
    pub peak_nm_per_s: f64,
    /// Centre, mm (in the TIF's coordinates).
    pub centre_mm: (f64, f64),
    /// Standard deviation along x, mm.
    pub sigma_x_mm: f64,
    /// Standard deviation along y, mm.
    pub sigma_y_mm: f64,
}

/// The TIF of a spot and what was done to get it.
#[derive(Debug, Clone, PartialEq)]
pub struct SpotTif {
    /// The TIF grid (rates nm/s).
    pub tif: GridTif,
    /// The rate-weighted centroid in the maps' coordinates, mm (before any recentring).
    pub spot_centroid_mm: (f64, f64),
    /// Crop radius used, mm.
    pub crop_radius_mm: f64,
    /// Background removed: piston nm/s, and x and y slopes nm/s per mm.
    pub background: (f64, f64, f64),
}

/// A regular lattice holding a map's points: origin, pitch, shape, node values (NaN where absent).
struct Lattice {
    x0: f64,
    y0: f64,
    pitch: f64,
    nx: usize,
    ny: usize,
}

/// Coordinates closer than this fraction of the pitch are the same node.
const NODE_TOL: f64 = 1e-6;
/// Largest lattice built, nodes.
const MAX_NODES: usize = 1 << 26;

impl Lattice {
    fn of(map: &HeightMap) -> Result<Self> {
        let step = |v: &[f64]| {
            let mut s: Vec<f64> = v.to_vec();
            s.sort_by(f64::total_cmp);
            s.windows(2)
                .map(|w| w[1] - w[0])
                .filter(|d| *d > 1e-9)
                .fold(f64::INFINITY, f64::min)
        };
        let pitch = step(map.x_mm()).min(step(map.y_mm()));
        let bb = map
            .bounding_box_mm()
            .ok_or_else(|| Error::invalid("spot map", "is empty"))?;
        if !pitch.is_finite() {
            return Err(Error::NotRegularGrid {
                what: "spot map",
                why: "fewer than two distinct coordinates".into(),
            });
        }
        let nx = ((bb.x_max_mm - bb.x_min_mm) / pitch).round() as usize + 1;
        let ny = ((bb.y_max_mm - bb.y_min_mm) / pitch).round() as usize + 1;
        if nx.saturating_mul(ny) > MAX_NODES {
            return Err(Error::NotRegularGrid {
                what: "spot map",
                why: format!("{nx} x {ny} lattice nodes at pitch {pitch} mm is too many"),
            });
        }
        Ok(Self {
            x0: bb.x_min_mm,
            y0: bb.y_min_mm,
            pitch,
            nx,
            ny,
        })
    }

    fn index(&self, x: f64, y: f64) -> Option<usize> {
        let fx = (x - self.x0) / self.pitch;
        let fy = (y - self.y0) / self.pitch;
        let (ix, iy) = (fx.round(), fy.round());
        if (fx - ix).abs() > NODE_TOL
            || (fy - iy).abs() > NODE_TOL
            || ix < 0.0
            || iy < 0.0
            || ix as usize >= self.nx
            || iy as usize >= self.ny
        {
            return None;
        }
        Some(iy as usize * self.nx + ix as usize)
    }

    fn xy(&self, k: usize) -> (f64, f64) {
        (
            self.x0 + (k % self.nx) as f64 * self.pitch,
            self.y0 + (k / self.nx) as f64 * self.pitch,
        )
    }

    fn values(&self, map: &HeightMap, what: &'static str) -> Result<Vec<f64>> {
        let mut v = vec![f64::NAN; self.nx * self.ny];
        for ((x, y), z) in map.x_mm().iter().zip(map.y_mm()).zip(map.z_nm()) {
            let k = self.index(*x, *y).ok_or_else(|| Error::NotRegularGrid {
                what,
                why: format!(
                    "point ({x}, {y}) mm is not on the before map's grid (pitch {} mm); \
                     resample or register the maps onto one grid first",
                    self.pitch
                ),
            })?;
            v[k] = *z;
        }
        Ok(v)
    }
}

/// The TIF of a removal spot (see the module documentation).
pub fn tif_from_spot(before: &HeightMap, after: &HeightMap, opts: &SpotOptions) -> Result<SpotTif> {
    if !(opts.dwell_s > 0.0 && opts.dwell_s.is_finite()) {
        return Err(Error::invalid(
            "dwell_s",
            format!("{} must be positive", opts.dwell_s),
        ));
    }
    let lat = Lattice::of(before)?;
    let b = lat.values(before, "before map")?;
    let a = lat.values(after, "after map")?;
    let rate: Vec<f64> = b
        .iter()
        .zip(&a)
        .map(|(b, a)| (b - a) / opts.dwell_s)
        .collect();
    // Spot centre: the largest 3 x 3 mean of valid nodes.
    let (nx, ny) = (lat.nx, lat.ny);
    let mut best = (f64::NEG_INFINITY, 0usize);
    for iy in 0..ny {
        for ix in 0..nx {
            let (mut s, mut c) = (0.0, 0);
            for dy in iy.saturating_sub(1)..=(iy + 1).min(ny - 1) {
                for dx in ix.saturating_sub(1)..=(ix + 1).min(nx - 1) {
                    let v = rate[dy * nx + dx];
                    if v.is_finite() {
                        s += v;
                        c += 1;
                    }
                }
            }
            if c == 9 && s / 9.0 > best.0 {
                best = (s / 9.0, iy * nx + ix);
            }
        }
    }
    if !(best.0 > 0.0) {
        return Err(Error::invalid(
            "spot",
            "no removal found (before - after is nowhere positive over a 3 x 3 patch)",
        ));
    }
    let (cx, cy) = lat.xy(best.1);
    let side = (nx.min(ny) - 1) as f64 * lat.pitch;
    let crop = opts.crop_radius_mm.unwrap_or(0.4 * side);
    if !(crop > 0.0 && crop.is_finite()) {
        return Err(Error::invalid(
            "crop_radius_mm",
            format!("{crop} must be positive"),
        ));
    }
    let inside = |k: usize| {
        let (x, y) = lat.xy(k);
        (x - cx).hypot(y - cy) <= crop
    };
    // Background by least squares over the valid nodes outside the crop (normal equations of
    // [1, x - cx, y - cy] or [1]).
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    let mut n_out = 0usize;
    for (k, &r) in rate.iter().enumerate() {
        if r.is_finite() && !inside(k) {
            let (x, y) = lat.xy(k);
            let row = Vector3::new(1.0, x - cx, y - cy);
            ata += row * row.transpose();
            atb += row * r;
            n_out += 1;
        }
    }
    let background = if n_out == 0 {
        (0.0, 0.0, 0.0)
    } else if opts.remove_tilt {
        let c = ata.lu().solve(&atb).ok_or_else(|| {
            Error::invalid(
                "spot background",
                "the nodes outside the crop do not determine a plane (crop too large?)",
            )
        })?;
        (c[0], c[1], c[2])
    } else {
        (atb[0] / ata[(0, 0)], 0.0, 0.0)
    };
    let mut out = vec![0.0; rate.len()];
    let mut nan_inside = 0usize;
    for (k, o) in out.iter_mut().enumerate() {
        if !inside(k) {
            continue;
        }
        let r = rate[k];
        if !r.is_finite() {
            nan_inside += 1;
            continue;
        }
        let (x, y) = lat.xy(k);
        let v = r - background.0 - background.1 * (x - cx) - background.2 * (y - cy);
        *o = v.max(0.0);
    }
    if nan_inside > 0 {
        return Err(Error::invalid(
            "spot",
            format!(
                "{nan_inside} nodes inside the crop radius ({crop} mm) lack a height in one of \
                 the maps; use a smaller --crop-radius-mm"
            ),
        ));
    }
    let tif = GridTif::new(lat.x0, lat.y0, lat.pitch, lat.pitch, nx, ny, out)?;
    let spot_centroid_mm = tif.centroid_mm();
    let tif = if opts.recentre { tif.recentred()? } else { tif };
    Ok(SpotTif {
        tif,
        spot_centroid_mm,
        crop_radius_mm: crop,
        background,
    })
}

/// Fits an elliptical Gaussian to the non-zero nodes of `tif` (and their zero neighbours) by
/// Levenberg-Marquardt from the moments.
pub fn fit_gaussian(tif: &GridTif) -> Result<GaussianFit> {
    let (nx, ny) = tif.shape();
    let (x0, y0) = tif.origin_mm();
    let (px, py) = tif.pitch_mm();
    let r = tif.rates_nm_per_s();
    let pts: Vec<(f64, f64, f64)> = (0..nx * ny)
        .map(|k| (x0 + (k % nx) as f64 * px, y0 + (k / nx) as f64 * py, r[k]))
        .collect();
    let total: f64 = r.iter().sum();
    if !(total > 0.0) {
        return Err(Error::invalid("spot", "has no positive rate to fit"));
    }
    let (cx, cy) = tif.centroid_mm();
    let (mut sxx, mut syy) = (0.0, 0.0);
    for &(x, y, v) in &pts {
        sxx += v * (x - cx).powi(2);
        syy += v * (y - cy).powi(2);
    }
    // p = [A, x0, y0, sx, sy].
    let mut p = Vector5::new(
        tif.peak_rate_nm_per_s(),
        cx,
        cy,
        (sxx / total).sqrt().max(px),
        (syy / total).sqrt().max(py),
    );
    let cost = |p: &Vector5<f64>| -> f64 {
        pts.iter()
            .map(|&(x, y, v)| {
                let g = p[0]
                    * (-(x - p[1]).powi(2) / (2.0 * p[3] * p[3])
                        - (y - p[2]).powi(2) / (2.0 * p[4] * p[4]))
                        .exp();
                (g - v).powi(2)
            })
            .sum()
    };
    let mut lambda = 1e-3;
    let mut c = cost(&p);
    for _ in 0..200 {
        let mut jtj = Matrix5::<f64>::zeros();
        let mut jtr = Vector5::<f64>::zeros();
        for &(x, y, v) in &pts {
            let (dx, dy) = (x - p[1], y - p[2]);
            let (sx2, sy2) = (p[3] * p[3], p[4] * p[4]);
            let e = (-dx * dx / (2.0 * sx2) - dy * dy / (2.0 * sy2)).exp();
            let g = p[0] * e;
            let j = Vector5::new(
                e,
                g * dx / sx2,
                g * dy / sy2,
                g * dx * dx / (sx2 * p[3]),
                g * dy * dy / (sy2 * p[4]),
            );
            jtj += j * j.transpose();
            jtr += j * (v - g);
        }
        let mut improved = false;
        for _ in 0..20 {
            let mut a = jtj;
            for i in 0..5 {
                a[(i, i)] += lambda * jtj[(i, i)].max(1e-12);
            }
            let Some(step) = a.lu().solve(&jtr) else {
                lambda *= 10.0;
                continue;
            };
            let trial = p + step;
            let ct = cost(&trial);
            if ct < c && trial[3] > 0.0 && trial[4] > 0.0 {
                let rel = (c - ct) / c.max(1e-300);
                p = trial;
                c = ct;
                lambda = (lambda * 0.3).max(1e-12);
                improved = true;
                if rel < 1e-14 {
                    return Ok(gaussian_of(&p));
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Ok(gaussian_of(&p))
}

fn gaussian_of(p: &Vector5<f64>) -> GaussianFit {
    GaussianFit {
        peak_nm_per_s: p[0],
        centre_mm: (p[1], p[2]),
        sigma_x_mm: p[3].abs(),
        sigma_y_mm: p[4].abs(),
    }
}

/// What `preston tif spot` prints (JSON) and the Python package's `tif_spot` returns.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpotSummary {
    /// Always [`TifModelKind::Spot`].
    pub model: TifModelKind,
    /// Largest rate, nm/s.
    pub peak_rate_nm_per_s: f64,
    /// Equivalent-circle FWHM, mm.
    pub fwhm_mm: f64,
    /// Rate-weighted centroid of the TIF, mm (the origin after recentring).
    pub centroid_mm: (f64, f64),
    /// Rate-weighted centroid in the maps' coordinates, mm.
    pub spot_centroid_mm: (f64, f64),
    /// Volumetric removal rate, mm^3/min.
    pub volume_rate_mm3_per_min: f64,
    /// Crop radius used, mm.
    pub crop_radius_mm: f64,
    /// Background removed outside the crop: piston nm/s, slopes nm/s per mm (x, y).
    pub background_nm_per_s: (f64, f64, f64),
    /// Fitted Gaussian's standard deviation along x, mm (with a fit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_x_mm: Option<f64>,
    /// Fitted Gaussian's standard deviation along y, mm (with a fit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_y_mm: Option<f64>,
    /// Fitted Gaussian's peak rate, nm/s (with a fit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussian_peak_nm_per_s: Option<f64>,
    /// Fitted Gaussian's centre, mm (with a fit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gaussian_centre_mm: Option<(f64, f64)>,
    /// Grid nodes along x.
    pub nx: usize,
    /// Grid nodes along y.
    pub ny: usize,
    /// Grid pitch along x, mm.
    pub pitch_mm: f64,
}

impl SpotSummary {
    /// The summary of `spot`, with the fitted Gaussian `fit` if one was fitted.
    pub fn of(spot: &SpotTif, fit: Option<&GaussianFit>) -> Self {
        let g = &spot.tif;
        let (nx, ny) = g.shape();
        Self {
            model: TifModelKind::Spot,
            peak_rate_nm_per_s: g.peak_rate_nm_per_s(),
            fwhm_mm: g.fwhm_mm(),
            centroid_mm: g.centroid_mm(),
            spot_centroid_mm: spot.spot_centroid_mm,
            volume_rate_mm3_per_min: g.volume_rate_mm3_per_s() * 60.0,
            crop_radius_mm: spot.crop_radius_mm,
            background_nm_per_s: spot.background,
            sigma_x_mm: fit.map(|f| f.sigma_x_mm),
            sigma_y_mm: fit.map(|f| f.sigma_y_mm),
            gaussian_peak_nm_per_s: fit.map(|f| f.peak_nm_per_s),
            gaussian_centre_mm: fit.map(|f| f.centre_mm),
            nx,
            ny,
            pitch_mm: g.pitch_mm().0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A noise-free Gaussian spot on a tilted background with a NaN border.
    fn spot(tilt_nm_per_mm: f64) -> (HeightMap, HeightMap) {
        let (mut x, mut y, mut zb, mut za) = (vec![], vec![], vec![], vec![]);
        let n = 101;
        for i in 0..n {
            for j in 0..n {
                if i == 0 || j == 0 || i == n - 1 || j == n - 1 {
                    continue; // the NaN border: absent points
                }
                let (xi, yj) = (-5.0 + 0.1 * j as f64, -5.0 + 0.1 * i as f64);
                let g =
                    6.0 * (-((xi - 0.3).powi(2) + (yj + 0.2).powi(2)) / (2.0 * 1.2 * 1.2)).exp();
                let figure = 3.0 * (0.7 * xi).sin() + 2.0 * yj;
                x.push(xi);
                y.push(yj);
                zb.push(figure);
                za.push(figure - 10.0 * g + tilt_nm_per_mm * xi + 0.5);
            }
        }
        (
            HeightMap::new(x.clone(), y.clone(), zb).unwrap(),
            HeightMap::new(x, y, za).unwrap(),
        )
    }

    #[test]
    fn noise_free_spot_gives_its_gaussian() {
        let (b, a) = spot(0.2);
        let s = tif_from_spot(
            &b,
            &a,
            &SpotOptions {
                dwell_s: 10.0,
                crop_radius_mm: Some(4.5),
                remove_tilt: true,
                recentre: true,
            },
        )
        .unwrap();
        // The tilt (0.02 nm/s per mm) and the offset are taken out from outside the crop, where
        // the Gaussian's tail (exp(-4.5^2 / 2.88) = 9e-4 of the peak at most) barely biases it.
        assert!((s.background.1 + 0.02).abs() < 2e-3, "{:?}", s.background);
        let (cx, cy) = s.tif.centroid_mm();
        assert!(cx.abs() < 1e-9 && cy.abs() < 1e-9);
        assert!((s.spot_centroid_mm.0 - 0.3).abs() < 0.01);
        assert!((s.spot_centroid_mm.1 + 0.2).abs() < 0.01);
        let g = fit_gaussian(&s.tif).unwrap();
        assert!((g.sigma_x_mm - 1.2).abs() < 0.01, "{g:?}");
        assert!((g.sigma_y_mm - 1.2).abs() < 0.01, "{g:?}");
        assert!((g.peak_nm_per_s - 6.0).abs() < 0.03, "{g:?}");
    }

    #[test]
    fn maps_on_different_grids_are_refused() {
        let (b, _) = spot(0.0);
        let shifted = HeightMap::new(
            b.x_mm().iter().map(|x| x + 0.05).collect(),
            b.y_mm().to_vec(),
            b.z_nm().to_vec(),
        )
        .unwrap();
        let e = tif_from_spot(
            &b,
            &shifted,
            &SpotOptions {
                dwell_s: 1.0,
                crop_radius_mm: None,
                remove_tilt: false,
                recentre: false,
            },
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("grid"), "{e}");
    }
}
