//! Offset geometry of the fitted edge: polygon cleaning and corner detection, the Bezier fit of
//! a closed edge, trimmed inward offset curves and their equal-arc-length resampling.

use super::bezier::{fit_bezier_spline, sample_curve, CubicBezier, EdgeIndex};
use crate::error::{Error, Result};

/// starts a new segment there (a cubic cannot follow a sharp corner within a small tolerance).
pub const CORNER_TURN_DEG: f64 = 15.0;

/// Turn angle at every vertex of the closed polygon `p`, radians (positive left).
pub(super) fn turns(p: &[[f64; 2]]) -> Vec<f64> {
    let n = p.len();
    (0..n)
        .map(|i| {
            let a = p[(i + n - 1) % n];
            let b = p[i];
            let c = p[(i + 1) % n];
            let u = [b[0] - a[0], b[1] - a[1]];
            let v = [c[0] - b[0], c[1] - b[1]];
            (u[0] * v[1] - u[1] * v[0]).atan2(u[0] * v[0] + u[1] * v[1])
        })
        .collect()
}

/// Closed counter-clockwise polygon from `edge`: repeated (consecutive, and last = first)
/// vertices removed; returns it and whether the input was clockwise.
pub(super) fn clean_polygon(edge: &[[f64; 2]]) -> Result<(Vec<[f64; 2]>, bool)> {
    if edge.iter().any(|p| !(p[0].is_finite() && p[1].is_finite())) {
        return Err(Error::invalid("edge", "non-finite coordinate"));
    }
    let scale = edge
        .iter()
        .map(|p| p[0].abs().max(p[1].abs()))
        .fold(0.0, f64::max)
        .max(1.0);
    let mut p: Vec<[f64; 2]> = Vec::with_capacity(edge.len());
    for &q in edge {
        if p.last()
            .is_none_or(|l: &[f64; 2]| (l[0] - q[0]).hypot(l[1] - q[1]) > 1e-12 * scale)
        {
            p.push(q);
        }
    }
    while p.len() > 1 && {
        let (a, b) = (p[0], p[p.len() - 1]);
        (a[0] - b[0]).hypot(a[1] - b[1]) <= 1e-12 * scale
    } {
        p.pop();
    }
    if p.len() < 3 {
        return Err(Error::invalid(
            "edge",
            "needs at least three distinct points",
        ));
    }
    let n = p.len();
    let area2: f64 = (0..n)
        .map(|i| {
            let (a, b) = (p[i], p[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    if !area2.is_finite() || area2.abs() <= 1e-12 * scale * scale {
        return Err(Error::invalid("edge", "encloses no area"));
    }
    let cw = area2 < 0.0;
    if cw {
        p.reverse();
    }
    Ok((p, cw))
}

/// Fits the closed counter-clockwise polygon `p`: corners (turn above [`CORNER_TURN_DEG`]) end
/// segments, each stretch between corners is densified to points at most `spacing` apart
/// (vertices kept) and fitted by [`fit_bezier_spline`]. Returns segments, error, corners.
pub(super) fn fit_closed_edge(
    p: &[[f64; 2]],
    tolerance_mm: f64,
    spacing: f64,
) -> Result<(Vec<CubicBezier>, f64, usize)> {
    let n = p.len();
    let t = turns(p);
    let corner: Vec<usize> = (0..n)
        .filter(|&i| t[i].abs() > CORNER_TURN_DEG.to_radians())
        .collect();
    let starts = if corner.is_empty() {
        vec![0]
    } else {
        corner.clone()
    };
    let mut spline = Vec::new();
    let mut err: f64 = 0.0;
    for (k, &s) in starts.iter().enumerate() {
        let e = if starts.len() == 1 {
            s + n
        } else {
            let nxt = starts[(k + 1) % starts.len()];
            if nxt > s {
                nxt
            } else {
                nxt + n
            }
        };
        let mut pts = vec![p[s % n]];
        for i in s..e {
            let (a, b) = (p[i % n], p[(i + 1) % n]);
            let m = ((a[0] - b[0]).hypot(a[1] - b[1]) / spacing).ceil().max(1.0) as usize;
            for j in 1..=m {
                let f = j as f64 / m as f64;
                pts.push([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])]);
            }
        }
        let (segs, e_fit) = fit_bezier_spline(&pts, tolerance_mm)?;
        err = err.max(e_fit);
        spline.extend(segs);
    }
    Ok((spline, err, corner.len()))
}

/// Unit inward (left, for a counter-clockwise edge) normal of `c` at `t`.
pub(super) fn left_normal(c: &CubicBezier, t: f64) -> Option<[f64; 2]> {
    let mut d = c.d1(t);
    let mut len = d[0].hypot(d[1]);
    if len <= 1e-12 * (1.0 + c.p[0][0].abs() + c.p[0][1].abs()) {
        // A cusp-free cubic with a zero end derivative: the direction there is the chord of a
        // nearby parameter step.
        let (a, b) = if t < 0.5 {
            (c.eval(t), c.eval(t + 1e-6))
        } else {
            (c.eval(t - 1e-6), c.eval(t))
        };
        d = [b[0] - a[0], b[1] - a[1]];
        len = d[0].hypot(d[1]);
        if len == 0.0 {
            return None;
        }
    }
    Some([-d[1] / len, d[0] / len])
}

/// Approximate arc length of a segment from its dense samples, mm.
pub(super) fn curve_length(c: &CubicBezier) -> f64 {
    sample_curve(c)
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .sum()
}

/// Even-odd point-in-polygon test for the closed polyline `poly`.
#[cfg(test)]
pub(super) fn inside(poly: &[[f64; 2]], p: [f64; 2]) -> bool {
    let n = poly.len();
    let mut c = false;
    for i in 0..n {
        let (a, b) = (poly[i], poly[(i + 1) % n]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if p[0] < x {
                c = !c;
            }
        }
    }
    c
}

/// Intersection of segments `a b` and `c d` if they cross (parameters within [−s, 1+s]).
pub(super) fn crossing(
    a: [f64; 2],
    b: [f64; 2],
    c: [f64; 2],
    d: [f64; 2],
    s: f64,
) -> Option<[f64; 2]> {
    let r = [b[0] - a[0], b[1] - a[1]];
    let q = [d[0] - c[0], d[1] - c[1]];
    let den = r[0] * q[1] - r[1] * q[0];
    if den == 0.0 {
        return None;
    }
    let w = [c[0] - a[0], c[1] - a[1]];
    let u = (w[0] * q[1] - w[1] * q[0]) / den;
    let v = (w[0] * r[1] - w[1] * r[0]) / den;
    ((-s..=1.0 + s).contains(&u) && (-s..=1.0 + s).contains(&v))
        .then(|| [a[0] + u * r[0], a[1] + u * r[1]])
}

/// The inward offset of the fitted edge at distance `o`: every segment moved along its normal,
/// joins between segments bridged by arcs of radius `o` about the join, then every point
/// closer than `o` to the edge (the loops an offset forms at convex corners and where the
/// edge's radius of curvature is below `o`) trimmed away, the crossing of the two sides of a
/// trimmed loop kept as a corner. Returns the closed offset polyline and its corner flags.
pub(super) fn trimmed_offset(
    spline: &[CubicBezier],
    edge: &EdgeIndex,
    o: f64,
    raw_step: f64,
) -> Result<(Vec<[f64; 2]>, Vec<bool>)> {
    let mut raw: Vec<[f64; 2]> = Vec::new();
    let ns = spline.len();
    for (k, c) in spline.iter().enumerate() {
        let m = ((curve_length(c) / raw_step).ceil() as usize).max(4);
        for i in 0..m {
            let t = i as f64 / m as f64;
            let q = c.eval(t);
            let nrm = left_normal(c, t)
                .ok_or_else(|| Error::Geometry("degenerate Bezier segment of the edge".into()))?;
            raw.push([q[0] + o * nrm[0], q[1] + o * nrm[1]]);
        }
        let next = &spline[(k + 1) % ns];
        let (Some(n0), Some(n1)) = (left_normal(c, 1.0), left_normal(next, 0.0)) else {
            return Err(Error::Geometry(
                "degenerate Bezier segment of the edge".into(),
            ));
        };
        let phi = (n0[0] * n1[1] - n0[1] * n1[0]).atan2(n0[0] * n1[0] + n0[1] * n1[1]);
        let q = c.eval(1.0);
        let dphi = (raw_step / o).min(5f64.to_radians());
        let m = (phi.abs() / dphi).ceil() as usize;
        for j in 0..m {
            let a = phi * j as f64 / m as f64;
            let (s, co) = a.sin_cos();
            let nn = [co * n0[0] - s * n0[1], s * n0[0] + co * n0[1]];
            raw.push([q[0] + o * nn[0], q[1] + o * nn[1]]);
        }
    }
    let scale = o.max(1.0);
    let keep: Vec<bool> = raw
        .iter()
        .map(|&p| edge.distance_within(p, o) >= o - 1e-4 * scale)
        .collect();
    let n = raw.len();
    let Some(first) = (0..n).find(|&i| keep[i] && !keep[(i + n - 1) % n]) else {
        if keep.iter().all(|&k| k) {
            return Ok((raw, vec![false; n]));
        }
        return Err(Error::Geometry(format!(
            "an offset of {o} mm leaves no curve inside the edge"
        )));
    };
    let mut out: Vec<[f64; 2]> = Vec::new();
    let mut corner: Vec<bool> = Vec::new();
    let mut i = first;
    let mut count = 0;
    while count < n {
        if keep[i] {
            out.push(raw[i]);
            corner.push(false);
            i = (i + 1) % n;
            count += 1;
            continue;
        }
        // A dropped run from i: join the kept point before it to the kept point after it
        // through the crossing of the raw segments that enter and leave the run.
        let a = (i + n - 1) % n;
        let mut j = i;
        while !keep[j] {
            j = (j + 1) % n;
            count += 1;
        }
        let b = j;
        let before = (b + n - 1) % n;
        if let Some(x) = crossing(raw[a], raw[i], raw[before], raw[b], 0.5) {
            out.push(x);
            corner.push(true);
        }
        i = b;
    }
    Ok((out, corner))
}

/// Resamples the closed polyline `c` at equal arc length no more than `step` apart between
/// its corners (corners kept), dropping repeated points.
pub(super) fn resample_closed(c: &[[f64; 2]], corner: &[bool], step: f64) -> Vec<[f64; 2]> {
    let n = c.len();
    let marks: Vec<usize> = (0..n).filter(|&i| corner[i]).collect();
    let starts = if marks.is_empty() { vec![0] } else { marks };
    let mut out: Vec<[f64; 2]> = Vec::new();
    for (k, &s) in starts.iter().enumerate() {
        let e = if starts.len() == 1 {
            s + n
        } else {
            let nx = starts[(k + 1) % starts.len()];
            if nx > s {
                nx
            } else {
                nx + n
            }
        };
        let piece: Vec<[f64; 2]> = (s..=e).map(|i| c[i % n]).collect();
        let mut cum = vec![0.0];
        for w in piece.windows(2) {
            let l = cum[cum.len() - 1] + (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]);
            cum.push(l);
        }
        let len = cum[cum.len() - 1];
        let m = ((len / step).ceil() as usize).max(1);
        let mut seg = 0usize;
        for j in 0..m {
            let target = len * j as f64 / m as f64;
            while seg + 2 < cum.len() && cum[seg + 1] < target {
                seg += 1;
            }
            let l = cum[seg + 1] - cum[seg];
            let f = if l > 0.0 {
                ((target - cum[seg]) / l).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (a, b) = (piece[seg], piece[seg + 1]);
            out.push([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])]);
        }
    }
    let tiny = 1e-9 * step.max(1.0);
    let mut dedup: Vec<[f64; 2]> = Vec::with_capacity(out.len());
    for p in out {
        if dedup
            .last()
            .is_none_or(|l: &[f64; 2]| (l[0] - p[0]).hypot(l[1] - p[1]) > tiny)
        {
            dedup.push(p);
        }
    }
    while dedup.len() > 1 && {
        let (a, b) = (dedup[0], dedup[dedup.len() - 1]);
        (a[0] - b[0]).hypot(a[1] - b[1]) <= tiny
    } {
        dedup.pop();
    }
    dedup
}
