//! Programs for rotationally symmetric aspheres polished on a rotating workpiece with a tool that
//! feeds radially (`preston asphere`).
//!
//! Constant removal volume (the tool sweeps equal area per unit time): workpiece speed
//! `n(x) = phi n_max n_min / (phi n_min + 2 x (n_max - n_min))` for radius `x` in `[0, phi/2]`
//! (`n(0) = n_max`, `n(phi/2) = n_min`), radial feed `F(x) = n(x) dx` (mm/min, `dx` the feed per
//! revolution). Closed-loop compensation from a measured profile error `dz(x)`:
//! `k(x) = a + b [1 - (dz(x) - dz_min) / (dz_max - dz_min)]`, `F'(x) = k(x) F(x)` (slower where the
//! error is high). Edge compression correction: `dZ = c + (d - c)(x - x1)/(x2 - x1)` on
//! `[x1, x2]` (0 elsewhere), `Z = Z0 + dZ`. `Z0` is the even-asphere sag
//! `z = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + sum A_{2i} r^{2i}` and `B = atan(dZ0/dx)`.
//!
//! NC lines: `N<k> X<x> Z<z> B<b> S<rpm> F<feed>` (X, Z mm with 4 decimals, B deg with 4,
//! S rpm with 1, F mm/min with 3; trailing zeros dropped, so `X0 S1000 F10`).

use super::trimmed;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::io::Write;

/// The speed law: aperture, spindle limits and feed per revolution.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpeedLaw {
    /// Clear aperture `phi`, mm.
    pub aperture_mm: f64,
    /// Workpiece speed at the centre, rpm.
    pub n_max_rpm: f64,
    /// Workpiece speed at the edge (`x = phi/2`), rpm.
    pub n_min_rpm: f64,
    /// Radial feed per revolution `dx`, mm.
    pub dx_mm: f64,
}

impl SpeedLaw {
    /// Checks `phi, n_min, dx > 0` and `n_min <= n_max`, all finite.
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("aperture_mm", self.aperture_mm),
            ("n_max_rpm", self.n_max_rpm),
            ("n_min_rpm", self.n_min_rpm),
            ("dx_mm", self.dx_mm),
        ])?;
        if self.n_min_rpm > self.n_max_rpm {
            return Err(Error::invalid(
                "n_min_rpm",
                format!("{} exceeds n_max_rpm {}", self.n_min_rpm, self.n_max_rpm),
            ));
        }
        Ok(())
    }

    /// `n(x) = phi n_max n_min / (phi n_min + 2 x (n_max - n_min))`, rpm.
    pub fn speed_rpm(&self, x_mm: f64) -> f64 {
        let (phi, n1, n0) = (self.aperture_mm, self.n_max_rpm, self.n_min_rpm);
        phi * n1 * n0 / (phi * n0 + 2.0 * x_mm * (n1 - n0))
    }

    /// `F(x) = n(x) dx`, mm/min.
    pub fn feed_mm_per_min(&self, x_mm: f64) -> f64 {
        self.speed_rpm(x_mm) * self.dx_mm
    }

    /// The `n_min` for which `n(x) = s` (the law solved for `n_min`):
    /// `n_min = 2 x s n_max / (phi (n_max - s) + 2 x s)`, rpm.
    pub fn n_min_for_speed(aperture_mm: f64, n_max_rpm: f64, x_mm: f64, s_rpm: f64) -> Result<f64> {
        let den = aperture_mm * (n_max_rpm - s_rpm) + 2.0 * x_mm * s_rpm;
        let n0 = 2.0 * x_mm * s_rpm * n_max_rpm / den;
        if !(n0.is_finite() && n0 > 0.0 && n0 <= n_max_rpm) {
            return Err(Error::invalid(
                "speed at x",
                format!("no n_min in (0, n_max] gives {s_rpm} rpm at {x_mm} mm (got {n0})"),
            ));
        }
        Ok(n0)
    }
}

