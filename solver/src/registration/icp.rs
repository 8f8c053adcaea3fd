//! Point-to-plane ICP against an analytic surface (Chen & Medioni 1992; Gauss-Newton form as in
//! Low, "Linear least-squares optimization for point-to-plane ICP", 2004), with the exact
//! closest point on the design surface as correspondence.
//!
//! The residual of measured point `q_i` under the transform `M` is the signed distance
//! `r_i = n_i . (M q_i - s_i) - r_probe` with `s_i` the closest surface point and `n_i` its normal;
//! its gradient with respect to `M q_i` is `n_i`. A step rotates by `omega` about the centroid `c`
//! of the transformed points and translates by `tau`:
//! `p -> c + tau + Exp(omega) (p - c)`, linearised `r_i + ((p_i - c) x n_i) . omega + n_i . tau`.
//! The 6 x 6 normal equations (rotation columns scaled by the point cloud's RMS radius) are
//! solved by a symmetric eigen-decomposition; directions the surface does not constrain (for
//! example rotation about the axis of a conic) get no step. Optional Huber weights
//! (`w = min(1, delta / |r|)`, `delta = k * 1.4826 * median|r|`) make the steps iteratively
//! reweighted least squares.

use super::{RegisterSettings, Registration, Robust};
use crate::error::{Error, Result};
use crate::surface::Surface;
use nalgebra::{Isometry3, Matrix6, Point3, SymmetricEigen, Vector3, Vector6};
use rayon::prelude::*;

/// Points per task when summing the normal equations (fixed, so sums are reproducible).
const CHUNK: usize = 2048;
/// Eigenvalues of the scaled normal matrix below this fraction of the largest are unconstrained.
const RANK_TOL: f64 = 1e-10;
/// Lower bound of the Huber threshold, mm (keeps noise-free data from becoming an L1 problem).
const HUBER_FLOOR_MM: f64 = 1e-7;
/// mm to nm.
const NM_PER_MM: f64 = 1e6;

/// Per-point state of one iteration.
#[derive(Clone, Copy)]
struct Corr {
    p: [f64; 3],
    n: [f64; 3],
    foot: [f64; 3],
    r: f64,
}

/// Registers measured points (mm, probe tip centres when `probe_radius_mm > 0`) to `surface`.
pub fn register(
    surface: &Surface,
    measured_mm: &[[f64; 3]],
    settings: &RegisterSettings,
) -> Result<Registration> {
    settings.validate()?;
    surface.validate()?;
    check_points(measured_mm)?;
    let probe = settings.probe_radius_mm;
    let mut m = Isometry3::identity();
    let mut feet: Vec<[f64; 2]> = measured_mm.iter().map(|q| [q[0], q[1]]).collect();
    let mut corr = correspond(surface, measured_mm, &m, &mut feet, probe)?;
    let mut cost = robust_cost(&corr, settings.robust);
    let mut iterations = 0;
    let mut converged = false;
    while iterations < settings.max_iterations {
        let weights = weights(&corr, settings.robust);
        let step = gauss_newton_step(&corr, &weights)?;
        m = step.isometry * m;
        iterations += 1;
        corr = correspond(surface, measured_mm, &m, &mut feet, probe)?;
        let new_cost = robust_cost(&corr, settings.robust);
        let cost_change = (cost - new_cost).abs();
        cost = new_cost;
        if step.size_mm <= settings.step_tol_mm
            || cost_change <= settings.cost_rel_tol * cost.max(f64::MIN_POSITIVE)
        {
            converged = true;
            break;
        }
    }
    let form_error_nm: Vec<f64> = corr.iter().map(|c| c.r * NM_PER_MM).collect();
    let ss: f64 = form_error_nm.iter().map(|r| r * r).sum();
    Ok(Registration {
        transform: m,
        iterations,
        converged,
        rms_nm: (ss / corr.len() as f64).sqrt(),
        design_xy_mm: corr.iter().map(|c| [c.foot[0], c.foot[1]]).collect(),
        surface_points_mm: corr
            .iter()
            .map(|c| {
                [
                    c.p[0] - probe * c.n[0],
                    c.p[1] - probe * c.n[1],
                    c.p[2] - probe * c.n[2],
                ]
            })
            .collect(),
        weights: weights(&corr, settings.robust),
        form_error_nm,
    })
}

/// At least 6 finite points, not all on one line.
fn check_points(q: &[[f64; 3]]) -> Result<()> {
    if q.len() < 6 {
        return Err(Error::Geometry(format!(
            "registration needs at least 6 points to determine 6 degrees of freedom, got {}",
            q.len()
        )));
    }
    if let Some((i, p)) = q
        .iter()
        .enumerate()
        .find(|(_, p)| !p.iter().all(|c| c.is_finite()))
    {
        return Err(Error::NonFinite {
            what: "measured",
            index: i,
            detail: format!("{p:?}"),
        });
    }
    let n = q.len() as f64;
    let mut c = Vector3::zeros();
    for p in q {
        c += Vector3::from(*p);
    }
    c /= n;
    let mut cov = nalgebra::Matrix3::zeros();
    for p in q {
        let d = Vector3::from(*p) - c;
        cov += d * d.transpose();
    }
    let mut ev: Vec<f64> = SymmetricEigen::new(cov)
        .eigenvalues
        .iter()
        .copied()
        .collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    if !(ev[1] > 1e-20 * ev[0].max(f64::MIN_POSITIVE) && ev[0] > 0.0) {
        return Err(Error::Geometry(
            "the measured points are collinear (or coincide): rotation about their line is undetermined"
                .into(),
        ));
    }
    Ok(())
}

