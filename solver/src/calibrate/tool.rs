//! The tool that actually ran: the spot-test TIF `f` under a few physical changes.
//!
//! With `c` the spot test's centroid, `rho` its second-moment radius and `θ` the figures,
//!
//! ```text
//! f_θ(d) = r / w² · f(u) · max(0, 1 + k · v),
//! u = c + exp(-E) (d - c - o) / w,      v = (u - c) / rho,      E = [[e, e45], [e45, -e]],
//! ```
//!
//! - `r` the rate factor: the ratio of the TIF's volume (the Jacobian of `d -> u` is `1 / w²`,
//!   `det exp(E) = 1`, and `v` has zero mean under `f`);
//! - `w` the width factor: the footprint scaled about its centroid, its volume kept; with `E = 0`
//!   the ratio of the second-moment radii (to first order in `E` otherwise);
//! - `o` the offset of the centroid from where the tool is programmed, mm;
//! - `e`, `e45` the ellipticity (log of the axis ratio's square root) along x/y and along the
//!   diagonals: an area-keeping stretch;
//! - `k_x`, `k_y` the skew: a linear change of the rate across the footprint (a tilted jet, a
//!   pressure gradient under a pad), the lowest-order asymmetry. Measured from the centroid
//!   (`∫ (u - c) f = 0`) it keeps the volume exactly and moves the centroid by `Σ k / rho`
//!   (`Σ` the spot test's second-moment matrix per unit volume,
//!   [`SpotFootprint::second_moments_mm2`]); on a Gaussian footprint that is all it does to first
//!   order (a tilted Gaussian is a shifted one), so there the skew and the offset are told apart
//!   only by the footprint's higher moments and the priors. A calibration therefore reports the
//!   fitted footprint's moments ([`footprint_moments`]): its centroid, whatever mix of offset and
//!   skew puts it there.
//!
//! The rate's drift over a run is not part of the footprint: it weights each contact sample by
//! `1 + δ (t - t_mid) / 3600` ([`super::forward`]).

use crate::error::{Error, Result};
use crate::tif::{GridTif, InfluenceFunction, Tif};
use serde::{Deserialize, Serialize};

/// The figures of a calibrated tool (module documentation), with their units in their names.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ToolFigures {
    /// Ratio of the TIF's volume to the spot test's.
    pub rate_factor: f64,
    /// Ratio of the footprint's size to the spot test's (second-moment radius), its volume kept.
    pub width_factor: f64,
    /// Centroid offset along x from the programmed point, mm.
    pub offset_x_mm: f64,
    /// Centroid offset along y from the programmed point, mm.
    pub offset_y_mm: f64,
    /// Ellipticity along the axes: the footprint stretched by `exp(e)` along x and shrunk by
    /// `exp(-e)` along y.
    pub ellipticity: f64,
    /// Ellipticity along the diagonals (the same stretch turned by 45 degrees).
    pub ellipticity_45: f64,
    /// Skew along x: the weight of the footprint's third-moment shape `φ_x`.
    pub skew_x: f64,
    /// Skew along y.
    pub skew_y: f64,
    /// Relative change of the removal rate per hour of program time.
    pub drift_per_hour: f64,
}

impl Default for ToolFigures {
    fn default() -> Self {
        Self::NOMINAL
    }
}

impl ToolFigures {
    /// The spot test as it was measured.
    pub const NOMINAL: Self = Self {
        rate_factor: 1.0,
        width_factor: 1.0,
        offset_x_mm: 0.0,
        offset_y_mm: 0.0,
        ellipticity: 0.0,
        ellipticity_45: 0.0,
        skew_x: 0.0,
        skew_y: 0.0,
        drift_per_hour: 0.0,
    };

    /// The names of the figures, in the order of [`ToolFigures::to_array`].
    pub const NAMES: [&'static str; 9] = [
        "rate_factor",
        "width_factor",
        "offset_x_mm",
        "offset_y_mm",
        "ellipticity",
        "ellipticity_45",
        "skew_x",
        "skew_y",
        "drift_per_hour",
    ];

    /// The figures as an array, in the order of [`ToolFigures::NAMES`].
    pub fn to_array(&self) -> [f64; 9] {
        [
            self.rate_factor,
            self.width_factor,
            self.offset_x_mm,
            self.offset_y_mm,
            self.ellipticity,
            self.ellipticity_45,
            self.skew_x,
            self.skew_y,
            self.drift_per_hour,
        ]
    }

