//! The solve pipeline: job -> inputs -> influence matrix -> problem -> solution -> output files.

use crate::atomic::commit_all;
use crate::error::{Error, Result};
use crate::job::Job;
use crate::machine::read_dwell_times;
use crate::metrology::{MapInput, MapRead};
use crate::readers::{read_dwell, read_tif, DwellFile};
use crate::report::{centred_residual_nm, feeds_mm_per_min, ExecutedReport, Report};
use crate::surface::read_surface;
use crate::writers::{stage_dwell_csv, stage_report, stage_residual_csv};
use preston_solver::dwell::{
    self, DwellBounds, OperatorChoice, Problem, Solution, SolverChoice, AUTO_FFT_MIN_NNZ,
};
use preston_solver::edge;
use preston_solver::influence::fft::FftOperator;
use preston_solver::influence::surface::assemble_on_surface;
use preston_solver::influence::InfluenceMatrix;
use preston_solver::machine::feeds::FeedSchedule;
use preston_solver::machine::gcode::motion::Kinematics;
use preston_solver::machine::gcode::{run_on_map, write_and_check};
use preston_solver::machine::nc::{NcProgram, NcSettings};
use preston_solver::machine::Flat;
use preston_solver::map::{HeightMap, HeightStats};
use preston_solver::observer::Observer;
use preston_solver::path::{raster, DwellPath};
use preston_solver::psd::LineAxis;
use preston_solver::tif::{InfluenceFunction, Tif};
use std::path::Path;
use std::time::Instant;

/// Everything read and built for a solve, before the solver runs.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The error map (rows with an empty/NaN height removed).
    pub map: HeightMap,
    /// Map rows skipped.
    pub skipped_rows: usize,
    /// How the map was read (format, dropped points, removed form terms).
    pub map_input: MapInput,
    /// The TIF.
    pub tif: Tif,
    /// The dwell path.
    pub path: DwellPath,
    /// Path length per dwell point, mm.
    pub ds_mm: Vec<f64>,
    /// Dwell times of a previous solution read with the path, if the file had them.
    pub previous_dwell_s: Option<Vec<f64>>,
    /// The validated problem: the map's rows first, then the edge extension's.
    pub problem: Problem,
    /// Edge extension points appended to the map's rows of the problem.
    pub edge_points: usize,
    /// Seconds spent reading and assembling.
    pub build_seconds: f64,
    /// Warnings about the inputs, for the report and stderr.
    pub warnings: Vec<String>,
}

/// A finished solve: the solution and what to write.
#[derive(Debug, Clone)]
pub struct Solved {
    /// The inputs.
    pub prepared: Prepared,
    /// The solver's answer.
    pub solution: Solution,
    /// Predicted removal at the map points, nm.
    pub removal_nm: Vec<f64>,
    /// The report.
    pub report: Report,
}

/// Loads the TIF a job names (exactly one of a file or a Gaussian model).
pub fn load_tif(job: &Job, job_path: &Path) -> Result<Tif> {
    match (&job.tif.file, &job.tif.gaussian) {
        (Some(f), None) => Ok(Tif::Grid(read_tif(f)?)),
        (None, Some(g)) => {
            g.validate().map_err(|e| Error::engine(job_path, e))?;
            Ok(Tif::Gaussian(g.clone()))
        }
        (Some(_), Some(_)) => Err(Error::Job {
            file: job_path.to_path_buf(),
            why: "[tif] gives both `file` and `gaussian`; choose one".into(),
        }),
        (None, None) => Err(Error::Job {
            file: job_path.to_path_buf(),
            why: "no TIF: set [tif] file or gaussian (or --tif / --gaussian-sigma-mm)".into(),
        }),
    }
}

/// Values held per dwell point through a solve (path, lengths, dwell, feeds, solver work
/// vectors), not counting the influence matrix: the memory budget's lower bound.
const DWELL_POINT_VALUES: f64 = 16.0;

