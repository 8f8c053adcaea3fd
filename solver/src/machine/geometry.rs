//! The design surfaces of the engine ([`Surface`]) as part geometry for the NC writer.
//!
//! Sag and unit normal come from [`Surface::derivs`] (`n = (-z_x, -z_y, 1) / sqrt(1 + z_x^2 +
//! z_y^2)`, towards the tool). The curvature radius of the contact model is the smallest principal
//! radius, `R_e = 1 / max(|k1|, |k2|)` (do Carmo 3-3 for `k1, k2`), `+inf` where both vanish.

use super::PartGeometry;
use crate::error::Result;
use crate::surface::Surface;

impl PartGeometry for Surface {
    fn sag_mm(&self, x_mm: f64, y_mm: f64) -> Result<f64> {
        Surface::sag_mm(self, x_mm, y_mm)
    }

    fn unit_normal(&self, x_mm: f64, y_mm: f64) -> Result<[f64; 3]> {
        self.normal(x_mm, y_mm)
    }

    fn curvature_radius_mm(&self, x_mm: f64, y_mm: f64) -> Result<f64> {
        let (k1, k2) = self.principal_curvatures_per_mm(x_mm, y_mm)?;
        let k = k1.abs().max(k2.abs());
        Ok(if k > 0.0 { 1.0 / k } else { f64::INFINITY })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::{Conic, Plane};

    #[test]
    fn sphere_radius_and_normal() {
        let r = 40.0;
        let s = Surface::Conic(Conic {
            curvature_per_mm: 1.0 / r,
            conic: 0.0,
        });
        let g: &dyn PartGeometry = &s;
        let (x, y) = (6.0, -8.0);
        let z = r - (r * r - x * x - y * y).sqrt();
        assert!((g.sag_mm(x, y).unwrap() - z).abs() < 1e-12);
        let n = g.unit_normal(x, y).unwrap();
        let want = [-x / r, -y / r, (r - z) / r];
        for k in 0..3 {
            assert!((n[k] - want[k]).abs() < 1e-12);
        }
        assert!((g.curvature_radius_mm(x, y).unwrap() - r).abs() < 1e-9);
        let p = Surface::Plane(Plane {});
        assert_eq!(
            PartGeometry::curvature_radius_mm(&p, 1.0, 2.0).unwrap(),
            f64::INFINITY
        );
    }
}
