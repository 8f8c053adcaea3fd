//! How the executed part depends on how well the TIF is known.
//!
//! The program's contact motion is fixed; only the tool's footprint is uncertain. For each
//! scenario the TIF `f` is replaced by a perturbed `f'` and integrated along the same executed
//! motion, `h'_i = Σ_k f'(x_i - p_k) τ_k` (samples `p_k` carrying time `τ_k`), and the residual
//! `z - h'` (piston removed) is summarised:
//!
//! - width `w` with the volume kept: `f'(d) = f(d / w) / w²` (`w` = 1.03 and 1/1.03);
//! - rate `r`: `f' = r f`, so `h' = r h` (`r` = 1.03);
//! - tool offset `o`: the tool lands `o` away from where it is programmed, `f'(d) = f(d - o)`
//!   (`o` = 0.05 mm along x and along y).
//!
//! The motion is the executed program's where the solve runs one (an acceleration limit), the
//! plan's own otherwise (each dwell point's stretch samples under the swept model, the dwell
//! points under the point model: the program at its programmed feeds). On a curved part each
//! sample applies the TIF in its tangent frame and an offset moves the samples in plan
//! ([`crate::simulate::contact::contact_removals`]).

use crate::error::Result;
use crate::map::HeightStats;
use crate::tif::Perturbation;
use serde::{Deserialize, Serialize};

/// Relative change of the TIF's width and of its rate in the scenarios.
pub const RELATIVE_CHANGE: f64 = 0.03;

/// Offset of the tool in the offset scenarios, mm.
pub const OFFSET_MM: f64 = 0.05;

/// RMS and PV of one scenario's executed residual (piston removed), nm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScenarioFigures {
    /// RMS about the mean, nm.
    pub rms_nm: f64,
    /// Peak to valley, nm.
    pub pv_nm: f64,
}

/// The executed residual of the same program under each scenario of TIF uncertainty.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sensitivity {
    /// The TIF 3% wider, its volume kept.
    pub tif_wider_3pct: ScenarioFigures,
    /// The TIF 3% narrower (width / 1.03), its volume kept.
    pub tif_narrower_3pct: ScenarioFigures,
    /// The removal rate 3% higher.
    pub rate_plus_3pct: ScenarioFigures,
    /// The tool 0.05 mm off along x.
    pub offset_x_0p05mm: ScenarioFigures,
    /// The tool 0.05 mm off along y.
    pub offset_y_0p05mm: ScenarioFigures,
}

impl Sensitivity {
    /// The worst RMS over the scenarios, nm.
    pub fn worst_rms_nm(&self) -> f64 {
        [
            self.tif_wider_3pct,
            self.tif_narrower_3pct,
            self.rate_plus_3pct,
            self.offset_x_0p05mm,
            self.offset_y_0p05mm,
        ]
        .iter()
        .map(|s| s.rms_nm)
        .fold(0.0, f64::max)
    }
}

/// The four scenarios integrated along the motion, in the order [`Sensitivity::of_removals`]
/// takes them: TIF wider, narrower, tool off in x, in y (the rate scenario scales the nominal
/// removal).
pub const MOTION_SCENARIOS: [Perturbation; 4] = [
    Perturbation {
        width_factor: 1.0 + RELATIVE_CHANGE,
        ..Perturbation::NONE
    },
    Perturbation {
        width_factor: 1.0 / (1.0 + RELATIVE_CHANGE),
        ..Perturbation::NONE
    },
    Perturbation {
        offset_mm: (OFFSET_MM, 0.0),
        ..Perturbation::NONE
    },
    Perturbation {
        offset_mm: (0.0, OFFSET_MM),
        ..Perturbation::NONE
    },
];

impl Sensitivity {
    /// The sensitivity of a residual: `removal_nm` is the nominal removal at the map points whose
    /// error is `z_nm`, `motion` the removals of the same motion under [`MOTION_SCENARIOS`].
    pub fn of_removals(z_nm: &[f64], removal_nm: &[f64], motion: &[Vec<f64>]) -> Result<Self> {
        let figures = |h: &[f64]| {
            let s = HeightStats::of(&super::centred_residual_nm(z_nm, h));
            ScenarioFigures {
                rms_nm: s.rms_nm,
                pv_nm: s.pv_nm,
            }
        };
        let rate: Vec<f64> = removal_nm
            .iter()
            .map(|h| h * (1.0 + RELATIVE_CHANGE))
            .collect();
        let [wider, narrower, offset_x, offset_y] = motion else {
            return Err(crate::error::Error::invalid(
                "sensitivity",
                "four scenario removals expected",
            ));
        };
        Ok(Self {
            tif_wider_3pct: figures(wider),
            tif_narrower_3pct: figures(narrower),
            rate_plus_3pct: figures(&rate),
            offset_x_0p05mm: figures(offset_x),
            offset_y_0p05mm: figures(offset_y),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent as NoObserver;
    use crate::simulate::SampledProgram;
    use crate::tif::gaussian::GaussianTif;

    fn gaussian(sigma: f64, peak: f64) -> GaussianTif {
        GaussianTif::new(sigma, peak, 4.0 * sigma).unwrap()
    }

    /// On a motion that removes exactly the error with the nominal TIF, every scenario leaves a
    /// residual, the rate scenario exactly `0.03 z` (piston removed), and the sensitivity of
    /// the nominal removal itself is zero residual.
    #[test]
    fn scenarios_of_an_exact_removal_leave_the_perturbation_alone() {
        let g = gaussian(1.0, 5.0);
        // A row of samples along x, one second each, and map points around it.
        let contact = SampledProgram {
            x_mm: (0..41).map(|k| -4.0 + 0.2 * k as f64).collect(),
            y_mm: vec![0.0; 41],
            dwell_s: vec![1.0; 41],
            half_mm: Vec::new(),
        };
        let (mut mx, mut my) = (Vec::new(), Vec::new());
        for i in 0..21 {
            for j in 0..5 {
                mx.push(-5.0 + 0.5 * i as f64);
                my.push(-1.0 + 0.5 * j as f64);
            }
        }
        let h = crate::simulate::direct::removal_of_samples(&mx, &my, &contact, &g, &NoObserver)
            .unwrap();
        let tifs: Vec<_> = MOTION_SCENARIOS.iter().map(|p| p.of(&g)).collect();
        let motion = crate::simulate::direct::removals_nm(
            &mx,
            &my,
            &contact.x_mm,
            &contact.y_mm,
            &contact.dwell_s,
            &tifs,
            &NoObserver,
        )
        .unwrap();
        let s = Sensitivity::of_removals(&h, &h, &motion).unwrap();
        let expect = HeightStats::of(&super::super::centred_residual_nm(
            &h,
            &h.iter().map(|v| v * 1.03).collect::<Vec<_>>(),
        ));
        assert!((s.rate_plus_3pct.rms_nm - expect.rms_nm).abs() <= 1e-12 * expect.rms_nm);
        for f in [
            s.tif_wider_3pct,
            s.tif_narrower_3pct,
            s.offset_x_0p05mm,
            s.offset_y_0p05mm,
        ] {
            assert!(f.rms_nm > 0.0 && f.pv_nm >= f.rms_nm);
        }
        assert!(s.worst_rms_nm() >= s.rate_plus_3pct.rms_nm);
    }
}
