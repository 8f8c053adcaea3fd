//! Several tools in one solve: each tool `k` has its own TIF (`R_k`), dwell path and feed limits,
//! and one optimisation runs over all dwell times at once,
//!
//! `min 0.5 ||sum_k R_k t_k - z - c 1||^2 + rho sum_k w_k sum_j t_kj`,
//! `ds_kj / v_max,k <= t_kj <= ds_kj / v_min,k`,
//!
//! with `w_k` the tool's machining-time weight (`time_weight`, default 1). With `u_k = w_k t_k` this
//! is the single-tool contract ([`preston_solver::dwell`]) for the stacked operator
//! `[R_1 / w_1, R_2 / w_2, ...]` and the bounds scaled by `w_k`, so the QP and the first-order
//! solver run on it unchanged (the assembled block matrix; the smoothness term `lambda` would
//! couple the last dwell of one tool to the first of the next, so it is refused here).
//! Large and small tools in one plan: the large tool takes the low spatial frequencies cheaply,
//! the small one what it cannot reach.

use crate::atomic::commit_all;
use crate::error::{Error, Result};
use crate::job::{Job, TifSource};
use crate::readers::read_dwell;
pub use crate::report::ToolReport;
use crate::report::{centred_residual_nm, feeds_mm_per_min, Report};
use crate::writers::{stage_dwell_csv, stage_report, stage_residual_csv};
use preston_solver::dwell::{self, DwellBounds, FeedLimits, OperatorChoice, Problem, Solution};
use preston_solver::influence::stacked::stack_scaled;
use preston_solver::influence::InfluenceMatrix;
use preston_solver::map::{HeightMap, HeightStats};
use preston_solver::observer::Observer;
use preston_solver::path::DwellPath;
use preston_solver::tif::Tif;
use std::path::Path;
use std::time::Instant;

/// One tool, read: its TIF, path, path lengths and bounds (unscaled).
#[derive(Debug, Clone)]
pub struct Tool {
    /// The TIF.
    pub tif: Tif,
    /// The dwell path.
    pub path: DwellPath,
    /// Path length per dwell point, mm.
    pub ds_mm: Vec<f64>,
    /// Feed limits.
    pub limits: FeedLimits,
    /// Machining-time weight `w_k`.
    pub time_weight: f64,
}

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

/// Reads each `[[tool]]`'s TIF and path and checks what multi-tool solves support.
pub fn read_tools(job: &Job, job_path: &Path) -> Result<Vec<Tool>> {
    let refuse = |why: &str| Error::Job {
        file: job_path.to_path_buf(),
        why: format!("several tools cannot be combined with {why}"),
    };
    if job.objective.lambda > 0.0 {
        return Err(refuse(
            "lambda > 0 (it would couple one tool's path to the next)",
        ));
    }
    if job.machine.a_max_mm_per_s2.is_some() {
        return Err(refuse("an acceleration limit"));
    }
    if job.surface.file.is_some() {
        return Err(refuse("a [surface] file"));
    }
    if job.dwell.warm_start.is_some() {
        return Err(refuse("a warm start"));
    }
    if !matches!(
        job.solver.operator,
        OperatorChoice::Auto | OperatorChoice::Sparse
    ) {
        return Err(refuse(
            "a matrix-free operator (the stacked R is assembled)",
        ));
    }
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
            limits.validate().map_err(|e| Error::engine(job_path, e))?;
            let time_weight = spec.time_weight.unwrap_or(1.0);
            if !(time_weight.is_finite() && time_weight > 0.0) {
                return Err(Error::Job {
                    file: job_path.to_path_buf(),
                    why: format!("tool {k}: time_weight must be positive, got {time_weight}"),
                });
            }
            let ds_mm = d.path.ds_mm();
            Ok(Tool {
                tif,
                path: d.path,
                ds_mm,
                limits,
                time_weight,
            })
        })
        .collect()
}

/// The stacked problem `[R_1 / w_1, R_2 / w_2, ...]` over `map` with bounds `w_k ds / v`.
pub fn stacked_problem(
    map: &HeightMap,
    tools: &[Tool],
    rho: f64,
    observer: &dyn Observer,
) -> std::result::Result<Problem, preston_solver::Error> {
    let mut blocks = Vec::with_capacity(tools.len());
    let (mut lower, mut upper, mut any_upper) = (Vec::new(), Vec::new(), false);
    for tool in tools {
        let r = InfluenceMatrix::assemble(
            map.x_mm(),
            map.y_mm(),
            tool.path.x_mm(),
            tool.path.y_mm(),
            &tool.tif,
            observer,
        )?;
        let w = tool.time_weight;
        blocks.push((r, w));
        let b = DwellBounds::from_feeds(&tool.ds_mm, &tool.limits)?;
        lower.extend(b.lower_s().iter().map(|l| l * w));
        match b.upper_s() {
            Some(u) => {
                any_upper = true;
                upper.extend(u.iter().map(|u| u * w));
            }
            None => upper.extend(std::iter::repeat_n(f64::INFINITY, tool.path.len())),
        }
    }
    let refs: Vec<(&InfluenceMatrix, f64)> = blocks.iter().map(|(r, w)| (r, *w)).collect();
    let stacked = stack_scaled(&refs)?;
    let bounds = DwellBounds::new(lower, any_upper.then_some(upper))?;
    Problem::new(stacked, map.z_nm().to_vec(), bounds, rho, 0.0)
}

