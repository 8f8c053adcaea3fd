//! A virtual shop for a measured part: the tool the shop really has and the interferometer that
//! reads the part, to rehearse the measure-calibrate-plan-polish loop.
//!
//! The true tool is the spot test `f` changed as a real tool differs from it:
//!
//! ```text
//! f_true(d, t) = r (1 + δ_run (t - t_mid) / T) / w² · f(u) · max(0, 1 + k (d - c - o)·e / (w rho)),
//! u = c + exp(-E) (d - c - o) / w,
//! ```
//!
//! a rate `r`, a width `w` (volume kept), an offset `o`, an ellipticity `E`, a *linear* skew `k`
//! across the footprint along direction `e` (it also moves the centroid; taken in the part's axes,
//! `(d - c - o) / w = exp(E) (u - c)`, so with an ellipticity it is [`crate::calibrate`]'s skew
//! turned and scaled by `exp(E)`), and a drift of the rate by `δ_run` over the run's span `T` about
//! its middle `t_mid`. The interferometer adds white noise and drops piston and
//! tilt (a least-squares plane), as a phase-shifting interferometer's software does.

use crate::calibrate::{ContactMotion, SpotFootprint, ToolFigures, TransformedTif};
use crate::error::{Error, Result};
use crate::map::remove_plane;
use crate::rng::SplitMix64;
use crate::tif::InfluenceFunction;
use serde::{Deserialize, Serialize};

/// The tool a shop really has, against its spot test (module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ShopTool {
    /// Rate factor `r`.
    pub rate_factor: f64,
    /// Width factor `w`, volume kept.
    pub width_factor: f64,
    /// Offset of the footprint from the programmed point along x, mm.
    pub offset_x_mm: f64,
    /// Offset along y, mm.
    pub offset_y_mm: f64,
    /// Ellipticity along the axes (log stretch).
    pub ellipticity: f64,
    /// Linear skew `k` across the footprint (relative rate change per second-moment radius).
    pub skew: f64,
    /// Direction of the skew, degrees from x.
    pub skew_angle_deg: f64,
    /// Relative change of the rate from the run's first contact to its last.
    pub drift_per_run: f64,
}

impl Default for ShopTool {
    fn default() -> Self {
        Self {
            rate_factor: 1.0,
            width_factor: 1.0,
            offset_x_mm: 0.0,
            offset_y_mm: 0.0,
            ellipticity: 0.0,
            skew: 0.0,
            skew_angle_deg: 0.0,
            drift_per_run: 0.0,
        }
    }
}

/// The true footprint at a fixed time (drift aside).
pub(crate) struct TrueFootprint<'a> {
    transformed: TransformedTif<'a>,
    spot: &'a SpotFootprint,
    tool: ShopTool,
}

impl InfluenceFunction for TrueFootprint<'_> {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let f = self.transformed.rate_nm_per_s(dx_mm, dy_mm);
        if f == 0.0 || self.tool.skew == 0.0 {
            return f;
        }
        let (cx, cy) = self.spot.centroid_mm();
        let (ex, ey) = (
            self.tool.skew_angle_deg.to_radians().cos(),
            self.tool.skew_angle_deg.to_radians().sin(),
        );
        let along =
            (dx_mm - cx - self.tool.offset_x_mm) * ex + (dy_mm - cy - self.tool.offset_y_mm) * ey;
        let scale = self.tool.width_factor * self.spot.radius_mm();
        f * (1.0 + self.tool.skew * along / scale).max(0.0)
    }

    fn support_radius_mm(&self) -> f64 {
        self.transformed.support_radius_mm()
    }
}

/// Volume ratio, second-moment width ratio and centroid offset of a footprint against the spot
/// test, by sums over a fine grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FootprintFigures {
    /// Volume ratio.
    pub rate_factor: f64,
    /// Ratio of second-moment radii.
    pub width_factor: f64,
    /// Centroid offset from the spot test's along x, mm.
    pub offset_x_mm: f64,
    /// Along y, mm.
    pub offset_y_mm: f64,
}

