//! Archimedes spiral `r = b theta`, `b = P / (2 pi)`, from the centre out to a radius, for round
//! parts: constant pitch `P` between turns and (roughly) constant point spacing along the curve.
//!
//! Points step in `theta` by `dtheta = step / sqrt(r^2 + b^2)` (the arc-length element
//! `ds = sqrt(r^2 + b^2) dtheta`) evaluated at the step's midpoint (two predictor passes), so
//! consecutive points are about `step` apart; the last point is at `theta = R / b` exactly.

use super::intersection::MAX_PATH_POINTS;
use super::DwellPath;
use crate::error::{Error, Result};
use std::f64::consts::PI;

/// Archimedes spiral of pitch `pitch_mm` out to `radius_mm`, points about `step_mm` apart,
/// centred on `(cx, cy)`; starts at the centre.
pub fn archimedes(
    centre_mm: [f64; 2],
    radius_mm: f64,
    pitch_mm: f64,
    step_mm: f64,
) -> Result<DwellPath> {
    Error::require_positive(&[
        ("spiral radius_mm", radius_mm),
        ("spiral pitch_mm", pitch_mm),
        ("spiral step_mm", step_mm),
    ])?;
    if !(centre_mm[0].is_finite() && centre_mm[1].is_finite()) {
        return Err(Error::invalid("spiral centre", "not finite"));
    }
    let b = pitch_mm / (2.0 * PI);
    // Length ~ pi R^2 / P; points ~ length / step.
    let estimate = PI * radius_mm * radius_mm / pitch_mm / step_mm + radius_mm / step_mm + 2.0;
    if estimate > MAX_PATH_POINTS as f64 {
        return Err(Error::invalid(
            "spiral",
            format!("about {estimate:.3e} points (limit {MAX_PATH_POINTS})"),
        ));
    }
    let theta_end = radius_mm / b;
    let cap = estimate as usize + 16;
    let (mut xs, mut ys) = (Vec::with_capacity(cap), Vec::with_capacity(cap));
    let mut theta = 0.0_f64;
    loop {
        let r = b * theta;
        let (s, c) = theta.sin_cos();
        xs.push(centre_mm[0] + r * c);
        ys.push(centre_mm[1] + r * s);
        if theta >= theta_end {
            break;
        }
        let mut d = step_mm / (r * r + b * b).sqrt();
        for _ in 0..2 {
            let rm = b * (theta + 0.5 * d);
            d = step_mm / (rm * rm + b * b).sqrt();
        }
        // Do not leave a sliver: finish exactly at the outer radius.
        theta = if theta + 1.5 * d >= theta_end {
            if theta + d >= theta_end || theta_end - theta < 0.5 * d {
                theta_end
            } else {
                theta + 0.5 * (theta_end - theta)
            }
        } else {
            theta + d
        };
        if xs.len() > cap * 2 {
            return Err(Error::Numerical {
                stage: "spiral",
                why: "point count ran past the estimate".into(),
            });
        }
    }
    DwellPath::new(xs, ys)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spiral_pitch_is_constant_and_spacing_even() {
        let (c, rad, p, step) = ([3.0, -2.0], 40.0, 1.3, 0.4);
        let s = archimedes(c, rad, p, step).unwrap();
        let (x, y) = (s.x_mm(), s.y_mm());
        // Radii where the spiral crosses the positive x axis (about the centre), interpolated
        // linearly along the chord: consecutive crossings are one pitch apart.
        let mut crossings = Vec::new();
        for j in 1..s.len() {
            let (y0, y1) = (y[j - 1] - c[1], y[j] - c[1]);
            let (x0, x1) = (x[j - 1] - c[0], x[j] - c[0]);
            if y0 < 0.0 && y1 >= 0.0 && x0 + x1 > 0.0 {
                let f = -y0 / (y1 - y0);
                crossings.push(x0 + f * (x1 - x0));
            }
        }
        assert!(crossings.len() > 25);
        // Chord interpolation is short of the arc by about step^2 / (8 r): tolerance.
        for w in crossings.windows(2) {
            let tol = step * step / (4.0 * w[0]);
            assert!((w[1] - w[0] - p).abs() < tol, "{w:?}");
        }
        // Spacing: within 2 % of the step past the first turn (the chord of a tightly curved arc
        // is shorter than the arc), never above it; the last two steps share the remainder so
        // the last point is exactly on the outer radius.
        let ds: Vec<f64> = (1..s.len())
            .map(|j| (x[j] - x[j - 1]).hypot(y[j] - y[j - 1]))
            .collect();
        for (j, &d) in ds.iter().enumerate() {
            let r = (x[j] - c[0]).hypot(y[j] - c[1]);
            assert!(d <= step * (1.0 + 1e-3), "{d}");
            if r > p && j + 2 < ds.len() {
                assert!(d > 0.98 * step, "j={j} r={r} d={d}");
            }
        }
        let last = s.len() - 1;
        assert!(((x[last] - c[0]).hypot(y[last] - c[1]) - rad).abs() < 1e-9);
        assert!(archimedes(c, rad, 0.0, step).is_err());
    }
}
