//! `report.json`: what a solve achieved, in the keys of the engine contract.

use preston_solver::dwell::accel::AccelReport;
use preston_solver::dwell::certificate::ConvergenceCriterion;
use preston_solver::dwell::{MinTimeReport, OperatorKind, Problem, Solution, SolverKind, Status};
use preston_solver::edge::EdgeMethod;
use preston_solver::influence::InfluenceModel;
use preston_solver::machine::feeds::FeedSchedule;
use preston_solver::machine::machinability::max_neighbour_feed_ratio;
use preston_solver::map::HeightStats;
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
    /// points on one lattice), `fft-spread` (dwell points spread onto the map lattice, then FFT)
    /// `stencil` (one tabulated stencil per dwell position within a map cell; exact) or `nufft`
    /// (dwell points spread by a smooth kernel onto a fine lattice, deconvolved FFT; error
    /// measured, `operator_error`).
    #[serde(default)]
    pub operator: OperatorKind,
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
    pub solver: SolverLabel,
    /// Solver iterations.
    pub iterations: usize,
    /// How the solve ended (`converged`, `max_iterations`, ...; `simulated` when no solver ran).
    pub status: ReportStatus,
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
    /// Notes on what the set-up chose (the operator `auto` took, the swept columns made exact),
    /// for information; also printed on stderr as notes.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// Each tool of a multi-tool solve (`[[tool]]` or repeated `--tif`/`--dwell`); absent for
    /// a single tool.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tools: Vec<ToolReport>,
    /// What the interferometer is expected to read after the run, RMS, nm: the executed
    /// residual under the tool as it is known (a calibration's uncertainty, else the spot
    /// test's), with the measurement's noise, piston and tilt dropped; `rms_after_nm` is the
    /// model's with the nominal tool.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub expected_rms_nm: Option<f64>,
    /// Expected PV of that reading, nm.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub expected_pv_nm: Option<f64>,
    /// 90% range of the expected RMS, nm.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub expected_rms_range_nm: Option<[f64; 2]>,
    /// How the expected reading was drawn: the uncertainty, the nominal RMS, the draws.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub expected: Option<preston_solver::calibrate::Expected>,
    /// Whether the run is expected to improve the part by more than its risk: the 95th
    /// percentile of the expected reading below the RMS measured before the run (both with
    /// piston and tilt removed, as the interferometer reads them;
    /// [`preston_solver::setup::pays`]).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub run_pays: Option<bool>,
    /// What the plan corrects: the whole map (`map`), or the correctable band alone (`band`,
    /// with its cap's transfer gain, cut-off frequency in 1/mm, fit degrees and the RMS it
    /// leaves out, nm) where its expected cost is below the whole map's plan's.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub plan_scope: Option<preston_solver::setup::pays::PlanScope>,
    /// The time weight the plan kept was solved with, nm^2 per s: the job's `rho`, or a lighter
    /// plan's larger weight where its expected cost is below the job's plan's.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub plan_rho_nm2_per_s: Option<f64>,
    /// The expected RMS of the job's plan of the whole map where another plan replaced it, nm.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub map_plan_expected_rms_nm: Option<f64>,
    /// The dwell of the job's plan of the whole map where another plan replaced it, s.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub map_plan_dwell_s: Option<f64>,
    /// The largest part of the expected reading (`expected.parts`): what keeps the run from
    /// doing better (`band`, `tool_uncertainty` or `noise`).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub expected_floor_cause: Option<preston_solver::calibrate::FloorCause>,
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
    /// Iterations of the acceleration-limited method after the feed-limited optimum: gradient
    /// steps (squared speed) or QP solves (SCP); 0 when that optimum already met the limit.
    /// Absent without a limit.
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
    /// With an acceleration limit: the default program (ISO, G94; on a curved part following the
    /// design surface) executed at that limit and its removal integrated along the motion (on a
    /// curved part each contact sample applying the TIF in its tangent frame), against the plan.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub executed: Option<ExecutedReport>,
    /// `simulate --program`: the resolution of `rms_after_nm` and `pv_after_nm`, the program
    /// run again with half the sample step (as a solve's `executed.integration`).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub integration: Option<preston_solver::setup::IntegrationResolution>,
    /// With an approximate (spreading) operator: its measured error on the returned dwell and
    /// the residual it predicted; `rms_after_nm` above is the exact `R`'s.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub operator_error: Option<preston_solver::setup::OperatorError>,
    /// How the plan modelled the tool at a dwell point: `swept` (the TIF averaged along the
    /// point's stretch of path, as the program runs it) or `point`; for a simulation, the model
    /// of its removal (`point` for discrete motion, `swept` for continuous motion and programs).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub influence: Option<InfluenceModel>,
    /// A generated raster's placement: `pitch_mm`, `origin_mm` (its lower corner), the map's
    /// `map_lattice_pitch_mm` and the raster's `phase_cells` on that lattice (zero: Preston put
    /// the raster on the lattice, so the FFT or phase-stencil operator serves it).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub raster: Option<preston_solver::path::raster::RasterPlacement>,
    /// The plan's model residual `z - R t` (RMS, PV, nm) where `rms_after_nm` / `pv_after_nm`
    /// are the program's as executed at the acceleration limit. Absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub model: Option<ResidualFigures>,
    /// The residual (RMS, PV, nm) of the plan's program (as executed where the solve executes
    /// it, else at its programmed feeds) with the TIF 3% wider and narrower (volume kept), its
    /// rate 3% higher and the tool 0.05 mm off in x and in y
    /// ([`preston_solver::setup::sensitivity`]). Absent where the plan cannot be written as a
    /// program.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensitivity: Option<preston_solver::setup::sensitivity::Sensitivity>,
    /// With `robust`: the robust plan against the nominal plan of the same job.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robust: Option<RobustReport>,
}

