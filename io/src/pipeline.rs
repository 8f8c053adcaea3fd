//! The solve pipeline: job -> inputs -> influence matrix -> problem -> solution -> output files.

use crate::atomic::commit_all;
use crate::calibration::{read_calibration, CalibrationRecord};
use crate::error::{Error, Result};
use crate::job::{DwellSource, Job, TifInput};
use crate::machine::read_dwell_times;
use crate::metrology::{MapInput, MapRead};
use crate::readers::{read_dwell, read_tif, DwellFile};
use crate::report::{ExecutedReport, Report, ResidualFigures, RobustReport};
use crate::surface::read_surface;
use crate::writers::{stage_dwell_csv, stage_report, stage_residual_csv};
use preston_solver::calibrate::{map_noise_rms_nm, ToolUncertainty, DRIFT_SIGMA_PER_RUN};
use preston_solver::dwell::{Problem, Solution};
use preston_solver::machine::gcode::ProgramCheck;
use preston_solver::map::HeightMap;
use preston_solver::observer::Observer;
use preston_solver::path::DwellPath;
use preston_solver::psd::LineAxis;
use preston_solver::setup::robust;
use preston_solver::setup::{
    Checked, DwellPoints, Outcome, Setup, SetupData, SetupError, SetupInput,
};
use preston_solver::tif::model::{HertzPart, ProcessModel};
use preston_solver::tif::{InfluenceFunction, Tif};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Everything read and built for a solve, before the solver runs.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// The job resolved once: map, TIF, path, limits, weights, settings.
    pub setup: Setup,
    /// Map rows skipped.
    pub skipped_rows: usize,
    /// How the map was read (format, dropped points, removed form terms).
    pub map_input: MapInput,
    /// The validated problem: the map's rows first, then the edge extension's.
    pub problem: Problem,
    /// Edge extension points appended to the map's rows of the problem.
    pub edge_points: usize,
    /// Seconds spent reading and assembling.
    pub build_seconds: f64,
    /// Warnings about the inputs, for the report and stderr.
    pub warnings: Vec<String>,
    /// Notes on what the set-up chose (the operator, the exact swept columns), for the report
    /// and stderr.
    pub notes: Vec<String>,
    /// A robust plan's scenario weights (`None` for a nominal plan).
    pub scenario_weights: Option<Vec<f64>>,
    /// The tool's calibration, when the job names one.
    pub calibration: Option<CalibrationRecord>,
    /// How well the tool of this run is known (the expected result draws from it).
    pub uncertainty: ToolUncertainty,
}

impl Prepared {
    /// The error map (rows with an empty/NaN height removed).
    pub fn map(&self) -> &HeightMap {
        &self.setup.map
    }

    /// The TIF.
    pub fn tif(&self) -> &Tif {
        &self.setup.tif
    }

    /// The dwell path.
    pub fn path(&self) -> &DwellPath {
        &self.setup.path
    }

    /// Path length per dwell point, mm.
    pub fn ds_mm(&self) -> &[f64] {
        &self.setup.ds_mm
    }
}

/// A finished solve: the outcome and what to write.
#[derive(Debug, Clone)]
pub struct Solved {
    /// The inputs.
    pub prepared: Prepared,
    /// The solver's answer, the removal and the feed schedule.
    pub outcome: Outcome,
    /// The report.
    pub report: Report,
    /// The program for the plan on the job's machine ([`Job::nc_settings`]), written, read
    /// back and checked; or why no program can deliver the plan.
    pub program_check: std::result::Result<ProgramCheck, preston_solver::Error>,
}

impl Solved {
    /// The solver's answer.
    pub fn solution(&self) -> &Solution {
        &self.outcome.solution
    }

    /// Predicted removal at the map points, nm, as the headline states it: the executed
    /// program's where the solve executed one ([`crate::residual::Delivered`]), else the
    /// model's at the programmed feeds.
    pub fn removal_nm(&self) -> &[f64] {
        crate::residual::executed_removal_nm(&self.outcome).unwrap_or(&self.outcome.removal_nm)
    }

    /// The removal and residual the headline (`report.json` `rms_after_nm`) states.
    pub fn delivered(&self) -> crate::residual::Delivered<'_> {
        crate::residual::Delivered::of(self.prepared.map().z_nm(), &self.outcome)
    }
}

