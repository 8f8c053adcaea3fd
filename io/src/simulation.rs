//! Simulation and loop outputs: `preston simulate` (the removal a dwell program produces, in the
//! solver's file formats) and the files of `preston iterate` (convergence table, last run, plots).
//!
//! This module only reads the inputs and writes the outputs; the simulation itself (a plan's or
//! an executed program's motion and the removal it leaves) is the solver's
//! (`preston_solver::simulate`).

use crate::atomic::{commit_all, stage, Staged};
use crate::error::{Error, Result};
use crate::figures::FigureStyle;
use crate::machine::{read_dwell_times, DwellTimes};
use crate::metrology::{MapRead, MapSource};
use crate::plots::{
    stage_convergence_plot, stage_map_plot, stage_map_plot_scaled, stage_map_plot_with,
    stage_path_plot, ColourScale,
};
use crate::report::{centred_residual_nm, feeds_mm_per_min, Report, SolverLabel};
use crate::writers::{stage_dwell_csv, stage_report, stage_residual_csv};
use preston_solver::dwell::accel::AccelLimits;
use preston_solver::dwell::{FeedLimits, Problem};
use preston_solver::influence::Stretches;
use preston_solver::influence::{InfluenceModel, TifFrame};
use preston_solver::iterate::{IterationRecord, LoopOutcome};
use preston_solver::machine::feeds::FeedSchedule;
use preston_solver::machine::gcode::dialect::Dialect;
use preston_solver::machine::gcode::motion::{Kinematics, StretchCheck};
use preston_solver::machine::gcode::program::{Program, MAX_PROGRAM_BYTES};
use preston_solver::machine::machinability::dwell_outside_map_s;
use preston_solver::machine::PartGeometry;
use preston_solver::map::HeightMap;
use preston_solver::observer::Observer;
use preston_solver::path::DwellPath;
use preston_solver::setup::sensitivity::Sensitivity;
use preston_solver::setup::{
    Choices, DwellPoints, Setup, SetupData, SetupError, SetupInput, TifModel,
};
use preston_solver::simulate::program::ProgramRun;
use preston_solver::simulate::{removal_nm, sample_program, Motion, SampledProgram};
use preston_solver::surface::Surface;
use preston_solver::tif::Tif;
use std::io::Write;
use std::path::Path;
use std::time::Instant;

/// A simulated run: inputs, removal and report.
#[derive(Debug, Clone)]
pub struct Simulated {
    /// The error map.
    pub map: HeightMap,
    /// The dwell path.
    pub path: DwellPath,
    /// Path length per dwell point, mm.
    pub ds_mm: Vec<f64>,
    /// Dwell times, s.
    pub dwell_s: Vec<f64>,
    /// Removal at the map points, nm.
    pub removal_nm: Vec<f64>,
    /// The report (same keys as `preston solve`; `solver` is `simulate`).
    pub report: Report,
}

/// How a dwell plan is run on the map by [`simulate`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlanMotion {
    /// The tool swept along each dwell point's stretch of path at the point's feed, the TIF
    /// averaged along the stretch exactly as the solver's swept influence model (its default)
    /// does ([`preston_solver::influence::model::swept`]): the removal the plan itself predicts.
    Swept,
    /// One of the simulator's own motions: the tool dwelling at the points (the solver's point
    /// influence model), or sweeping the path with a number of midpoint samples per point.
    Sampled(Motion),
}

