//! Runs that pay: the expected reading of a plan's run, and a lighter plan or a plan of the
//! correctable band where the plan of the whole map spends dwell its run cannot pay for.
//!
//! The reading the interferometer is expected to give after the run
//! ([`crate::calibrate::expect`]) is drawn from the tool's uncertainty along the run's contact
//! motion: the executed program's where the solve executes one, else the plan's own (each dwell
//! point's stretch at its mid-dwell program time).
//!
//! A run *pays* when its gain beats its risk: the 95th percentile of the expected reading lies
//! below the RMS measured before the run. A plan of the whole map chases every feature, those
//! the tool cannot place or size well enough included (structure near the tool's width under a
//! width or placement uncertainty, noise), and removes as deep as the deepest of them needs.
//!
//! Plans are compared by their *expected cost*, the job's objective `0.5 sum r_i^2 + rho sum
//! t_j` with the expected reading in place of the model's residual: `E[rms^2] + (2 rho / m) T`
//! per map point. When the plan of the whole map does not pay, when the map's noise it would
//! imprint on the part ([`crate::calibrate::ReadingParts::noise_imprint_nm`]) outweighs what it
//! leaves and what the tool's uncertainty adds, or when its dwell weighs at least
//! [`DWELL_WEIGHS`] of its expected mean square, two kinds of plan are tried beside it:
//! - *lighter plans* of the whole map, the time weight raised to [`LIGHTER_STEPS`] times `rho_n = m
//!   sigma^2 / (2 T)`, the weight at which the plan's dwell `T` costs as much as the map's noise
//!   `sigma^2`, step by step until the expected cost rises (a step that does not converge is passed
//!   over): a plan chasing noise spends its dwell on modulations that imprint the noise, and a
//!   heavier time weight stops it where a second of dwell gains too little;
//! - where the job's plan does not pay or chases the noise, *band plans*: the measured error split
//!   into the smooth part the tool corrects at transfer gains of at least `g` and the rest
//!   ([`crate::band`]), for each `g` of [`BAND_GAINS`], the same set-up planned against the band
//!   alone (the problem's target the band, its edge rows extrapolated from it).
//!
//! Every figure of an outcome stays on the measured map; the plan kept is the one with the
//! smallest expected cost, of those that converged. When it does not pay, the outcome says so
//! with the floor (its expected reading) and its cause ([`crate::calibrate::FloorCause`]).

use super::{Outcome, Setup};
use crate::band::{self, CorrectableBand};
use crate::calibrate::{
    expected_reading, mid_times_s, tool::tif_grid, ContactMotion, Expected, FloorCause,
    ToolUncertainty,
};
use crate::error::Result;
use crate::map::HeightStats;
use crate::observer::{check_cancelled, Observer};
use serde::{Deserialize, Serialize};

/// Draws of the expected reading.
pub const EXPECTED_DRAWS: usize = 32;
/// Seed of the expected reading's draws (a fixed seed: the same plan gives the same figures).
pub const EXPECTED_SEED: u64 = 0x005e_ed0f_7001;

/// The transfer gains at whose frequency the band plans are cut, widest band first
/// ([`CorrectableBand::Tif`]).
pub const BAND_GAINS: [f64; 3] = [0.05, 0.25, 0.6];

/// What part of the measured error the plan corrects.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum PlanScope {
    /// The whole measured map.
    Map,
    /// The correctable band only ([`crate::band`]).
    Band {
        /// The transfer gain at the band's cap.
        min_gain: f64,
        /// The band's cut-off frequency, 1/mm.
        cutoff_per_mm: f64,
        /// Legendre degrees of the band's fit, `[n_x, n_y]`.
        degrees: [usize; 2],
        /// RMS of what the band leaves out (noise and structure finer than the band), nm.
        left_out_rms_nm: f64,
    },
}

/// The share of a plan's expected mean square its dwell must weigh, in the job's time weight,
/// before lighter plans are tried for a plan that pays and does not chase noise: below it no
/// plan can lower the expected cost by more than this share.
pub const DWELL_WEIGHS: f64 = 0.01;

/// The lighter plans' time weights, in multiples of the weight at which the whole map's plan's
/// dwell costs as much as the map's noise.
pub const LIGHTER_STEPS: [f64; 3] = [1.0, 10.0, 100.0];