/// Loads the TIF a job names (exactly one of a file, a Gaussian model or a Hertzian tool).
pub fn load_tif(job: &Job, job_path: &Path) -> Result<Tif> {
    load_tif_input(job.tif.resolve(job_path)?, job_path)
}

/// The TIF of one resolved source; `job_path` names the job in messages. A Hertzian tool is its
/// model on a flat part ([`ProcessModel::hertz`], the TIF-model service) sampled on the grid of `pitch_mm`, as
/// `preston tif hertz` writes it; with `curvature_dependent` the set-up stage replaces it per
/// dwell point ([`preston_solver::setup::TifModel::CurvatureDependent`]) and this one sets the
/// raster margin, the edge band and the TIF figure.
pub fn load_tif_input(input: TifInput, job_path: &Path) -> Result<Tif> {
    let engine = |e| Error::engine(job_path, e);
    match input {
        TifInput::File(f) => Ok(Tif::Grid(read_tif(&f)?)),
        TifInput::Gaussian(g) => {
            g.validate().map_err(engine)?;
            Ok(Tif::Gaussian(g))
        }
        TifInput::Hertz {
            params, pitch_mm, ..
        } => {
            let grid = ProcessModel::hertz(&params, HertzPart::Flat)
                .and_then(|m| m.grid(pitch_mm))
                .map_err(engine)?;
            Ok(Tif::Grid(grid))
        }
    }
}

/// The inputs of a solve, read from files or given in memory (the Python package passes arrays).
#[derive(Debug, Clone)]
pub struct Inputs {
    /// The error map and how it was read.
    pub map: MapRead,
    /// The TIF.
    pub tif: Tif,
    /// The dwell points; `None`: the job's `[dwell] raster_pitch_mm` generates a serpentine
    /// raster.
    pub dwell: Option<DwellFile>,
    /// The tool's calibration (`[tif] calibration`).
    pub calibration: Option<CalibrationRecord>,
}

/// The job's choices validated once (the set-up stage's [`Choices::check`]), `job_path` naming
/// the job in messages.
pub fn check_job(job: &Job, job_path: &Path, observer: &dyn Observer) -> Result<Checked> {
    job.choices()
        .map_err(|e| Error::engine(job_path, e))?
        .check(observer)
        .map_err(|e| Error::engine(job_path, e.source))
}

/// Reads the inputs a job names: the map (through its [`crate::metrology::MapSource`]), the TIF
/// and the dwell file (none when the job asks for a raster).
pub fn read_inputs(job: &Job, job_path: &Path) -> Result<Inputs> {
    check_job(job, job_path, &preston_solver::observer::Silent)?;
    read_checked(job, job_path, Given::default())
}

/// Inputs handed over already read (the Python package's arrays) in place of the job's files.
#[derive(Debug, Clone, Default)]
pub struct Given {
    /// The map.
    pub map: Option<MapRead>,
    /// The TIF.
    pub tif: Option<Tif>,
    /// The dwell points.
    pub dwell: Option<DwellFile>,
}

/// The inputs: each one given, or read from the file the job names.
fn read_checked(job: &Job, job_path: &Path, given: Given) -> Result<Inputs> {
    let map = match given.map {
        Some(m) => m,
        None if job.map.file.is_none() => {
            return Err(Error::Job {
                file: job_path.to_path_buf(),
                why: "no map: set [map] file (--map; Python: map= or map_xyz=)".into(),
            })
        }
        None => job.map.read()?,
    };
    let calibration = job
        .tif
        .calibration
        .as_deref()
        .map(read_calibration)
        .transpose()?;
    let source_given =
        job.tif.file.is_some() || job.tif.gaussian.is_some() || job.tif.hertz.is_some();
    let tif = match (given.tif, &calibration) {
        (Some(t), _) => t,
        (None, Some(c)) if !source_given || is_spot_test_of(c, job.tif.file.as_deref()) => {
            Tif::Grid(read_tif(&c.tif_file)?)
        }
        (None, _) => load_tif(job, job_path)?,
    };
    let dwell = match (given.dwell, &job.dwell.source) {
        (Some(d), _) => Some(d),
        (None, DwellSource::File(f)) => Some(read_dwell(f)?),
        (None, DwellSource::Raster { .. }) => None,
        (None, DwellSource::Unset) => return Err(no_dwell_points(job_path)),
    };
    Ok(Inputs {
        map,
        tif,
        dwell,
        calibration,
    })
}