/// Simulates the dwell program in `dwell_file` (`x_mm,y_mm,dwell_s`, as `preston solve` writes it)
/// on the map with `tif` under `motion`. With `limits`, `max_bound_violation_s` reports how far
/// the program is outside the feed limits.
pub fn simulate(
    map_source: &MapSource,
    tif: &Tif,
    dwell_file: &Path,
    motion: PlanMotion,
    limits: Option<&FeedLimits>,
    observer: &dyn Observer,
) -> Result<Simulated> {
    let start = Instant::now();
    let MapRead { map, input } = map_source.read()?;
    let map_file = map_source.file.as_deref().unwrap_or(Path::new("map"));
    let DwellTimes { path, dwell_s } = read_dwell_times(dwell_file)?;
    // The plan through the set-up stage, evaluated as given: the feed limits (if any) for the
    // bounds the report checks, the assembled `R` over the map alone, no solve.
    let at_fault = |e: SetupError| match e.input {
        SetupInput::Map => Error::engine(map_file, e.source),
        SetupInput::None => Error::Solver(e.source),
        _ => Error::engine(dwell_file, e.source),
    };
    let mut choices = Choices::evaluation(limits.copied());
    if motion == PlanMotion::Swept {
        choices.settings.influence = InfluenceModel::Swept;
    }
    let checked = choices.check(observer).map_err(at_fault)?;
    let mut setup = Setup::resolve(
        checked,
        SetupData {
            map,
            tif: tif.clone(),
            dwell: DwellPoints::Given(path),
            surface: None,
            warm_start_s: None,
        },
        observer,
    )
    .map_err(at_fault)?;
    if motion == PlanMotion::Swept && setup.swept.is_none() {
        // The solver's stretches and their quadrature (the set-up builds them itself only for
        // a plan with feed limits).
        let stretches = Stretches::of_path(&setup.path, default_sample_step_mm(&setup.tif))
            .map_err(|e| Error::engine(dwell_file, e))?;
        let kernel = stretches.dominant_kernel(setup.tif.clone());
        setup.swept = Some((stretches, kernel));
    }
    let problem = setup.problem(observer).map_err(at_fault)?.problem;
    let build_seconds = start.elapsed().as_secs_f64();
    let sim_start = Instant::now();
    let removal = match motion {
        PlanMotion::Swept | PlanMotion::Sampled(Motion::Discrete) => {
            setup.removal_of(&problem, &dwell_s, observer)?
        }
        PlanMotion::Sampled(m @ Motion::Continuous { .. }) => removal_nm(
            setup.map.x_mm(),
            setup.map.y_mm(),
            &setup.path,
            &dwell_s,
            tif,
            m,
            observer,
        )
        .map_err(|e| Error::engine(dwell_file, e))?,
    };
    // The same motion's removal with the TIF perturbed.
    let samples = match (motion, &setup.swept) {
        (PlanMotion::Swept, Some((stretches, _))) => {
            Ok(swept_samples(&setup.path, stretches, &dwell_s))
        }
        (PlanMotion::Sampled(m), _) => sample_program(&setup.path, &dwell_s, m),
        (PlanMotion::Swept, None) => sample_program(&setup.path, &dwell_s, Motion::Discrete),
    };
    let sensitivity = samples
        .and_then(|samples| setup.sensitivity_of(&samples, &removal, observer))
        .map_err(|e| Error::engine(dwell_file, e))?;
    let label = match motion {
        PlanMotion::Swept => SolverLabel::SimulateSwept,
        PlanMotion::Sampled(Motion::Discrete) => SolverLabel::Simulate,
        PlanMotion::Sampled(Motion::Continuous { samples_per_point }) => {
            SolverLabel::SimulateContinuous { samples_per_point }
        }
    };
    assemble(
        MapRead {
            map: setup.map,
            input,
        },
        dwell_file,
        Sweep {
            path: setup.path,
            dwell_s,
            removal_nm: removal,
            problem,
            label,
            sensitivity,
        },
        build_seconds,
        sim_start,
    )
}

/// The motion of dwell times `dwell_s` on `path` under the swept model: each dwell point's
/// stretch samples, each the piece it stands for, carrying its dwell in proportion to their
/// weights.
fn swept_samples(path: &DwellPath, stretches: &Stretches, dwell_s: &[f64]) -> SampledProgram {
    let (mut x, mut y, mut t, mut h) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (j, &tj) in dwell_s.iter().enumerate() {
        for (&[dx, dy, w], &half) in stretches.of(j).iter().zip(stretches.pieces_of(j)) {
            x.push(path.x_mm()[j] + dx);
            y.push(path.y_mm()[j] + dy);
            t.push(tj * w);
            h.push(half);
        }
    }
    SampledProgram {
        x_mm: x,
        y_mm: y,
        dwell_s: t,
        half_mm: h,
    }
}

/// A simulated sweep on the map: the dwell points it is reported on, their (executed) dwell, the
/// removal and the influence matrix of the points.
struct Sweep {
    path: DwellPath,
    dwell_s: Vec<f64>,
    removal_nm: Vec<f64>,
    /// The points' problem (`R`, the map's heights, the bounds), for the report.
    problem: Problem,
    label: SolverLabel,
    /// The residual of the same motion with the TIF perturbed.
    sensitivity: Sensitivity,
}

