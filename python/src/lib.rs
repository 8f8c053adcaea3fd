//! `preston._preston`: the native half of the `preston` Python package.
//!
//! Arrays cross as numpy `float64` (copied once into the engine's vectors, never through files),
//! long work runs with the interpreter released ([`Python::detach`]), and every Preston error
//! becomes a Python exception of the `PrestonError` hierarchy carrying Preston's message. The
//! Python layer (`python/preston/__init__.py`) builds the job from keyword arguments and calls
//! the functions here with the job as JSON (the job file's structure, see `preston_io::job`).
#![warn(missing_docs)]

mod errors;
mod figures;
mod paths;
mod progress;
mod shop;
mod solve;
mod workflow;

pub(crate) use errors::{
    engine_to_py, json_error_in_python_terms, make_input_types, to_py, InputError,
    NotConvergedError, PrestonError, SolverError, INPUT_TYPES,
};
pub(crate) use progress::{interruptible, PyProgress};
pub(crate) use solve::SolveResult;

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1, PyReadonlyArray2};
use preston_io::job::Job;
use preston_io::metrology::{MapFormat, MapInput, MapRead, MapSource};
use preston_io::pipeline::{self, Given, Solved};
use preston_io::readers::DwellFile;
use preston_io::surface::{read_surface, FitSummary};
use preston_solver::fit::{fit_xy_polynomial, ConicBase, FitSettings};
use preston_solver::machine::gcode::write_and_check;
use preston_solver::machine::nc::{NcProgram, NcSettings};
use preston_solver::machine::{Flat, PartGeometry};
use preston_solver::map::{BoundingBox, HeightMap};
use preston_solver::observer::{IterationInfo, Observer, Silent, Stage};
use preston_solver::path::raster::{serpentine, RasterAxis};
use preston_solver::path::DwellPath;
use preston_solver::simulate::{removal_nm, Motion};
use preston_solver::surface::Surface;
use preston_solver::tif::{GridTif, Tif};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyFileNotFoundError, PyOSError, PyValueError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::PyDict;
use pyo3::types::{PyTuple, PyType};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

/// Runs `f` on a rayon pool of `threads` threads (the engine's parallel loops and faer's
/// factorisations then use that many), or on the global pool (`RAYON_NUM_THREADS`, else one
/// thread per core) when `None`. Results do not depend on the thread count: every parallel
/// reduction of the engine has a fixed order.
pub(crate) fn with_threads<T: Send>(
    threads: Option<usize>,
    f: impl FnOnce() -> T + Send,
) -> PyResult<T> {
    match threads {
        None => Ok(f()),
        Some(0) => Err(InputError::new_err(
            "threads: at least 1 (None: every core)",
        )),
        Some(n) => {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| InputError::new_err(format!("threads: {e}")))?;
            Ok(pool.install(f))
        }
    }
}

/// Columns of an `(N, k)` float64 array, checked for its width.
pub(crate) fn columns(
    a: &PyReadonlyArray2<'_, f64>,
    name: &str,
    k: usize,
) -> PyResult<Vec<Vec<f64>>> {
    let v = a.as_array();
    if v.ncols() != k {
        return Err(InputError::new_err(format!(
            "{name}: expected an array of shape (N, {k}), got ({}, {})",
            v.nrows(),
            v.ncols()
        )));
    }
    Ok((0..k).map(|j| v.column(j).to_vec()).collect())
}

fn parse_job(job_json: &str, job_name: &str) -> PyResult<Job> {
    serde_json::from_str(job_json).map_err(|e| {
        let why = json_error_in_python_terms(job_json, &e);
        if job_name == "<python>" {
            InputError::new_err(why)
        } else {
            InputError::new_err(format!("{job_name}: {why}"))
        }
    })
}

/// A numpy float64 vector.
pub(crate) type Array<'py> = Bound<'py, PyArray1<f64>>;

pub(crate) fn array<'py>(py: Python<'py>, v: &[f64]) -> Array<'py> {
    v.to_vec().into_pyarray(py)
}

