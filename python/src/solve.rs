//! `preston.solve` and `preston.influence_matrix`: the job checked, the arrays handed over, the
//! solve run with the interpreter released, and the result ([`SolveResult`]) with its arrays,
//! report and writers.

use crate::*;
use preston_io::overrides::Overrides;

/// The result of a solve: dwell times, feeds, removal and residual as numpy arrays, the report
/// as a dict (the keys of `report.json`).
#[pyclass(module = "preston._preston", frozen)]
pub struct SolveResult {
    solved: Solved,
    /// The job as solved (its files and settings for the report's provenance).
    job: Job,
    /// The job file (or `<python>`).
    job_path: PathBuf,
    /// The job's raster direction (`[dwell] raster_along`): the PSD's line direction.
    raster_along: RasterAxis,
    /// The job's raster pitch, mm, marked on the PSD plot.
    raster_pitch_mm: Option<f64>,
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
        array(py, &self.solved.outcome.feeds_mm_per_min)
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
    /// Predicted removal at each map point, nm, as the report states it: the program as
    /// executed where the solve executes it (an acceleration limit), else the model's.
    #[getter]
    fn removal_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, self.solved.removal_nm())
    }
    /// Residual `z - removal` at each map point with its mean removed (as in residual.csv; its
    /// RMS is the report's `rms_after_nm`), nm.
    #[getter]
    fn residual_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, &self.solved.delivered().residual_nm)
    }
    /// The model's removal `R t` at the programmed feeds at each map point, nm (equal to
    /// `removal_nm` where no program is executed).
    #[getter]
    fn model_removal_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, &self.solved.outcome.removal_nm)
    }
    /// The model's residual at the programmed feeds with its mean removed (as in
    /// residual_model.csv; equal to `residual_nm` where no program is executed), nm.
    #[getter]
    fn model_residual_nm<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        array(py, &self.solved.outcome.residual_nm)
    }
    /// The report as JSON text (the content of report.json).
    #[getter]
    fn report_json(&self) -> PyResult<String> {
        serde_json::to_string(&self.solved.report)
            .map_err(|e| InputError::new_err(format!("report: {e}")))
    }
    /// What the program of the job's machine does with the plan, as JSON text (the
    /// `program_check` of `preston solve --json`), or `None` when no program can deliver it.
    #[getter]
    fn program_check_json(&self) -> Option<String> {
        let check = self.solved.program_check.as_ref().ok()?;
        Some(preston_io::machine::program_check_summary(check).to_string())
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
            replace_earlier: None,
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
pub(crate) fn job_to_json(job: &Job, job_name: &str) -> PyResult<String> {
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
pub(crate) fn load_job(path: PathBuf) -> PyResult<String> {
    let job = Job::load(&path).map_err(to_py)?;
    job_to_json(&job, &path.display().to_string())
}

/// Checks a job given as JSON (the job file's structure) and returns it back normalised.
#[pyfunction]
#[pyo3(signature = (job_json, base_dir=None, job_name="<job>"))]
pub(crate) fn check_job(
    job_json: &str,
    base_dir: Option<PathBuf>,
    job_name: &str,
) -> PyResult<String> {
    let mut job = parse_job(job_json, job_name)?;
    if let Some(b) = base_dir {
        job.resolve_paths(&b);
    }
    job_to_json(&job, job_name)
}

/// A job (JSON) with the keywords of `preston.solve` applied over it ([`Overrides::apply`], the
/// same layer as the command line's flags), relative paths resolved against `base_dir`.
#[pyfunction]
#[pyo3(signature = (job_json, overrides_json, base_dir, job_name="<python>"))]
pub(crate) fn apply_overrides(
    job_json: &str,
    overrides_json: &str,
    base_dir: PathBuf,
    job_name: &str,
) -> PyResult<String> {
    let mut job = parse_job(job_json, job_name)?;
    let overrides: Overrides = serde_json::from_str(overrides_json)
        .map_err(|e| InputError::new_err(keyword_error(overrides_json, &e)))?;
    overrides
        .apply(&mut job, Path::new(job_name))
        .map_err(to_py)?;
    job.resolve_paths(&base_dir);
    job_to_json(&job, job_name)
}

/// A keyword's value that is not an override, in the keyword's terms: `solver=: unknown variant
/// ...`, `gaussian=: unknown field `peak` ...`, or `unknown keyword `vmax`, expected one of ...`.
fn keyword_error(json: &str, e: &serde_json::Error) -> String {
    let (msg, mut path) = crate::errors::message_and_key_path(json, e);
    // An unknown keyword's path is the keyword alone.
    let unknown_keyword = msg.starts_with("unknown field") && path.len() == 1;
    if unknown_keyword {
        path.pop();
    }
    match (path.first(), msg.strip_prefix("unknown field")) {
        (None, Some(rest)) => format!("unknown keyword{rest}"),
        (Some(kw), _) => format!("{kw}=: {msg}"),
        (None, None) => msg,
    }
}

/// Arrays given in place of the job's files.
pub(crate) struct ArrayInputs {
    map: Option<Vec<Vec<f64>>>,
    tif: Option<Vec<Vec<f64>>>,
    dwell: Option<Vec<Vec<f64>>>,
}

/// Reads what the job names and takes the rest from the arrays, then builds the problem.
pub(crate) fn prepare_arrays(
    job: &Job,
    job_path: &Path,
    arrays: ArrayInputs,
    observer: &dyn Observer,
) -> preston_io::Result<pipeline::Prepared> {
    let map = match arrays.map {
        Some(c) => {
            let [x, y, z]: [Vec<f64>; 3] = c
                .try_into()
                .map_err(|_| preston_io::Error::option("map_xyz", "needs three columns"))?;
            Some(MapRead {
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
            })
        }
        None => None,
    };
    let tif = match arrays.tif {
        Some(c) => Some(Tif::Grid(
            GridTif::from_samples(&c[0], &c[1], &c[2])
                .map_err(|e| preston_io::Error::engine("tif_xyr", e))?,
        )),
        None => None,
    };
    let dwell = match arrays.dwell {
        Some(mut c) => {
            let y = c.pop().unwrap_or_default();
            let x = c.pop().unwrap_or_default();
            Some(DwellFile {
                path: DwellPath::new(x, y).map_err(|e| preston_io::Error::engine("dwell_xy", e))?,
                dwell_s: None,
            })
        }
        None => None,
    };
    pipeline::prepare_given(job, job_path, Given { map, tif, dwell }, observer)
}

/// Reads what the job names and takes the rest from the arrays, then prepares and solves.
pub(crate) fn run_solve(
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
pub(crate) fn influence_matrix<'py>(
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
    let r = prepared.problem.influence().ok_or_else(|| {
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
pub(crate) fn solve(
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
    let solved = crate::interruptible(py, observer.as_ref(), |obs| {
        with_threads(threads, || run_solve(&job, &job_path, arrays, obs))
    })??;
    if let Some(e) = observer.as_ref().and_then(PyProgress::take_error) {
        return Err(e);
    }
    let solved = solved.map_err(to_py)?;
    Ok(SolveResult {
        solved,
        raster_along: job.dwell.raster_along,
        raster_pitch_mm: job.dwell.source.raster_pitch_mm(),
        job,
        job_path,
    })
}
