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

/// Distance from `p` to the segment `a b`, mm.
fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let l2 = dx * dx + dy * dy;
    let u = if l2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a[0] + u * dx - p[0]).hypot(a[1] + u * dy - p[1])
}

/// Distance from `p` to the open polyline `pts` and the index of the nearest vertex, mm.
fn polyline_distance(pts: &[[f64; 2]], p: [f64; 2]) -> (f64, usize) {
    if pts.len() == 1 {
        return ((pts[0][0] - p[0]).hypot(pts[0][1] - p[1]), 0);
    }
    let mut best = (f64::INFINITY, 0usize);
    for (i, w) in pts.windows(2).enumerate() {
        let d = segment_distance(p, w[0], w[1]);
        if d < best.0 {
            let d0 = (w[0][0] - p[0]).hypot(w[0][1] - p[1]);
            let d1 = (w[1][0] - p[0]).hypot(w[1][1] - p[1]);
            best = (d, if d0 <= d1 { i } else { i + 1 });
        }
    }
    best
}

/// The closed polyline of the fitted edge with its segments bucketed in a uniform grid, for
/// distance queries that only look at nearby segments.
struct EdgeIndex {
    pts: Vec<[f64; 2]>,
    origin: [f64; 2],
    cell: f64,
    nx: usize,
    ny: usize,
    cells: Vec<Vec<u32>>,
}

