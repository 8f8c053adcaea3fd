//! A plan robust to how well the TIF is known: one dwell vector for every scenario at once.
//!
//! The scenarios are drawn from how well the tool is known ([`ToolUncertainty`]: a spot test's
//! defaults, the job's `[tif] width_sigma` and `offset_sigma_mm`, or a calibration's standard
//! deviations), the ones a plan can answer (a rate error only scales the removal; the loop
//! corrects it): the nominal TIF `f`, `f` one standard deviation wider and narrower with its
//! volume kept (`1 + σ_w` and `1 / (1 + σ_w)`), and the tool one standard deviation off either
//! way along x and along y (`±σ_x`, `±σ_y`; both signs, so that the mean over the scenarios is
//! the nominal tool's to first order and the plan is not pulled towards one side). These seven
//! points are a symmetric quadrature of the tool's distribution (the sigma points of Julier and
//! Uhlmann's unscented transform, Proc. IEEE 92, 2004, without the centre's extra weight). With
//! `R_s` the influence matrix of scenario `s` (same path, same influence model), the robust plan
//! solves
//!
//! `min_t  (1/S) Σ_s ½ ||R_s t + c − z||² + ρ Σ t   (+ λ)`,  `t` within its bounds,
//!
//! i.e. the rows `[R_1; ...; R_S]` stacked against `[z; ...; z]` with `ρ` and `λ` times `S` (each
//! `R_s` the nominal plan's lattice operator with scenario `s`'s kernel where that is the FFT or
//! stencil operator, [`crate::influence::StackedRows`], else assembled, on a curved part in the
//! tangent frames with the tool's offset moving the dwell points): the
//! mean squared residual over the scenarios (Ben-Tal, El Ghaoui and Nemirovski, *Robust
//! Optimization*, 2009: the scenario (sample-average) counterpart). One piston `c` serves every
//! scenario (a width change keeps the volume, an offset moves nothing in or out).
//!
//! **Minimax weights** (`robust_weighting = "minimax"`). The plan whose worst scenario is
//! smallest, `min_t max_s f_s(t)` with `f_s` scenario `s`'s mean squared residual, is the saddle
//! point of `max_w g(w)`, `g(w) = min_t (1/S) Σ_s w_s f_s(t)` over weights `w >= 0` summing to
//! `S`; `g` is concave, its gradient `f(t(w))`, and every `g(w)` is a lower bound on the minimax
//! value (weak duality; with a time weight `ρ` both sides carry it, `τ Σ t` with `τ = 2 ρ / m`
//! in these mean-square units). [`minimax_weights`] climbs it by exponentiated gradient steps
//! (Kivinen and Warmuth, Inform. and Comput. 132, 1997): solve with the block of scenario `s`
//! scaled by `sqrt(w_s)` (so `ρ S` keeps its meaning), then
//! `w_s <- w_s exp(η (f_s - f̄) / f̄)`, `f̄ = (1/S) Σ w_k f_k`, renormalised; a step that raises
//! `g` (and stays below the kept plan's primal value, as a true dual value must) is kept and the
//! next one 1.5 times longer, one that does not is retried from the kept weights 0.3 times as
//! long. It keeps the weights of the round whose worst scenario was
//! smallest and stops when its primal value `max_s f_s + τ Σ t` is within [`MINIMAX_GAP`] of the
//! best bound or after [`MINIMAX_ROUNDS`] solves. Each solve is to the solver's tolerance, so the
//! bound is as good as the solves.

use super::sensitivity::Sensitivity;
use super::{Outcome, Setup};
use crate::calibrate::ToolUncertainty;
use crate::dwell::Problem;
use crate::error::Result;
use crate::influence::InfluenceMatrix;
use crate::map::HeightStats;
use crate::observer::Observer;
use crate::tif::Perturbation;
use serde::{Deserialize, Serialize};

