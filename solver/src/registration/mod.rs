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

/// Default range of the installation error's translations, mm: what a fixture or a setter's
/// indicator leaves on an optical part mounted for measurement, about the part itself (the
/// measured points' centroid). A motion whose standard deviation (estimated from the residual's
/// own scatter) exceeds its range is not determined by the data to within what the mounting can
/// be, and is held instead of estimated.
pub const INSTALLATION_RANGE_MM: f64 = 0.5;

/// Default range of the installation error's rotations about the measured points' centroid,
/// degrees (see [`INSTALLATION_RANGE_MM`]).
pub const INSTALLATION_RANGE_DEG: f64 = 0.2;

/// A rigid-body degree of freedom of the transform `M`, in the design frame (rotations about the
/// design origin's axes, translations along them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
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
    /// A rigid-body motion (a rotation about an axis through the measured points' centroid, or a
    /// translation of the centroid) that the data do not determine: its standard deviation from
    /// the residual's scatter exceeds its installation range (or the points and the surface give
    /// no information on it at all). Held within that range, not estimated.
    Weak,
    /// A DOF held at its prior bound (`max_rotation_arcsec`, `max_translation_um`).
    Bound,
}

/// A rigid motion that the registration did not estimate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LockedMotion {
    /// Why it was held.
    pub source: LockSource,
    /// The motion held: a DOF's name (`tz`; a held weak motion is about the points' centroid).
    pub label: String,
    /// Unit direction in the scaled parameters `[rx, ry, rz, tx, ty, tz]`: rotations about the
    /// centroid of the points, multiplied by their RMS radius (mm), and translations (mm).
    pub direction: [f64; 6],
    /// `v^T A v / lambda_max` of the direction: how strongly the surface determines it.
    pub relative_eigenvalue: f64,
    /// Why it was held, in physical terms (for a weak motion: its standard deviation against its
    /// installation range).
    pub reason: String,
    /// A weak motion on which the points and the surface give no information at all (zero to
    /// rounding, whatever the noise): [`Registration::refuse_undetermined`] refuses it.
    #[serde(default)]
    pub undetermined: bool,
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
    /// Stop when a step lowers the cost by less than this fraction (a step that raises it within
    /// rounding also stops).
    pub cost_rel_tol: f64,
    /// Robust weights.
    pub robust: Robust,
    /// Radius of the contact probe's tip, mm; the measured points are then tip centres.
    pub probe_radius_mm: f64,
    /// DOFs held at zero, indexed by [`Dof::index`].
    pub lock: [bool; 6],
    /// Range of the installation error's translations of the measured points' centroid, mm
    /// ([`INSTALLATION_RANGE_MM`]). A motion (a translation of the centroid, or a rotation about
    /// it) is held when its standard deviation `s sqrt((A^-1)_kk)` over the motions left free
    /// (`s^2 = sum w r^2 / (N - 6)` the residual variance) is the largest multiple of its range
    /// while the free motions' deviations, in units of their ranges, exceed 1 in some direction.
    pub installation_range_mm: f64,
    /// Range of the installation error's rotations about the measured points' centroid, degrees
    /// ([`INSTALLATION_RANGE_DEG`]).
    pub installation_range_deg: f64,
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
            installation_range_mm: INSTALLATION_RANGE_MM,
            installation_range_deg: INSTALLATION_RANGE_DEG,
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
        for (name, v) in [
            ("installation_range_mm", self.installation_range_mm),
            ("installation_range_deg", self.installation_range_deg),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid(name, format!("must be positive, got {v}")));
            }
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
    /// `sqrt(diag(T C T^T))` with `C = s^2 P + sum_held rho_k^2 g_k g_k^T`, `P = sum_kept v v^T /
    /// mu` over the estimated directions, the residual variance `s^2 = sum w r^2 / (N - k)` over
    /// the `k` estimated directions, and for each motion held because the data do not determine
    /// it, its installation range `rho_k` carried through the estimated motions that absorb it
    /// (`g_k = e_k - P A e_k`): a held motion's uncertainty is the range it was held within. 0 for
    /// a DOF the user locked or a prior bound holds.
    pub dof_sigma: [f64; 6],
    /// Motions held fixed (user locks, weak eigen-directions, active prior bounds).
    pub locked: Vec<LockedMotion>,
    /// How much of the form error each DOF `[rx, ry, rz, tx, ty, tz]` could absorb: the
    /// correlation `|u . e| / (|u| |e|)` (weighted sums) of its unique signature `u` (its
    /// normal-displacement pattern `[p x n, n]_k` made orthogonal to the other free DOFs'
    /// patterns) with the form error `e`. An estimated motion has absorbed what it could: 0 at
    /// convergence (the normal equations). A held motion (user lock, bound, undetermined) would
    /// take this share of the reported form error if it were estimated.
    pub form_correlation: [f64; 6],
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
    /// with no information at all, whatever the noise and the installation range (coplanar points
    /// on a plane design leave rz, tx, ty free). A motion that is merely weak is held within its
    /// range, not refused. [`Registration::refuse_undetermined`] refuses them.
    pub fn undetermined(&self) -> Vec<&str> {
        self.locked
            .iter()
            .filter(|m| m.source == LockSource::Weak && m.undetermined)
            .map(|m| m.label.as_str())
            .collect()
    }

    /// The refusal of a registration that leaves motions exactly undetermined (rank-deficient
    /// information matrix) which the user did not hold: `lock_hint` names how the caller's face
    /// holds them (`--lock` or `lock=`). Every face (CLI, Python, the loop) refuses with this.
    pub fn refuse_undetermined(&self, lock_hint: &str) -> Result<()> {
        let undetermined = self.undetermined();
        if undetermined.is_empty() {
            return Ok(());
        }
        Err(Error::Geometry(format!(
            "the points and the design surface do not determine these motions (no point's \
             distance to the surface changes with them): {}; hold them \
             with {lock_hint} (for points on a plane design: rz, tx, ty) or measure where the \
             surface is curved",
            undetermined.join("; ")
        )))
    }
}
