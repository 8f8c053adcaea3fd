//! `preston._preston`: the native half of the `preston` Python package.
//!
//! Arrays cross as numpy `float64` (copied once into the engine's vectors, never through files),
//! long work runs with the interpreter released ([`Python::detach`]), and every Preston error
//! becomes a Python exception of the `PrestonError` hierarchy carrying Preston's message. The
//! Python layer (`python/preston/__init__.py`) builds the job from keyword arguments and calls
//! the functions here with the job as JSON (the job file's structure, see `preston_io::job`).
#![warn(missing_docs)]

mod figures;
mod paths;
mod workflow;

use numpy::{IntoPyArray, PyArray1, PyReadonlyArray1, PyReadonlyArray2};
use preston_io::job::Job;
use preston_io::metrology::{MapFormat, MapInput, MapRead, MapSource};
use preston_io::pipeline::{self, Inputs, Solved};
use preston_io::readers::{read_dwell, DwellFile};
use preston_io::report::centred_residual_nm;
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
use std::time::Instant;

create_exception!(
    preston,
    PrestonError,
    PyException,
    "Base class of every error Preston raises; the message is Preston's (file, line, field)."
);
/// The Python types of the input errors, made at import (they subclass Python's builtins as well
/// as [`PrestonError`], which a `create_exception!` type cannot).
static INPUT_TYPES: PyOnceLock<[Py<PyType>; 3]> = PyOnceLock::new();

/// `InputError(PrestonError, ValueError)`, `InputFileError(InputError, OSError)` and
/// `InputFileNotFoundError(InputFileError, FileNotFoundError)`.
fn make_input_types(py: Python<'_>) -> PyResult<[Py<PyType>; 3]> {
    let builtins = py.import("builtins")?;
    let type_ = builtins.getattr("type")?;
    let make = |name: &str, bases: Bound<'_, PyTuple>, doc: &str| -> PyResult<Py<PyType>> {
        let dict = PyDict::new(py);
        dict.set_item("__module__", "preston")?;
        dict.set_item("__doc__", doc)?;
        Ok(type_
            .call1((name, bases, dict))?
            .cast_into::<PyType>()?
            .unbind())
    };
    let input = make(
        "InputError",
        PyTuple::new(
            py,
            [
                py.get_type::<PrestonError>().into_any(),
                py.get_type::<PyValueError>().into_any(),
            ],
        )?,
        "Bad input: a malformed map/TIF/job, an invalid option, keyword or array. A ValueError.",
    )?;
    let file = make(
        "InputFileError",
        PyTuple::new(
            py,
            [
                input.bind(py).clone().into_any(),
                py.get_type::<PyOSError>().into_any(),
            ],
        )?,
        "A file that cannot be opened, read or written. An InputError and an OSError.",
    )?;
    let missing = make(
        "InputFileNotFoundError",
        PyTuple::new(
            py,
            [
                file.bind(py).clone().into_any(),
                py.get_type::<PyFileNotFoundError>().into_any(),
            ],
        )?,
        "A file that does not exist. An InputFileError and a FileNotFoundError.",
    )?;
    Ok([input, file, missing])
}

/// Raises the input errors ([`make_input_types`]).
pub(crate) struct InputError;

impl InputError {
    /// `InputError(msg)`.
    pub(crate) fn new_err(msg: impl Into<String>) -> PyErr {
        input_err(0, msg.into())
    }
}

/// The input error of kind `k` (0 input, 1 file, 2 missing file) with `msg`.
fn input_err(k: usize, msg: String) -> PyErr {
    Python::attach(
        |py| match INPUT_TYPES.get_or_try_init(py, || make_input_types(py)) {
            Ok(types) => PyErr::from_type(types[k].bind(py).clone(), msg),
            Err(e) => e,
        },
    )
}

create_exception!(
    preston,
    SolverError,
    PrestonError,
    "The engine failed numerically (a factorisation or solver broke down)."
);
create_exception!(
    preston,
    NotConvergedError,
    PrestonError,
    "The solver stopped before converging (raised only with require_converged=True)."
);

