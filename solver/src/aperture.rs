//! Clear apertures: the region of the plane (mm) whose points a map keeps.

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// A clear aperture in the plane of the map, mm. Points on the boundary are inside.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case")]
pub enum Aperture {
    /// `(x - cx)^2 + (y - cy)^2 <= r^2`.
    Circle {
        /// Radius, mm.
        radius_mm: f64,
        /// Centre x, mm.
        centre_x_mm: f64,
        /// Centre y, mm.
        centre_y_mm: f64,
    },
    /// `r_inner^2 <= x^2 + y^2 <= r_outer^2` (about the origin).
    Annulus {
        /// Inner radius, mm.
        inner_radius_mm: f64,
        /// Outer radius, mm.
        outer_radius_mm: f64,
    },
    /// `|x| <= w / 2` and `|y| <= h / 2` (about the origin).
    Rect {
        /// Full width along x, mm.
        width_mm: f64,
        /// Full height along y, mm.
        height_mm: f64,
    },
    /// A simple polygon (vertices in order, closed implicitly); inside by the even-odd rule.
    Polygon {
        /// Vertices `(x_mm, y_mm)`.
        vertices_mm: Vec<(f64, f64)>,
    },
}

impl Aperture {
    /// Checks the dimensions: positive and finite radii and sides, `r_inner < r_outer`, at least
    /// three finite polygon vertices.
    pub fn validate(&self) -> Result<()> {
        let positive = |what: &str, v: f64| {
            if v > 0.0 && v.is_finite() {
                Ok(())
            } else {
                Err(Error::invalid(
                    format!("aperture {what}"),
                    format!("{v} must be positive and finite"),
                ))
            }
        };
        match self {
            Aperture::Circle {
                radius_mm,
                centre_x_mm,
                centre_y_mm,
            } => {
                positive("radius_mm", *radius_mm)?;
                if !(centre_x_mm.is_finite() && centre_y_mm.is_finite()) {
                    return Err(Error::invalid("aperture centre", "must be finite"));
                }
                Ok(())
            }
            Aperture::Annulus {
                inner_radius_mm,
                outer_radius_mm,
            } => {
                positive("outer_radius_mm", *outer_radius_mm)?;
                if !(*inner_radius_mm >= 0.0 && inner_radius_mm < outer_radius_mm) {
                    return Err(Error::invalid(
                        "aperture inner_radius_mm",
                        format!(
                            "{inner_radius_mm} must be at least 0 and below the outer radius {outer_radius_mm}"
                        ),
                    ));
                }
                Ok(())
            }
            Aperture::Rect {
                width_mm,
                height_mm,
            } => {
                positive("width_mm", *width_mm)?;
                positive("height_mm", *height_mm)
            }
            Aperture::Polygon { vertices_mm } => {
                if vertices_mm.len() < 3 {
                    return Err(Error::invalid(
                        "aperture polygon",
                        format!("has {} vertices, needs at least 3", vertices_mm.len()),
                    ));
                }
                if let Some(k) = vertices_mm
                    .iter()
                    .position(|(x, y)| !(x.is_finite() && y.is_finite()))
                {
                    return Err(Error::invalid(
                        "aperture polygon",
                        format!("vertex {k} is not finite"),
                    ));
                }
                Ok(())
            }
        }
    }

    /// Whether `(x, y)` (mm) lies inside or on the boundary.
    ///
    /// Polygons use the crossing-number (even-odd) test of a horizontal ray (Shimrat 1962).
    pub fn contains(&self, x: f64, y: f64) -> bool {
        match self {
            Aperture::Circle {
                radius_mm,
                centre_x_mm,
                centre_y_mm,
            } => {
                let (dx, dy) = (x - centre_x_mm, y - centre_y_mm);
                dx * dx + dy * dy <= radius_mm * radius_mm
            }
            Aperture::Annulus {
                inner_radius_mm,
                outer_radius_mm,
            } => {
                let r2 = x * x + y * y;
                r2 >= inner_radius_mm * inner_radius_mm && r2 <= outer_radius_mm * outer_radius_mm
            }
            Aperture::Rect {
                width_mm,
                height_mm,
            } => x.abs() <= 0.5 * width_mm && y.abs() <= 0.5 * height_mm,
            Aperture::Polygon { vertices_mm } => {
                let n = vertices_mm.len();
                let mut inside = false;
                for k in 0..n {
                    let (xa, ya) = vertices_mm[k];
                    let (xb, yb) = vertices_mm[(k + 1) % n];
                    if on_segment(x, y, xa, ya, xb, yb) {
                        return true;
                    }
                    if (ya > y) != (yb > y) {
                        let xc = xa + (y - ya) * (xb - xa) / (yb - ya);
                        if x < xc {
                            inside = !inside;
                        }
                    }
                }
                inside
            }
        }
    }
}

