//! [`Setup::solve`]: the dwell solve (with the acceleration limit's methods and the correction
//! passes against the executed program), the exact residual of approximate operators, the
//! sensitivity; and the plans evaluated as given ([`Setup::removal_of`], [`Setup::run_program`]).

use super::*;
use crate::dwell::first_order::FIT_RMS_SETTLED_NM;
use crate::observer::check_cancelled;
use crate::simulate::contact::{contact_removal, contact_removals, ContactPart};
use crate::simulate::plan::{path_motion, push_stretch};
use crate::simulate::SampledProgram;
use crate::tif::Perturbation;

/// Most correction passes against the executed program.
pub const MAX_CORRECTION_PASSES: usize = 4;

/// Smallest relative fall of the executed RMS for which a correction pass is kept. A kept pass
/// that lowered it by less than [`FIT_RMS_SETTLED_NM`] (the fall the solver counts as settled)
/// is the last.
pub const PASS_GAIN: f64 = 1e-3;

/// The exact removal and the operator's error on it.
pub(super) struct Exact {
    pub(super) exact_removal_nm: Vec<f64>,
    pub(super) error: OperatorError,
}

/// Whether every figure of a solve is finite and within physical range (a dwell of more than
/// 10^12 s, a piston or removal of more than 10^12 nm is a run-away iteration).
pub(super) fn solution_is_finite(solution: &Solution, removal_nm: &[f64]) -> bool {
    const RUNAWAY: f64 = 1e12;
    let ok = |v: f64| v.is_finite() && v.abs() < RUNAWAY;
    ok(solution.piston_nm)
        && solution.objective.is_finite()
        && solution.dwell_s.iter().all(|&t| ok(t))
        && removal_nm.iter().all(|&h| ok(h))
}

impl Setup {
    /// The sensitivity of the motion `samples` (positions and the time the tool spends at each)
    /// whose nominal removal at the measured map points is `removal_nm`: the motion's removal
    /// under each of [`sensitivity::MOTION_SCENARIOS`] on the set-up's part
    /// ([`crate::simulate::contact::contact_removals`]), its residual against the map summarised
    /// ([`sensitivity::Sensitivity::of_removals`]). On a flat part the samples at a common offset
    /// from the map's lattice are lattice products ([`crate::simulate::contact::contact_removals`]).
    pub fn sensitivity_of(
        &self,
        samples: &SampledProgram,
        removal_nm: &[f64],
        observer: &dyn Observer,
    ) -> Result<sensitivity::Sensitivity> {
        let motion = self.contact_removals(samples, &sensitivity::MOTION_SCENARIOS, observer)?;
        sensitivity::Sensitivity::of_removals(self.map.z_nm(), removal_nm, &motion)
    }

