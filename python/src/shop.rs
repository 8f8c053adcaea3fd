//! The shop loop (`preston calibrate`, `preston shop`): the tool that ran learned from a run's
//! measured change, and the virtual shop that rehearses the loop. Each calls the io functions the
//! CLI calls; the records are the JSON files the CLI writes.

use crate::{array, columns, to_py, Array, InputError};
use numpy::PyReadonlyArray2;
use preston_io::calibration::{run_calibration, tif_digest, write_calibration, CalibrationInputs};
use preston_io::figures::FigureStyle;
use preston_io::metrology::MapSource;
use preston_io::shop::{visit, write_visit, ShopInputs};
use preston_solver::calibrate::CalibrationSettings;
use preston_solver::iterate::shop::{Interferometer, ShopTool};
use preston_solver::machine::gcode::dialect::Dialect;
use preston_solver::machine::gcode::motion::Kinematics;
use pyo3::prelude::*;
use serde_json::Value;
use std::path::PathBuf;

/// JSON text as a settings struct, the error naming `what`.
fn settings<T: serde::de::DeserializeOwned>(text: &str, what: &str) -> PyResult<T> {
    serde_json::from_str(text).map_err(|e| {
        InputError::new_err(format!(
            "{what}: {}",
            crate::json_error_in_python_terms(text, &e)
        ))
    })
}

/// The controller's dialect by its name (`"iso"`, `"sinumerik"`, ...).
fn dialect_of(dialect: Option<&str>) -> PyResult<Option<Dialect>> {
    dialect
        .map(|d| {
            serde_json::from_value(Value::String(d.to_string()))
                .map_err(|e| InputError::new_err(format!("dialect: {e}")))
        })
        .transpose()
}

/// How the controller runs a program: acceleration-limited look-ahead with `a_max_mm_per_s2`,
/// else every block at its feed.
fn kinematics_of(a_max_mm_per_s2: Option<f64>, corner_angle_deg: f64) -> PyResult<Kinematics> {
    Kinematics::of_limit(a_max_mm_per_s2, corner_angle_deg)
        .map_err(|e| to_py(preston_io::Error::Solver(e)))
}

/// The calibrated TIF as `(N, 3)` grid samples would be, in three columns.
type TifColumns<'py> = (Array<'py>, Array<'py>, Array<'py>);

/// Calibrates the tool from one run (`preston calibrate`): the maps before and after it (each a
/// `[map]` table as JSON), the program that ran, the spot test (a `[tif]` table as JSON or grid
/// samples; `tif_file` names it in the record), how the controller ran it, and the
/// `CalibrationSettings` (JSON). With `out` writes `calibration.json`, `tif.csv` and
/// `removal.csv` (and with `plot_format` the figures) there, all or none. Returns
/// `(record_json, tif_x_mm, tif_y_mm, tif_rate_nm_per_s, converged)`, the record being what
/// `calibration.json` holds.
#[pyfunction]
#[pyo3(signature = (before_json, after_json, program, tif_json="{}", tif_xyr=None, tif_file=None, a_max_mm_per_s2=None, corner_angle_deg=preston_solver::kinematics::DEFAULT_CORNER_ANGLE_DEG, dialect=None, settings_json="{}", out=None, plot_format=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn calibrate<'py>(
    py: Python<'py>,
    before_json: &str,
    after_json: &str,
    program: PathBuf,
    tif_json: &str,
    tif_xyr: Option<PyReadonlyArray2<'py, f64>>,
    tif_file: Option<PathBuf>,
    a_max_mm_per_s2: Option<f64>,
    corner_angle_deg: f64,
    dialect: Option<&str>,
    settings_json: &str,
    out: Option<PathBuf>,
    plot_format: Option<&str>,
) -> PyResult<(String, TifColumns<'py>, bool)> {
    let before: MapSource = settings(before_json, "before")?;
    let after: MapSource = settings(after_json, "after")?;
    let calibration_settings: CalibrationSettings = settings(settings_json, "calibration")?;
    let tif = crate::tif_of(
        tif_json,
        tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
    )?;
    let style = plot_format
        .map(|f| {
            crate::figures::plot_format(f).map(|format| FigureStyle {
                format,
                ..FigureStyle::default()
            })
        })
        .transpose()?;
    let inputs = CalibrationInputs {
        before,
        after,
        program,
        dialect: dialect_of(dialect)?,
        tif,
        tif_file,
        kinematics: kinematics_of(a_max_mm_per_s2, corner_angle_deg)?,
        sample_step_mm: None,
        settings: calibration_settings,
    };
    let calibrated = py.detach(|| {
        let mut c = run_calibration(&inputs)?;
        match &out {
            Some(dir) => write_calibration(&mut c, dir, style.as_ref())?,
            None => c.record.tif_sha256 = tif_digest(&c.calibration.tif),
        }
        Ok::<_, preston_io::Error>(c)
    });
    let calibrated = calibrated.map_err(to_py)?;
    let record = serde_json::to_string(&calibrated.record)
        .map_err(|e| InputError::new_err(e.to_string()))?;
    let (x, y, rate) = calibrated.calibration.tif.columns();
    Ok((
        record,
        (array(py, &x), array(py, &y), array(py, rate)),
        calibrated.calibration.status.is_converged(),
    ))
}

