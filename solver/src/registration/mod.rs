//! On-machine measurement: probe-radius compensation and installation-error extraction (ICP).
//!
//! [`register`] finds the rigid transform `M` (3 rotations, 3 translations) with
//! `p_design = M p_measured` that puts the measured points onto the design surface, and the form
//! error of every point: its signed normal deviation from the design surface, positive where
//! material lies above it (on the +z normal side).

pub mod icp;
pub mod probe;

pub use icp::register;
pub use probe::compensate_probe;

use crate::error::{Error, Result};
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};

/// Arcseconds per radian: `180 * 3600 / pi`.
pub const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

/// Robust weighting of the Gauss-Newton steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Robust {
    /// Plain least squares.
    None,
    /// Huber weights `min(1, delta / |r|)` with `delta = k * 1.4826 * median|r|` (Huber 1964;
    /// `k = 1.345` gives 95 % efficiency for Gaussian noise).
    Huber {
        /// Threshold in robust standard deviations.
        k: f64,
    },
}

impl Robust {
    /// Huber weights with the customary `k = 1.345`.
    pub const HUBER: Robust = Robust::Huber { k: 1.345 };
}

/// Settings of [`register`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RegisterSettings {
    /// Gauss-Newton iterations at most.
    pub max_iterations: usize,
    /// Stop when a step moves the points by less than this (rotation scaled by the RMS radius of
    /// the points about their centroid), mm.
    pub step_tol_mm: f64,
    /// Stop when the cost changes by less than this fraction.
    pub cost_rel_tol: f64,
    /// Robust weights.
    pub robust: Robust,
    /// Radius of the contact probe's tip, mm; the measured points are then tip centres.
    pub probe_radius_mm: f64,
}

impl Default for RegisterSettings {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            step_tol_mm: 1e-10,
            cost_rel_tol: 1e-12,
            robust: Robust::None,
            probe_radius_mm: 0.0,
        }
    }
}

impl RegisterSettings {
    /// Checks every field.
    pub fn validate(&self) -> Result<()> {
        if self.max_iterations == 0 {
            return Err(Error::invalid("max_iterations", "must be at least 1"));
        }
        if !(self.step_tol_mm.is_finite() && self.step_tol_mm >= 0.0) {
            return Err(Error::invalid(
                "step_tol_mm",
                format!("must be zero or positive, got {}", self.step_tol_mm),
            ));
        }
        if !(self.cost_rel_tol.is_finite() && self.cost_rel_tol >= 0.0) {
            return Err(Error::invalid(
                "cost_rel_tol",
                format!("must be zero or positive, got {}", self.cost_rel_tol),
            ));
        }
        if !(self.probe_radius_mm.is_finite() && self.probe_radius_mm >= 0.0) {
            return Err(Error::invalid(
                "probe_radius_mm",
                format!("must be zero or positive, got {}", self.probe_radius_mm),
            ));
        }
        if let Robust::Huber { k } = self.robust {
            if !(k.is_finite() && k > 0.0) {
                return Err(Error::invalid(
                    "huber k",
                    format!("must be positive, got {k}"),
                ));
            }
        }
        Ok(())
    }
}

/// The outcome of a registration.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// `M`: `p_design = M p_measured`.
    pub transform: Isometry3<f64>,
    /// Gauss-Newton steps taken.
    pub iterations: usize,
    /// Whether a stopping test (step size or cost change) was met within the iteration limit.
    pub converged: bool,
    /// Root mean square of the form error, nm.
    pub rms_nm: f64,
    /// Signed normal deviation of every point from the design surface, nm (probe radius removed).
    pub form_error_nm: Vec<f64>,
    /// Foot of every point on the design surface `(x, y)`, mm: where its form error belongs.
    pub design_xy_mm: Vec<[f64; 2]>,
    /// The measured surface points in the design frame (probe-compensated), mm.
    pub surface_points_mm: Vec<[f64; 3]>,
    /// Final robust weight of every point (1 without robust weights).
    pub weights: Vec<f64>,
}

impl Registration {
    /// `M` as a row-major 4 x 4 homogeneous matrix.
    pub fn matrix(&self) -> [[f64; 4]; 4] {
        let h = self.transform.to_homogeneous();
        let mut out = [[0.0; 4]; 4];
        for (r, row) in out.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = h[(r, c)];
            }
        }
        out
    }

    /// Rotation vector (axis times angle) of `M`'s rotation, rad.
    pub fn rotation_rad(&self) -> [f64; 3] {
        let v = self.transform.rotation.scaled_axis();
        [v.x, v.y, v.z]
    }

    /// Rotation vector of `M`'s rotation, arcsec.
    pub fn rotation_arcsec(&self) -> [f64; 3] {
        self.rotation_rad().map(|a| a * ARCSEC_PER_RAD)
    }

    /// Translation of `M`, mm.
    pub fn translation_mm(&self) -> [f64; 3] {
        let t = self.transform.translation.vector;
        [t.x, t.y, t.z]
    }

    /// Translation of `M`, um.
    pub fn translation_um(&self) -> [f64; 3] {
        self.translation_mm().map(|t| t * 1e3)
    }
}
