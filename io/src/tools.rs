//! Several tools in one solve (`[[tool]]`, repeated `--tif`/`--dwell`): this module reads each
//! tool's TIF and path, hands them to the set-up stage
//! ([`preston_solver::setup::tools`]: the stacked problem and its solve), and builds the report
//! and writes the outputs.

use crate::error::{Error, Result};
use crate::figures::{stage_tool_figures, ToolFigureData};
use crate::job::{Job, TifSource};
use crate::pipeline::OutputOptions;
use crate::readers::read_dwell;
pub use crate::report::ToolReport;
use crate::report::{centred_residual_nm, feeds_mm_per_min, Report};
use crate::writers::{stage_dwell_csv, stage_report, stage_residual_csv};
use preston_solver::dwell::{FeedLimits, Solution};
use preston_solver::machine::feeds::FeedSchedule;
use preston_solver::map::{HeightMap, HeightStats};
use preston_solver::observer::Observer;
use preston_solver::psd::LineAxis;
pub use preston_solver::setup::tools::Tool;
use preston_solver::setup::tools::{ToolChoices, ToolsOutcome, ToolsSetup};
use preston_solver::setup::{SetupError, SetupInput};
use preston_solver::tif::Tif;
use std::path::Path;
use std::time::Instant;

/// A finished multi-tool solve.
#[derive(Debug, Clone)]
pub struct MultiSolved {
    /// The map.
    pub map: HeightMap,
    /// The tools.
    pub tools: Vec<Tool>,
    /// The solver's answer on the stacked problem (scaled dwell `u_k = w_k t_k`).
    pub solution: Solution,
    /// Each tool's dwell times, s.
    pub dwell_s: Vec<Vec<f64>>,
    /// Predicted removal of all tools at the map points, nm.
    pub removal_nm: Vec<f64>,
    /// Predicted residual at the map points about its mean, nm.
    pub residual_nm: Vec<f64>,
    /// The report (with `tools`).
    pub report: Report,
}

/// Whether the job names several tools (`[[tool]]`).
pub fn is_multi_tool(job: &Job) -> bool {
    !job.tool.is_empty()
}

fn load_tool_tif(src: &TifSource, job_path: &Path, k: usize) -> Result<Tif> {
    let input = src.resolve(job_path).map_err(|e| match e {
        Error::Job { file, why } => Error::Job {
            file,
            why: format!("tool {k}: {why}"),
        },
        e => e,
    })?;
    if src.curvature_dependent {
        return Err(Error::Job {
            file: job_path.to_path_buf(),
            why: format!(
                "tool {k}: several tools cannot be combined with a curvature-dependent TIF"
            ),
        });
    }
    crate::pipeline::load_tif_input(input, job_path)
}

/// Reads each `[[tool]]`'s TIF and path; the set-up stage checks the tools
/// ([`Tool::new`]); what a multi-tool solve supports is checked before ([`ToolChoices::check`]).
pub fn read_tools(job: &Job, job_path: &Path) -> Result<Vec<Tool>> {
    job.tool
        .iter()
        .enumerate()
        .map(|(i, spec)| {
            let k = i + 1;
            let tif = load_tool_tif(&spec.tif, job_path, k)?;
            let d = read_dwell(&spec.dwell)?;
            if d.path.len() < 2 {
                return Err(Error::Empty {
                    file: spec.dwell.clone(),
                    why: format!("tool {k}: a path needs at least two dwell points"),
                });
            }
            let v_max = spec
                .v_max_mm_per_min
                .or(job.machine.v_max_mm_per_min)
                .ok_or_else(|| Error::Job {
                    file: job_path.to_path_buf(),
                    why: format!("tool {k}: no v_max_mm_per_min (in [[tool]] or [machine])"),
                })?;
            let limits = FeedLimits {
                v_max_mm_per_min: v_max,
                v_min_mm_per_min: spec
                    .v_min_mm_per_min
                    .or(job.machine.v_min_mm_per_min)
                    .unwrap_or(0.0),
            };
            Tool::new(k, tif, d.path, limits, spec.time_weight.unwrap_or(1.0))
                .map_err(|e| Error::engine(job_path, e))
        })
        .collect()
}

