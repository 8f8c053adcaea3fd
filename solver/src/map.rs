//! Height maps: measured (or predicted) heights at scattered points in the plane.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Heights `z_nm` at points `(x_mm, y_mm)`: the form error to remove, a removal or a residual.
///
/// Validated on construction: equal lengths, all values finite.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeightMap {
    x_mm: Vec<f64>,
    y_mm: Vec<f64>,
    z_nm: Vec<f64>,
}

impl HeightMap {
    /// Builds a map from its columns; every value must be finite and the lengths equal.
    pub fn new(x_mm: Vec<f64>, y_mm: Vec<f64>, z_nm: Vec<f64>) -> Result<Self> {
        if y_mm.len() != x_mm.len() {
            return Err(Error::LengthMismatch {
                what: "map y_mm",
                got: y_mm.len(),
                expected: x_mm.len(),
            });
        }
        if z_nm.len() != x_mm.len() {
            return Err(Error::LengthMismatch {
                what: "map z_nm",
                got: z_nm.len(),
                expected: x_mm.len(),
            });
        }
        for (i, ((x, y), z)) in x_mm.iter().zip(&y_mm).zip(&z_nm).enumerate() {
            if !(x.is_finite() && y.is_finite() && z.is_finite()) {
                return Err(Error::NonFinite {
                    what: "map",
                    index: i,
                    detail: format!("x_mm={x}, y_mm={y}, z_nm={z}"),
                });
            }
        }
        Ok(Self { x_mm, y_mm, z_nm })
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.x_mm.len()
    }

    /// True when the map has no points.
    pub fn is_empty(&self) -> bool {
        self.x_mm.is_empty()
    }

    /// x coordinates, mm.
    pub fn x_mm(&self) -> &[f64] {
        &self.x_mm
    }

    /// y coordinates, mm.
    pub fn y_mm(&self) -> &[f64] {
        &self.y_mm
    }

    /// Heights, nm.
    pub fn z_nm(&self) -> &[f64] {
        &self.z_nm
    }

    /// The same points with other heights (same length required).
    pub fn with_heights(&self, z_nm: Vec<f64>) -> Result<Self> {
        Self::new(self.x_mm.clone(), self.y_mm.clone(), z_nm)
    }

    /// Axis-aligned bounding box `(x_min, x_max, y_min, y_max)` in mm, `None` for an empty map.
    pub fn bounding_box_mm(&self) -> Option<BoundingBox> {
        BoundingBox::of_points(&self.x_mm, &self.y_mm)
    }
}

/// An axis-aligned rectangle in mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoundingBox {
    /// Smallest x, mm.
    pub x_min_mm: f64,
    /// Largest x, mm.
    pub x_max_mm: f64,
    /// Smallest y, mm.
    pub y_min_mm: f64,
    /// Largest y, mm.
    pub y_max_mm: f64,
}

impl BoundingBox {
    /// The bounding box of a point set, `None` if empty.
    pub fn of_points(x_mm: &[f64], y_mm: &[f64]) -> Option<Self> {
        if x_mm.is_empty() || y_mm.is_empty() {
            return None;
        }
        let fold = |v: &[f64]| {
            v.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &a| {
                    (lo.min(a), hi.max(a))
                })
        };
        let (x_min_mm, x_max_mm) = fold(x_mm);
        let (y_min_mm, y_max_mm) = fold(y_mm);
        Some(Self {
            x_min_mm,
            x_max_mm,
            y_min_mm,
            y_max_mm,
        })
    }

    /// The box grown by `margin_mm` on every side.
    pub fn expanded(&self, margin_mm: f64) -> Self {
        Self {
            x_min_mm: self.x_min_mm - margin_mm,
            x_max_mm: self.x_max_mm + margin_mm,
            y_min_mm: self.y_min_mm - margin_mm,
            y_max_mm: self.y_max_mm + margin_mm,
        }
    }
}

