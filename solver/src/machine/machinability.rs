//! Machinability figures of a plan: how sharply the feed changes between neighbouring dwell
//! points, and how much dwell sits where no measured point constrains it.
//!
//! - Neighbour feed ratio: `max_j max(v_j / v_{j+1}, v_{j+1} / v_j)` over consecutive dwell
//!   points that both move (`v > 0`). A stage cannot follow a 100x step between neighbours.
//! - Dwell off the map: the dwell on points with no map point under the TIF centre, i.e. whose
//!   nearest map point is farther than the map's pitch `p` (inside a regular grid the nearest
//!   node is at most `p / sqrt 2` away). `p` is the median nearest-neighbour distance of the map
//!   points. Found with a bucket grid of cell `p`: `O(m + n)`.

use std::collections::HashMap;

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

/// Map points bucketed on a square grid of cell `h` (mm).
struct Buckets {
    h: f64,
    cells: HashMap<(i64, i64), Vec<u32>>,
}

impl Buckets {
    fn new(x: &[f64], y: &[f64], h: f64) -> Self {
        let mut cells: HashMap<(i64, i64), Vec<u32>> = HashMap::with_capacity(x.len());
        for (i, (&px, &py)) in x.iter().zip(y).enumerate() {
            cells
                .entry(((px / h).floor() as i64, (py / h).floor() as i64))
                .or_default()
                .push(i as u32);
        }
        Self { h, cells }
    }

    /// Distance to the nearest point within the 3 x 3 cells around `(px, py)` (skipping index
    /// `skip`); `f64::INFINITY` when there is none there (the nearest is then farther than `h`).
    fn nearest(&self, x: &[f64], y: &[f64], px: f64, py: f64, skip: Option<usize>) -> f64 {
        let (cx, cy) = ((px / self.h).floor() as i64, (py / self.h).floor() as i64);
        let mut best = f64::INFINITY;
        for dx in -1..=1 {
            for dy in -1..=1 {
                if let Some(v) = self.cells.get(&(cx + dx, cy + dy)) {
                    for &i in v {
                        let i = i as usize;
                        if Some(i) != skip {
                            best = best.min((x[i] - px).hypot(y[i] - py));
                        }
                    }
                }
            }
        }
        best
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
        .map(|i| b.nearest(map_x_mm, map_y_mm, map_x_mm[i], map_y_mm[i], Some(i)))
        .map(|v| v.min(h0))
        .collect();
    d.sort_by(f64::total_cmp);
    Some(d[m / 2])
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
    dwell_x_mm
        .iter()
        .zip(dwell_y_mm)
        .zip(dwell_s)
        .filter(|((&x, &y), _)| b.nearest(map_x_mm, map_y_mm, x, y, None) > p)
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