/// The robust plan against the nominal plan ([`preston_solver::setup::robust`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobustReport {
    /// Both plans' residual RMS in every scenario (as executed where both programs are, else
    /// as planned: `basis`), what the robust plan costs nominally and what it saves in the
    /// worst scenario.
    #[serde(flatten)]
    pub planned: preston_solver::setup::robust::RobustSummary,
    /// How the scenarios were weighed: `mean` or `minimax`.
    pub weighting: preston_solver::dwell::RobustWeighting,
    /// The scenarios' weights in the plan, in the order of `scenarios`, summing to their count
    /// (all 1 for `mean`).
    pub scenario_weights: Vec<f64>,
    /// The nominal plan's residual RMS, nm: as executed where the program is executed, else
    /// its model's.
    pub nominal_plan_rms_after_nm: f64,
    /// The nominal plan's executed sensitivity (the robust plan's is `sensitivity`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nominal_plan_sensitivity: Option<preston_solver::setup::sensitivity::Sensitivity>,
}

/// RMS and PV of a residual (piston removed), nm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ResidualFigures {
    /// RMS about the mean, nm.
    pub rms_nm: f64,
    /// Peak to valley, nm.
    pub pv_nm: f64,
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
    /// Largest `|executed - planned| / planned` over the stretches, relative (a fraction: 5.74
    /// is 574%). Read also under its former key `max_stretch_error`.
    #[serde(alias = "max_stretch_error")]
    pub max_stretch_error_rel: f64,
    /// Stretches more than 5% off their dwell.
    pub stretches_over_5_percent: usize,
    /// Correction passes against the executed program kept (`accel_method =
    /// "correction-passes"`; 0 otherwise).
    #[serde(default)]
    pub correction_passes: usize,
    /// The resolution of `rms_after_nm` and `pv_after_nm`: the sample step of the removal
    /// integral and how far the executed residual moves at half that step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub integration: Option<preston_solver::setup::IntegrationResolution>,
}

pub use preston_solver::setup::{centred_residual_nm, feeds_mm_per_min};

/// What produced the dwell times of a report; serialised as the names reports have always
/// carried (`qp`, `first-order`, `simulate`, `simulate-continuous-N`, `simulate-program`,
/// `simulate-program-aA`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SolverLabel {
    /// A dwell solver.
    Solver(SolverKind),
    /// A simulation of given dwell times, removal `R t` at the dwell points.
    Simulate,
    /// A simulation of given dwell times under the swept influence model: `R t` with each
    /// column the TIF averaged along its dwell point's stretch, the solver's default model.
    SimulateSwept,
    /// A simulation of the continuous sweep with this many samples per dwell point.
    SimulateContinuous {
        /// Midpoint-rule samples per dwell point.
        samples_per_point: usize,
    },
    /// A program executed at its programmed feeds.
    SimulateProgram,
    /// A program executed at an acceleration limit, mm/s^2.
    SimulateProgramAtLimit {
        /// The path acceleration, mm/s^2.
        a_max_mm_per_s2: f64,
    },
}