/// Summary statistics of heights, as optical shops quote them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeightStats {
    /// Population standard deviation about the mean, nm.
    pub rms_nm: f64,
    /// Peak to valley, `max - min`, nm.
    pub pv_nm: f64,
    /// Mean, nm.
    pub mean_nm: f64,
    /// Largest absolute deviation from the mean, nm.
    pub max_abs_nm: f64,
    /// Mean absolute deviation from the mean, nm.
    pub mean_abs_nm: f64,
}

impl HeightStats {
    /// Statistics of `z_nm` (RMS and deviations about the mean). All zero for an empty slice.
    ///
    /// Summation runs in index order, so the result does not depend on the thread count.
    pub fn of(z_nm: &[f64]) -> Self {
        if z_nm.is_empty() {
            return Self {
                rms_nm: 0.0,
                pv_nm: 0.0,
                mean_nm: 0.0,
                max_abs_nm: 0.0,
                mean_abs_nm: 0.0,
            };
        }
        let n = z_nm.len() as f64;
        let mean = z_nm.iter().sum::<f64>() / n;
        let mut ss = 0.0;
        let mut sa = 0.0;
        let mut max_abs = 0.0_f64;
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        for &z in z_nm {
            let d = z - mean;
            ss += d * d;
            sa += d.abs();
            max_abs = max_abs.max(d.abs());
            lo = lo.min(z);
            hi = hi.max(z);
        }
        Self {
            rms_nm: (ss / n).sqrt(),
            pv_nm: hi - lo,
            mean_nm: mean,
            max_abs_nm: max_abs,
            mean_abs_nm: sa / n,
        }
    }
}

/// Removes the least-squares plane `a + b x + c y` from `z`.
pub fn remove_plane(x_mm: &[f64], y_mm: &[f64], z: &mut [f64]) -> Result<()> {
    let n = z.len() as f64;
    if z.len() < 3 {
        return Err(Error::invalid("map", "a plane needs at least three points"));
    }
    let (mx, my) = (x_mm.iter().sum::<f64>() / n, y_mm.iter().sum::<f64>() / n);
    let mz = z.iter().sum::<f64>() / n;
    let (mut sxx, mut sxy, mut syy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for i in 0..z.len() {
        let (dx, dy, dz) = (x_mm[i] - mx, y_mm[i] - my, z[i] - mz);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
        sxz += dx * dz;
        syz += dy * dz;
    }
    let det = sxx * syy - sxy * sxy;
    let (b, c) = if det.abs() > 1e-12 * (sxx * syy).max(f64::MIN_POSITIVE) {
        ((sxz * syy - syz * sxy) / det, (syz * sxx - sxz * sxy) / det)
    } else if sxx > syy {
        (sxz / sxx.max(f64::MIN_POSITIVE), 0.0)
    } else {
        (0.0, syz / syy.max(f64::MIN_POSITIVE))
    };
    for i in 0..z.len() {
        z[i] -= mz + b * (x_mm[i] - mx) + c * (y_mm[i] - my);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_of_known_values() {
        // z = {1, 2, 3, 6}: mean 3, deviations {-2,-1,0,3}, variance 14/4.
        let s = HeightStats::of(&[1.0, 2.0, 3.0, 6.0]);
        assert!((s.mean_nm - 3.0).abs() < 1e-15);
        assert!((s.rms_nm - (14.0f64 / 4.0).sqrt()).abs() < 1e-15);
        assert!((s.pv_nm - 5.0).abs() < 1e-15);
        assert!((s.max_abs_nm - 3.0).abs() < 1e-15);
        assert!((s.mean_abs_nm - 1.5).abs() < 1e-15);
    }

    #[test]
    fn map_rejects_nan_and_mismatch() {
        assert!(HeightMap::new(vec![0.0], vec![0.0], vec![f64::NAN]).is_err());
        assert!(HeightMap::new(vec![0.0, 1.0], vec![0.0], vec![0.0]).is_err());
    }
}
