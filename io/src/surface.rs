//! Files of the geometry commands: surface JSON, point clouds (`x_mm,y_mm,z_mm`), the fit
//! summary, `transform.json` and surface evaluations. Key and column names are a contract.

use crate::atomic::Staged;
use crate::error::{Error, Result};
use crate::table::{read_table, ColumnSpec};
use crate::writers::stage_json;
use preston_solver::fit::FitResult;
use preston_solver::registration::{LockedMotion, RegisterSettings, Registration};
use preston_solver::status::Status;
use preston_solver::surface::{Surface, XyTerm};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Reads and validates a surface JSON document (`{"type": "xy_polynomial", ...}`).
pub fn read_surface(path: &Path) -> Result<Surface> {
    let text = crate::limits::read_document(path, "surface file")?;
    let surface: Surface = serde_json::from_str(&text).map_err(|e| Error::Json {
        file: path.to_path_buf(),
        why: crate::limits::quote_message(&e.to_string()),
    })?;
    surface.validate().map_err(|e| Error::engine(path, e))?;
    Ok(surface)
}

/// Stages a surface JSON document.
pub fn stage_surface(path: &Path, surface: &Surface) -> Result<Staged> {
    stage_json(path, surface)
}

/// A 3-D point cloud, mm.
#[derive(Debug, Clone, PartialEq)]
pub struct PointCloud {
    /// x, mm.
    pub x_mm: Vec<f64>,
    /// y, mm.
    pub y_mm: Vec<f64>,
    /// z, mm.
    pub z_mm: Vec<f64>,
}

impl PointCloud {
    /// The points as `[x, y, z]`.
    pub fn points(&self) -> Vec<[f64; 3]> {
        self.x_mm
            .iter()
            .zip(&self.y_mm)
            .zip(&self.z_mm)
            .map(|((x, y), z)| [*x, *y, *z])
            .collect()
    }
}

/// Reads points `x_mm,y_mm,z_mm` (every cell a finite number; at least one row).
pub fn read_points(path: &Path) -> Result<PointCloud> {
    let mut t = read_table(
        path,
        &[
            ColumnSpec::required("x_mm"),
            ColumnSpec::required("y_mm"),
            ColumnSpec::required("z_mm"),
        ],
    )?;
    if t.is_empty() {
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: "no data rows".into(),
        });
    }
    Ok(PointCloud {
        x_mm: t.take(0).unwrap_or_default(),
        y_mm: t.take(1).unwrap_or_default(),
        z_mm: t.take(2).unwrap_or_default(),
    })
}

/// What `preston fit` prints: the fitted surface's parameters and the quality of the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitSummary {
    /// RMS of the fit residual, nm.
    pub rms_nm: f64,
    /// PV of the fit residual, nm.
    pub pv_nm: f64,
    /// Condition estimate of the column-scaled least-squares matrix.
    pub condition_number: f64,
    /// Number of points fitted.
    pub points: usize,
    /// Levenberg-Marquardt iterations (0 when the conic was fixed).
    pub iterations: usize,
    /// How the Levenberg-Marquardt iteration ended (`converged`, `max_iterations`).
    pub status: Status,
    /// Vertex curvature of the conic base, 1/mm.
    pub curvature_per_mm: f64,
    /// Conic constant of the base.
    pub conic: f64,
    /// Normalisation radius, mm.
    pub norm_radius_mm: f64,
    /// The fitted terms `{"m", "n", "coef_mm"}`.
    pub terms: Vec<XyTerm>,
}

impl FitSummary {
    /// The summary of a fit.
    pub fn of(fit: &FitResult) -> Self {
        Self {
            rms_nm: fit.rms_nm,
            pv_nm: fit.pv_nm,
            condition_number: fit.condition_number,
            points: fit.points,
            iterations: fit.iterations,
            status: fit.status,
            curvature_per_mm: fit.surface.curvature_per_mm,
            conic: fit.surface.conic,
            norm_radius_mm: fit.surface.norm_radius_mm,
            terms: fit.surface.terms.clone(),
        }
    }
}

