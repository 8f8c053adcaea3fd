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
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::PyDict;
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
create_exception!(
    preston,
    InputError,
    PrestonError,
    "Bad input: a file that cannot be read, a malformed map/TIF/job, an invalid option or array."
);
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
        SolverError::new_err(e.to_string())
    } else {
        InputError::new_err(e.to_string())
    }
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
        to_py(preston_io::Error::Job {
            file: PathBuf::from(job_name),
            why: e.to_string(),
        })
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
    #[pyo3(signature = (out_dir, plots=false))]
    fn write(&self, py: Python<'_>, out_dir: PathBuf, plots: bool) -> PyResult<Vec<String>> {
        let figures = plots.then(|| {
            (
                figures::line_axis_of(self.raster_along),
                self.raster_pitch_mm,
            )
        });
        py.detach(|| pipeline::write_outputs_with_figures(&self.solved, &out_dir, figures))
            .map_err(to_py)
    }
    /// Writes the figures of `preston solve --plots` into `out_dir` (created if needed): maps of
    /// the error, removal, residual (nm), dwell (s) and feed (mm/min), the path, the TIF (nm/s)
    /// and the PSDs of error and residual along `along` (`"x"`/`"y"`; default: the job's raster
    /// direction) with `psd.csv`, all committed together. Returns `(files, notes)`: the paths
    /// written and why a figure was left out (no PSD for a map off a lattice).
    #[pyo3(signature = (out_dir, along=None))]
    fn write_plots(
        &self,
        py: Python<'_>,
        out_dir: PathBuf,
        along: Option<&str>,
    ) -> PyResult<(Vec<PathBuf>, Vec<String>)> {
        let axis = figures::line_axis(along, self.raster_along)?;
        py.detach(|| figures::write_figures(&self.solved, &out_dir, axis, self.raster_pitch_mm))
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

/// Reads what the job names and takes the rest from the arrays, then prepares and solves.
fn run_solve(
    job: &Job,
    job_path: &Path,
    arrays: ArrayInputs,
    observer: &dyn Observer,
) -> preston_io::Result<Solved> {
    let started = Instant::now();
    let map_from_array = arrays.map.is_some();
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
    let prepared =
        pipeline::prepare_inputs(job, job_path, Inputs { map, tif, dwell }, started, observer)?;
    let mut solved = pipeline::solve(prepared, job, observer)?;
    if map_from_array {
        solved.report.map_input = None;
    }
    Ok(solved)
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
        tif: serde_json::from_str(tif_json)
            .map_err(|e| InputError::new_err(format!("tif: {e}")))?,
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
    m.add("InputError", py.get_type::<InputError>())?;
    m.add("SolverError", py.get_type::<SolverError>())?;
    m.add("NotConvergedError", py.get_type::<NotConvergedError>())?;
    m.add_class::<SolveResult>()?;
    m.add_function(wrap_pyfunction!(load_job, m)?)?;
    m.add_function(wrap_pyfunction!(check_job, m)?)?;
    m.add_function(wrap_pyfunction!(read_map, m)?)?;
    m.add_function(wrap_pyfunction!(solve, m)?)?;
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