/// Preston's I/O error as the matching Python exception.
pub(crate) fn to_py(e: preston_io::Error) -> PyErr {
    let numerical = matches!(
        &e,
        preston_io::Error::Engine {
            source: preston_solver::Error::Numerical { .. },
            ..
        } | preston_io::Error::Solver(preston_solver::Error::Numerical { .. })
    );
    if numerical {
        return SolverError::new_err(e.to_string());
    }
    match &e {
        preston_io::Error::Io { source, .. } => {
            let k = if source.kind() == std::io::ErrorKind::NotFound {
                2
            } else {
                1
            };
            input_err(k, e.to_string())
        }
        _ => InputError::new_err(e.to_string()),
    }
}

/// A job's JSON as Python gave it, the error in Python's terms: the keyword of `solve` (or the
/// job key) at fault and serde's message without its position in the internal JSON.
pub(crate) fn json_error_in_python_terms(json: &str, e: &serde_json::Error) -> String {
    let mut msg = e.to_string();
    if let Some(k) = msg.rfind(" at line ") {
        msg.truncate(k);
    }
    let offset = json
        .split_inclusive('\n')
        .take(e.line().saturating_sub(1))
        .map(str::len)
        .sum::<usize>()
        + e.column().saturating_sub(1);
    let mut path = key_path_at(json, offset);
    // An unknown field is named by the message; its path is the object's plus the field.
    if let Some(field) = msg
        .strip_prefix("unknown field `")
        .and_then(|r| r.split('`').next())
    {
        if path.last().map(String::as_str) != Some(field) {
            path.push(field.to_string());
        }
    }
    let dotted = path.join(".");
    match python_keyword(&dotted) {
        Some(kw) => format!("{kw}: {msg} (job key {dotted})"),
        None if dotted.is_empty() => msg,
        None => format!("key {dotted}: {msg}"),
    }
}

/// The keyword of `preston.solve` a job key comes from, where there is one.
fn python_keyword(dotted: &str) -> Option<String> {
    const KEYS: [(&str, &str); 16] = [
        ("machine.v_max_mm_per_min", "v_max"),
        ("machine.v_min_mm_per_min", "v_min"),
        ("machine.a_max_mm_per_s2", "a_max"),
        ("machine.accel_method", "accel_method"),
        ("machine.corner_angle_deg", "corner_angle_deg"),
        ("objective.rho", "rho"),
        ("objective.lambda", "lambda_"),
        ("dwell.raster_pitch_mm", "raster_pitch_mm"),
        ("dwell.raster_along", "raster_along"),
        ("edge.method", "edge"),
        ("edge.width_mm", "edge_width_mm"),
        ("surface.tif_frame", "tif_frame"),
        ("solver.first_order_tolerance", "tolerance"),
        ("solver.first_order_max_iterations", "max_iterations"),
        ("solver.min_time", "min_time"),
        ("tif.file", "tif"),
    ];
    if let Some((_, kw)) = KEYS.iter().find(|(k, _)| *k == dotted) {
        return Some(format!("{kw}="));
    }
    if let Some(rest) = dotted.strip_prefix("tif.gaussian.") {
        return Some(format!("gaussian['{rest}']"));
    }
    if dotted == "tif.gaussian" {
        return Some("gaussian=".into());
    }
    if let Some(rest) = dotted.strip_prefix("map.") {
        return Some(format!("map_options['{rest}']"));
    }
    if let Some(rest) = dotted.strip_prefix("solver.") {
        return Some(format!("{rest}="));
    }
    None
}

