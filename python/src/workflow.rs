//! The rest of the workflow: TIF models and measured grids (`preston tif`), tool paths
//! (`preston path`), registration of measured points (`preston register`) and the simulation of a
//! G-code program (`preston simulate --program`). Each calls the engine's own functions; the
//! summaries carry the keys the CLI prints.

use crate::{array, columns, engine_to_py, to_py, Array, InputError, PyProgress};
use numpy::PyReadonlyArray2;
use preston_io::metrology::MapSource;
use preston_io::report::centred_residual_nm;
use preston_io::simulation::{simulate_program as run_program, ProgramOptions};
use preston_io::surface::TransformFile;
use preston_solver::influence::TifFrame;
use preston_solver::machine::gcode::dialect::Dialect;
use preston_solver::machine::gcode::motion::Kinematics;
use preston_solver::map::{BoundingBox, HeightMap};
use preston_solver::observer::{Observer, Silent};
use preston_solver::path::edge_offset::{edge_offset, EdgeOffsetSettings};
use preston_solver::path::random::{random_unicursal, RandomPathSettings};
use preston_solver::path::spiral::archimedes;
use preston_solver::path::PathSummary;
use preston_solver::registration::{register as icp, RegisterSettings};
use preston_solver::setup::TifModel;
use preston_solver::surface::Surface;
use preston_solver::tif::spot::{fit_gaussian, tif_from_spot, SpotOptions, SpotSummary};
use preston_solver::tif::{
    BonnetParams, GaussianTif, GridAdjustment, GridTif, HertzParams, HertzPart, ProcessModel, Tif,
    TifSummary,
};
use pyo3::prelude::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// JSON text as a settings struct, the error naming `what`.
fn settings<T: serde::de::DeserializeOwned>(text: &str, what: &str) -> PyResult<T> {
    serde_json::from_str(text).map_err(|e| {
        InputError::new_err(format!(
            "{what}: {}",
            crate::json_error_in_python_terms(text, &e)
        ))
    })
}

/// A design surface from its JSON (what `preston fit --out` writes), validated.
pub(crate) fn surface_of(text: &str) -> PyResult<Surface> {
    let s: Surface = settings(text, "surface")?;
    s.validate().map_err(|e| engine_to_py("surface", e))?;
    Ok(s)
}

/// A TIF grid as the columns of its CSV (`x_mm, y_mm, rate_nm_per_s`, row-major).
fn grid_arrays<'py>(py: Python<'py>, g: &GridTif) -> (Array<'py>, Array<'py>, Array<'py>) {
    let (x, y, rate) = g.columns();
    (array(py, &x), array(py, &y), array(py, rate))
}

/// A summary (of a TIF, a path) as the JSON text the CLI prints.
pub(crate) fn summary_json<T: serde::Serialize>(s: &T) -> PyResult<String> {
    serde_json::to_string(s).map_err(|e| InputError::new_err(e.to_string()))
}

/// A TIF from a process model (`"hertz"`, `"bonnet"`, `"gaussian"`) with its parameters (JSON,
/// the fields of `HertzParams`, `BonnetParams` or `GaussianTif`), sampled at `pitch_mm`:
/// `(x_mm, y_mm, rate_nm_per_s, summary_json)`. A Hertz tool sits on a flat part, a sphere of
/// `part_radius_mm` (positive convex), or the design surface `surface_json` at `at_mm`.
#[pyfunction]
#[pyo3(signature = (model, params_json, pitch_mm, part_radius_mm=None, surface_json=None, at_mm=None))]
#[allow(clippy::type_complexity)]
pub(crate) fn tif_model<'py>(
    py: Python<'py>,
    model: &str,
    params_json: &str,
    pitch_mm: f64,
    part_radius_mm: Option<f64>,
    surface_json: Option<&str>,
    at_mm: Option<(f64, f64)>,
) -> PyResult<(Array<'py>, Array<'py>, Array<'py>, String)> {
    let e = |e| engine_to_py(model, e);
    let m = match model {
        "hertz" => {
            let p: HertzParams = settings(params_json, "hertz parameters")?;
            let part = match (part_radius_mm, surface_json, at_mm) {
                (Some(radius_mm), None, None) => HertzPart::Sphere { radius_mm },
                (None, Some(s), Some((x, y))) => {
                    let (k1_per_mm, k2_per_mm) = surface_of(s)?
                        .principal_curvatures_per_mm(x, y)
                        .map_err(|er| {
                        engine_to_py(&format!("surface curvature at ({x}, {y}) mm"), er)
                    })?;
                    HertzPart::Curvatures {
                        k1_per_mm,
                        k2_per_mm,
                    }
                }
                (None, None, None) => HertzPart::Flat,
                _ => {
                    return Err(InputError::new_err(
                        "hertz: give part_radius_mm, or surface with at_mm, or neither (flat)",
                    ))
                }
            };
            ProcessModel::hertz(&p, part).map_err(e)?
        }
        "bonnet" | "gaussian" if part_radius_mm.is_some() || surface_json.is_some() => {
            return Err(InputError::new_err(format!(
                "{model}: part_radius_mm and surface apply to the hertz model"
            )))
        }
        "bonnet" => {
            let p: BonnetParams = settings(params_json, "bonnet parameters")?;
            ProcessModel::bonnet(&p).map_err(e)?
        }
        "gaussian" => {
            let g: GaussianTif = settings(params_json, "gaussian parameters")?;
            ProcessModel::gaussian(g).map_err(e)?
        }
        other => {
            return Err(InputError::new_err(format!(
                "tif model `{other}`: expected hertz, bonnet or gaussian"
            )))
        }
    };
    let sampled = py.detach(|| m.sample(pitch_mm)).map_err(e)?;
    let (x, y, r) = grid_arrays(py, &sampled.grid);
    Ok((x, y, r, summary_json(&sampled.summary)?))
}

