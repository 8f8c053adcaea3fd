//! Curvature-dependent influence: every dwell point gets its own Hertzian TIF from the design
//! surface's principal curvatures there (the contact radius, pressure and hence the footprint
//! change with the local curvature), applied in the tangent plane of the dwell point as in
//! [`super::surface::assemble_on_surface`] and assembled into one sparse `R`.
//!
//! The per-point models are built in parallel (rayon, collected in dwell order) and the matrix
//! is assembled by [`InfluenceMatrix::assemble_with`], so the result is identical for any thread
//! count. With a constant curvature (plane, sphere) every column equals the shift-invariant
//! assembly with the one TIF.

use super::piece::piece_rate;
use super::surface::{assemble_on_surface_swept_with, assemble_on_surface_with, TifFrame};
use super::swept::Stretches;
use crate::error::{Error, Result};
use crate::influence::operator::matrix::InfluenceMatrix;
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::surface::Surface;
use crate::tif::{HertzParams, HertzTif, InfluenceFunction};
use rayon::prelude::*;

/// The Hertz TIF of every dwell point, from the surface's principal curvatures there.
pub fn hertz_tifs_on_surface(
    surface: &Surface,
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    params: &HertzParams,
) -> Result<Vec<HertzTif>> {
    if dwell_x_mm.len() != dwell_y_mm.len() {
        return Err(Error::LengthMismatch {
            what: "dwell y_mm",
            got: dwell_y_mm.len(),
            expected: dwell_x_mm.len(),
        });
    }
    params.validate()?;
    dwell_x_mm
        .par_iter()
        .zip(dwell_y_mm.par_iter())
        .map(|(&x, &y)| {
            let (k1, k2) = surface.principal_curvatures_per_mm(x, y)?;
            HertzTif::with_curvatures(params, k1, k2)
        })
        .collect()
}

/// The largest support radius of the per-point TIFs `tifs`, mm (0 for none): the reach of one
/// assembly over all of them.
pub fn largest_support_radius_mm(tifs: &[HertzTif]) -> f64 {
    tifs.iter()
        .map(|t| t.support_radius_mm())
        .fold(0.0, f64::max)
}

/// Assembles `R` with a Hertz TIF per dwell point (see the module documentation).
#[allow(clippy::too_many_arguments)]
pub fn assemble_curvature_dependent(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    params: &HertzParams,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    let tifs = hertz_tifs_on_surface(surface, dwell_x_mm, dwell_y_mm, params)?;
    let radius = largest_support_radius_mm(&tifs);
    assemble_on_surface_with(
        surface,
        map_x_mm,
        map_y_mm,
        dwell_x_mm,
        dwell_y_mm,
        radius,
        |j, u, w| tifs.get(j).map_or(0.0, |t| t.rate_nm_per_s(u, w)),
        frame,
        observer,
    )
}

