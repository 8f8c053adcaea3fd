//! A plan robust to how well the TIF is known: one dwell vector for every scenario at once.
//!
//! The scenarios are those of [`super::sensitivity`] that a plan can answer (a rate error only
//! scales the removal; the loop corrects it): the nominal TIF `f`, `f` 3% wider and 3% narrower
//! with its volume kept, and the tool 0.05 mm off along x and along y. With `R_s` the influence
//! matrix of scenario `s` (same path, same influence model), the robust plan solves
//!
//! `min_t  (1/S) Σ_s ½ ||R_s t + c − z||² + ρ Σ t   (+ λ)`,  `t` within its bounds,
//!
//! i.e. the rows `[R_1; ...; R_S]` stacked against `[z; ...; z]` with `ρ` and `λ` times `S`: the
//! mean squared residual over the scenarios (Ben-Tal, El Ghaoui and Nemirovski, *Robust
//! Optimization*, 2009: the scenario (sample-average) counterpart). One piston `c` serves every
//! scenario (a width change keeps the volume, an offset moves nothing in or out).

use super::sensitivity::{PerturbedTif, OFFSET_MM, RELATIVE_CHANGE};
use crate::error::Result;
use crate::influence::swept::{assemble_swept, Stretches};
use crate::influence::InfluenceMatrix;
use crate::map::HeightStats;
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::tif::InfluenceFunction;
use serde::{Deserialize, Serialize};

/// One scenario of a robust plan: the TIF's width factor (volume kept) and the tool's offset.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scenario {
    /// The name `report.json` gives it (the keys of [`super::sensitivity::Sensitivity`]).
    pub name: &'static str,
    /// Width factor of the TIF, its volume kept.
    pub width_factor: f64,
    /// Offset of the tool from where it is programmed, mm.
    pub offset_mm: (f64, f64),
}

/// The scenarios of a robust plan, the nominal first.
pub const SCENARIOS: [Scenario; 5] = [
    Scenario {
        name: "nominal",
        width_factor: 1.0,
        offset_mm: (0.0, 0.0),
    },
    Scenario {
        name: "tif_wider_3pct",
        width_factor: 1.0 + RELATIVE_CHANGE,
        offset_mm: (0.0, 0.0),
    },
    Scenario {
        name: "tif_narrower_3pct",
        width_factor: 1.0 / (1.0 + RELATIVE_CHANGE),
        offset_mm: (0.0, 0.0),
    },
    Scenario {
        name: "offset_x_0p05mm",
        width_factor: 1.0,
        offset_mm: (OFFSET_MM, 0.0),
    },
    Scenario {
        name: "offset_y_0p05mm",
        width_factor: 1.0,
        offset_mm: (0.0, OFFSET_MM),
    },
];

/// The stacked influence matrix `[R_1; ...; R_S]` of [`SCENARIOS`] over the rows `(x, y)`: each
/// block assembled with the scenario's TIF, swept along `stretches` (the swept model) or at the
/// points (the point model, `stretches` `None`).
pub fn stacked_matrix<T: InfluenceFunction + ?Sized>(
    x_mm: &[f64],
    y_mm: &[f64],
    path: &DwellPath,
    stretches: Option<&Stretches>,
    tif: &T,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    let mut blocks = Vec::with_capacity(SCENARIOS.len());
    for s in &SCENARIOS {
        let f = PerturbedTif::new(tif, s.width_factor, 1.0, s.offset_mm);
        blocks.push(match stretches {
            Some(st) => assemble_swept(x_mm, y_mm, path, st, &f, observer)?,
            None => InfluenceMatrix::assemble(x_mm, y_mm, path.x_mm(), path.y_mm(), &f, observer)?,
        });
    }
    crate::influence::stacked::stack_rows(&blocks)
}

/// The executed residual RMS of each scenario, nm: the nominal's and the sensitivity's
/// ([`SCENARIOS`] order).
pub fn executed_scenario_rms_nm(
    nominal_rms_nm: f64,
    s: &super::sensitivity::Sensitivity,
) -> Vec<f64> {
    vec![
        nominal_rms_nm,
        s.tif_wider_3pct.rms_nm,
        s.tif_narrower_3pct.rms_nm,
        s.offset_x_0p05mm.rms_nm,
        s.offset_y_0p05mm.rms_nm,
    ]
}