/// The report of a simulated sweep (same keys as `preston solve`).
fn assemble(
    map: MapRead,
    dwell_file: &Path,
    sweep: Sweep,
    build_seconds: f64,
    sim_start: Instant,
) -> Result<Simulated> {
    let Sweep {
        path,
        dwell_s,
        removal_nm: removal,
        problem,
        label,
        sensitivity,
    } = sweep;
    let ds_mm = path.ds_mm();
    let feeds = feeds_mm_per_min(&ds_mm, &dwell_s);
    let mut report = Report::of_dwell(
        &problem,
        &dwell_s,
        &removal,
        &feeds,
        map.input.invalid_points,
        build_seconds,
    );
    report.solve_seconds = sim_start.elapsed().as_secs_f64();
    report.map_input = Some(map.input.clone());
    report.solver = label;
    report.sensitivity = Some(sensitivity);
    // The removal's model: the tool at the points for discrete motion, swept otherwise.
    report.influence = Some(match label {
        SolverLabel::Simulate => InfluenceModel::Point,
        _ => InfluenceModel::Swept,
    });
    report.dwell_outside_map_s = Some(dwell_outside_map_s(
        map.map.x_mm(),
        map.map.y_mm(),
        path.x_mm(),
        path.y_mm(),
        &dwell_s,
    ));
    if dwell_s
        .iter()
        .zip(&ds_mm)
        .all(|(t, d)| *t > 0.0 || *d == 0.0)
    {
        let schedule = FeedSchedule::new(
            &path,
            &dwell_s,
            None,
            AccelLimits::default().corner_angle_deg,
        )
        .map_err(|e| Error::engine(dwell_file, e))?;
        report.set_machine(&schedule, None);
    }
    Ok(Simulated {
        map: map.map,
        path,
        ds_mm,
        dwell_s,
        removal_nm: removal,
        report,
    })
}

/// Options of [`simulate_program`].
#[derive(Clone)]
pub struct ProgramOptions<'a> {
    /// Dialect to read the program in (default: the one its header names, else ISO).
    pub dialect: Option<Dialect>,
    /// How the controller moves.
    pub kinematics: Kinematics,
    /// Largest arc length of a removal sample, mm (default: [`default_sample_step_mm`]).
    pub sample_step_mm: Option<f64>,
    /// The part's design surface and the tool-centre offset along its normal (tool radius), mm:
    /// tool centres are mapped back to contact points and each contact sample applies the TIF
    /// in its tangent frame, oriented by `tif_frame`; none: a flat part, the program's X, Y the
    /// contact points.
    pub part: Option<(&'a Surface, f64)>,
    /// How the TIF is oriented in each tangent plane on a curved part.
    pub tif_frame: TifFrame,
    /// How the TIF acts on the part: one TIF, or a Hertz TIF at each contact sample from the
    /// design surface's curvature there (needs `part`).
    pub tif_model: TifModel,
}

pub use preston_solver::setup::default_sample_step_mm;

/// A simulated program: the simulation on the map plus the executed dwell per stretch.
#[derive(Debug, Clone)]
pub struct ProgramSimulated {
    /// Removal, residual and report (the dwell points are the program's marked points, their
    /// dwell the executed stretch times; without markers, one point per feed move or pause, its
    /// executed time).
    pub sim: Simulated,
    /// Planned dwell per marked stretch, s.
    pub planned_dwell_s: Vec<f64>,
    /// Executed against planned.
    pub check: StretchCheck,
    /// Executed time of the feed blocks and pauses, s.
    pub executed_time_s: f64,
    /// Removal samples used.
    pub samples: usize,
}

