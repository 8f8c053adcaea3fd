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
//! `o_k = o_{k+1} + d_k` inwards. Each offset curve is the Bezier edge moved by `o` along its
//! inward normal; its achieved offset (mean distance of its points to the edge) is measured and
//! the offset is corrected by the ratio of the set to the achieved distance (three passes).
//!
//! # Bezier fit
//!
//! Cubic segments with fixed end points; the inner control points by linear least squares on
//! chord-length parameters, refined by Newton reparametrisation (Schneider, *An Algorithm for
//! Automatically Fitting Digitized Curves*, Graphics Gems 1990); a segment whose largest point
//! error exceeds the tolerance is split at that point and both halves are fitted again.

use super::DwellPath;
use crate::error::{Error, Result};
use crate::tif::bonnet::depth_for_spot_mm;
use serde::{Deserialize, Serialize};

/// How the spot radius shrinks towards the edge.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum SpotProgression {
    /// `r_k = q^k r_max`, `0 < q < 1`.
    Geometric {
        /// Ratio q.
        ratio: f64,
    },
    /// `r_k = r_max - k d`.
    Arithmetic {
        /// Decrement d, mm.
        decrement_mm: f64,
    },
}

/// Settings of the edge-offset trajectory (lengths mm).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeOffsetSettings {
    /// Bonnet radius R, mm.
    pub bonnet_radius_mm: f64,
    /// Spot radius of the innermost line, mm.
    pub spot_max_mm: f64,
    /// Smallest spot radius, mm.
    pub spot_min_mm: f64,
    /// Progression of spot radii.
    pub progression: SpotProgression,
    /// Residual (scallop) height between lines, mm.
    pub residual_height_mm: f64,
    /// How far the edge-most spot may overhang the edge, mm (0: tangent to it).
    pub overhang_mm: f64,
    /// Bezier fit tolerance, mm.
    pub bezier_tolerance_mm: f64,
    /// Point spacing along the offset curves, mm.
    pub step_mm: f64,
}

impl Default for EdgeOffsetSettings {
    fn default() -> Self {
        Self {
            bonnet_radius_mm: 20.0,
            spot_max_mm: 6.0,
            spot_min_mm: 1.5,
            progression: SpotProgression::Geometric { ratio: 0.8 },
            residual_height_mm: 1e-3,
            overhang_mm: 0.0,
            bezier_tolerance_mm: 0.01,
            step_mm: 0.5,
        }
    }
}

impl EdgeOffsetSettings {
    /// Checks ranges: positive lengths, `spot_min <= spot_max < R`, residual below `spot_min`,
    /// ratio in (0, 1) or a positive decrement, overhang in `[0, spot_min)`.
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("edge-offset bonnet_radius_mm", self.bonnet_radius_mm),
            ("edge-offset spot_max_mm", self.spot_max_mm),
            ("edge-offset spot_min_mm", self.spot_min_mm),
            ("edge-offset residual_height_mm", self.residual_height_mm),
            ("edge-offset bezier_tolerance_mm", self.bezier_tolerance_mm),
            ("edge-offset step_mm", self.step_mm),
        ])?;
        if !(self.spot_min_mm <= self.spot_max_mm && self.spot_max_mm < self.bonnet_radius_mm) {
            return Err(Error::invalid(
                "edge-offset spot radii",
                format!(
                    "need spot_min <= spot_max < bonnet radius, got {} <= {} < {}",
                    self.spot_min_mm, self.spot_max_mm, self.bonnet_radius_mm
                ),
            ));
        }
        if self.residual_height_mm >= self.spot_min_mm {
            return Err(Error::invalid(
                "edge-offset residual_height_mm",
                "must be below the smallest spot radius",
            ));
        }
        if !(self.overhang_mm.is_finite()
            && self.overhang_mm >= 0.0
            && self.overhang_mm < self.spot_min_mm)
        {
            return Err(Error::invalid(
                "edge-offset overhang_mm",
                format!("must be in [0, spot_min), got {}", self.overhang_mm),
            ));
        }
        match self.progression {
            SpotProgression::Geometric { ratio } if !(ratio > 0.0 && ratio < 1.0) => {
                Err(Error::invalid(
                    "edge-offset ratio",
                    format!("must be in (0, 1), got {ratio}"),
                ))
            }
            SpotProgression::Arithmetic { decrement_mm }
                if !(decrement_mm.is_finite() && decrement_mm > 0.0) =>
            {
                Err(Error::invalid(
                    "edge-offset decrement_mm",
                    format!("must be positive, got {decrement_mm}"),
                ))
            }
            _ => Ok(()),
        }
    }

    /// Spot radii from `spot_max` down to no less than `spot_min`, mm.
    pub fn spot_radii_mm(&self) -> Result<Vec<f64>> {
        self.validate()?;
        let mut out = Vec::new();
        let mut k = 0usize;
        loop {
            let r = match self.progression {
                SpotProgression::Geometric { ratio } => self.spot_max_mm * ratio.powi(k as i32),
                SpotProgression::Arithmetic { decrement_mm } => {
                    self.spot_max_mm - k as f64 * decrement_mm
                }
            };
            if r < self.spot_min_mm * (1.0 - 1e-12) {
                break;
            }
            out.push(r);
            k += 1;
            if k > 10_000 {
                return Err(Error::invalid(
                    "edge-offset progression",
                    "more than 10000 offset lines",
                ));
            }
        }
        Ok(out)
    }
}