/// The residual RMS (piston removed) of each scenario, nm: `removal_nm` holds the stacked
/// removal `[R_1 t; ...; R_S t]` of blocks of `removal_nm.len() / S` rows whose first
/// `z_nm.len()` rows are the measured map.
pub fn scenario_rms_nm(z_nm: &[f64], removal_nm: &[f64]) -> Vec<f64> {
    let block = removal_nm.len() / SCENARIOS.len();
    (0..SCENARIOS.len())
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
    /// The summary of two plans' per-scenario RMS ([`SCENARIOS`] order) on `basis`.
    pub fn new(
        basis: RobustBasis,
        robust_plan_rms_nm: Vec<f64>,
        nominal_plan_rms_nm: Vec<f64>,
    ) -> Self {
        let worst = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        Self {
            basis,
            scenarios: SCENARIOS.iter().map(|s| s.name.to_string()).collect(),
            nominal_cost_nm: robust_plan_rms_nm[0] - nominal_plan_rms_nm[0],
            worst_scenario_saving_nm: worst(&nominal_plan_rms_nm) - worst(&robust_plan_rms_nm),
            robust_plan_rms_nm,
            nominal_plan_rms_nm,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::operator::InfluenceOperator;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    /// Each block of the stacked matrix is the scenario's own assembled `R`: its products are
    /// those of a directly assembled matrix with the perturbed Gaussian's closed form (the
    /// wider Gaussian's sigma times 1.03 and peak over 1.03², the offset one moved).
    #[test]
    fn each_block_is_the_scenario_matrix() {
        let (mx, my): (Vec<f64>, Vec<f64>) = (0..144)
            .map(|k| ((k % 12) as f64 * 0.5, (k / 12) as f64 * 0.5))
            .unzip();
        let path = DwellPath::new(vec![1.0, 2.5, 4.0], vec![2.0, 3.0, 2.5]).unwrap();
        let tif = GaussianTif::new(0.8, 5.0, 6.0).unwrap();
        let stacked = stacked_matrix(&mx, &my, &path, None, &tif, &Silent).unwrap();
        assert_eq!(stacked.shape(), (144 * SCENARIOS.len(), 3));
        let t = [1.0, 0.5, 2.0];
        let h = stacked.removal_nm(&t).unwrap();
        for (k, s) in SCENARIOS.iter().enumerate() {
            let w = s.width_factor;
            for i in 0..144 {
                let mut want = 0.0;
                for (j, tj) in t.iter().enumerate() {
                    let dx = mx[i] - path.x_mm()[j] - s.offset_mm.0;
                    let dy = my[i] - path.y_mm()[j] - s.offset_mm.1;
                    let r2 = (dx * dx + dy * dy) / (w * w);
                    // Truncated at 6 mm of the unperturbed Gaussian, scaled with the width.
                    if r2.sqrt() <= 6.0 {
                        want += tj * 5.0 / (w * w) * (-r2 / (2.0 * 0.8 * 0.8)).exp();
                    }
                }
                let got = h[k * 144 + i];
                assert!((got - want).abs() <= 1e-12 * want.abs().max(1.0), "{k} {i}");
            }
        }
        let rms = scenario_rms_nm(&vec![1.0; 144], &h);
        assert_eq!(rms.len(), SCENARIOS.len());
        assert!(rms.iter().all(|r| r.is_finite() && *r > 0.0));
    }

    #[test]
    fn the_summary_states_cost_and_saving() {
        let s = RobustSummary::new(
            RobustBasis::Planned,
            vec![1.3, 2.0, 3.0, 2.5, 1.5],
            vec![0.1, 11.8, 13.9, 4.0, 3.0],
        );
        assert!((s.nominal_cost_nm - 1.2).abs() < 1e-12);
        assert!((s.worst_scenario_saving_nm - 10.9).abs() < 1e-12);
        assert_eq!(s.scenarios[2], "tif_narrower_3pct");
    }
}
