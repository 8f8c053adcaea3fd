//! Influence matrix on a curved part: the TIF is applied in the tangent plane of the design
//! surface at each dwell point, and removal is along the surface normal.
//!
//! For dwell point `S_j = (X_j, Y_j, f(X_j, Y_j))` with unit normal `n_j` and in-plane unit axes
//! `(t_j, b_j = n_j x t_j)`, a measurement point `P_i = (x_i, y_i, f(x_i, y_i))` receives
//! `R[i, j] = tif((P_i - S_j) . t_j, (P_i - S_j) . b_j)`. On the plane `z = 0` with
//! [`TifFrame::MachineX`] this is bit for bit [`InfluenceMatrix::assemble`].

use super::InfluenceMatrix;
use crate::error::{Error, Result};
use crate::observer::Observer;
use crate::surface::Surface;
use crate::tif::InfluenceFunction;
use serde::{Deserialize, Serialize};

/// Plan-view search radius as a multiple of the TIF support radius: a point within the support
/// in the tangent plane can lie slightly farther in plan where the surface curves away from the
/// tangent plane (by `sqrt(1 + (a / 2 rho)^2)` for support `a` and curvature radius `rho`).
pub const SEARCH_RADIUS_FACTOR: f64 = 1.1;

/// How the TIF's own x axis is oriented in the tangent plane of each dwell point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum TifFrame {
    /// The TIF x axis follows the path tangent.
    ///
    /// The TIF x axis is the path tangent (central difference of the neighbouring dwell points,
    /// projected into the tangent plane) and y is `normal x tangent`: the tool footprint turns with
    /// the path. Falls back to [`TifFrame::MachineX`] where the path has no direction.
    #[default]
    PathTangent,
    /// The TIF x axis is the machine x axis projected into the tangent plane: the footprint keeps
    /// its orientation as on a flat part (exactly the plan assembly on a plane).
    MachineX,
}

#[inline]
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `v` projected into the plane normal to `n`, normalised; `None` if (nearly) parallel to `n`.
fn tangent_from(v: [f64; 3], n: [f64; 3]) -> Option<[f64; 3]> {
    let a = dot(v, n);
    let t = [v[0] - a * n[0], v[1] - a * n[1], v[2] - a * n[2]];
    let len = dot(t, t).sqrt();
    let vlen = dot(v, v).sqrt();
    if !(len > 1e-12 * vlen && len > 0.0) {
        return None;
    }
    Some([t[0] / len, t[1] / len, t[2] / len])
}

/// Assembles the influence matrix on a curved design surface (see the module documentation).
///
/// Errors: a map or dwell point outside the surface's domain, length mismatches, a TIF without a
/// positive support radius.
#[allow(clippy::too_many_arguments)]
pub fn assemble_on_surface<T: InfluenceFunction + ?Sized>(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    tif: &T,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    assemble_on_surface_with(
        surface,
        map_x_mm,
        map_y_mm,
        dwell_x_mm,
        dwell_y_mm,
        tif.support_radius_mm(),
        |_j, u, w| tif.rate_nm_per_s(u, w),
        frame,
        observer,
    )
}

