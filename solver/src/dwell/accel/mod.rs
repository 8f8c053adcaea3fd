//! Acceleration limits inside the dwell optimisation.
//!
//! The default method ([`AccelMethod::CorrectionPasses`]) puts no constraint in the plan: the
//! set-up re-solves the feed-limited plan against the program executed at the limit (the
//! controller holds it), which leaves the smallest residual on the part as made. Two methods put
//! the limit into the plan's own feeds: [`speed`], an accelerated projected gradient in
//! squared speed with an exact linear-time projection onto each line's chain of constraints
//! ([`chain`]), which needs only products with `R` and scales to 10^5 dwell points and more; and
//! the reference, sequential convex programming around the Clarabel QP (below), exact on small
//! cases and kept to check the other. The two chain as a third: the SCP started from the
//! squared-speed result, which it can only improve (it keeps its best feasible iterate).
//!
//! The feed at dwell point `j` is `v_j = ds_j / t_j` (mm/s, `ds_j` from
//! [`DwellPath::ds_mm`]). With constant acceleration between consecutive dwell points `j` and
//! `j+1`, a distance `s_j = |P_{j+1} - P_j|` apart, the machine needs
//! `|v_{j+1}^2 - v_j^2| <= 2 a_max s_j` (kinematics of uniform acceleration, `v^2 = u^2 + 2 a s`).
//! In dwell time this is not convex. Each SCP iteration linearises `v^2 = ds^2 / t^2` around the
//! current dwell times, adds the two linear rows per segment to the Clarabel QP of [`super::qp`]
//! together with a relative trust region `|t - t_k| <= tau t_k`, and solves. The trust region
//! halves after a step that violates the true constraint by more than the tolerance or worsens
//! the objective, and grows after a good step. The loop stops when the true constraint holds within
//! `constraint_tolerance` (1%) and the objective changes by less than `objective_tolerance`.
//!
//! **Lines.** Consecutive dwell points are on the same line unless the segment between them is a
//! *connecting move*: a segment at both of whose ends the path turns by more than
//! `corner_angle_deg` (the step between raster lines, for example). Connecting moves carry no
//! constraint (the machine reorients there); every other segment does. With the default 60 deg a
//! serpentine raster splits into its lines; a spiral is one line.
//!
//! **Start.** The SCP starts from a point that satisfies the limits: interval propagation of
//! `u_j = v_j^2` along each line (forward: reachable sets; backward: the value nearest to the
//! feed-limited optimum). An empty reachable set proves that no feed schedule meets the limits
//! inside the dwell bounds; that is an [`Error::InvalidInput`] naming the point.

pub mod chain;
mod speed;

use super::first_order::Data;
use super::qp::{self, ExtraRows};
use super::{DwellBounds, Problem, Settings, Solution, SolverKind, Status};
use crate::error::{Error, Result};
use crate::kinematics::lines::{
    constrained_segments, max_acceleration_mm_per_s2, segment_accelerations_mm_per_s2,
    segment_lengths_mm,
};
use crate::kinematics::{check_a_max_mm_per_s2, check_corner_angle_deg, DEFAULT_CORNER_ANGLE_DEG};
use crate::observer::{IterationInfo, Observer, Stage};
use crate::path::DwellPath;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// How the acceleration-limited problem is solved.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum AccelMethod {
    /// Projected gradient in squared speed: the limit in the plan's feeds (any size and operator).
    ///
    /// Accelerated projected gradient in squared speed ([`speed`]): products with `R` only, any
    /// operator, 10^5 points and more. The plan's own feeds meet the limit.
    SquaredSpeed,
    /// Sequential convex programming with one Clarabel QP per iteration: the reference for small
    /// cases (it needs the assembled `R`).
    ScpQp,
    /// Squared speed, then the SCP-QP from its result (QP-exact refinement; needs the assembled R).
    ///
    /// The squared-speed method, then the SCP-QP from its result: a KKT point of the first refined
    /// by the second (QP-exact where the QP is affordable; it needs the assembled `R`).
    SquaredSpeedThenScpQp,
    /// The default: the feed-limited optimum, then correction passes against the program executed
    /// at the limit, kept while the executed residual falls (the best part as executed).
    ///
    /// No constraint in the plan: the feed-limited optimum, then correction passes against the
    /// program executed at the limit with look-ahead (the set-up's
    /// [`crate::setup::Setup::solve`]): each pass re-solves for the target less the executed
    /// removal's departure from the plan's, `z - (h_exec - R t)`, from the last dwell times,
    /// and is kept while the executed residual falls. The controller holds the limit; the plan
    /// is the program as the controller runs it. The default: of the methods it leaves the
    /// smallest residual on the part as the machine makes it (the other methods meet the limit
    /// in the plan's feeds, and the controller's ramps then still depart from the plan). The
    /// dwell-level [`solve`] has no program to execute and returns the feed-limited optimum the
    /// passes start from.
    #[default]
    CorrectionPasses,
}

impl AccelMethod {
    /// Whether the method solves QPs with the assembled `R`.
    pub fn needs_assembled_r(self) -> bool {
        !matches!(
            self,
            AccelMethod::SquaredSpeed | AccelMethod::CorrectionPasses
        )
    }
}

/// Relative excess over the limit that a returned plan may show from rounding alone (the
/// acceleration recomputed from `t = ds / sqrt(u)` against the `u` a method held).
const LIMIT_HELD: f64 = 1e-9;

/// Relative excess over the limit up to which the feed-limited optimum is taken as meeting it
/// (round-off in `|v_{j+1}^2 - v_j^2| / (2 s)`): beyond it the constrained problem is solved.
const REFERENCE_MEETS_LIMIT: f64 = 1e-9;

