//! Circular-arc transitions between serpentine raster lines, for smooth machine motion.
//!
//! From the end `E` of a line with unit direction `d` to the start `S` of the next, antiparallel
//! line a distance `P` away in the unit direction `n = (S - E)/P`: a quarter arc of radius `r`
//! about `E + r n` (leaving `E` along `d`, arriving along `n`), a straight move across of length
//! `P - 2r`, and a quarter arc about `E + (P - r) n` ending at `S` along `-d`. The path is
//! tangent-continuous; the turn lies outside the line ends by `r`. Needs `0 < r <= P/2`.
//!
//! Each quarter arc is cut into `m` equal chords, with `m` the larger of what the point spacing
//! asks (`ceil(pi r / (2 step))`) and what the chord tolerance `e` asks: a chord spanning the angle
//! `phi` of a circle of radius `r` lies `r (1 - cos(phi / 2))` inside the arc at its middle (the
//! sagitta), so `phi <= 2 acos(1 - e / r)` and `m >= (pi / 2) / (2 acos(1 - e / r))`.

use super::intersection::{push_line, push_point, Line};
use super::DwellPath;
use crate::error::{Error, Result};
use std::f64::consts::FRAC_PI_2;

/// Most chords per quarter arc.
const MAX_ARC_SEGMENTS: usize = 1_000_000;

/// Chords per quarter arc of radius `r_mm`: points at most `step_mm` apart and every chord's
/// sagitta at most `tol_mm` (see the module docs).
pub fn quarter_arc_segments(r_mm: f64, step_mm: f64, tol_mm: f64) -> usize {
    let by_step = ((FRAC_PI_2 * r_mm) / step_mm - 1e-9).ceil().max(1.0);
    let by_tol = if tol_mm >= r_mm {
        1.0
    } else {
        let phi = 2.0 * (1.0 - tol_mm / r_mm).acos();
        (FRAC_PI_2 / phi - 1e-9).ceil().max(1.0)
    };
    by_step.max(by_tol) as usize
}

/// The lines joined by arc turns of radius `radius_mm`, points at most `step_mm` apart along
/// lines and arcs, and arcs sampled so that no chord departs from the arc by more than
/// `arc_tolerance_mm` whatever the step.
pub fn lines_with_arcs(
    lines: &[Line],
    step_mm: f64,
    radius_mm: f64,
    arc_tolerance_mm: f64,
) -> Result<DwellPath> {
    if !(arc_tolerance_mm.is_finite() && arc_tolerance_mm > 0.0) {
        return Err(Error::invalid(
            "arc tolerance",
            format!("must be positive, got {arc_tolerance_mm} mm"),
        ));
    }
    if !(step_mm.is_finite() && step_mm > 0.0) {
        return Err(Error::invalid(
            "path step_mm",
            format!("must be positive, got {step_mm}"),
        ));
    }
    if !(radius_mm.is_finite() && radius_mm > 0.0) {
        return Err(Error::invalid(
            "arc radius_mm",
            format!("must be positive, got {radius_mm}"),
        ));
    }
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for (i, l) in lines.iter().enumerate() {
        push_line(l, step_mm, &mut xs, &mut ys)?;
        let Some(next) = lines.get(i + 1) else { break };
        let len = l.length_mm();
        if len == 0.0 {
            return Err(Error::invalid("arc turns", "a raster line has zero length"));
        }
        let d = [(l.end[0] - l.start[0]) / len, (l.end[1] - l.start[1]) / len];
        let e = l.end;
        let gap = [next.start[0] - e[0], next.start[1] - e[1]];
        let p = gap[0].hypot(gap[1]);
        if p == 0.0 {
            continue;
        }
        let n = [gap[0] / p, gap[1] / p];
        let along = gap[0] * d[0] + gap[1] * d[1];
        if along.abs() > 1e-9 * p.max(1.0) || radius_mm > 0.5 * p * (1.0 + 1e-12) {
            return Err(Error::invalid(
                "arc radius_mm",
                format!(
                    "{radius_mm} mm: a turn needs antiparallel lines whose ends face each other and a radius of at most half the line spacing ({} mm)",
                    0.5 * p
                ),
            ));
        }
        let r = radius_mm.min(0.5 * p);
        let segs = quarter_arc_segments(r, step_mm, arc_tolerance_mm);
        if segs > MAX_ARC_SEGMENTS {
            return Err(Error::invalid(
                "arc tolerance",
                format!(
                    "{arc_tolerance_mm} mm on a {r} mm arc needs {segs} chords per quarter turn \
                     (more than {MAX_ARC_SEGMENTS})"
                ),
            ));
        }
        let c1 = [e[0] + r * n[0], e[1] + r * n[1]];
        for k in 1..=segs {
            let phi = FRAC_PI_2 * k as f64 / segs as f64;
            let (s, c) = phi.sin_cos();
            push_point(
                [
                    c1[0] + r * (-n[0] * c + d[0] * s),
                    c1[1] + r * (-n[1] * c + d[1] * s),
                ],
                &mut xs,
                &mut ys,
            );
        }
        let c2 = [e[0] + (p - r) * n[0], e[1] + (p - r) * n[1]];
        let across = Line {
            start: [c1[0] + r * d[0], c1[1] + r * d[1]],
            end: [c2[0] + r * d[0], c2[1] + r * d[1]],
        };
        push_line(&across, step_mm, &mut xs, &mut ys)?;
        for k in 1..segs {
            let psi = FRAC_PI_2 * k as f64 / segs as f64;
            let (s, c) = psi.sin_cos();
            push_point(
                [
                    c2[0] + r * (d[0] * c + n[0] * s),
                    c2[1] + r * (d[1] * c + n[1] * s),
                ],
                &mut xs,
                &mut ys,
            );
        }
    }
    DwellPath::new(xs, ys)
}