/// Reads the map and tools, solves the stacked problem through the set-up stage and builds the
/// report.
pub fn solve_tools(job: &Job, job_path: &Path, observer: &dyn Observer) -> Result<MultiSolved> {
    let started = Instant::now();
    let map_path = job.map.file.as_deref().unwrap_or(job_path);
    let at_fault = |e: SetupError| match e.input {
        SetupInput::None => Error::Solver(e.source),
        SetupInput::Map => Error::engine(map_path, e.source),
        _ => Error::engine(job_path, e.source),
    };
    let checked = job
        .choices_with_feed(None)
        .map_err(|e| Error::engine(job_path, e))?
        .check(observer)
        .and_then(ToolChoices::check)
        .map_err(at_fault)?;
    if job.surface.file.is_some() {
        return Err(Error::Job {
            file: job_path.to_path_buf(),
            why: "several tools cannot be combined with a [surface] file".into(),
        });
    }
    if job.map.file.is_none() {
        return Err(Error::Job {
            file: job_path.to_path_buf(),
            why: "no map: set [map] file (or --map)".into(),
        });
    }
    let map_read = job.map.read()?;
    let tools = read_tools(job, job_path)?;
    let setup = ToolsSetup::resolve(&checked, map_read.map, tools).map_err(at_fault)?;
    let problem = setup.problem(observer).map_err(at_fault)?;
    let build_seconds = started.elapsed().as_secs_f64();
    let ToolsOutcome {
        solution,
        dwell_s,
        removal_nm,
        tool_removal_nm,
        sensitivity,
    } = setup.solve(&problem, observer)?;
    // The stacked report: dwell and feeds in seconds of each tool (not the scaled variables).
    let ds_all: Vec<f64> = setup
        .tools
        .iter()
        .flat_map(|t| t.ds_mm.iter().copied())
        .collect();
    let mut unscaled = solution.clone();
    unscaled.dwell_s = dwell_s.concat();
    let residual_nm = centred_residual_nm(setup.map.z_nm(), &removal_nm);
    let mut report = Report::with_feeds(
        &problem,
        &unscaled,
        &residual_nm,
        &feeds_mm_per_min(&ds_all, &unscaled.dwell_s),
        map_read.input.invalid_points,
        build_seconds,
    );
    report.map_input = Some(map_read.input);
    report.influence = Some(setup.influence_model());
    report.sensitivity = Some(sensitivity);
    report.machining_time_s = report.total_dwell_s;
    if job.edge.method != preston_solver::edge::EdgeMethod::None {
        report.warnings.push(
            "several tools: no edge extension beyond the map (the [edge] setting applies to \
             single-tool solves)"
                .into(),
        );
    }
    // Each tool's feed schedule on its own path (its lines and corners at the job's corner
    // angle): the largest acceleration its feeds ask of the machine.
    let schedules = setup
        .tools
        .iter()
        .zip(&dwell_s)
        .map(|(tool, t)| FeedSchedule::new(&tool.path, t, None, job.corner_angle_deg()))
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| Error::engine(job_path, e))?;
    report.max_accel_mm_per_s2 = schedules
        .iter()
        .map(|f| f.max_accel_mm_per_s2)
        .fold(0.0, f64::max);
    report.tools = setup
        .tools
        .iter()
        .zip(&dwell_s)
        .zip(&tool_removal_nm)
        .zip(&schedules)
        .enumerate()
        .map(|(i, (((tool, t), h), schedule))| {
            let stats = HeightStats::of(h);
            let feeds = feeds_mm_per_min(&tool.ds_mm, t);
            let moving: Vec<f64> = feeds.iter().copied().filter(|&f| f > 0.0).collect();
            let total: f64 = t.iter().sum();
            ToolReport {
                tool: i + 1,
                n: t.len(),
                total_dwell_s: total,
                machining_time_s: total,
                time_weight: tool.time_weight,
                removal_rms_nm: stats.rms_nm,
                removal_pv_nm: stats.pv_nm,
                removal_mean_nm: h.iter().sum::<f64>() / h.len().max(1) as f64,
                min_feed_mm_per_min: moving
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min)
                    .min(f64::MAX),
                max_feed_mm_per_min: moving.iter().copied().fold(0.0, f64::max),
                max_accel_mm_per_s2: schedule.max_accel_mm_per_s2,
            }
        })
        .collect();
    Ok(MultiSolved {
        map: setup.map,
        tools: setup.tools,
        solution,
        dwell_s,
        removal_nm,
        residual_nm,
        report,
    })
}

/// Writes `dwell_tool1.csv`, `dwell_tool2.csv`, ..., `residual.csv` and `report.json` into
/// `out_dir`, and the figures and `report.html` where `options` asks for them
/// ([`crate::figures::stage_tool_figures`]), all staged before any is renamed into place. With
/// `options.replace_earlier`, an earlier solve's outputs that this one does not write are
/// removed with the commit, except the paths listed (the run's inputs). Returns notes on figures
/// left out.
pub fn write_tool_outputs(
    solved: &MultiSolved,
    out_dir: &Path,
    options: &OutputOptions,
) -> Result<Vec<String>> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let mut staged = Vec::new();
    let feeds: Vec<Vec<f64>> = solved
        .tools
        .iter()
        .zip(&solved.dwell_s)
        .map(|(tool, t)| feeds_mm_per_min(&tool.ds_mm, t))
        .collect();
    for (k, ((tool, t), feeds)) in solved
        .tools
        .iter()
        .zip(&solved.dwell_s)
        .zip(&feeds)
        .enumerate()
    {
        staged.push(stage_dwell_csv(
            &out_dir.join(format!("dwell_tool{}.csv", k + 1)),
            tool.path.x_mm(),
            tool.path.y_mm(),
            &tool.ds_mm,
            t,
            feeds,
        )?);
    }
    let m = &solved.map;
    staged.push(stage_residual_csv(
        &out_dir.join("residual.csv"),
        m.x_mm(),
        m.y_mm(),
        m.z_nm(),
        &solved.removal_nm,
        &solved.residual_nm,
    )?);
    staged.push(stage_report(&out_dir.join("report.json"), &solved.report)?);
    let (figures, notes) = if options.plots || options.html.is_some() {
        let tools: Vec<ToolFigureData<'_>> = solved
            .tools
            .iter()
            .zip(&solved.dwell_s)
            .zip(&feeds)
            .map(|((tool, t), feeds)| ToolFigureData {
                x_mm: tool.path.x_mm(),
                y_mm: tool.path.y_mm(),
                dwell_s: t,
                feeds_mm_per_min: feeds,
            })
            .collect();
        stage_tool_figures(
            out_dir,
            (m.x_mm(), m.y_mm(), m.z_nm()),
            &solved.removal_nm,
            &solved.residual_nm,
            &tools,
            options.figures.map_or(LineAxis::X, |(axis, _)| axis),
            &options.style,
        )?
    } else {
        (Vec::new(), Vec::new())
    };
    crate::pipeline::commit_solve_outputs(
        staged,
        figures,
        &solved.report,
        &notes,
        out_dir,
        options,
    )?;
    Ok(notes)
}