/// The swept model with a Hertz TIF per dwell point: column `j` is dwell point `j`'s own Hertz
/// TIF averaged along its stretch in its tangent frame
/// ([`super::surface::assemble_on_surface_swept_with`]); the curvature is taken at the dwell
/// point for its whole stretch.
#[allow(clippy::too_many_arguments)]
pub fn assemble_curvature_dependent_swept(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    path: &DwellPath,
    stretches: &Stretches,
    params: &HertzParams,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    let tifs = hertz_tifs_on_surface(surface, path.x_mm(), path.y_mm(), params)?;
    let radius = largest_support_radius_mm(&tifs);
    assemble_on_surface_swept_with(
        surface,
        map_x_mm,
        map_y_mm,
        path,
        stretches,
        radius,
        |j, half, u, w| tifs.get(j).map_or(0.0, |t| piece_rate(t, half, u, w)),
        frame,
        observer,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::assemble_on_surface;
    use crate::observer::Silent;
    use crate::surface::{Conic, Plane};

    fn grid(n: usize, step: f64, x0: f64) -> (Vec<f64>, Vec<f64>) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for iy in 0..n {
            for ix in 0..n {
                x.push(x0 + ix as f64 * step);
                y.push(x0 + iy as f64 * step);
            }
        }
        (x, y)
    }

    fn params() -> HertzParams {
        HertzParams {
            preston_k_mm2_per_n: 1e-6,
            ..HertzParams::default()
        }
    }

    #[test]
    fn constant_curvature_equals_shift_invariant() {
        let (mx, my) = grid(60, 0.25, -7.0);
        let dx = vec![-1.0, 0.0, 1.0, 2.0, 2.5];
        let dy = vec![0.0, 0.5, 0.5, 1.0, -1.5];
        let p = params();
        // Plane: the flat Hertz TIF in the plan, bit for bit.
        let plane = Surface::Plane(Plane {});
        let flat = HertzTif::flat(&p).unwrap();
        let a = assemble_curvature_dependent(
            &plane,
            &mx,
            &my,
            &dx,
            &dy,
            &p,
            TifFrame::MachineX,
            &Silent,
        )
        .unwrap();
        let b = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &flat, &Silent).unwrap();
        assert_eq!(a, b);
        assert!(a.nnz() > 100);
        // Convex sphere (negative curvature in the surface convention) of radius 60 mm.
        let s = Surface::Conic(Conic {
            curvature_per_mm: -1.0 / 60.0,
            conic: 0.0,
        });
        let t = HertzTif::with_part_radius(&p, 60.0).unwrap();
        let a = assemble_curvature_dependent(
            &s,
            &mx,
            &my,
            &dx,
            &dy,
            &p,
            TifFrame::PathTangent,
            &Silent,
        )
        .unwrap();
        let b = assemble_on_surface(&s, &mx, &my, &dx, &dy, &t, TifFrame::PathTangent, &Silent)
            .unwrap();
        assert_eq!(a.nnz(), b.nnz());
        for (x, y) in a.csc().values().iter().zip(b.csc().values()) {
            assert!((x - y).abs() <= 1e-12 * y.abs());
        }
    }

    #[test]
    fn varying_curvature_gives_each_column_its_own_tif() {
        // Prolate ellipsoid: curvature varies with the radius, so contact radii differ.
        let s = Surface::Conic(Conic {
            curvature_per_mm: -1.0 / 40.0,
            conic: -0.6,
        });
        let (mx, my) = grid(80, 0.25, -5.0);
        let dx = vec![-2.0, 3.0, 8.0];
        let dy = vec![-2.0, 3.0, 8.0];
        let p = params();
        let tifs = hertz_tifs_on_surface(&s, &dx, &dy, &p).unwrap();
        assert!(tifs[0].contact_radius_mm() != tifs[2].contact_radius_mm());
        let a =
            assemble_curvature_dependent(&s, &mx, &my, &dx, &dy, &p, TifFrame::MachineX, &Silent)
                .unwrap();
        // Independent: each column assembled alone with its own TIF.
        for j in 0..3 {
            let (k1, k2) = s.principal_curvatures_per_mm(dx[j], dy[j]).unwrap();
            let t = HertzTif::with_curvatures(&p, k1, k2).unwrap();
            let one = assemble_on_surface(
                &s,
                &mx,
                &my,
                &dx[j..=j],
                &dy[j..=j],
                &t,
                TifFrame::MachineX,
                &Silent,
            )
            .unwrap();
            let col = a.csc().col(j);
            let want = one.csc().col(0);
            assert_eq!(col.row_indices(), want.row_indices());
            assert_eq!(col.values(), want.values());
            assert!(!col.values().is_empty());
        }
    }

    /// The swept model with a Hertz TIF per dwell point: on a plane in the machine-x frame the
    /// plan's swept assembly of the flat Hertz TIF bit for bit; on a sphere (one curvature) the
    /// tangent-frame swept assembly of the sphere's Hertz TIF; on an ellipsoid each column its
    /// own point's TIF swept (assembled alone).
    #[test]
    fn swept_columns_carry_each_points_own_tif() {
        let (mx, my) = grid(50, 0.25, -6.0);
        let path = DwellPath::new(
            vec![-2.0, -1.0, 0.0, 1.0, 2.0, 2.0, 1.0, 0.0],
            vec![0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
        )
        .unwrap();
        let stretches = Stretches::of_path(&path, 0.05).unwrap();
        let p = params();
        let swept = |surface: &Surface, frame| {
            assemble_curvature_dependent_swept(
                surface, &mx, &my, &path, &stretches, &p, frame, &Silent,
            )
            .unwrap()
        };
        let plane = Surface::Plane(Plane {});
        let a = swept(&plane, TifFrame::MachineX);
        let flat = HertzTif::flat(&p).unwrap();
        let b =
            crate::influence::assemble_swept(&mx, &my, &path, &stretches, &flat, &Silent).unwrap();
        assert_eq!(a, b);
        let sphere = Surface::Conic(Conic {
            curvature_per_mm: -1.0 / 60.0,
            conic: 0.0,
        });
        let a = swept(&sphere, TifFrame::PathTangent);
        let t = HertzTif::with_part_radius(&p, 60.0).unwrap();
        let b = crate::influence::assemble_on_surface_swept(
            &sphere,
            &mx,
            &my,
            &path,
            &stretches,
            &t,
            TifFrame::PathTangent,
            &Silent,
        )
        .unwrap();
        assert_eq!(a.nnz(), b.nnz());
        for (x, y) in a.csc().values().iter().zip(b.csc().values()) {
            assert!((x - y).abs() <= 1e-12 * y.abs());
        }
        let ellipsoid = Surface::Conic(Conic {
            curvature_per_mm: -1.0 / 40.0,
            conic: -0.6,
        });
        let a = swept(&ellipsoid, TifFrame::MachineX);
        let tifs = hertz_tifs_on_surface(&ellipsoid, path.x_mm(), path.y_mm(), &p).unwrap();
        assert!(tifs[2].contact_radius_mm() != tifs[4].contact_radius_mm());
        for j in [0, 2, 5] {
            let one = crate::influence::model::surface::assemble_on_surface_swept_with(
                &ellipsoid,
                &mx,
                &my,
                &path,
                &stretches,
                tifs[j].support_radius_mm(),
                |k, half, u, w| {
                    if k == j {
                        piece_rate(&tifs[j], half, u, w)
                    } else {
                        0.0
                    }
                },
                TifFrame::MachineX,
                &Silent,
            )
            .unwrap();
            let mut unit = vec![0.0; path.len()];
            unit[j] = 1.0;
            let (got, want) = (a.removal_nm(&unit).unwrap(), one.removal_nm(&unit).unwrap());
            assert!(want.iter().any(|v| *v > 0.0));
            assert_eq!(got, want, "column {j}");
        }
    }
}
