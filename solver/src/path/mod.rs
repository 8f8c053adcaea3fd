//! Dwell paths: the ordered points where the tool dwells, and their path-length shares `ds`.

pub mod arcs;
pub mod chord_height;
pub mod edge_offset;
pub mod intersection;
pub mod project;
pub mod random;
pub mod raster;
pub mod spiral;
pub mod summary;

pub use intersection::intersection;
pub use project::{project, ProjectedPath};
pub use summary::PathSummary;

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Dwell points `(x_mm, y_mm)` in the order the machine visits them.
///
/// Validated on construction: equal lengths, at least one point, all coordinates finite.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DwellPath {
    x_mm: Vec<f64>,
    y_mm: Vec<f64>,
}

impl DwellPath {
    /// Builds a path from its coordinates in visiting order.
    pub fn new(x_mm: Vec<f64>, y_mm: Vec<f64>) -> Result<Self> {
        if x_mm.len() != y_mm.len() {
            return Err(Error::LengthMismatch {
                what: "dwell y_mm",
                got: y_mm.len(),
                expected: x_mm.len(),
            });
        }
        if x_mm.is_empty() {
            return Err(Error::invalid("dwell path", "has no points"));
        }
        for (i, (x, y)) in x_mm.iter().zip(&y_mm).enumerate() {
            if !(x.is_finite() && y.is_finite()) {
                return Err(Error::NonFinite {
                    what: "dwell",
                    index: i,
                    detail: format!("x_mm={x}, y_mm={y}"),
                });
            }
        }
        Ok(Self { x_mm, y_mm })
    }

    /// Number of dwell points.
    pub fn len(&self) -> usize {
        self.x_mm.len()
    }

    /// Always false: a path has at least one point.
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

    /// Path length attributed to each dwell point, mm (the contract of the engine issue):
    /// half the distance to the previous point plus half the distance to the next; the first and
    /// last points take the full distance to their only neighbour. A single point gets 0.
    pub fn ds_mm(&self) -> Vec<f64> {
        let n = self.len();
        let seg: Vec<f64> = self
            .x_mm
            .windows(2)
            .zip(self.y_mm.windows(2))
            .map(|(x, y)| match (x, y) {
                ([x0, x1], [y0, y1]) => (x1 - x0).hypot(y1 - y0),
                _ => 0.0,
            })
            .collect();
        let mut ds = vec![0.0; n];
        if n < 2 {
            return ds;
        }
        for (j, d) in ds.iter_mut().enumerate() {
            *d = if j == 0 {
                seg[0]
            } else if j == n - 1 {
                seg[n - 2]
            } else {
                0.5 * (seg[j - 1] + seg[j])
            };
        }
        ds
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ds_follows_the_contract() {
        // Segments of length 1, 2 (3-4-5 triangle scaled: (1,0)->(1,2)), 5.
        let p = DwellPath::new(vec![0.0, 1.0, 1.0, 4.0], vec![0.0, 0.0, 2.0, 6.0]).unwrap();
        let ds = p.ds_mm();
        assert_eq!(ds, vec![1.0, 1.5, 3.5, 5.0]);
        let single = DwellPath::new(vec![3.0], vec![4.0]).unwrap();
        assert_eq!(single.ds_mm(), vec![0.0]);
        assert!(DwellPath::new(vec![], vec![]).is_err());
    }
}