/// Whether the TIF file `tif_file` is the spot test `c` was calibrated from (its SHA-256 the one
/// `calibration.json` records): the calibration refines that TIF, so the calibrated TIF takes its
/// place. Any other TIF is planned with as given ([`calibrated_tif_warning`]).
pub fn is_spot_test_of(c: &CalibrationRecord, tif_file: Option<&Path>) -> bool {
    match (tif_file, &c.source_tif_sha256) {
        (Some(f), Some(sha)) => crate::calibration::file_sha256(f, "TIF").is_ok_and(|s| &s == sha),
        _ => false,
    }
}

/// A job that names no dwell points and was given none.
fn no_dwell_points(job_path: &Path) -> Error {
    Error::Job {
        file: job_path.to_path_buf(),
        why: "no dwell points: set [dwell] file or raster_pitch_mm (or --dwell / \
              --raster-pitch-mm)"
            .into(),
    }
}

/// Reads the inputs, generates the dwell raster if asked, assembles `R` and builds the problem.
pub fn prepare(job: &Job, job_path: &Path, observer: &dyn Observer) -> Result<Prepared> {
    prepare_given(job, job_path, Given::default(), observer)
}

/// [`prepare`] with some inputs handed over already read: the job's choices are checked first,
/// then what is not given is read from the files the job names.
pub fn prepare_given(
    job: &Job,
    job_path: &Path,
    given: Given,
    observer: &dyn Observer,
) -> Result<Prepared> {
    let start = Instant::now();
    let checked = check_job(job, job_path, observer)?;
    let inputs = read_checked(job, job_path, given)?;
    prepare_checked(job, job_path, checked, inputs, start, observer)
}

/// The file a set-up failure is about.
fn file_at_fault(job: &Job, job_path: &Path, input: SetupInput) -> PathBuf {
    let or_job = |p: &Option<PathBuf>| p.clone().unwrap_or_else(|| job_path.to_path_buf());
    match input {
        SetupInput::Job | SetupInput::None => job_path.to_path_buf(),
        SetupInput::Map => or_job(&job.map.file),
        SetupInput::Dwell => or_job(&job.dwell.source.file().map(Path::to_path_buf)),
        SetupInput::Surface => or_job(&job.surface.file),
        SetupInput::WarmStart => or_job(&job.dwell.warm_start),
    }
}

fn prepare_checked(
    job: &Job,
    job_path: &Path,
    checked: Checked,
    inputs: Inputs,
    started: Instant,
    observer: &dyn Observer,
) -> Result<Prepared> {
    let at_fault = |e: SetupError| match e.input {
        SetupInput::None => Error::Solver(e.source),
        input => Error::engine(file_at_fault(job, job_path, input), e.source),
    };
    let map_path = job.map.file.as_deref().unwrap_or(job_path);
    let Inputs {
        map: map_file,
        tif,
        dwell,
        calibration,
    } = inputs;
    // Points handed over already read (the Python package's arrays) need no `[dwell]` section.
    let dwell = match (dwell, &job.dwell.source) {
        (Some(d), source) => {
            if d.path.len() < 2 {
                return Err(Error::Empty {
                    file: source.file().unwrap_or(job_path).to_path_buf(),
                    why: "one dwell point: a path of length zero has no feed; give at least two \
                          points"
                        .into(),
                });
            }
            DwellPoints::Given(d.path)
        }
        (None, &DwellSource::Raster { pitch_mm }) => DwellPoints::Raster {
            pitch_mm,
            along: job.dwell.raster_along,
        },
        (None, DwellSource::File(f)) => {
            return Err(Error::Job {
                file: job_path.to_path_buf(),
                why: format!("the dwell file {} was not read", f.display()),
            })
        }
        (None, DwellSource::Unset) => return Err(no_dwell_points(job_path)),
    };
    let surface = match &job.surface.file {
        Some(f) => Some(read_surface(f)?),
        None => None,
    };
    let warm_start_s = match &job.dwell.warm_start {
        Some(p) => Some(read_dwell_times(p)?.dwell_s),
        None => None,
    };
    let mut warnings = Vec::new();
    if let Some(w) = tif_wider_than_map(&map_file.map, &tif, map_path) {
        warnings.push(w);
    }
    if let Some(w) = calibration
        .as_ref()
        .and_then(|c| calibrated_tif_warning(c, &tif))
    {
        warnings.push(w);
    }
    let mut setup = Setup::resolve(
        checked,
        SetupData {
            map: map_file.map,
            tif,
            dwell,
            surface,
            warm_start_s,
        },
        observer,
    )
    .map_err(at_fault)?;
    setup.rate_drift_per_hour = calibration.as_ref().map_or(0.0, |c| c.drift_per_hour);
    setup.tool_uncertainty = tool_uncertainty(job, calibration.as_ref());
    let built = setup.problem(observer).map_err(at_fault)?;
    warnings.extend(built.warnings);
    let notes = built.notes;
    let uncertainty = setup.tool_uncertainty;
    Ok(Prepared {
        setup,
        skipped_rows: map_file.input.invalid_points,
        map_input: map_file.input,
        problem: built.problem,
        edge_points: built.edge_points,
        build_seconds: started.elapsed().as_secs_f64(),
        warnings,
        notes,
        scenario_weights: built.scenario_weights,
        uncertainty,
        calibration,
    })
}