/// Whether `(x, y)` lies on the segment from `a` to `b` (to rounding).
fn on_segment(x: f64, y: f64, xa: f64, ya: f64, xb: f64, yb: f64) -> bool {
    let cross = (xb - xa) * (y - ya) - (yb - ya) * (x - xa);
    let len = ((xb - xa).powi(2) + (yb - ya).powi(2)).sqrt();
    cross.abs() <= 1e-12 * len.max(1.0)
        && x >= xa.min(xb) - 1e-12
        && x <= xa.max(xb) + 1e-12
        && y >= ya.min(yb) - 1e-12
        && y <= ya.max(yb) + 1e-12
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_contain_what_their_formulas_say() {
        let c = Aperture::Circle {
            radius_mm: 2.0,
            centre_x_mm: 1.0,
            centre_y_mm: -1.0,
        };
        assert!(c.contains(3.0, -1.0) && c.contains(1.0, 1.0) && !c.contains(3.01, -1.0));
        let a = Aperture::Annulus {
            inner_radius_mm: 1.0,
            outer_radius_mm: 2.0,
        };
        assert!(!a.contains(0.5, 0.0) && a.contains(1.5, 0.0) && !a.contains(0.0, 2.1));
        let r = Aperture::Rect {
            width_mm: 4.0,
            height_mm: 2.0,
        };
        assert!(r.contains(2.0, 1.0) && !r.contains(2.0, 1.01) && !r.contains(-2.1, 0.0));
        // An L-shaped polygon: the notch at (1.5, 1.5) is outside.
        let l = Aperture::Polygon {
            vertices_mm: vec![
                (0.0, 0.0),
                (2.0, 0.0),
                (2.0, 1.0),
                (1.0, 1.0),
                (1.0, 2.0),
                (0.0, 2.0),
            ],
        };
        assert!(l.contains(0.5, 1.5) && l.contains(1.5, 0.5) && !l.contains(1.5, 1.5));
        assert!(l.contains(1.0, 1.5) && !l.contains(-0.1, 0.5));
    }

    #[test]
    fn polygon_area_fraction_matches_shoelace() {
        // A triangle of area 0.5 in the unit square: the share of a fine lattice inside it.
        let t = Aperture::Polygon {
            vertices_mm: vec![(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)],
        };
        let n = 400;
        let inside = (0..n)
            .flat_map(|i| (0..n).map(move |j| (i, j)))
            .filter(|&(i, j)| {
                t.contains(
                    (i as f64 + 0.5) / n as f64 + 1e-9,
                    (j as f64 + 0.5) / n as f64,
                )
            })
            .count();
        let frac = inside as f64 / (n * n) as f64;
        assert!((frac - 0.5).abs() < 2.0 / n as f64, "{frac}");
    }

    #[test]
    fn validation() {
        assert!(Aperture::Annulus {
            inner_radius_mm: 2.0,
            outer_radius_mm: 1.0
        }
        .validate()
        .is_err());
        assert!(Aperture::Polygon {
            vertices_mm: vec![(0.0, 0.0), (1.0, 0.0)]
        }
        .validate()
        .is_err());
        assert!(Aperture::Circle {
            radius_mm: f64::NAN,
            centre_x_mm: 0.0,
            centre_y_mm: 0.0
        }
        .validate()
        .is_err());
    }
}