    /// The sensitivity of the plan `dwell_s` at its programmed feeds (no program executed),
    /// whose removal is `removal_nm`: on a flat part whose plan takes the FFT or the stencil
    /// operator, each scenario's removal is the same operator with the scenario's shared
    /// kernel over the dwell points that share it (on the FFT lattice one transform of each
    /// kernel and one convolution), plus the other points' stretches (row and path ends) summed
    /// directly; otherwise the plan's motion summed directly ([`Setup::plan_motion`]).
    pub(super) fn plan_sensitivity(
        &self,
        problem: &Problem,
        dwell_s: &[f64],
        removal_nm: &[f64],
        observer: &dyn Observer,
    ) -> Result<sensitivity::Sensitivity> {
        use crate::influence::operator::{InfluenceOperator, OperatorKind};
        let scenarios = &sensitivity::MOTION_SCENARIOS;
        let kind = problem.operator_kind();
        let lattice = match kind {
            OperatorKind::Fft | OperatorKind::Stencil if self.surface.is_none() => {
                FftOperator::lattice_pitch_mm(self.map.x_mm(), self.map.y_mm())
            }
            _ => None,
        };
        let Some(pitch_mm) = lattice else {
            return self.sensitivity_of(&self.plan_motion(dwell_s), removal_nm, observer);
        };
        // The points whose stretch is not the shared kernel's, summed directly.
        let own = self
            .swept
            .as_ref()
            .map(|(stretches, _)| stretches.outside_dominant())
            .unwrap_or_default();
        let mut shared = dwell_s.to_vec();
        let mut samples = SampledProgram {
            x_mm: Vec::new(),
            y_mm: Vec::new(),
            dwell_s: Vec::new(),
            half_mm: Vec::new(),
        };
        if let Some((stretches, _)) = &self.swept {
            for &j in &own {
                push_stretch(&mut samples, &self.path, stretches, j, dwell_s[j]);
                shared[j] = 0.0;
            }
        }
        let mut motion = if samples.dwell_s.is_empty() {
            vec![vec![0.0; self.map.len()]; scenarios.len()]
        } else {
            self.contact_removals(&samples, scenarios, observer)?
        };
        let tifs: Vec<_> = scenarios.iter().map(|p| p.of(&self.tif)).collect();
        let swept: Vec<_> = tifs.iter().map(|t| self.shared_kernel(t)).collect();
        let kernels: Vec<&dyn InfluenceFunction> = tifs
            .iter()
            .zip(&swept)
            .map(|(t, s)| match s {
                Some(k) => k as &dyn InfluenceFunction,
                None => t,
            })
            .collect();
        let (mx, my) = (self.map.x_mm(), self.map.y_mm());
        let (px, py) = (self.path.x_mm(), self.path.y_mm());
        let lattice_removals = match kind {
            // One lattice, padded for the widest kernel, each kernel transformed once.
            OperatorKind::Fft => {
                let widest = kernels
                    .iter()
                    .copied()
                    .max_by(|a, b| a.support_radius_mm().total_cmp(&b.support_radius_mm()))
                    .unwrap_or(&self.tif);
                FftOperator::for_products(mx, my, px, py, pitch_mm, widest)?
                    .removals_with(&shared, &kernels)?
            }
            _ => kernels
                .iter()
                .map(|k| {
                    crate::influence::StencilOperator::new(mx, my, px, py, pitch_mm, *k)?
                        .removal_nm(&shared)
                })
                .collect::<Result<Vec<_>>>()?,
        };
        for (sum, h) in motion.iter_mut().zip(lattice_removals) {
            sum.iter_mut().zip(h).for_each(|(s, v)| *s += v);
        }
        sensitivity::Sensitivity::of_removals(self.map.z_nm(), removal_nm, &motion)
    }