/// Largest distance between a TIF's node and the calibrated TIF's, mm: `tif.csv` prints the
/// nodes to six decimals, and a grid read back from it refits its pitch from them.
const CALIBRATED_NODE_TOL_MM: f64 = 1e-5;
/// Largest difference of a TIF's rate from the calibrated TIF's at a node, nm/s: `tif.csv`
/// prints the rates to nine decimals.
const CALIBRATED_RATE_TOL_NM_PER_S: f64 = 1e-8;

/// A warning when the solve's TIF is not the calibration's `tif.csv` (or that file has changed
/// since the calibration wrote it): the calibration's figures describe that TIF. The grids are
/// compared node by node to the file's printed precision, so the file itself, the same file read
/// again or the grid `preston.calibrate` returns all count as the calibrated TIF.
pub fn calibrated_tif_warning(c: &CalibrationRecord, tif: &Tif) -> Option<String> {
    let file = c.tif_file.display();
    let sha256 = match crate::calibration::file_sha256(&c.tif_file, "calibrated TIF") {
        Ok(h) => h,
        Err(e) => {
            return Some(format!(
                "the calibrated TIF cannot be read to compare ({e})"
            ))
        }
    };
    if !c.tif_sha256.is_empty() && sha256 != c.tif_sha256 {
        return Some(format!(
            "the calibrated TIF {file} has changed since the calibration: its SHA-256 is not the one calibration.json records"
        ));
    }
    let not_it = || {
        Some(format!(
            "the TIF is not the calibrated one ({file}): the calibration's figures describe that TIF"
        ))
    };
    let Tif::Grid(g) = tif else {
        return not_it();
    };
    let calibrated = match read_tif(&c.tif_file) {
        Ok(g) => g,
        Err(e) => {
            return Some(format!(
                "the calibrated TIF cannot be read to compare ({e})"
            ))
        }
    };
    let (gx, gy, gr) = g.columns();
    let (cx, cy, cr) = calibrated.columns();
    let same = gr.len() == cr.len()
        && (0..gr.len()).all(|k| {
            (gx[k] - cx[k]).abs() <= CALIBRATED_NODE_TOL_MM
                && (gy[k] - cy[k]).abs() <= CALIBRATED_NODE_TOL_MM
                && (gr[k] - cr[k]).abs() <= CALIBRATED_RATE_TOL_NM_PER_S
        });
    if same {
        None
    } else {
        not_it()
    }
}

use preston_solver::iterate::learned::next_run_rate_sigma;
pub use preston_solver::iterate::learned::RUN_TO_RUN_RATE_SIGMA;

