//! Bonnet (inflated membrane) tool pressed into the part by a depth `h` and spun about an axis
//! precessed by an angle from the part normal.
//!
//! # Geometry
//!
//! The undeformed bonnet is a sphere of radius `R` whose centre sits at height `R - h` above the
//! part; its intersection with the part plane is the polishing spot of radius
//! `a = sqrt(R^2 - (R - h)^2) = sqrt(2 R h - h^2)`.
//!
//! # Pressure (Winkler foundation on the interference)
//!
//! The membrane is pushed back by the interference `delta(r) = sqrt(R^2 - r^2) - (R - h)` (`h` at
//! the centre, 0 at the spot edge) and the pressure is proportional to it:
//! `p(r) = p_max delta(r) / h`. `p_max` follows from the normal force:
//! `F = p_max / h * 2 pi [ (R^3 - (R - h)^3) / 3 - (R - h) a^2 / 2 ]`.
//!
//! # Velocity
//!
//! As for the tilted sphere of [`super::hertz`], with the centre at height `R - h`:
//! `v_t(x, y) = omega sqrt(((R - h) sin t + y cos t)^2 + x^2 cos^2 t)` for precession angle `t`.
//! With `precession_azimuths = N > 1` the tilt plane is turned to the `N` azimuths
//! `2 pi k / N` and the removal rates are averaged (the usual multi-precession TIF).
//!
//! Removal: `rate = K p v` (K mm^2/N, p MPa, v mm/s -> mm/s, stored as nm/s).

use super::grid::GridTif;
use super::hertz::{sample_on_grid, tilted_spin_speed};
use super::InfluenceFunction;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Parameters of a bonnet tool (settings).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BonnetParams {
    /// Bonnet radius, mm.
    pub bonnet_radius_mm: f64,
    /// Pressing depth (tool offset), mm; below the bonnet radius.
    pub depth_mm: f64,
    /// Precession angle between the spindle axis and the part normal, degrees.
    pub precession_deg: f64,
    /// Number of precession azimuths averaged (1: a single tilted position).
    pub precession_azimuths: usize,
    /// Spindle speed, rad/s.
    pub spindle_rad_s: f64,
    /// Normal force, N.
    pub force_n: f64,
    /// Preston coefficient, mm^2/N.
    pub preston_k_mm2_per_n: f64,
}

impl Default for BonnetParams {
    fn default() -> Self {
        Self {
            bonnet_radius_mm: 20.0,
            depth_mm: 0.3,
            precession_deg: 20.0,
            precession_azimuths: 1,
            spindle_rad_s: 104.72,
            force_n: 10.0,
            preston_k_mm2_per_n: 1e-7,
        }
    }
}

impl BonnetParams {
    /// Checks ranges: radius, force, K positive; `0 < depth < radius`; precession in [0, 90];
    /// at least one azimuth (at most 360); spindle speed non-negative.
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("bonnet bonnet_radius_mm", self.bonnet_radius_mm),
            ("bonnet depth_mm", self.depth_mm),
            ("bonnet force_n", self.force_n),
            ("bonnet preston_k_mm2_per_n", self.preston_k_mm2_per_n),
        ])?;
        if self.depth_mm >= self.bonnet_radius_mm {
            return Err(Error::invalid(
                "bonnet depth_mm",
                format!(
                    "{} mm must be below the bonnet radius {} mm",
                    self.depth_mm, self.bonnet_radius_mm
                ),
            ));
        }
        if !(self.precession_deg.is_finite() && (0.0..=90.0).contains(&self.precession_deg)) {
            return Err(Error::invalid(
                "bonnet precession_deg",
                format!("must be in [0, 90], got {}", self.precession_deg),
            ));
        }
        if !(1..=360).contains(&self.precession_azimuths) {
            return Err(Error::invalid(
                "bonnet precession_azimuths",
                format!("must be 1..=360, got {}", self.precession_azimuths),
            ));
        }
        if !(self.spindle_rad_s.is_finite() && self.spindle_rad_s >= 0.0) {
            return Err(Error::invalid(
                "bonnet spindle_rad_s",
                format!("must be non-negative, got {}", self.spindle_rad_s),
            ));
        }
        Ok(())
    }
}

/// Spot radius of a sphere of radius `r` pressed by depth `h`: `sqrt(2 r h - h^2)`, mm.
pub fn spot_radius_mm(bonnet_radius_mm: f64, depth_mm: f64) -> f64 {
    (2.0 * bonnet_radius_mm * depth_mm - depth_mm * depth_mm)
        .max(0.0)
        .sqrt()
}

/// Pressing depth giving spot radius `a`: `h = R - sqrt(R^2 - a^2)` (inverse of
/// [`spot_radius_mm`]), mm; `None` if `a > R`.
pub fn depth_for_spot_mm(bonnet_radius_mm: f64, spot_radius_mm: f64) -> Option<f64> {
    let d = bonnet_radius_mm * bonnet_radius_mm - spot_radius_mm * spot_radius_mm;
    (d >= 0.0).then(|| bonnet_radius_mm - d.sqrt())
}