/// Closest points of the transformed points, warm-started from the previous feet.
fn correspond(
    surface: &Surface,
    q: &[[f64; 3]],
    m: &Isometry3<f64>,
    feet: &mut [[f64; 2]],
    probe: f64,
) -> Result<Vec<Corr>> {
    let out: Vec<Corr> = q
        .par_iter()
        .zip(feet.par_iter())
        .enumerate()
        .map(|(i, (qi, foot))| {
            let p = m * Point3::from(*qi);
            let p = [p.x, p.y, p.z];
            let cp = surface
                .closest_point_from(p, *foot)
                .map_err(|e| Error::Geometry(format!("measured point {i}: {e}")))?;
            Ok(Corr {
                p,
                n: cp.normal,
                foot: cp.point_mm,
                r: cp.signed_distance_mm - probe,
            })
        })
        .collect::<Result<_>>()?;
    for (f, c) in feet.iter_mut().zip(&out) {
        *f = [c.foot[0], c.foot[1]];
    }
    Ok(out)
}

/// Huber threshold `k * 1.4826 * median|r|` (at least [`HUBER_FLOOR_MM`]).
fn huber_delta(corr: &[Corr], k: f64) -> f64 {
    let mut a: Vec<f64> = corr.iter().map(|c| c.r.abs()).collect();
    let mid = a.len() / 2;
    let (_, med, _) = a.select_nth_unstable_by(mid, |x, y| x.total_cmp(y));
    (k * 1.4826 * *med).max(HUBER_FLOOR_MM)
}

fn weights(corr: &[Corr], robust: Robust) -> Vec<f64> {
    match robust {
        Robust::None => vec![1.0; corr.len()],
        Robust::Huber { k } => {
            let delta = huber_delta(corr, k);
            corr.iter()
                .map(|c| {
                    if c.r.abs() <= delta {
                        1.0
                    } else {
                        delta / c.r.abs()
                    }
                })
                .collect()
        }
    }
}

/// `sum r^2` or the Huber cost `sum rho(r)` with `rho = r^2 / 2` inside `delta`,
/// `delta (|r| - delta / 2)` outside.
fn robust_cost(corr: &[Corr], robust: Robust) -> f64 {
    match robust {
        Robust::None => corr.iter().map(|c| c.r * c.r).sum(),
        Robust::Huber { k } => {
            let d = huber_delta(corr, k);
            corr.iter()
                .map(|c| {
                    let a = c.r.abs();
                    if a <= d {
                        0.5 * a * a
                    } else {
                        d * (a - 0.5 * d)
                    }
                })
                .sum()
        }
    }
}

struct Step {
    isometry: Isometry3<f64>,
    size_mm: f64,
}

fn gauss_newton_step(corr: &[Corr], w: &[f64]) -> Result<Step> {
    let n = corr.len() as f64;
    let mut c = Vector3::zeros();
    for k in corr {
        c += Vector3::from(k.p);
    }
    c /= n;
    let mut l2 = 0.0;
    for k in corr {
        l2 += (Vector3::from(k.p) - c).norm_squared();
    }
    let len = (l2 / n).sqrt().max(f64::MIN_POSITIVE);
    let partial: Vec<(Matrix6<f64>, Vector6<f64>)> = corr
        .par_chunks(CHUNK)
        .zip(w.par_chunks(CHUNK))
        .map(|(cs, ws)| {
            let mut a = Matrix6::zeros();
            let mut b = Vector6::zeros();
            for (k, &wk) in cs.iter().zip(ws) {
                let nv = Vector3::from(k.n);
                let rot = (Vector3::from(k.p) - c).cross(&nv) / len;
                let row = Vector6::new(rot.x, rot.y, rot.z, nv.x, nv.y, nv.z);
                a += wk * row * row.transpose();
                b += (wk * k.r) * row;
            }
            (a, b)
        })
        .collect();
    let mut a = Matrix6::zeros();
    let mut b = Vector6::zeros();
    for (pa, pb) in partial {
        a += pa;
        b += pb;
    }
    let eig = SymmetricEigen::new(a);
    let max = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    if !(max > 0.0) || !max.is_finite() {
        return Err(Error::Numerical {
            stage: "registration",
            why: "the normal equations are zero or not finite".into(),
        });
    }
    let qtb = eig.eigenvectors.transpose() * b;
    let mut y = Vector6::zeros();
    for k in 0..6 {
        let lam = eig.eigenvalues[k];
        if lam > RANK_TOL * max {
            y[k] = -qtb[k] / lam;
        }
    }
    let delta = eig.eigenvectors * y;
    let omega = Vector3::new(delta[0], delta[1], delta[2]) / len;
    let tau = Vector3::new(delta[3], delta[4], delta[5]);
    let rot = nalgebra::Rotation3::new(omega);
    let t = c + tau - rot * c;
    Ok(Step {
        isometry: Isometry3::new(t, omega),
        size_mm: delta.norm(),
    })
}