/// Reads a G-code program file (a regular file within the size limit, UTF-8) and parses it in
/// `dialect`, else the dialect its header names, else ISO.
pub fn read_program(program_file: &Path, dialect: Option<Dialect>) -> Result<Program> {
    let meta = std::fs::metadata(program_file).map_err(|e| Error::io(program_file, e))?;
    if !meta.is_file() {
        return Err(Error::engine(
            program_file,
            preston_solver::Error::invalid("program", "not a regular file"),
        ));
    }
    if meta.len() > MAX_PROGRAM_BYTES as u64 {
        return Err(Error::engine(
            program_file,
            preston_solver::Error::invalid(
                "program",
                format!(
                    "{} bytes is more than the {MAX_PROGRAM_BYTES}-byte limit",
                    meta.len()
                ),
            ),
        ));
    }
    let bytes = crate::limits::read_regular(
        program_file,
        preston_solver::budget::limit_bytes(),
        "program",
    )?;
    let text = String::from_utf8(bytes).map_err(|e| {
        Error::engine(
            program_file,
            preston_solver::Error::invalid(
                "program",
                format!(
                    "not text (invalid UTF-8 at byte {})",
                    e.utf8_error().valid_up_to()
                ),
            ),
        )
    })?;
    let dialect = dialect
        .or_else(|| Program::detect_dialect(&text))
        .unwrap_or_default();
    let program = Program::parse(&text, dialect).map_err(|e| Error::engine(program_file, e))?;
    Ok(program)
}

/// Simulates the G-code program in `program_file` as the machine runs it ([`preston_solver::machine::gcode`]):
/// reads it back, then through the set-up stage as `simulate --dwell` ([`Choices::evaluation`],
/// the program's marked points as the dwell points, [`DwellPoints::of_program`]):
/// [`Setup::run_program`] executes its motion and integrates the TIF along the contact motion,
/// and the report is on the map in `map_file`.
pub fn simulate_program(
    map_source: &MapSource,
    tif: &Tif,
    program_file: &Path,
    options: ProgramOptions,
    observer: &dyn Observer,
) -> Result<ProgramSimulated> {
    let start = Instant::now();
    let map = map_source.read()?;
    let map_file = map_source.file.as_deref().unwrap_or(Path::new("map"));
    let program = read_program(program_file, options.dialect)?;
    let at_fault = |e: SetupError| match e.input {
        SetupInput::Map => Error::engine(map_file, e.source),
        SetupInput::None => Error::Solver(e.source),
        _ => Error::engine(program_file, e.source),
    };
    let dwell = DwellPoints::of_program(&program).map_err(|e| Error::engine(program_file, e))?;
    let checked = Choices {
        tif_frame: options.tif_frame,
        tif_model: options.tif_model.clone(),
        ..Choices::evaluation(None)
    }
    .check(observer)
    .map_err(at_fault)?;
    let MapRead { map, input } = map;
    let setup = Setup::resolve(
        checked,
        SetupData {
            map,
            tif: tif.clone(),
            dwell,
            surface: options.part.map(|(s, _)| s.clone()),
            warm_start_s: None,
        },
        observer,
    )
    .map_err(at_fault)?;
    let part = options.part.map(|(s, r)| (s as &dyn PartGeometry, r));
    let run = setup
        .run_program(
            &program,
            options.kinematics,
            options.sample_step_mm,
            part,
            observer,
        )
        .map_err(|e| Error::engine(program_file, e))?;
    let integration = setup
        .program_resolution(
            &program,
            options.kinematics,
            options.sample_step_mm,
            part,
            &run,
            observer,
        )
        .map_err(|e| Error::engine(program_file, e))?;
    let ProgramRun {
        executed,
        check,
        removal_nm: removal,
        samples: n_samples,
        contact,
        ..
    } = run;
    let problem = setup.problem(observer).map_err(at_fault)?.problem;
    let build_seconds = start.elapsed().as_secs_f64();
    // The executed motion's removal with the TIF perturbed.
    let sensitivity = setup
        .sensitivity_of(&contact, &removal, observer)
        .map_err(|e| Error::engine(program_file, e))?;
    let label = match options.kinematics {
        Kinematics::ProgrammedFeed => SolverLabel::SimulateProgram,
        Kinematics::Trapezoidal {
            a_max_mm_per_s2, ..
        } => SolverLabel::SimulateProgramAtLimit { a_max_mm_per_s2 },
    };
    let mut sim = assemble(
        MapRead {
            map: setup.map,
            input,
        },
        program_file,
        Sweep {
            path: setup.path,
            dwell_s: if program.stretches.is_empty() {
                program
                    .contact_blocks()
                    .map(|k| executed.profiles[k].time_s)
                    .collect()
            } else {
                executed.stretch_time_s.clone()
            },
            sensitivity,
            removal_nm: removal,
            problem,
            label,
        },
        build_seconds,
        Instant::now(),
    )?;
    sim.report.integration = integration;
    Ok(ProgramSimulated {
        sim,
        planned_dwell_s: program
            .stretches
            .iter()
            .map(|s| s.planned_dwell_s)
            .collect(),
        check,
        executed_time_s: executed.total_time_s,
        samples: n_samples,
    })
}