/// `transform.json` of `preston register`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransformFile {
    /// `M`, row-major 4 x 4: `p_design = M p_measured` (homogeneous, mm).
    pub matrix: [[f64; 4]; 4],
    /// Rotation vector `[rx, ry, rz]` of `M`'s rotation, arcsec.
    pub rotation_arcsec: [f64; 3],
    /// Translation `[tx, ty, tz]` of `M`, um.
    pub translation_um: [f64; 3],
    /// RMS of the form error, nm.
    pub rms_nm: f64,
    /// Gauss-Newton iterations.
    pub iterations: usize,
    /// Whether a stopping test was met.
    pub converged: bool,
    /// How the iteration ended (`converged`, `max_iterations`).
    pub status: Status,
    /// Number of points registered.
    pub points: usize,
    /// Probe radius compensated, mm.
    pub probe_radius_mm: f64,
    /// Eigenvalues of the scaled information matrix at the solution, largest first
    /// (dimensionless; see [`Registration::information_eigenvalues`]).
    pub information_eigenvalues: [f64; 6],
    /// `lambda_max / lambda_min` (`null` when the smallest eigenvalue is zero).
    pub condition_number: Option<f64>,
    /// Standard deviation of `[rx, ry, rz]` (arcsec) and `[tx, ty, tz]` (um); 0 for held motions.
    pub dof_sigma: [f64; 6],
    /// Motions held fixed: user locks, motions the data do not determine within the installation
    /// range, DOFs at a prior bound; each with its `reason`.
    pub locked: Vec<LockedMotion>,
    /// Share of the form error each DOF `[rx, ry, rz, tx, ty, tz]` takes or could take, 0..1
    /// (see [`Registration::form_correlation`]).
    pub form_correlation: [f64; 6],
    /// The installation ranges the registration compared each motion's standard deviation with:
    /// translations (mm) and rotations (degrees).
    pub installation_range_mm: f64,
    /// Range of the rotations, degrees.
    pub installation_range_deg: f64,
}

impl TransformFile {
    /// The file content for a registration.
    pub fn of(reg: &Registration, settings: &RegisterSettings) -> Self {
        Self {
            matrix: reg.matrix(),
            rotation_arcsec: reg.rotation_arcsec(),
            translation_um: reg.translation_um(),
            rms_nm: reg.rms_nm,
            iterations: reg.iterations,
            converged: reg.status.is_converged(),
            status: reg.status,
            points: reg.form_error_nm.len(),
            probe_radius_mm: settings.probe_radius_mm,
            information_eigenvalues: reg.information_eigenvalues,
            condition_number: reg.condition_number,
            dof_sigma: reg.dof_sigma,
            locked: reg.locked.clone(),
            form_correlation: reg.form_correlation,
            installation_range_mm: settings.installation_range_mm,
            installation_range_deg: settings.installation_range_deg,
        }
    }
}

pub use crate::writers::stage_columns_csv;

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn surface_and_points_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.json");
        std::fs::write(
            &p,
            r#"{"type":"xy_polynomial","curvature_per_mm":0.001,"conic":-1,"norm_radius_mm":50,"terms":[{"m":1,"n":1,"coef_mm":0.1}]}"#,
        )
        .unwrap();
        let s = read_surface(&p).unwrap();
        stage_surface(&dir.path().join("t.json"), &s)
            .unwrap()
            .commit()
            .unwrap();
        assert_eq!(read_surface(&dir.path().join("t.json")).unwrap(), s);
        std::fs::write(&p, r#"{"type":"xy_polynomial","norm_radius_mm":-1}"#).unwrap();
        assert!(read_surface(&p)
            .unwrap_err()
            .to_string()
            .contains("norm_radius_mm"));
        std::fs::write(&p, r#"{"type":"torus"}"#).unwrap();
        assert!(matches!(read_surface(&p), Err(Error::Json { .. })));

        let c = dir.path().join("p.csv");
        let mut f = std::fs::File::create(&c).unwrap();
        writeln!(f, "z_mm,x_mm,y_mm\n3,1,2\n6,4,5").unwrap();
        let pc = read_points(&c).unwrap();
        assert_eq!(pc.points(), vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        let out = dir.path().join("o.csv");
        stage_columns_csv(&out, &["a_mm", "b_nm"], &[&[1.0, 2.5], &[3.0, -4.0]])
            .unwrap()
            .commit()
            .unwrap();
        assert_eq!(
            std::fs::read_to_string(&out).unwrap(),
            "a_mm,b_nm\n1,3\n2.5,-4\n"
        );
    }
}
