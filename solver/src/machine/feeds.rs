//! Feed schedule along a dwell path and the machining time, with acceleration and deceleration
//! ramps.
//!
//! Model: the feed at dwell point `j` is `v_j = ds_j / t_j`, held over the whole stretch the
//! point owns (from the midpoint of the segment before to the midpoint of the segment after; the
//! end points' stretches run half a segment beyond the path: run-in and run-out), which is how
//! [`super::gcode::write`] programs it. The nominal time is then `sum t_j`. With an acceleration
//! limit `a`, the ramps add: from rest to `v_0` and from `v_{n-1}` to rest, `v / (2 a)` each (a
//! ramp over `v^2 / (2 a)` takes `v / a` instead of `v / (2 a)`), and a stop-and-go at every
//! corner (turn > `corner_angle_deg`), `v_j / a`. This is an estimate for reports; the program
//! as written is executed by [`super::gcode::motion`]. The accelerations reported are those of
//! the solver's model ([`crate::kinematics`]: speed changing uniformly between points).

use crate::error::{Error, Result};
use crate::kinematics::check_a_max_mm_per_s2;
use crate::kinematics::lines::{segment_accelerations_mm_per_s2, turn_angles_deg};
use crate::path::DwellPath;
use serde::{Deserialize, Serialize};

/// The feeds and times of a dwell path.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeedSchedule {
    /// Feed at each dwell point, `60 ds_j / t_j`, mm/min.
    pub point_feed_mm_per_min: Vec<f64>,
    /// Sum of the dwell times, s.
    pub total_dwell_s: f64,
    /// Every stretch crossed at its point's feed, `sum t_j`, s.
    pub nominal_time_s: f64,
    /// Extra time of the acceleration and deceleration ramps, s (0 without a limit).
    pub ramp_time_s: f64,
    /// `nominal_time_s + ramp_time_s`, s.
    pub machining_time_s: f64,
    /// Largest acceleration between dwell points on a line, mm/s^2.
    pub max_accel_mm_per_s2: f64,
    /// Moves whose acceleration exceeds the limit by more than 1%.
    pub segments_over_limit: usize,
    /// Points where the machine stops to turn a corner.
    pub corner_stops: usize,
}

impl FeedSchedule {
    /// Schedules `dwell_s` (s, all positive where `ds > 0`) on `path`; `a_max_mm_per_s2` adds the
    /// ramps; `corner_angle_deg` decides corners and lines (see [`crate::kinematics`]).
    pub fn new(
        path: &DwellPath,
        dwell_s: &[f64],
        a_max_mm_per_s2: Option<f64>,
        corner_angle_deg: f64,
    ) -> Result<Self> {
        let n = path.len();
        if dwell_s.len() != n {
            return Err(Error::LengthMismatch {
                what: "dwell_s",
                got: dwell_s.len(),
                expected: n,
            });
        }
        if let Some(a) = a_max_mm_per_s2 {
            check_a_max_mm_per_s2(a)?;
        }
        let ds = path.ds_mm();
        let mut v = Vec::with_capacity(n);
        for (j, (&d, &t)) in ds.iter().zip(dwell_s).enumerate() {
            if !(t.is_finite() && t >= 0.0) {
                return Err(Error::invalid(
                    "dwell_s",
                    format!("point {j}: {t} s is not a finite non-negative time"),
                ));
            }
            if d > 0.0 && t == 0.0 {
                return Err(Error::invalid(
                    "dwell_s",
                    format!("point {j}: zero dwell over {d} mm needs an infinite feed"),
                ));
            }
            v.push(if d > 0.0 { d / t } else { 0.0 });
        }
        let total_dwell_s: f64 = dwell_s.iter().sum();
        let nominal = total_dwell_s;
        let turns = turn_angles_deg(path);
        let corners: Vec<usize> = (0..n).filter(|&j| turns[j] > corner_angle_deg).collect();
        let ramp = match a_max_mm_per_s2 {
            Some(a) if n >= 1 => {
                let start_end = (v[0] + v[n - 1]) / (2.0 * a);
                start_end + corners.iter().map(|&j| v[j] / a).sum::<f64>()
            }
            _ => 0.0,
        };
        let accels = segment_accelerations_mm_per_s2(path, dwell_s, corner_angle_deg);
        let max_accel = accels.iter().flatten().fold(0.0, |m: f64, &a| m.max(a));
        let over = a_max_mm_per_s2.map_or(0, |lim| {
            accels.iter().flatten().filter(|&&a| a > 1.01 * lim).count()
        });
        Ok(Self {
            point_feed_mm_per_min: v.iter().map(|x| 60.0 * x).collect(),
            total_dwell_s,
            nominal_time_s: nominal,
            ramp_time_s: ramp,
            machining_time_s: nominal + ramp,
            max_accel_mm_per_s2: max_accel,
            segments_over_limit: over,
            corner_stops: corners.len(),
        })
    }

