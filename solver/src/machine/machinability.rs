//! Machinability figures of a plan: how sharply the feed changes between neighbouring dwell
//! points, and how much dwell sits where no measured point constrains it.
//!
//! - Neighbour feed ratio: `max_j max(v_j / v_{j+1}, v_{j+1} / v_j)` over consecutive dwell
//!   points that both move (`v > 0`). A stage cannot follow a 100x step between neighbours.
//! - Dwell off the map: the dwell on points with no map point under the TIF centre, i.e. whose
//!   nearest map point is farther than the map's pitch `p` (inside a regular grid the nearest
//!   node is at most `p / sqrt 2` away). `p` is the median nearest-neighbour distance of the map
//!   points. Found with a bucket grid of cell `p`: `O(m + n)`.

use rayon::prelude::*;

/// Largest ratio of the feeds of two consecutive moving dwell points (1 when none move).
pub fn max_neighbour_feed_ratio(feed_mm_per_min: &[f64]) -> f64 {
    feed_mm_per_min
        .windows(2)
        .filter_map(|w| match w {
            [a, b] if *a > 0.0 && *b > 0.0 => Some((a / b).max(b / a)),
            _ => None,
        })
        .fold(1.0, f64::max)
}

/// Points bucketed on a square grid over their bounding box: cells of side `h` (mm), or a
/// power of two times `h` where the box would otherwise hold more than about two cells per point
/// (a coarser cell still finds every neighbour within `h` in the 3 x 3 cells around a point).
/// Each cell's points in ascending index order (compressed rows).
struct Buckets {
    h: f64,
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    /// Cell `c`'s points are `points[starts[c]..starts[c + 1]]`.
    starts: Vec<usize>,
    points: Vec<u32>,
}

impl Buckets {
    fn new(x: &[f64], y: &[f64], h: f64) -> Self {
        let bounds = |v: &[f64]| {
            v.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &p| {
                    (a.min(p), b.max(p))
                })
        };
        let ((x0, x1), (y0, y1)) = (bounds(x), bounds(y));
        let (x0, y0) = if x.is_empty() { (0.0, 0.0) } else { (x0, y0) };
        let span = |lo: f64, hi: f64, h: f64| {
            (((hi - lo).max(0.0) / h).floor() as usize).saturating_add(1)
        };
        let most = 2 * x.len() + 1024;
        let mut h = h;
        while !x.is_empty() && span(x0, x1, h).saturating_mul(span(y0, y1, h)) > most {
            h *= 2.0;
        }
        let (nx, ny) = if x.is_empty() {
            (1, 1)
        } else {
            (span(x0, x1, h), span(y0, y1, h))
        };
        let cell = |px: f64, py: f64| {
            let i = (((px - x0) / h).floor() as usize).min(nx - 1);
            let j = (((py - y0) / h).floor() as usize).min(ny - 1);
            j * nx + i
        };
        let mut starts = vec![0usize; nx * ny + 1];
        for (&px, &py) in x.iter().zip(y) {
            starts[cell(px, py) + 1] += 1;
        }
        for c in 0..nx * ny {
            starts[c + 1] += starts[c];
        }
        let mut next = starts.clone();
        let mut points = vec![0u32; x.len()];
        for (i, (&px, &py)) in x.iter().zip(y).enumerate() {
            let c = cell(px, py);
            points[next[c]] = i as u32;
            next[c] += 1;
        }
        Self {
            h,
            x0,
            y0,
            nx,
            ny,
            starts,
            points,
        }
    }

    /// Distance to the nearest point within the 3 x 3 cells around `(px, py)` (skipping index
    /// `skip`); `f64::INFINITY` when there is none there (the nearest is then farther than `h`).
    fn nearest(&self, x: &[f64], y: &[f64], px: f64, py: f64, skip: Option<usize>) -> f64 {
        let cx = ((px - self.x0) / self.h).floor();
        let cy = ((py - self.y0) / self.h).floor();
        let mut best = f64::INFINITY;
        for j in [cy - 1.0, cy, cy + 1.0] {
            if !(j >= 0.0 && j < self.ny as f64) {
                continue;
            }
            for i in [cx - 1.0, cx, cx + 1.0] {
                if !(i >= 0.0 && i < self.nx as f64) {
                    continue;
                }
                let c = j as usize * self.nx + i as usize;
                for &k in &self.points[self.starts[c]..self.starts[c + 1]] {
                    let k = k as usize;
                    if Some(k) != skip {
                        let (dx, dy) = (x[k] - px, y[k] - py);
                        best = best.min(dx * dx + dy * dy);
                    }
                }
            }
        }
        best.sqrt()
    }
}