/// The arrays of a visit to the shop: `(x_mm, y_mm, surface_after_nm, measured_nm)`.
type VisitArrays<'py> = (Array<'py>, Array<'py>, Array<'py>, Array<'py>);

/// A visit to the virtual shop (`preston shop`): the true surface (a `[map]` table as JSON), the
/// program to run (none: only measure) with the spot test (a `[tif]` table as JSON or grid
/// samples) and how the controller runs it, the shop's true tool (`ShopTool` as JSON), the
/// interferometer's noise and its seed. With `out` writes `surface_after.csv`, `measured.csv`
/// and `shop.json` there, all or none. Returns `(record_json, arrays)`, the record being what
/// `shop.json` holds.
#[pyfunction]
#[pyo3(signature = (surface_json, program=None, tif_json="{}", tif_xyr=None, a_max_mm_per_s2=None, corner_angle_deg=preston_solver::kinematics::DEFAULT_CORNER_ANGLE_DEG, dialect=None, tool_json="{}", noise_rms_nm=0.3, seed=1, out=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn shop<'py>(
    py: Python<'py>,
    surface_json: &str,
    program: Option<PathBuf>,
    tif_json: &str,
    tif_xyr: Option<PyReadonlyArray2<'py, f64>>,
    a_max_mm_per_s2: Option<f64>,
    corner_angle_deg: f64,
    dialect: Option<&str>,
    tool_json: &str,
    noise_rms_nm: f64,
    seed: u64,
    out: Option<PathBuf>,
) -> PyResult<(String, VisitArrays<'py>)> {
    let surface: MapSource = settings(surface_json, "surface")?;
    let tool: ShopTool = settings(tool_json, "tool")?;
    let inputs = ShopInputs {
        surface,
        program,
        dialect: dialect_of(dialect)?,
        tif: crate::tif_of(
            tif_json,
            tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
        )?,
        kinematics: kinematics_of(a_max_mm_per_s2, corner_angle_deg)?,
        tool,
        interferometer: Interferometer { noise_rms_nm },
        seed,
    };
    let v = py.detach(|| {
        let v = visit(&inputs)?;
        if let Some(dir) = &out {
            write_visit(&v, dir)?;
        }
        Ok::<_, preston_io::Error>(v)
    });
    let v = v.map_err(to_py)?;
    let record =
        serde_json::to_string(&v.record).map_err(|e| InputError::new_err(e.to_string()))?;
    Ok((
        record,
        (
            array(py, &v.x_mm),
            array(py, &v.y_mm),
            array(py, &v.surface_after_nm),
            array(py, &v.measured_nm),
        ),
    ))
}