/// Half-width at which a circular profile of radius `r` reaches residual height `e`:
/// `sqrt(2 r e - e^2)`, mm.
pub fn residual_half_width_mm(spot_radius_mm: f64, residual_mm: f64) -> f64 {
    (2.0 * spot_radius_mm * residual_mm - residual_mm * residual_mm)
        .max(0.0)
        .sqrt()
}

/// One offset line of the trajectory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OffsetLine {
    /// Spot radius, mm.
    pub spot_radius_mm: f64,
    /// Pressing depth giving that spot, mm.
    pub depth_mm: f64,
    /// Set distance of the tool centre inside the edge, mm.
    pub offset_mm: f64,
    /// Distance achieved by the corrected offset curve (mean over its points), mm.
    pub achieved_offset_mm: f64,
    /// Spacing to the next line towards the edge, mm (0 for the edge-most line).
    pub spacing_mm: f64,
}

/// Spot radii, depths, spacings and set offsets of the lines, innermost first.
pub fn plan_offsets(settings: &EdgeOffsetSettings) -> Result<Vec<OffsetLine>> {
    let radii = settings.spot_radii_mm()?;
    let e = settings.residual_height_mm;
    let n = radii.len();
    let mut lines: Vec<OffsetLine> = radii
        .iter()
        .map(|&r| {
            Ok(OffsetLine {
                spot_radius_mm: r,
                depth_mm: depth_for_spot_mm(settings.bonnet_radius_mm, r).ok_or_else(|| {
                    Error::invalid("edge-offset spot radius", "larger than the bonnet")
                })?,
                offset_mm: 0.0,
                achieved_offset_mm: 0.0,
                spacing_mm: 0.0,
            })
        })
        .collect::<Result<_>>()?;
    let mut o = radii[n - 1] - settings.overhang_mm;
    lines[n - 1].offset_mm = o;
    for k in (0..n - 1).rev() {
        let d = residual_half_width_mm(radii[k], e) + residual_half_width_mm(radii[k + 1], e);
        lines[k].spacing_mm = d;
        o += d;
        lines[k].offset_mm = o;
    }
    Ok(lines)
}

/// A cubic Bezier segment with control points `p[0..4]`, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CubicBezier {
    /// Control points.
    pub p: [[f64; 2]; 4],
}

fn bernstein(t: f64) -> [f64; 4] {
    let s = 1.0 - t;
    [s * s * s, 3.0 * s * s * t, 3.0 * s * t * t, t * t * t]
}

impl CubicBezier {
    /// Point at parameter `t` in [0, 1].
    pub fn eval(&self, t: f64) -> [f64; 2] {
        let b = bernstein(t);
        let mut q = [0.0; 2];
        for (bk, pk) in b.iter().zip(&self.p) {
            q[0] += bk * pk[0];
            q[1] += bk * pk[1];
        }
        q
    }

    /// First derivative at `t`.
    pub fn d1(&self, t: f64) -> [f64; 2] {
        let s = 1.0 - t;
        let p = &self.p;
        let c = [3.0 * s * s, 6.0 * s * t, 3.0 * t * t];
        let mut q = [0.0; 2];
        for i in 0..2 {
            q[i] = c[0] * (p[1][i] - p[0][i])
                + c[1] * (p[2][i] - p[1][i])
                + c[2] * (p[3][i] - p[2][i]);
        }
        q
    }

