//! `report.json`: what a solve achieved, in the keys of the engine contract.

use preston_solver::dwell::accel::AccelReport;
use preston_solver::dwell::certificate::ConvergenceCriterion;
use preston_solver::dwell::{MinTimeReport, Problem, Solution, SolverKind, Status};
use preston_solver::edge::EdgeMethod;
use preston_solver::machine::feeds::FeedSchedule;
use preston_solver::machine::machinability::{dwell_outside_map_s, max_neighbour_feed_ratio};
use preston_solver::map::{HeightMap, HeightStats};
use preston_solver::path::DwellPath;
use serde::{Deserialize, Serialize};

/// The report of one solve (or simulation). Key names are a contract: tests and benchmarks
/// outside the project read them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// Number of measurement points used.
    pub m: usize,
    /// Edge extension points appended to the `m` map rows of the problem
    /// ([`preston_solver::edge`]); the RMS and PV figures are on the measured map only.
    #[serde(default)]
    pub edge_points: usize,
    /// The edge model (`none`, `zero-band`, `gaussian`, `polynomial`, `gerchberg-papoulis`);
    /// `none` for a simulation.
    #[serde(default)]
    pub edge: EdgeMethod,
    /// Number of dwell points.
    pub n: usize,
    /// Non-zeros of the influence matrix (stored, or implicit in the FFT operator).
    pub nnz: usize,
    /// How `R` was applied: `sparse` (assembled), `fft` (matrix-free convolution, map and dwell
    /// points on one lattice) or `fft-spread` (dwell points spread onto the map lattice, then FFT).
    #[serde(default)]
    pub operator: String,
    /// Map rows skipped for an empty or NaN height.
    pub skipped_rows: usize,
    /// RMS of the error map about its mean, nm.
    pub rms_before_nm: f64,
    /// PV of the error map, nm.
    pub pv_before_nm: f64,
    /// RMS of the predicted residual about its mean, nm.
    pub rms_after_nm: f64,
    /// PV of the predicted residual, nm.
    pub pv_after_nm: f64,
    /// Sum of the dwell times, s.
    pub total_dwell_s: f64,
    /// Uniform extra removal, nm (the optimal free piston `c = mean(R t - z)`).
    pub piston_nm: f64,
    /// `0.5 ||R t - z - c||^2` at the optimal piston, nm^2.
    pub objective: f64,
    /// Largest violation of the dwell bounds, s.
    pub max_bound_violation_s: f64,
    /// Slowest feed on the path, mm/min.
    pub min_feed_mm_per_min: f64,
    /// Fastest feed on the path, mm/min.
    pub max_feed_mm_per_min: f64,
    /// Time to read inputs and assemble `R`, s.
    pub build_seconds: f64,
    /// Time in the solver, s.
    pub solve_seconds: f64,
    /// Solver that produced the dwell times (`qp`, `first-order`, `simulate`, ...).
    pub solver: String,
    /// Solver iterations.
    pub iterations: usize,
    /// How the solve ended (`converged`, `max_iterations`, ...).
    pub status: String,
    /// Projected-gradient (KKT) residual, when the solver computes one.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub kkt_residual: Option<f64>,
    /// Proven upper bound on `full objective - optimum` (nm^2); `null` when none exists, with
    /// the reason in `gap_bound_reason`.
    #[serde(default)]
    pub objective_gap_bound: Option<f64>,
    /// Why `objective_gap_bound` is `null` (a sentence), absent when there is a bound.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub gap_bound_reason: Option<String>,
    /// Which test a converged solve met: `objective_gap`, `kkt_residual` or `interior_point`;
    /// `null` when the solve did not converge or no solver ran.
    #[serde(default)]
    pub converged_by: Option<ConvergenceCriterion>,
    /// The `rho = 0` optimum a minimum-time solve started from.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub min_time: Option<MinTimeReport>,
    /// Dwell points with no measurement point in the tool's reach (dwell at lower bound).
    pub unreachable_dwell_points: usize,
    /// Indices (0-based, path order) of the unreachable dwell points.
    #[serde(default)]
    pub unreachable_dwell_indices: Vec<usize>,
    /// How the map was read: format, dropped points, unit notes, removed form terms.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub map_input: Option<crate::metrology::MapInput>,
    /// Warnings about the inputs (for example a TIF wider than the map), also printed on stderr.
    #[serde(default)]
    pub warnings: Vec<String>,
    /// Each tool of a multi-tool solve (`[[tool]]` or repeated `--tif`/`--dwell`); absent for
    /// a single tool.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tools: Vec<crate::tools::ToolReport>,
    /// Machining time of the feed schedule, s: every stretch at its point's feed (`sum t_j`),
    /// plus the acceleration ramps when `a_max` is set
    /// ([`preston_solver::machine::feeds`]). Set by [`Report::set_machine`].
    #[serde(default)]
    pub machining_time_s: f64,
    /// Largest `|v_{j+1}^2 - v_j^2| / (2 s_j)` between consecutive dwell points on a line,
    /// mm/s^2 (computed with or without a limit). Set by [`Report::set_machine`].
    #[serde(default)]
    pub max_accel_mm_per_s2: f64,
    /// The acceleration limit imposed, mm/s^2 (absent without one).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub a_max_mm_per_s2: Option<f64>,
    /// Sequential-convex-programming iterations (QP solves after the feed-limited optimum; 0 when
    /// that optimum already met the limit). Absent without a limit.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub accel_iterations: Option<usize>,
    /// RMS of the residual of the feed-limited-only optimum (no acceleration limit), nm: the
    /// price of the limit is `rms_after_nm - rms_feed_limited_only_nm >= 0`. Absent without a
    /// limit.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub rms_feed_limited_only_nm: Option<f64>,
    /// The whole account of the acceleration-limited solve (objectives, binding segments,
    /// maximum acceleration of the feed-limited optimum). Absent without a limit.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub accel: Option<AccelReport>,
    /// Largest feed ratio of two consecutive moving dwell points
    /// ([`preston_solver::machine::machinability`]).
    #[serde(default)]
    pub max_neighbour_feed_ratio: f64,
    /// Dwell on points with no map point under the TIF centre, s (nearest map point farther
    /// than the map's pitch). Set by [`Report::set_map_coverage`].
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub dwell_outside_map_s: Option<f64>,
    /// With an acceleration limit on a flat part: the default program (ISO, G94) executed at
    /// that limit and its removal integrated along the motion, against the plan.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub executed: Option<ExecutedReport>,
}