/// The even-asphere sag profile `Z0(x)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct AsphereProfile {
    /// Vertex radius of curvature, mm; absent: flat (`c = 0`).
    pub radius_mm: Option<f64>,
    /// Conic constant `k`.
    pub conic: f64,
    /// Even coefficients `A4, A6, ...` (mm^(1-2i)).
    pub coefficients: Vec<f64>,
}

impl AsphereProfile {
    fn curvature(&self) -> f64 {
        match self.radius_mm {
            Some(r) if r != 0.0 && r.is_finite() => 1.0 / r,
            _ => 0.0,
        }
    }

    /// Sag `z(r)`, mm; an error where the conic term has no real value.
    pub fn sag_mm(&self, r_mm: f64) -> Result<f64> {
        let c = self.curvature();
        let arg = 1.0 - (1.0 + self.conic) * c * c * r_mm * r_mm;
        if arg < 0.0 {
            return Err(Error::Geometry(format!(
                "asphere sag undefined at r = {r_mm} mm (1 - (1+k) c^2 r^2 = {arg})"
            )));
        }
        let mut z = c * r_mm * r_mm / (1.0 + arg.sqrt());
        for (i, a) in self.coefficients.iter().enumerate() {
            z += a * r_mm.powi(2 * i as i32 + 4);
        }
        Ok(z)
    }

    /// Slope `dz/dr = c r / sqrt(1 - (1+k) c^2 r^2) + sum 2i A_{2i} r^{2i-1}`.
    pub fn slope(&self, r_mm: f64) -> Result<f64> {
        let c = self.curvature();
        let arg = 1.0 - (1.0 + self.conic) * c * c * r_mm * r_mm;
        if arg <= 0.0 && c != 0.0 {
            return Err(Error::Geometry(format!(
                "asphere slope undefined at r = {r_mm} mm"
            )));
        }
        let mut s = if c == 0.0 { 0.0 } else { c * r_mm / arg.sqrt() };
        for (i, a) in self.coefficients.iter().enumerate() {
            let p = 2 * i as i32 + 4;
            s += f64::from(p) * a * r_mm.powi(p - 1);
        }
        Ok(s)
    }
}

/// Closed-loop feed factor `k(x) = a + b [1 - (dz - dz_min)/(dz_max - dz_min)]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FeedCompensation {
    /// Factor where the error is largest.
    pub a: f64,
    /// Added factor where the error is smallest (`k = a + b` there).
    pub b: f64,
}

impl Default for FeedCompensation {
    fn default() -> Self {
        Self { a: 0.5, b: 1.0 }
    }
}

/// Edge compression correction `dZ = c + (d - c)(x - x1)/(x2 - x1)` on `[x1, x2]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EdgeCorrection {
    /// Start of the correction, mm.
    pub x1_mm: f64,
    /// End of the correction, mm.
    pub x2_mm: f64,
    /// `dZ` at `x1`, mm.
    pub c_mm: f64,
    /// `dZ` at `x2`, mm.
    pub d_mm: f64,
}

impl EdgeCorrection {
    /// `dZ(x)`, mm (0 outside `[x1, x2]`).
    pub fn dz_mm(&self, x_mm: f64) -> f64 {
        if x_mm < self.x1_mm || x_mm > self.x2_mm {
            0.0
        } else {
            self.c_mm + (self.d_mm - self.c_mm) * (x_mm - self.x1_mm) / (self.x2_mm - self.x1_mm)
        }
    }
}

/// A measured profile error `dz(x)`, linear between samples, constant beyond the ends.
#[derive(Debug, Clone, PartialEq)]
pub struct ProfileError {
    x_mm: Vec<f64>,
    error_nm: Vec<f64>,
}