/// The bonnet TIF (analytic; see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct BonnetTif {
    params: BonnetParams,
    spot_radius_mm: f64,
    peak_pressure_mpa: f64,
    azimuths: Vec<(f64, f64)>,
    sin_t: f64,
    cos_t: f64,
}

impl BonnetTif {
    /// Builds the model from validated parameters.
    pub fn new(params: &BonnetParams) -> Result<Self> {
        params.validate()?;
        let (r, h) = (params.bonnet_radius_mm, params.depth_mm);
        let a = spot_radius_mm(r, h);
        let c = r - h;
        let integral = 2.0 * PI * ((r.powi(3) - c.powi(3)) / 3.0 - c * a * a / 2.0);
        let p_max = params.force_n * h / integral;
        let n = params.precession_azimuths;
        let azimuths = (0..n)
            .map(|k| (2.0 * PI * k as f64 / n as f64).sin_cos())
            .collect();
        let t = params.precession_deg.to_radians();
        Ok(Self {
            params: params.clone(),
            spot_radius_mm: a,
            peak_pressure_mpa: p_max,
            azimuths,
            sin_t: t.sin(),
            cos_t: t.cos(),
        })
    }

    /// Spot radius `sqrt(2 R h - h^2)`, mm.
    pub fn spot_radius_mm(&self) -> f64 {
        self.spot_radius_mm
    }

    /// Pressure at the spot centre, MPa.
    pub fn peak_pressure_mpa(&self) -> f64 {
        self.peak_pressure_mpa
    }

    /// Pressure `p_max (sqrt(R^2 - r^2) - (R - h)) / h`, MPa; 0 outside the spot.
    #[inline]
    pub fn pressure_mpa(&self, x_mm: f64, y_mm: f64) -> f64 {
        let (r, h) = (self.params.bonnet_radius_mm, self.params.depth_mm);
        let d = (r * r - x_mm * x_mm - y_mm * y_mm).max(0.0).sqrt() - (r - h);
        if d > 0.0 {
            self.peak_pressure_mpa * d / h
        } else {
            0.0
        }
    }

    /// Sliding speed for the first azimuth (tilt in the y-z plane), mm/s.
    #[inline]
    pub fn sliding_speed_mm_per_s(&self, x_mm: f64, y_mm: f64) -> f64 {
        tilted_spin_speed(
            x_mm,
            y_mm,
            self.params.spindle_rad_s,
            self.params.bonnet_radius_mm - self.params.depth_mm,
            self.sin_t,
            self.cos_t,
        )
    }

    /// Samples the TIF on a square grid of pitch `pitch_mm` covering the spot.
    pub fn to_grid(&self, pitch_mm: f64) -> Result<GridTif> {
        sample_on_grid(self, self.spot_radius_mm, pitch_mm)
    }
}

impl InfluenceFunction for BonnetTif {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let p = self.pressure_mpa(dx_mm, dy_mm);
        if p == 0.0 {
            return 0.0;
        }
        // Rotate the offset into each azimuth's frame (tilt plane along its y axis).
        let v: f64 = self
            .azimuths
            .iter()
            .map(|&(s, c)| {
                self.sliding_speed_mm_per_s(c * dx_mm + s * dy_mm, -s * dx_mm + c * dy_mm)
            })
            .sum::<f64>()
            / self.azimuths.len() as f64;
        self.params.preston_k_mm2_per_n * p * v * 1e6
    }

    fn support_radius_mm(&self) -> f64 {
        self.spot_radius_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spot_radius_pressure_and_force() {
        let p = BonnetParams::default();
        let t = BonnetTif::new(&p).unwrap();
        // sqrt(2 * 20 * 0.3 - 0.09) = sqrt(11.91).
        assert!((t.spot_radius_mm() - 11.91f64.sqrt()).abs() < 1e-12);
        assert!((depth_for_spot_mm(20.0, t.spot_radius_mm()).unwrap() - 0.3).abs() < 1e-12);
        // Pressure integrates to the force (midpoint rule in r).
        let a = t.spot_radius_mm();
        let n = 20_000;
        let dr = a / n as f64;
        let f: f64 = (0..n)
            .map(|k| {
                let r = (k as f64 + 0.5) * dr;
                t.pressure_mpa(r, 0.0) * 2.0 * PI * r * dr
            })
            .sum();
        assert!((f - p.force_n).abs() < 1e-6 * p.force_n, "{f}");
        assert!((t.pressure_mpa(0.0, 0.0) - t.peak_pressure_mpa()).abs() < 1e-12);
        assert_eq!(t.pressure_mpa(a * 1.001, 0.0), 0.0);
        // Four azimuths: symmetric under a quarter turn.
        let t4 = BonnetTif::new(&BonnetParams {
            precession_azimuths: 4,
            ..p.clone()
        })
        .unwrap();
        let (x, y) = (1.3, -2.1);
        assert!((t4.rate_nm_per_s(x, y) - t4.rate_nm_per_s(-y, x)).abs() < 1e-9);
        assert!(BonnetTif::new(&BonnetParams {
            depth_mm: 25.0,
            ..p
        })
        .is_err());
    }
}