/// The plan as the machine executes it at an acceleration limit (`preston simulate --program
/// --a-max-mm-per-s2` on the program `preston nc` writes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExecutedReport {
    /// The path acceleration, mm/s^2.
    pub a_max_mm_per_s2: f64,
    /// Residual RMS of the executed motion (piston removed), nm.
    pub rms_after_nm: f64,
    /// Residual PV of the executed motion, nm.
    pub pv_after_nm: f64,
    /// `rms_after_nm / planned rms_after_nm`.
    pub rms_ratio_to_plan: f64,
    /// Time of the dwell stretches as executed, s.
    pub stretch_time_s: f64,
    /// Largest `|executed - planned| / planned` over the stretches.
    pub max_stretch_error: f64,
    /// Stretches more than 5% off their dwell.
    pub stretches_over_5_percent: usize,
}

/// Feed at each dwell point, mm/min: `ds / dwell * 60` (0 where `ds` is 0).
pub fn feeds_mm_per_min(ds_mm: &[f64], dwell_s: &[f64]) -> Vec<f64> {
    ds_mm
        .iter()
        .zip(dwell_s)
        .map(|(&d, &t)| {
            if d > 0.0 && t > 0.0 {
                d / t * 60.0
            } else {
                0.0
            }
        })
        .collect()
}

/// Name of a solver in reports.
pub fn solver_name(kind: SolverKind) -> String {
    serde_json::to_value(kind)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{kind:?}"))
}

/// Name of a status in reports.
pub fn status_name(status: Status) -> String {
    serde_json::to_value(status)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{status:?}"))
}