impl EdgeIndex {
    fn new(pts: Vec<[f64; 2]>, cell: f64) -> Self {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &pts {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        // At most about 4096 cells per side.
        let cell = cell
            .max((hi[0] - lo[0]).max(hi[1] - lo[1]) / 4096.0)
            .max(1e-9);
        let nx = ((hi[0] - lo[0]) / cell).floor() as usize + 1;
        let ny = ((hi[1] - lo[1]) / cell).floor() as usize + 1;
        let mut cells = vec![Vec::new(); nx * ny];
        let n = pts.len();
        for i in 0..n {
            let (a, b) = (pts[i], pts[(i + 1) % n]);
            let i0 = ((a[0].min(b[0]) - lo[0]) / cell).floor() as usize;
            let i1 = (((a[0].max(b[0]) - lo[0]) / cell).floor() as usize).min(nx - 1);
            let j0 = ((a[1].min(b[1]) - lo[1]) / cell).floor() as usize;
            let j1 = (((a[1].max(b[1]) - lo[1]) / cell).floor() as usize).min(ny - 1);
            for j in j0..=j1 {
                for ii in i0..=i1 {
                    cells[j * nx + ii].push(i as u32);
                }
            }
        }
        Self {
            pts,
            origin: lo,
            cell,
            nx,
            ny,
            cells,
        }
    }

    /// Distance from `p` to the edge if it is at most `reach`, else a value above `reach`.
    fn distance_within(&self, p: [f64; 2], reach: f64) -> f64 {
        let c = self.cell;
        let span = |v: f64, o: f64, n: usize| -> (usize, usize) {
            let lo = ((v - reach - o) / c).floor().max(0.0);
            let hi = ((v + reach - o) / c).floor().min(n as f64 - 1.0);
            (lo as usize, hi.max(-1.0) as usize)
        };
        let (i0, i1) = span(p[0], self.origin[0], self.nx);
        let (j0, j1) = span(p[1], self.origin[1], self.ny);
        let mut best = f64::INFINITY;
        if p[0] + reach < self.origin[0] || p[1] + reach < self.origin[1] || i0 > i1 || j0 > j1 {
            return best;
        }
        let n = self.pts.len();
        for j in j0..=j1 {
            for i in i0..=i1 {
                for &k in &self.cells[j * self.nx + i] {
                    let k = k as usize;
                    best = best.min(segment_distance(p, self.pts[k], self.pts[(k + 1) % n]));
                }
            }
        }
        best
    }
}

/// Samples per Bezier segment where the fit error is measured (and of the edge polyline the
/// offsets are measured against).
pub const FIT_SAMPLES_PER_SEGMENT: usize = 256;

/// `FIT_SAMPLES_PER_SEGMENT + 1` points of a segment, equally spaced in `t`.
fn sample_curve(c: &CubicBezier) -> Vec<[f64; 2]> {
    (0..=FIT_SAMPLES_PER_SEGMENT)
        .map(|i| c.eval(i as f64 / FIT_SAMPLES_PER_SEGMENT as f64))
        .collect()
}

/// Two-sided fit error of `curve` against the polyline `pts` it replaces: the larger of the
/// largest distance of the curve's dense samples from the polyline and the largest distance of
/// the polyline's vertices from the sampled curve. Returns it with the polyline vertex nearest
/// to where it occurs (the split point).
pub fn curve_polyline_error(curve: &CubicBezier, pts: &[[f64; 2]]) -> (f64, usize) {
    let q = sample_curve(curve);
    let mut worst = (0.0, 0usize);
    for &s in &q {
        let (d, i) = polyline_distance(pts, s);
        if d > worst.0 {
            worst = (d, i);
        }
    }
    for (i, &p) in pts.iter().enumerate() {
        let (d, _) = polyline_distance(&q, p);
        if d > worst.0 {
            worst = (d, i);
        }
    }
    worst
}

/// Piecewise cubic Bezier fit of the open polyline `points` within `tolerance_mm`, the error
/// measured along the whole curve ([`curve_polyline_error`]): a segment whose error exceeds the
/// tolerance is split at the polyline vertex nearest its worst point (recursively; a segment
/// between two adjacent vertices is their straight line, error 0, so the recursion ends).
/// Returns the segments and the largest error.
pub fn fit_bezier_spline(
    points: &[[f64; 2]],
    tolerance_mm: f64,
) -> Result<(Vec<CubicBezier>, f64)> {
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
    let mut max_err: f64 = 0.0;
    // Work stack of index ranges, processed left to right.
    let mut stack = vec![(0usize, points.len() - 1)];
    while let Some((a, b)) = stack.pop() {
        let seg = &points[a..=b];
        let (c, _, _) = fit_segment(seg)?;
        let (err, worst) = curve_polyline_error(&c, seg);
        if err <= tolerance_mm || seg.len() <= 2 {
            max_err = max_err.max(err);
            out.push(c);
        } else {
            let split = a + worst.clamp(1, seg.len() - 2);
            stack.push((split, b));
            stack.push((a, split));
        }
    }
    Ok((out, max_err))
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
    /// The fitted edge (counter-clockwise).
    pub edge: Vec<CubicBezier>,
    /// Largest fit error of the edge against the edge polygon ([`curve_polyline_error`]), mm.
    pub fit_error_mm: f64,
    /// Vertices of the edge polygon kept as corners (turn above [`CORNER_TURN_DEG`]).
    pub corners: usize,
}

/// A polygon vertex whose direction turns by more than this is a corner: the Bezier fit
/// starts a new segment there (a cubic cannot follow a sharp corner within a small tolerance).
pub const CORNER_TURN_DEG: f64 = 15.0;

/// Turn angle at every vertex of the closed polygon `p`, radians (positive left).
fn turns(p: &[[f64; 2]]) -> Vec<f64> {
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
fn clean_polygon(edge: &[[f64; 2]]) -> Result<(Vec<[f64; 2]>, bool)> {
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
fn fit_closed_edge(
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
fn left_normal(c: &CubicBezier, t: f64) -> Option<[f64; 2]> {
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
fn curve_length(c: &CubicBezier) -> f64 {
    sample_curve(c)
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .sum()
}

/// Even-odd point-in-polygon test for the closed polyline `poly`.
#[cfg(test)]
fn inside(poly: &[[f64; 2]], p: [f64; 2]) -> bool {
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
fn crossing(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2], s: f64) -> Option<[f64; 2]> {
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
fn trimmed_offset(
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
fn resample_closed(c: &[[f64; 2]], corner: &[bool], step: f64) -> Vec<[f64; 2]> {
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
    for line in lines.iter_mut() {
        let mut used = line.offset_mm;
        let mut pts = Vec::new();
        let mut achieved = 0.0;
        for _ in 0..3 {
            let (c, corner) = trimmed_offset(&spline, &index, used, raw_step)?;
            pts = resample_closed(&c, &corner, settings.step_mm);
            if pts.len() < 3 {
                return Err(Error::Geometry(format!(
                    "the offset curve at {} mm has fewer than three points",
                    line.offset_mm
                )));
            }
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
                // Nothing outside the edge by more than the overhang: the spot of the
                // edge-most line reaches at most the overhang beyond it.
                assert!(d >= s.spot_min_mm - s.overhang_mm - tol - chord);
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
}
