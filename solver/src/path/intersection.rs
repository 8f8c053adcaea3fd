//! Straight raster lines and intersection paths for iterative polishing.
//!
//! Intersection paths alternate the raster direction between iterations and shift every other
//! pair of iterations by half the pitch, so the ridges left between the lines of one pass fall
//! on the lines of a later one: iteration `K` (0-based) runs along x for even `K`, along y for
//! odd `K`, and its lines are shifted by `P/2` when `(K / 2)` is odd (K = 0: x, 1: y, 2: x + P/2,
//! 3: y + P/2, then repeating).

use super::raster::RasterAxis;
use super::DwellPath;
use crate::error::{Error, Result};
use crate::map::BoundingBox;

/// Most points a generated path may have.
pub const MAX_PATH_POINTS: usize = 100_000_000;

/// A straight raster line from `start` to `end` (mm), in visiting order.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Line {
    /// First point, mm.
    pub start: [f64; 2],
    /// Last point, mm.
    pub end: [f64; 2],
}

impl Line {
    /// Length, mm.
    pub fn length_mm(&self) -> f64 {
        (self.end[0] - self.start[0]).hypot(self.end[1] - self.start[1])
    }
}

fn check_positive(what: &str, v: f64) -> Result<()> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(what, format!("must be positive, got {v}")))
    }
}

fn check_region(region: &BoundingBox) -> Result<()> {
    let ok = [
        region.x_min_mm,
        region.x_max_mm,
        region.y_min_mm,
        region.y_max_mm,
    ]
    .iter()
    .all(|v| v.is_finite())
        && region.x_max_mm >= region.x_min_mm
        && region.y_max_mm >= region.y_min_mm;
    if ok {
        Ok(())
    } else {
        Err(Error::invalid(
            "path region",
            format!(
                "needs finite limits with min <= max, got x [{}, {}], y [{}, {}] mm",
                region.x_min_mm, region.x_max_mm, region.y_min_mm, region.y_max_mm
            ),
        ))
    }
}

/// Serpentine raster lines at pitch `pitch_mm` across the region, shifted by `shift_mm`.
///
/// Line positions are `lo + shift + k P` for every `k` with the position in
/// `[lo - P/2, hi + P/2]`, so every point of the region lies within `P/2` of a line. Lines span
/// the full region along their direction; odd lines run backwards.
pub fn raster_lines(
    region: &BoundingBox,
    pitch_mm: f64,
    along: RasterAxis,
    shift_mm: f64,
) -> Result<Vec<Line>> {
    check_positive("raster pitch_mm", pitch_mm)?;
    check_region(region)?;
    if !shift_mm.is_finite() {
        return Err(Error::invalid("raster shift_mm", "not finite"));
    }
    let (a_lo, a_hi, c_lo, c_hi) = match along {
        RasterAxis::X => (
            region.x_min_mm,
            region.x_max_mm,
            region.y_min_mm,
            region.y_max_mm,
        ),
        RasterAxis::Y => (
            region.y_min_mm,
            region.y_max_mm,
            region.x_min_mm,
            region.x_max_mm,
        ),
    };
    let base = c_lo + shift_mm;
    let tol = 1e-9;
    let k0 = ((c_lo - 0.5 * pitch_mm - base) / pitch_mm - tol).ceil();
    let k1 = ((c_hi + 0.5 * pitch_mm - base) / pitch_mm + tol).floor();
    if k1 - k0 > MAX_PATH_POINTS as f64 {
        return Err(Error::invalid(
            "raster pitch_mm",
            format!("{pitch_mm} mm gives more than {MAX_PATH_POINTS} lines"),
        ));
    }
    let mut lines = Vec::new();
    let mut k = k0;
    let mut forward = true;
    while k <= k1 {
        let c = base + k * pitch_mm;
        let (s, e) = if forward { (a_lo, a_hi) } else { (a_hi, a_lo) };
        forward = !forward;
        lines.push(match along {
            RasterAxis::X => Line {
                start: [s, c],
                end: [e, c],
            },
            RasterAxis::Y => Line {
                start: [c, s],
                end: [c, e],
            },
        });
        k += 1.0;
    }
    Ok(lines)
}

/// Pushes the points of `line` at equal spacing no larger than `step_mm`, both ends included
/// (the start is skipped when it repeats the last point already in `xs, ys`).
pub(crate) fn push_line(
    line: &Line,
    step_mm: f64,
    xs: &mut Vec<f64>,
    ys: &mut Vec<f64>,
) -> Result<()> {
    let len = line.length_mm();
    let n = (len / step_mm - 1e-9).ceil().max(0.0);
    if xs.len() as f64 + n > MAX_PATH_POINTS as f64 {
        return Err(Error::invalid(
            "path",
            format!("more than {MAX_PATH_POINTS} points"),
        ));
    }
    let n = n as usize;
    for k in 0..=n {
        let f = if n == 0 { 0.0 } else { k as f64 / n as f64 };
        let p = [
            line.start[0] + f * (line.end[0] - line.start[0]),
            line.start[1] + f * (line.end[1] - line.start[1]),
        ];
        push_point(p, xs, ys);
    }
    Ok(())
}