/// One scenario of a robust plan: the TIF's width factor (volume kept) and the tool's offset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scenario {
    /// The name `report.json` gives it ([`SCENARIO_NAMES`]).
    pub name: &'static str,
    /// Width factor of the TIF, its volume kept.
    pub width_factor: f64,
    /// Offset of the tool from where it is programmed, mm.
    pub offset_mm: (f64, f64),
}

/// Number of scenarios of a robust plan.
pub const SCENARIO_COUNT: usize = 7;

/// The scenarios' names, the nominal first ([`scenarios`] order).
pub const SCENARIO_NAMES: [&str; SCENARIO_COUNT] = [
    "nominal",
    "tif_wider_1sigma",
    "tif_narrower_1sigma",
    "offset_x_plus_1sigma",
    "offset_x_minus_1sigma",
    "offset_y_plus_1sigma",
    "offset_y_minus_1sigma",
];

/// The scenarios of a robust plan for a tool known to `u` (module documentation), the nominal
/// first.
pub fn scenarios(u: &ToolUncertainty) -> [Scenario; SCENARIO_COUNT] {
    let wider = 1.0 + u.width_sigma;
    let (ox, oy) = (u.offset_x_sigma_mm, u.offset_y_sigma_mm);
    let figures = [
        (1.0, (0.0, 0.0)),
        (wider, (0.0, 0.0)),
        (1.0 / wider, (0.0, 0.0)),
        (1.0, (ox, 0.0)),
        (1.0, (-ox, 0.0)),
        (1.0, (0.0, oy)),
        (1.0, (0.0, -oy)),
    ];
    std::array::from_fn(|s| Scenario {
        name: SCENARIO_NAMES[s],
        width_factor: figures[s].0,
        offset_mm: figures[s].1,
    })
}

impl Scenario {
    /// The scenario as a perturbation of the tool (its rate nominal).
    pub fn perturbation(&self) -> Perturbation {
        Perturbation {
            width_factor: self.width_factor,
            rate_factor: 1.0,
            offset_mm: self.offset_mm,
        }
    }
}

impl Setup {
    /// The scenarios of this set-up's robust plan ([`scenarios`] of its tool's uncertainty).
    pub fn robust_scenarios(&self) -> [Scenario; SCENARIO_COUNT] {
        scenarios(&self.tool_uncertainty)
    }

    /// The executed residual RMS of each robust scenario, nm ([`SCENARIO_NAMES`] order): the
    /// executed contact motion `executed` integrated with each scenario's TIF on the set-up's
    /// part ([`crate::simulate::contact::contact_removals`]), the nominal the executed run's own.
    pub fn executed_scenario_rms_nm(
        &self,
        executed: &super::Executed,
        observer: &dyn Observer,
    ) -> Result<Vec<f64>> {
        let perturbed: Vec<Perturbation> = self.robust_scenarios()[1..]
            .iter()
            .map(Scenario::perturbation)
            .collect();
        let removals = self.contact_removals(&executed.run.contact, &perturbed, observer)?;
        let z = self.map.z_nm();
        let mut rms = vec![executed.after.rms_nm];
        rms.extend(
            removals
                .iter()
                .map(|h| HeightStats::of(&super::centred_residual_nm(z, h)).rms_nm),
        );
        Ok(rms)
    }
}

/// Most solves of the minimax rounds (the first is the mean plan).
pub const MINIMAX_ROUNDS: usize = 6;
/// The rounds stop once the worst scenario's mean square is within this share of the best lower
/// bound `g(w)` (module documentation).
pub const MINIMAX_GAP: f64 = 0.01;
/// The first exponentiated-gradient step `η`.
const MINIMAX_FIRST_STEP: f64 = 4.0;
/// The step after a kept round, and after a refused one, as a multiple of the last.
const MINIMAX_STEP_GROWTH: f64 = 1.5;
const MINIMAX_STEP_CUT: f64 = 0.3;