/// The inputs of a solve, read from files or given in memory (the Python package passes arrays).
#[derive(Debug, Clone)]
pub struct Inputs {
    /// The error map and how it was read.
    pub map: MapRead,
    /// The TIF.
    pub tif: Tif,
    /// The dwell points (with a previous solution's dwell times when the file had them); `None`:
    /// the job's `[dwell] raster_pitch_mm` generates a serpentine raster.
    pub dwell: Option<DwellFile>,
}

/// Reads the inputs a job names: the map (through its [`crate::metrology::MapSource`]), the TIF
/// and the dwell file (none when the job asks for a raster).
pub fn read_inputs(job: &Job, job_path: &Path) -> Result<Inputs> {
    job.solver
        .validate()
        .map_err(|e| Error::engine(job_path, e))?;
    job.feed_limits().map_err(|e| Error::engine(job_path, e))?;
    job.accel_limits().map_err(|e| Error::engine(job_path, e))?;
    if job.map.file.is_none() {
        return Err(Error::Job {
            file: job_path.to_path_buf(),
            why: "no map: set [map] file (or --map)".into(),
        });
    }
    let map = job.map.read()?;
    let tif = load_tif(job, job_path)?;
    let dwell = match (&job.dwell.file, job.dwell.raster_pitch_mm) {
        (Some(f), None) => Some(read_dwell(f)?),
        _ => None,
    };
    Ok(Inputs { map, tif, dwell })
}

/// Reads the inputs, generates the dwell raster if asked, assembles `R` and builds the problem.
pub fn prepare(job: &Job, job_path: &Path, observer: &dyn Observer) -> Result<Prepared> {
    let start = Instant::now();
    let inputs = read_inputs(job, job_path)?;
    prepare_inputs(job, job_path, inputs, start, observer)
}