/// Acceleration limit and solver settings. Job files may set any field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AccelLimits {
    /// Largest tangential acceleration of the machine along a line, mm/s^2.
    pub a_max_mm_per_s2: f64,
    /// A segment at both of whose ends the path turns by more than this angle, degrees, is a
    /// connecting move without a constraint (see the module documentation).
    pub corner_angle_deg: f64,
    /// Relative tolerance on the constraint: achieved `|dv^2| / (2 s) <= (1 + tol) a_max`.
    pub constraint_tolerance: f64,
    /// The objective has settled when it changes by less than this fraction between iterations.
    pub objective_tolerance: f64,
    /// Largest number of SCP iterations (QP solves after the feed-limited reference).
    pub max_iterations: usize,
    /// Initial relative trust region `tau`: `|t_j - t_j^k| <= tau t_j^k`.
    pub trust_region: f64,
    /// The method.
    pub method: AccelMethod,
    /// Squared-speed method: relative KKT residual at which it stops.
    pub kkt_tolerance: f64,
    /// Squared-speed method: gradient steps at most.
    pub max_gradient_steps: usize,
}

impl Default for AccelLimits {
    fn default() -> Self {
        Self {
            a_max_mm_per_s2: 1000.0,
            corner_angle_deg: DEFAULT_CORNER_ANGLE_DEG,
            constraint_tolerance: 0.01,
            objective_tolerance: 1e-4,
            max_iterations: 50,
            trust_region: 0.5,
            method: AccelMethod::default(),
            kkt_tolerance: 1e-4,
            max_gradient_steps: 20_000,
        }
    }
}

impl AccelLimits {
    /// Limits with `a_max` (mm/s^2) and default SCP settings.
    pub fn new(a_max_mm_per_s2: f64) -> Self {
        Self {
            a_max_mm_per_s2,
            ..Self::default()
        }
    }

    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        check_a_max_mm_per_s2(self.a_max_mm_per_s2)?;
        check_corner_angle_deg(self.corner_angle_deg)?;
        for (name, v) in [
            ("constraint_tolerance", self.constraint_tolerance),
            ("objective_tolerance", self.objective_tolerance),
        ] {
            if !(v.is_finite() && v > 0.0 && v < 1.0) {
                return Err(Error::invalid(name, format!("must be in (0, 1), got {v}")));
            }
        }
        if !(self.trust_region.is_finite() && self.trust_region > 0.0 && self.trust_region <= 1.0) {
            return Err(Error::invalid(
                "trust_region",
                format!("must be in (0, 1], got {}", self.trust_region),
            ));
        }
        if self.max_iterations == 0 {
            return Err(Error::invalid("max_iterations", "must be at least 1"));
        }
        if !(self.kkt_tolerance.is_finite() && self.kkt_tolerance > 0.0 && self.kkt_tolerance < 1.0)
        {
            return Err(Error::invalid(
                "kkt_tolerance",
                format!("must be in (0, 1), got {}", self.kkt_tolerance),
            ));
        }
        if self.max_gradient_steps == 0 {
            return Err(Error::invalid("max_gradient_steps", "must be at least 1"));
        }
        Ok(())
    }
}

/// What the acceleration-limited solve achieved, next to the feed-limited-only optimum.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AccelReport {
    /// The limit imposed, mm/s^2.
    pub a_max_mm_per_s2: f64,
    /// Largest `|v_{j+1}^2 - v_j^2| / (2 s_j)` over constrained segments of the result, mm/s^2.
    pub max_accel_mm_per_s2: f64,
    /// The same for the feed-limited-only optimum, mm/s^2.
    pub max_accel_reference_mm_per_s2: f64,
    /// The method that ran.
    pub method: AccelMethod,
    /// SCP iterations (QP solves after the reference; 0 for the squared-speed method).
    pub scp_iterations: usize,
    /// Squared-speed method: gradient steps after the reference (0 for the SCP).
    pub gradient_steps: usize,
    /// Squared-speed method: the last relative KKT residual.
    pub kkt_residual: Option<f64>,
    /// Segments that carry the constraint.
    pub constrained_segments: usize,
    /// Segments whose acceleration is within 1% of the limit (binding).
    pub binding_segments: usize,
    /// RMS of the predicted residual about its mean, nm: `sqrt(2 objective / m)`.
    pub rms_after_nm: f64,
    /// The same for the feed-limited-only optimum, nm.
    pub rms_after_reference_nm: f64,
    /// `0.5 ||R t - z - c||^2` of the result, nm^2.
    pub objective: f64,
    /// The same for the feed-limited-only optimum, nm^2.
    pub objective_reference: f64,
    /// Price of the limit: `objective - objective_reference`, nm^2 (non-negative up to solver
    /// tolerance when `rho = lambda = 0`).
    pub objective_gap: f64,
    /// How the SCP ended.
    pub status: Status,
}

/// The acceleration-limited solution with its report and the feed-limited reference.
#[derive(Debug, Clone, PartialEq)]
pub struct AccelSolution {
    /// The dwell times that meet the limit (the best point found that meets it within tolerance).
    pub solution: Solution,
    /// What was achieved.
    pub report: AccelReport,
    /// The feed-limited-only optimum the SCP started from.
    pub reference: Solution,
}

/// The kinematic data of the constraint: per point `ds`, per segment `2 a_max s` and whether it
/// is constrained.
struct LineCaps {
    ds: Vec<f64>,
    cap: Vec<f64>,
    constrained: Vec<bool>,
}

impl LineCaps {
    fn new(path: &DwellPath, limits: &AccelLimits) -> Self {
        let seg = segment_lengths_mm(path);
        Self {
            ds: path.ds_mm(),
            cap: seg
                .iter()
                .map(|s| 2.0 * limits.a_max_mm_per_s2 * s)
                .collect(),
            constrained: constrained_segments(path, limits.corner_angle_deg),
        }
    }

    fn v2(&self, j: usize, t: &[f64]) -> f64 {
        let d = self.ds[j];
        if d == 0.0 {
            0.0
        } else {
            (d / t[j]) * (d / t[j])
        }
    }