/// The keys leading to byte `offset` of a JSON text (`["tif", "gaussian", "peak"]`); array
/// elements appear as their index.
fn key_path_at(json: &str, offset: usize) -> Vec<String> {
    enum Frame {
        Object(Option<String>),
        Array(usize),
    }
    let bytes = json.as_bytes();
    let mut stack: Vec<Frame> = Vec::new();
    let mut i = 0;
    let mut last_string: Option<String> = None;
    while i < bytes.len() && i < offset {
        match bytes[i] {
            b'"' => {
                let start = i + 1;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
                last_string = json.get(start..i.min(json.len())).map(str::to_string);
            }
            b':' => {
                if let Some(Frame::Object(key)) = stack.last_mut() {
                    *key = last_string.take();
                }
            }
            b'{' => stack.push(Frame::Object(None)),
            b'[' => stack.push(Frame::Array(0)),
            b'}' | b']' => {
                stack.pop();
            }
            b',' => match stack.last_mut() {
                Some(Frame::Array(k)) => *k += 1,
                Some(Frame::Object(key)) => *key = None,
                None => {}
            },
            _ => {}
        }
        i += 1;
    }
    stack
        .into_iter()
        .filter_map(|f| match f {
            Frame::Object(k) => k,
            Frame::Array(k) => Some(k.to_string()),
        })
        .collect()
}

/// An engine error on data named `what` (an array argument) as a Python exception.
pub(crate) fn engine_to_py(what: &str, e: preston_solver::Error) -> PyErr {
    to_py(preston_io::Error::engine(what, e))
}

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

/// Forwards the engine's progress to a Python callable, at most about once per percent of a
/// stage and once per solver iteration. An exception raised by the callable is kept (the first
/// one) and raised when the work returns; later calls are skipped.
pub(crate) struct PyProgress {
    callback: Py<PyAny>,
    error: Mutex<Option<PyErr>>,
    total: [AtomicU64; 3],
    done: [AtomicU64; 3],
    reported: [AtomicU64; 3],
}

fn stage_index(s: Stage) -> usize {
    match s {
        Stage::Assembly => 0,
        Stage::Solve => 1,
        Stage::Loop => 2,
    }
}

fn stage_name(s: Stage) -> &'static str {
    match s {
        Stage::Assembly => "assembly",
        Stage::Solve => "solve",
        Stage::Loop => "loop",
    }
}

impl PyProgress {
    pub(crate) fn new(callback: Py<PyAny>) -> Self {
        Self {
            callback,
            error: Mutex::new(None),
            total: Default::default(),
            done: Default::default(),
            reported: Default::default(),
        }
    }

    fn failed(&self) -> bool {
        self.error.lock().map_or(true, |e| e.is_some())
    }

    fn send(&self, stage: Stage, event: &str, info: Option<&IterationInfo>) {
        if self.failed() {
            return;
        }
        let i = stage_index(stage);
        let result = Python::attach(|py| -> PyResult<()> {
            let d = PyDict::new(py);
            d.set_item("stage", stage_name(stage))?;
            d.set_item("event", event)?;
            d.set_item("done", self.done[i].load(Ordering::Relaxed))?;
            d.set_item("total", self.total[i].load(Ordering::Relaxed))?;
            if let Some(info) = info {
                d.set_item("iteration", info.iteration)?;
                d.set_item("objective", info.objective)?;
                d.set_item("kkt_residual", info.kkt_residual)?;
            }
            self.callback.call1(py, (d,))?;
            Ok(())
        });
        if let Err(e) = result {
            if let Ok(mut slot) = self.error.lock() {
                slot.get_or_insert(e);
            }
        }
    }

    pub(crate) fn take_error(&self) -> Option<PyErr> {
        self.error.lock().ok().and_then(|mut e| e.take())
    }
}

impl Observer for PyProgress {
    fn start(&self, stage: Stage, total: u64) {
        let i = stage_index(stage);
        self.total[i].store(total, Ordering::Relaxed);
        self.done[i].store(0, Ordering::Relaxed);
        self.reported[i].store(0, Ordering::Relaxed);
        self.send(stage, "start", None);
    }

    fn advance(&self, stage: Stage, units: u64) {
        let i = stage_index(stage);
        let done = self.done[i].fetch_add(units, Ordering::Relaxed) + units;
        let step = (self.total[i].load(Ordering::Relaxed) / 100).max(1);
        let last = self.reported[i].load(Ordering::Relaxed);
        if done >= last + step
            && self.reported[i]
                .compare_exchange(last, done, Ordering::Relaxed, Ordering::Relaxed)
                .is_ok()
        {
            self.send(stage, "advance", None);
        }
    }