    /// Solves `problem` (built by [`Setup::problem`]): the acceleration-limited SCP when the
    /// set-up has a limit, the dwell solver the settings choose otherwise (from the warm start
    /// if there is one). Computes the removal `R t` and the feed schedule once.
    pub fn solve(&self, problem: &Problem, observer: &dyn Observer) -> Result<Outcome> {
        observer.setup_step(SetupStep::Solve);
        let m = self.map.len();
        let (solution, removal_all, accel, reference) = match &self.accel {
            Some(limits) => {
                let a =
                    accel::solve_validated(problem, &self.path, limits, &self.settings, observer)?;
                observer.setup_step(SetupStep::Removal);
                let removal = problem.removal_nm(&a.solution.dwell_s)?;
                let report = self.report_on_map(problem, &a, &removal)?;
                (a.solution, removal, Some(report), Some(a.reference))
            }
            None => {
                let s = dwell::solve_validated(
                    problem,
                    &self.settings,
                    observer,
                    self.warm_start_s.as_deref(),
                )?;
                observer.setup_step(SetupStep::Removal);
                let removal = problem.removal_nm(&s.dwell_s)?;
                (s, removal, None, None)
            }
        };
        let (solution, removal_all, accel, executed) = match (&self.accel, reference) {
            (Some(l), Some(reference)) => {
                let first = self.executed_at_limit(&solution.dwell_s, l.a_max_mm_per_s2, observer);
                if l.method == AccelMethod::CorrectionPasses {
                    let (solution, removal_all, executed) =
                        self.correction_passes(problem, l, solution, removal_all, first, observer)?;
                    self.better_executed(
                        problem,
                        l,
                        &reference,
                        (solution, removal_all, accel, executed),
                        observer,
                    )?
                } else {
                    (solution, removal_all, accel, Some(first))
                }
            }
            _ => (solution, removal_all, accel, None),
        };
        // The executed residual's resolution, once, for the plan returned, and beside it the
        // executed motion's sensitivity (independent work on the same run; its error, if any,
        // is returned where the sensitivity is taken below).
        let mut executed_sensitivity = None;
        let executed = match executed {
            Some(Ok(mut e)) => {
                let (resolution, sensitivity) = rayon::join(
                    || self.integration_resolution(&e, observer),
                    || self.sensitivity_of(&e.run.contact, &e.run.removal_nm, observer),
                );
                e.resolution = resolution?;
                executed_sensitivity = Some(sensitivity);
                Some(Ok(e))
            }
            other => other,
        };
        // The nominal scenario's removal (the first block of a robust plan's rows, over its
        // scale) on the measured map.
        let mut removal_nm = removal_all;
        removal_nm.truncate(m);
        let nominal_scale = problem.scenario_scales()[0];
        let mut solution = solution;
        if nominal_scale != 1.0 {
            removal_nm.iter_mut().for_each(|h| *h /= nominal_scale);
            // The solver's piston serves the scaled blocks together; the nominal scenario's
            // own is its mean departure.
            let departure: f64 = removal_nm
                .iter()
                .zip(self.map.z_nm())
                .map(|(h, z)| h - z)
                .sum();
            solution.piston_nm = departure / m.max(1) as f64;
        }
        // A solve that ran away (a non-finite or astronomically large figure) is no answer.
        if !solution_is_finite(&solution, &removal_nm) {
            solution.status = Status::NumericalError;
        }
        check_cancelled(observer)?;
        let approximation = self.exact_removal(problem, &solution.dwell_s, observer)?;
        if let Some(a) = &approximation {
            // The report gives the exact residual of the dwell returned, and where the problem
            // has no rows beyond the map, its piston and objective.
            removal_nm.clone_from(&a.exact_removal_nm);
            if problem.m() == m && m > 0 {
                let d: Vec<f64> = removal_nm
                    .iter()
                    .zip(self.map.z_nm())
                    .map(|(h, z)| h - z)
                    .collect();
                let piston = d.iter().sum::<f64>() / m as f64;
                solution.piston_nm = piston;
                solution.objective = 0.5 * d.iter().map(|v| (v - piston).powi(2)).sum::<f64>();
            }
        }
        let approximation = approximation.map(|a| a.error);
        observer.setup_step(SetupStep::FeedSchedule);
        let feeds = feeds_mm_per_min(&self.ds_mm, &solution.dwell_s);
        let schedule = FeedSchedule::new(
            &self.path,
            &solution.dwell_s,
            self.accel.as_ref().map(|l| l.a_max_mm_per_s2),
            self.corner_angle_deg,
        )?;
        check_cancelled(observer)?;
        // The sensitivity of the executed motion, or of the plan's own where no program is
        // executed.
        let sensitivity = match (&executed, executed_sensitivity) {
            (Some(Ok(_)), Some(sensitivity)) => Some(sensitivity?),
            (Some(Ok(e)), None) => {
                Some(self.sensitivity_of(&e.run.contact, &e.run.removal_nm, observer)?)
            }
            (Some(Err(_)), _) => None,
            (None, _) => {
                Some(self.plan_sensitivity(problem, &solution.dwell_s, &removal_nm, observer)?)
            }
        };
        let residual_nm = centred_residual_nm(self.map.z_nm(), &removal_nm);
        let dwell_outside_map_s = crate::machine::machinability::dwell_outside_map_s(
            self.map.x_mm(),
            self.map.y_mm(),
            self.path.x_mm(),
            self.path.y_mm(),
            &solution.dwell_s,
        );
        Ok(Outcome {
            solution,
            removal_nm,
            residual_nm,
            dwell_outside_map_s,
            feeds_mm_per_min: feeds,
            schedule,
            accel,
            executed,
            approximation,
            sensitivity,
        })
    }