    /// Largest `|dv^2| / cap - 1` over constrained segments (<= 0: the limit holds).
    fn violation(&self, t: &[f64]) -> f64 {
        let mut worst = f64::NEG_INFINITY;
        for j in 0..self.cap.len() {
            if !self.constrained[j] {
                continue;
            }
            let g = (self.v2(j + 1, t) - self.v2(j, t)).abs();
            let r = if self.cap[j] > 0.0 {
                g / self.cap[j] - 1.0
            } else if g > 0.0 {
                f64::INFINITY
            } else {
                -1.0
            };
            worst = worst.max(r);
        }
        if worst == f64::NEG_INFINITY {
            -1.0
        } else {
            worst
        }
    }
}

/// Solves the dwell problem with the acceleration limit: first the feed-limited optimum
/// ([`super::solve`]), then the SCP. `settings` apply to each QP; the SCP minimises the contract
/// objective (minimum-time mode applies to the reference only).
pub fn solve(
    problem: &Problem,
    path: &DwellPath,
    limits: &AccelLimits,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<AccelSolution> {
    limits.validate()?;
    settings.validate()?;
    solve_validated(problem, path, limits, settings, observer)
}

/// As [`solve`], with `limits` and `settings` already validated (by
/// [`crate::setup::Choices::check`]).
pub(crate) fn solve_validated(
    problem: &Problem,
    path: &DwellPath,
    limits: &AccelLimits,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<AccelSolution> {
    let start = Instant::now();
    let n = problem.n();
    if path.len() != n {
        return Err(Error::LengthMismatch {
            what: "dwell path",
            got: path.len(),
            expected: n,
        });
    }
    let kin = LineCaps::new(path, limits);
    let bounds = problem.bounds();
    let (lo_u, hi_u) = speed_boxes(&kin, bounds)?;
    let reachable = forward_reachable(&kin, &lo_u, &hi_u, limits)?;
    let limited = Limited {
        problem,
        kin: &kin,
        reachable: &reachable,
        limits,
        settings,
        observer,
    };
    let reference = super::solve_validated(
        problem,
        &reference_settings(limits, settings),
        observer,
        None,
    )?;
    let run = limited.constrain(&reference)?;

    // The status speaks for the dwell times returned: a result whose acceleration, recomputed
    // from the dwell times as every report does, exceeds the limit beyond the constraint
    // tolerance is not converged, whatever the method's own stopping test said. Under
    // correction passes the controller holds the limit, not the dwell times.
    let status = if limits.method != AccelMethod::CorrectionPasses
        && run.status.is_converged()
        && kin.violation(&run.dwell_s) > limits.constraint_tolerance
    {
        Status::Stalled
    } else {
        run.status
    };
    let eval = problem.evaluate(&run.dwell_s)?;
    let report = accel_report(&limited, path, &run, &reference, eval.objective, status);
    let kkt_residual = run.kkt_residual;
    let solution = Solution {
        status,
        solver: run.solver,
        piston_nm: eval.piston_nm,
        objective: eval.objective,
        dwell_s: run.dwell_s,
        iterations: reference.iterations + run.qp_iterations,
        solve_seconds: start.elapsed().as_secs_f64(),
        kkt_residual,
        objective_gap_bound: None,
        gap_bound_reason: Some(super::certificate::GapBoundReason::NonConvexAccelerationLimit),
        converged_by: (kkt_residual.is_some() && status == Status::Converged)
            .then_some(super::certificate::ConvergenceCriterion::KktResidual),
        min_time: reference.min_time,
    };
    Ok(AccelSolution {
        solution,
        report,
        reference,
    })
}

/// Gradient steps at most of the squared-speed plan [`squared_speed_candidate`] makes next to
/// the correction passes: a tenth of the default [`AccelLimits::max_gradient_steps`]. A plan
/// stopped there still meets the limit (clamped onto the reachable chain) and is judged, like
/// the passes' plan, by its executed residual.
pub(crate) const CANDIDATE_GRADIENT_STEPS: usize = 2_000;

/// The squared-speed plan of `problem` (the limit in the plan's own feeds; `limits` but for the
/// method and at most [`CANDIDATE_GRADIENT_STEPS`] gradient steps), solved as
/// `--accel-method squared-speed` solves it, from its own feed-limited reference at that
/// method's tolerance. `None` where `reference`, the feed-limited optimum the correction passes
/// start from, meets the limit (to round-off): then no ramp departs from it.
pub(crate) fn squared_speed_candidate(
    problem: &Problem,
    path: &DwellPath,
    limits: &AccelLimits,
    settings: &Settings,
    observer: &dyn Observer,
    reference: &Solution,
) -> Result<Option<AccelSolution>> {
    let limits = AccelLimits {
        method: AccelMethod::SquaredSpeed,
        max_gradient_steps: limits.max_gradient_steps.min(CANDIDATE_GRADIENT_STEPS),
        ..limits.clone()
    };
    if path.len() == reference.dwell_s.len()
        && LineCaps::new(path, &limits).violation(&reference.dwell_s) <= REFERENCE_MEETS_LIMIT
    {
        return Ok(None);
    }
    solve_validated(problem, path, &limits, settings, observer).map(Some)
}

/// The settings of the feed-limited reference solve. The feed-limited optimum is the start and
/// the price-of-the-limit reference; for the squared-speed method a first-order reference is
/// solved to that method's own tolerance.
fn reference_settings(limits: &AccelLimits, settings: &Settings) -> Settings {
    match limits.method {
        AccelMethod::SquaredSpeed | AccelMethod::SquaredSpeedThenScpQp => Settings {
            first_order_tolerance: settings.first_order_tolerance.max(limits.kkt_tolerance),
            ..settings.clone()
        },
        AccelMethod::ScpQp | AccelMethod::CorrectionPasses => settings.clone(),
    }
}

/// One acceleration-limited solve: the problem, the path's kinematics and the reachable speed
/// boxes along it, the limits and settings.
struct Limited<'a> {
    problem: &'a Problem,
    kin: &'a LineCaps,
    reachable: &'a [(f64, f64)],
    limits: &'a AccelLimits,
    settings: &'a Settings,
    observer: &'a dyn Observer,
}

/// What the limited solve returned beyond the reference: the dwell times, their status and
/// solver, and the iterations it took.
struct LimitedRun {
    dwell_s: Vec<f64>,
    status: Status,
    solver: SolverKind,
    scp_iterations: usize,
    gradient_steps: usize,
    kkt_residual: Option<f64>,
    /// QP iterations or gradient steps on top of the reference's iterations.
    qp_iterations: usize,
}

impl LimitedRun {
    /// The reference's dwell times kept as they are.
    fn reference(reference: &Solution) -> Self {
        Self {
            dwell_s: reference.dwell_s.clone(),
            status: reference.status,
            solver: reference.solver,
            scp_iterations: 0,
            gradient_steps: 0,
            kkt_residual: None,
            qp_iterations: 0,
        }
    }
}

impl Limited<'_> {
    /// The dwell times under the limit, from the feed-limited `reference` by the method of
    /// the limits.
    fn constrain(&self, reference: &Solution) -> Result<LimitedRun> {
        if self.limits.method == AccelMethod::CorrectionPasses {
            // The controller holds the limit on the feed-limited optimum.
            return Ok(LimitedRun::reference(reference));
        }
        if self.kin.violation(&reference.dwell_s) <= REFERENCE_MEETS_LIMIT {
            // The feed-limited optimum meets the limit (to round-off): nothing to constrain. One
            // that exceeds it at all, even within the constraint tolerance, is solved for below.
            return Ok(LimitedRun::reference(reference));
        }
        match self.limits.method {
            AccelMethod::ScpQp => self.scp_qp(&reference.dwell_s),
            AccelMethod::SquaredSpeed
            | AccelMethod::SquaredSpeedThenScpQp
            | AccelMethod::CorrectionPasses => self.squared_speed(&reference.dwell_s),
        }
    }

    /// The SCP around the QP, from the feasible start nearest the reference.
    fn scp_qp(&self, reference_dwell_s: &[f64]) -> Result<LimitedRun> {
        let (problem, kin, bounds) = (self.problem, self.kin, self.problem.bounds());
        let start = feasible_start(kin, self.reachable, reference_dwell_s, bounds);
        let r = scp(
            problem,
            kin,
            start,
            self.limits,
            self.settings,
            self.observer,
        )?;
        Ok(LimitedRun {
            dwell_s: onto_the_limit(kin, self.reachable, r.dwell_s, bounds),
            status: r.status,
            solver: SolverKind::Qp,
            scp_iterations: r.iterations,
            gradient_steps: 0,
            kkt_residual: None,
            qp_iterations: r.qp_iterations,
        })
    }

    /// The squared-speed method from the reference, then (`SquaredSpeedThenScpQp`) the SCP
    /// from its result.
    fn squared_speed(&self, reference_dwell_s: &[f64]) -> Result<LimitedRun> {
        let (problem, kin, limits, observer) = (self.problem, self.kin, self.limits, self.observer);
        let bounds = problem.bounds();
        let speed_limits = speed::SpeedLimits {
            tolerance: limits.kkt_tolerance,
            max_steps: limits.max_gradient_steps,
            time_limit_s: self.settings.time_limit_s,
        };
        // The power iteration alone pays for a Gram matrix where the first-order
        // solvers form one.
        let products = super::first_order::POWER_STEPS;
        let r = super::with_solver_operator(problem, products, limits.kkt_tolerance, |op| {
            let (data, mut work, kkt_scale) =
                Data::prepare(op, problem.z_nm(), bounds, problem.rho(), problem.lambda());
            // On a worker of the pool, as the first-order solvers run: called
            // from outside it, every parallel loop would wait on a futex.
            Ok(rayon::scope(|_| {
                speed::minimise(
                    &data,
                    &mut work,
                    kkt_scale,
                    kin,
                    reference_dwell_s,
                    &speed_limits,
                    observer,
                    Some(problem.scaled_hessian_norm()),
                )
            }))
        })?;
        crate::observer::check_cancelled(observer)?;
        // The iteration ends on the constraint set up to rounding; should it end further off,
        // the squared speeds are clamped into the reachable chain, which one feed schedule
        // within the bounds always satisfies, so the limit holds in what is returned. The
        // iteration's status stands for the clamped plan only where the clamp cost no more
        // than the method's tolerance in objective.
        let r = if kin.violation(&r.dwell_s) > LIMIT_HELD {
            let clamped = feasible_start(kin, self.reachable, &r.dwell_s, bounds);
            let (before, after) = (
                problem.evaluate(&r.dwell_s)?.objective,
                problem.evaluate(&clamped)?.objective,
            );
            let status = if after <= before + limits.kkt_tolerance * before.abs() {
                r.status
            } else {
                Status::Stalled
            };
            speed::SpeedResult {
                dwell_s: clamped,
                status,
                ..r
            }
        } else {
            r
        };
        if limits.method != AccelMethod::SquaredSpeedThenScpQp {
            return Ok(LimitedRun {
                dwell_s: r.dwell_s,
                status: r.status,
                solver: SolverKind::FirstOrder,
                scp_iterations: 0,
                gradient_steps: r.iterations,
                kkt_residual: Some(r.kkt_residual),
                qp_iterations: r.iterations,
            });
        }
        // The squared-speed result meets the limit exactly: the SCP starts there.
        let start = r.dwell_s.clone();
        let polished = scp(problem, kin, r.dwell_s, limits, self.settings, observer)?;
        // Clamping an SCP iterate that overshoots the limit can cost more than the
        // SCP gained: keep whichever of it and the squared-speed start (exactly on
        // the limit) has the lower objective, so the refinement never loses.
        let clamped = onto_the_limit(kin, self.reachable, polished.dwell_s, bounds);
        let best = if problem.evaluate(&clamped)?.objective <= problem.evaluate(&start)?.objective {
            clamped
        } else {
            start
        };
        Ok(LimitedRun {
            dwell_s: best,
            status: polished.status,
            solver: SolverKind::Qp,
            scp_iterations: polished.iterations,
            gradient_steps: r.iterations,
            kkt_residual: None,
            qp_iterations: r.iterations + polished.qp_iterations,
        })
    }
}

