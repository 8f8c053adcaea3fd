//! Edge-offset trajectory for bonnet polishing by the lifting-bonnet method, and the
//! least-squares cubic Bezier fit of the part edge it is built on.
//!
//! # Offset lines
//!
//! Near the edge the bonnet is lifted so its polishing spot shrinks line by line: spot radii
//! `r_0 = r_max`, then `r_k = q^k r_max` (geometric, `0 < q < 1`) or `r_k = r_max - k d`
//! (arithmetic), while `r_k >= r_min`. The pressing depth for spot radius `r` on a bonnet of
//! radius `R` is `h = R - sqrt(R^2 - r^2)` (inverse of `r = sqrt(2 R h - h^2)`).
//!
//! # Equal residual height
//!
//! Across a line the spot is modelled as a circular profile of its radius (the ball-end scallop
//! model): a line with spot `r` leaves height `r - sqrt(r^2 - u^2)` at distance `u`, reaching the
//! residual height `e` at `w(r) = sqrt(2 r e - e^2)`. Lines `k` and `k + 1` are therefore spaced
//! `d_k = w(r_k) + w(r_{k+1})`, so their profiles cross exactly at height `e`.
//!
//! # Centre offsets
//!
//! The edge-most line (smallest spot) has its centre `o_N = r_N - overhang` inside the edge, and
//! `o_k = o_{k+1} + d_k` inwards. Each offset curve is the inward offset of the fitted edge at
//! distance `o`: every Bezier segment moved by `o` along its normal, joins bridged by arcs of
//! radius `o`, and the loops an offset forms at convex corners (and wherever the edge's radius
//! of curvature is below `o`) trimmed, so every point of the curve is `o` from the edge. Its
//! achieved offset (mean distance of its points to the fitted edge) is measured and the offset
//! is corrected by the ratio of the set to the achieved distance (three passes). The curve is
//! resampled at equal arc length no more than the step apart, its corners kept, no point
//! repeated.
//!
//! # Bezier fit
//!
//! Polygon vertices turning by more than [`CORNER_TURN_DEG`] are corners and end segments; the
//! stretches between them are densified and fitted by cubic segments with fixed end points, the
//! inner control points by linear least squares on chord-length parameters, refined by Newton
//! reparametrisation (Schneider, *An Algorithm for Automatically Fitting Digitized Curves*,
//! Graphics Gems 1990). The fit error is measured along the whole curve: the larger of the
//! largest distance of 257 samples of the segment from the polyline it replaces and the largest
//! distance of that polyline's vertices from the sampled segment; a segment above the tolerance
//! is split at the vertex nearest its worst point and both halves are fitted again.

mod bezier;
mod offset;
mod plan;

pub use bezier::{
    curve_polyline_error, fit_bezier_spline, fit_cubic, spline_distance_mm, CubicBezier,
    FIT_SAMPLES_PER_SEGMENT,
};
pub use offset::CORNER_TURN_DEG;
pub use plan::{
    plan_offsets, residual_half_width_mm, EdgeOffsetSettings, OffsetLine, SpotProgression,
};

use super::DwellPath;
use crate::error::{Error, Result};
#[cfg(test)]
use bezier::segment_distance;
use bezier::EdgeIndex;
#[cfg(test)]
use offset::inside;
use offset::{clean_polygon, curve_length, fit_closed_edge, resample_closed, trimmed_offset};

/// The edge-offset trajectory: lines innermost first, each the fitted edge offset inwards.
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeOffsetPath {
    /// All offset curves' points in visiting order.
    pub path: DwellPath,
    /// The lines (spot, depth, offsets).
    pub lines: Vec<OffsetLine>,
    /// Index of the first point of each line in `path`.
    pub line_starts: Vec<usize>,
    /// The fitted edge (counter-clockwise).
    pub edge: Vec<CubicBezier>,
    /// Largest fit error of the edge against the edge polygon ([`curve_polyline_error`]), mm.
    pub fit_error_mm: f64,
    /// Vertices of the edge polygon kept as corners (turn above [`CORNER_TURN_DEG`]).
    pub corners: usize,
}