/// Builds the problem from inputs already read (`started`: when reading began, for the report's
/// build time). `job_path` names the job in messages; the job's `[dwell]` decides between the
/// given points and a generated raster, exactly one of which must be set.
pub fn prepare_inputs(
    job: &Job,
    job_path: &Path,
    inputs: Inputs,
    started: Instant,
    observer: &dyn Observer,
) -> Result<Prepared> {
    job.solver
        .validate()
        .map_err(|e| Error::engine(job_path, e))?;
    let limits = job.feed_limits().map_err(|e| Error::engine(job_path, e))?;
    job.accel_limits().map_err(|e| Error::engine(job_path, e))?;
    let map_path = job.map.file.as_deref().unwrap_or(job_path);
    let Inputs {
        map: map_file,
        tif,
        dwell,
    } = inputs;
    let (path, previous_dwell_s) = match (dwell, job.dwell.raster_pitch_mm) {
        (Some(d), None) => {
            if d.path.len() < 2 {
                return Err(Error::Empty {
                    file: job.dwell.file.clone().unwrap_or_else(|| job_path.to_path_buf()),
                    why: "one dwell point: a path of length zero has no feed; give at least two \
                          points"
                        .into(),
                });
            }
            (d.path, d.dwell_s)
        }
        (None, Some(pitch)) => {
            let bbox = map_file
                .map
                .bounding_box_mm()
                .ok_or_else(|| Error::Empty {
                    file: map_path.to_path_buf(),
                    why: "no data rows".into(),
                })?
                .expanded(tif.nominal_radius_mm());
            if pitch.is_finite() && pitch > 0.0 {
                let points = ((bbox.x_max_mm - bbox.x_min_mm) / pitch + 1.0)
                    * ((bbox.y_max_mm - bbox.y_min_mm) / pitch + 1.0);
                preston_solver::budget::check_f64s(
                    "--raster-pitch-mm",
                    &format!(
                        "a raster of pitch {pitch} mm over the map plus the TIF radius \
                         ({points:.3e} dwell points, at least {DWELL_POINT_VALUES} values each)"
                    ),
                    points,
                    DWELL_POINT_VALUES,
                )?;
            }
            let p = raster::serpentine(&bbox, pitch, job.dwell.raster_along)
                .map_err(|e| Error::engine(job_path, e))?;
            (p, None)
        }
        (Some(_), Some(_)) => {
            return Err(Error::Job {
                file: job_path.to_path_buf(),
                why: "[dwell] gives both `file` and `raster_pitch_mm`; choose one".into(),
            })
        }
        (None, None) => {
            return Err(Error::Job {
                file: job_path.to_path_buf(),
                why: "no dwell points: set [dwell] file or raster_pitch_mm (or --dwell / --raster-pitch-mm)"
                    .into(),
            })
        }
    };
    let mut warnings = Vec::new();
    if let Some(w) = tif_wider_than_map(&map_file.map, &tif, map_path) {
        warnings.push(w);
    }
    let ds_mm = path.ds_mm();
    let bounds =
        DwellBounds::from_feeds(&ds_mm, &limits).map_err(|e| Error::engine(job_path, e))?;
    let map = map_file.map;
    // The problem's rows: the map, then the edge extension into the dwell area.
    let extension = edge::extend(
        &job.edge,
        map.x_mm(),
        map.y_mm(),
        map.z_nm(),
        path.x_mm(),
        path.y_mm(),
        tif.nominal_radius_mm(),
        tif.support_radius_mm(),
    )
    .map_err(|e| Error::engine(map_path, e))?;
    let edge_points = extension.len();
    let rows = if extension.is_empty() {
        map.clone()
    } else {
        let cat = |a: &[f64], b: &[f64]| [a, b].concat();
        HeightMap::new(
            cat(map.x_mm(), &extension.x_mm),
            cat(map.y_mm(), &extension.y_mm),
            cat(map.z_nm(), &extension.z_nm),
        )
        .map_err(|e| Error::engine(map_path, e))?
    };
    let fft = match fft_pitch(job, job_path, &rows, &path, &tif, &mut warnings)? {
        None => None,
        Some(pitch) => match FftOperator::new(
            rows.x_mm(),
            rows.y_mm(),
            path.x_mm(),
            path.y_mm(),
            pitch,
            &tif,
        ) {
            Ok(op) => Some(op),
            Err(e) if job.solver.operator == OperatorChoice::Fft => {
                return Err(Error::engine(map_path, e));
            }
            Err(e) => {
                warnings.push(format!(
                    "operator auto: the FFT operator does not apply ({e}); assembling R"
                ));
                None
            }
        },
    };
    let spread = match fft {
        Some(_) => None,
        None => crate::off_lattice::off_lattice_applicable(
            job,
            job_path,
            &rows,
            &path,
            &tif,
            &mut warnings,
        )?,
    };
    let (z_nm, rho, lambda) = (
        rows.z_nm().to_vec(),
        job.objective.rho,
        job.objective.lambda,
    );
    let problem = match (fft, spread) {
        (Some(op), _) => Problem::matrix_free(op, z_nm, bounds, rho, lambda),
        (None, Some(op)) => Problem::off_lattice(op, z_nm, bounds, rho, lambda),
        (None, None) => Problem::new(
            assemble(job, &rows, &path, &tif, observer)?,
            z_nm,
            bounds,
            rho,
            lambda,
        ),
    }
    .map_err(|e| Error::engine(job_path, e))?;
    Ok(Prepared {
        map,
        skipped_rows: map_file.input.invalid_points,
        map_input: map_file.input,
        tif,
        path,
        ds_mm,
        previous_dwell_s,
        problem,
        edge_points,
        build_seconds: started.elapsed().as_secs_f64(),
        warnings,
    })
}