/// Header of `executed_dwell.csv` (a contract).
pub const EXECUTED_DWELL_HEADER: &str = "x_mm,y_mm,planned_dwell_s,executed_dwell_s";

/// Writes the outputs of [`simulate_program`]: those of [`write_simulation`] plus, for a program
/// with DWELL markers, `executed_dwell.csv`, all committed together.
pub fn write_program_simulation(
    sim: &ProgramSimulated,
    out_dir: &Path,
    plots: Option<FigureStyle>,
) -> Result<()> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let s = &sim.sim;
    if sim.check.stretches == 0 {
        return write_simulation_with(s, out_dir, plots, Vec::new());
    }
    let executed = stage(&out_dir.join("executed_dwell.csv"), |w: &mut dyn Write| {
        writeln!(w, "{EXECUTED_DWELL_HEADER}")?;
        for k in 0..s.dwell_s.len() {
            writeln!(
                w,
                "{},{},{},{}",
                s.path.x_mm()[k],
                s.path.y_mm()[k],
                sim.planned_dwell_s[k],
                s.dwell_s[k]
            )?;
        }
        Ok(())
    })?;
    let mut extra = vec![executed];
    if let Some(style) = plots {
        let index = |v: &[f64]| -> Vec<(f64, f64)> {
            v.iter().enumerate().map(|(k, t)| (k as f64, *t)).collect()
        };
        extra.push(crate::plots::stage_series_plot(
            &style.path(out_dir, "dwell_planned_vs_executed"),
            &format!(
                "Dwell per point: planned {:.1} s, executed {:.1} s in the stretches",
                sim.planned_dwell_s.iter().sum::<f64>(),
                s.dwell_s.iter().sum::<f64>()
            ),
            "dwell point (path order)",
            "dwell (s)",
            &[
                ("planned", index(&sim.planned_dwell_s)),
                ("executed", index(&s.dwell_s)),
                (
                    "executed - planned",
                    index(
                        &s.dwell_s
                            .iter()
                            .zip(&sim.planned_dwell_s)
                            .map(|(e, p)| e - p)
                            .collect::<Vec<_>>(),
                    ),
                ),
            ],
        )?);
    }
    write_simulation_with(s, out_dir, plots, extra)
}

/// Writes `residual.csv` and `report.json` of a simulation into `out_dir`; with `plots`, also
/// the figures `error_before`, `removal`, `residual` and the PSDs of
/// [`crate::figures::stage_psd_figures`] (along x) in that style, and for a program
/// `dwell_planned_vs_executed`.
pub fn write_simulation(sim: &Simulated, out_dir: &Path, plots: Option<FigureStyle>) -> Result<()> {
    write_simulation_with(sim, out_dir, plots, Vec::new())
}

/// [`write_simulation`] with `extra` staged files committed together with the CSVs.
fn write_simulation_with(
    sim: &Simulated,
    out_dir: &Path,
    plots: Option<FigureStyle>,
    extra: Vec<Staged>,
) -> Result<()> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let residual = centred_residual_nm(sim.map.z_nm(), &sim.removal_nm);
    let mut staged = extra;
    staged.extend([
        stage_residual_csv(
            &out_dir.join("residual.csv"),
            sim.map.x_mm(),
            sim.map.y_mm(),
            sim.map.z_nm(),
            &sim.removal_nm,
            &residual,
        )?,
        stage_report(&out_dir.join("report.json"), &sim.report)?,
    ]);
    if let Some(style) = plots {
        let (x, y) = (sim.map.x_mm(), sim.map.y_mm());
        staged.push(stage_map_plot_with(
            &style.path(out_dir, "error_before"),
            "Surface error before",
            "nm",
            x,
            y,
            sim.map.z_nm(),
            style.color_limits,
        )?);
        staged.push(stage_map_plot(
            &style.path(out_dir, "removal"),
            "Simulated removal",
            "nm",
            x,
            y,
            &sim.removal_nm,
        )?);
        staged.push(stage_map_plot_scaled(
            &style.path(out_dir, "residual"),
            "Residual (piston removed)",
            "nm",
            x,
            y,
            &residual,
            style.color_limits,
            ColourScale::Diverging,
        )?);
        // A map off a lattice has no PSD; the other figures are written all the same.
        let (psd, _left_out) = crate::figures::stage_psd_figures(
            out_dir,
            x,
            y,
            sim.map.z_nm(),
            &residual,
            preston_solver::psd::LineAxis::X,
            None,
            style.format,
        )?;
        staged.extend(psd);
    }
    commit_all(staged)
}