/// Reads a map with the options of a job's `[map]` table (JSON), returning `(x_mm, y_mm, z_nm,
/// how_read_json)`.
#[pyfunction]
fn read_map<'py>(
    py: Python<'py>,
    source_json: &str,
) -> PyResult<(Array<'py>, Array<'py>, Array<'py>, String)> {
    let source: MapSource = serde_json::from_str(source_json)
        .map_err(|e| InputError::new_err(format!("map options: {e}")))?;
    let read = py.detach(|| source.read()).map_err(to_py)?;
    let how = serde_json::to_string(&read.input)
        .map_err(|e| InputError::new_err(format!("map options: {e}")))?;
    let MapRead { map, .. } = read;
    Ok((
        array(py, map.x_mm()),
        array(py, map.y_mm()),
        array(py, map.z_nm()),
        how,
    ))
}

/// The TIF of a `[tif]` table (JSON: `file` or `gaussian`), or the `(N, 3)` grid samples.
pub(crate) fn tif_of(tif_json: &str, tif_xyr: Option<Vec<Vec<f64>>>) -> PyResult<Tif> {
    if let Some(c) = tif_xyr {
        return GridTif::from_samples(&c[0], &c[1], &c[2])
            .map(Tif::Grid)
            .map_err(|e| engine_to_py("tif_xyr", e));
    }
    let job = Job {
        tif: serde_json::from_str(tif_json).map_err(|e| {
            InputError::new_err(format!("tif: {}", json_error_in_python_terms(tif_json, &e)))
        })?,
        ..Job::default()
    };
    pipeline::load_tif(&job, Path::new("tif")).map_err(to_py)
}

/// Removal (nm) at map points `(N, 2)` of the dwell program `dwell_xy` `(M, 2)` with `dwell_s`
/// `(M,)`: discrete dwells (`samples_per_point` None; the solver's model, `R t`) or continuous
/// motion at the scheduled feeds (midpoint rule, `samples_per_point` samples per dwell point).
#[pyfunction]
#[pyo3(signature = (map_xy, dwell_xy, dwell_s, tif_json="{}", tif_xyr=None, samples_per_point=None, progress=None))]
#[allow(clippy::too_many_arguments)]
fn simulate<'py>(
    py: Python<'py>,
    map_xy: PyReadonlyArray2<'py, f64>,
    dwell_xy: PyReadonlyArray2<'py, f64>,
    dwell_s: PyReadonlyArray1<'py, f64>,
    tif_json: &str,
    tif_xyr: Option<PyReadonlyArray2<'py, f64>>,
    samples_per_point: Option<usize>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let map = columns(&map_xy, "map_xy", 2)?;
    let mut pts = columns(&dwell_xy, "dwell_xy", 2)?;
    let dwell = dwell_s.as_array().to_vec();
    let tif = tif_of(
        tif_json,
        tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
    )?;
    let (y, x) = (pts.pop().unwrap_or_default(), pts.pop().unwrap_or_default());
    let path = DwellPath::new(x, y).map_err(|e| engine_to_py("dwell_xy", e))?;
    let motion = match samples_per_point {
        None => Motion::Discrete,
        Some(samples_per_point) => Motion::Continuous { samples_per_point },
    };
    let observer = progress.map(PyProgress::new);
    let removal = py.detach(|| {
        let obs: &dyn Observer = match &observer {
            Some(o) => o,
            None => &Silent,
        };
        removal_nm(&map[0], &map[1], &path, &dwell, &tif, motion, obs)
    });
    if let Some(e) = observer.as_ref().and_then(PyProgress::take_error) {
        return Err(e);
    }
    Ok(removal
        .map_err(|e| engine_to_py("simulate", e))?
        .into_pyarray(py))
}