/// A polygon vertex whose direction turns by more than this is a corner: the Bezier fit
/// How far a line's nearest point may fall short of the distance that keeps its spot inside
/// the fitted edge, mm (the offset curves are trimmed and resampled to about this precision).
pub const CONTAINMENT_TOLERANCE_MM: f64 = 1e-6;

/// Largest set offset of the plan, mm.
fn lines_offset_max(settings: &EdgeOffsetSettings) -> Result<f64> {
    Ok(plan_offsets(settings)?
        .iter()
        .map(|l| l.offset_mm)
        .fold(0.0, f64::max))
}

/// Builds the trajectory for the closed edge polygon `edge` (first point not repeated; either
/// orientation, lines follow it): Bezier fit within the tolerance against the polygon, offset
/// plan, trimmed offset curves with the set/achieved correction.
pub fn edge_offset(edge: &[[f64; 2]], settings: &EdgeOffsetSettings) -> Result<EdgeOffsetPath> {
    settings.validate()?;
    let (poly, cw) = clean_polygon(edge)?;
    let (spline, fit_error_mm, corners) = fit_closed_edge(
        &poly,
        settings.bezier_tolerance_mm,
        settings.step_mm.min(1.0),
    )?;
    let raw_step = 0.25 * settings.step_mm;
    // The fitted edge as a closed polyline, each segment cut into chords no longer than the
    // raw offset step (at most FIT_SAMPLES_PER_SEGMENT).
    let mut edge_dense: Vec<[f64; 2]> = Vec::new();
    for c in &spline {
        let m = ((curve_length(c) / raw_step).ceil() as usize).clamp(4, FIT_SAMPLES_PER_SEGMENT);
        for i in 0..m {
            edge_dense.push(c.eval(i as f64 / m as f64));
        }
    }
    let largest = lines_offset_max(settings)?;
    let index = EdgeIndex::new(edge_dense, largest.max(settings.step_mm));
    let mut lines = plan_offsets(settings)?;
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    let mut line_starts = Vec::new();
    // Each line starts at the point nearest to where the previous one started.
    let mut start_ref = spline[0].eval(0.0);
    let curve_at = |used: f64, set: f64| -> Result<Vec<[f64; 2]>> {
        let (c, corner) = trimmed_offset(&spline, &index, used, raw_step)?;
        let pts = resample_closed(&c, &corner, settings.step_mm);
        if pts.len() < 3 {
            return Err(Error::Geometry(format!(
                "the offset curve at {set} mm has fewer than three points"
            )));
        }
        Ok(pts)
    };
    for line in lines.iter_mut() {
        let mut used = line.offset_mm;
        let mut pts = Vec::new();
        let mut achieved = 0.0;
        let mut used_pts = used;
        for _ in 0..3 {
            pts = curve_at(used, line.offset_mm)?;
            used_pts = used;
            achieved = pts
                .iter()
                .map(|&p| index.distance_within(p, 2.0 * used + settings.step_mm))
                .sum::<f64>()
                / pts.len() as f64;
            if achieved.is_nan() || achieved <= 0.0 {
                return Err(Error::Geometry(format!(
                    "offset curve at {} mm collapsed",
                    line.offset_mm
                )));
            }
            used *= line.offset_mm / achieved;
        }
        // Containment: the nearest point of the line must be at least its spot radius from the
        // edge (the edge-most line: its set offset, which allows the set overhang). The mean
        // correction above can pull straight stretches closer where corners push the mean out.
        let need = line.spot_radius_mm.min(line.offset_mm);
        let mut used = used_pts;
        let nearest = |pts: &[[f64; 2]], used: f64| {
            pts.iter()
                .map(|&p| index.distance_within(p, 2.0 * used + settings.step_mm))
                .fold(f64::INFINITY, f64::min)
        };
        let mut near = nearest(&pts, used);
        for _ in 0..8 {
            if near >= need - CONTAINMENT_TOLERANCE_MM {
                break;
            }
            used += need - near + 0.5 * CONTAINMENT_TOLERANCE_MM;
            pts = curve_at(used, line.offset_mm)?;
            near = nearest(&pts, used);
            achieved = pts
                .iter()
                .map(|&p| index.distance_within(p, 2.0 * used + settings.step_mm))
                .sum::<f64>()
                / pts.len() as f64;
        }
        if near < need - CONTAINMENT_TOLERANCE_MM {
            return Err(Error::Geometry(format!(
                "the line of spot radius {} mm cannot be kept inside the edge: its nearest point \
                 is {near} mm from it",
                line.spot_radius_mm
            )));
        }
        line.clearance_mm = near - line.spot_radius_mm;
        line.achieved_offset_mm = achieved;
        if cw {
            pts.reverse();
        }
        let k0 = (0..pts.len())
            .min_by(|&a, &b| {
                let da = (pts[a][0] - start_ref[0]).hypot(pts[a][1] - start_ref[1]);
                let db = (pts[b][0] - start_ref[0]).hypot(pts[b][1] - start_ref[1]);
                da.total_cmp(&db)
            })
            .unwrap_or(0);
        pts.rotate_left(k0);
        start_ref = pts[0];
        line_starts.push(xs.len());
        for p in pts {
            xs.push(p[0]);
            ys.push(p[1]);
        }
    }
    Ok(EdgeOffsetPath {
        path: DwellPath::new(xs, ys)?,
        lines,
        line_starts,
        edge: spline,
        fit_error_mm,
        corners,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounded_square_edge_offsets_are_achieved() {
        // Square of half-side 30 mm with corner radius 10 mm, clockwise, sampled every ~0.5 mm.
        let mut edge = Vec::new();
        let (h, rc) = (30.0, 10.0);
        let corners = [
            (h - rc, -(h - rc)),
            (-(h - rc), -(h - rc)),
            (-(h - rc), h - rc),
            (h - rc, h - rc),
        ];
        for (q, &(cx, cy)) in corners.iter().enumerate() {
            // Clockwise: each corner arc runs from angle -q*90 deg down by 90 deg.
            let a0 = -(q as f64) * std::f64::consts::FRAC_PI_2;
            for i in 0..32 {
                let a = a0 - std::f64::consts::FRAC_PI_2 * i as f64 / 32.0;
                edge.push([cx + rc * a.cos(), cy + rc * a.sin()]);
            }
            let (nx, ny) = corners[(q + 1) % 4];
            let end = [
                cx + rc * (a0 - std::f64::consts::FRAC_PI_2).cos(),
                cy + rc * (a0 - std::f64::consts::FRAC_PI_2).sin(),
            ];
            let start_next = [
                nx + rc * (a0 - std::f64::consts::FRAC_PI_2).cos(),
                ny + rc * (a0 - std::f64::consts::FRAC_PI_2).sin(),
            ];
            for i in 0..80 {
                let f = i as f64 / 80.0;
                edge.push([
                    end[0] + f * (start_next[0] - end[0]),
                    end[1] + f * (start_next[1] - end[1]),
                ]);
            }
        }
        let s = EdgeOffsetSettings {
            bezier_tolerance_mm: 0.005,
            ..EdgeOffsetSettings::default()
        };
        let t = edge_offset(&edge, &s).unwrap();
        assert!(
            t.fit_error_mm <= s.bezier_tolerance_mm,
            "{} segments, error {}",
            t.edge.len(),
            t.fit_error_mm
        );
        for (k, l) in t.lines.iter().enumerate() {
            assert!(
                (l.achieved_offset_mm - l.offset_mm).abs() < 1e-3 * l.offset_mm,
                "{l:?}"
            );
            // Every point of the line lies inside the square, at least the offset from its sides
            // minus the fit tolerance, and on the inner side (orientation handled).
            let end = t.line_starts.get(k + 1).copied().unwrap_or(t.path.len());
            for j in t.line_starts[k]..end {
                let (x, y) = (t.path.x_mm()[j], t.path.y_mm()[j]);
                let margin = h - x.abs().max(y.abs());
                assert!(margin >= l.offset_mm - 0.01, "line {k} point {j}: {margin}");
            }
        }
    }

    #[test]
    fn bezier_exact_on_a_cubic() {
        let c = CubicBezier {
            p: [[0.0, 0.0], [3.0, 7.0], [9.0, -4.0], [12.0, 2.0]],
        };
        let t: Vec<f64> = (0..400).map(|i| i as f64 / 399.0).collect();
        let pts: Vec<[f64; 2]> = t.iter().map(|&ti| c.eval(ti)).collect();
        // With the true parameters the least squares reproduces the control points.
        let f = fit_cubic(&pts, &t).unwrap();
        for k in 0..4 {
            for i in 0..2 {
                assert!((f.p[k][i] - c.p[k][i]).abs() < 1e-10);
            }
        }
        // From chord-length parameters, reparametrisation converges onto the cubic: one segment
        // within 1e-3 mm of the 400-point polyline, measured both ways along the whole curve (the
        // polyline's own chords depart from the cubic by up to about 1e-4 mm).
        let (spline, err) = fit_bezier_spline(&pts, 1e-3).unwrap();
        assert_eq!(spline.len(), 1);
        assert!(err <= 1e-3);
        for k in 0..4 {
            for i in 0..2 {
                assert!(
                    (spline[0].p[k][i] - c.p[k][i]).abs() < 1e-2,
                    "{:?}",
                    spline[0]
                );
            }
        }
    }

    #[test]
    fn bezier_splits_until_within_tolerance_on_noisy_edge() {
        // Circle of radius 50 with a deterministic +-0.02 mm ripple.
        let n = 720;
        let pts: Vec<[f64; 2]> = (0..=n)
            .map(|i| {
                let a = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
                let r = 50.0 + 0.02 * ((i * 7919 % 13) as f64 / 6.0 - 1.0);
                [r * a.cos(), r * a.sin()]
            })
            .collect();
        for tol in [0.05, 0.03] {
            let (spline, err) = fit_bezier_spline(&pts, tol).unwrap();
            assert!(spline.len() >= 2 && err <= tol);
            let worst = pts
                .iter()
                .map(|&p| spline_distance_mm(&spline, p))
                .fold(0.0, f64::max);
            assert!(worst <= tol, "tol {tol}: worst {worst}");
        }
    }

    #[test]
    fn offsets_follow_progression_and_residual() {
        let s = EdgeOffsetSettings::default();
        let r = s.spot_radii_mm().unwrap();
        assert!((r[0] - 6.0).abs() < 1e-12);
        for w in r.windows(2) {
            assert!((w[1] / w[0] - 0.8).abs() < 1e-12);
        }
        assert!(*r.last().unwrap() >= 1.5 && r.last().unwrap() * 0.8 < 1.5);
        let a = EdgeOffsetSettings {
            progression: SpotProgression::Arithmetic { decrement_mm: 0.7 },
            ..s.clone()
        };
        let ra = a.spot_radii_mm().unwrap();
        for w in ra.windows(2) {
            assert!((w[0] - w[1] - 0.7).abs() < 1e-12);
        }
        let lines = plan_offsets(&s).unwrap();
        for w in lines.windows(2) {
            // The two circular profiles of radii r_k, r_{k+1}, bottoms d apart, cross at the
            // requested residual height: solve r1 - sqrt(r1^2 - u^2) = r2 - sqrt(r2^2 - (d-u)^2)
            // by bisection and compare.
            let (r1, r2, d) = (w[0].spot_radius_mm, w[1].spot_radius_mm, w[0].spacing_mm);
            let f = |u: f64| {
                (r1 - (r1 * r1 - u * u).sqrt()) - (r2 - (r2 * r2 - (d - u) * (d - u)).sqrt())
            };
            let (mut lo, mut hi) = (0.0, d);
            for _ in 0..200 {
                let m = 0.5 * (lo + hi);
                if f(m) < 0.0 {
                    lo = m;
                } else {
                    hi = m;
                }
            }
            let e = r1 - (r1 * r1 - lo * lo).sqrt();
            // At the equal-residual spacing the profiles cross at the residual height; lines
            // closer than that (fill lines keeping the spots inside) leave less.
            let d_eq = residual_half_width_mm(r1, s.residual_height_mm)
                + residual_half_width_mm(r2, s.residual_height_mm);
            assert!(d <= d_eq * (1.0 + 1e-12));
            assert!(e <= s.residual_height_mm * (1.0 + 1e-9));
            if (d - d_eq).abs() <= 1e-12 * d_eq {
                assert!((e - s.residual_height_mm).abs() < 1e-9 * s.residual_height_mm.max(1.0));
            }
            assert!((w[0].offset_mm - w[1].offset_mm - d).abs() < 1e-12);
            // Spots shrink towards the edge and every centre is a spot radius inside.
            assert!(w[1].spot_radius_mm <= w[0].spot_radius_mm);
            assert!(w[0].offset_mm >= w[0].spot_radius_mm - 1e-12);
            // Depth reproduces the spot radius: sqrt(2 R h - h^2).
            let h = w[0].depth_mm;
            assert!((((2.0 * 20.0 * h - h * h).sqrt()) - r1).abs() < 1e-9);
        }
        let last = lines.last().unwrap();
        assert!((last.offset_mm - last.spot_radius_mm).abs() < 1e-12);
        // On a circular edge the corrected offset curves sit at their set offsets.
        let edge: Vec<[f64; 2]> = (0..360)
            .map(|i| {
                let a = (i as f64).to_radians();
                [40.0 * a.cos(), 40.0 * a.sin()]
            })
            .collect();
        let t = edge_offset(&edge, &s).unwrap();
        assert!(t.fit_error_mm <= s.bezier_tolerance_mm);
        for (k, l) in t.lines.iter().enumerate() {
            assert!((l.achieved_offset_mm - l.offset_mm).abs() < 1e-3, "{l:?}");
            let j = t.line_starts[k];
            let rr = t.path.x_mm()[j].hypot(t.path.y_mm()[j]);
            assert!((40.0 - rr - l.offset_mm).abs() < 2e-3);
        }
    }

    /// Distance from `p` to the closed polygon `poly`, computed segment by segment.
    fn dist_to_polygon(poly: &[[f64; 2]], p: [f64; 2]) -> f64 {
        (0..poly.len())
            .map(|i| segment_distance(p, poly[i], poly[(i + 1) % poly.len()]))
            .fold(f64::INFINITY, f64::min)
    }

    /// The three properties on `edge`: fit error measured independently (4000 samples per
    /// segment against the polygon, and every vertex against the spline) within tolerance;
    /// every path point inside the polygon at its line's offset (fit tolerance and chord
    /// allowance aside), so none beyond the edge; no repeated points and no step longer than
    /// the set step.
    fn check_properties(edge: &[[f64; 2]], s: &EdgeOffsetSettings) -> EdgeOffsetPath {
        let t = edge_offset(edge, s).unwrap();
        let tol = s.bezier_tolerance_mm;
        let mut worst: f64 = 0.0;
        for c in &t.edge {
            for i in 0..=4000 {
                worst = worst.max(dist_to_polygon(edge, c.eval(i as f64 / 4000.0)));
            }
        }
        for &v in edge {
            worst = worst.max(spline_distance_mm(&t.edge, v));
        }
        assert!(worst <= tol * (1.0 + 1e-6), "fit error {worst} > {tol}");
        assert!(t.fit_error_mm <= tol && t.fit_error_mm >= 0.98 * worst - 1e-9);
        let chord = 0.005;
        let (x, y) = (t.path.x_mm(), t.path.y_mm());
        for (k, l) in t.lines.iter().enumerate() {
            let end = t.line_starts.get(k + 1).copied().unwrap_or(x.len());
            assert!(end - t.line_starts[k] >= 3);
            for j in t.line_starts[k]..end {
                let p = [x[j], y[j]];
                assert!(inside(edge, p), "line {k} point {j} {p:?} outside the edge");
                let d = dist_to_polygon(edge, p);
                assert!(
                    (d - l.offset_mm).abs() <= tol + chord,
                    "line {k} point {j}: distance {d}, offset {}",
                    l.offset_mm
                );
                // The whole spot inside the polygon: the distance to the polygon is at least the
                // line's spot radius (lines of the smallest spot: less the set overhang).
                let smallest = t
                    .lines
                    .iter()
                    .map(|l| l.spot_radius_mm)
                    .fold(f64::INFINITY, f64::min);
                let allowed = if l.spot_radius_mm <= smallest * (1.0 + 1e-12) {
                    s.overhang_mm
                } else {
                    0.0
                };
                assert!(
                    d >= l.spot_radius_mm - allowed - tol - 1e-6,
                    "line {k} point {j}: spot {} overhangs by {}",
                    l.spot_radius_mm,
                    l.spot_radius_mm - d
                );
                if j + 1 < end {
                    let step = (x[j + 1] - x[j]).hypot(y[j + 1] - y[j]);
                    assert!(
                        step > 1e-3 && step <= s.step_mm * (1.0 + 1e-9),
                        "step {step}"
                    );
                }
            }
        }
        let mut pts: Vec<(f64, f64)> = x.iter().copied().zip(y.iter().copied()).collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
        for w in pts.windows(2) {
            assert!(
                (w[0].0 - w[1].0).hypot(w[0].1 - w[1].1) > 1e-6,
                "repeated {w:?}"
            );
        }
        t
    }

    fn bonnet40() -> EdgeOffsetSettings {
        EdgeOffsetSettings {
            bonnet_radius_mm: 40.0,
            ..EdgeOffsetSettings::default()
        }
    }

    #[test]
    fn square_of_four_corners_stays_on_the_part() {
        // The 4-corner 60 mm square with a 40 mm bonnet, both orientations, with and without
        // overhang: every segment of the fit is a side (straight, exact), offsets are squares.
        let sq = [[-30.0, -30.0], [30.0, -30.0], [30.0, 30.0], [-30.0, 30.0]];
        let t = check_properties(&sq, &bonnet40());
        assert_eq!(t.corners, 4);
        assert!(t.fit_error_mm < 1e-9);
        let cw: Vec<[f64; 2]> = sq.iter().rev().copied().collect();
        let over = EdgeOffsetSettings {
            overhang_mm: 1.0,
            ..bonnet40()
        };
        check_properties(&cw, &over);
        // The edge-most line is a square of half-side 30 - (r_min - overhang).
        let t = check_properties(&sq, &over);
        let k = t.lines.len() - 1;
        let o = t.lines[k].offset_mm;
        for j in t.line_starts[k]..t.path.len() {
            let m = t.path.x_mm()[j].abs().max(t.path.y_mm()[j].abs());
            assert!((m - (30.0 - o)).abs() < 1e-9, "{m}");
        }
    }

    #[test]
    fn rectangle_circle_polygons_and_non_convex_shape() {
        let rect = [[0.0, 0.0], [80.0, 0.0], [80.0, 25.0], [0.0, 25.0]];
        check_properties(&rect, &bonnet40());
        // Coarse circle polygons: 12 vertices (30 deg turns: all corners) and 36 vertices
        // (10 deg: smoothed within tolerance of the polygon), and a fine 360-gon.
        for n in [12usize, 36, 360] {
            let c: Vec<[f64; 2]> = (0..n)
                .map(|i| {
                    let a = std::f64::consts::TAU * i as f64 / n as f64;
                    [25.0 * a.cos(), 25.0 * a.sin()]
                })
                .collect();
            check_properties(&c, &bonnet40());
        }
        // Non-convex: an L (one reflex corner, offset arcs around it) and a 5-point star.
        let ell = [
            [0.0, 0.0],
            [50.0, 0.0],
            [50.0, 20.0],
            [20.0, 20.0],
            [20.0, 50.0],
            [0.0, 50.0],
        ];
        check_properties(&ell, &bonnet40());
        let star: Vec<[f64; 2]> = (0..10)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / 10.0;
                let r = if i % 2 == 0 { 40.0 } else { 22.0 };
                [r * a.cos(), r * a.sin()]
            })
            .collect();
        check_properties(&star, &bonnet40());
    }

    #[test]
    fn too_large_an_offset_for_the_part_is_refused() {
        // A 4 mm wide strip cannot hold a line 6 mm inside its edge.
        let strip = [[0.0, 0.0], [50.0, 0.0], [50.0, 4.0], [0.0, 4.0]];
        assert!(edge_offset(&strip, &bonnet40()).is_err());
    }

    /// The largest overhang of any line's spot beyond the polygon, measured point by point
    /// against the polygon itself (not the fitted edge), and the number of lines that overhang.
    fn spot_overhang(edge: &[[f64; 2]], t: &EdgeOffsetPath, tol: f64) -> (f64, usize) {
        let (x, y) = (t.path.x_mm(), t.path.y_mm());
        let mut worst: f64 = f64::NEG_INFINITY;
        let mut lines_over = 0;
        for (k, l) in t.lines.iter().enumerate() {
            let end = t.line_starts.get(k + 1).copied().unwrap_or(x.len());
            let line_worst = (t.line_starts[k]..end)
                .map(|j| {
                    let p = [x[j], y[j]];
                    let d = dist_to_polygon(edge, p);
                    l.spot_radius_mm - if inside(edge, p) { d } else { -d }
                })
                .fold(f64::NEG_INFINITY, f64::max);
            if line_worst > tol {
                lines_over += 1;
            }
            worst = worst.max(line_worst);
        }
        (worst, lines_over)
    }

    #[test]
    fn large_spots_stay_inside_circle_polygon_and_l_shape() {
        // A 15 mm spot on a 40 mm bonnet shrinking by 0.67935 to 1 mm with a 50 um residual:
        // the equal-residual spacing alone puts the innermost line ~10.4 mm from the edge,
        // 4.6 mm less than its spot radius.
        let s = EdgeOffsetSettings {
            bonnet_radius_mm: 40.0,
            spot_max_mm: 15.0,
            spot_min_mm: 1.0,
            progression: SpotProgression::Geometric { ratio: 0.67935 },
            residual_height_mm: 0.05,
            ..EdgeOffsetSettings::default()
        };
        let circle: Vec<[f64; 2]> = (0..720)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / 720.0;
                [24.5 * a.cos(), 24.5 * a.sin()]
            })
            .collect();
        let hexagon: Vec<[f64; 2]> = (0..6)
            .map(|i| {
                let a = std::f64::consts::TAU * i as f64 / 6.0;
                [40.0 * a.cos(), 40.0 * a.sin()]
            })
            .collect();
        let ell = [
            [0.0, 0.0],
            [80.0, 0.0],
            [80.0, 40.0],
            [40.0, 40.0],
            [40.0, 80.0],
            [0.0, 80.0],
        ];
        for edge in [&circle[..], &hexagon[..], &ell[..]] {
            let t = check_properties(edge, &s);
            let (worst, over) = spot_overhang(edge, &t, s.bezier_tolerance_mm + 1e-6);
            assert_eq!(over, 0, "{over} lines overhang, worst {worst} mm");
            assert!(worst <= s.bezier_tolerance_mm + 1e-6, "overhang {worst} mm");
            // The method's purpose: the spot shrinks monotonically towards the edge, from the
            // largest to the smallest.
            assert_eq!(t.lines[0].spot_radius_mm, 15.0);
            assert!(t.lines.last().unwrap().spot_radius_mm < 1.01);
            for w in t.lines.windows(2) {
                assert!(w[1].spot_radius_mm <= w[0].spot_radius_mm);
                assert!(w[1].offset_mm < w[0].offset_mm);
            }
            for l in &t.lines {
                assert!(l.clearance_mm >= -CONTAINMENT_TOLERANCE_MM, "{l:?}");
            }
        }
    }
}