impl ProfileError {
    /// Sorts the samples by `x`; at least two, finite, with distinct `x`.
    pub fn new(x_mm: Vec<f64>, error_nm: Vec<f64>) -> Result<Self> {
        if x_mm.len() != error_nm.len() {
            return Err(Error::LengthMismatch {
                what: "profile error_nm",
                got: error_nm.len(),
                expected: x_mm.len(),
            });
        }
        if x_mm.len() < 2 {
            return Err(Error::invalid(
                "profile error",
                "needs at least two samples",
            ));
        }
        let mut pairs: Vec<(f64, f64)> = x_mm.into_iter().zip(error_nm).collect();
        if let Some((i, p)) = pairs
            .iter()
            .enumerate()
            .find(|(_, p)| !(p.0.is_finite() && p.1.is_finite()))
        {
            return Err(Error::NonFinite {
                what: "profile error",
                index: i,
                detail: format!("x_mm={}, error_nm={}", p.0, p.1),
            });
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
        if pairs.windows(2).any(|w| w[0].0 == w[1].0) {
            return Err(Error::invalid("profile error", "repeats an x_mm value"));
        }
        Ok(Self {
            x_mm: pairs.iter().map(|p| p.0).collect(),
            error_nm: pairs.iter().map(|p| p.1).collect(),
        })
    }

    /// Sample positions, mm (ascending).
    pub fn x_mm(&self) -> &[f64] {
        &self.x_mm
    }

    /// `dz(x)`, nm, interpolated linearly.
    pub fn at(&self, x_mm: f64) -> f64 {
        let xs = &self.x_mm;
        let n = xs.len();
        if x_mm <= xs[0] {
            return self.error_nm[0];
        }
        if x_mm >= xs[n - 1] {
            return self.error_nm[n - 1];
        }
        let i = xs.partition_point(|&v| v <= x_mm).clamp(1, n - 1);
        let (x0, x1) = (xs[i - 1], xs[i]);
        let (e0, e1) = (self.error_nm[i - 1], self.error_nm[i]);
        e0 + (e1 - e0) * (x_mm - x0) / (x1 - x0)
    }

    /// `(dz_min, dz_max)`, nm.
    pub fn range_nm(&self) -> (f64, f64) {
        self.error_nm
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            })
    }
}

/// A whole asphere job (a job-file section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AsphereJob {
    /// The speed law.
    pub law: SpeedLaw,
    /// Radial step of the program, mm (default: `dx_mm`); ignored when `x_mm` is given.
    #[serde(default)]
    pub step_mm: Option<f64>,
    /// Explicit radii of the program lines, mm, in `[0, phi/2]`.
    #[serde(default)]
    pub x_mm: Option<Vec<f64>>,
    /// The sag profile (default flat).
    #[serde(default)]
    pub profile: AsphereProfile,
    /// Closed-loop feed factor (used with a profile error).
    #[serde(default)]
    pub feed_compensation: FeedCompensation,
    /// Edge compression correction.
    #[serde(default)]
    pub edge: Option<EdgeCorrection>,
}

impl AsphereJob {
    /// A job with the law and defaults for everything else.
    pub fn new(law: SpeedLaw) -> Self {
        Self {
            law,
            step_mm: None,
            x_mm: None,
            profile: AsphereProfile::default(),
            feed_compensation: FeedCompensation::default(),
            edge: None,
        }
    }