/// A serpentine raster at `pitch_mm` over a box (mm), lines along `along` (`"x"` or `"y"`):
/// `(x_mm, y_mm)` in path order.
#[pyfunction]
fn raster<'py>(
    py: Python<'py>,
    x_min_mm: f64,
    x_max_mm: f64,
    y_min_mm: f64,
    y_max_mm: f64,
    pitch_mm: f64,
    along: &str,
) -> PyResult<(Array<'py>, Array<'py>)> {
    let axis: RasterAxis = serde_json::from_value(serde_json::Value::String(along.to_string()))
        .map_err(|e| InputError::new_err(format!("raster along: {e}")))?;
    let region = BoundingBox {
        x_min_mm,
        x_max_mm,
        y_min_mm,
        y_max_mm,
    };
    let p = serpentine(&region, pitch_mm, axis).map_err(|e| engine_to_py("raster", e))?;
    Ok((array(py, p.x_mm()), array(py, p.y_mm())))
}

/// Least-squares XY-polynomial surface through points `(N, 3)` (x, y, z in mm) of `order` on a
/// conic base (fixed `curvature_per_mm`/`conic`, or fitted): `(surface_json, summary_json,
/// residual_nm)`, the surface JSON being what `preston fit --out` writes.
#[pyfunction]
#[pyo3(signature = (points_xyz, order=10, norm_radius_mm=None, curvature_per_mm=0.0, conic=0.0, fit_conic=false))]
fn fit<'py>(
    py: Python<'py>,
    points_xyz: PyReadonlyArray2<'py, f64>,
    order: u32,
    norm_radius_mm: Option<f64>,
    curvature_per_mm: f64,
    conic: f64,
    fit_conic: bool,
) -> PyResult<(String, String, Bound<'py, PyArray1<f64>>)> {
    let c = columns(&points_xyz, "points_xyz", 3)?;
    let settings = FitSettings {
        order,
        norm_radius_mm: norm_radius_mm.unwrap_or(0.0),
        base: if fit_conic {
            ConicBase::Fitted
        } else {
            ConicBase::Fixed {
                curvature_per_mm,
                conic,
            }
        },
        ..FitSettings::default()
    };
    let f = py
        .detach(|| fit_xy_polynomial(&c[0], &c[1], &c[2], &settings))
        .map_err(|e| engine_to_py("points_xyz", e))?;
    let json = |v: serde_json::Result<String>| v.map_err(|e| InputError::new_err(e.to_string()));
    Ok((
        json(serde_json::to_string(&Surface::XyPolynomial(
            f.surface.clone(),
        )))?,
        json(serde_json::to_string(&FitSummary::of(&f)))?,
        array(py, &f.residual_nm),
    ))
}

/// The G-code program (`preston nc`) for dwell points `(N, 2)` (mm, path order) and `dwell_s`
/// `(N,)`, with the settings of a job's `[nc]`-style table (JSON, `NcSettings`) on a flat part or
/// the design surface in `surface_file`; `notes` are written as comment lines of the header.
/// Returns `(program_text, feed_blocks)`.
#[pyfunction]
#[pyo3(signature = (dwell_xy, dwell_s, settings_json="{}", surface_file=None, notes=Vec::new()))]
fn nc(
    py: Python<'_>,
    dwell_xy: PyReadonlyArray2<'_, f64>,
    dwell_s: PyReadonlyArray1<'_, f64>,
    settings_json: &str,
    surface_file: Option<PathBuf>,
    notes: Vec<String>,
) -> PyResult<(String, usize)> {
    let settings: NcSettings = serde_json::from_str(settings_json)
        .map_err(|e| InputError::new_err(format!("nc settings: {e}")))?;
    settings
        .validate()
        .map_err(|e| engine_to_py("nc settings", e))?;
    let mut pts = columns(&dwell_xy, "dwell_xy", 2)?;
    let (y, x) = (pts.pop().unwrap_or_default(), pts.pop().unwrap_or_default());
    let path = DwellPath::new(x, y).map_err(|e| engine_to_py("dwell_xy", e))?;
    let dwell = dwell_s.as_array().to_vec();
    let surface = surface_file
        .as_deref()
        .map(read_surface)
        .transpose()
        .map_err(to_py)?;
    let check = py.detach(|| {
        let geometry: &dyn PartGeometry = match &surface {
            Some(s) => s,
            None => &Flat,
        };
        NcProgram::plan(&path, &dwell, geometry, &settings)
            .and_then(|p| write_and_check(&p, &notes))
    });
    let check = check.map_err(|e| engine_to_py("nc", e))?;
    Ok((check.written.text, check.written.feed_blocks))
}