/// Header of `convergence.csv` (a contract: checks outside the project read it).
pub const CONVERGENCE_HEADER: &str = "iteration,pv_nm,rms_nm,max_abs_nm,mean_abs_nm,time_s";

/// Stages `convergence.csv`: one row per measurement, then as extra columns the prediction of
/// the next measurement, the TIF rate error applied, the rate factor the run was planned with and
/// its relative uncertainty, the RMS of the measured error outside the correctable band, and
/// (when the loop calibrates each run) the width factor, offset and drift the run was planned
/// with.
pub fn stage_convergence_csv(path: &Path, records: &[IterationRecord]) -> Result<Staged> {
    stage(path, |w: &mut dyn Write| {
        writeln!(
            w,
            "{CONVERGENCE_HEADER},predicted_rms_nm,tif_rate_error,rate_factor_estimate,\
             rate_factor_sigma,uncorrectable_rms_nm,width_factor_estimate,offset_x_mm_estimate,\
             offset_y_mm_estimate,drift_per_hour_estimate"
        )?;
        for r in records {
            let opt = |v: Option<f64>| v.map(|x| format!("{x}")).unwrap_or_default();
            writeln!(
                w,
                "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
                r.iteration,
                r.pv_nm,
                r.rms_nm,
                r.max_abs_nm,
                r.mean_abs_nm,
                r.time_s,
                opt(r.predicted_rms_nm),
                opt(r.tif_rate_error),
                opt(r.rate_factor_estimate),
                opt(r.rate_factor_sigma),
                opt(r.uncorrectable_rms_nm),
                opt(r.width_factor_estimate),
                opt(r.offset_x_mm_estimate),
                opt(r.offset_y_mm_estimate),
                opt(r.drift_per_hour_estimate)
            )?;
        }
        Ok(())
    })
}

/// Writes the outputs of a polishing loop into `out_dir`: `convergence.csv`, the last run's
/// `dwell.csv` and `measured.csv` (`x_mm,y_mm,z_nm`, the map it was planned on), the final
/// measured map `final_measured.csv` and `report.html`; with `plots`, the figures of the error
/// before the last run, the predicted removal, the residual, the dwell-time and feed maps, the
/// path and the convergence, in `style` (the page embeds them in every run).
pub fn write_loop(
    outcome: &LoopOutcome,
    out_dir: &Path,
    plots: bool,
    style: FigureStyle,
) -> Result<()> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let mut staged = vec![stage_convergence_csv(
        &out_dir.join("convergence.csv"),
        &outcome.records,
    )?];
    let fin = &outcome.final_measured;
    staged.push(crate::writers::stage_map_csv(
        &out_dir.join("final_measured.csv"),
        fin.x_mm(),
        fin.y_mm(),
        fin.z_nm(),
    )?);
    if let Some(run) = &outcome.last_run {
        let ds = run.path.ds_mm();
        let feeds = feeds_mm_per_min(&ds, &run.dwell_s);
        staged.push(stage_dwell_csv(
            &out_dir.join("dwell.csv"),
            run.path.x_mm(),
            run.path.y_mm(),
            &ds,
            &run.dwell_s,
            &feeds,
        )?);
        staged.push(crate::writers::stage_map_csv(
            &out_dir.join("measured.csv"),
            run.measured.x_mm(),
            run.measured.y_mm(),
            run.measured.z_nm(),
        )?);
    }
    // The figures are drawn for the page in every run, and written as files with `plots`.
    let figures = stage_loop_plots(outcome, out_dir, style)?;
    staged.push(stage_loop_page(outcome, out_dir, &figures)?);
    if plots {
        staged.extend(figures);
    }
    commit_all(staged)
}