    /// The figures from an array in the order of [`ToolFigures::NAMES`].
    pub fn from_array(a: [f64; 9]) -> Self {
        Self {
            rate_factor: a[0],
            width_factor: a[1],
            offset_x_mm: a[2],
            offset_y_mm: a[3],
            ellipticity: a[4],
            ellipticity_45: a[5],
            skew_x: a[6],
            skew_y: a[7],
            drift_per_hour: a[8],
        }
    }

    /// Checks that every figure is finite and the rate and width factors positive.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in Self::NAMES.iter().zip(self.to_array()) {
            if !v.is_finite() {
                return Err(Error::invalid(
                    format!("tool figure {name}"),
                    format!("must be finite, got {v}"),
                ));
            }
        }
        for (name, v) in [
            ("rate_factor", self.rate_factor),
            ("width_factor", self.width_factor),
        ] {
            if v <= 0.0 {
                return Err(Error::invalid(
                    format!("tool figure {name}"),
                    format!("must be positive, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

/// The spot test's footprint with what the transform needs: centroid and second-moment radius.
#[derive(Debug, Clone)]
pub struct SpotFootprint {
    grid: GridTif,
    centroid_mm: (f64, f64),
    radius_mm: f64,
    /// Second-moment matrix per unit volume `[Σxx, Σxy, Σyy]`, mm².
    second_mm2: [f64; 3],
}

/// Nodes per standard deviation at which a Gaussian spot test is sampled onto a grid.
pub const GAUSSIAN_NODES_PER_SIGMA: f64 = 12.0;

/// A TIF as a grid: a measured grid as it is, a Gaussian sampled at
/// [`GAUSSIAN_NODES_PER_SIGMA`] nodes per sigma over its support.
pub fn tif_grid(tif: &Tif) -> Result<GridTif> {
    match tif {
        Tif::Grid(g) => Ok(g.clone()),
        Tif::Gaussian(g) => {
            let pitch = g.sigma_mm / GAUSSIAN_NODES_PER_SIGMA;
            let half = (g.support_radius_mm() / pitch).ceil() as usize;
            let n = 2 * half + 1;
            let x0 = -(half as f64) * pitch;
            let rates = (0..n * n)
                .map(|k| g.rate_nm_per_s(x0 + (k % n) as f64 * pitch, x0 + (k / n) as f64 * pitch))
                .collect();
            GridTif::new(x0, x0, pitch, pitch, n, n, rates)
        }
    }
}

impl SpotFootprint {
    /// The footprint of a spot test given as any TIF ([`tif_grid`]).
    pub fn of_tif(tif: &Tif) -> Result<Self> {
        Self::new(tif_grid(tif)?)
    }

    /// The footprint of a spot test sampled on a grid.
    ///
    /// Errors: a grid whose rates sum to zero.
    pub fn new(grid: GridTif) -> Result<Self> {
        let (nx, _) = grid.shape();
        let (px, py) = grid.pitch_mm();
        let (x0, y0) = grid.origin_mm();
        let rates = grid.rates_nm_per_s();
        let node = |k: usize| (x0 + (k % nx) as f64 * px, y0 + (k / nx) as f64 * py);
        let total: f64 = rates.iter().sum();
        if !(total > 0.0 && total.is_finite()) {
            return Err(Error::invalid("TIF", "its rates sum to zero"));
        }
        let (cx, cy) = grid.centroid_mm();
        let second: f64 = rates
            .iter()
            .enumerate()
            .map(|(k, &f)| {
                let (x, y) = node(k);
                f * ((x - cx).powi(2) + (y - cy).powi(2))
            })
            .sum::<f64>()
            / total;
        let radius_mm = second.sqrt();
        let mut second_mm2 = [0.0; 3];
        for (k, &f) in rates.iter().enumerate() {
            let (x, y) = node(k);
            let (dx, dy) = (x - cx, y - cy);
            second_mm2[0] += f * dx * dx;
            second_mm2[1] += f * dx * dy;
            second_mm2[2] += f * dy * dy;
        }
        for v in second_mm2.iter_mut() {
            *v /= total;
        }
        if !(radius_mm > 0.0 && radius_mm.is_finite()) {
            return Err(Error::invalid(
                "TIF",
                "its footprint has no extent (second-moment radius zero)",
            ));
        }
        Ok(Self {
            grid,
            centroid_mm: (cx, cy),
            radius_mm,
            second_mm2,
        })
    }

    /// The spot test's grid.
    pub fn grid(&self) -> &GridTif {
        &self.grid
    }

    /// Rate-weighted centroid, mm.
    pub fn centroid_mm(&self) -> (f64, f64) {
        self.centroid_mm
    }

    /// Second-moment radius `sqrt(Σ f |d - c|² / Σ f)`, mm.
    pub fn radius_mm(&self) -> f64 {
        self.radius_mm
    }

    /// Second moments per unit volume about the centroid, `[Σxx, Σxy, Σyy]`, mm².
    pub fn second_moments_mm2(&self) -> [f64; 3] {
        self.second_mm2
    }

    /// The footprint under `figures` (its drift aside), its skew linear.
    pub fn transformed(&self, figures: &ToolFigures) -> TransformedTif<'_> {
        self.transformed_as(figures, SkewForm::Linear)
    }

    /// The footprint under `figures` with the skew of the form `skew_form`.
    pub fn transformed_as(&self, figures: &ToolFigures, skew_form: SkewForm) -> TransformedTif<'_> {
        let (e, e45) = (figures.ellipticity, figures.ellipticity_45);
        let lambda = e.hypot(e45);
        // exp(-E) = cosh(λ) I - sinh(λ)/λ E for symmetric traceless E with eigenvalues ±λ.
        let (ch, sh) = if lambda > 0.0 {
            (lambda.cosh(), lambda.sinh() / lambda)
        } else {
            (1.0, 1.0)
        };
        let inv = [[ch - sh * e, -sh * e45], [-sh * e45, ch + sh * e]];
        let w = figures.width_factor;
        TransformedTif {
            spot: self,
            inv_over_w: [
                [inv[0][0] / w, inv[0][1] / w],
                [inv[1][0] / w, inv[1][1] / w],
            ],
            scale: figures.rate_factor / (w * w),
            offset_mm: (figures.offset_x_mm, figures.offset_y_mm),
            skew: (figures.skew_x, figures.skew_y),
            skew_form,
            reach_mm: w
                * (ch + sh * lambda)
                * (self.grid.support_radius_mm() + self.centroid_mm.0.hypot(self.centroid_mm.1))
                + self.centroid_mm.0.hypot(self.centroid_mm.1)
                + figures.offset_x_mm.hypot(figures.offset_y_mm),
        }
    }
}

/// Volume (nm mm² / s), centroid (mm) and second-moment radius (mm) of a footprint, by sums over
/// a grid of pitch `pitch_mm` within its support.
pub fn footprint_moments(f: &dyn InfluenceFunction, pitch_mm: f64) -> (f64, (f64, f64), f64) {
    let r = f.support_radius_mm();
    let n = (r / pitch_mm).ceil() as i64;
    let mut m = [0.0; 4];
    for j in -n..=n {
        for i in -n..=n {
            let (x, y) = (i as f64 * pitch_mm, j as f64 * pitch_mm);
            let v = f.rate_nm_per_s(x, y);
            m[0] += v;
            m[1] += v * x;
            m[2] += v * y;
            m[3] += v * (x * x + y * y);
        }
    }
    let s = m[0].max(f64::MIN_POSITIVE);
    let (cx, cy) = (m[1] / s, m[2] / s);
    (
        m[0] * pitch_mm * pitch_mm,
        (cx, cy),
        (m[3] / s - cx * cx - cy * cy).max(0.0).sqrt(),
    )
}

/// How the skew changes the footprint.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SkewForm {
    /// A linear change of the rate across the footprint, `f (1 + k·v)` (module documentation).
    #[default]
    Linear,
    /// The same less its first-order shift, `f (1 + k·v) + (Σ k)·∇f / rho`: it keeps the
    /// centroid, exactly so only on a Gaussian footprint. The calibration fits it beside the
    /// linear form to measure how far the figures depend on the skew's shape.
    ShiftFree,
}

/// The spot test's footprint under a set of figures ([`SpotFootprint::transformed`]).
#[derive(Debug, Clone, Copy)]
pub struct TransformedTif<'a> {
    spot: &'a SpotFootprint,
    inv_over_w: [[f64; 2]; 2],
    scale: f64,
    offset_mm: (f64, f64),
    skew: (f64, f64),
    skew_form: SkewForm,
    reach_mm: f64,
}

impl InfluenceFunction for TransformedTif<'_> {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let (cx, cy) = self.spot.centroid_mm;
        let (qx, qy) = (dx_mm - cx - self.offset_mm.0, dy_mm - cy - self.offset_mm.1);
        let a = &self.inv_over_w;
        let (ux, uy) = (a[0][0] * qx + a[0][1] * qy, a[1][0] * qx + a[1][1] * qy);
        let grid = &self.spot.grid;
        let f = grid.rate_nm_per_s(cx + ux, cy + uy);
        let (kx, ky) = self.skew;
        let r = self.spot.radius_mm;
        let skewed = f * (1.0 + (kx * ux + ky * uy) / r);
        let skewed = match self.skew_form {
            SkewForm::Linear => skewed,
            SkewForm::ShiftFree if (kx, ky) == (0.0, 0.0) => skewed,
            SkewForm::ShiftFree => {
                let (hx, hy) = grid.pitch_mm();
                let gx = (grid.rate_nm_per_s(cx + ux + hx, cy + uy)
                    - grid.rate_nm_per_s(cx + ux - hx, cy + uy))
                    / (2.0 * hx);
                let gy = (grid.rate_nm_per_s(cx + ux, cy + uy + hy)
                    - grid.rate_nm_per_s(cx + ux, cy + uy - hy))
                    / (2.0 * hy);
                let [sxx, sxy, syy] = self.spot.second_mm2;
                skewed + ((sxx * kx + sxy * ky) * gx + (sxy * kx + syy * ky) * gy) / r
            }
        };
        self.scale * skewed.max(0.0)
    }

    fn support_radius_mm(&self) -> f64 {
        self.reach_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tif::GaussianTif;

    /// Agreement of sums over a fine grid with their closed forms.
    const MOMENT_REL_TOL: f64 = 2e-3;

    fn gaussian_grid(sigma: f64, pitch: f64) -> GridTif {
        let g = GaussianTif::new(sigma, 10.0, 4.5 * sigma).expect("gaussian");
        let n = (2.0 * 4.5 * sigma / pitch).ceil() as usize + 1;
        let x0 = -(n as f64 - 1.0) / 2.0 * pitch;
        let rates = (0..n * n)
            .map(|k| g.rate_nm_per_s(x0 + (k % n) as f64 * pitch, x0 + (k / n) as f64 * pitch))
            .collect();
        GridTif::new(x0, x0, pitch, pitch, n, n, rates).expect("grid")
    }

    /// Volume, centroid and second moments of `f` sampled on a fine square grid.
    fn moments(f: &dyn InfluenceFunction, half: f64, h: f64) -> [f64; 6] {
        let n = (2.0 * half / h) as i64;
        let mut m = [0.0; 6];
        for i in 0..=n {
            for j in 0..=n {
                let (x, y) = (-half + i as f64 * h, -half + j as f64 * h);
                let v = f.rate_nm_per_s(x, y) * h * h;
                m[0] += v;
                m[1] += v * x;
                m[2] += v * y;
                m[3] += v * x * x;
                m[4] += v * y * y;
                m[5] += v * x * x * x;
            }
        }
        m
    }

    #[test]
    fn rate_width_and_offset_act_as_their_closed_forms() {
        let sigma = 1.5;
        let spot = SpotFootprint::new(gaussian_grid(sigma, 0.05)).expect("spot");
        // A Gaussian's second-moment radius is sqrt(2) sigma.
        assert!((spot.radius_mm() / (2f64.sqrt() * sigma) - 1.0).abs() < MOMENT_REL_TOL);
        let nominal = moments(&spot.transformed(&ToolFigures::NOMINAL), 9.0, 0.05);
        let figures = ToolFigures {
            rate_factor: 1.08,
            width_factor: 1.05,
            offset_x_mm: 0.2,
            offset_y_mm: -0.1,
            ..ToolFigures::NOMINAL
        };
        let m = moments(&spot.transformed(&figures), 9.0, 0.05);
        assert!((m[0] / nominal[0] - 1.08).abs() < MOMENT_REL_TOL);
        assert!((m[1] / m[0] - 0.2).abs() < 1e-3);
        assert!((m[2] / m[0] + 0.1).abs() < 1e-3);
        let var_x = m[3] / m[0] - (m[1] / m[0]).powi(2);
        assert!((var_x / (1.05 * sigma).powi(2) - 1.0).abs() < MOMENT_REL_TOL);
    }

    #[test]
    fn skew_keeps_volume_and_moves_the_centroid_by_its_closed_form() {
        let sigma = 1.2;
        let spot = SpotFootprint::new(gaussian_grid(sigma, 0.04)).expect("spot");
        let nominal = moments(&spot.transformed(&ToolFigures::NOMINAL), 8.0, 0.04);
        let (kx, ky) = (0.08, -0.05);
        let skewed = ToolFigures {
            skew_x: kx,
            skew_y: ky,
            ..ToolFigures::NOMINAL
        };
        let m = moments(&spot.transformed(&skewed), 8.0, 0.04);
        assert!((m[0] / nominal[0] - 1.0).abs() < MOMENT_REL_TOL);
        // ∫ u f (1 + k·u / rho) = Σ k / rho per unit volume; Σ = sigma² I on a Gaussian.
        let rho = spot.radius_mm();
        let [sxx, sxy, syy] = spot.second_moments_mm2();
        assert!((sxx / (sigma * sigma) - 1.0).abs() < MOMENT_REL_TOL && sxy.abs() < 1e-9);
        let expected = ((sxx * kx + sxy * ky) / rho, (sxy * kx + syy * ky) / rho);
        assert!((m[1] / m[0] - expected.0).abs() < MOMENT_REL_TOL * expected.0.abs());
        assert!((m[2] / m[0] - expected.1).abs() < MOMENT_REL_TOL * expected.1.abs());
        // A tilted Gaussian is the shifted one (to first order in k): the offset that moves the
        // centroid as far reproduces it up to the second order of the shift over sigma.
        let shifted = ToolFigures {
            offset_x_mm: expected.0,
            offset_y_mm: expected.1,
            ..ToolFigures::NOMINAL
        };
        let (a, b) = (spot.transformed(&skewed), spot.transformed(&shifted));
        let peak = b.rate_nm_per_s(expected.0, expected.1);
        let shift_over_sigma2 = (expected.0.powi(2) + expected.1.powi(2)) / (sigma * sigma);
        for (x, y) in [(0.0, 0.0), (1.0, 0.5), (-1.5, 1.0), (2.0, -2.0)] {
            let diff = (a.rate_nm_per_s(x, y) - b.rate_nm_per_s(x, y)).abs();
            assert!(
                diff < 4.0 * shift_over_sigma2 * peak,
                "{diff} at ({x}, {y})"
            );
        }
        // The shift-free form takes that shift out: on a Gaussian it moves nothing.
        let m = moments(
            &spot.transformed_as(&skewed, SkewForm::ShiftFree),
            8.0,
            0.04,
        );
        assert!((m[0] / nominal[0] - 1.0).abs() < MOMENT_REL_TOL);
        assert!((m[1] / m[0]).abs() < 1e-3 * sigma, "{}", m[1] / m[0]);
        assert!((m[2] / m[0]).abs() < 1e-3 * sigma, "{}", m[2] / m[0]);
        let stretched = ToolFigures {
            ellipticity: 0.1,
            ..ToolFigures::NOMINAL
        };
        let e = moments(&spot.transformed(&stretched), 8.0, 0.04);
        assert!((e[0] / nominal[0] - 1.0).abs() < MOMENT_REL_TOL);
        // exp(0.1) along x, exp(-0.1) along y: the x variance grows by exp(0.2).
        let var_ratio = (e[3] / e[0]) / (nominal[3] / nominal[0]);
        assert!((var_ratio / 0.2f64.exp() - 1.0).abs() < MOMENT_REL_TOL);
        let var_ratio_y = (e[4] / e[0]) / (nominal[4] / nominal[0]);
        assert!((var_ratio_y / (-0.2f64).exp() - 1.0).abs() < MOMENT_REL_TOL);
    }
}