    /// Slowest and fastest point feed, mm/min (ignoring points with no path length).
    pub fn feed_range_mm_per_min(&self) -> (f64, f64) {
        let moving = self.point_feed_mm_per_min.iter().filter(|&&f| f > 0.0);
        let lo = moving.clone().fold(f64::INFINITY, |a, &b| a.min(b));
        let hi = moving.fold(0.0, |a: f64, &b| a.max(b));
        (if lo.is_finite() { lo } else { 0.0 }, hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOL: f64 = 1e-12;

    #[test]
    fn constant_feed_line_time_is_length_over_speed_plus_ramps() {
        // 11 points, pitch 1 mm, 10 mm/s: ds = 1 everywhere, t = 0.1 s.
        let p = DwellPath::new((0..11).map(f64::from).collect(), vec![0.0; 11]).unwrap();
        let t = vec![0.1; 11];
        let f = FeedSchedule::new(&p, &t, None, 60.0).unwrap();
        assert!((f.nominal_time_s - 1.1).abs() < TOL, "{}", f.nominal_time_s);
        assert!((f.nominal_time_s - f.total_dwell_s).abs() < TOL);
        assert!(f
            .point_feed_mm_per_min
            .iter()
            .all(|&v| (v - 600.0).abs() < 1e-9));
        // a = 100 mm/s^2: start and stop ramps add 10 / 200 s each.
        let g = FeedSchedule::new(&p, &t, Some(100.0), 60.0).unwrap();
        assert!((g.ramp_time_s - 0.1).abs() < TOL);
        assert_eq!(g.max_accel_mm_per_s2, 0.0);
    }

    #[test]
    fn nominal_time_is_the_dwell_and_accelerations_follow_the_model() {
        // v from 10 to 30 mm/s over 1 mm: a = (900 - 100) / 2; each stretch at its own feed.
        let p = DwellPath::new(vec![0.0, 1.0], vec![0.0, 0.0]).unwrap();
        let t = [0.1, 1.0 / 30.0];
        let f = FeedSchedule::new(&p, &t, Some(100.0), 60.0).unwrap();
        assert!((f.nominal_time_s - (t[0] + t[1])).abs() < TOL);
        assert!(f.machining_time_s >= f.total_dwell_s);
        assert!((f.max_accel_mm_per_s2 - 400.0).abs() < 1e-9);
        assert_eq!(f.segments_over_limit, 1);
        assert!((f.point_feed_mm_per_min[1] - 1800.0).abs() < 1e-9);
    }

    #[test]
    fn raster_corners_stop() {
        let p = DwellPath::new(
            vec![0.0, 1.0, 2.0, 2.0, 1.0, 0.0],
            vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
        )
        .unwrap();
        let f = FeedSchedule::new(&p, &[0.1; 6], Some(50.0), 60.0).unwrap();
        assert_eq!(f.corner_stops, 2);
        // v = 10 mm/s: start + end 2 * 10 / 100, corners 2 * 10 / 50.
        assert!((f.ramp_time_s - (0.2 + 0.4)).abs() < TOL);
        assert!(FeedSchedule::new(&p, &[0.0; 6], None, 60.0).is_err());
    }
}
