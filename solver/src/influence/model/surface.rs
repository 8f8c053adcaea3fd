//! Influence matrix on a curved part: the TIF is applied in the tangent plane of the design
//! surface at each dwell point, and removal is along the surface normal.
//!
//! For dwell point `S_j = (X_j, Y_j, f(X_j, Y_j))` with unit normal `n_j` and in-plane unit axes
//! `(t_j, b_j = n_j x t_j)`, a measurement point `P_i = (x_i, y_i, f(x_i, y_i))` receives
//! `R[i, j] = tif((P_i - S_j) . t_j, (P_i - S_j) . b_j)`. On the plane `z = 0` with
//! [`TifFrame::MachineX`] this is bit for bit [`InfluenceMatrix::assemble`].

use super::piece::piece_rate;
use super::swept::{swept_sum, Stretches};
use crate::error::{Error, Result};
use crate::influence::operator::matrix::InfluenceMatrix;
use crate::observer::Observer;
use crate::path::DwellPath;
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

/// Each dwell point's surface point `S_j` and tangent-plane axes `(t_j, b_j)`, with `t_j` as
/// `frame` orients it (module documentation).
#[allow(clippy::type_complexity)]
fn dwell_frames(
    surface: &Surface,
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    frame: TifFrame,
) -> Result<(Vec<[f64; 3]>, Vec<([f64; 3], [f64; 3])>)> {
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
    Ok((origin, axes))
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
    let (origin, axes) = dwell_frames(surface, dwell_x_mm, dwell_y_mm, frame)?;
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

/// The swept model on a curved part: column `j` is the TIF averaged along dwell point `j`'s
/// stretch ([`Stretches`]), each sample and the piece it stands for ([`Stretches::pieces_of`])
/// placed in `j`'s tangent plane (their plan offsets lifted onto the plane along z) and the TIF
/// applied in `j`'s frame, `R[i, j] = Σ_s w_s piece(h_s; u_ij - u_s, v_ij - v_s)` with
/// `(u_ij, v_ij)` as in [`assemble_on_surface`], `(u_s, v_s)` the sample's and `h_s` its piece's
/// half in tangent-plane coordinates, and `piece` the flat part's rule ([`piece_rate`]: a TIF
/// cut where its rate is not zero integrated exactly where the cut circle crosses a piece).
/// Over a stretch (half a segment either side) the frame turns by `ds / rho` for curvature
/// radius `rho`, which this neglects. On a plane with [`TifFrame::MachineX`] it is
/// [`super::assemble_swept`] bit for bit (the same sum, [`swept_sum`]).
#[allow(clippy::too_many_arguments)]
pub fn assemble_on_surface_swept<T: InfluenceFunction + ?Sized>(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    path: &DwellPath,
    stretches: &Stretches,
    tif: &T,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    assemble_on_surface_swept_with(
        surface,
        map_x_mm,
        map_y_mm,
        path,
        stretches,
        tif.support_radius_mm(),
        |_j, half, u, w| piece_rate(tif, half, u, w),
        frame,
        observer,
    )
}

/// A plan offset `d` lifted along z onto the plane through the origin normal to `t x b`, in the
/// plane's coordinates `(d . t, d . b)`: a stretch's samples and pieces in a dwell point's
/// tangent frame.
#[inline]
fn in_tangent_plane(d: [f64; 2], (t, b): ([f64; 3], [f64; 3])) -> [f64; 2] {
    let normal = cross(t, b);
    let dz = if normal[2] != 0.0 {
        -(normal[0] * d[0] + normal[1] * d[1]) / normal[2]
    } else {
        0.0
    };
    let d = [d[0], d[1], dz];
    [dot(d, t), dot(d, b)]
}

/// As [`assemble_on_surface_swept`] with a per-dwell-point kernel `piece(j, h, u_mm, w_mm)`
/// (nm/s): column `j`'s TIF at the tangent-plane offset `(u, w)` from the midpoint of a piece of
/// half `h` (tangent-plane coordinates, mm), swept along it ([`piece_rate`] of that TIF), zero
/// beyond `support_radius_mm` (the largest over all `j`) plus the piece's half:
/// `R[i, j] = sum_s w_s piece(j, h_s, u_ij - u_s, v_ij - v_s)`.
#[allow(clippy::too_many_arguments)]
pub fn assemble_on_surface_swept_with<K>(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    path: &DwellPath,
    stretches: &Stretches,
    support_radius_mm: f64,
    piece: K,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix>
where
    K: Fn(usize, [f64; 2], f64, f64) -> f64 + Sync,
{
    if stretches.len() != path.len() {
        return Err(Error::LengthMismatch {
            what: "stretches",
            got: stretches.len(),
            expected: path.len(),
        });
    }
    let (_, axes) = dwell_frames(surface, path.x_mm(), path.y_mm(), frame)?;
    let mut offsets = Vec::with_capacity(path.len() + 1);
    let mut local: Vec<[f64; 3]> = Vec::new();
    let mut halves: Vec<[f64; 2]> = Vec::new();
    offsets.push(0);
    for (j, &tb) in axes.iter().enumerate() {
        for (s, &h) in stretches.of(j).iter().zip(stretches.pieces_of(j)) {
            let [u, w] = in_tangent_plane([s[0], s[1]], tb);
            local.push([u, w, s[2]]);
            halves.push(in_tangent_plane(h, tb));
        }
        offsets.push(local.len());
    }
    // The pieces' ends: a piece whose TIF is cut is integrated up to them.
    let reach = local
        .iter()
        .zip(&halves)
        .map(|(l, h)| l[0].hypot(l[1]) + h[0].hypot(h[1]))
        .fold(0.0, f64::max);
    assemble_on_surface_with(
        surface,
        map_x_mm,
        map_y_mm,
        path.x_mm(),
        path.y_mm(),
        support_radius_mm + reach,
        |j, u, w| {
            let (from, to) = (offsets[j], offsets[j + 1]);
            swept_sum(&local[from..to], &halves[from..to], u, w, |h, a, b| {
                piece(j, h, a, b)
            })
        },
        frame,
        observer,
    )
}

/// The removal of dwell times `dwell_s` at points on a curved part without assembling `R` (a
/// program's contact motion: tens of thousands of samples used once), for `radii_mm.len()`
/// kernels in one traversal: `h_s,i = sum_k t_k piece(s, k, h_k, u_ik, w_ik)` over the points
/// `k` with `u_ik^2 + w_ik^2 <= (radii_mm[s] + |h|_max)^2`, `(u_ik, w_ik)` the offset of map
/// point `i` in point `k`'s tangent frame as in [`assemble_on_surface`] (each sample its own
/// frame, oriented by `frame`: along the motion for [`TifFrame::PathTangent`]) and `h_k` the
/// half of the piece of motion sample `k` stands for, `half_mm[k]` in plan lifted into that
/// frame as a swept column's pieces are ([`assemble_on_surface_swept_with`]; zero, points, when
/// `half_mm` is empty). `piece(s, k, h, u, w)` is kernel `s`'s TIF for sample `k` at `(u, w)`
/// along the piece of half `h` ([`piece_rate`]), `radii_mm[s]` its support radius (a TIF cut
/// where its rate is not zero reaches the piece's half farther; the rate is zero beyond the
/// support, so the longest half is added to every radius). On a plane with
/// [`TifFrame::MachineX`] it is [`crate::simulate::direct::piece_removals_nm`] to rounding.
#[allow(clippy::too_many_arguments)]
pub fn removals_on_surface_with<K>(
    surface: &Surface,
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    half_mm: &[[f64; 2]],
    dwell_s: &[f64],
    radii_mm: &[f64],
    piece: K,
    frame: TifFrame,
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>>
where
    K: Fn(usize, usize, [f64; 2], f64, f64) -> f64 + Sync,
{
    super::point::check_lengths(
        map_x_mm.len(),
        dwell_x_mm.len(),
        map_y_mm,
        dwell_y_mm,
        dwell_s,
    )?;
    if !half_mm.is_empty() && half_mm.len() != dwell_x_mm.len() {
        return Err(Error::LengthMismatch {
            what: "dwell half_mm",
            got: half_mm.len(),
            expected: dwell_x_mm.len(),
        });
    }
    let radius = radii_mm.iter().copied().fold(0.0, f64::max);
    if !(radius.is_finite() && radius > 0.0) || radii_mm.iter().any(|r| !(*r > 0.0)) {
        return Err(Error::invalid(
            "TIF support radius",
            format!("must be positive and finite, got {radius} mm"),
        ));
    }
    let map_z: Vec<f64> = map_x_mm
        .iter()
        .zip(map_y_mm)
        .map(|(&x, &y)| surface.sag_mm(x, y))
        .collect::<Result<_>>()?;
    let (origin, axes) = dwell_frames(surface, dwell_x_mm, dwell_y_mm, frame)?;
    let halves: Vec<[f64; 2]> = half_mm
        .iter()
        .zip(&axes)
        .map(|(&h, &tb)| in_tangent_plane(h, tb))
        .collect();
    let longest = halves.iter().map(|h| h[0].hypot(h[1])).fold(0.0, f64::max);
    let r2: Vec<f64> = radii_mm.iter().map(|r| (r + longest).powi(2)).collect();
    let sums = super::point::sum_near(
        map_x_mm,
        map_y_mm,
        dwell_x_mm,
        dwell_y_mm,
        radii_mm.len(),
        (radius + longest) * SEARCH_RADIUS_FACTOR,
        observer,
        |i, k, dx, dy, sums| {
            let (t, b) = axes[k];
            let dz = map_z[i] - origin[k][2];
            let u = dx * t[0] + dy * t[1] + dz * t[2];
            let w = dx * b[0] + dy * b[1] + dz * b[2];
            let d2 = u * u + w * w;
            let half = halves.get(k).copied().unwrap_or([0.0, 0.0]);
            for (s, (sum, r2)) in sums.iter_mut().zip(&r2).enumerate() {
                if d2 <= *r2 {
                    *sum += piece(s, k, half, u, w) * dwell_s[k];
                }
            }
        },
    );
    crate::observer::check_cancelled(observer)?;
    Ok(sums)
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

    /// A serpentine raster: 1 mm along x, rows 1 mm apart (row ends with L-shaped stretches).
    fn serpentine(rows: usize, per_row: usize) -> DwellPath {
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for r in 0..rows {
            for k in 0..per_row {
                let i = if r % 2 == 0 { k } else { per_row - 1 - k };
                x.push(2.0 + i as f64);
                y.push(2.0 + r as f64);
            }
        }
        DwellPath::new(x, y).unwrap()
    }

    #[test]
    fn swept_on_a_plane_is_the_plan_swept_assembly() {
        let (mx, my) = grid(40, 0.3);
        let path = serpentine(4, 8);
        let stretches = Stretches::of_path(&path, 0.05).unwrap();
        let plane = Surface::Plane(Plane {});
        let on_plane = |tif: &dyn InfluenceFunction| {
            let flat =
                super::super::swept::assemble_swept(&mx, &my, &path, &stretches, tif, &Silent)
                    .unwrap();
            let curved = assemble_on_surface_swept(
                &plane,
                &mx,
                &my,
                &path,
                &stretches,
                tif,
                TifFrame::MachineX,
                &Silent,
            )
            .unwrap();
            assert_eq!(flat, curved);
        };
        on_plane(&asymmetric_tif());
        // A Gaussian cut within the map, its pieces the circle crosses integrated along them: the
        // same rule in the tangent frame.
        let cut = GaussianTif::new(0.8, 3.0, 1.3).unwrap();
        let crossed = (0..path.len()).any(|j| {
            mx.iter().zip(&my).any(|(&x, &y)| {
                let (dx, dy) = (x - path.x_mm()[j], y - path.y_mm()[j]);
                let midpoints = super::super::swept::swept_rate(&cut, stretches.of(j), &[], dx, dy);
                stretches.rate_nm_per_s(j, &cut, dx, dy) != midpoints
            })
        });
        assert!(crossed, "no piece crosses the cut");
        on_plane(&cut);
    }

    /// On a sphere of radius 500 mm each swept column is, to within the frame's turn over half a
    /// stretch (1e-3 rad), the average of the tangent-frame columns of dwell points placed at its
    /// stretch's samples (an independent sum of [`assemble_on_surface`] columns), and differs
    /// from the point column by far more.
    #[test]
    fn swept_on_a_sphere_averages_the_tangent_frame_columns_along_the_stretch() {
        /// Agreement relative to the largest entry (the frame's turn moves offsets by
        /// about 3e-3 mm at the TIF's reach).
        const FRAME_TOL: f64 = 5e-3;
        let (mx, my) = grid(40, 0.3);
        let path = serpentine(4, 8);
        let stretches = Stretches::of_path(&path, 0.05).unwrap();
        let tif = GaussianTif::new(1.0, 3.0, 3.0).unwrap();
        let sphere = Surface::Conic(Conic {
            curvature_per_mm: 1.0 / 500.0,
            conic: 0.0,
        });
        let frame = TifFrame::MachineX;
        let swept =
            assemble_on_surface_swept(&sphere, &mx, &my, &path, &stretches, &tif, frame, &Silent)
                .unwrap();
        let point = assemble_on_surface(
            &sphere,
            &mx,
            &my,
            path.x_mm(),
            path.y_mm(),
            &tif,
            frame,
            &Silent,
        )
        .unwrap();
        let (m, n) = (mx.len(), path.len());
        let column = |r: &InfluenceMatrix, j: usize| {
            let mut t = vec![0.0; r.ncols()];
            t[j] = 1.0;
            r.removal_nm(&t).unwrap()
        };
        let mut worst_point = 0.0f64;
        for j in 0..n {
            let samples = stretches.of(j);
            let (sx, sy): (Vec<f64>, Vec<f64>) = samples
                .iter()
                .map(|s| (path.x_mm()[j] + s[0], path.y_mm()[j] + s[1]))
                .unzip();
            let at_samples =
                assemble_on_surface(&sphere, &mx, &my, &sx, &sy, &tif, frame, &Silent).unwrap();
            let weights: Vec<f64> = samples.iter().map(|s| s[2]).collect();
            let want = at_samples.removal_nm(&weights).unwrap();
            let got = column(&swept, j);
            let peak = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            for i in 0..m {
                assert!(
                    (got[i] - want[i]).abs() <= FRAME_TOL * peak,
                    "column {j}, row {i}: {} vs {}",
                    got[i],
                    want[i]
                );
            }
            let p = column(&point, j);
            for i in 0..m {
                worst_point = worst_point.max((p[i] - want[i]).abs() / peak);
            }
        }
        assert!(worst_point > 4.0 * FRAME_TOL, "{worst_point}");
    }

    /// Direct sum against the assembled product: the same terms in another order.
    const DIRECT_VS_ASSEMBLED_RTOL: f64 = 1e-12;

    fn assert_close(got: &[f64], want: &[f64], what: &str) {
        let scale = want.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
        assert!(scale > 0.0, "{what}: nothing removed");
        for (i, (a, b)) in got.iter().zip(want).enumerate() {
            assert!(
                (a - b).abs() <= DIRECT_VS_ASSEMBLED_RTOL * scale,
                "{what}, point {i}: direct {a} against assembled {b}"
            );
        }
    }

    /// The direct tangent-frame sum of a motion is the assembled tangent-frame `R t` of its
    /// samples on a sphere and on an ellipsoid (each sample its own frame, the path frame from
    /// its neighbours), for an asymmetric grid TIF in both frames; several kernels in one pass
    /// are each their own sum (on a plane with the machine-x frame it is the plan's direct sum:
    /// [`crate::simulate::direct`]'s tests).
    #[test]
    fn direct_sum_on_a_surface_is_the_assembled_product() {
        let (mx, my) = grid(36, 0.3);
        // A curved motion crossing the map: samples 0.07 mm apart.
        let (sx, sy): (Vec<f64>, Vec<f64>) = (0..160)
            .map(|k| {
                let a = k as f64 * 0.07;
                (0.5 + a, 3.0 + 2.0 * (0.4 * a).sin())
            })
            .unzip();
        let t: Vec<f64> = (0..sx.len())
            .map(|k| 0.2 + 0.1 * (k as f64 * 0.37).cos().abs())
            .collect();
        let grid_tif = asymmetric_tif();
        let gauss = GaussianTif::new(0.9, 4.0, 2.7).unwrap();
        for surface in [
            Surface::Conic(Conic {
                curvature_per_mm: 1.0 / 40.0,
                conic: 0.0,
            }),
            Surface::Conic(Conic {
                curvature_per_mm: -1.0 / 35.0,
                conic: -0.5,
            }),
        ] {
            for frame in [TifFrame::PathTangent, TifFrame::MachineX] {
                let r =
                    assemble_on_surface(&surface, &mx, &my, &sx, &sy, &grid_tif, frame, &Silent)
                        .unwrap();
                let want = r.removal_nm(&t).unwrap();
                let got = removals_on_surface_with(
                    &surface,
                    &mx,
                    &my,
                    &sx,
                    &sy,
                    &[],
                    &t,
                    &[grid_tif.support_radius_mm(), gauss.support_radius_mm()],
                    |s, _, _, u, w| match s {
                        0 => grid_tif.rate_nm_per_s(u, w),
                        _ => gauss.rate_nm_per_s(u, w),
                    },
                    frame,
                    &Silent,
                )
                .unwrap();
                assert_close(&got[0], &want, "grid TIF");
                let r = assemble_on_surface(&surface, &mx, &my, &sx, &sy, &gauss, frame, &Silent)
                    .unwrap();
                assert_close(&got[1], &r.removal_nm(&t).unwrap(), "Gaussian");
            }
        }
    }
}