impl std::fmt::Display for SolverLabel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SolverLabel::Solver(k) => f.write_str(&solver_name(*k)),
            SolverLabel::Simulate => f.write_str("simulate"),
            SolverLabel::SimulateSwept => f.write_str("simulate-swept"),
            SolverLabel::SimulateContinuous { samples_per_point } => {
                write!(f, "simulate-continuous-{samples_per_point}")
            }
            SolverLabel::SimulateProgram => f.write_str("simulate-program"),
            SolverLabel::SimulateProgramAtLimit { a_max_mm_per_s2 } => {
                write!(f, "simulate-program-a{a_max_mm_per_s2}")
            }
        }
    }
}

impl std::str::FromStr for SolverLabel {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let bad = || format!("unknown solver `{s}`");
        match s {
            "qp" => Ok(SolverLabel::Solver(SolverKind::Qp)),
            "first-order" => Ok(SolverLabel::Solver(SolverKind::FirstOrder)),
            "simulate" => Ok(SolverLabel::Simulate),
            "simulate-swept" => Ok(SolverLabel::SimulateSwept),
            "simulate-program" => Ok(SolverLabel::SimulateProgram),
            _ => {
                if let Some(n) = s.strip_prefix("simulate-continuous-") {
                    n.parse()
                        .map(|samples_per_point| SolverLabel::SimulateContinuous {
                            samples_per_point,
                        })
                        .map_err(|_| bad())
                } else if let Some(a) = s.strip_prefix("simulate-program-a") {
                    a.parse()
                        .map(|a_max_mm_per_s2| SolverLabel::SimulateProgramAtLimit {
                            a_max_mm_per_s2,
                        })
                        .map_err(|_| bad())
                } else {
                    Err(bad())
                }
            }
        }
    }
}

impl Serialize for SolverLabel {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for SolverLabel {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

/// How the step that produced a report's dwell times ended: a solver's [`Status`], or
/// `simulated` when the dwell times were given and no solver ran.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReportStatus {
    /// A solver ran and ended so.
    Solved(Status),
    /// No solver ran: the dwell times were given (`preston simulate`).
    Simulated,
}

impl ReportStatus {
    /// True when a solver ran and converged, or nothing was solved.
    pub fn is_converged(self) -> bool {
        match self {
            ReportStatus::Solved(s) => s.is_converged(),
            ReportStatus::Simulated => true,
        }
    }
}

impl std::fmt::Display for ReportStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReportStatus::Solved(s) => s.fmt(f),
            ReportStatus::Simulated => f.write_str("simulated"),
        }
    }
}

impl Serialize for ReportStatus {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            ReportStatus::Solved(status) => status.serialize(s),
            ReportStatus::Simulated => s.serialize_str("simulated"),
        }
    }
}

impl<'de> Deserialize<'de> for ReportStatus {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        if text == "simulated" {
            return Ok(ReportStatus::Simulated);
        }
        serde_json::from_value(serde_json::Value::String(text))
            .map(ReportStatus::Solved)
            .map_err(serde::de::Error::custom)
    }
}

/// Name of a solver in reports.
pub fn solver_name(kind: SolverKind) -> String {
    serde_json::to_value(kind)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{kind:?}"))
}

/// The residual of a dwell on the map, and the piston and objective that go with it.
struct Fit<'a> {
    /// Residual about its mean, nm.
    residual_nm: &'a [f64],
    /// `mean(R t - z)`, nm.
    piston_nm: f64,
    /// `0.5 ||R t - z - c||^2`, nm^2.
    objective: f64,
}

/// Name of a status in reports.
pub fn status_name(status: Status) -> String {
    serde_json::to_value(status)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{status:?}"))
}

impl Report {
    /// Builds the report of `solution` on `problem`; `removal_nm` is `R t` on the measured map:
    /// the first `removal_nm.len()` rows of the problem (edge extension rows follow them).
    pub fn new(
        problem: &Problem,
        solution: &Solution,
        removal_nm: &[f64],
        ds_mm: &[f64],
        skipped_rows: usize,
        build_seconds: f64,
    ) -> Self {
        let feeds = feeds_mm_per_min(ds_mm, &solution.dwell_s);
        let z = &problem.z_nm()[..removal_nm.len().min(problem.m())];
        let residual = centred_residual_nm(z, removal_nm);
        Self::with_feeds(
            problem,
            solution,
            &residual,
            &feeds,
            skipped_rows,
            build_seconds,
        )
    }