/// Assembles `R` for the job: in the plane, or in each dwell point's tangent frame on the job's
/// design surface.
fn assemble(
    job: &Job,
    map: &HeightMap,
    path: &DwellPath,
    tif: &Tif,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    match &job.surface.file {
        None => Ok(InfluenceMatrix::assemble(
            map.x_mm(),
            map.y_mm(),
            path.x_mm(),
            path.y_mm(),
            tif,
            observer,
        )?),
        Some(f) => {
            let surface = read_surface(f)?;
            assemble_on_surface(
                &surface,
                map.x_mm(),
                map.y_mm(),
                path.x_mm(),
                path.y_mm(),
                tif,
                job.surface.tif_frame,
                observer,
            )
            .map_err(|e| Error::engine(f, e))
        }
    }
}

/// The FFT operator is used only when the map's bounding box holds at most this many lattice cells
/// per map point (a round aperture fills 79% of its square, i.e. 1.27 cells per point).
const MAX_LATTICE_CELLS_PER_MAP_POINT: f64 = 4.0;

/// The lattice pitch (mm) for the matrix-free FFT operator when the job's `operator` asks for it
/// (`fft`) or `auto` finds it worthwhile, `None` for the assembled matrix. `fft` with inputs it
/// cannot serve is an error naming why; `auto` then quietly assembles `R`.
fn fft_pitch(
    job: &Job,
    job_path: &Path,
    map: &HeightMap,
    path: &DwellPath,
    tif: &Tif,
    warnings: &mut Vec<String>,
) -> Result<Option<f64>> {
    let choice = job.solver.operator;
    if matches!(choice, OperatorChoice::Sparse | OperatorChoice::FftSpread) {
        return Ok(None);
    }
    let blocker = if job.surface.file.is_some() {
        Some("a [surface] file (the TIF acts in each point's tangent frame)")
    } else if job
        .accel_limits()
        .map_err(|e| Error::engine(job_path, e))?
        .is_some()
    {
        Some("an acceleration limit (its sequential QP needs R)")
    } else if job.solver.min_time {
        Some("the minimum-time mode (it runs the QP)")
    } else if job.solver.solver == SolverChoice::Qp {
        Some("solver = \"qp\" (the QP needs R)")
    } else {
        None
    };
    // The map must fill a fair share of its lattice (a gridded map, perhaps with a round
    // aperture), or the FFT buffers would dwarf the map.
    let pitch = FftOperator::lattice_pitch_mm(map.x_mm(), map.y_mm()).filter(|&p| {
        map.bounding_box_mm().is_some_and(|b| {
            let cells =
                ((b.x_max_mm - b.x_min_mm) / p + 1.0) * ((b.y_max_mm - b.y_min_mm) / p + 1.0);
            cells <= MAX_LATTICE_CELLS_PER_MAP_POINT * map.len() as f64
        })
    });
    match (choice, blocker, pitch) {
        (OperatorChoice::Fft, Some(why), _) => Err(Error::Job {
            file: job_path.to_path_buf(),
            why: format!("operator = \"fft\" cannot be used with {why}"),
        }),
        (OperatorChoice::Fft, None, None) => Err(Error::Job {
            file: job_path.to_path_buf(),
            why:
                "operator = \"fft\" needs map points on a regular lattice that they fill at least \
                  a quarter of"
                    .into(),
        }),
        (OperatorChoice::Fft, None, Some(p)) => Ok(Some(p)),
        (_, Some(_), _) | (_, None, None) => Ok(None),
        (_, None, Some(p)) => {
            // Map points inside one TIF disc, at most all of them, per dwell point.
            let r = tif.support_radius_mm();
            let per_column = (std::f64::consts::PI * r * r / (p * p)).min(map.len() as f64);
            let estimate = per_column * path.len() as f64;
            if estimate >= AUTO_FFT_MIN_NNZ as f64 {
                warnings.push(format!(
                    "operator auto: about {estimate:.2e} non-zeros in R, so products use the \
                     matrix-free FFT operator (operator = \"sparse\" assembles R)"
                ));
                Ok(Some(p))
            } else {
                Ok(None)
            }
        }
    }
}