    /// Checks the law, the grid and the corrections.
    pub fn validate(&self) -> Result<()> {
        self.law.validate()?;
        let half = 0.5 * self.law.aperture_mm;
        if let Some(s) = self.step_mm {
            if !(s.is_finite() && s > 0.0) {
                return Err(Error::invalid(
                    "step_mm",
                    format!("must be positive, got {s}"),
                ));
            }
            if half / s > 1e7 {
                return Err(Error::invalid("step_mm", "gives more than 1e7 lines"));
            }
        } else if half / self.law.dx_mm > 1e7 {
            return Err(Error::invalid("dx_mm", "gives more than 1e7 lines"));
        }
        if let Some(xs) = &self.x_mm {
            if let Some(x) = xs
                .iter()
                .find(|x| !(**x >= 0.0 && **x <= half * (1.0 + 1e-12)))
            {
                return Err(Error::invalid(
                    "x_mm",
                    format!("{x} mm is outside [0, {half}] mm (half the aperture)"),
                ));
            }
        }
        let k = self.feed_compensation;
        if !(k.a.is_finite() && k.b.is_finite() && k.a > 0.0 && k.a + k.b > 0.0) {
            return Err(Error::invalid(
                "feed_compensation",
                format!(
                    "k = a + b [..] must stay positive, got a = {}, b = {}",
                    k.a, k.b
                ),
            ));
        }
        if let Some(e) = &self.edge {
            if !(e.x1_mm.is_finite() && e.x2_mm.is_finite() && e.x2_mm > e.x1_mm) {
                return Err(Error::invalid(
                    "edge",
                    format!("needs x1_mm < x2_mm, got [{}, {}]", e.x1_mm, e.x2_mm),
                ));
            }
            if !(e.c_mm.is_finite() && e.d_mm.is_finite()) {
                return Err(Error::invalid("edge", "c_mm and d_mm must be finite"));
            }
        }
        Ok(())
    }

    /// The radii of the program: `x_mm`, else the profile-error samples inside the aperture, else
    /// `0, step, 2 step, ...` up to and including `phi / 2`.
    pub fn grid_mm(&self, error: Option<&ProfileError>) -> Vec<f64> {
        let half = 0.5 * self.law.aperture_mm;
        if let Some(xs) = &self.x_mm {
            return xs.clone();
        }
        if let Some(e) = error {
            let inside: Vec<f64> = e
                .x_mm()
                .iter()
                .copied()
                .filter(|&x| (0.0..=half).contains(&x))
                .collect();
            if !inside.is_empty() {
                return inside;
            }
        }
        let step = self.step_mm.unwrap_or(self.law.dx_mm);
        let count = (half / step - 1e-9).ceil().max(0.0) as usize;
        let mut xs: Vec<f64> = (0..count).map(|i| i as f64 * step).collect();
        xs.push(half);
        xs
    }
}

/// One NC line.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AsphereLine {
    /// Radius, mm.
    pub x_mm: f64,
    /// `Z = Z0 + dZ`, mm.
    pub z_mm: f64,
    /// Tool-axis angle `atan(dZ0/dx)`, degrees.
    pub b_deg: f64,
    /// Workpiece speed `n(x)`, rpm.
    pub s_rpm: f64,
    /// Compensation factor `k(x)` (1 without a profile error).
    pub k: f64,
    /// Feed `k(x) n(x) dx`, mm/min.
    pub f_mm_per_min: f64,
}

/// Computes the lines of the program.
pub fn program(job: &AsphereJob, error: Option<&ProfileError>) -> Result<Vec<AsphereLine>> {
    job.validate()?;
    let range = error.map(ProfileError::range_nm);
    job.grid_mm(error)
        .into_iter()
        .map(|x| {
            let k = match (error, range) {
                (Some(e), Some((lo, hi))) if hi > lo => {
                    let fc = job.feed_compensation;
                    fc.a + fc.b * (1.0 - (e.at(x) - lo) / (hi - lo))
                }
                _ => 1.0,
            };
            let z0 = job.profile.sag_mm(x)?;
            let dz = job.edge.map_or(0.0, |e| e.dz_mm(x));
            let s = job.law.speed_rpm(x);
            Ok(AsphereLine {
                x_mm: x,
                z_mm: z0 + dz,
                b_deg: job.profile.slope(x)?.atan().to_degrees(),
                s_rpm: s,
                k,
                f_mm_per_min: k * s * job.law.dx_mm,
            })
        })
        .collect()
}