    /// Second derivative at `t`.
    pub fn d2(&self, t: f64) -> [f64; 2] {
        let p = &self.p;
        let mut q = [0.0; 2];
        for i in 0..2 {
            q[i] = 6.0 * (1.0 - t) * (p[2][i] - 2.0 * p[1][i] + p[0][i])
                + 6.0 * t * (p[3][i] - 2.0 * p[2][i] + p[1][i]);
        }
        q
    }
}

/// Least-squares cubic through `points` at parameters `t` with the end control points fixed to
/// the first and last point: the normal equations of the two inner control points.
pub fn fit_cubic(points: &[[f64; 2]], t: &[f64]) -> Result<CubicBezier> {
    let (Some(&p0), Some(&p3)) = (points.first(), points.last()) else {
        return Err(Error::invalid("Bezier fit", "no points"));
    };
    if t.len() != points.len() {
        return Err(Error::LengthMismatch {
            what: "Bezier parameters",
            got: t.len(),
            expected: points.len(),
        });
    }
    let (mut a11, mut a12, mut a22) = (0.0, 0.0, 0.0);
    let (mut r1, mut r2) = ([0.0; 2], [0.0; 2]);
    for (p, &ti) in points.iter().zip(t) {
        let b = bernstein(ti);
        a11 += b[1] * b[1];
        a12 += b[1] * b[2];
        a22 += b[2] * b[2];
        for i in 0..2 {
            let rest = p[i] - b[0] * p0[i] - b[3] * p3[i];
            r1[i] += b[1] * rest;
            r2[i] += b[2] * rest;
        }
    }
    let det = a11 * a22 - a12 * a12;
    let third = |f: f64| [p0[0] + f * (p3[0] - p0[0]), p0[1] + f * (p3[1] - p0[1])];
    let floor = 1e-12 * (a11 * a22).max(f64::MIN_POSITIVE);
    if det.is_nan() || det.abs() <= floor {
        // Too few interior points for two control points: least squares with P1 = P2 = Q
        // (exact through a single interior point), or the straight cubic without any.
        let w: f64 = a11 + 2.0 * a12 + a22;
        if w > 0.0 {
            let q = [(r1[0] + r2[0]) / w, (r1[1] + r2[1]) / w];
            return Ok(CubicBezier { p: [p0, q, q, p3] });
        }
        return Ok(CubicBezier {
            p: [p0, third(1.0 / 3.0), third(2.0 / 3.0), p3],
        });
    }
    let mut p1 = [0.0; 2];
    let mut p2 = [0.0; 2];
    for i in 0..2 {
        p1[i] = (a22 * r1[i] - a12 * r2[i]) / det;
        p2[i] = (a11 * r2[i] - a12 * r1[i]) / det;
    }
    Ok(CubicBezier {
        p: [p0, p1, p2, p3],
    })
}

/// Largest distance between `points[i]` and `curve(t[i])`, and its index.
fn max_error(curve: &CubicBezier, points: &[[f64; 2]], t: &[f64]) -> (f64, usize) {
    let mut worst = (0.0, 0usize);
    for (i, (p, &ti)) in points.iter().zip(t).enumerate() {
        let q = curve.eval(ti);
        let d = (q[0] - p[0]).hypot(q[1] - p[1]);
        if d > worst.0 {
            worst = (d, i);
        }
    }
    worst
}