/// Whether a run pays, and the plan chosen for it.
#[derive(Debug, Clone)]
pub struct PayingPlan {
    /// The plan's outcome (every figure on the measured map).
    pub outcome: Outcome,
    /// The expected reading after its run (`None` on a curved part, or where the plan spends no
    /// time in contact).
    pub expected: Option<Expected>,
    /// What the plan corrects.
    pub scope: PlanScope,
    /// The time weight the plan was solved with, nm^2 per s (the job's `rho` unless a lighter
    /// plan of the whole map was kept).
    pub rho: f64,
    /// The expected RMS of the job's plan of the whole map where another plan replaced it, nm.
    pub map_plan_expected_rms_nm: Option<f64>,
    /// The dwell of the job's plan of the whole map where another plan replaced it, s.
    pub map_plan_dwell_s: Option<f64>,
}

impl PayingPlan {
    /// Whether the run is expected to improve the part by more than its risk (module
    /// documentation); `None` without an expected reading.
    pub fn pays(&self) -> Option<bool> {
        self.expected.as_ref().map(pays)
    }

    /// The floor and its cause where no run pays: the smallest expected reading, nm.
    pub fn floor(&self) -> Option<(f64, FloorCause)> {
        match (&self.expected, self.pays()) {
            (Some(e), Some(false)) => Some((e.expected_rms_nm, e.parts.cause())),
            _ => None,
        }
    }
}

/// The planned dwell of an outcome, s.
fn dwell_s(outcome: &Outcome) -> f64 {
    outcome.solution.dwell_s.iter().sum()
}

/// Whether an expected reading pays: its 95th percentile below the measured RMS.
pub fn pays(e: &Expected) -> bool {
    e.expected_rms_range_nm[1] < e.measured_rms_nm
}

/// Whether the map's noise that the plan imprints on the part outweighs what the plan leaves
/// and what the tool's uncertainty adds: a plan of the smooth band may then read lower.
fn chases_noise(e: &Expected) -> bool {
    let p = &e.parts;
    p.noise_imprint_nm > p.residual_nm.max(p.tool_nm)
}

impl Setup {
    /// The job's time weight on the mean square of the map: `2 rho / m` nm^2 per s of dwell,
    /// the exchange rate of the objective `0.5 sum r_i^2 + rho sum t_j` between dwell and the
    /// mean square residual over the `m` map points.
    pub fn time_weight_nm2_per_s(&self) -> f64 {
        2.0 * self.rho / self.map.len().max(1) as f64
    }

    /// The expected reading after the run of `outcome` with the tool known to `uncertainty`
    /// (module documentation); `None` on a curved part or where the plan spends no time in
    /// contact.
    pub fn expected_reading(
        &self,
        outcome: &Outcome,
        uncertainty: &ToolUncertainty,
    ) -> Result<Option<Expected>> {
        if self.surface.is_some() {
            return Ok(None);
        }
        let (motion, removal) = match &outcome.executed {
            Some(Ok(executed)) => {
                let run = &executed.run;
                (
                    ContactMotion {
                        x_mm: run.contact.x_mm.clone(),
                        y_mm: run.contact.y_mm.clone(),
                        dwell_s: run.contact.dwell_s.clone(),
                        time_s: run.contact_at_s.clone(),
                    },
                    run.removal_nm.clone(),
                )
            }
            _ => {
                let dwell = &outcome.solution.dwell_s;
                (
                    ContactMotion {
                        x_mm: self.path.x_mm().to_vec(),
                        y_mm: self.path.y_mm().to_vec(),
                        dwell_s: dwell.clone(),
                        time_s: mid_times_s(dwell),
                    },
                    outcome.removal_nm.clone(),
                )
            }
        };
        if motion.contact_time_s() <= 0.0 {
            return Ok(None);
        }
        let map = &self.map;
        expected_reading(
            map.x_mm(),
            map.y_mm(),
            map.z_nm(),
            &removal,
            &motion,
            &tif_grid(&self.tif)?,
            uncertainty,
            EXPECTED_DRAWS,
            EXPECTED_SEED,
        )
        .map(Some)
    }

