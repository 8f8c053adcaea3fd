//! Learning the tool's removal rate from the runs already made.
//!
//! After a run planned with the TIF scaled by `F`, the measured removal `d = m_before - m_after`
//! (at the same measurement points) is regressed on the planned removal `h`:
//! `d = a + b x + c y + g h` (piston and tilt are taken out by every registration, so they are
//! free). The run's actual rate factor is `F g`, with the standard error
//! `F s sqrt((X^T X)^-1_gg)`, `s^2` the regression's residual variance. The factor for the next
//! run is the precision-weighted mean of every run's factor; its spread from run to run (or a
//! prior before there are two runs) is the rate uncertainty the next prediction carries.

use nalgebra::{Matrix4, Vector4};
use serde::{Deserialize, Serialize};

/// One run's observed removal-rate factor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RateObservation {
    /// The run's actual rate against the nominal TIF.
    pub factor: f64,
    /// Its standard error.
    pub sigma: f64,
}

/// Regresses the measured removal on the planned one (see the module documentation); `None`
/// when the planned removal has no variation beyond piston and tilt to regress on.
pub fn observe(
    x_mm: &[f64],
    y_mm: &[f64],
    planned_nm: &[f64],
    measured_nm: &[f64],
    planned_factor: f64,
) -> Option<RateObservation> {
    let n = planned_nm.len();
    if n < 5 || x_mm.len() != n || y_mm.len() != n || measured_nm.len() != n {
        return None;
    }
    let mean_h = planned_nm.iter().sum::<f64>() / n as f64;
    let var_h: f64 = planned_nm.iter().map(|h| (h - mean_h).powi(2)).sum();
    let size: f64 = planned_nm.iter().map(|h| h * h).sum();
    if !(var_h > 1e-12 * size) {
        return None;
    }
    let mut xtx = Matrix4::<f64>::zeros();
    let mut xty = Vector4::<f64>::zeros();
    for i in 0..n {
        let row = Vector4::new(1.0, x_mm[i], y_mm[i], planned_nm[i]);
        xtx += row * row.transpose();
        xty += row * measured_nm[i];
    }
    let inv = xtx.try_inverse()?;
    let coef = inv * xty;
    let ss: f64 = (0..n)
        .map(|i| {
            let fit = coef[0] + coef[1] * x_mm[i] + coef[2] * y_mm[i] + coef[3] * planned_nm[i];
            (measured_nm[i] - fit).powi(2)
        })
        .sum();
    let s2 = ss / (n - 4) as f64;
    let var = inv[(3, 3)] * s2;
    let (g, sg) = (coef[3], var.max(0.0).sqrt());
    (g.is_finite() && sg.is_finite() && g > 0.0).then_some(RateObservation {
        factor: planned_factor * g,
        sigma: planned_factor * sg,
    })
}

/// What the runs so far say about the rate of the next one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RateEstimate {
    /// The factor to plan the next run with.
    pub factor: f64,
    /// The expected relative deviation of the next run's rate from `factor`: the runs' spread
    /// about it and the estimate's own standard error in quadrature (the prior before two runs).
    pub sigma: f64,
}

/// The precision-weighted mean of the observations, or `initial` with the `prior_sigma`
/// uncertainty when there are none.
pub fn estimate(observed: &[RateObservation], initial: f64, prior_sigma: f64) -> RateEstimate {
    let weights: Vec<f64> = observed
        .iter()
        .map(|o| 1.0 / o.sigma.max(1e-6 * o.factor).powi(2))
        .collect();
    let wsum: f64 = weights.iter().sum();
    if observed.is_empty() || !(wsum > 0.0) {
        return RateEstimate {
            factor: initial,
            sigma: prior_sigma,
        };
    }
    let mean = observed
        .iter()
        .zip(&weights)
        .map(|(o, w)| w * o.factor)
        .sum::<f64>()
        / wsum;
    let standard_error = 1.0 / wsum.sqrt();
    let spread = if observed.len() >= 2 {
        let unweighted: f64 = observed
            .iter()
            .map(|o| (o.factor - mean).powi(2))
            .sum::<f64>()
            / (observed.len() - 1) as f64;
        unweighted.sqrt()
    } else {
        prior_sigma * mean
    };
    RateEstimate {
        factor: mean,
        sigma: spread.hypot(standard_error) / mean,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    #[test]
    fn a_known_rate_is_recovered_within_its_standard_error() {
        // A run planned at factor 1.02 that removed 1.05 / 1.02 of the plan, plus piston, tilt
        // and 1 nm of noise on each of two measurements.
        let mut rng = SplitMix64::new(9);
        let (mut x, mut y, mut h, mut d) = (vec![], vec![], vec![], vec![]);
        for j in 0..31 {
            for i in 0..31 {
                let (xi, yj) = (i as f64 - 15.0, j as f64 - 15.0);
                let hi = 40.0 + 20.0 * (xi / 7.0).sin() * (yj / 5.0).cos();
                x.push(xi);
                y.push(yj);
                h.push(hi);
                let noise = std::f64::consts::SQRT_2 * rng.normal();
                d.push(3.0 + 0.1 * xi - 0.05 * yj + hi * 1.05 / 1.02 + noise);
            }
        }
        let o = observe(&x, &y, &h, &d, 1.02).unwrap();
        assert!((o.factor - 1.05).abs() < 3.0 * o.sigma, "{o:?}");
        assert!(o.sigma > 0.0 && o.sigma < 0.01, "{o:?}");
        // A flat plan (a uniform layer) says nothing about the rate.
        let flat = vec![40.0; h.len()];
        assert!(observe(&x, &y, &flat, &d, 1.0).is_none());
    }

    #[test]
    fn the_estimate_is_the_precision_weighted_mean() {
        let obs = [
            RateObservation {
                factor: 1.04,
                sigma: 0.01,
            },
            RateObservation {
                factor: 0.98,
                sigma: 0.02,
            },
        ];
        let e = estimate(&obs, 1.0, 0.03);
        // (1.04 / 1e-4 + 0.98 / 4e-4) / (1 / 1e-4 + 1 / 4e-4) = 1.028
        assert!((e.factor - 1.028).abs() < 1e-12, "{e:?}");
        assert!(e.sigma > 0.03, "{e:?}");
        let none = estimate(&[], 1.0, 0.03);
        assert_eq!((none.factor, none.sigma), (1.0, 0.03));
    }
}
