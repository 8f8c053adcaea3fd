//! Runs that pay: the expected reading of a plan's run, and a plan of the correctable band when
//! the plan of the whole map is not expected to improve the part.
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
//! When it does not pay, or when the map's noise it would imprint on the part
//! ([`crate::calibrate::ReadingParts::noise_imprint_nm`]) outweighs what it leaves and what the
//! tool's uncertainty adds, the measured error is split into the smooth part the tool corrects
//! at transfer gains of at least `g` and the rest ([`crate::band`]), for each `g` of
//! [`BAND_GAINS`], and the same set-up plans against the band alone (the problem's target the
//! band, its edge rows extrapolated from it; every figure of the outcome still on the measured
//! map). The plan kept is the one with the smallest expected reading, the whole map's included.
//! When none pays, the outcome says so with the floor (the smallest expected reading) and its
//! cause ([`crate::calibrate::FloorCause`]).

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
    /// The expected RMS of the whole map's plan where a band plan replaced it, nm.
    pub map_plan_expected_rms_nm: Option<f64>,
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
    /// where its run pays and it does not chase the map's noise; else the plan of the whole map
    /// or of one of the bands, whichever has the smallest expected reading.
    pub fn plan_that_pays(
        &self,
        outcome: Outcome,
        uncertainty: &ToolUncertainty,
        observer: &dyn Observer,
    ) -> Result<PayingPlan> {
        let expected = self.expected_reading(&outcome, uncertainty)?;
        let mut best = PayingPlan {
            outcome,
            expected,
            scope: PlanScope::Map,
            map_plan_expected_rms_nm: None,
        };
        let Some(map_expected) = best
            .expected
            .as_ref()
            .filter(|e| !pays(e) || chases_noise(e))
        else {
            return Ok(best);
        };
        let map_expected_rms_nm = map_expected.expected_rms_nm;
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
            let Some(expected) = self.expected_reading(&outcome, uncertainty)? else {
                continue;
            };
            let better = best
                .expected
                .as_ref()
                .is_none_or(|b| expected.expected_rms_nm < b.expected_rms_nm);
            if better {
                best = PayingPlan {
                    outcome,
                    expected: Some(expected),
                    scope: PlanScope::Band {
                        min_gain,
                        cutoff_per_mm: split.cutoff_per_mm.unwrap_or(f64::NAN),
                        degrees: split.degrees,
                        left_out_rms_nm: HeightStats::of(&split.uncorrectable_nm).rms_nm,
                    },
                    map_plan_expected_rms_nm: Some(map_expected_rms_nm),
                };
            }
        }
        Ok(best)
    }
}