    /// The plan of a run that pays (module documentation): `outcome`, this set-up's solve,
    /// where its run pays, it does not chase the map's noise and its dwell weighs little in the
    /// job's time weight; else, of the whole map's plan, the lighter plans and the band plans,
    /// the one with the smallest expected cost ([`Setup::expected_cost_nm2`]).
    pub fn plan_that_pays(
        &self,
        outcome: Outcome,
        uncertainty: &ToolUncertainty,
        observer: &dyn Observer,
    ) -> Result<PayingPlan> {
        let expected = self.expected_reading(&outcome, uncertainty)?;
        let map_dwell_s = dwell_s(&outcome);
        let mut best = PayingPlan {
            outcome,
            expected,
            scope: PlanScope::Map,
            rho: self.rho,
            map_plan_expected_rms_nm: None,
            map_plan_dwell_s: None,
        };
        let Some(map_expected) = best.expected.clone().filter(|e| {
            !pays(e)
                || chases_noise(e)
                || self.time_weight_nm2_per_s() * map_dwell_s
                    >= DWELL_WEIGHS * e.expected_rms_nm.powi(2)
        }) else {
            return Ok(best);
        };
        let map_cost = self.expected_cost_nm2(&map_expected, map_dwell_s);
        let mut best_cost = map_cost;
        // The candidate's expected cost (`None` where it did not converge or has no expected
        // reading), kept where it is the smallest yet.
        let mut consider = |outcome: Outcome, scope: PlanScope, rho: f64| -> Result<Option<f64>> {
            if !outcome.solution.status.is_converged() {
                return Ok(None);
            }
            let Some(expected) = self.expected_reading(&outcome, uncertainty)? else {
                return Ok(None);
            };
            let cost = self.expected_cost_nm2(&expected, dwell_s(&outcome));
            if cost < best_cost {
                best_cost = cost;
                best = PayingPlan {
                    outcome,
                    expected: Some(expected),
                    scope,
                    rho,
                    map_plan_expected_rms_nm: Some(map_expected.expected_rms_nm),
                    map_plan_dwell_s: Some(map_dwell_s),
                };
            }
            Ok(Some(cost))
        };
        // Lighter plans of the whole map: the time weight raised from where the plan's dwell
        // costs as much as the map's noise (`c T = sigma^2`, `rho = m sigma^2 / (2 T)`), step by
        // step until the expected cost rises.
        let noise_rho = 0.5 * self.map.len() as f64 * map_expected.uncertainty.noise_rms_nm.powi(2)
            / map_dwell_s;
        let mut previous_cost = map_cost;
        for step in LIGHTER_STEPS {
            let rho = noise_rho * step;
            if !(rho.is_finite() && rho > self.rho) {
                continue;
            }
            check_cancelled(observer)?;
            let mut lighter = self.clone();
            lighter.rho = rho;
            let built = lighter.problem(observer).map_err(|e| e.source)?;
            let outcome = lighter.solve(&built.problem, observer)?;
            match consider(outcome, PlanScope::Map, rho)? {
                Some(cost) if cost >= previous_cost => break,
                Some(cost) => previous_cost = cost,
                None => {}
            }
        }
        // Band plans where the job's plan does not pay or chases the map's noise.
        if pays(&map_expected) && !chases_noise(&map_expected) {
            return Ok(best);
        }
        let (x, y, z) = (self.map.x_mm(), self.map.y_mm(), self.map.z_nm());
        for min_gain in BAND_GAINS {
            check_cancelled(observer)?;
            let split = band::split(x, y, z, &self.tif, CorrectableBand::Tif { min_gain })?;
            let band_rms_nm = HeightStats::of(&split.correctable_nm).rms_nm;
            if !(band_rms_nm > 0.0) {
                continue;
            }
            let mut banded = self.clone();
            banded.map = self.map.with_heights(split.correctable_nm.clone())?;
            let built = banded.problem(observer).map_err(|e| e.source)?;
            let mut outcome = self.solve(&built.problem, observer)?;
            // The solver's piston and objective are the band's; the outcome's figures are the
            // measured map's (where the problem has no rows beyond it, as for the map's plan).
            let m = self.map.len();
            if built.problem.m() == m && m > 0 {
                let d: Vec<f64> = outcome
                    .removal_nm
                    .iter()
                    .zip(z)
                    .map(|(h, z)| h - z)
                    .collect();
                let piston_nm = d.iter().sum::<f64>() / m as f64;
                outcome.solution.piston_nm = piston_nm;
                outcome.solution.objective =
                    0.5 * d.iter().map(|v| (v - piston_nm).powi(2)).sum::<f64>();
            }
            let scope = PlanScope::Band {
                min_gain,
                cutoff_per_mm: split.cutoff_per_mm.unwrap_or(f64::NAN),
                degrees: split.degrees,
                left_out_rms_nm: HeightStats::of(&split.uncorrectable_nm).rms_nm,
            };
            consider(outcome, scope, self.rho)?;
        }
        Ok(best)
    }

    /// The expected cost of a plan in the job's objective `0.5 sum r_i^2 + rho sum t_j` with
    /// the expected reading in place of the model's residual, per map point and doubled:
    /// `E[rms^2] + (2 rho / m) T`, nm^2.
    pub fn expected_cost_nm2(&self, expected: &Expected, dwell_s: f64) -> f64 {
        expected.expected_rms_nm.powi(2) + self.time_weight_nm2_per_s() * dwell_s
    }
}