/// The stacked matrix with the rows of scenario block `s` scaled by `sqrt(weights[s])`: the
/// matrix of `Σ_s w_s ||R_s t + c - z||²` (the target's blocks scaled alike by
/// [`weighted_target`]).
pub fn weighted_rows(stacked: &InfluenceMatrix, weights: &[f64]) -> Result<InfluenceMatrix> {
    let rows = stacked.csc().nrows();
    if weights.is_empty() || !rows.is_multiple_of(weights.len()) {
        return Err(crate::error::Error::LengthMismatch {
            what: "scenario weights",
            got: weights.len(),
            expected: SCENARIO_COUNT,
        });
    }
    let block = rows / weights.len();
    let scale: Vec<f64> = weights.iter().map(|w| w.max(0.0).sqrt()).collect();
    let mut csc = stacked.csc().clone();
    let (_, row_indices, values) = csc.csc_data_mut();
    for (v, &i) in values.iter_mut().zip(row_indices.iter()) {
        *v *= scale[i / block];
    }
    Ok(InfluenceMatrix::from_csc(csc))
}

/// The target `z` repeated once per scenario, block `s` scaled by `sqrt(weights[s])`.
pub fn weighted_target(z_nm: &[f64], weights: &[f64]) -> Vec<f64> {
    weights
        .iter()
        .flat_map(|w| {
            let a = w.max(0.0).sqrt();
            z_nm.iter().map(move |z| a * z)
        })
        .collect()
}

/// The exponentiated-gradient step of the module documentation from `weights` (summing to the
/// scenario count) and the scenarios' residual RMS at their plan: `w_s exp(η (f_s - f̄) / f̄)`,
/// `f_s = rms_s²`, `f̄ = (1/S) Σ w_k f_k`, renormalised to sum `S`. Equal residuals leave the
/// weights as they are.
pub fn minimax_step(weights: &[f64], rms_nm: &[f64], step: f64) -> Vec<f64> {
    let s = weights.len() as f64;
    let mean = weighted_mean_square(weights, rms_nm);
    if !(mean.is_finite() && mean > 0.0) {
        return weights.to_vec();
    }
    let raised: Vec<f64> = weights
        .iter()
        .zip(rms_nm)
        .map(|(w, r)| w * (step * (r * r - mean) / mean).exp())
        .collect();
    let total: f64 = raised.iter().sum();
    if !(total.is_finite() && total > 0.0) {
        return weights.to_vec();
    }
    raised.iter().map(|v| v * s / total).collect()
}

/// `(1/S) Σ_s w_s rms_s²`: the weighted plan's `g(w)` (module documentation), nm².
fn weighted_mean_square(weights: &[f64], rms_nm: &[f64]) -> f64 {
    weights
        .iter()
        .zip(rms_nm)
        .map(|(w, r)| w * r * r)
        .sum::<f64>()
        / weights.len() as f64
}

/// What the minimax rounds found.
#[derive(Debug, Clone, PartialEq)]
pub struct MinimaxRounds {
    /// The kept weights (those of the round with the smallest worst scenario), summing to the
    /// scenario count, [`SCENARIO_NAMES`] order.
    pub weights: Vec<f64>,
    /// The worst scenario's residual RMS of each round's plan, nm (the first: equal weights).
    pub worst_rms_nm: Vec<f64>,
    /// How far the kept plan's `max_s rms_s² + τ Σ t` lies above the best lower bound the rounds
    /// proved, `g(w) + τ Σ t_w` (module documentation), relative: 0 at the minimax plan, as
    /// exact as the solves.
    pub duality_gap: f64,
}