    fn finish(&self, stage: Stage) {
        self.send(stage, "finish", None);
    }

    fn iteration(&self, info: &IterationInfo) {
        self.send(Stage::Solve, "iteration", Some(info));
    }
}

/// The result of a solve: dwell times, feeds, removal and residual as numpy arrays, the report
/// as a dict (the keys of `report.json`).
#[pyclass(module = "preston._preston", frozen)]
pub struct SolveResult {
    solved: Solved,
    /// The job as solved (its files and settings for the report's provenance).
    job: Job,
    /// The job file (or `<python>`).
    job_path: PathBuf,
    feeds: Vec<f64>,
    residual: Vec<f64>,
    /// The job's raster direction (`[dwell] raster_along`): the PSD's line direction.
    raster_along: RasterAxis,
    /// The job's raster pitch, mm, marked on the PSD plot.
    raster_pitch_mm: Option<f64>,
}

/// A numpy float64 vector.
pub(crate) type Array<'py> = Bound<'py, PyArray1<f64>>;

pub(crate) fn array<'py>(py: Python<'py>, v: &[f64]) -> Array<'py> {
    v.to_vec().into_pyarray(py)
}

#[pymethods]
impl SolveResult {
    /// Dwell time at each dwell point, s (path order).
    #[getter]
    fn dwell_s<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, &self.solved.solution().dwell_s)
    }
    /// Feed into each dwell point, mm/min (`ds_mm / dwell_s * 60`).
    #[getter]
    fn feed_mm_per_min<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, &self.feeds)
    }
    /// Path length each dwell point stands for, mm.
    #[getter]
    fn ds_mm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.prepared.ds_mm())
    }
    /// Dwell point x, mm (path order).
    #[getter]
    fn dwell_x_mm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.prepared.path().x_mm())
    }
    /// Dwell point y, mm (path order).
    #[getter]
    fn dwell_y_mm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.prepared.path().y_mm())
    }
    /// Map point x, mm (the points kept after reading).
    #[getter]
    fn map_x_mm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.prepared.map().x_mm())
    }
    /// Map point y, mm.
    #[getter]
    fn map_y_mm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.prepared.map().y_mm())
    }
    /// Map error height, nm.
    #[getter]
    fn z_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.prepared.map().z_nm())
    }
    /// Predicted removal at each map point, nm.
    #[getter]
    fn removal_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.removal_nm())
    }
    /// Residual `z - removal` at each map point with its mean removed (as in residual.csv), nm.
    #[getter]
    fn residual_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, &self.residual)
    }
    /// The report as JSON text (the content of report.json).
    #[getter]
    fn report_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.solved.report)
            .map_err(|e| InputError::new_err(format!("report: {e}")))
    }
    /// Solver status (`converged`, `almost_converged`, ...), as in the report.
    #[getter]
    fn status(&self) -> String {
        self.solved.report.status.to_string()
    }
    /// Whether the solver converged (to the requested or a reduced tolerance).
    #[getter]
    fn converged(&self) -> bool {
        self.solved.solution().status.is_converged()
    }
    /// Writes dwell.csv, residual.csv and report.json into `out_dir` (created if needed) and,
    /// with `plots`, the figures and psd.csv of `preston solve --plots`; everything is staged
    /// first and committed together (all files or none). Returns the notes on figures left out.
    /// With `report`, also report.html (`preston solve --report`); `color_limits` (`"robust"`,
    /// `"full"` or `"LO,HI"` in nm) sets the colour range of the error and residual maps,
    /// `plot_format` (`"png"`, `"svg"`) the figures' file format.
    #[pyo3(signature = (out_dir, plots=false, report=false, color_limits=None, plot_format="png"))]
    fn write(
        &self,
        py: Python<'_>,
        out_dir: PathBuf,
        plots: bool,
        report: bool,
        color_limits: Option<&str>,
        plot_format: &str,
    ) -> PyResult<Vec<String>> {
        let format = figures::plot_format(plot_format)?;
        let color_limits = match color_limits {
            Some(c) => c
                .parse::<preston_io::plots::ColorLimits>()
                .map_err(|e| InputError::new_err(format!("color_limits: {e}")))?,
            None => preston_io::plots::ColorLimits::default(),
        };
        let options = pipeline::OutputOptions {
            figures: Some((
                figures::line_axis_of(self.raster_along),
                self.raster_pitch_mm,
            )),
            plots,
            html: report.then(|| {
                preston_io::html::Provenance::of_job(
                    &self.job,
                    &self.job_path,
                    Some(format!(
                        "preston.solve (Python package {})",
                        env!("CARGO_PKG_VERSION")
                    )),
                )
            }),
            style: preston_io::figures::FigureStyle {
                color_limits,
                format,
            },
        };
        py.detach(|| pipeline::write_solve_outputs(&self.solved, &out_dir, &options))
            .map_err(to_py)
    }
    /// Writes the figures of `preston solve --plots` into `out_dir` (created if needed): maps of
    /// the error, removal, residual (nm), dwell (s) and feed (mm/min), the path, the TIF (nm/s)
    /// and the PSDs of error and residual along `along` (`"x"`/`"y"`; default: the job's raster
    /// direction) with `psd.csv`, all committed together. Returns `(files, notes)`: the paths
    /// written and why a figure was left out (no PSD for a map off a lattice). `plot_format`:
    /// `"png"` or `"svg"`.
    #[pyo3(signature = (out_dir, along=None, plot_format="png"))]
    fn write_plots(
        &self,
        py: Python<'_>,
        out_dir: PathBuf,
        along: Option<&str>,
        plot_format: &str,
    ) -> PyResult<(Vec<PathBuf>, Vec<String>)> {
        let axis = figures::line_axis(along, self.raster_along)?;
        let format = figures::plot_format(plot_format)?;
        py.detach(|| {
            figures::write_figures(&self.solved, &out_dir, axis, self.raster_pitch_mm, format)
        })
        .map_err(to_py)
    }
    /// The 1-D PSDs (nm^2 mm) of the map error and the residual along lattice lines in `along`
    /// (default: the job's raster direction) against frequency (1/mm), the columns of psd.csv:
    /// `(frequency_per_mm, error_psd_nm2_mm, residual_psd_nm2_mm, info_json)`.
    #[pyo3(signature = (along=None))]
    fn psd<'py>(
        &self,
        py: Python<'py>,
        along: Option<&str>,
    ) -> PyResult<(Array<'py>, Array<'py>, Array<'py>, String)> {
        let axis = figures::line_axis(along, self.raster_along)?;
        figures::psd(py, &self.solved, axis)
    }
}