/// Fits one cubic to `points`: chord-length parameters, then up to 200 rounds of least squares
/// and two Newton reparametrisation passes, while the largest error keeps falling. Returns the curve, its parameters and its largest error.
fn fit_segment(points: &[[f64; 2]]) -> Result<(CubicBezier, Vec<f64>, (f64, usize))> {
    let n = points.len();
    let mut t = vec![0.0; n];
    for i in 1..n {
        t[i] = t[i - 1] + (points[i][0] - points[i - 1][0]).hypot(points[i][1] - points[i - 1][1]);
    }
    let total = t[n - 1];
    if total > 0.0 {
        t.iter_mut().for_each(|v| *v /= total);
    }
    let mut best = fit_cubic(points, &t)?;
    let mut best_err = max_error(&best, points, &t);
    let mut best_t = t.clone();
    for _ in 0..200 {
        let c = fit_cubic(points, &t)?;
        for _ in 0..2 {
            for (ti, p) in t.iter_mut().zip(points) {
                let q = c.eval(*ti);
                let d1 = c.d1(*ti);
                let d2 = c.d2(*ti);
                let diff = [q[0] - p[0], q[1] - p[1]];
                let num = diff[0] * d1[0] + diff[1] * d1[1];
                let den = d1[0] * d1[0] + d1[1] * d1[1] + diff[0] * d2[0] + diff[1] * d2[1];
                if den > 0.0 {
                    *ti = (*ti - num / den).clamp(0.0, 1.0);
                }
            }
        }
        let c = fit_cubic(points, &t)?;
        let e = max_error(&c, points, &t);
        if e.0 < best_err.0 {
            let gain = best_err.0 - e.0;
            best = c;
            best_err = e;
            best_t.clone_from(&t);
            if gain < 1e-9 * best_err.0 {
                break;
            }
        } else {
            break;
        }
    }
    Ok((best, best_t, best_err))
}

/// Piecewise cubic Bezier fit of the polyline `points` within `tolerance_mm`: a segment whose
/// largest error exceeds the tolerance is split at its worst point (recursively).
pub fn fit_bezier_spline(points: &[[f64; 2]], tolerance_mm: f64) -> Result<Vec<CubicBezier>> {
    if points.len() < 2 {
        return Err(Error::invalid("Bezier fit", "needs at least two points"));
    }
    if !(tolerance_mm.is_finite() && tolerance_mm > 0.0) {
        return Err(Error::invalid(
            "Bezier tolerance_mm",
            format!("must be positive, got {tolerance_mm}"),
        ));
    }
    let mut out = Vec::new();
    // Work stack of index ranges, processed left to right.
    let mut stack = vec![(0usize, points.len() - 1)];
    while let Some((a, b)) = stack.pop() {
        let seg = &points[a..=b];
        let (c, _, (err, worst)) = fit_segment(seg)?;
        if err <= tolerance_mm || seg.len() <= 4 {
            out.push(c);
        } else {
            let split = a + worst.clamp(1, seg.len() - 2);
            stack.push((split, b));
            stack.push((a, split));
        }
    }
    Ok(out)
}

/// Largest distance from `points` to a spline, each point measured at its nearest of 200
/// samples per segment refined by Newton steps.
pub fn spline_distance_mm(spline: &[CubicBezier], p: [f64; 2]) -> f64 {
    let mut best = (f64::INFINITY, 0usize, 0.0);
    for (k, c) in spline.iter().enumerate() {
        for i in 0..=200 {
            let t = i as f64 / 200.0;
            let q = c.eval(t);
            let d = (q[0] - p[0]).hypot(q[1] - p[1]);
            if d < best.0 {
                best = (d, k, t);
            }
        }
    }
    let c = &spline[best.1];
    let mut t = best.2;
    for _ in 0..8 {
        let q = c.eval(t);
        let d1 = c.d1(t);
        let d2 = c.d2(t);
        let diff = [q[0] - p[0], q[1] - p[1]];
        let num = diff[0] * d1[0] + diff[1] * d1[1];
        let den = d1[0] * d1[0] + d1[1] * d1[1] + diff[0] * d2[0] + diff[1] * d2[1];
        if den > 0.0 {
            t = (t - num / den).clamp(0.0, 1.0);
        }
    }
    let q = c.eval(t);
    best.0.min((q[0] - p[0]).hypot(q[1] - p[1]))
}

/// The edge-offset trajectory: lines innermost first, each the fitted edge offset inwards.
#[derive(Debug, Clone, PartialEq)]
pub struct EdgeOffsetPath {
    /// All offset curves' points in visiting order.
    pub path: DwellPath,
    /// The lines (spot, depth, offsets).
    pub lines: Vec<OffsetLine>,
    /// Index of the first point of each line in `path`.
    pub line_starts: Vec<usize>,
    /// The fitted edge.
    pub edge: Vec<CubicBezier>,
    /// Largest fit error of the edge, mm.
    pub fit_error_mm: f64,
}