/// A measured TIF grid (`(N, 3)`: x_mm, y_mm, rate_nm_per_s) resampled to `pitch_mm`,
/// recentred on its rate-weighted centroid, scaled to a peak rate (nm/s) or a volumetric rate
/// (mm^3/min), in that order (`preston tif grid`).
#[pyfunction]
#[pyo3(signature = (tif_xyr, pitch_mm=None, recentre=false, peak_nm_per_s=None, volume_mm3_per_min=None))]
#[allow(clippy::type_complexity)]
pub(crate) fn tif_grid<'py>(
    py: Python<'py>,
    tif_xyr: PyReadonlyArray2<'py, f64>,
    pitch_mm: Option<f64>,
    recentre: bool,
    peak_nm_per_s: Option<f64>,
    volume_mm3_per_min: Option<f64>,
) -> PyResult<(Array<'py>, Array<'py>, Array<'py>, String)> {
    if peak_nm_per_s.is_some() && volume_mm3_per_min.is_some() {
        return Err(InputError::new_err(
            "tif grid: give peak_nm_per_s or volume_mm3_per_min, not both",
        ));
    }
    let c = columns(&tif_xyr, "tif_xyr", 3)?;
    let e = |e| engine_to_py("tif_xyr", e);
    let g = GridTif::from_samples(&c[0], &c[1], &c[2]).map_err(e)?;
    let adjust = GridAdjustment {
        pitch_mm,
        recentre,
        peak_nm_per_s,
        volume_mm3_per_min,
    };
    let g = py.detach(|| adjust.apply(g)).map_err(e)?;
    let (x, y, r) = grid_arrays(py, &g);
    Ok((x, y, r, summary_json(&TifSummary::of_measured(&g))?))
}

/// The TIF of a removal spot (`preston tif spot`): maps before and after a stationary dwell of
/// `dwell_s` s (`(N, 3)`: x_mm, y_mm, z_nm on one grid), `(before - after) / dwell`, background
/// (piston, and tilt with `remove_tilt`) fitted outside `crop_radius_mm` and removed, zero
/// outside it; optionally recentred and fitted with an elliptical Gaussian.
#[pyfunction]
#[pyo3(signature = (before_xyz, after_xyz, dwell_s, crop_radius_mm=None, remove_tilt=false, recentre=false, fit_gaussian_model=false))]
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub(crate) fn tif_spot<'py>(
    py: Python<'py>,
    before_xyz: PyReadonlyArray2<'py, f64>,
    after_xyz: PyReadonlyArray2<'py, f64>,
    dwell_s: f64,
    crop_radius_mm: Option<f64>,
    remove_tilt: bool,
    recentre: bool,
    fit_gaussian_model: bool,
) -> PyResult<(Array<'py>, Array<'py>, Array<'py>, String)> {
    let map = |a: &PyReadonlyArray2<'py, f64>, name: &str| -> PyResult<HeightMap> {
        let [x, y, z]: [Vec<f64>; 3] = columns(a, name, 3)?
            .try_into()
            .map_err(|_| InputError::new_err(format!("{name}: needs three columns")))?;
        HeightMap::new(x, y, z).map_err(|e| engine_to_py(name, e))
    };
    let before = map(&before_xyz, "before_xyz")?;
    let after = map(&after_xyz, "after_xyz")?;
    let opts = SpotOptions {
        dwell_s,
        crop_radius_mm,
        remove_tilt,
        recentre,
    };
    let (spot, fit) = py
        .detach(|| {
            let spot = tif_from_spot(&before, &after, &opts)?;
            let fit = if fit_gaussian_model {
                Some(fit_gaussian(&spot.tif)?)
            } else {
                None
            };
            Ok((spot, fit))
        })
        .map_err(|e| engine_to_py("spot", e))?;
    let (x, y, r) = grid_arrays(py, &spot.tif);
    Ok((
        x,
        y,
        r,
        summary_json(&SpotSummary::of(&spot, fit.as_ref()))?,
    ))
}