/// Appends `p` unless it repeats the last point.
pub(crate) fn push_point(p: [f64; 2], xs: &mut Vec<f64>, ys: &mut Vec<f64>) {
    if let (Some(&x), Some(&y)) = (xs.last(), ys.last()) {
        if (x - p[0]).abs() < 1e-12 && (y - p[1]).abs() < 1e-12 {
            return;
        }
    }
    xs.push(p[0]);
    ys.push(p[1]);
}

/// The points of consecutive lines joined directly (sharp corners), spacing at most `step_mm`.
pub fn lines_to_path(lines: &[Line], step_mm: f64) -> Result<DwellPath> {
    check_positive("path step_mm", step_mm)?;
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for l in lines {
        push_line(l, step_mm, &mut xs, &mut ys)?;
    }
    DwellPath::new(xs, ys)
}

/// Direction and half-pitch shift of iteration `k`: `(axis, shifted)`.
pub fn iteration_pattern(iteration: usize) -> (RasterAxis, bool) {
    let axis = if iteration & 1 == 0 {
        RasterAxis::X
    } else {
        RasterAxis::Y
    };
    (axis, (iteration >> 1) & 1 == 1)
}

/// The lines of intersection iteration `iteration` (see the module documentation).
pub fn intersection_lines(
    region: &BoundingBox,
    pitch_mm: f64,
    iteration: usize,
) -> Result<Vec<Line>> {
    let (axis, shifted) = iteration_pattern(iteration);
    let shift = if shifted { 0.5 * pitch_mm } else { 0.0 };
    raster_lines(region, pitch_mm, axis, shift)
}

/// The intersection path of iteration `iteration` (0-based), points at most `pitch_mm` apart
/// along the lines, sharp corners.
pub fn intersection(region: &BoundingBox, pitch_mm: f64, iteration: usize) -> Result<DwellPath> {
    lines_to_path(&intersection_lines(region, pitch_mm, iteration)?, pitch_mm)
}

