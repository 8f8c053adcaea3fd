//! Normal-displacement compensation: how far the tool must be moved along the surface normal so
//! that a plane toolhead, loaded with abrasive grains, presses on the part with the intended force.
//!
//! Hertz contact (Johnson, *Contact Mechanics*, 1985, ch. 4) for the toolhead on the part and for
//! a grain on the part:
//!
//! ```text
//! delta       = delta_e0 + delta_e2max + 3 sigma
//! delta_e0    = (9 F^2 / (16 R_e E0*^2))^(1/3)          toolhead (E1, nu1) on part (E2, nu2)
//! delta_e2max = pi^2 R_rho2 H^2 / (16 E2*^2)            grain on part, up to yield (H)
//! 1/E*        = (1 - nu1^2)/E1 + (1 - nu2^2)/E2
//! 1/R_rho2    = 1/R_grain + 1/R_e                       R_e: local curvature radius of the part
//! ```
//!
//! `H` is the smaller hardness of grain and part (the body that yields first). Units: F in N,
//! radii and sigma in mm, moduli and hardness in GPa (converted to N/mm^2 = MPa); delta in mm.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// GPa to N/mm^2.
const N_PER_MM2_PER_GPA: f64 = 1000.0;

/// Elastic and plastic properties of one body (a row of the material table).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// Young's modulus, GPa.
    pub e_gpa: f64,
    /// Poisson's ratio.
    pub nu: f64,
    /// Hardness (Brinell or Vickers as a pressure), GPa; needed for the part or the grain.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hardness_gpa: Option<f64>,
}

impl Material {
    /// Diamond grains of the published table: E 1050 GPa, nu 0.2, hardness 102 GPa.
    pub fn diamond() -> Self {
        Self {
            e_gpa: 1050.0,
            nu: 0.2,
            hardness_gpa: Some(102.0),
        }
    }

    /// Aluminium part of the published table: E 70 GPa, nu 0.34, Brinell hardness 0.06 GPa.
    pub fn aluminium() -> Self {
        Self {
            e_gpa: 70.0,
            nu: 0.34,
            hardness_gpa: Some(0.06),
        }
    }

    /// Wool-felt toolhead of the published table: E 0.015 GPa, nu 0.079.
    pub fn wool_felt() -> Self {
        Self {
            e_gpa: 0.015,
            nu: 0.079,
            hardness_gpa: None,
        }
    }

    /// Checks `E > 0`, `-1 < nu < 0.5` and a positive hardness when given.
    pub fn validate(&self, what: &str) -> Result<()> {
        if !(self.e_gpa.is_finite() && self.e_gpa > 0.0) {
            return Err(Error::invalid(
                format!("{what} e_gpa"),
                format!("must be positive, got {}", self.e_gpa),
            ));
        }
        if !(self.nu > -1.0 && self.nu < 0.5) {
            return Err(Error::invalid(
                format!("{what} nu"),
                format!("must be in (-1, 0.5), got {}", self.nu),
            ));
        }
        if let Some(h) = self.hardness_gpa {
            if !(h.is_finite() && h > 0.0) {
                return Err(Error::invalid(
                    format!("{what} hardness_gpa"),
                    format!("must be positive, got {h}"),
                ));
            }
        }
        Ok(())
    }
}

/// Effective modulus of two bodies in contact, GPa: `1/E* = (1-nu1^2)/E1 + (1-nu2^2)/E2`.
pub fn effective_modulus_gpa(a: &Material, b: &Material) -> f64 {
    1.0 / ((1.0 - a.nu * a.nu) / a.e_gpa + (1.0 - b.nu * b.nu) / b.e_gpa)
}

/// The material table and load of the contact model (a job-file section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NormalDisplacement {
    /// The toolhead (default: wool felt).
    pub tool: Material,
    /// The part (default: aluminium); needs `hardness_gpa` unless the grain has one.
    pub part: Material,
    /// The abrasive grains (default: diamond).
    pub grain: Material,
    /// Grain tip radius, mm.
    pub grain_radius_mm: f64,
    /// Standard deviation of grain heights, mm.
    pub grain_sigma_mm: f64,
    /// Normal force of the toolhead, N.
    pub force_n: f64,
    /// Curvature radius of the part, mm; when absent it comes from the surface at each point
    /// (infinite on a flat part, which makes `delta_e0` zero).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub curvature_radius_mm: Option<f64>,
}