/// As [`assemble_on_surface`] with a per-dwell-point kernel `rate(j, u_mm, w_mm)` (nm/s) of the
/// tangent-plane offset `(u, w)`, zero beyond `support_radius_mm` (the largest over all `j`).
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
pub fn assemble_on_surface_with<K>(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    support_radius_mm: f64,
    kernel: K,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix>
where
    K: Fn(usize, f64, f64) -> f64 + Sync,
{
    if map_x_mm.len() != map_y_mm.len() {
        return Err(Error::LengthMismatch {
            what: "map y_mm",
            got: map_y_mm.len(),
            expected: map_x_mm.len(),
        });
    }
    if dwell_x_mm.len() != dwell_y_mm.len() {
        return Err(Error::LengthMismatch {
            what: "dwell y_mm",
            got: dwell_y_mm.len(),
            expected: dwell_x_mm.len(),
        });
    }
    let map_z: Vec<f64> = map_x_mm
        .iter()
        .zip(map_y_mm)
        .map(|(&x, &y)| surface.sag_mm(x, y))
        .collect::<Result<_>>()?;
    let n = dwell_x_mm.len();
    let mut origin = Vec::with_capacity(n);
    let mut normal = Vec::with_capacity(n);
    for (&x, &y) in dwell_x_mm.iter().zip(dwell_y_mm) {
        let d = surface.derivs(x, y)?;
        origin.push([x, y, d.z]);
        normal.push(d.normal());
    }
    let mut axes = Vec::with_capacity(n);
    for (j, &nj) in normal.iter().enumerate() {
        let path_dir = match frame {
            TifFrame::MachineX => None,
            TifFrame::PathTangent if n >= 2 => {
                let (a, b) = (j.saturating_sub(1), (j + 1).min(n - 1));
                let v = [
                    origin[b][0] - origin[a][0],
                    origin[b][1] - origin[a][1],
                    origin[b][2] - origin[a][2],
                ];
                tangent_from(v, nj)
            }
            TifFrame::PathTangent => None,
        };
        let t = match path_dir {
            Some(t) => t,
            None => tangent_from([1.0, 0.0, 0.0], nj)
                .or_else(|| tangent_from([0.0, 1.0, 0.0], nj))
                .ok_or_else(|| Error::Geometry(format!("dwell point {j} has no tangent plane")))?,
        };
        axes.push((t, cross(nj, t)));
    }
    let radius = support_radius_mm * SEARCH_RADIUS_FACTOR;
    InfluenceMatrix::assemble_with(
        map_x_mm,
        map_y_mm,
        dwell_x_mm,
        dwell_y_mm,
        radius,
        |j, i, dx, dy| {
            let (Some(&(t, b)), Some(o), Some(&zi)) = (axes.get(j), origin.get(j), map_z.get(i))
            else {
                return 0.0;
            };
            let dz = zi - o[2];
            let u = dx * t[0] + dy * t[1] + dz * t[2];
            let w = dx * b[0] + dy * b[1] + dz * b[2];
            kernel(j, u, w)
        },
        observer,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::surface::{Conic, Plane};
    use crate::tif::{GaussianTif, GridTif};

    fn grid(n: usize, step: f64) -> (Vec<f64>, Vec<f64>) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for iy in 0..n {
            for ix in 0..n {
                x.push(ix as f64 * step - 0.37);
                y.push(iy as f64 * step + 0.11);
            }
        }
        (x, y)
    }

    fn asymmetric_tif() -> GridTif {
        let rates: Vec<f64> = (0..35)
            .map(|k| 1.0 + (k as f64 * 0.77).sin().abs() * k as f64)
            .collect();
        GridTif::new(-1.9, -1.3, 0.6, 0.5, 7, 5, rates).unwrap()
    }

    #[test]
    fn plane_is_bit_identical_to_plan_assembly() {
        let (mx, my) = grid(40, 0.3);
        // A raster with both directions and a diagonal move.
        let dx = vec![1.0, 2.0, 3.0, 4.0, 4.0, 3.0, 2.0, 1.0, 2.5, 7.0];
        let dy = vec![1.0, 1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 2.0, 5.5, 9.0];
        let plane = Surface::Plane(Plane {});
        let tif = asymmetric_tif();
        let flat = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        let curved = assemble_on_surface(
            &plane,
            &mx,
            &my,
            &dx,
            &dy,
            &tif,
            TifFrame::MachineX,
            &Silent,
        )
        .unwrap();
        assert_eq!(flat, curved);
        // Rotationally symmetric TIF, path tangent frame, axis-aligned path (+x then -x).
        let g = GaussianTif::new(0.8, 3.0, 2.4).unwrap();
        let (px, py) = (&dx[..8], &dy[..4]);
        let py: Vec<f64> = py.iter().chain(py.iter()).copied().collect();
        let flat = InfluenceMatrix::assemble(&mx, &my, px, &py, &g, &Silent).unwrap();
        let curved = assemble_on_surface(
            &plane,
            &mx,
            &my,
            px,
            &py,
            &g,
            TifFrame::PathTangent,
            &Silent,
        )
        .unwrap();
        assert_eq!(flat, curved);
        // A grid TIF on a +x path in the path frame is the plan result too.
        let flat = InfluenceMatrix::assemble(&mx, &my, &dx[..4], &dy[..4], &tif, &Silent).unwrap();
        let curved = assemble_on_surface(
            &plane,
            &mx,
            &my,
            &dx[..4],
            &dy[..4],
            &tif,
            TifFrame::PathTangent,
            &Silent,
        )
        .unwrap();
        assert_eq!(flat, curved);
    }

    #[test]
    fn sphere_uses_tangent_plane_offsets() {
        // On a sphere the tangent-plane distance of a map point from a dwell point is
        // sqrt(|P - S|^2 - ((P - S) . n)^2); a Gaussian TIF must see exactly that radius.
        let r = 60.0;
        let s = Surface::Conic(Conic {
            curvature_per_mm: 1.0 / r,
            conic: 0.0,
        });
        let (mx, my) = grid(30, 0.5);
        let dx = vec![5.0, 6.0, 7.0];
        let dy = vec![4.0, 5.0, 6.5];
        let g = GaussianTif::new(1.0, 2.0, 3.0).unwrap();
        let m = assemble_on_surface(&s, &mx, &my, &dx, &dy, &g, TifFrame::PathTangent, &Silent)
            .unwrap();
        let mut count = 0;
        for j in 0..3 {
            let sj = [dx[j], dy[j], s.sag_mm(dx[j], dy[j]).unwrap()];
            let nj = s.normal(dx[j], dy[j]).unwrap();
            for i in 0..mx.len() {
                let p = [mx[i], my[i], s.sag_mm(mx[i], my[i]).unwrap()];
                let d = [p[0] - sj[0], p[1] - sj[1], p[2] - sj[2]];
                let a = dot(d, nj);
                let rho2 = dot(d, d) - a * a;
                let want = if rho2 > 9.0 {
                    0.0
                } else {
                    2.0 * (-rho2 / 2.0).exp()
                };
                let got = m
                    .csc()
                    .get_entry(i, j)
                    .map(|e| e.into_value())
                    .unwrap_or(0.0);
                if (rho2 - 9.0).abs() > 1e-9 {
                    assert!(
                        (got - want).abs() < 1e-12,
                        "i={i} j={j} got {got} want {want}"
                    );
                }
                count += usize::from(want != 0.0);
            }
        }
        assert!(count > 100);
    }
}