/// Keeps the points of `path` inside the closed polygon `aperture` (vertices in order, first
/// not repeated) or within `margin_mm` of its boundary (the clear aperture plus an extension
/// margin); the order of the kept points is unchanged. Inside is by the even-odd rule.
pub fn clip_to_aperture(
    path: &DwellPath,
    aperture: &[[f64; 2]],
    margin_mm: f64,
) -> Result<DwellPath> {
    if aperture.len() < 3 {
        return Err(Error::invalid("aperture", "needs at least three vertices"));
    }
    if !(margin_mm.is_finite() && margin_mm >= 0.0) {
        return Err(Error::invalid(
            "aperture margin_mm",
            format!("must be non-negative, got {margin_mm}"),
        ));
    }
    let m2 = margin_mm * margin_mm;
    let n = aperture.len();
    let keep = |x: f64, y: f64| -> bool {
        let mut inside = false;
        let mut near = false;
        for i in 0..n {
            let a = aperture[i];
            let b = aperture[(i + 1) % n];
            if (a[1] > y) != (b[1] > y) {
                let xc = a[0] + (y - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
                if x < xc {
                    inside = !inside;
                }
            }
            let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
            let l2 = ex * ex + ey * ey;
            let t = if l2 > 0.0 {
                (((x - a[0]) * ex + (y - a[1]) * ey) / l2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (dx, dy) = (a[0] + t * ex - x, a[1] + t * ey - y);
            near |= dx * dx + dy * dy <= m2;
        }
        inside || near
    };
    let (mut xs, mut ys) = (Vec::new(), Vec::new());
    for (&x, &y) in path.x_mm().iter().zip(path.y_mm()) {
        if keep(x, y) {
            xs.push(x);
            ys.push(y);
        }
    }
    if xs.is_empty() {
        return Err(Error::invalid(
            "aperture",
            "no path point lies in the aperture plus margin",
        ));
    }
    DwellPath::new(xs, ys)
}

#[cfg(test)]
mod tests {
    use super::*;

    const REGION: BoundingBox = BoundingBox {
        x_min_mm: -10.0,
        x_max_mm: 13.3,
        y_min_mm: 2.0,
        y_max_mm: 17.9,
    };

    /// Cross-line positions of a path's lines (y for x-lines, x for y-lines), in order.
    fn positions(lines: &[Line], axis: RasterAxis) -> Vec<f64> {
        lines
            .iter()
            .map(|l| match axis {
                RasterAxis::X => l.start[1],
                RasterAxis::Y => l.start[0],
            })
            .collect()
    }

    #[test]
    fn clip_keeps_aperture_plus_margin() {
        // Unit-pitch raster over [-10, 10]^2 clipped to a triangle plus 1 mm.
        let region = BoundingBox {
            x_min_mm: -10.0,
            x_max_mm: 10.0,
            y_min_mm: -10.0,
            y_max_mm: 10.0,
        };
        let path = lines_to_path(
            &raster_lines(&region, 1.0, RasterAxis::X, 0.0).unwrap(),
            1.0,
        )
        .unwrap();
        let tri = [[0.0, 0.0], [8.0, 0.0], [0.0, 8.0]];
        let c = clip_to_aperture(&path, &tri, 1.0).unwrap();
        for (&x, &y) in c.x_mm().iter().zip(c.y_mm()) {
            // Inside the triangle grown by 1 mm: x >= -1, y >= -1, x + y <= 8 + sqrt(2).
            assert!(x >= -1.0 - 1e-12 && y >= -1.0 - 1e-12 && x + y <= 8.0 + 2f64.sqrt() + 1e-9);
        }
        // Every raster point inside the triangle is kept.
        let inside = path
            .x_mm()
            .iter()
            .zip(path.y_mm())
            .filter(|(&x, &y)| x > 0.0 && y > 0.0 && x + y < 8.0)
            .count();
        let kept = c
            .x_mm()
            .iter()
            .zip(c.y_mm())
            .filter(|(&x, &y)| x > 0.0 && y > 0.0 && x + y < 8.0)
            .count();
        assert_eq!(inside, kept);
        assert!(c.len() > kept);
        assert!(clip_to_aperture(&path, &[[50.0, 50.0], [51.0, 50.0], [50.0, 51.0]], 0.1).is_err());
    }

    #[test]
    fn intersection_alternates_shifts_and_covers() {
        let p = 1.5;
        let mut pos = Vec::new();
        for k in 0..8 {
            let lines = intersection_lines(&REGION, p, k).unwrap();
            let (axis, shifted) = iteration_pattern(k);
            assert_eq!(
                axis,
                if k & 1 == 0 {
                    RasterAxis::X
                } else {
                    RasterAxis::Y
                }
            );
            assert_eq!(shifted, k % 4 >= 2);
            // Direction: every line is parallel to its axis and consecutive lines reverse.
            for (i, l) in lines.iter().enumerate() {
                let (da, dc) = match axis {
                    RasterAxis::X => (l.end[0] - l.start[0], l.end[1] - l.start[1]),
                    RasterAxis::Y => (l.end[1] - l.start[1], l.end[0] - l.start[0]),
                };
                assert_eq!(dc, 0.0);
                assert!(if i & 1 == 0 { da > 0.0 } else { da < 0.0 });
            }
            let c = positions(&lines, axis);
            // Constant pitch.
            for w in c.windows(2) {
                assert!((w[1] - w[0] - p).abs() < 1e-9);
            }
            // Coverage: every point of the aperture within P/2 of a line (sampled finely), and
            // every line spans the aperture.
            let (lo, hi) = match axis {
                RasterAxis::X => (REGION.y_min_mm, REGION.y_max_mm),
                RasterAxis::Y => (REGION.x_min_mm, REGION.x_max_mm),
            };
            for s in 0..=1000 {
                let v = lo + (hi - lo) * s as f64 / 1000.0;
                let d = c
                    .iter()
                    .map(|&ci| (ci - v).abs())
                    .fold(f64::INFINITY, f64::min);
                assert!(d <= 0.5 * p + 1e-9, "k={k} v={v} d={d}");
            }
            pos.push(c);
            // The dwell path has the lines' points at no more than P apart.
            let path = intersection(&REGION, p, k).unwrap();
            assert!(path.ds_mm().iter().all(|&d| d <= p + 1e-9));
        }
        // K=2 lines lie midway between K=0 lines (half-pitch shift); K=4 repeats K=0.
        for (a, b) in [(0usize, 2usize), (1, 3)] {
            for &v in &pos[b] {
                let d = pos[a]
                    .iter()
                    .map(|&u| (u - v).abs())
                    .fold(f64::INFINITY, f64::min);
                assert!((d - 0.5 * p).abs() < 1e-9);
            }
        }
        assert_eq!(pos[0], pos[4]);
        assert_eq!(pos[3], pos[7]);
        assert!(intersection(&REGION, 0.0, 0).is_err());
    }
}
