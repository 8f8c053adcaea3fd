//! The tool as the loop learns it: each run's measured removal calibrated
//! ([`crate::calibrate::calibrate`]) against the run's contact motion, and the next run planned
//! with the calibrated footprint and its drift.
//!
//! The contact motion of a planned run is its dwell points' stretches as the swept model samples
//! them: dwell point `j` (dwell `t_j`, started at `τ_j = Σ_{i<j} t_i`) contributes its stretch's
//! samples `(x_j + dx, y_j + dy)` with dwell `w t_j` at time `τ_j + t_j / 2`.
//!
//! A rate drifting linearly in program time, `r (1 + d (τ - τ_mid) / 3600)` (`d` per hour), is
//! compensated to first order by dwelling `t_j / (1 + d (τ_j' - τ_mid') / 3600)`, the times `τ'`
//! those of the compensated program (a fixed point, a few passes).

use crate::calibrate::{mid_times_s, Calibration, ContactMotion};
use crate::error::Result;
use crate::influence::Stretches;
use crate::path::DwellPath;
use crate::tif::Tif;

/// Relative wander of the rate from one run to the next that a calibrated plan allows for: the
/// rate learned from one run is the next run's to within this.
pub const RUN_TO_RUN_RATE_SIGMA: f64 = 0.01;

/// Seconds per hour.
const S_PER_HOUR: f64 = 3600.0;
/// Passes of the drift compensation's fixed point (its change shrinks by the drift over a run,
/// a few per cent, each pass).
const DRIFT_PASSES: usize = 4;

/// The tool learned from the last run's calibration.
#[derive(Debug, Clone)]
pub struct LearnedTool {
    /// The calibrated footprint (rate, width, offset, shape and free-form correction).
    pub tif: Tif,
    /// The calibration it came from.
    pub calibration: Calibration,
}

impl LearnedTool {
    /// The learned tool of a calibration.
    pub fn of(calibration: Calibration) -> Self {
        Self {
            tif: Tif::Grid(calibration.tif.clone()),
            calibration,
        }
    }

    /// Relative standard deviation of the next run's rate: the calibration's, with
    /// [`RUN_TO_RUN_RATE_SIGMA`] in quadrature.
    pub fn rate_sigma(&self) -> f64 {
        let c = &self.calibration;
        next_run_rate_sigma(c.figures.rate_factor, c.sigma.rate_factor)
    }

    /// The calibrated drift of the rate, relative per hour of program time.
    pub fn drift_per_hour(&self) -> f64 {
        self.calibration.figures.drift_per_hour
    }
}

/// Relative standard deviation of the next run's rate after a calibration that found the rate
/// factor `rate_factor` with standard deviation `rate_factor_sigma`: the calibration's relative
/// one with [`RUN_TO_RUN_RATE_SIGMA`] in quadrature.
pub fn next_run_rate_sigma(rate_factor: f64, rate_factor_sigma: f64) -> f64 {
    (rate_factor_sigma / rate_factor).hypot(RUN_TO_RUN_RATE_SIGMA)
}

/// The contact motion of a planned run (module documentation).
pub fn run_motion(path: &DwellPath, stretches: &Stretches, dwell_s: &[f64]) -> ContactMotion {
    let mut m = ContactMotion {
        x_mm: Vec::new(),
        y_mm: Vec::new(),
        dwell_s: Vec::new(),
        time_s: Vec::new(),
    };
    let points = path.x_mm().iter().zip(path.y_mm()).zip(dwell_s);
    for (j, (((&x, &y), &t), at)) in points.zip(mid_times_s(dwell_s)).enumerate() {
        if t > 0.0 {
            for &[dx, dy, w] in stretches.of(j) {
                m.x_mm.push(x + dx);
                m.y_mm.push(y + dy);
                m.dwell_s.push(w * t);
                m.time_s.push(at);
            }
        }
    }
    m
}

/// Dwell times compensating a rate drift of `drift_per_hour` (module documentation).
pub fn drift_compensated(dwell_s: &[f64], drift_per_hour: f64) -> Result<Vec<f64>> {
    let mut out = dwell_s.to_vec();
    if drift_per_hour == 0.0 {
        return Ok(out);
    }
    for _ in 0..DRIFT_PASSES {
        let total: f64 = out.iter().sum();
        let mid = total / 2.0;
        let mut next = Vec::with_capacity(out.len());
        for (&t0, at) in dwell_s.iter().zip(mid_times_s(&out)) {
            let factor = 1.0 + drift_per_hour * (at - mid) / S_PER_HOUR;
            if !(factor > 0.0 && factor.is_finite()) {
                return Err(crate::error::Error::invalid(
                    "drift_per_hour",
                    format!(
                        "a drift of {drift_per_hour} per hour stops the tool within this run \
                         ({total:.0} s)"
                    ),
                ));
            }
            next.push(t0 / factor);
        }
        out = next;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The compensated dwell times a drifting rate turns into removals within rounding of the
    /// planned ones: `t_j' r(τ_j')` equals `t_j` to second order in the drift.
    #[test]
    fn drift_compensation_restores_the_planned_dose() {
        let dwell: Vec<f64> = (0..200).map(|k| 10.0 + (k % 7) as f64).collect();
        let d = 0.05; // 5% per hour over a run of about 45 minutes
        let comp = drift_compensated(&dwell, d).unwrap();
        let total: f64 = comp.iter().sum();
        let mut start = 0.0;
        let mut worst: f64 = 0.0;
        for (&t0, &t) in dwell.iter().zip(&comp) {
            let dose = t * (1.0 + d * (start + t / 2.0 - total / 2.0) / S_PER_HOUR);
            worst = worst.max((dose / t0 - 1.0).abs());
            start += t;
        }
        // Uncompensated the dose is off by up to d * T / 2 / 3600 = 1.1%.
        assert!(worst < 1e-6, "worst relative dose error {worst}");
        assert_eq!(drift_compensated(&dwell, 0.0).unwrap(), dwell);
    }

    /// The motion of a run carries each dwell point's dwell, split over its stretch's samples,
    /// at the middle of its time in the program.
    #[test]
    fn run_motion_keeps_each_points_dwell_and_time() {
        let path = DwellPath::new(vec![0.0, 1.0, 2.0, 3.0], vec![0.0; 4]).unwrap();
        let stretches = Stretches::of_path(&path, 0.1).unwrap();
        let dwell = [2.0, 0.0, 3.0, 1.0];
        let m = run_motion(&path, &stretches, &dwell);
        m.validate().unwrap();
        let total: f64 = m.dwell_s.iter().sum();
        assert!((total - 6.0).abs() < 1e-12);
        let at = |t: f64| -> f64 {
            m.dwell_s
                .iter()
                .zip(&m.time_s)
                .filter(|(_, s)| (**s - t).abs() < 1e-12)
                .map(|(d, _)| d)
                .sum()
        };
        assert!((at(1.0) - 2.0).abs() < 1e-12);
        assert!((at(3.5) - 3.0).abs() < 1e-12);
        assert!((at(5.5) - 1.0).abs() < 1e-12);
    }
}