/// An Archimedes spiral of `pitch_mm` between turns from `centre_mm` out to `radius_mm`, points
/// about `step_mm` apart (`preston path spiral`): `(x_mm, y_mm)`.
#[pyfunction]
pub(crate) fn path_spiral<'py>(
    py: Python<'py>,
    centre_mm: (f64, f64),
    radius_mm: f64,
    pitch_mm: f64,
    step_mm: f64,
) -> PyResult<(Array<'py>, Array<'py>)> {
    let p = py
        .detach(|| archimedes([centre_mm.0, centre_mm.1], radius_mm, pitch_mm, step_mm))
        .map_err(|e| engine_to_py("spiral", e))?;
    Ok((array(py, p.x_mm()), array(py, p.y_mm())))
}

/// A pseudo-random unicursal path over a box (mm) with the settings of `RandomPathSettings`
/// (JSON: `pitch_mm`, `seed`, `max_run`, `jitter`), `preston path random`:
/// `(x_mm, y_mm, summary_json)`.
#[pyfunction]
pub(crate) fn path_random<'py>(
    py: Python<'py>,
    x_range_mm: (f64, f64),
    y_range_mm: (f64, f64),
    settings_json: &str,
) -> PyResult<(Array<'py>, Array<'py>, String)> {
    let set: RandomPathSettings = settings(settings_json, "random path settings")?;
    let (x0, x1) = x_range_mm;
    let (y0, y1) = y_range_mm;
    let region = BoundingBox {
        x_min_mm: x0.min(x1),
        x_max_mm: x0.max(x1),
        y_min_mm: y0.min(y1),
        y_max_mm: y0.max(y1),
    };
    let r = py
        .detach(|| random_unicursal(&region, &set))
        .map_err(|e| engine_to_py("random path", e))?;
    let s = summary_json(&PathSummary::random(&r, &set, None))?;
    Ok((array(py, r.path.x_mm()), array(py, r.path.y_mm()), s))
}

/// The lifting-bonnet edge-offset trajectory inside the closed edge `edge_xy` (`(N, 2)`, mm)
/// with the settings of `EdgeOffsetSettings` (JSON), `preston path edge-offset`:
/// `(x_mm, y_mm, summary_json)`.
#[pyfunction]
pub(crate) fn path_edge_offset<'py>(
    py: Python<'py>,
    edge_xy: PyReadonlyArray2<'py, f64>,
    settings_json: &str,
) -> PyResult<(Array<'py>, Array<'py>, String)> {
    let set: EdgeOffsetSettings = settings(settings_json, "edge-offset settings")?;
    let c = columns(&edge_xy, "edge_xy", 2)?;
    let edge: Vec<[f64; 2]> = c[0].iter().zip(&c[1]).map(|(x, y)| [*x, *y]).collect();
    let t = py
        .detach(|| edge_offset(&edge, &set))
        .map_err(|e| engine_to_py("edge offset", e))?;
    let s = summary_json(&PathSummary::edge_offset(t.path.len(), &t))?;
    Ok((array(py, t.path.x_mm()), array(py, t.path.y_mm()), s))
}

