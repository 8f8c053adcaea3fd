//! Contact-probe radius compensation.
//!
//! A contact probe records the centre `q` of its spherical tip. The tip touches the surface at
//! `s` where the surface normal passes through the centre, `q = s + r n(s)`, so `s` is the foot
//! of the closest point of the surface to `q` (for `r` smaller than the concave radii of
//! curvature) and the surface point is `q - r n(s)`. The foot is found by the safeguarded Newton
//! iteration of [`crate::surface::closest`] on the design (or fitted) surface.

use crate::error::{Error, Result};
use crate::surface::Surface;
use rayon::prelude::*;

/// Surface points `q - r n(s)` (mm) for probe tip centres `q` (mm) of a probe of radius
/// `probe_radius_mm`, with `s` the closest point of `surface` to `q`. The tip centres must lie on
/// the normal (+z) side of the surface, where the probe approaches from.
pub fn compensate_probe(
    surface: &Surface,
    tip_centres_mm: &[[f64; 3]],
    probe_radius_mm: f64,
) -> Result<Vec<[f64; 3]>> {
    if !(probe_radius_mm.is_finite() && probe_radius_mm >= 0.0) {
        return Err(Error::invalid(
            "probe_radius_mm",
            format!("must be zero or positive, got {probe_radius_mm}"),
        ));
    }
    tip_centres_mm
        .par_iter()
        .map(|&q| {
            let cp = surface.closest_point(q)?;
            let n = cp.normal;
            Ok([
                q[0] - probe_radius_mm * n[0],
                q[1] - probe_radius_mm * n[1],
                q[2] - probe_radius_mm * n[2],
            ])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::Conic;

    #[test]
    fn zero_radius_is_identity_and_negative_rejected() {
        let s = Surface::Conic(Conic {
            curvature_per_mm: 0.01,
            conic: 0.0,
        });
        let q = [[1.0, 2.0, 3.0]];
        let p = compensate_probe(&s, &q, 0.0).unwrap();
        assert_eq!(p, q.to_vec());
        assert!(compensate_probe(&s, &q, -1.0).is_err());
    }
}