/// The minimax rounds of the module documentation over `count` scenarios. `plan(weights, warm)`
/// solves the weighted
/// problem (from the previous round's dwell `warm` when given) and returns the dwell and each
/// scenario's residual RMS (unweighted, [`SCENARIO_NAMES`] order). `time_nm2_per_s` is the plan's
/// time weight in the same mean-square units, `2 ρ / m` (`m` map points), so that the bound holds
/// for plans that trade residual for dwell time.
pub fn minimax_weights(
    count: usize,
    time_nm2_per_s: f64,
    mut plan: impl FnMut(&[f64], Option<&[f64]>) -> Result<(Vec<f64>, Vec<f64>)>,
) -> Result<MinimaxRounds> {
    let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    let time = |t: &[f64]| time_nm2_per_s * t.iter().sum::<f64>();
    let mut weights = vec![1.0; count];
    let (mut dwell_s, mut rms_nm) = plan(&weights, None)?;
    let mut worst_rms_nm = vec![worst(&rms_nm)];
    // The kept plan: its worst RMS, weights and primal value `max rms² + τ Σ t`.
    let primal = |rms: &[f64], t: &[f64]| worst(rms).powi(2) + time(t);
    let mut kept = (worst_rms_nm[0], weights.clone(), primal(&rms_nm, &dwell_s));
    // The ascent's base: its weights, their plan's residuals and the dual value.
    let mut bound = weighted_mean_square(&weights, &rms_nm) + time(&dwell_s);
    let mut step = MINIMAX_FIRST_STEP;
    while worst_rms_nm.len() < MINIMAX_ROUNDS && kept.2 > bound * (1.0 + MINIMAX_GAP) {
        let trial = minimax_step(&weights, &rms_nm, step);
        let (trial_dwell_s, trial_rms_nm) = plan(&trial, Some(&dwell_s))?;
        let w = worst(&trial_rms_nm);
        worst_rms_nm.push(w);
        if w < kept.0 {
            kept = (w, trial.clone(), primal(&trial_rms_nm, &trial_dwell_s));
        }
        let g = weighted_mean_square(&trial, &trial_rms_nm) + time(&trial_dwell_s);
        // A dual value above a plan's primal one breaks weak duality: that solve was not the
        // weighted optimum (extreme weights make it hard), so the step is refused like a poor one.
        if g > bound && g <= kept.2 * (1.0 + 1e-9) {
            bound = g;
            (weights, dwell_s, rms_nm) = (trial, trial_dwell_s, trial_rms_nm);
            step *= MINIMAX_STEP_GROWTH;
        } else {
            step *= MINIMAX_STEP_CUT;
        }
    }
    Ok(MinimaxRounds {
        weights: kept.1,
        worst_rms_nm,
        duality_gap: if bound > 0.0 {
            kept.2 / bound - 1.0
        } else {
            0.0
        },
    })
}

/// The residual RMS (piston removed) of each scenario, nm: `removal_nm` holds the stacked
/// removal `[R_1 t; ...; R_S t]` of blocks of `removal_nm.len() / S` rows whose first
/// `z_nm.len()` rows are the measured map.
pub fn scenario_rms_nm(z_nm: &[f64], removal_nm: &[f64]) -> Vec<f64> {
    let block = removal_nm.len() / SCENARIO_COUNT;
    (0..SCENARIO_COUNT)
        .map(|s| {
            let h = &removal_nm[s * block..s * block + z_nm.len().min(block)];
            HeightStats::of(&super::centred_residual_nm(&z_nm[..h.len()], h)).rms_nm
        })
        .collect()
}

/// Where the per-scenario figures of a [`RobustSummary`] come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RobustBasis {
    /// The programs as executed at the acceleration limit, each scenario's TIF integrated along
    /// the executed motion ([`super::sensitivity`]).
    Executed,
    /// The plans' model: the scenario blocks of the stacked `R` applied to each plan's dwell.
    Planned,
}

/// What a robust plan costs and saves against the nominal plan: each plan's residual RMS per
/// scenario, as executed where both programs are executed, else as planned.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RobustSummary {
    /// Where the figures come from.
    pub basis: RobustBasis,
    /// The scenarios, in the order of the RMS lists.
    pub scenarios: Vec<String>,
    /// The robust plan's residual RMS in each scenario, nm.
    pub robust_plan_rms_nm: Vec<f64>,
    /// The nominal plan's residual RMS in each scenario, nm.
    pub nominal_plan_rms_nm: Vec<f64>,
    /// What the robust plan costs in the nominal scenario: its RMS less the nominal plan's, nm.
    pub nominal_cost_nm: f64,
    /// What it saves in the worst scenario: the nominal plan's worst RMS less its own, nm.
    pub worst_scenario_saving_nm: f64,
}