    /// As [`Report::new`] with the residual on the measured map (about its mean, nm) and the
    /// feeds (one per dwell point, mm/min) already computed; the piston and objective are the
    /// solution's.
    pub fn with_feeds(
        problem: &Problem,
        solution: &Solution,
        residual_nm: &[f64],
        feeds: &[f64],
        skipped_rows: usize,
        build_seconds: f64,
    ) -> Self {
        let fit = Fit {
            residual_nm,
            piston_nm: solution.piston_nm,
            objective: solution.objective,
        };
        let mut r = Self::of_fit(
            problem,
            &solution.dwell_s,
            fit,
            feeds,
            skipped_rows,
            build_seconds,
        );
        r.solve_seconds = solution.solve_seconds;
        r.solver = SolverLabel::Solver(solution.solver);
        r.iterations = solution.iterations;
        r.status = ReportStatus::Solved(solution.status);
        r.kkt_residual = solution.kkt_residual;
        r.objective_gap_bound = solution.objective_gap_bound;
        r.gap_bound_reason = solution.gap_bound_reason.map(|r| r.to_string());
        r.converged_by = solution.converged_by;
        r.min_time = solution.min_time;
        r
    }

    /// The report of dwell times that no solver produced (a simulation): the piston and
    /// objective are those of `removal_nm` on the map (`c = mean(R t - z)`,
    /// `0.5 ||R t - z - c||^2`), the solver [`SolverLabel::Simulate`] and the status
    /// [`ReportStatus::Simulated`], no iterations.
    pub fn of_dwell(
        problem: &Problem,
        dwell_s: &[f64],
        removal_nm: &[f64],
        feeds: &[f64],
        skipped_rows: usize,
        build_seconds: f64,
    ) -> Self {
        let z = &problem.z_nm()[..removal_nm.len().min(problem.m())];
        let residual_nm = centred_residual_nm(z, removal_nm);
        let piston_nm = removal_nm.iter().zip(z).map(|(h, z)| h - z).sum::<f64>()
            / removal_nm.len().max(1) as f64;
        let objective = 0.5
            * removal_nm
                .iter()
                .zip(z)
                .map(|(h, z)| (h - z - piston_nm).powi(2))
                .sum::<f64>();
        let fit = Fit {
            residual_nm: &residual_nm,
            piston_nm,
            objective,
        };
        Self::of_fit(problem, dwell_s, fit, feeds, skipped_rows, build_seconds)
    }

    /// The report's keys of the dwell and its fit to the map, with no solver.
    fn of_fit(
        problem: &Problem,
        dwell_s: &[f64],
        fit: Fit<'_>,
        feeds: &[f64],
        skipped_rows: usize,
        build_seconds: f64,
    ) -> Self {
        let Fit {
            residual_nm,
            piston_nm,
            objective,
        } = fit;
        // The measured rows (of the nominal block, over its scale, in a robust plan).
        let a0 = problem.scenario_scales()[0];
        let z: Vec<f64> = problem.z_nm()[..residual_nm.len().min(problem.m())]
            .iter()
            .map(|v| v / a0)
            .collect();
        let before = HeightStats::of(&z);
        let after = HeightStats::of(residual_nm);
        let moving: Vec<f64> = feeds.iter().copied().filter(|&f| f > 0.0).collect();
        let empty = problem.empty_columns();
        Self {
            m: z.len(),
            edge_points: problem.m() - z.len(),
            edge: EdgeMethod::None,
            n: problem.n(),
            nnz: problem.nnz(),
            operator: problem.operator_kind(),
            skipped_rows,
            rms_before_nm: before.rms_nm,
            pv_before_nm: before.pv_nm,
            rms_after_nm: after.rms_nm,
            pv_after_nm: after.pv_nm,
            total_dwell_s: dwell_s.iter().sum(),
            piston_nm,
            objective,
            max_bound_violation_s: problem.bounds().max_violation_s(dwell_s),
            min_feed_mm_per_min: moving
                .iter()
                .copied()
                .fold(f64::INFINITY, f64::min)
                .min(f64::MAX),
            max_feed_mm_per_min: moving.iter().copied().fold(0.0, f64::max),
            build_seconds,
            solve_seconds: 0.0,
            solver: SolverLabel::Simulate,
            iterations: 0,
            status: ReportStatus::Simulated,
            kkt_residual: None,
            objective_gap_bound: None,
            gap_bound_reason: None,
            converged_by: None,
            min_time: None,
            unreachable_dwell_points: empty.len(),
            unreachable_dwell_indices: empty,
            map_input: None,
            warnings: Vec::new(),
            notes: Vec::new(),
            tools: Vec::new(),
            expected_rms_nm: None,
            expected_pv_nm: None,
            expected_rms_range_nm: None,
            expected: None,
            run_pays: None,
            plan_scope: None,
            plan_rho_nm2_per_s: None,
            map_plan_expected_rms_nm: None,
            map_plan_dwell_s: None,
            expected_floor_cause: None,
            machining_time_s: 0.0,
            max_accel_mm_per_s2: 0.0,
            a_max_mm_per_s2: None,
            accel_iterations: None,
            rms_feed_limited_only_nm: None,
            accel: None,
            max_neighbour_feed_ratio: max_neighbour_feed_ratio(feeds),
            dwell_outside_map_s: None,
            executed: None,
            integration: None,
            operator_error: None,
            influence: None,
            raster: None,
            model: None,
            sensitivity: None,
            robust: None,
        }
    }