/// What the limited solve achieved next to the feed-limited `reference` (`objective`: the
/// limited run's objective; `status`: its final status).
fn accel_report(
    limited: &Limited<'_>,
    path: &DwellPath,
    run: &LimitedRun,
    reference: &Solution,
    objective: f64,
    status: Status,
) -> AccelReport {
    let limits = limited.limits;
    let best_t = &run.dwell_s;
    let ref_eval_obj = reference.objective;
    let m = limited.problem.m() as f64;
    let max_a = max_acceleration_mm_per_s2(path, best_t, limits.corner_angle_deg);
    let accels = segment_accelerations_mm_per_s2(path, best_t, limits.corner_angle_deg);
    AccelReport {
        a_max_mm_per_s2: limits.a_max_mm_per_s2,
        max_accel_mm_per_s2: max_a,
        max_accel_reference_mm_per_s2: max_acceleration_mm_per_s2(
            path,
            &reference.dwell_s,
            limits.corner_angle_deg,
        ),
        method: limits.method,
        scp_iterations: run.scp_iterations,
        gradient_steps: run.gradient_steps,
        kkt_residual: run.kkt_residual,
        constrained_segments: limited.kin.constrained.iter().filter(|&&c| c).count(),
        binding_segments: accels
            .iter()
            .flatten()
            .filter(|&&a| a >= 0.99 * limits.a_max_mm_per_s2)
            .count(),
        rms_after_nm: (2.0 * objective / m).max(0.0).sqrt(),
        rms_after_reference_nm: (2.0 * ref_eval_obj / m).max(0.0).sqrt(),
        objective,
        objective_gap: objective - ref_eval_obj,
        objective_reference: ref_eval_obj,
        status,
    }
}

