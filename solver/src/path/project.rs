//! Projection of a plan path onto a design surface: `z`, unit 3-D tangents and 3-D `ds`.
//!
//! Point `j` goes to `(x_j, y_j, f(x_j, y_j))`. The tangent is the plan direction
//! `d = p_{j+1} - p_{j-1}` (one-sided at the ends) lifted onto the tangent plane,
//! `t = (d_x, d_y, f_x d_x + f_y d_y) / |.|`; on a flat part (no surface) `z = 0` and
//! `t = (d_x, d_y, 0) / |d|`. `ds_j` follows the contract of [`DwellPath::ds_mm`] with 3-D
//! distances between consecutive projected points.

use super::DwellPath;
use crate::error::Result;
use crate::surface::Surface;
use rayon::prelude::*;

/// A path on the part: points, unit tangents and path-length shares, all in mm.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ProjectedPath {
    /// x, mm.
    pub x_mm: Vec<f64>,
    /// y, mm.
    pub y_mm: Vec<f64>,
    /// z (surface sag, 0 on a flat part), mm.
    pub z_mm: Vec<f64>,
    /// Unit tangent, x component.
    pub tx: Vec<f64>,
    /// Unit tangent, y component.
    pub ty: Vec<f64>,
    /// Unit tangent, z component.
    pub tz: Vec<f64>,
    /// Path length each point stands for (3-D), mm.
    pub ds_mm: Vec<f64>,
}

impl ProjectedPath {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.x_mm.len()
    }

    /// True when there are no points.
    pub fn is_empty(&self) -> bool {
        self.x_mm.is_empty()
    }

    /// Column names of the path CSV, in order.
    pub const HEADER: [&'static str; 7] = ["x_mm", "y_mm", "z_mm", "tx", "ty", "tz", "ds_mm"];

    /// The columns in [`ProjectedPath::HEADER`] order.
    pub fn columns(&self) -> [&[f64]; 7] {
        [
            &self.x_mm,
            &self.y_mm,
            &self.z_mm,
            &self.tx,
            &self.ty,
            &self.tz,
            &self.ds_mm,
        ]
    }
}

/// Projects `path` onto `surface` (or keeps it flat at `z = 0` with `None`); errors where a point
/// lies outside the surface's domain.
#[allow(clippy::needless_range_loop)]
pub fn project(path: &DwellPath, surface: Option<&Surface>) -> Result<ProjectedPath> {
    let (x, y) = (path.x_mm(), path.y_mm());
    let n = path.len();
    let derivs: Vec<(f64, f64, f64)> = match surface {
        None => vec![(0.0, 0.0, 0.0); n],
        Some(s) => x
            .par_iter()
            .zip(y.par_iter())
            .map(|(&xi, &yi)| s.derivs(xi, yi).map(|d| (d.z, d.zx, d.zy)))
            .collect::<Result<_>>()?,
    };
    let mut out = ProjectedPath {
        x_mm: x.to_vec(),
        y_mm: y.to_vec(),
        z_mm: derivs.iter().map(|d| d.0).collect(),
        tx: vec![0.0; n],
        ty: vec![0.0; n],
        tz: vec![0.0; n],
        ds_mm: vec![0.0; n],
    };
    for j in 0..n {
        let (a, b) = (j.saturating_sub(1), (j + 1).min(n - 1));
        let (dx, dy) = (x[b] - x[a], y[b] - y[a]);
        let (_, fx, fy) = derivs[j];
        let t = [dx, dy, fx * dx + fy * dy];
        let len = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
        if len > 0.0 {
            out.tx[j] = t[0] / len;
            out.ty[j] = t[1] / len;
            out.tz[j] = t[2] / len;
        }
    }
    let seg: Vec<f64> = (1..n)
        .map(|j| {
            let d = [
                x[j] - x[j - 1],
                y[j] - y[j - 1],
                out.z_mm[j] - out.z_mm[j - 1],
            ];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        })
        .collect();
    if n >= 2 {
        for (j, d) in out.ds_mm.iter_mut().enumerate() {
            *d = if j == 0 {
                seg[0]
            } else if j == n - 1 {
                seg[n - 2]
            } else {
                0.5 * (seg[j - 1] + seg[j])
            };
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::Conic;

    #[test]
    fn flat_and_sphere_projection() {
        let p = DwellPath::new(vec![0.0, 1.0, 2.0], vec![0.0, 0.0, 1.0]).unwrap();
        let f = project(&p, None).unwrap();
        assert_eq!(f.z_mm, vec![0.0; 3]);
        assert_eq!(f.ds_mm, p.ds_mm());
        assert_eq!((f.tx[0], f.ty[0], f.tz[0]), (1.0, 0.0, 0.0));
        let s = Surface::Conic(Conic {
            curvature_per_mm: 0.01,
            conic: 0.0,
        });
        let q = project(&p, Some(&s)).unwrap();
        for j in 0..3 {
            // Tangent is unit and normal to the surface normal.
            let nrm = s.normal(q.x_mm[j], q.y_mm[j]).unwrap();
            let t = [q.tx[j], q.ty[j], q.tz[j]];
            let dot: f64 = (0..3).map(|k| t[k] * nrm[k]).sum();
            let len: f64 = t.iter().map(|v| v * v).sum::<f64>().sqrt();
            assert!(dot.abs() < 1e-14 && (len - 1.0).abs() < 1e-14);
            assert!((q.z_mm[j] - s.sag_mm(q.x_mm[j], q.y_mm[j]).unwrap()).abs() < 1e-15);
        }
        assert!(q.ds_mm[0] > f.ds_mm[0]);
    }
}