/// Registers measured points `(N, 3)` (x, y, z in mm; probe tip centres with a probe radius) on
/// the design surface (JSON) with the settings of `RegisterSettings` (JSON), `preston register`:
/// `(transform_json, design_x_mm, design_y_mm, form_error_nm, points_xyz_mm (flat, N x 3),
/// weights)`. Motions the points leave undetermined are refused, as by the CLI.
#[pyfunction]
#[allow(clippy::type_complexity)]
pub(crate) fn register<'py>(
    py: Python<'py>,
    surface_json: &str,
    points_xyz: PyReadonlyArray2<'py, f64>,
    settings_json: &str,
) -> PyResult<(
    String,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
)> {
    let surface = surface_of(surface_json)?;
    let set: RegisterSettings = settings(settings_json, "register settings")?;
    let c = columns(&points_xyz, "points_xyz", 3)?;
    let pts: Vec<[f64; 3]> = (0..c[0].len())
        .map(|i| [c[0][i], c[1][i], c[2][i]])
        .collect();
    let reg = py
        .detach(|| icp(&surface, &pts, &set))
        .map_err(|e| engine_to_py("points_xyz", e))?;
    reg.refuse_undetermined("lock=[...]")
        .map_err(|e| engine_to_py("points_xyz", e))?;
    let tf = TransformFile::of(&reg, &set);
    let tf = serde_json::to_string(&tf).map_err(|e| InputError::new_err(e.to_string()))?;
    let fx: Vec<f64> = reg.design_xy_mm.iter().map(|p| p[0]).collect();
    let fy: Vec<f64> = reg.design_xy_mm.iter().map(|p| p[1]).collect();
    let flat: Vec<f64> = reg.surface_points_mm.iter().flatten().copied().collect();
    Ok((
        tf,
        array(py, &fx),
        array(py, &fy),
        array(py, &reg.form_error_nm),
        array(py, &flat),
        array(py, &reg.weights),
    ))
}

/// The removal a G-code program produces as the machine runs it (`preston simulate
/// --program`): the map read with a `[map]` table's options (JSON), the TIF of a `[tif]` table
/// (JSON) or grid samples, the program file, and the controller: `a_max_mm_per_s2` (None: the
/// programmed feed in every block) with `corner_angle_deg`, `dialect`, `sample_step_mm`, the part
/// surface (JSON) with the tool radius. Returns `(map_x_mm, map_y_mm, z_nm, removal_nm,
/// residual_nm, report_json, check_json)`, the residual `z - removal` with its mean removed.
#[pyfunction]
#[pyo3(signature = (map_json, program, tif_json="{}", tif_xyr=None, a_max_mm_per_s2=None, corner_angle_deg=preston_solver::kinematics::DEFAULT_CORNER_ANGLE_DEG, dialect=None, sample_step_mm=None, surface_json=None, tool_radius_mm=0.0, tif_frame="path_tangent", progress=None))]
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub(crate) fn simulate_program<'py>(
    py: Python<'py>,
    map_json: &str,
    program: PathBuf,
    tif_json: &str,
    tif_xyr: Option<PyReadonlyArray2<'py, f64>>,
    a_max_mm_per_s2: Option<f64>,
    corner_angle_deg: f64,
    dialect: Option<&str>,
    sample_step_mm: Option<f64>,
    surface_json: Option<&str>,
    tool_radius_mm: f64,
    tif_frame: &str,
    progress: Option<Py<PyAny>>,
) -> PyResult<(
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    String,
    String,
)> {
    let tif_frame: TifFrame = serde_json::from_value(Value::String(tif_frame.to_string()))
        .map_err(|e| InputError::new_err(format!("tif_frame: {e}")))?;
    let source: MapSource = settings(map_json, "map options")?;
    let tif: Tif = crate::tif_of(
        tif_json,
        tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
    )?;
    let kinematics = Kinematics::of_limit(a_max_mm_per_s2, corner_angle_deg)
        .map_err(|e| to_py(preston_io::Error::Solver(e)))?;
    let dialect: Option<Dialect> = dialect
        .map(|d| {
            serde_json::from_value(Value::String(d.to_string()))
                .map_err(|e| InputError::new_err(format!("dialect: {e}")))
        })
        .transpose()?;
    let surface = surface_json.map(surface_of).transpose()?;
    let observer = progress.map(PyProgress::new);
    let sim = py.detach(|| {
        let part = surface.as_ref().map(|s| (s, tool_radius_mm));
        let options = ProgramOptions {
            dialect,
            kinematics,
            sample_step_mm,
            part,
            tif_frame,
            tif_model: TifModel::ShiftInvariant,
        };
        let obs: &dyn Observer = match &observer {
            Some(o) => o,
            None => &Silent,
        };
        run_program(&source, &tif, Path::new(&program), options, obs)
    });
    if let Some(e) = observer.as_ref().and_then(PyProgress::take_error) {
        return Err(e);
    }
    let sim = sim.map_err(to_py)?;
    let report =
        serde_json::to_string(&sim.sim.report).map_err(|e| InputError::new_err(e.to_string()))?;
    let c = &sim.check;
    let check = json!({
        "stretches": c.stretches, "planned_total_s": c.planned_total_s,
        "executed_total_s": c.executed_total_s, "max_relative_error": c.max_relative_error,
        "worst_point": c.worst_point, "over_5_percent": c.over_5_percent,
        "executed_time_s": sim.executed_time_s, "samples": sim.samples,
    });
    let m = &sim.sim.map;
    Ok((
        array(py, m.x_mm()),
        array(py, m.y_mm()),
        array(py, m.z_nm()),
        array(py, &sim.sim.removal_nm),
        array(py, &centred_residual_nm(m.z_nm(), &sim.sim.removal_nm)),
        report,
        check.to_string(),
    ))
}