/// The `preston` command line run in this process on `argv` (the program name first), with the
/// interpreter released: the code of the `preston` binary, for the package's console script.
/// Returns the exit code (0 ok, 2 bad input, 3 not converged).
#[pyfunction]
fn run_cli(py: Python<'_>, argv: Vec<std::ffi::OsString>) -> u8 {
    py.detach(|| preston_cli::run_from_args(argv))
}

/// Writes the sample job into `dir` (`preston sample --out DIR`); returns its job file.
#[pyfunction]
#[pyo3(signature = (dir, overwrite = false))]
fn sample_job(py: Python<'_>, dir: PathBuf, overwrite: bool) -> PyResult<PathBuf> {
    py.detach(|| preston_io::sample::write_sample(&dir, overwrite))
        .map_err(to_py)
}

/// An engine error raised on purpose, for the exception-mapping tests.
#[pyfunction]
fn _raise_numerical() -> PyResult<()> {
    Err(engine_to_py(
        "<test>",
        preston_solver::Error::Numerical {
            stage: "test",
            why: "raised on request".into(),
        },
    ))
}

/// The native module.
#[pymodule]
fn _preston(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    // The crates' version: the same as `preston --version` and the wheel's.
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("PrestonError", py.get_type::<PrestonError>())?;
    let [input, file, missing] = INPUT_TYPES.get_or_try_init(py, || make_input_types(py))?;
    m.add("InputError", input.bind(py))?;
    m.add("InputFileError", file.bind(py))?;
    m.add("InputFileNotFoundError", missing.bind(py))?;
    m.add("SolverError", py.get_type::<SolverError>())?;
    m.add("NotConvergedError", py.get_type::<NotConvergedError>())?;
    m.add_class::<SolveResult>()?;
    m.add_function(wrap_pyfunction!(solve::load_job, m)?)?;
    m.add_function(wrap_pyfunction!(solve::check_job, m)?)?;
    m.add_function(wrap_pyfunction!(solve::apply_overrides, m)?)?;
    m.add_function(wrap_pyfunction!(read_map, m)?)?;
    m.add_function(wrap_pyfunction!(solve::solve, m)?)?;
    m.add_function(wrap_pyfunction!(solve::influence_matrix, m)?)?;
    m.add_function(wrap_pyfunction!(simulate, m)?)?;
    m.add_function(wrap_pyfunction!(raster, m)?)?;
    m.add_function(wrap_pyfunction!(fit, m)?)?;
    m.add_function(wrap_pyfunction!(nc, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::tif_model, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::tif_grid, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::tif_spot, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::path_spiral, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::path_random, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::path_edge_offset, m)?)?;
    m.add_function(wrap_pyfunction!(paths::path_lines, m)?)?;
    m.add_function(wrap_pyfunction!(paths::path_chord_height, m)?)?;
    m.add_function(wrap_pyfunction!(paths::path_project, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::register, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::simulate_program, m)?)?;
    m.add_function(wrap_pyfunction!(workflow::iterate, m)?)?;
    m.add_function(wrap_pyfunction!(shop::calibrate, m)?)?;
    m.add_function(wrap_pyfunction!(shop::shop, m)?)?;
    m.add_function(wrap_pyfunction!(run_cli, m)?)?;
    m.add_function(wrap_pyfunction!(sample_job, m)?)?;
    m.add_function(wrap_pyfunction!(_raise_numerical, m)?)?;
    Ok(())
}