/// A warning when the TIF's footprint (twice its support radius) is wider than the map in both
/// x and y: the solve still works, but every dwell point then touches most of the map and the
/// dwell map cannot resolve the error's shape.
pub fn tif_wider_than_map(map: &HeightMap, tif: &Tif, map_path: &Path) -> Option<String> {
    let bbox = map.bounding_box_mm()?;
    let width_mm = bbox.x_max_mm - bbox.x_min_mm;
    let height_mm = bbox.y_max_mm - bbox.y_min_mm;
    let footprint_mm = 2.0 * tif.support_radius_mm();
    (footprint_mm > width_mm.max(height_mm)).then(|| {
        format!(
            "the TIF footprint ({footprint_mm:.3} mm across) is wider than the map {} \
             ({width_mm:.3} x {height_mm:.3} mm): the tool cannot shape features smaller than itself",
            map_path.display()
        )
    })
}

/// The `dwell_s` column of a previous dwell file, checked against the number of dwell points.
fn read_warm_start(path: &Path, n: usize) -> Result<Vec<f64>> {
    let previous = read_dwell_times(path)?;
    if previous.dwell_s.len() != n {
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: format!(
                "warm start has {} dwell times but the job has {n} dwell points",
                previous.dwell_s.len()
            ),
        });
    }
    Ok(previous.dwell_s)
}

/// Runs the solver on prepared inputs and builds the report. With `[machine] a_max_mm_per_s2`
/// the acceleration limit is imposed by sequential convex programming ([`dwell::accel::solve`]);
/// either way the report gets the machining time and the largest acceleration of the schedule.
pub fn solve(prepared: Prepared, job: &Job, observer: &dyn Observer) -> Result<Solved> {
    let warm = match &job.dwell.warm_start {
        Some(path) => Some(read_warm_start(path, prepared.problem.n())?),
        None => None,
    };
    let limits = job.accel_limits()?;
    let (solution, accel) = match &limits {
        Some(l) => {
            let a =
                dwell::accel::solve(&prepared.problem, &prepared.path, l, &job.solver, observer)?;
            let mut report = a.report;
            if prepared.edge_points > 0 {
                // The SCP's RMS figures are over every row; give them on the measured map.
                let on_map = |t: &[f64]| -> Result<f64> {
                    let mut h = prepared.problem.removal_nm(t)?;
                    h.truncate(prepared.map.len());
                    Ok(HeightStats::of(&centred_residual_nm(prepared.map.z_nm(), &h)).rms_nm)
                };
                report.rms_after_nm = on_map(&a.solution.dwell_s)?;
                report.rms_after_reference_nm = on_map(&a.reference.dwell_s)?;
            }
            (a.solution, Some(report))
        }
        None => (
            dwell::solve_from(&prepared.problem, &job.solver, observer, warm.as_deref())?,
            None,
        ),
    };
    let mut removal_nm = prepared.problem.removal_nm(&solution.dwell_s)?;
    removal_nm.truncate(prepared.map.len());
    let mut report = Report::new(
        &prepared.problem,
        &solution,
        &removal_nm,
        &prepared.ds_mm,
        prepared.skipped_rows,
        prepared.build_seconds,
    );
    report.warnings.clone_from(&prepared.warnings);
    report.edge = job.edge.method;
    report.map_input = Some(prepared.map_input.clone());
    let schedule = FeedSchedule::new(
        &prepared.path,
        &solution.dwell_s,
        limits.as_ref().map(|l| l.a_max_mm_per_s2),
        job.corner_angle_deg(),
    )?;
    report.set_machine(&schedule, accel.as_ref());
    report.set_map_coverage(&prepared.map, &prepared.path, &solution.dwell_s);
    if let (Some(l), None) = (&limits, &job.surface.file) {
        let planned = report.rms_after_nm;
        let a = l.a_max_mm_per_s2;
        match executed_at_limit(&prepared, &solution.dwell_s, job, a, planned, observer) {
            Ok(e) => report.executed = Some(e),
            Err(e) => report
                .warnings
                .push(format!("the plan cannot be written as a program: {e}")),
        }
    }
    Ok(Solved {
        prepared,
        solution,
        removal_nm,
        report,
    })
}