/// The map's pitch: the median distance of its points to their nearest neighbour, mm (`None`
/// for fewer than two points).
pub fn map_pitch_mm(map_x_mm: &[f64], map_y_mm: &[f64]) -> Option<f64> {
    let m = map_x_mm.len();
    if m < 2 {
        return None;
    }
    let (lo_x, hi_x) = map_x_mm
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    let (lo_y, hi_y) = map_y_mm
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    // Cells of twice the mean spacing (about four points each): the 3 x 3 cells around a point
    // reach at least that far, so a regular grid's neighbours are always found.
    let area = (hi_x - lo_x) * (hi_y - lo_y);
    let h0 = 2.0
        * if area > 0.0 {
            (area / m as f64).sqrt()
        } else {
            ((hi_x - lo_x) + (hi_y - lo_y)) / m as f64
        };
    if !(h0.is_finite() && h0 > 0.0) {
        return None;
    }
    let b = Buckets::new(map_x_mm, map_y_mm, h0);
    let mut d: Vec<f64> = (0..m)
        .into_par_iter()
        .map(|i| b.nearest(map_x_mm, map_y_mm, map_x_mm[i], map_y_mm[i], Some(i)))
        .map(|v| v.min(h0))
        .collect();
    let (_, median, _) = d.select_nth_unstable_by(m / 2, f64::total_cmp);
    Some(*median)
}

/// Dwell (s) on the points whose nearest map point is farther than the map's pitch.
pub fn dwell_outside_map_s(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    dwell_s: &[f64],
) -> f64 {
    let Some(p) = map_pitch_mm(map_x_mm, map_y_mm).filter(|p| *p > 0.0) else {
        return dwell_s.iter().sum();
    };
    let b = Buckets::new(map_x_mm, map_y_mm, p);
    let outside: Vec<bool> = dwell_x_mm
        .par_iter()
        .zip(dwell_y_mm)
        .map(|(&x, &y)| b.nearest(map_x_mm, map_y_mm, x, y, None) > p)
        .collect();
    // Summed in point order, whatever the thread count.
    outside
        .iter()
        .zip(dwell_s)
        .filter(|(out, _)| **out)
        .map(|(_, &t)| t)
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feed_ratio_of_neighbours() {
        assert_eq!(
            max_neighbour_feed_ratio(&[10.0, 20.0, 5.0, 0.0, 1000.0]),
            4.0
        );
        assert_eq!(max_neighbour_feed_ratio(&[3.0]), 1.0);
    }

    /// The bucket grid's nearest distance against a brute-force search, for queries inside,
    /// between and outside two clusters 1 km apart (the grid coarsened to stay small): equal
    /// wherever the nearest point is within `h`, and beyond `h` otherwise.
    #[test]
    fn bucket_nearest_is_the_brute_force_nearest_within_reach() {
        let mut rng = crate::rng::SplitMix64::new(7);
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for k in 0..400 {
            let shift = if k % 2 == 0 { 0.0 } else { 1000.0 };
            x.push(shift + 10.0 * rng.uniform());
            y.push(5.0 * rng.uniform());
        }
        let h = 0.4;
        let b = Buckets::new(&x, &y, h);
        assert!(b.nx * b.ny <= 2 * x.len() + 1024, "{} x {}", b.nx, b.ny);
        for q in 0..2000 {
            let (px, py) = if q < 400 {
                (x[q], y[q])
            } else {
                (
                    -5.0 + 1020.0 * rng.uniform() * if q % 3 == 0 { 1.0 } else { 0.011 },
                    -2.0 + 9.0 * rng.uniform(),
                )
            };
            let skip = (q < 400).then_some(q);
            let brute = (0..x.len())
                .filter(|&k| Some(k) != skip)
                .map(|k| (x[k] - px).hypot(y[k] - py))
                .fold(f64::INFINITY, f64::min);
            let got = b.nearest(&x, &y, px, py, skip);
            if brute <= h {
                assert!(
                    (got - brute).abs() <= 1e-12,
                    "({px}, {py}): {got} vs {brute}"
                );
            } else {
                assert!(got > h, "({px}, {py}): {got} vs {brute}");
            }
        }
    }

    #[test]
    fn dwell_off_a_grid_map_is_counted() {
        // A 0.5 mm grid over [0, 10] x [0, 5].
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for i in 0..=20 {
            for j in 0..=10 {
                x.push(0.5 * i as f64);
                y.push(0.5 * j as f64);
            }
        }
        assert!((map_pitch_mm(&x, &y).unwrap() - 0.5).abs() < 1e-12);
        // Inside (between nodes), on the edge, 0.3 mm outside (nearest node 0.3 < 0.5), and
        // 2 mm and 7 mm outside.
        let dx = [3.26, 10.0, 10.3, 12.0, -7.0];
        let dy = [1.13, 2.5, 2.5, 2.5, 1.0];
        let t = [1.0, 2.0, 4.0, 8.0, 16.0];
        assert_eq!(dwell_outside_map_s(&x, &y, &dx, &dy, &t), 24.0);
    }
}
