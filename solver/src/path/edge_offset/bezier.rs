//! Cubic Bezier segments and their least-squares fit to a polyline, with the distance queries
//! the offset curves are measured by.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

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
pub(super) fn max_error(curve: &CubicBezier, points: &[[f64; 2]], t: &[f64]) -> (f64, usize) {
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
pub(super) fn fit_segment(points: &[[f64; 2]]) -> Result<(CubicBezier, Vec<f64>, (f64, usize))> {
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
pub(super) fn segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
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
pub(super) fn polyline_distance(pts: &[[f64; 2]], p: [f64; 2]) -> (f64, usize) {
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
pub(super) struct EdgeIndex {
    pts: Vec<[f64; 2]>,
    origin: [f64; 2],
    cell: f64,
    nx: usize,
    ny: usize,
    cells: Vec<Vec<u32>>,
}

impl EdgeIndex {
    pub(super) fn new(pts: Vec<[f64; 2]>, cell: f64) -> Self {
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
    pub(super) fn distance_within(&self, p: [f64; 2], reach: f64) -> f64 {
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
pub(super) fn sample_curve(c: &CubicBezier) -> Vec<[f64; 2]> {
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