impl ShopTool {
    /// Checks that the figures are finite and the rate and width positive.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("rate_factor", self.rate_factor),
            ("width_factor", self.width_factor),
            ("offset_x_mm", self.offset_x_mm),
            ("offset_y_mm", self.offset_y_mm),
            ("ellipticity", self.ellipticity),
            ("skew", self.skew),
            ("skew_angle_deg", self.skew_angle_deg),
            ("drift_per_run", self.drift_per_run),
        ] {
            if !v.is_finite() {
                return Err(Error::invalid(
                    format!("shop tool {name}"),
                    format!("must be finite, got {v}"),
                ));
            }
        }
        if !(self.rate_factor > 0.0 && self.width_factor > 0.0) {
            return Err(Error::invalid(
                "shop tool",
                "rate_factor and width_factor must be positive",
            ));
        }
        Ok(())
    }

    pub(crate) fn footprint<'a>(&self, spot: &'a SpotFootprint) -> TrueFootprint<'a> {
        let figures = ToolFigures {
            rate_factor: self.rate_factor,
            width_factor: self.width_factor,
            offset_x_mm: self.offset_x_mm,
            offset_y_mm: self.offset_y_mm,
            ellipticity: self.ellipticity,
            ..ToolFigures::NOMINAL
        };
        TrueFootprint {
            transformed: spot.transformed(&figures),
            spot,
            tool: *self,
        }
    }

    /// The true footprint's figures against the spot test (what a calibration should find).
    pub fn figures(&self, spot: &SpotFootprint) -> FootprintFigures {
        let moments = |f: &dyn InfluenceFunction| {
            let r = f.support_radius_mm();
            let h = spot.radius_mm() / 40.0;
            let n = (r / h).ceil() as i64;
            let mut m = [0.0; 4];
            for j in -n..=n {
                for i in -n..=n {
                    let (x, y) = (i as f64 * h, j as f64 * h);
                    let v = f.rate_nm_per_s(x, y);
                    m[0] += v;
                    m[1] += v * x;
                    m[2] += v * y;
                    m[3] += v * (x * x + y * y);
                }
            }
            let (cx, cy) = (m[1] / m[0], m[2] / m[0]);
            (
                m[0],
                cx,
                cy,
                (m[3] / m[0] - cx * cx - cy * cy).max(0.0).sqrt(),
            )
        };
        let nominal = spot.transformed(&ToolFigures::NOMINAL);
        let (v0, x0, y0, r0) = moments(&nominal);
        let (v1, x1, y1, r1) = moments(&self.footprint(spot));
        FootprintFigures {
            rate_factor: v1 / v0,
            width_factor: r1 / r0,
            offset_x_mm: x1 - x0,
            offset_y_mm: y1 - y0,
        }
    }

    /// The rate's factor from its drift at program time `at_s` of a run whose contacts span
    /// `span_s` about `mid_s`: `1 + δ_run (t - t_mid) / T`.
    pub fn drift_factor(&self, at_s: f64, mid_s: f64, span_s: f64) -> f64 {
        1.0 + self.drift_per_run * (at_s - mid_s) / span_s.max(f64::MIN_POSITIVE)
    }

    /// The removal of `motion` at the points `(x_mm, y_mm)` by this tool, summed directly over
    /// the contact samples, nm.
    pub fn removal_nm(
        &self,
        spot: &SpotFootprint,
        motion: &ContactMotion,
        x_mm: &[f64],
        y_mm: &[f64],
    ) -> Result<Vec<f64>> {
        self.validate()?;
        motion.validate()?;
        let span = motion.span_s().max(f64::MIN_POSITIVE);
        let mid = motion.mid_time_s();
        let dwell: Vec<f64> = motion
            .dwell_s
            .iter()
            .zip(&motion.time_s)
            .map(|(d, &t)| d * self.drift_factor(t, mid, span))
            .collect();
        crate::simulate::direct::removal_nm(
            x_mm,
            y_mm,
            &motion.x_mm,
            &motion.y_mm,
            &dwell,
            &self.footprint(spot),
            &crate::observer::Silent,
        )
    }
}

/// An interferometer: white noise of `noise_rms_nm` per pixel, piston and tilt dropped.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Interferometer {
    /// Noise per pixel, nm RMS.
    pub noise_rms_nm: f64,
}

impl Interferometer {
    /// The reading of the surface `z_nm` at `(x, y)`: plus noise from `rng`, less its
    /// least-squares plane.
    pub fn measure(
        &self,
        x_mm: &[f64],
        y_mm: &[f64],
        z_nm: &[f64],
        rng: &mut SplitMix64,
    ) -> Result<Vec<f64>> {
        if !(self.noise_rms_nm.is_finite() && self.noise_rms_nm >= 0.0) {
            return Err(Error::invalid(
                "interferometer noise_rms_nm",
                format!("must be finite and >= 0, got {}", self.noise_rms_nm),
            ));
        }
        let mut z: Vec<f64> = z_nm
            .iter()
            .map(|v| v + self.noise_rms_nm * rng.normal())
            .collect();
        remove_plane(x_mm, y_mm, &mut z)?;
        Ok(z)
    }
}