impl RobustSummary {
    /// The summary of two plans' per-scenario RMS ([`SCENARIO_NAMES`] order) on `basis`.
    pub fn new(
        basis: RobustBasis,
        robust_plan_rms_nm: Vec<f64>,
        nominal_plan_rms_nm: Vec<f64>,
    ) -> Self {
        let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        Self {
            basis,
            scenarios: SCENARIO_NAMES.iter().map(|s| s.to_string()).collect(),
            nominal_cost_nm: robust_plan_rms_nm[0] - nominal_plan_rms_nm[0],
            worst_scenario_saving_nm: worst(&nominal_plan_rms_nm) - worst(&robust_plan_rms_nm),
            robust_plan_rms_nm,
            nominal_plan_rms_nm,
        }
    }
}

/// A robust plan beside the nominal plan of the same set-up ([`Setup::compare_with_nominal`]):
/// what `report.json` `robust` reports, computed by the engine so the report only reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct NominalComparison {
    /// Both plans' residual RMS in every scenario, as executed where both programs are, else
    /// as planned.
    pub planned: RobustSummary,
    /// The nominal plan's residual RMS, nm: as executed where the program is executed, else
    /// its model's.
    pub nominal_plan_rms_after_nm: f64,
    /// The nominal plan's executed sensitivity.
    pub nominal_plan_sensitivity: Option<Sensitivity>,
}