/// Largest turning angle, rad, between consecutive segments of a path (0 for a straight path).
pub fn max_turn_angle_rad(path: &DwellPath) -> f64 {
    let (x, y) = (path.x_mm(), path.y_mm());
    let mut worst = 0.0_f64;
    for j in 1..path.len().saturating_sub(1) {
        let a = [x[j] - x[j - 1], y[j] - y[j - 1]];
        let b = [x[j + 1] - x[j], y[j + 1] - y[j]];
        let cross = a[0] * b[1] - a[1] * b[0];
        let dot = a[0] * b[0] + a[1] * b[1];
        worst = worst.max(cross.atan2(dot).abs());
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::BoundingBox;
    use crate::path::intersection::{lines_to_path, raster_lines};
    use crate::path::raster::RasterAxis;

    #[test]
    fn arc_turns_are_tangent_continuous() {
        let region = BoundingBox {
            x_min_mm: 0.0,
            x_max_mm: 20.0,
            y_min_mm: 0.0,
            y_max_mm: 10.0,
        };
        let (pitch, step) = (2.0, 0.1);
        for axis in [RasterAxis::X, RasterAxis::Y] {
            let lines = raster_lines(&region, pitch, axis, 0.0).unwrap();
            let sharp = lines_to_path(&lines, step).unwrap();
            assert!((max_turn_angle_rad(&sharp) - FRAC_PI_2).abs() < 1e-9);
            for r in [0.5, 1.0] {
                let smooth = lines_with_arcs(&lines, step, r, 1e-3).unwrap();
                // A chord polygon of an arc sampled at spacing <= step turns by at most step / r
                // per vertex; a corner would turn by pi/2.
                let turn = max_turn_angle_rad(&smooth);
                assert!(turn <= step / r + 1e-9, "r={r} turn={turn}");
                // Every arc point lies at distance r from its centre: check the far-end points.
                assert!(smooth.ds_mm().iter().all(|&d| d <= step + 1e-9));
                // The arc bulges beyond the line ends by exactly r.
                let xmax = smooth.x_mm().iter().copied().fold(f64::MIN, f64::max);
                let ymax = smooth.y_mm().iter().copied().fold(f64::MIN, f64::max);
                let over = match axis {
                    RasterAxis::X => xmax - 20.0,
                    RasterAxis::Y => ymax - 10.0,
                };
                assert!((over - r).abs() < 1e-9, "{over}");
            }
            assert!(lines_with_arcs(&lines, step, 1.5, 1e-3).is_err());
        }
    }

    #[test]
    fn arcs_meet_the_chord_tolerance_whatever_the_step() {
        let region = BoundingBox {
            x_min_mm: 0.0,
            x_max_mm: 20.0,
            y_min_mm: 0.0,
            y_max_mm: 10.0,
        };
        let lines = raster_lines(&region, 2.0, RasterAxis::X, 0.0).unwrap();
        let r = 1.0;
        for tol_mm in [1e-3, 1e-4, 1e-6] {
            // A step longer than the whole arc: the step alone would give one chord per quarter.
            let p = lines_with_arcs(&lines, 10.0, r, tol_mm).unwrap();
            // Each chord of a circle polygon turns the path by its angle phi at the next vertex,
            // and its sagitta is r (1 - cos(phi / 2)).
            let turn = max_turn_angle_rad(&p);
            let sagitta = r * (1.0 - (0.5 * turn).cos());
            assert!(sagitta <= tol_mm * (1.0 + 1e-9), "tol {tol_mm}: {sagitta}");
            // ... and no finer than needed: one chord fewer would exceed the tolerance.
            let m = quarter_arc_segments(r, 10.0, tol_mm);
            let coarser = r * (1.0 - (FRAC_PI_2 / (2.0 * (m - 1).max(1) as f64)).cos());
            assert!(m == 1 || coarser > tol_mm, "{m} {coarser}");
            // The arc points lie on their circles: the turn bulges past the line ends by r.
            let xmax = p.x_mm().iter().copied().fold(f64::MIN, f64::max);
            assert!((xmax - 20.0 - r).abs() < 1e-9);
        }
        // The published figure: 1 um on a 1 mm arc needs 18 chords per quarter turn
        // (2 acos(1 - 1e-3) = 0.0894 rad; (pi / 2) / 0.0894 = 17.6).
        assert_eq!(quarter_arc_segments(1.0, 10.0, 1e-3), 18);
        assert!(lines_with_arcs(&lines, 1.0, 1.0, 0.0).is_err());
    }
}