/// Residual about its mean, nm: `(z - h) - mean(z - h)`.
pub fn centred_residual_nm(z_nm: &[f64], removal_nm: &[f64]) -> Vec<f64> {
    let e: Vec<f64> = z_nm.iter().zip(removal_nm).map(|(z, h)| z - h).collect();
    let mean = if e.is_empty() {
        0.0
    } else {
        e.iter().sum::<f64>() / e.len() as f64
    };
    e.into_iter().map(|v| v - mean).collect()
}

impl Report {
    /// Builds the report of `solution` on `problem`; `removal_nm` is `R t` on the measured map:
    /// the first `removal_nm.len()` rows of the problem (edge extension rows follow them).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        problem: &Problem,
        solution: &Solution,
        removal_nm: &[f64],
        ds_mm: &[f64],
        skipped_rows: usize,
        build_seconds: f64,
    ) -> Self {
        let z = &problem.z_nm()[..removal_nm.len().min(problem.m())];
        let before = HeightStats::of(z);
        let after = HeightStats::of(&centred_residual_nm(z, removal_nm));
        let feeds = feeds_mm_per_min(ds_mm, &solution.dwell_s);
        let moving: Vec<f64> = feeds.iter().copied().filter(|&f| f > 0.0).collect();
        let empty = problem.empty_columns();
        Self {
            m: z.len(),
            edge_points: problem.m() - z.len(),
            edge: EdgeMethod::None,
            n: problem.n(),
            nnz: problem.nnz(),
            operator: problem.operator_name().into(),
            skipped_rows,
            rms_before_nm: before.rms_nm,
            pv_before_nm: before.pv_nm,
            rms_after_nm: after.rms_nm,
            pv_after_nm: after.pv_nm,
            total_dwell_s: solution.dwell_s.iter().sum(),
            piston_nm: solution.piston_nm,
            objective: solution.objective,
            max_bound_violation_s: problem.bounds().max_violation_s(&solution.dwell_s),
            min_feed_mm_per_min: moving
                .iter()
                .copied()
                .fold(f64::INFINITY, f64::min)
                .min(f64::MAX),
            max_feed_mm_per_min: moving.iter().copied().fold(0.0, f64::max),
            build_seconds,
            solve_seconds: solution.solve_seconds,
            solver: solver_name(solution.solver),
            iterations: solution.iterations,
            status: status_name(solution.status),
            kkt_residual: solution.kkt_residual,
            objective_gap_bound: solution.objective_gap_bound,
            gap_bound_reason: solution.gap_bound_reason.map(|r| r.to_string()),
            converged_by: solution.converged_by,
            min_time: solution.min_time,
            unreachable_dwell_points: empty.len(),
            unreachable_dwell_indices: empty,
            map_input: None,
            warnings: Vec::new(),
            tools: Vec::new(),
            machining_time_s: 0.0,
            max_accel_mm_per_s2: 0.0,
            a_max_mm_per_s2: None,
            accel_iterations: None,
            rms_feed_limited_only_nm: None,
            accel: None,
            max_neighbour_feed_ratio: max_neighbour_feed_ratio(&feeds),
            dwell_outside_map_s: None,
            executed: None,
        }
    }

    /// Sets `dwell_outside_map_s` from the map points and the dwell points with their dwell.
    pub fn set_map_coverage(&mut self, map: &HeightMap, path: &DwellPath, dwell_s: &[f64]) {
        self.dwell_outside_map_s = Some(dwell_outside_map_s(
            map.x_mm(),
            map.y_mm(),
            path.x_mm(),
            path.y_mm(),
            dwell_s,
        ));
    }

    /// Adds the machine keys: machining time and largest acceleration from `schedule`, and the
    /// acceleration-limited solve's account when there was one.
    pub fn set_machine(&mut self, schedule: &FeedSchedule, accel: Option<&AccelReport>) {
        self.machining_time_s = schedule.machining_time_s;
        self.max_accel_mm_per_s2 = schedule.max_accel_mm_per_s2;
        self.a_max_mm_per_s2 = accel.map(|a| a.a_max_mm_per_s2);
        self.accel_iterations = accel.map(|a| a.scp_iterations);
        self.rms_feed_limited_only_nm = accel.map(|a| a.rms_after_reference_nm);
        self.accel = accel.cloned();
    }
}