    /// With an approximate operator (the spreading operator): the removal of `dwell_s` by the
    /// exact `R` (summed directly, [`crate::simulate::direct`]) at the measured map points and
    /// the operator's measured error on it. `None` for the exact operators.
    pub(super) fn exact_removal(
        &self,
        problem: &Problem,
        dwell_s: &[f64],
        observer: &dyn Observer,
    ) -> Result<Option<Exact>> {
        use crate::influence::operator::OperatorKind;
        let tolerance = match problem.operator_kind() {
            OperatorKind::FftSpread | OperatorKind::Expansion => self.settings.spread_tolerance,
            OperatorKind::Nufft => crate::influence::operator::nufft::DEFAULT_NUFFT_TOLERANCE,
            _ => return Ok(None),
        };
        let m = self.map.len();
        // The nominal block's removal (a robust plan's first block, over its scale).
        let mut approx = problem.removal_nm(dwell_s)?;
        approx.truncate(m);
        let nominal_scale = problem.scenario_scales()[0];
        approx.iter_mut().for_each(|h| *h /= nominal_scale);
        // The exact removal of the plan's own model: with the swept model every dwell point's
        // stretch samples carry its dwell in proportion to their weights.
        let exact = self.contact_removal(&self.plan_motion(dwell_s), observer)?;
        let norm = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x * x).sum::<f64>().sqrt();
        let diff = norm(&mut approx.iter().zip(&exact).map(|(a, e)| a - e));
        let size = norm(&mut exact.iter().copied());
        let rms = |h: &[f64]| HeightStats::of(&centred_residual_nm(self.map.z_nm(), h)).rms_nm;
        let error = OperatorError {
            relative_removal_error: if size > 0.0 { diff / size } else { 0.0 },
            tolerance,
            rms_after_operator_nm: rms(&approx),
            rms_after_exact_nm: rms(&exact),
        };
        Ok(Some(Exact {
            exact_removal_nm: exact,
            error,
        }))
    }

    /// The acceleration-limited solve's report `a` with its RMS figures on the measured map
    /// (the SCP's are over every row, edge rows included); `removal`: `R t` of its dwell times
    /// over every row.
    fn report_on_map(
        &self,
        problem: &Problem,
        a: &accel::AccelSolution,
        removal: &[f64],
    ) -> Result<AccelReport> {
        let m = self.map.len();
        let mut report = a.report.clone();
        if problem.m() > m {
            let a0 = problem.scenario_scales()[0];
            let on_map = |h: &[f64]| {
                let h: Vec<f64> = h[..m].iter().map(|v| v / a0).collect();
                HeightStats::of(&centred_residual_nm(self.map.z_nm(), &h)).rms_nm
            };
            report.rms_after_nm = on_map(removal);
            report.rms_after_reference_nm = on_map(&problem.removal_nm(&a.reference.dwell_s)?);
        }
        Ok(report)
    }

    /// Under correction passes that did not converge, where the feed-limited optimum
    /// `reference` breaks the limit: the squared-speed plan (the limit in the plan's own feeds),
    /// executed at the limit, in place of the passes' plan `passes` (dwell solution, removal over
    /// every row, report, executed run) where it leaves the lower executed residual. At a low
    /// limit the controller's ramps move much of the time between neighbouring stretches of a
    /// plan whose feeds break the limit; passes against them may then not settle, and end above
    /// the plan that meets it. The executed residual decides; a tie keeps the passes. Passes
    /// that converged are kept as they are (no second plan is made).
    #[allow(clippy::type_complexity)]
    fn better_executed(
        &self,
        problem: &Problem,
        limits: &AccelLimits,
        reference: &Solution,
        passes: (
            Solution,
            Vec<f64>,
            Option<AccelReport>,
            Option<Result<Executed>>,
        ),
        observer: &dyn Observer,
    ) -> Result<(
        Solution,
        Vec<f64>,
        Option<AccelReport>,
        Option<Result<Executed>>,
    )> {
        if passes.0.status.is_converged() {
            return Ok(passes);
        }
        check_cancelled(observer)?;
        let Some(a) = accel::squared_speed_candidate(
            problem,
            &self.path,
            limits,
            &self.settings,
            observer,
            reference,
        )?
        else {
            return Ok(passes);
        };
        check_cancelled(observer)?;
        let Ok(e) = self.executed_at_limit(&a.solution.dwell_s, limits.a_max_mm_per_s2, observer)
        else {
            return Ok(passes);
        };
        let passes_nm = match &passes.3 {
            Some(Ok(p)) => p.after.rms_nm,
            _ => f64::INFINITY,
        };
        if e.after.rms_nm.total_cmp(&passes_nm).is_ge() {
            return Ok(passes);
        }
        let removal = problem.removal_nm(&a.solution.dwell_s)?;
        let report = self.report_on_map(problem, &a, &removal)?;
        Ok((a.solution, removal, Some(report), Some(Ok(e))))
    }

    /// Correction passes against the executed program ([`AccelMethod::CorrectionPasses`]):
    /// from `solution` (removal `removal_all` over every row, executed run `first`), each pass
    /// re-solves the feed-limited problem for the target less the executed removal's departure
    /// from the plan's on the measured map, `z_i - (h_exec_i - (R t)_i)`, warm-started from the
    /// last dwell times, and executes the result; a pass is kept while the executed RMS falls by
    /// more than [`PASS_GAIN`], at most [`MAX_CORRECTION_PASSES`] passes.
    #[allow(clippy::type_complexity)]
    pub(super) fn correction_passes(
        &self,
        problem: &Problem,
        limits: &AccelLimits,
        solution: Solution,
        removal_all: Vec<f64>,
        first: Result<Executed>,
        observer: &dyn Observer,
    ) -> Result<(Solution, Vec<f64>, Option<Result<Executed>>)> {
        let mut current = match first {
            Ok(e) => e,
            Err(e) => return Ok((solution, removal_all, Some(Err(e)))),
        };
        let (mut solution, mut removal_all) = (solution, removal_all);
        let m = self.map.len();
        for _ in 0..MAX_CORRECTION_PASSES {
            check_cancelled(observer)?;
            // The executed departure from the plan (the nominal block's removal over its
            // scale), on the measured rows of every scenario's block, each at its scale (one
            // unscaled block unless the plan is robust).
            let scales = problem.scenario_scales();
            let block = problem.m() / scales.len();
            let mut target = problem.z_nm().to_vec();
            for (b, a) in scales.iter().enumerate() {
                for i in 0..m {
                    let departure = current.run.removal_nm[i] - removal_all[i] / scales[0];
                    target[b * block + i] -= a * departure;
                }
            }
            let pass = problem.with_target_nm(target)?;
            let s =
                dwell::solve_validated(&pass, &self.settings, observer, Some(&solution.dwell_s))?;
            // A pass whose plan cannot be written as a program is not kept.
            let executed = self.executed_at_limit(&s.dwell_s, limits.a_max_mm_per_s2, observer);
            check_cancelled(observer)?;
            let Ok(e) = executed else {
                break;
            };
            if e.after.rms_nm >= current.after.rms_nm * (1.0 - PASS_GAIN) {
                break;
            }
            let gain_nm = current.after.rms_nm - e.after.rms_nm;
            removal_all = problem.removal_nm(&s.dwell_s)?;
            solution = s;
            current = Executed {
                correction_passes: current.correction_passes + 1,
                ..e
            };
            // A pass that gained less than the solver's settled fall is the last one.
            if gain_nm < FIT_RMS_SETTLED_NM {
                break;
            }
        }
        check_cancelled(observer)?;
        Ok((solution, removal_all, Some(Ok(current))))
    }

    /// The removal `R t` of given dwell times `dwell_s` at the measured map points, nm (edge
    /// rows dropped), with `problem` built by [`Setup::problem`]: a plan evaluated, no solve.
    pub fn removal_of(
        &self,
        problem: &Problem,
        dwell_s: &[f64],
        observer: &dyn Observer,
    ) -> Result<Vec<f64>> {
        observer.setup_step(SetupStep::Removal);
        let mut removal = problem.removal_nm(dwell_s)?;
        removal.truncate(self.map.len());
        Ok(removal)
    }

    /// Runs `program` as the machine would (block by block under `kinematics`) and integrates
    /// the TIF along the contact motion at the measured map points, in pieces of at most
    /// `step_mm` of arc length (default [`default_sample_step_mm`]); `part`: the part geometry
    /// and the tool-centre offset along its normal, to map tool centres back to contact points
    /// (none: the program's X, Y are the contact points). The executed removal of a given
    /// program, as [`Setup::removal_of`] is of given dwell times; the set-up's dwell points are
    /// the program's marked points ([`DwellPoints::of_program`]) for the report.
    pub fn run_program(
        &self,
        program: &Program,
        kinematics: Kinematics,
        step_mm: Option<f64>,
        part: Option<(&dyn PartGeometry, f64)>,
        observer: &dyn Observer,
    ) -> Result<ProgramRun> {
        observer.setup_step(SetupStep::Removal);
        self.run_on_map(program, kinematics, step_mm, part, observer)
    }

    /// [`Setup::run_program`] without the step report (also the solve's executed program).
    pub(super) fn run_on_map(
        &self,
        program: &Program,
        kinematics: Kinematics,
        step_mm: Option<f64>,
        part: Option<(&dyn PartGeometry, f64)>,
        observer: &dyn Observer,
    ) -> Result<ProgramRun> {
        run_on_map(
            program,
            kinematics,
            step_mm.unwrap_or_else(|| default_sample_step_mm(&self.tif)),
            part,
            self.rate_drift_per_hour,
            &|samples| self.contact_removal(samples, observer),
        )
    }

    /// The resolution of the executed run `e` ([`IntegrationResolution`]): its program run
    /// again under the same kinematics with half the default sample step. `None` where that
    /// many samples are beyond [`crate::machine::gcode::motion::MAX_SAMPLES`].
    pub(super) fn integration_resolution(
        &self,
        e: &Executed,
        observer: &dyn Observer,
    ) -> Result<Option<IntegrationResolution>> {
        let kinematics = Kinematics::Trapezoidal {
            a_max_mm_per_s2: e.a_max_mm_per_s2,
            corner_angle_deg: e.settings.corner_angle_deg,
        };
        let part = self
            .surface
            .as_ref()
            .map(|s| (s as &dyn PartGeometry, e.settings.tool_radius_mm));
        self.program_resolution(&e.program.program, kinematics, None, part, &e.run, observer)
    }

    /// The resolution of `run`, the run of `program` under `kinematics` with removal samples of
    /// at most `step_mm` (default [`default_sample_step_mm`]) on `part`
    /// ([`Setup::run_program`]): the same program run again with half the step
    /// ([`IntegrationResolution`]). `None` where that many samples are beyond
    /// [`crate::machine::gcode::motion::MAX_SAMPLES`].
    pub fn program_resolution(
        &self,
        program: &Program,
        kinematics: Kinematics,
        step_mm: Option<f64>,
        part: Option<(&dyn PartGeometry, f64)>,
        run: &ProgramRun,
        observer: &dyn Observer,
    ) -> Result<Option<IntegrationResolution>> {
        let step_mm = step_mm.unwrap_or_else(|| default_sample_step_mm(&self.tif));
        let finer = self.run_on_map(program, kinematics, Some(0.5 * step_mm), part, observer);
        check_cancelled(observer)?;
        Ok(finer.ok().map(|f| {
            IntegrationResolution::of(&run.removal_nm, &f.removal_nm, step_mm, run.samples)
        }))
    }

    /// The default program for `dwell_s` (ISO, G94, the feed limit; on a curved part following
    /// the design surface, the tool's tip at the contact point) executed at `a_max` with
    /// look-ahead, and the removal integrated along the executed motion
    /// ([`crate::machine::gcode::motion`], [`Setup::contact_removal`]), on the measured map.
    pub(super) fn executed_at_limit(
        &self,
        dwell_s: &[f64],
        a_max_mm_per_s2: f64,
        observer: &dyn Observer,
    ) -> Result<Executed> {
        let settings = NcSettings {
            a_max_mm_per_s2: Some(a_max_mm_per_s2),
            corner_angle_deg: self.corner_angle_deg,
            v_max_mm_per_min: self.feed.map(|f| f.v_max_mm_per_min),
            ..NcSettings::default()
        };
        // On a curved part the program follows the design surface, the tool's tip at the
        // contact point.
        let geometry: &dyn PartGeometry = match &self.surface {
            Some(s) => s,
            None => &Flat,
        };
        let nc = NcProgram::plan(&self.path, dwell_s, geometry, &settings)?;
        let check = write_and_check(&nc, &[])?;
        let kinematics = Kinematics::Trapezoidal {
            a_max_mm_per_s2,
            corner_angle_deg: settings.corner_angle_deg,
        };
        let part = self
            .surface
            .as_ref()
            .map(|s| (s as &dyn PartGeometry, settings.tool_radius_mm));
        let run = self.run_on_map(&check.program, kinematics, None, part, observer)?;
        let after = HeightStats::of(&centred_residual_nm(self.map.z_nm(), &run.removal_nm));
        Ok(Executed {
            a_max_mm_per_s2,
            after,
            run,
            correction_passes: 0,
            settings,
            program: check,
            resolution: None,
        })
    }
}