/// What the SCP returns.
struct ScpResult {
    dwell_s: Vec<f64>,
    status: Status,
    iterations: usize,
    qp_iterations: usize,
}

/// Sequential convex programming from the feasible `start` (see the module documentation).
fn scp(
    problem: &Problem,
    kin: &LineCaps,
    start: Vec<f64>,
    limits: &AccelLimits,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<ScpResult> {
    let bounds = problem.bounds();
    let settle_scale = 1e-12 * 0.5 * problem.z_nm().iter().map(|z| z * z).sum::<f64>();
    let tol = limits.constraint_tolerance;
    let mut t = start;
    let mut best_t = t.clone();
    let mut best_f = problem.evaluate(&t)?.full_objective;
    let mut prev_f = best_f;
    let mut tau = limits.trust_region;
    let mut status = Status::MaxIterations;
    let mut iterations = 0;
    let mut qp_iterations = 0;
    observer.start(Stage::Loop, limits.max_iterations as u64);
    while iterations < limits.max_iterations {
        crate::observer::check_cancelled(observer)?;
        iterations += 1;
        let (trust, rows) = linearise(kin, &t, bounds, tau)?;
        let (st, t_new, it) = qp::solve_with_rows(problem, &trust, &rows, settings, observer)?;
        qp_iterations += it;
        observer.advance(Stage::Loop, 1);
        if !st.is_converged() {
            // Restart from the best point with a smaller region.
            t = best_t.clone();
            prev_f = best_f;
            tau *= 0.5;
            if tau < 1e-6 {
                break;
            }
            continue;
        }
        let mut t_new = t_new;
        bounds.project(&mut t_new);
        let f = problem.evaluate(&t_new)?.full_objective;
        let viol = kin.violation(&t_new);
        observer.iteration(&IterationInfo {
            iteration: iterations,
            objective: f,
            kkt_residual: None,
        });
        let feasible = viol <= tol;
        let settled = (f - prev_f).abs() <= limits.objective_tolerance * f.abs().max(settle_scale);
        if feasible && f <= best_f {
            best_f = f;
            best_t = t_new.clone();
        }
        if feasible && settled {
            status = Status::Converged;
            if f <= best_f {
                best_t = t_new;
            }
            break;
        }
        if !feasible || f > prev_f {
            tau = (tau * 0.5).max(1e-6);
        } else {
            tau = (tau * 1.5).min(limits.trust_region);
        }
        prev_f = f;
        t = t_new;
    }
    observer.finish(Stage::Loop);
    Ok(ScpResult {
        dwell_s: best_t,
        status,
        iterations,
        qp_iterations,
    })
}

/// Boxes on `u_j = v_j^2` implied by the dwell bounds: `[(ds/ub)^2, (ds/lb)^2]`, mm^2/s^2.
fn speed_boxes(kin: &LineCaps, bounds: &DwellBounds) -> Result<(Vec<f64>, Vec<f64>)> {
    let n = kin.ds.len();
    let mut lo = vec![0.0; n];
    let mut hi = vec![0.0; n];
    for j in 0..n {
        let d = kin.ds[j];
        if d == 0.0 {
            continue;
        }
        let lb = bounds.lower_s()[j];
        if !(lb > 0.0) {
            return Err(Error::invalid(
                "dwell lower bound",
                format!(
                    "point {j}: acceleration limits need a positive lower dwell bound \
                     (a finite maximum feed), got {lb} s"
                ),
            ));
        }
        let ub = bounds.upper(j);
        lo[j] = if ub.is_finite() {
            (d / ub).powi(2)
        } else {
            0.0
        };
        hi[j] = (d / lb).powi(2);
    }
    Ok((lo, hi))
}

/// Forward reachable intervals of `u_j` along each line; an empty one is an error.
fn forward_reachable(
    kin: &LineCaps,
    lo: &[f64],
    hi: &[f64],
    limits: &AccelLimits,
) -> Result<Vec<(f64, f64)>> {
    let n = lo.len();
    let mut out = Vec::with_capacity(n);
    out.push((lo[0], hi[0]));
    for j in 0..n.saturating_sub(1) {
        let (plo, phi) = out[j];
        let (mut a, mut b) = (lo[j + 1], hi[j + 1]);
        if kin.constrained[j] {
            a = a.max(plo - kin.cap[j]);
            b = b.min(phi + kin.cap[j]);
        }
        if a > b * (1.0 + 1e-12) + 1e-300 {
            let fmt = |u: f64| u.max(0.0).sqrt() * 60.0;
            return Err(Error::invalid(
                "a_max_mm_per_s2",
                format!(
                    "no feed schedule meets {} mm/s^2 within the feed limits: dwell point {} \
                     needs a feed in [{:.6}, {:.6}] mm/min but from point {} only \
                     [{:.6}, {:.6}] mm/min can be reached over {:.6} mm",
                    limits.a_max_mm_per_s2,
                    j + 1,
                    fmt(lo[j + 1]),
                    fmt(hi[j + 1]),
                    j,
                    fmt(plo - kin.cap[j]),
                    fmt(phi + kin.cap[j]),
                    kin.cap[j] / (2.0 * limits.a_max_mm_per_s2)
                ),
            ));
        }
        out.push((a, b.max(a)));
    }
    Ok(out)
}

/// Backward pass: `u_j` nearest to the target inside the reachable interval and within `cap` of
/// `u_{j+1}`; returns dwell times `t_j = ds_j / sqrt(u_j)`.
/// The SCP's result moved onto the limit itself: the SCP accepts an iterate whose acceleration
/// exceeds `a_max` by up to the constraint tolerance (its linearisation is exact only at the
/// iterate), so the squared speeds of an iterate that exceeds it at all are clamped into the
/// constraint, as [`feasible_start`] does, and the limit holds as reported. An iterate that
/// meets the limit is returned unchanged.
fn onto_the_limit(
    kin: &LineCaps,
    reach: &[(f64, f64)],
    t: Vec<f64>,
    bounds: &DwellBounds,
) -> Vec<f64> {
    if kin.violation(&t) <= 0.0 {
        return t;
    }
    feasible_start(kin, reach, &t, bounds)
}

fn feasible_start(
    kin: &LineCaps,
    reach: &[(f64, f64)],
    target_t: &[f64],
    bounds: &DwellBounds,
) -> Vec<f64> {
    let n = reach.len();
    let target_u = |j: usize| -> f64 {
        let t = target_t.get(j).copied().unwrap_or(0.0);
        if t > 0.0 {
            (kin.ds[j] / t).powi(2)
        } else {
            f64::INFINITY
        }
    };
    let mut u = vec![0.0; n];
    for j in (0..n).rev() {
        let (mut a, mut b) = reach[j];
        if j + 1 < n && kin.constrained[j] {
            a = a.max(u[j + 1] - kin.cap[j]);
            b = b.min(u[j + 1] + kin.cap[j]);
        }
        u[j] = if a <= b {
            target_u(j).clamp(a, b)
        } else {
            0.5 * (a + b)
        };
    }
    let mut t: Vec<f64> = (0..n)
        .map(|j| {
            if kin.ds[j] == 0.0 || u[j] <= 0.0 {
                if kin.ds[j] == 0.0 {
                    target_t.get(j).copied().unwrap_or(0.0)
                } else {
                    bounds.upper(j)
                }
            } else {
                kin.ds[j] / u[j].sqrt()
            }
        })
        .collect();
    bounds.project(&mut t);
    t
}

/// The trust-region box and the linearised rows around `t`.
fn linearise(
    kin: &LineCaps,
    t: &[f64],
    bounds: &DwellBounds,
    tau: f64,
) -> Result<(DwellBounds, ExtraRows)> {
    let n = t.len();
    let lower: Vec<f64> = (0..n)
        .map(|j| bounds.lower_s()[j].max(t[j] * (1.0 - tau)))
        .collect();
    let upper: Vec<f64> = (0..n)
        .map(|j| bounds.upper(j).min(t[j] * (1.0 + tau)).max(lower[j]))
        .collect();
    let trust = DwellBounds::new(lower, Some(upper))?;
    // p_j(t) = ds_j^2 / t_j^2, p'_j = -2 ds_j^2 / t_j^3.
    let p = |j: usize| kin.v2(j, t);
    let dp = |j: usize| {
        if kin.ds[j] == 0.0 {
            0.0
        } else {
            -2.0 * p(j) / t[j]
        }
    };
    let mut rows = ExtraRows {
        by_column: vec![Vec::new(); n],
        rhs: Vec::new(),
    };
    for j in 0..n.saturating_sub(1) {
        if !kin.constrained[j] {
            continue;
        }
        let cap = kin.cap[j];
        // Scale each row by 1 / cap (or by 1 / |g0| scale where cap is 0).
        let scale = if cap > 0.0 {
            1.0 / cap
        } else {
            1.0 / (p(j) + p(j + 1)).max(1e-12)
        };
        let g0 = p(j + 1) - p(j);
        let (a1, a0) = (dp(j + 1), -dp(j));
        let lin0 = a1 * t[j + 1] + a0 * t[j];
        // g0 + a1 (t1 - t1k) + a0 (t0 - t0k) <= cap
        let r_up = rows.rhs.len();
        rows.rhs.push(scale * (cap - g0 + lin0));
        rows.by_column[j + 1].push((r_up, scale * a1));
        rows.by_column[j].push((r_up, scale * a0));
        // -(...) <= cap
        let r_dn = rows.rhs.len();
        rows.rhs.push(scale * (cap + g0 - lin0));
        rows.by_column[j + 1].push((r_dn, -scale * a1));
        rows.by_column[j].push((r_dn, -scale * a0));
    }
    Ok((trust, rows))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwell::FeedLimits;
    use crate::influence::InfluenceMatrix;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    /// A 1-D line of dwell points over a map with a deep trench: the feed-limited optimum slows
    /// sharply, so a small acceleration limit binds.
    fn trench_problem(a_free: bool) -> (Problem, DwellPath) {
        trench_problem_on((0..161).map(|i| -2.0 + i as f64 * 0.15).collect(), a_free)
    }

    /// The trench line measured at `mx` (mm, on the line y = 0).
    fn trench_problem_on(mx: Vec<f64>, a_free: bool) -> (Problem, DwellPath) {
        let pitch = 0.5;
        let n = 41;
        let xs: Vec<f64> = (0..n).map(|j| j as f64 * pitch).collect();
        let path = DwellPath::new(xs.clone(), vec![0.0; n]).unwrap();
        let my = vec![0.0; mx.len()];
        let z: Vec<f64> = mx
            .iter()
            .map(|&x| 50.0 + 400.0 * (-(x - 10.0f64).powi(2) / 2.0).exp())
            .collect();
        let tif = GaussianTif::new(1.0, 100.0, 3.0).unwrap();
        let r = InfluenceMatrix::assemble(&mx, &my, &xs, &vec![0.0; n], &tif, &Silent).unwrap();
        let lim = FeedLimits {
            v_max_mm_per_min: 600.0,
            v_min_mm_per_min: if a_free { 0.0 } else { 6.0 },
        };
        let b = DwellBounds::from_feeds(&path.ds_mm(), &lim).unwrap();
        (Problem::new(r, z, b, 0.0, 0.0).unwrap(), path)
    }

    #[test]
    fn lines_split_at_raster_steps() {
        // Two lines of three points joined by a step in y.
        let p = DwellPath::new(
            vec![0.0, 1.0, 2.0, 2.0, 1.0, 0.0],
            vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
        )
        .unwrap();
        let c = constrained_segments(&p, 60.0);
        assert_eq!(c, vec![true, true, false, true, true]);
        let whole = constrained_segments(&p, 180.0);
        assert!(whole.iter().all(|&b| b));
    }

    #[test]
    fn segment_acceleration_matches_kinematics() {
        // Uniform pitch 1 mm, ds = 1 mm: v = 1/t; from 10 to 20 mm/s over 1 mm: (400-100)/2.
        let p = DwellPath::new(vec![0.0, 1.0, 2.0], vec![0.0; 3]).unwrap();
        let a = segment_accelerations_mm_per_s2(&p, &[0.1, 0.05, 0.05], 60.0);
        assert!((a[0].unwrap() - 150.0).abs() < 1e-9);
        assert!(a[1].unwrap().abs() < 1e-9);
    }

    #[test]
    fn scp_meets_binding_limit() {
        let (problem, path) = trench_problem(false);
        let settings = Settings::default();
        let free = crate::dwell::solve(&problem, &settings, &Silent).unwrap();
        let a_free = max_acceleration_mm_per_s2(&path, &free.dwell_s, 60.0);
        let a_max = 0.2 * a_free;
        let limits = with_method(a_max, AccelMethod::SquaredSpeed);
        let out = solve(&problem, &path, &limits, &settings, &Silent).unwrap();
        let a = max_acceleration_mm_per_s2(&path, &out.solution.dwell_s, 60.0);
        assert!(
            a <= a_max * (1.0 + limits.constraint_tolerance),
            "{a} > {a_max}"
        );
        assert!(out.report.binding_segments > 0, "{:?}", out.report);
        assert!(out.solution.objective >= free.objective * (1.0 - 1e-6));
        assert_eq!(out.solution.status, Status::Converged, "{:?}", out.report);
        assert!(problem.bounds().max_violation_s(&out.solution.dwell_s) < 1e-12);
    }

    /// Relative rounding allowed on a limit a method reports as held: the recomputed acceleration
    /// `|v_{j+1}^2 - v_j^2| / (2 s_j)` of dwell times `t = ds / sqrt(u)` differs from the `u` the
    /// method held by a few ulps.
    const LIMIT_ROUNDING: f64 = 1e-9;

    /// Every method that reports the limit held holds it in the dwell times it returns, not only
    /// within the SCP's acceptance tolerance (1%), over limits from loose to binding.
    #[test]
    fn every_method_holds_the_limit_it_reports() {
        let (problem, path) = trench_problem(false);
        let settings = Settings::default();
        let free = crate::dwell::solve(&problem, &settings, &Silent).unwrap();
        let a_free = max_acceleration_mm_per_s2(&path, &free.dwell_s, 60.0);
        for method in [
            AccelMethod::ScpQp,
            AccelMethod::SquaredSpeed,
            AccelMethod::SquaredSpeedThenScpQp,
        ] {
            for fraction in [0.05, 0.2, 0.5, 0.9] {
                let a_max = fraction * a_free;
                let out = solve(
                    &problem,
                    &path,
                    &with_method(a_max, method),
                    &settings,
                    &Silent,
                )
                .unwrap();
                let a = max_acceleration_mm_per_s2(&path, &out.solution.dwell_s, 60.0);
                assert!(
                    a <= a_max * (1.0 + LIMIT_ROUNDING),
                    "{method:?} at {fraction} of the free acceleration: {a} > {a_max}"
                );
                assert!((out.report.max_accel_mm_per_s2 - a).abs() <= 1e-12 * a_max);
                assert!(out.solution.status.is_converged(), "{:?}", out.report);
            }
        }
    }

    /// The squared-speed method's objective may exceed the SCP reference's by this fraction (the
    /// target for cases of at most 500 points).
    const OBJECTIVE_TO_REFERENCE: f64 = 0.01;

    fn with_method(a_max: f64, method: AccelMethod) -> AccelLimits {
        AccelLimits {
            method,
            ..AccelLimits::new(a_max)
        }
    }

    #[test]
    fn squared_speed_meets_the_limit_and_matches_the_scp_reference() {
        check_squared_speed_against_scp(trench_problem(false));
    }

    /// The map only under the path (the measured points are the dwell points): the residual
    /// falls to under 1% of the error, and the stopping test must not stop early there.
    #[test]
    fn squared_speed_matches_the_scp_reference_when_the_residual_falls_a_hundredfold() {
        let mx: Vec<f64> = (0..41).map(|i| i as f64 * 0.5).collect();
        check_squared_speed_against_scp(trench_problem_on(mx, false));
    }

    fn check_squared_speed_against_scp((problem, path): (Problem, DwellPath)) {
        let settings = Settings::default();
        let free = crate::dwell::solve(&problem, &settings, &Silent).unwrap();
        let a_free = max_acceleration_mm_per_s2(&path, &free.dwell_s, 60.0);
        for frac in [0.5, 0.2, 0.05] {
            let a_max = frac * a_free;
            let run = |method| {
                solve(
                    &problem,
                    &path,
                    &with_method(a_max, method),
                    &settings,
                    &Silent,
                )
                .unwrap()
            };
            let reference = run(AccelMethod::ScpQp);
            let fast = run(AccelMethod::SquaredSpeed);
            let t = &fast.solution.dwell_s;
            // Exactly on the constraint set (up to rounding), inside the dwell bounds.
            let a = max_acceleration_mm_per_s2(&path, t, 60.0);
            assert!(a <= a_max * (1.0 + 1e-9), "fraction {frac}: {a} > {a_max}");
            assert!(problem.bounds().max_violation_s(t) < 1e-12);
            assert!(fast.report.binding_segments > 0, "{:?}", fast.report);
            assert_eq!(fast.report.method, AccelMethod::SquaredSpeed);
            let (f, f_ref) = (fast.solution.objective, reference.solution.objective);
            assert!(
                f <= f_ref * (1.0 + OBJECTIVE_TO_REFERENCE),
                "fraction {frac}: objective {f} against the SCP's {f_ref} ({:?})",
                fast.report
            );
            assert!(f >= free.objective * (1.0 - 1e-6));
            // The SCP from the squared-speed result keeps the limit and never loses objective.
            let refined = run(AccelMethod::SquaredSpeedThenScpQp);
            let t = &refined.solution.dwell_s;
            let a = max_acceleration_mm_per_s2(&path, t, 60.0);
            let tolerance = AccelLimits::default().constraint_tolerance;
            assert!(a <= a_max * (1.0 + tolerance), "fraction {frac}: {a}");
            assert!(refined.report.gradient_steps > 0 && refined.report.scp_iterations > 0);
            assert!(
                refined.solution.objective <= f * (1.0 + 1e-12),
                "fraction {frac}: refined {} above its start {f}",
                refined.solution.objective
            );
        }
    }

    #[test]
    fn squared_speed_serves_the_fft_operator_as_the_assembled_r() {
        // A 2-D serpentine raster on the map's 0.5 mm lattice: the FFT operator applies.
        use crate::influence::operator::fft::FftOperator;
        let (mut mx, mut my, mut z) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..25 {
            for i in 0..41 {
                let (x, y) = (0.5 * i as f64, 0.5 * j as f64);
                mx.push(x);
                my.push(y);
                z.push(30.0 + 200.0 * (-((x - 8.0).powi(2) + (y - 6.0).powi(2)) / 3.0).exp());
            }
        }
        let (mut px, mut py) = (Vec::new(), Vec::new());
        for j in 0..9 {
            for k in 0..15 {
                let i = if j % 2 == 0 { k } else { 14 - k };
                px.push(3.0 + 1.0 * i as f64);
                py.push(2.0 + 1.0 * j as f64);
            }
        }
        let path = DwellPath::new(px.clone(), py.clone()).unwrap();
        let tif = GaussianTif::new(1.0, 100.0, 3.0).unwrap();
        let lim = FeedLimits {
            v_max_mm_per_min: 600.0,
            v_min_mm_per_min: 0.0,
        };
        let b = DwellBounds::from_feeds(&path.ds_mm(), &lim).unwrap();
        let r = InfluenceMatrix::assemble(&mx, &my, &px, &py, &tif, &Silent).unwrap();
        let sparse = Problem::new(r, z.clone(), b.clone(), 0.0, 0.0).unwrap();
        let fft = FftOperator::new(&mx, &my, &px, &py, 0.5, &tif).unwrap();
        let matrix_free = Problem::new(fft, z, b, 0.0, 0.0).unwrap();
        let settings = Settings {
            solver: crate::dwell::SolverChoice::FirstOrder,
            ..Settings::default()
        };
        let free = crate::dwell::solve(&sparse, &settings, &Silent).unwrap();
        let a_max = 0.1 * max_acceleration_mm_per_s2(&path, &free.dwell_s, 60.0);
        let limits = with_method(a_max, AccelMethod::SquaredSpeed);
        let a = solve(&sparse, &path, &limits, &settings, &Silent).unwrap();
        let f = solve(&matrix_free, &path, &limits, &settings, &Silent).unwrap();
        for out in [&a, &f] {
            let t = &out.solution.dwell_s;
            assert!(max_acceleration_mm_per_s2(&path, t, 60.0) <= a_max * (1.0 + 1e-9));
            assert!(out.report.binding_segments > 0);
        }
        // The two operators agree to rounding, so the iterations land together.
        let (fa, ff) = (a.solution.objective, f.solution.objective);
        assert!((fa - ff).abs() <= 1e-3 * fa, "{fa} vs {ff}");
    }

    #[test]
    fn impossible_limits_are_errors() {
        // Point 1 must be slow (>= 1 s dwell), its neighbours fast, 1 mm apart, tiny a_max.
        let path = DwellPath::new(vec![0.0, 1.0, 2.0], vec![0.0; 3]).unwrap();
        let b = DwellBounds::new(vec![0.01, 1.0, 0.01], Some(vec![0.011, 2.0, 0.011])).unwrap();
        let r = nalgebra_sparse::CscMatrix::identity(3);
        let problem =
            Problem::new(InfluenceMatrix::from_csc(r), vec![1.0; 3], b, 0.0, 0.0).unwrap();
        let err = solve(
            &problem,
            &path,
            &AccelLimits::new(1.0),
            &Settings::default(),
            &Silent,
        )
        .unwrap_err();
        assert!(err.to_string().contains("no feed schedule"), "{err}");
    }
}