impl Default for NormalDisplacement {
    fn default() -> Self {
        Self {
            tool: Material::wool_felt(),
            part: Material::aluminium(),
            grain: Material::diamond(),
            grain_radius_mm: 0.005,
            grain_sigma_mm: 0.001,
            force_n: 10.0,
            curvature_radius_mm: None,
        }
    }
}

/// The terms of the normal displacement, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Displacement {
    /// Toolhead-on-part Hertz approach, mm.
    pub delta_e0_mm: f64,
    /// Grain-on-part elastic approach at yield, mm.
    pub delta_e2max_mm: f64,
    /// Three standard deviations of grain height, mm.
    pub three_sigma_mm: f64,
    /// The sum, mm.
    pub delta_mm: f64,
}

impl NormalDisplacement {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        self.tool.validate("tool")?;
        self.part.validate("part")?;
        self.grain.validate("grain")?;
        for (name, v) in [
            ("grain_radius_mm", self.grain_radius_mm),
            ("force_n", self.force_n),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid(name, format!("must be positive, got {v}")));
            }
        }
        if !(self.grain_sigma_mm.is_finite() && self.grain_sigma_mm >= 0.0) {
            return Err(Error::invalid(
                "grain_sigma_mm",
                format!("must be >= 0, got {}", self.grain_sigma_mm),
            ));
        }
        if let Some(r) = self.curvature_radius_mm {
            if !(r > 0.0) {
                return Err(Error::invalid(
                    "curvature_radius_mm",
                    format!("must be positive (inf for flat), got {r}"),
                ));
            }
        }
        self.hardness_gpa().map(|_| ())
    }

    /// `H`: the smaller hardness of grain and part, GPa.
    pub fn hardness_gpa(&self) -> Result<f64> {
        match (self.part.hardness_gpa, self.grain.hardness_gpa) {
            (Some(a), Some(b)) => Ok(a.min(b)),
            (Some(a), None) | (None, Some(a)) => Ok(a),
            (None, None) => Err(Error::invalid(
                "part hardness_gpa",
                "the grain-on-part term needs the hardness of the part or the grain",
            )),
        }
    }

    /// The displacement where the part's curvature radius is `r_e_mm` (`+inf`: flat); the
    /// configured `curvature_radius_mm` takes precedence.
    pub fn at(&self, r_e_mm: f64) -> Result<Displacement> {
        self.validate()?;
        let r_e = self.curvature_radius_mm.unwrap_or(r_e_mm).abs();
        if !(r_e > 0.0) {
            return Err(Error::invalid(
                "curvature radius",
                format!("must be positive, got {r_e_mm} mm"),
            ));
        }
        let e0 = effective_modulus_gpa(&self.tool, &self.part) * N_PER_MM2_PER_GPA;
        let e2 = effective_modulus_gpa(&self.grain, &self.part) * N_PER_MM2_PER_GPA;
        let h = self.hardness_gpa()? * N_PER_MM2_PER_GPA;
        let f = self.force_n;
        let delta_e0 = if r_e.is_finite() {
            (9.0 * f * f / (16.0 * r_e * e0 * e0)).cbrt()
        } else {
            0.0
        };
        let r_rho2 = 1.0 / (1.0 / self.grain_radius_mm + 1.0 / r_e);
        let delta_e2 = std::f64::consts::PI.powi(2) * r_rho2 * h * h / (16.0 * e2 * e2);
        let three_sigma = 3.0 * self.grain_sigma_mm;
        Ok(Displacement {
            delta_e0_mm: delta_e0,
            delta_e2max_mm: delta_e2,
            three_sigma_mm: three_sigma,
            delta_mm: delta_e0 + delta_e2 + three_sigma,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_part_has_no_toolhead_term() {
        let d = NormalDisplacement::default().at(f64::INFINITY).unwrap();
        assert_eq!(d.delta_e0_mm, 0.0);
        assert!((d.three_sigma_mm - 0.003).abs() < 1e-15);
        assert!(d.delta_mm > d.three_sigma_mm);
    }

    #[test]
    fn missing_hardness_is_an_error() {
        let mut nd = NormalDisplacement::default();
        nd.part.hardness_gpa = None;
        nd.grain.hardness_gpa = None;
        assert!(nd.at(10.0).is_err());
    }
}