/// The default program for `dwell_s` (ISO, G94, flat part, the job's feed limit) executed at
/// `a_max` with look-ahead, and the removal integrated along the executed motion
/// ([`preston_solver::machine::gcode::motion`]), on the prepared map.
fn executed_at_limit(
    prepared: &Prepared,
    dwell_s: &[f64],
    job: &Job,
    a_max_mm_per_s2: f64,
    planned_rms_nm: f64,
    observer: &dyn Observer,
) -> std::result::Result<ExecutedReport, preston_solver::Error> {
    let settings = NcSettings {
        a_max_mm_per_s2: Some(a_max_mm_per_s2),
        corner_angle_deg: job.corner_angle_deg(),
        v_max_mm_per_min: job.machine.v_max_mm_per_min,
        ..NcSettings::default()
    };
    let nc = NcProgram::plan(&prepared.path, dwell_s, &Flat, &settings)?;
    let check = write_and_check(&nc, &[])?;
    let kinematics = Kinematics::Trapezoidal {
        a_max_mm_per_s2,
        corner_angle_deg: settings.corner_angle_deg,
    };
    let m = &prepared.map;
    let run = run_on_map(
        &check.program,
        kinematics,
        prepared.tif.support_radius_mm() / 64.0,
        None,
        m.x_mm(),
        m.y_mm(),
        &prepared.tif,
        observer,
    )?;
    let after = HeightStats::of(&centred_residual_nm(m.z_nm(), &run.removal_nm));
    Ok(ExecutedReport {
        a_max_mm_per_s2,
        rms_after_nm: after.rms_nm,
        pv_after_nm: after.pv_nm,
        rms_ratio_to_plan: after.rms_nm / planned_rms_nm,
        stretch_time_s: run.check.executed_total_s,
        max_stretch_error: run.check.max_relative_error,
        stretches_over_5_percent: run.check.over_5_percent,
    })
}

/// Writes `dwell.csv`, `residual.csv` and `report.json` into `out_dir` (created if needed). All
/// three are fully written to temporary files before any is renamed into place.
pub fn write_outputs(solved: &Solved, out_dir: &Path) -> Result<()> {
    write_outputs_with_figures(solved, out_dir, None).map(|_| ())
}

/// [`write_outputs`], with the figure set of [`crate::figures`] when `figures` gives the raster
/// direction (and pitch); everything is staged first and committed together. Returns notes on
/// figures left out.
pub fn write_outputs_with_figures(
    solved: &Solved,
    out_dir: &Path,
    figures: Option<(LineAxis, Option<f64>)>,
) -> Result<Vec<String>> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let (mut staged, notes) = match figures {
        Some((axis, pitch)) => crate::figures::stage_solve_figures(solved, out_dir, axis, pitch)?,
        None => (Vec::new(), Vec::new()),
    };
    let p = &solved.prepared;
    let feeds = feeds_mm_per_min(&p.ds_mm, &solved.solution.dwell_s);
    let residual = centred_residual_nm(p.map.z_nm(), &solved.removal_nm);
    staged.extend([
        stage_dwell_csv(
            &out_dir.join("dwell.csv"),
            p.path.x_mm(),
            p.path.y_mm(),
            &p.ds_mm,
            &solved.solution.dwell_s,
            &feeds,
        )?,
        stage_residual_csv(
            &out_dir.join("residual.csv"),
            p.map.x_mm(),
            p.map.y_mm(),
            p.map.z_nm(),
            &solved.removal_nm,
            &residual,
        )?,
        stage_report(&out_dir.join("report.json"), &solved.report)?,
    ]);
    commit_all(staged)?;
    Ok(notes)
}