impl Setup {
    /// The robust plan `outcome` (solved on `problem`, this set-up's stacked scenarios) against
    /// the nominal plan of the same set-up, solved here the same way but for the nominal TIF
    /// alone: both plans' residual RMS in every scenario by the stacked model, and the nominal
    /// plan's executed residual and sensitivity where a program is executed.
    pub fn compare_with_nominal(
        &self,
        problem: &Problem,
        outcome: &Outcome,
        observer: &dyn Observer,
    ) -> Result<NominalComparison> {
        let mut nominal = self.clone();
        nominal.settings.robust = false;
        let built = nominal.problem(observer)?;
        let plan = nominal.solve(&built.problem, observer)?;
        let z = self.map.z_nm();
        // Each scenario's removal: its block of the robust problem's rows over the block's scale.
        let per_scenario = |t: &[f64]| -> Result<Vec<f64>> {
            let mut h = problem.removal_nm(t)?;
            let scales = problem.scenario_scales();
            let block = (h.len() / scales.len()).max(1);
            for (part, a) in h.chunks_mut(block).zip(scales) {
                part.iter_mut().for_each(|v| *v /= a);
            }
            Ok(scenario_rms_nm(z, &h))
        };
        let executed = |o: &Outcome| match &o.executed {
            Some(Ok(e)) => Some(self.executed_scenario_rms_nm(e, observer)),
            _ => None,
        };
        let planned = match (executed(outcome), executed(&plan)) {
            (Some(r), Some(n)) => RobustSummary::new(RobustBasis::Executed, r?, n?),
            _ => RobustSummary::new(
                RobustBasis::Planned,
                per_scenario(&outcome.solution.dwell_s)?,
                per_scenario(&plan.solution.dwell_s)?,
            ),
        };
        let nominal_plan_rms_after_nm = match &plan.executed {
            Some(Ok(e)) => e.after.rms_nm,
            _ => HeightStats::of(&plan.residual_nm).rms_nm,
        };
        Ok(NominalComparison {
            planned,
            nominal_plan_rms_after_nm,
            nominal_plan_sensitivity: plan.sensitivity,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A step keeps the weights' sum, leaves equal residuals where they are and moves weight to
    /// the scenarios above the weighted mean square, by the exponential of the closed form.
    #[test]
    fn minimax_step_keeps_the_sum_and_favours_the_worst() {
        let w = [1.0; 5];
        assert_eq!(minimax_step(&w, &[2.0; 5], 4.0), w.to_vec());
        let next = minimax_step(&w, &[1.0, 1.0, 2.0, 1.0, 1.0], 1.0);
        assert!((next.iter().sum::<f64>() - 5.0).abs() < 1e-12, "{next:?}");
        // f = (1, 1, 4, 1, 1), mean 1.6: exponents -0.375 and 1.5.
        let (lo, hi) = ((-0.375f64).exp(), 1.5f64.exp());
        let total = 4.0 * lo + hi;
        assert!((next[2] - 5.0 * hi / total).abs() < 1e-12, "{next:?}");
        assert!((next[0] - 5.0 * lo / total).abs() < 1e-12, "{next:?}");
    }

    /// Scalar scenarios `f_s(t) = (a_s t - 1)²`: the weighted plan is `t = Σ w a / Σ w a²`, the
    /// minimax plan equalises the extreme gains, `t* = 2 / (a_min + a_max)`, worst
    /// `(a_max - a_min) / (a_max + a_min)`. The rounds lower the worst scenario from the mean
    /// plan's (5.6% above that optimum) to within 2% of it, and the bound stays below it.
    #[test]
    fn minimax_rounds_approach_the_closed_form() {
        let a = [1.0, 1.4, 0.7, 1.1, 0.95];
        let plan = |w: &[f64]| -> f64 {
            let num: f64 = w.iter().zip(&a).map(|(w, a)| w * a).sum();
            let den: f64 = w.iter().zip(&a).map(|(w, a)| w * a * a).sum();
            num / den
        };
        let rms = |t: f64| -> Vec<f64> { a.iter().map(|a| (a * t - 1.0).abs()).collect() };
        let rounds = minimax_weights(5, 0.0, |w, _| {
            let t = plan(w);
            Ok((vec![t], rms(t)))
        })
        .unwrap();
        let optimum = (1.4 - 0.7) / (1.4 + 0.7);
        let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let kept = worst(&rms(plan(&rounds.weights)));
        let mean_plan = rounds.worst_rms_nm[0];
        assert!(mean_plan > optimum * 1.05, "{mean_plan} against {optimum}");
        assert!(
            kept <= optimum * 1.02,
            "{kept} against {optimum}: {rounds:?}"
        );
        assert!(kept >= optimum * (1.0 - 1e-12));
        // The kept plan is no better than the optimum, so its gap to a valid bound is at least
        // its own excess over the optimum.
        assert!(
            (1.0 + rounds.duality_gap) * optimum * optimum >= kept * kept * (1.0 - 1e-9),
            "{rounds:?}"
        );
        assert!((rounds.weights.iter().sum::<f64>() - 5.0).abs() < 1e-9);
        assert!(rounds.worst_rms_nm.len() <= MINIMAX_ROUNDS);
    }

    /// Least squares with five perturbed matrices: the rounds end at most 0.5% above the
    /// minimax value, which a long run of small steps gives (reference), and below the mean
    /// plan's worst.
    #[test]
    fn minimax_rounds_on_least_squares_scenarios() {
        let (m, n) = (30, 8);
        let mut rng = crate::rng::SplitMix64::new(7);
        let mut normal = || rng.normal();
        let base: Vec<f64> = (0..m * n).map(|_| normal()).collect();
        let z: Vec<f64> = (0..m).map(|_| normal()).collect();
        let blocks: Vec<Vec<f64>> = (0..5)
            .map(|_| base.iter().map(|b| b + 0.3 * normal()).collect())
            .collect();
        let plan = |w: &[f64]| -> (Vec<f64>, Vec<f64>) {
            // Normal equations Σ w_s A_s^T A_s t = Σ w_s A_s^T z, solved by nalgebra.
            let mut lhs = nalgebra::DMatrix::<f64>::zeros(n, n);
            let mut rhs = nalgebra::DVector::<f64>::zeros(n);
            for (ws, a) in w.iter().zip(&blocks) {
                let a = nalgebra::DMatrix::from_row_slice(m, n, a);
                lhs += *ws * a.transpose() * &a;
                rhs += *ws * a.transpose() * nalgebra::DVector::from_column_slice(&z);
            }
            let t = lhs.lu().solve(&rhs).unwrap();
            let rms = blocks
                .iter()
                .map(|a| {
                    let a = nalgebra::DMatrix::from_row_slice(m, n, a);
                    let r = a * &t - nalgebra::DVector::from_column_slice(&z);
                    (r.norm_squared() / m as f64).sqrt()
                })
                .collect();
            (t.as_slice().to_vec(), rms)
        };
        let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let mut w = vec![1.0; 5];
        for _ in 0..3000 {
            let (_, r) = plan(&w);
            w = minimax_step(&w, &r, 0.05);
        }
        let reference = worst(&plan(&w).1);
        let rounds = minimax_weights(5, 0.0, |w, _| Ok(plan(w))).unwrap();
        let kept = worst(&plan(&rounds.weights).1);
        assert!(
            kept <= reference * 1.005,
            "{kept} against {reference}: {rounds:?}"
        );
        assert!(kept < rounds.worst_rms_nm[0], "{rounds:?}");
        // Weak duality: the bound is at most the minimax value, so the kept plan's gap to it is
        // at least its own excess over the reference.
        assert!(rounds.duality_gap >= -1e-9, "{rounds:?}");
        assert!(
            (1.0 + rounds.duality_gap) * reference * reference >= kept * kept * (1.0 - 1e-9),
            "{rounds:?}"
        );
    }

    #[test]
    fn the_summary_states_cost_and_saving() {
        let s = RobustSummary::new(
            RobustBasis::Planned,
            vec![1.3, 2.0, 3.0, 2.5, 1.5, 2.4, 1.6],
            vec![0.1, 11.8, 13.9, 4.0, 3.0, 3.9, 3.1],
        );
        assert!((s.nominal_cost_nm - 1.2).abs() < 1e-12);
        assert!((s.worst_scenario_saving_nm - 10.9).abs() < 1e-12);
        assert_eq!(s.scenarios[2], "tif_narrower_1sigma");
        assert_eq!(s.scenarios.len(), SCENARIO_COUNT);
    }

    /// The scenarios are symmetric about the nominal tool: the width factors' logarithms and
    /// the offsets sum to zero, so the mean scenario is the nominal to first order, and their
    /// size is the uncertainty's.
    #[test]
    fn scenarios_are_the_uncertainty_s_symmetric_sigma_points() {
        let u = ToolUncertainty {
            width_sigma: 0.04,
            offset_x_sigma_mm: 0.12,
            offset_y_sigma_mm: 0.07,
            ..ToolUncertainty::default()
        };
        let s = scenarios(&u);
        assert_eq!(s[0].width_factor, 1.0);
        assert_eq!(s[0].offset_mm, (0.0, 0.0));
        let log_width: f64 = s.iter().map(|s| s.width_factor.ln()).sum();
        let (sx, sy) = s.iter().fold((0.0, 0.0), |a, s| {
            (a.0 + s.offset_mm.0, a.1 + s.offset_mm.1)
        });
        assert!(log_width.abs() < 1e-15 && sx.abs() < 1e-15 && sy.abs() < 1e-15);
        assert!((s[1].width_factor - 1.04).abs() < 1e-15);
        let largest_x = s.iter().map(|s| s.offset_mm.0.abs()).fold(0.0, f64::max);
        let largest_y = s.iter().map(|s| s.offset_mm.1.abs()).fold(0.0, f64::max);
        assert_eq!((largest_x, largest_y), (0.12, 0.07));
    }
}