/// Writes the program: a header of comments, `G21 G90 G94`, the numbered lines and `M30`.
pub fn write_nc(job: &AsphereJob, lines: &[AsphereLine], w: &mut dyn Write) -> std::io::Result<()> {
    let l = &job.law;
    writeln!(w, "%")?;
    writeln!(w, "(PRESTON ASPHERE PROGRAM)")?;
    writeln!(w, "(UNITS MM, SPEED RPM, FEED MM/MIN, ANGLE DEG)")?;
    writeln!(
        w,
        "(APERTURE {} MM, N_MAX {} RPM, N_MIN {} RPM, DX {} MM/REV, LINES {})",
        trimmed(l.aperture_mm, 6),
        trimmed(l.n_max_rpm, 6),
        trimmed(l.n_min_rpm, 6),
        trimmed(l.dx_mm, 6),
        lines.len()
    )?;
    writeln!(
        w,
        "(N = PHI NMAX NMIN / [PHI NMIN + 2 X [NMAX - NMIN]], F = K N DX)"
    )?;
    writeln!(w, "G21 G90 G94")?;
    for (i, p) in lines.iter().enumerate() {
        writeln!(
            w,
            "N{} X{} Z{} B{} S{} F{}",
            i + 1,
            trimmed(p.x_mm, 4),
            trimmed(p.z_mm, 4),
            trimmed(p.b_deg, 4),
            trimmed(p.s_rpm, 1),
            trimmed(p.f_mm_per_min, 3)
        )?;
    }
    writeln!(w, "M30")?;
    writeln!(w, "%")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn law_ends_and_inverse() {
        let law = SpeedLaw {
            aperture_mm: 15.0,
            n_max_rpm: 1000.0,
            n_min_rpm: 30.0,
            dx_mm: 0.01,
        };
        assert!((law.speed_rpm(0.0) - 1000.0).abs() < 1e-9);
        assert!((law.speed_rpm(7.5) - 30.0).abs() < 1e-9);
        let n0 = SpeedLaw::n_min_for_speed(15.0, 1000.0, 2.0, law.speed_rpm(2.0)).unwrap();
        assert!((n0 - 30.0).abs() < 1e-9);
    }

    #[test]
    fn sphere_sag_and_slope() {
        // R = 50: z = R - sqrt(R^2 - r^2), dz/dr = r / sqrt(R^2 - r^2).
        let p = AsphereProfile {
            radius_mm: Some(50.0),
            ..Default::default()
        };
        let r: f64 = 10.0;
        assert!((p.sag_mm(r).unwrap() - (50.0 - (2500.0 - r * r).sqrt())).abs() < 1e-12);
        assert!((p.slope(r).unwrap() - r / (2500.0 - r * r).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn compensation_factor_and_edge() {
        let e = ProfileError::new(vec![0.0, 1.0, 2.0], vec![10.0, 30.0, 20.0]).unwrap();
        let mut job = AsphereJob::new(SpeedLaw {
            aperture_mm: 4.0,
            n_max_rpm: 100.0,
            n_min_rpm: 50.0,
            dx_mm: 0.1,
        });
        job.feed_compensation = FeedCompensation { a: 0.5, b: 1.0 };
        job.edge = Some(EdgeCorrection {
            x1_mm: 1.5,
            x2_mm: 2.0,
            c_mm: 0.0,
            d_mm: 0.01,
        });
        let lines = program(&job, Some(&e)).unwrap();
        assert_eq!(lines.len(), 3);
        // dz = 10 (min) -> k = a + b; dz = 30 (max) -> k = a; dz = 20 -> a + b/2.
        assert!((lines[0].k - 1.5).abs() < 1e-12);
        assert!((lines[1].k - 0.5).abs() < 1e-12);
        assert!((lines[2].k - 1.0).abs() < 1e-12);
        assert!((lines[2].z_mm - 0.01).abs() < 1e-15);
        assert_eq!(lines[1].z_mm, 0.0);
    }
}