    /// Sets the expected reading after the run, whether the run pays, what the plan corrects
    /// and, where no run pays, the floor's cause.
    pub fn set_expected(&mut self, paying: &preston_solver::setup::pays::PayingPlan) {
        let expected = paying.expected.as_ref();
        self.expected_rms_nm = expected.map(|e| e.expected_rms_nm);
        self.expected_pv_nm = expected.map(|e| e.expected_pv_nm);
        self.expected_rms_range_nm = expected.map(|e| e.expected_rms_range_nm);
        self.run_pays = paying.pays();
        self.expected_floor_cause = expected.map(|e| e.parts.cause());
        self.expected = expected.cloned();
        self.plan_scope = expected.map(|_| paying.scope);
        self.plan_rho_nm2_per_s = expected.map(|_| paying.rho);
        self.map_plan_expected_rms_nm = paying.map_plan_expected_rms_nm;
        self.map_plan_dwell_s = paying.map_plan_dwell_s;
    }

    /// Adds the machine keys: machining time and largest acceleration from `schedule`, and the
    /// acceleration-limited solve's account when there was one.
    pub fn set_machine(&mut self, schedule: &FeedSchedule, accel: Option<&AccelReport>) {
        self.machining_time_s = schedule.machining_time_s;
        self.max_accel_mm_per_s2 = schedule.max_accel_mm_per_s2;
        self.a_max_mm_per_s2 = accel.map(|a| a.a_max_mm_per_s2);
        self.accel_iterations = accel.map(|a| a.scp_iterations + a.gradient_steps);
        self.rms_feed_limited_only_nm = accel.map(|a| a.rms_after_reference_nm);
        self.accel = accel.cloned();
    }
}

/// What one tool does in a multi-tool plan (`report.json` `tools`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToolReport {
    /// 1-based tool number (`dwell_tool{k}.csv`).
    pub tool: usize,
    /// Dwell points of the tool.
    pub n: usize,
    /// Total dwell of the tool, s.
    pub total_dwell_s: f64,
    /// Machining time of the tool along its path at the planned feeds, s (equal to the total
    /// dwell: the dwell of each point is the time spent on its path length).
    pub machining_time_s: f64,
    /// The tool's machining-time weight.
    pub time_weight: f64,
    /// RMS of the tool's removal over the map, nm.
    pub removal_rms_nm: f64,
    /// Peak-to-valley of the tool's removal over the map, nm.
    pub removal_pv_nm: f64,
    /// Mean removal of the tool over the map, nm.
    pub removal_mean_nm: f64,
    /// Slowest and fastest feed of the tool while moving, mm/min.
    pub min_feed_mm_per_min: f64,
    /// Fastest feed of the tool, mm/min.
    pub max_feed_mm_per_min: f64,
    /// Largest `|v_{j+1}^2 - v_j^2| / (2 s_j)` between consecutive dwell points on a line of
    /// the tool's path, mm/s^2 (the report's `max_accel_mm_per_s2` is the largest over the
    /// tools).
    #[serde(default)]
    pub max_accel_mm_per_s2: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The largest stretch departure is written under a key naming its unit (a fraction), and a
    /// report written before, under the former key, still reads to the same figure.
    #[test]
    fn the_stretch_error_key_names_its_unit_and_the_former_key_reads() {
        let e = ExecutedReport {
            a_max_mm_per_s2: 1000.0,
            rms_after_nm: 0.02,
            pv_after_nm: 0.6,
            rms_ratio_to_plan: 0.07,
            stretch_time_s: 27549.2,
            max_stretch_error_rel: 5.742,
            stretches_over_5_percent: 1790,
            correction_passes: 2,
            integration: None,
        };
        let v = serde_json::to_value(&e).unwrap();
        assert_eq!(v["max_stretch_error_rel"], 5.742);
        assert!(v.get("max_stretch_error").is_none(), "{v}");
        let mut old = v.clone();
        let obj = old.as_object_mut().unwrap();
        let x = obj.remove("max_stretch_error_rel").unwrap();
        obj.insert("max_stretch_error".into(), x);
        let back: ExecutedReport = serde_json::from_value(old).unwrap();
        assert_eq!(back, e);
    }
}