/// How well the tool of the next run is known: a calibration's figures and their uncertainty
/// (its rate with [`RUN_TO_RUN_RATE_SIGMA`] beside), else the job's `[tif]` spot-test
/// uncertainty (defaults [`ToolUncertainty::default`]). The noise is the calibration's, else
/// estimated from the map.
fn tool_uncertainty(job: &Job, calibration: Option<&CalibrationRecord>) -> ToolUncertainty {
    match calibration {
        Some(c) => ToolUncertainty {
            rate_sigma: next_run_rate_sigma(c.rate_factor, c.rate_factor_sigma),
            width_sigma: c.width_factor_sigma / c.width_factor,
            offset_x_sigma_mm: c.offset_x_mm_sigma,
            offset_y_sigma_mm: c.offset_y_mm_sigma,
            // The plan's executed run already carries the calibrated drift.
            drift_per_hour: 0.0,
            drift_sigma_per_hour: c.drift_per_hour_sigma,
            // A calibration measures the drift of its run, not the next run's scatter about it.
            drift_sigma_per_run: DRIFT_SIGMA_PER_RUN,
            noise_rms_nm: c.noise_rms_nm,
        },
        None => {
            let d = ToolUncertainty::default();
            ToolUncertainty {
                rate_sigma: job.tif.rate_sigma.unwrap_or(d.rate_sigma),
                width_sigma: job.tif.width_sigma.unwrap_or(d.width_sigma),
                offset_x_sigma_mm: job.tif.offset_sigma_mm.unwrap_or(d.offset_x_sigma_mm),
                offset_y_sigma_mm: job.tif.offset_sigma_mm.unwrap_or(d.offset_y_sigma_mm),
                ..d
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

/// The tool's uncertainty the expected reading draws from: the calibration's, or the job's
/// with the map's own noise where no calibration is named.
fn reading_uncertainty(prepared: &Prepared) -> ToolUncertainty {
    let mut uncertainty = prepared.uncertainty;
    if prepared.calibration.is_none() {
        let map = &prepared.setup.map;
        uncertainty.noise_rms_nm = map_noise_rms_nm(map.x_mm(), map.y_mm(), map.z_nm());
    }
    uncertainty
}

/// Runs the solver on prepared inputs ([`Setup::solve`]: the acceleration-limited SCP with
/// `[machine] a_max_mm_per_s2`, the dwell solver otherwise), builds the report from the outcome
/// and asks the engine for the program of the job's machine for the plan
/// ([`Setup::program_check`]; with a robust plan, the nominal plan beside it,
/// [`Setup::compare_with_nominal`]).
pub fn solve(prepared: Prepared, job: &Job, observer: &dyn Observer) -> Result<Solved> {
    let outcome = prepared.setup.solve(&prepared.problem, observer)?;
    let paying = prepared
        .setup
        .plan_that_pays(outcome, &reading_uncertainty(&prepared), observer)
        .map_err(Error::Solver)?;
    let outcome = paying.outcome.clone();
    let mut report = report_of(&prepared, &outcome);
    if let Some(w) = executed_integration_warning(&outcome) {
        report.warnings.push(w);
    }
    if prepared.setup.settings.robust {
        let c = prepared
            .setup
            .compare_with_nominal(&prepared.problem, &outcome, observer)?;
        report.robust = Some(RobustReport {
            planned: c.planned,
            weighting: prepared.setup.settings.robust_weighting,
            scenario_weights: prepared
                .scenario_weights
                .clone()
                .unwrap_or_else(|| vec![1.0; robust::SCENARIO_COUNT]),
            nominal_plan_rms_after_nm: c.nominal_plan_rms_after_nm,
            nominal_plan_sensitivity: c.nominal_plan_sensitivity,
        });
    }
    report.set_expected(&paying);
    let program_check = prepared.setup.program_check(&outcome, &job.nc_settings());
    Ok(Solved {
        prepared,
        outcome,
        report,
        program_check,
    })
}

/// A warning where the executed residual is not resolved by its own integration: the program's
/// removal integrated at half the step ([`preston_solver::setup::IntegrationResolution`], computed
/// once by the engine) moves the residual by more than the residual quoted, so the figure is
/// known only to that change, whatever the solver's status says (a TIF cut where its rate is not
/// zero, or a grid TIF sampled near its own pitch).
fn executed_integration_warning(outcome: &Outcome) -> Option<String> {
    let Some(Ok(e)) = &outcome.executed else {
        return None;
    };
    let r = e.resolution.as_ref()?;
    (r.rms_change_nm > e.after.rms_nm).then(|| {
        format!(
            "the executed residual {:.3} nm RMS is not resolved: the program's removal \
             integrated at half the {:.4} mm step moves it by {:.3} nm RMS; the plan is known only \
             to about that (preston simulate --program --sample-step-mm settles it)",
            e.after.rms_nm, r.sample_step_mm, r.rms_change_nm
        )
    })
}

/// The report of a solve, from the prepared set-up and the outcome (nothing recomputed).
fn report_of(prepared: &Prepared, outcome: &Outcome) -> Report {
    let solution = &outcome.solution;
    let mut report = Report::with_feeds(
        &prepared.problem,
        solution,
        &outcome.residual_nm,
        &outcome.feeds_mm_per_min,
        prepared.skipped_rows,
        prepared.build_seconds,
    );
    report.warnings.clone_from(&prepared.warnings);
    report.notes.clone_from(&prepared.notes);
    // The problem's rows beyond the map are the edge model's, or other scenarios' blocks.
    report.edge_points = prepared.edge_points;
    report.edge = prepared.setup.edge.method;
    report.map_input = Some(prepared.map_input.clone());
    report.set_machine(&outcome.schedule, outcome.accel.as_ref());
    report.dwell_outside_map_s = Some(outcome.dwell_outside_map_s);
    report.operator_error = outcome.approximation;
    if let Some(a) = outcome.approximation.filter(|a| a.exceeds_tolerance()) {
        report.warnings.push(a.warning());
    }
    report.influence = Some(prepared.setup.influence_model());
    report.sensitivity = outcome.sensitivity;
    report.raster = prepared.setup.raster;
    match &outcome.executed {
        Some(Ok(e)) => {
            let planned = report.rms_after_nm;
            report.executed = Some(ExecutedReport {
                a_max_mm_per_s2: e.a_max_mm_per_s2,
                rms_after_nm: e.after.rms_nm,
                pv_after_nm: e.after.pv_nm,
                rms_ratio_to_plan: e.after.rms_nm / planned,
                stretch_time_s: e.run.check.executed_total_s,
                max_stretch_error_rel: e.run.check.max_relative_error,
                stretches_over_5_percent: e.run.check.over_5_percent,
                correction_passes: e.correction_passes,
                integration: e.resolution,
            });
            // The plan's prediction is the program as executed; the model's residual is kept.
            report.model = Some(ResidualFigures {
                rms_nm: report.rms_after_nm,
                pv_nm: report.pv_after_nm,
            });
            report.rms_after_nm = e.after.rms_nm;
            report.pv_after_nm = e.after.pv_nm;
        }
        Some(Err(e)) => report
            .warnings
            .push(format!("the plan cannot be written as a program: {e}")),
        None => {}
    }
    report
}

/// Writes `dwell.csv`, `residual.csv` and `report.json` (and `residual_model.csv` where the
/// solve executed its program, [`crate::residual`]) into `out_dir` (created if needed). All are
/// fully written to temporary files before any is renamed into place.
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
    write_solve_outputs(
        solved,
        out_dir,
        &OutputOptions {
            figures,
            plots: figures.is_some(),
            ..OutputOptions::default()
        },
    )
}

/// The residual the headline states ([`crate::residual`]): the executed program's where the
/// solve executed one, else the model's at the programmed feeds.
pub const RESIDUAL_CSV: &str = "residual.csv";
/// The model's residual at the programmed feeds, written beside [`RESIDUAL_CSV`] where that one
/// is the executed program's.
pub const RESIDUAL_MODEL_CSV: &str = "residual_model.csv";

/// What a solve writes beside `dwell.csv`, `residual.csv` and `report.json`.
#[derive(Debug, Clone, Default)]
pub struct OutputOptions {
    /// The raster direction and pitch of the figures (their PSD's axis and marker); figures are
    /// drawn when `plots` or `html` asks for them.
    pub figures: Option<(LineAxis, Option<f64>)>,
    /// Write the figure files (PNG) and the PSD tables.
    pub plots: bool,
    /// Write `report.html` ([`crate::html`]) with this provenance, the figures embedded.
    pub html: Option<crate::html::Provenance>,
    /// How the figures are drawn.
    pub style: crate::figures::FigureStyle,
    /// Replace an earlier solve's outputs: remove, with the commit, the files of
    /// [`is_solve_output`] in the output directory that this solve does not write, except the
    /// paths listed (the run's inputs). `None`: other files are left as they are.
    pub replace_earlier: Option<Vec<PathBuf>>,
}

/// Whether `name` is the name of a file a solve writes into its output directory (single or
/// several tools, with every figure and table option, in either figure format): what a later
/// solve into the same directory replaces ([`OutputOptions::replace_earlier`]).
pub fn is_solve_output(name: &str) -> bool {
    const FILES: [&str; 8] = [
        "dwell.csv",
        RESIDUAL_CSV,
        RESIDUAL_MODEL_CSV,
        "report.json",
        "report.html",
        "psd.csv",
        "psd_2d.csv",
        "psd_azimuthal.csv",
    ];
    if FILES.contains(&name) {
        return true;
    }
    if let Some(k) = name
        .strip_prefix("dwell_tool")
        .and_then(|r| r.strip_suffix(".csv"))
    {
        return !k.is_empty() && k.bytes().all(|b| b.is_ascii_digit());
    }
    match name.rsplit_once('.') {
        Some((stem, "png" | "svg")) => {
            crate::figures::SOLVE_FIGURES.contains(&stem)
                || crate::figures::tool_figure(stem, "dwell")
                || crate::figures::tool_figure(stem, "feed")
        }
        _ => false,
    }
}

/// Writes a solve's outputs as `options` asks: all staged first and committed together (the
/// page, when asked, embeds the figures whether or not their files are written). Returns notes
/// on figures left out.
pub fn write_solve_outputs(
    solved: &Solved,
    out_dir: &Path,
    options: &OutputOptions,
) -> Result<Vec<String>> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let draw = options.plots || options.html.is_some();
    let axis = options.figures.unwrap_or((LineAxis::X, None));
    let (figures, notes) = if draw {
        crate::figures::stage_solve_figures_with(
            &solved.prepared.setup,
            &solved.outcome,
            out_dir,
            axis.0,
            axis.1,
            &options.style,
        )?
    } else {
        (Vec::new(), Vec::new())
    };
    let p = &solved.prepared;
    let (map, path) = (p.map(), p.path());
    let o = &solved.outcome;
    let delivered = solved.delivered();
    let mut staged = vec![
        stage_dwell_csv(
            &out_dir.join("dwell.csv"),
            path.x_mm(),
            path.y_mm(),
            p.ds_mm(),
            &o.solution.dwell_s,
            &o.feeds_mm_per_min,
        )?,
        stage_residual_csv(
            &out_dir.join(RESIDUAL_CSV),
            map.x_mm(),
            map.y_mm(),
            map.z_nm(),
            delivered.removal_nm,
            &delivered.residual_nm,
        )?,
        stage_report(&out_dir.join("report.json"), &solved.report)?,
    ];
    if delivered.executed {
        // The model's residual at the programmed feeds, named as what it is.
        staged.push(stage_residual_csv(
            &out_dir.join(RESIDUAL_MODEL_CSV),
            map.x_mm(),
            map.y_mm(),
            map.z_nm(),
            &o.removal_nm,
            &o.residual_nm,
        )?);
    }
    commit_solve_outputs(staged, figures, &solved.report, &notes, out_dir, options)?;
    Ok(notes)
}

/// Commits a solve's staged files, all or none: with `options.html` the report page (the
/// figures embedded), with `options.plots` the figures, replacing an earlier solve's outputs
/// where `options.replace_earlier` says so. One tool's outputs and several tools' share it.
pub(crate) fn commit_solve_outputs(
    mut staged: Vec<crate::atomic::Staged>,
    figures: Vec<crate::atomic::Staged>,
    report: &Report,
    notes: &[String],
    out_dir: &Path,
    options: &OutputOptions,
) -> Result<()> {
    if let Some(provenance) = &options.html {
        staged.push(crate::html::stage_report_page(
            &out_dir.join("report.html"),
            report,
            provenance,
            &figures,
            notes,
        )?);
    }
    if options.plots {
        staged.extend(figures);
    }
    match &options.replace_earlier {
        Some(keep) => {
            crate::atomic::commit_replacing(staged, out_dir, &is_solve_output, keep)?;
            Ok(())
        }
        None => commit_all(staged),
    }
}
