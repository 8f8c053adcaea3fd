//! Machine feed limits and the dwell-time bounds they imply.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Feed limits of the machine along the path, mm/min (the CNC `F` word).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeedLimits {
    /// Fastest feed, mm/min (required, positive).
    pub v_max_mm_per_min: f64,
    /// Slowest feed, mm/min; 0 means no lower limit (dwell may be arbitrarily long).
    #[serde(default)]
    pub v_min_mm_per_min: f64,
}

impl FeedLimits {
    /// Checks `0 < v_max`, `0 <= v_min <= v_max`, all finite.
    pub fn validate(&self) -> Result<()> {
        if !(self.v_max_mm_per_min.is_finite() && self.v_max_mm_per_min > 0.0) {
            return Err(Error::invalid(
                "v_max_mm_per_min",
                format!("must be positive, got {}", self.v_max_mm_per_min),
            ));
        }
        if !(self.v_min_mm_per_min.is_finite() && self.v_min_mm_per_min >= 0.0) {
            return Err(Error::invalid(
                "v_min_mm_per_min",
                format!(
                    "must be zero (no limit) or positive, got {}",
                    self.v_min_mm_per_min
                ),
            ));
        }
        if self.v_min_mm_per_min > self.v_max_mm_per_min {
            return Err(Error::invalid(
                "v_min_mm_per_min",
                format!(
                    "{} exceeds v_max_mm_per_min {}: no feed satisfies both",
                    self.v_min_mm_per_min, self.v_max_mm_per_min
                ),
            ));
        }
        Ok(())
    }
}

/// Box bounds on the dwell times, s: `lower_s[j] <= t_j <= upper_s[j]`.
#[derive(Debug, Clone, PartialEq)]
pub struct DwellBounds {
    lower_s: Vec<f64>,
    upper_s: Option<Vec<f64>>,
}

impl DwellBounds {
    /// Bounds from path lengths `ds_mm` and feed limits (engine contract):
    /// `t_j >= ds_j / (v_max / 60)` and, if `v_min > 0`, `t_j <= ds_j / (v_min / 60)`.
    pub fn from_feeds(ds_mm: &[f64], limits: &FeedLimits) -> Result<Self> {
        limits.validate()?;
        let vmax = limits.v_max_mm_per_min / 60.0;
        let lower_s = ds_mm.iter().map(|d| d / vmax).collect();
        let upper_s = (limits.v_min_mm_per_min > 0.0).then(|| {
            let vmin = limits.v_min_mm_per_min / 60.0;
            ds_mm.iter().map(|d| d / vmin).collect()
        });
        Self::new(lower_s, upper_s)
    }

    /// Explicit bounds; each lower bound must be finite and non-negative and each upper bound at
    /// least its lower bound.
    pub fn new(lower_s: Vec<f64>, upper_s: Option<Vec<f64>>) -> Result<Self> {
        for (j, &l) in lower_s.iter().enumerate() {
            if !(l.is_finite() && l >= 0.0) {
                return Err(Error::invalid(
                    "dwell lower bound",
                    format!("point {j}: {l} s is not a finite non-negative time"),
                ));
            }
        }
        if let Some(u) = &upper_s {
            if u.len() != lower_s.len() {
                return Err(Error::LengthMismatch {
                    what: "dwell upper bounds",
                    got: u.len(),
                    expected: lower_s.len(),
                });
            }
            for (j, (&l, &h)) in lower_s.iter().zip(u).enumerate() {
                if h.is_nan() || h < l {
                    return Err(Error::invalid(
                        "dwell upper bound",
                        format!("point {j}: upper {h} s is below lower {l} s"),
                    ));
                }
            }
        }
        Ok(Self { lower_s, upper_s })
    }

    /// Number of dwell points.
    pub fn len(&self) -> usize {
        self.lower_s.len()
    }

    /// True when there are no dwell points.
    pub fn is_empty(&self) -> bool {
        self.lower_s.is_empty()
    }

    /// Lower bounds, s.
    pub fn lower_s(&self) -> &[f64] {
        &self.lower_s
    }

    /// Upper bounds, s (`None`: no upper bound).
    pub fn upper_s(&self) -> Option<&[f64]> {
        self.upper_s.as_deref()
    }

    /// Upper bound of point `j`, `+inf` when there is none.
    #[inline]
    pub fn upper(&self, j: usize) -> f64 {
        self.upper_s
            .as_ref()
            .and_then(|u| u.get(j).copied())
            .unwrap_or(f64::INFINITY)
    }

    /// Projects `t` onto the box in place.
    pub fn project(&self, t: &mut [f64]) {
        for (j, tj) in t.iter_mut().enumerate() {
            let lo = self.lower_s.get(j).copied().unwrap_or(0.0);
            *tj = tj.max(lo).min(self.upper(j));
        }
    }

    /// Largest amount, s, by which `t` leaves the box.
    pub fn max_violation_s(&self, t: &[f64]) -> f64 {
        t.iter()
            .enumerate()
            .map(|(j, &tj)| {
                let lo = self.lower_s.get(j).copied().unwrap_or(0.0);
                (lo - tj).max(tj - self.upper(j)).max(0.0)
            })
            .fold(0.0, f64::max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_from_feeds() {
        // ds = 1 mm at v_max 3000 mm/min = 50 mm/s: 0.02 s; v_min 600 mm/min = 10 mm/s: 0.1 s.
        let lim = FeedLimits {
            v_max_mm_per_min: 3000.0,
            v_min_mm_per_min: 600.0,
        };
        let b = DwellBounds::from_feeds(&[1.0, 2.0], &lim).unwrap();
        assert!((b.lower_s()[0] - 0.02).abs() < 1e-15);
        assert!((b.upper(1) - 0.2).abs() < 1e-15);
        let none = FeedLimits {
            v_max_mm_per_min: 3000.0,
            v_min_mm_per_min: 0.0,
        };
        assert_eq!(
            DwellBounds::from_feeds(&[1.0], &none).unwrap().upper(0),
            f64::INFINITY
        );
    }

    #[test]
    fn contradictory_limits_are_errors() {
        let bad = [
            (0.0, 0.0),
            (-1.0, 0.0),
            (100.0, 200.0),
            (100.0, -1.0),
            (f64::NAN, 0.0),
        ];
        for (vmax, vmin) in bad {
            let lim = FeedLimits {
                v_max_mm_per_min: vmax,
                v_min_mm_per_min: vmin,
            };
            assert!(lim.validate().is_err(), "{vmax} {vmin}");
        }
    }
}