/// Splits a stacked (scaled) dwell vector into each tool's dwell times, s (`t_k = u_k / w_k`).
pub fn split_dwell(tools: &[Tool], u: &[f64]) -> Vec<Vec<f64>> {
    let mut start = 0;
    tools
        .iter()
        .map(|t| {
            let part = u[start..start + t.path.len()]
                .iter()
                .map(|v| v / t.time_weight)
                .collect();
            start += t.path.len();
            part
        })
        .collect()
}

/// Reads the map and tools, solves the stacked problem and builds the report.
pub fn solve_tools(job: &Job, job_path: &Path, observer: &dyn Observer) -> Result<MultiSolved> {
    let started = Instant::now();
    job.solver
        .validate()
        .map_err(|e| Error::engine(job_path, e))?;
    if job.map.file.is_none() {
        return Err(Error::Job {
            file: job_path.to_path_buf(),
            why: "no map: set [map] file (or --map)".into(),
        });
    }
    let map_read = job.map.read()?;
    let map = map_read.map;
    let tools = read_tools(job, job_path)?;
    let map_path = job.map.file.as_deref().unwrap_or(job_path);
    let problem = stacked_problem(&map, &tools, job.objective.rho, observer)
        .map_err(|e| Error::engine(map_path, e))?;
    let build_seconds = started.elapsed().as_secs_f64();
    let solution = dwell::solve(&problem, &job.solver, observer)?;
    let dwell_s = split_dwell(&tools, &solution.dwell_s);
    let removal_nm = problem.removal_nm(&solution.dwell_s)?;
    // The stacked report: dwell and feeds in seconds of each tool (not the scaled variables).
    let ds_all: Vec<f64> = tools.iter().flat_map(|t| t.ds_mm.clone()).collect();
    let mut unscaled = solution.clone();
    unscaled.dwell_s = dwell_s.concat();
    let mut report = Report::new(
        &problem,
        &unscaled,
        &removal_nm,
        &ds_all,
        map_read.input.invalid_points,
        build_seconds,
    );
    report.map_input = Some(map_read.input);
    report.machining_time_s = report.total_dwell_s;
    if job.edge.method != preston_solver::edge::EdgeMethod::None {
        report.warnings.push(
            "several tools: no edge extension beyond the map (the [edge] setting applies to \
             single-tool solves)"
                .into(),
        );
    }
    report.tools = tools
        .iter()
        .zip(&dwell_s)
        .enumerate()
        .map(|(i, (tool, t))| {
            // Tool i's removal `R_i t_i` through the stacked problem: its block of the scaled
            // variable `u = w t`, every other tool's zero (no second assembly of `R_i`).
            let start: usize = tools[..i].iter().map(|t| t.path.len()).sum();
            let mut u_i = vec![0.0; solution.dwell_s.len()];
            u_i[start..start + t.len()].copy_from_slice(&solution.dwell_s[start..start + t.len()]);
            let h = problem.removal_nm(&u_i)?;
            let stats = HeightStats::of(&h);
            let feeds = feeds_mm_per_min(&tool.ds_mm, t);
            let moving: Vec<f64> = feeds.iter().copied().filter(|&f| f > 0.0).collect();
            let total: f64 = t.iter().sum();
            Ok(ToolReport {
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
            })
        })
        .collect::<std::result::Result<Vec<_>, preston_solver::Error>>()
        .map_err(|e| Error::engine(map_path, e))?;
    Ok(MultiSolved {
        map,
        tools,
        solution,
        dwell_s,
        removal_nm,
        report,
    })
}

/// Writes `dwell_tool1.csv`, `dwell_tool2.csv`, ..., `residual.csv` and `report.json` into
/// `out_dir`, all staged before any is renamed into place.
pub fn write_tool_outputs(solved: &MultiSolved, out_dir: &Path) -> Result<()> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let mut staged = Vec::new();
    for (k, (tool, t)) in solved.tools.iter().zip(&solved.dwell_s).enumerate() {
        let feeds = feeds_mm_per_min(&tool.ds_mm, t);
        staged.push(stage_dwell_csv(
            &out_dir.join(format!("dwell_tool{}.csv", k + 1)),
            tool.path.x_mm(),
            tool.path.y_mm(),
            &tool.ds_mm,
            t,
            &feeds,
        )?);
    }
    let m = &solved.map;
    let residual = centred_residual_nm(m.z_nm(), &solved.removal_nm);
    staged.push(stage_residual_csv(
        &out_dir.join("residual.csv"),
        m.x_mm(),
        m.y_mm(),
        m.z_nm(),
        &solved.removal_nm,
        &residual,
    )?);
    staged.push(stage_report(&out_dir.join("report.json"), &solved.report)?);
    commit_all(staged)
}