/// The last run of a loop: `(dwell_x_mm, dwell_y_mm, dwell_s, measured_x_mm, measured_y_mm,
/// measured_z_nm)`.
type LastRun<'py> = (
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
);

/// The measure-register-solve-polish loop (`preston iterate`) with the settings of
/// `LoopSettings` (JSON) and the TIF of a `[tif]` table (JSON) or grid samples, on a virtual part
/// (`part_json`, the fields of `VirtualPart` without its surface) or, with `map_xyz` (`(N, 3)`,
/// mm and nm), one planned run `iteration` on a real part's measured error. Returns
/// `(outcome_json, final_x_mm, final_y_mm, final_z_nm, last_run)`; the outcome holds `records`
/// (the rows of convergence.csv), `met_spec` and `not_converged`.
#[pyfunction]
#[pyo3(signature = (settings_json, surface_json=None, tif_json="{}", tif_xyr=None, part_json="{}", map_xyz=None, iteration=0, progress=None, threads=None))]
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub(crate) fn iterate<'py>(
    py: Python<'py>,
    settings_json: &str,
    surface_json: Option<&str>,
    tif_json: &str,
    tif_xyr: Option<PyReadonlyArray2<'py, f64>>,
    part_json: &str,
    map_xyz: Option<PyReadonlyArray2<'py, f64>>,
    iteration: usize,
    progress: Option<Py<PyAny>>,
    threads: Option<usize>,
) -> PyResult<(
    String,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Option<LastRun<'py>>,
)> {
    use preston_solver::iterate::{plan_measured, run_virtual, LoopSettings, VirtualPart};
    let loop_settings: LoopSettings = settings(settings_json, "loop settings")?;
    loop_settings
        .validate()
        .map_err(|e| engine_to_py("loop settings", e))?;
    let surface = match surface_json {
        Some(s) => surface_of(s)?,
        None => Surface::Plane(preston_solver::surface::Plane {}),
    };
    let tif: Tif = crate::tif_of(
        tif_json,
        tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
    )?;
    let measured = match map_xyz {
        Some(a) => {
            let [x, y, z]: [Vec<f64>; 3] = columns(&a, "map_xyz", 3)?
                .try_into()
                .map_err(|_| InputError::new_err("map_xyz: needs three columns"))?;
            Some(HeightMap::new(x, y, z).map_err(|e| engine_to_py("map_xyz", e))?)
        }
        None => None,
    };
    // The part's fields with the surface added (the surface is given on its own).
    let mut part: Value = settings::<Value>(part_json, "virtual part")?;
    if let Value::Object(m) = &mut part {
        m.insert(
            "surface".into(),
            serde_json::to_value(&surface).map_err(|e| InputError::new_err(e.to_string()))?,
        );
    }
    let part: VirtualPart = serde_json::from_value(part)
        .map_err(|e| InputError::new_err(format!("virtual part: {e}")))?;
    let observer = progress.map(PyProgress::new);
    let outcome = crate::interruptible(py, observer.as_ref(), |obs| {
        crate::with_threads(threads, || match &measured {
            Some(m) => plan_measured(&surface, m, &tif, &loop_settings, iteration, obs),
            None => run_virtual(&part, &tif, &loop_settings, obs),
        })
    })??;
    if let Some(e) = observer.as_ref().and_then(PyProgress::take_error) {
        return Err(e);
    }
    let outcome = outcome.map_err(|e| engine_to_py("iterate", e))?;
    let text = serde_json::to_string(&json!({
        "records": outcome.records,
        "met_spec": outcome.met_spec,
        "not_converged": outcome.not_converged,
    }))
    .map_err(|e| InputError::new_err(e.to_string()))?;
    let f = &outcome.final_measured;
    let last = outcome.last_run.as_ref().map(|r| {
        (
            array(py, r.path.x_mm()),
            array(py, r.path.y_mm()),
            array(py, &r.dwell_s),
            array(py, r.measured.x_mm()),
            array(py, r.measured.y_mm()),
            array(py, r.measured.z_nm()),
        )
    });
    Ok((
        text,
        array(py, f.x_mm()),
        array(py, f.y_mm()),
        array(py, f.z_nm()),
        last,
    ))
}