/// A job as JSON text without its null values: an absent option is `None` when read back, and
/// a non-finite number (JSON has none: `time_limit_s = inf` is written `null`) takes its default.
fn job_to_json(job: &Job, job_name: &str) -> PyResult<String> {
    fn strip_nulls(v: &mut serde_json::Value) {
        match v {
            serde_json::Value::Object(m) => {
                m.retain(|_, x| !x.is_null());
                m.values_mut().for_each(strip_nulls);
            }
            serde_json::Value::Array(a) => a.iter_mut().for_each(strip_nulls),
            _ => {}
        }
    }
    let mut v =
        serde_json::to_value(job).map_err(|e| InputError::new_err(format!("{job_name}: {e}")))?;
    strip_nulls(&mut v);
    Ok(v.to_string())
}

/// Reads a job file (TOML) and returns it as JSON text, relative paths made relative to the
/// file's directory.
#[pyfunction]
fn load_job(path: PathBuf) -> PyResult<String> {
    let job = Job::load(&path).map_err(to_py)?;
    job_to_json(&job, &path.display().to_string())
}

/// Checks a job given as JSON (the job file's structure) and returns it back normalised.
#[pyfunction]
#[pyo3(signature = (job_json, base_dir=None, job_name="<job>"))]
fn check_job(job_json: &str, base_dir: Option<PathBuf>, job_name: &str) -> PyResult<String> {
    let mut job = parse_job(job_json, job_name)?;
    if let Some(b) = base_dir {
        job.resolve_paths(&b);
    }
    job_to_json(&job, job_name)
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

/// Arrays given in place of the job's files.
struct ArrayInputs {
    map: Option<Vec<Vec<f64>>>,
    tif: Option<Vec<Vec<f64>>>,
    dwell: Option<Vec<Vec<f64>>>,
}

/// Reads what the job names and takes the rest from the arrays, then builds the problem.
fn prepare_arrays(
    job: &Job,
    job_path: &Path,
    arrays: ArrayInputs,
    observer: &dyn Observer,
) -> preston_io::Result<pipeline::Prepared> {
    let started = Instant::now();
    let map = match arrays.map {
        Some(c) => {
            let [x, y, z]: [Vec<f64>; 3] = c
                .try_into()
                .map_err(|_| preston_io::Error::option("map_xyz", "needs three columns"))?;
            MapRead {
                map: HeightMap::new(x, y, z)
                    .map_err(|e| preston_io::Error::engine("map_xyz", e))?,
                // Arrays carry no file format; the report leaves `map_input` out for them.
                input: MapInput {
                    format: MapFormat::Csv,
                    invalid_points: 0,
                    outside_aperture: 0,
                    pitch_mm: None,
                    notes: Vec::new(),
                    removed: None,
                },
            }
        }
        None => {
            if job.map.file.is_none() {
                return Err(preston_io::Error::Job {
                    file: job_path.to_path_buf(),
                    why: "no map: give map= (a file) or map_xyz= (an (N, 3) array)".into(),
                });
            }
            job.map.read()?
        }
    };
    let tif = match arrays.tif {
        Some(c) => Tif::Grid(
            GridTif::from_samples(&c[0], &c[1], &c[2])
                .map_err(|e| preston_io::Error::engine("tif_xyr", e))?,
        ),
        None => pipeline::load_tif(job, job_path)?,
    };
    let dwell = match (arrays.dwell, &job.dwell.file, job.dwell.raster_pitch_mm) {
        (Some(mut c), _, _) => {
            let y = c.pop().unwrap_or_default();
            let x = c.pop().unwrap_or_default();
            Some(DwellFile {
                path: DwellPath::new(x, y).map_err(|e| preston_io::Error::engine("dwell_xy", e))?,
                dwell_s: None,
            })
        }
        (None, Some(f), None) => Some(read_dwell(f)?),
        _ => None,
    };
    pipeline::prepare_inputs(job, job_path, Inputs { map, tif, dwell }, started, observer)
}

/// Reads what the job names and takes the rest from the arrays, then prepares and solves.
fn run_solve(
    job: &Job,
    job_path: &Path,
    arrays: ArrayInputs,
    observer: &dyn Observer,
) -> preston_io::Result<Solved> {
    let map_from_array = arrays.map.is_some();
    let prepared = prepare_arrays(job, job_path, arrays, observer)?;
    let mut solved = pipeline::solve(prepared, job, observer)?;
    if map_from_array {
        solved.report.map_input = None;
    }
    Ok(solved)
}

/// The assembled influence matrix `R` of a job (the problem `solve` would build, `R` assembled
/// whatever operator the job names), in compressed sparse column form: `(rows of the map, rows,
/// columns, column offsets, row indices, values)` (the map's rows first, then the edge
/// extension's), with the dwell points and the map points.
#[pyfunction]
#[pyo3(signature = (job_json, job_name="<python>", map_xyz=None, tif_xyr=None, dwell_xy=None))]
#[allow(clippy::type_complexity)]
fn influence_matrix<'py>(
    py: Python<'py>,
    job_json: &str,
    job_name: &str,
    map_xyz: Option<PyReadonlyArray2<'_, f64>>,
    tif_xyr: Option<PyReadonlyArray2<'_, f64>>,
    dwell_xy: Option<PyReadonlyArray2<'_, f64>>,
) -> PyResult<(
    usize,
    usize,
    usize,
    Vec<usize>,
    Vec<usize>,
    Array<'py>,
    [Array<'py>; 4],
)> {
    let mut job = parse_job(job_json, job_name)?;
    job.solver.operator = preston_solver::dwell::OperatorChoice::Sparse;
    let arrays = ArrayInputs {
        map: map_xyz.map(|a| columns(&a, "map_xyz", 3)).transpose()?,
        tif: tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
        dwell: dwell_xy.map(|a| columns(&a, "dwell_xy", 2)).transpose()?,
    };
    let job_path = PathBuf::from(job_name);
    let prepared = py
        .detach(|| prepare_arrays(&job, &job_path, arrays, &Silent))
        .map_err(to_py)?;
    let r = prepared.problem.operator().matrix().ok_or_else(|| {
        InputError::new_err(
            "this job's R is not assembled (a curvature-dependent or off-lattice operator)",
        )
    })?;
    let csc = r.csc();
    let (map, path) = (prepared.map(), prepared.path());
    Ok((
        map.len(),
        r.nrows(),
        r.ncols(),
        csc.col_offsets().to_vec(),
        csc.row_indices().to_vec(),
        array(py, csc.values()),
        [
            array(py, path.x_mm()),
            array(py, path.y_mm()),
            array(py, map.x_mm()),
            array(py, map.y_mm()),
        ],
    ))
}

/// Solves a job (JSON, the job file's structure) with optional arrays in place of its map
/// (`(N, 3)`: x_mm, y_mm, z_nm), TIF (`(N, 3)`: x_mm, y_mm, rate_nm_per_s on a regular grid) and
/// dwell points (`(N, 2)`: x_mm, y_mm in path order). `progress(event: dict)` is called with the
/// engine's progress; `threads` bounds the engine's threads (None: the global pool). The
/// interpreter is released while the solve runs.
#[pyfunction]
#[pyo3(signature = (job_json, job_name="<python>", map_xyz=None, tif_xyr=None, dwell_xy=None, progress=None, threads=None))]
#[allow(clippy::too_many_arguments)]
fn solve(
    py: Python<'_>,
    job_json: &str,
    job_name: &str,
    map_xyz: Option<PyReadonlyArray2<'_, f64>>,
    tif_xyr: Option<PyReadonlyArray2<'_, f64>>,
    dwell_xy: Option<PyReadonlyArray2<'_, f64>>,
    progress: Option<Py<PyAny>>,
    threads: Option<usize>,
) -> PyResult<SolveResult> {
    let job = parse_job(job_json, job_name)?;
    let arrays = ArrayInputs {
        map: map_xyz.map(|a| columns(&a, "map_xyz", 3)).transpose()?,
        tif: tif_xyr.map(|a| columns(&a, "tif_xyr", 3)).transpose()?,
        dwell: dwell_xy.map(|a| columns(&a, "dwell_xy", 2)).transpose()?,
    };
    let job_path = PathBuf::from(job_name);
    let observer = progress.map(PyProgress::new);
    let solved = py.detach(|| {
        with_threads(threads, || {
            let obs: &dyn Observer = match &observer {
                Some(o) => o,
                None => &Silent,
            };
            run_solve(&job, &job_path, arrays, obs)
        })
    })?;
    if let Some(e) = observer.as_ref().and_then(PyProgress::take_error) {
        return Err(e);
    }
    let solved = solved.map_err(to_py)?;
    let p = &solved.prepared;
    let feeds = solved.outcome.feeds_mm_per_min.clone();
    let residual = centred_residual_nm(p.map().z_nm(), solved.removal_nm());
    Ok(SolveResult {
        solved,
        feeds,
        residual,
        raster_along: job.dwell.raster_along,
        raster_pitch_mm: job.dwell.raster_pitch_mm,
        job,
        job_path,
    })
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
    m.add_function(wrap_pyfunction!(load_job, m)?)?;
    m.add_function(wrap_pyfunction!(check_job, m)?)?;
    m.add_function(wrap_pyfunction!(read_map, m)?)?;
    m.add_function(wrap_pyfunction!(solve, m)?)?;
    m.add_function(wrap_pyfunction!(influence_matrix, m)?)?;
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
    m.add_function(wrap_pyfunction!(_raise_numerical, m)?)?;
    Ok(())
}