/// Stages `report.html` of a loop: the convergence table, the inner steps that did not converge
/// and the figures embedded ([`crate::html::loop_page`]).
fn stage_loop_page(outcome: &LoopOutcome, out_dir: &Path, figures: &[Staged]) -> Result<Staged> {
    let rows: Vec<crate::html::LoopRow> = outcome
        .records
        .iter()
        .map(|r| crate::html::LoopRow {
            iteration: r.iteration,
            pv_nm: r.pv_nm,
            rms_nm: r.rms_nm,
            time_s: r.time_s,
            predicted_rms_nm: r.predicted_rms_nm,
        })
        .collect();
    let failures: Vec<String> = outcome
        .not_converged
        .iter()
        .map(|f| {
            format!(
                "iteration {}: {:?} ended {} ({})",
                f.iteration, f.step, f.status, f.detail
            )
        })
        .collect();
    let mut embedded = Vec::new();
    for f in figures {
        let name = f
            .dest()
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        embedded.push(crate::html::Figure::from_staged(
            f,
            crate::figures::caption(&name),
        )?);
    }
    let provenance = crate::html::Provenance {
        command: Some(crate::html::Provenance::command_line()),
        ..Default::default()
    };
    let page = crate::html::loop_page(
        "Preston polishing loop",
        &rows,
        outcome.met_spec,
        &failures,
        &crate::html::PageExtras {
            provenance: Some(&provenance),
            figures: &embedded,
            notes: &[],
        },
    );
    crate::html::stage_html(&out_dir.join("report.html"), &page)
}

fn stage_loop_plots(
    outcome: &LoopOutcome,
    out_dir: &Path,
    style: FigureStyle,
) -> Result<Vec<Staged>> {
    let mut staged = Vec::new();
    let rec = &outcome.records;
    let series = |f: fn(&IterationRecord) -> f64| -> Vec<(f64, f64)> {
        rec.iter().map(|r| (r.iteration as f64, f(r))).collect()
    };
    staged.push(stage_convergence_plot(
        &style.path(out_dir, "convergence"),
        "Form error per iteration",
        "nm",
        &[
            ("PV", series(|r| r.pv_nm)),
            ("RMS", series(|r| r.rms_nm)),
            ("mean |dev|", series(|r| r.mean_abs_nm)),
        ],
    )?);
    let fin = &outcome.final_measured;
    staged.push(stage_map_plot_with(
        &style.path(out_dir, "final_error"),
        "Measured form error after the last run",
        "nm",
        fin.x_mm(),
        fin.y_mm(),
        fin.z_nm(),
        style.color_limits,
    )?);
    if let Some(run) = &outcome.last_run {
        let m = &run.measured;
        let residual = centred_residual_nm(&run.target_nm, &run.predicted_removal_nm);
        staged.push(stage_map_plot_with(
            &style.path(out_dir, "error_before"),
            "Measured form error before the last run",
            "nm",
            m.x_mm(),
            m.y_mm(),
            m.z_nm(),
            style.color_limits,
        )?);
        staged.push(stage_map_plot(
            &style.path(out_dir, "removal"),
            "Predicted removal",
            "nm",
            m.x_mm(),
            m.y_mm(),
            &run.predicted_removal_nm,
        )?);
        staged.push(stage_map_plot_scaled(
            &style.path(out_dir, "residual"),
            "Predicted residual (piston removed)",
            "nm",
            m.x_mm(),
            m.y_mm(),
            &residual,
            style.color_limits,
            ColourScale::Diverging,
        )?);
        let (px, py) = (run.path.x_mm(), run.path.y_mm());
        staged.push(stage_map_plot(
            &style.path(out_dir, "dwell"),
            "Dwell time",
            "s",
            px,
            py,
            &run.dwell_s,
        )?);
        let feeds = feeds_mm_per_min(&run.path.ds_mm(), &run.dwell_s);
        staged.push(stage_map_plot(
            &style.path(out_dir, "feed"),
            "Feed",
            "mm/min",
            px,
            py,
            &feeds,
        )?);
        staged.push(stage_path_plot(
            &style.path(out_dir, "path"),
            "Tool path",
            px,
            py,
        )?);
    }
    Ok(staged)
}