/// Builds the trajectory for the closed edge polygon `edge` (first point not repeated; either
/// orientation): Bezier fit, offset plan, offset curves with the set/achieved correction.
pub fn edge_offset(edge: &[[f64; 2]], settings: &EdgeOffsetSettings) -> Result<EdgeOffsetPath> {
    settings.validate()?;
    if edge.len() < 3 {
        return Err(Error::invalid("edge", "needs at least three points"));
    }
    let mut closed: Vec<[f64; 2]> = edge.to_vec();
    closed.push(edge[0]);
    let area2: f64 = closed
        .windows(2)
        .map(|w| w[0][0] * w[1][1] - w[1][0] * w[0][1])
        .sum();
    if area2 == 0.0 || !area2.is_finite() {
        return Err(Error::invalid("edge", "encloses no area"));
    }
    // Inward normal: left of the direction for a counter-clockwise edge.
    let inward = area2.signum();
    let spline = fit_bezier_spline(&closed, settings.bezier_tolerance_mm)?;
    let fit_error_mm = closed
        .iter()
        .map(|&p| spline_distance_mm(&spline, p))
        .fold(0.0, f64::max);
    let mut lines = plan_offsets(settings)?;
    // Dense samples of the edge with inward unit normals.
    let mut base: Vec<([f64; 2], [f64; 2], f64)> = Vec::new();
    let mut length = 0.0;
    for c in &spline {
        for i in 0..64 {
            let t = i as f64 / 64.0;
            let q = c.eval(t);
            let d = c.d1(t);
            let len = d[0].hypot(d[1]);
            if len == 0.0 {
                continue;
            }
            if let Some(last) = base.last() {
                length += (q[0] - last.0[0]).hypot(q[1] - last.0[1]);
            }
            base.push((q, [-inward * d[1] / len, inward * d[0] / len], length));
        }
    }
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    let mut line_starts = Vec::new();
    let n_pts = ((length / settings.step_mm).ceil() as usize).max(8);
    for line in lines.iter_mut() {
        let mut used = line.offset_mm;
        let mut pts = Vec::new();
        let mut achieved = 0.0;
        for _ in 0..3 {
            pts = offset_points(&base, length, n_pts, used);
            achieved = pts
                .iter()
                .map(|&p| spline_distance_mm(&spline, p))
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
        line.achieved_offset_mm = achieved;
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
    })
}

/// `n` points equally spaced in edge length, each moved by `offset` along the inward normal.
fn offset_points(
    base: &[([f64; 2], [f64; 2], f64)],
    length: f64,
    n: usize,
    offset: f64,
) -> Vec<[f64; 2]> {
    let mut out = Vec::with_capacity(n);
    let mut k = 0usize;
    for i in 0..n {
        let s = length * i as f64 / n as f64;
        while k + 1 < base.len() && base[k + 1].2 <= s {
            k += 1;
        }
        let (q, nrm, _) = base[k];
        out.push([q[0] + offset * nrm[0], q[1] + offset * nrm[1]]);
    }
    out
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
        let t: Vec<f64> = (0..40).map(|i| i as f64 / 39.0).collect();
        let pts: Vec<[f64; 2]> = t.iter().map(|&ti| c.eval(ti)).collect();
        // With the true parameters the least squares reproduces the control points.
        let f = fit_cubic(&pts, &t).unwrap();
        for k in 0..4 {
            for i in 0..2 {
                assert!((f.p[k][i] - c.p[k][i]).abs() < 1e-10);
            }
        }
        // From chord-length parameters, reparametrisation converges onto the cubic: one segment
        // within 1e-4 mm (the alternation converges linearly, so not to round-off).
        let spline = fit_bezier_spline(&pts, 1e-4).unwrap();
        assert_eq!(spline.len(), 1);
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
        let pts: Vec<[f64; 2]> = (0..n)
            .map(|i| {
                let a = 2.0 * std::f64::consts::PI * i as f64 / n as f64;
                let r = 50.0 + 0.02 * ((i * 7919 % 13) as f64 / 6.0 - 1.0);
                [r * a.cos(), r * a.sin()]
            })
            .collect();
        for tol in [0.05, 0.03] {
            let spline = fit_bezier_spline(&pts, tol).unwrap();
            assert!(spline.len() >= 2);
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
            assert!((e - s.residual_height_mm).abs() < 1e-9 * s.residual_height_mm.max(1.0));
            assert!((w[0].offset_mm - w[1].offset_mm - d).abs() < 1e-12);
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
}
