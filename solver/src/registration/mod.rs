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

/// Default threshold on the relative eigenvalue `lambda_k / lambda_max` of the scaled information
/// matrix below which a rigid motion counts as undetermined by the surface and is locked.
///
/// A motion of amplitude `a` (mm at the points' RMS radius) along an eigen-direction with
/// eigenvalue `lambda_k` changes the points' normal distances by `a sqrt(lambda_k / N)` RMS, and
/// the largest eigenvalue is about `N` (piston). Conversely a form error of RMS `e` can drag the
/// estimate along that direction by up to `e / sqrt(lambda_k / lambda_max)`: at `1e-5`, 43 nm of
/// form error could slide it 14 um, which is why such directions are held instead; a true
/// installation error of 5 um along one then shows as at most 16 nm RMS of form error. On
/// `data/design_freeform.json` over 50 x 50 mm the three sliding motions (about `ty - 0.4 rz`,
/// `tx`, `rz + 0.4 ty`) have relative eigenvalues of 4e-7 to 1.5e-6, the others 0.5 and 1.
pub const WEAK_EIGENVALUE_REL: f64 = 1e-5;

/// Relative eigenvalue of the information matrix below which a locked weak motion counts as
/// undetermined by the points and the surface (rank deficiency up to rounding), not merely weak:
/// see [`Registration::undetermined`].
pub const UNDETERMINED_REL: f64 = 1e-10;

/// A rigid-body degree of freedom of the transform `M`, in the design frame (rotations about the
/// design origin's axes, translations along them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Dof {
    /// Rotation about x.
    Rx,
    /// Rotation about y.
    Ry,
    /// Rotation about z.
    Rz,
    /// Translation along x.
    Tx,
    /// Translation along y.
    Ty,
    /// Translation along z.
    Tz,
}

impl Dof {
    /// The six DOFs in parameter order `rx, ry, rz, tx, ty, tz`.
    pub const ALL: [Dof; 6] = [Dof::Rx, Dof::Ry, Dof::Rz, Dof::Tx, Dof::Ty, Dof::Tz];

    /// Index in the parameter order.
    pub fn index(self) -> usize {
        self as usize
    }

    /// Short name (`rx` ... `tz`).
    pub fn name(self) -> &'static str {
        ["rx", "ry", "rz", "tx", "ty", "tz"][self.index()]
    }
}

/// Why a motion was held fixed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LockSource {
    /// Locked by the user (`RegisterSettings::lock`): held at zero.
    User,
    /// An eigen-direction of the information matrix below the weak threshold: not estimated.
    Weak,
    /// A DOF held at its prior bound (`max_rotation_arcsec`, `max_translation_um`).
    Bound,
}

/// A rigid motion that the registration did not estimate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LockedMotion {
    /// Why it was held.
    pub source: LockSource,
    /// Readable combination of DOFs, e.g. `tz` or `0.998 tx + 0.062 ry`.
    pub label: String,
    /// Unit direction in the scaled parameters `[rx, ry, rz, tx, ty, tz]`: rotations about the
    /// centroid of the points, multiplied by their RMS radius (mm), and translations (mm).
    pub direction: [f64; 6],
    /// `v^T A v / lambda_max` of the direction: how strongly the surface determines it.
    pub relative_eigenvalue: f64,
}

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
    /// DOFs held at zero, indexed by [`Dof::index`].
    pub lock: [bool; 6],
    /// Eigen-directions of the information matrix with `lambda / lambda_max` below this are
    /// locked automatically ([`WEAK_EIGENVALUE_REL`]; 0 locks only exactly undetermined ones).
    pub weak_eigenvalue_rel: f64,
    /// Prior bound on each rotation component `|rx|, |ry|, |rz|`, arcsec (`None`: unbounded).
    pub max_rotation_arcsec: Option<f64>,
    /// Prior bound on each translation component `|tx|, |ty|, |tz|`, um (`None`: unbounded).
    pub max_translation_um: Option<f64>,
}

impl Default for RegisterSettings {
    fn default() -> Self {
        Self {
            max_iterations: 50,
            step_tol_mm: 1e-10,
            cost_rel_tol: 1e-12,
            robust: Robust::None,
            probe_radius_mm: 0.0,
            lock: [false; 6],
            weak_eigenvalue_rel: WEAK_EIGENVALUE_REL,
            max_rotation_arcsec: None,
            max_translation_um: None,
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
        if !(self.weak_eigenvalue_rel.is_finite() && (0.0..1.0).contains(&self.weak_eigenvalue_rel))
        {
            return Err(Error::invalid(
                "weak_eigenvalue_rel",
                format!("must be in [0, 1), got {}", self.weak_eigenvalue_rel),
            ));
        }
        for (name, v) in [
            ("max_rotation_arcsec", self.max_rotation_arcsec),
            ("max_translation_um", self.max_translation_um),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v > 0.0) {
                    return Err(Error::invalid(name, format!("must be positive, got {v}")));
                }
            }
        }
        if self.lock.iter().all(|&l| l) {
            return Err(Error::invalid(
                "lock",
                "locks all six DOFs: nothing to register",
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
    /// How the Gauss-Newton iteration ended: [`Status::Converged`] when a stopping test (step
    /// size or cost change) was met, [`Status::MaxIterations`] otherwise.
    pub status: crate::status::Status,
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
    /// Eigenvalues of the scaled information matrix `A = sum w_i g_i g_i^T` at the solution,
    /// largest first (dimensionless: `g_i = [((p_i - c) x n_i) / L, n_i]`, `c` the centroid and
    /// `L` the RMS radius of the points), before any lock.
    pub information_eigenvalues: [f64; 6],
    /// `lambda_max / lambda_min` of `A` (`None` when `lambda_min` is zero).
    pub condition_number: Option<f64>,
    /// Standard deviation of each DOF `[rx, ry, rz]` arcsec, `[tx, ty, tz]` um:
    /// `sqrt(diag(T (sum_kept v v^T / mu) T^T) s^2)` with the residual variance
    /// `s^2 = sum w r^2 / (N - k)` over the `k` estimated directions; 0 for held motions.
    pub dof_sigma: [f64; 6],
    /// Motions held fixed (user locks, weak eigen-directions, active prior bounds).
    pub locked: Vec<LockedMotion>,
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

    /// Labels of the motions the points and the surface leave exactly undetermined: weak locks
    /// whose relative eigenvalue is below [`UNDETERMINED_REL`] (coplanar points on a plane
    /// design leave rz, tx, ty free). A caller should refuse these unless the user holds them.
    pub fn undetermined(&self) -> Vec<&str> {
        self.locked
            .iter()
            .filter(|m| m.source == LockSource::Weak && m.relative_eigenvalue < UNDETERMINED_REL)
            .map(|m| m.label.as_str())
            .collect()
    }
}