impl Setup {
    /// The program of `settings` for the outcome's plan, written, read back and checked: the one
    /// the solve executed when that was written with the same settings on a flat part, planned
    /// here otherwise (on the set-up's design surface when there is one).
    pub fn program_check(&self, outcome: &Outcome, settings: &NcSettings) -> Result<ProgramCheck> {
        if let (Some(Ok(e)), None) = (&outcome.executed, &self.surface) {
            if e.settings == *settings {
                return Ok(e.program.clone());
            }
        }
        let geometry: &dyn PartGeometry = match &self.surface {
            Some(s) => s,
            None => &Flat,
        };
        NcProgram::plan(&self.path, &outcome.solution.dwell_s, geometry, settings)
            .and_then(|nc| write_and_check(&nc, &[]))
    }
}

impl Setup {
    /// The set-up's part as a contact motion acts on it: the measured map, the design surface,
    /// the TIF (each sample's own Hertz TIF where it depends on the curvature) and its frame.
    fn contact_part(&self) -> ContactPart<'_> {
        ContactPart {
            map_x_mm: self.map.x_mm(),
            map_y_mm: self.map.y_mm(),
            surface: self.surface.as_ref(),
            tif: &self.tif,
            hertz: match &self.tif_model {
                TifModel::ShiftInvariant => None,
                TifModel::CurvatureDependent(params) => Some(params),
            },
            frame: self.tif_frame,
        }
    }

    /// The removal of the motion `samples` at the measured map points, nm
    /// ([`crate::simulate::contact::contact_removal`]).
    pub(super) fn contact_removal(
        &self,
        samples: &SampledProgram,
        observer: &dyn Observer,
    ) -> Result<Vec<f64>> {
        contact_removal(&self.contact_part(), samples, observer)
    }

    /// The removals of the motion `samples` at the measured map points under each of
    /// `scenarios`, nm, in their order ([`crate::simulate::contact::contact_removals`]: on a
    /// flat part as lattice products where that pays, on a curved part in each sample's
    /// tangent frame).
    pub(super) fn contact_removals(
        &self,
        samples: &SampledProgram,
        scenarios: &[Perturbation],
        observer: &dyn Observer,
    ) -> Result<Vec<Vec<f64>>> {
        contact_removals(&self.contact_part(), samples, scenarios, observer)
    }

    /// The motion of the plan `dwell_s` at its programmed feeds ([`path_motion`] of the
    /// set-up's path, with its stretches under the swept model).
    pub(super) fn plan_motion(&self, dwell_s: &[f64]) -> SampledProgram {
        path_motion(&self.path, self.swept.as_ref().map(|s| &s.0), dwell_s)
    }
}
