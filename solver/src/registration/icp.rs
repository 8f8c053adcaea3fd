//! Point-to-plane ICP against an analytic surface (Chen & Medioni 1992; Gauss-Newton form as in
//! Low, "Linear least-squares optimization for point-to-plane ICP", 2004), with the exact
//! closest point on the design surface as correspondence.
//!
//! The residual of measured point `q_i` under the transform `M` is the signed distance
//! `r_i = n_i . (M q_i - s_i) - r_probe` with `s_i` the closest surface point and `n_i` its normal;
//! its gradient with respect to `M q_i` is `n_i`. A step rotates by `omega` about the centroid `c`
//! of the transformed points and translates by `tau`:
//! `p -> c + tau + Exp(omega) (p - c)`, linearised `r_i + ((p_i - c) x n_i) . omega + n_i . tau`.
//! The 6 x 6 normal equations `A y = -b` (rotation columns scaled by the point cloud's RMS
//! radius `L`, so `A` is dimensionless and its eigenvalues compare motions by the normal
//! displacement they cause) are solved by a symmetric eigen-decomposition in the subspace left
//! free by locked DOFs and active prior bounds. Whether the data determine the transform is decided
//! per rigid-body motion the user can read: the rotations about the axes through the points'
//! centroid and the translations of the centroid (the scaled parameters' coordinates). The free
//! motions are estimated when their standard deviations (`s^2` times the inverse information matrix
//! over the motions left free, `s^2` the weighted residual variance of the current
//! correspondences), in units of their installation ranges, stay within 1 in every direction
//! (`installation_range_deg` for a rotation about the centroid, `installation_range_mm` for a
//! translation of it: the range is about the part, so an off-axis part's own rotation is not
//! counted as the translation it causes at the design origin). Otherwise the motion whose own
//! deviation is the largest multiple of its range is held (gets no step; it is reported as locked
//! with that comparison) and the rest judged again. A motion the points and the surface do not
//! determine at all (rotation about the axis of a conic, in-plane motions of points on a plane:
//! zero information to rounding) has an unbounded deviation and is held first. Noise-free data of
//! any well-posed part therefore determine every motion exactly, whatever the conditioning: the
//! test is the noise against the range, not an eigenvalue ratio. The covariance of the estimate is
//! `s^2 A^+` over the estimated motions (Gauss-Markov), plus, for each held motion, its range
//! squared carried through the estimated motions that absorb it; mapped to the design-frame DOFs. A
//! step that would raise the cost is halved until it does not, and the DOFs the user locked are set
//! to zero exactly after each step. Optional Huber weights (`w = min(1, delta / |r|)`, `delta = k *
//! 1.4826 * median|r|`) make the steps iteratively reweighted least squares.

use super::{
    Dof, LockSource, LockedMotion, RegisterSettings, Registration, Robust, ARCSEC_PER_RAD,
};
use crate::error::{Error, Result};
use crate::status::Status;
use crate::surface::Surface;
use nalgebra::{DMatrix, DVector, Isometry3, Matrix6, Point3, SymmetricEigen, Vector3, Vector6};
use rayon::prelude::*;

/// Points per task when summing the normal equations (fixed, so sums are reproducible).
const CHUNK: usize = 2048;
/// Eigenvalues of the scaled normal matrix at or below this fraction of the largest are numerically
/// zero (no step whatever the noise).
const RANK_FLOOR: f64 = 1e-12;
/// Eigenvalues of the constraints' Gram matrix below this fraction of the largest span their
/// null space.
const NULL_TOL: f64 = 1e-10;
/// A motion (unit coordinate of the scaled parameters) whose component in the space the
/// constraints leave free is below this is fixed by them; a numerically zero eigen-direction's
/// component on a motion below this does not make that motion undetermined.
const FREE_COMPONENT: f64 = 1e-9;
/// A point set whose second principal variance is at or below this fraction of the first is a line.
const COLLINEAR_REL: f64 = 1e-12;
/// Lower bound of the Huber threshold, mm (keeps noise-free data from becoming an L1 problem).
const HUBER_FLOOR_MM: f64 = 1e-7;
/// mm to nm.
const NM_PER_MM: f64 = 1e6;
/// Relative rise of the cost above which a Gauss-Newton step is halved (rounding below it).
const COST_RISE_TOL: f64 = 1e-9;
/// Most halvings of one Gauss-Newton step.
const MAX_HALVINGS: usize = 30;

/// Per-point state of one iteration.
#[derive(Clone, Copy)]
struct Corr {
    p: [f64; 3],
    n: [f64; 3],
    foot: [f64; 3],
    r: f64,
}

/// Registers measured points (mm, probe tip centres when `probe_radius_mm > 0`) to `surface`.
///
/// Each Gauss-Newton step is solved in the subspace the locks leave free (user locks and active
/// prior bounds as linear constraints on the design-frame DOFs), and within it the motions
/// whose standard deviation exceeds their installation range are held (see the module
/// documentation).
pub fn register(
    surface: &Surface,
    measured_mm: &[[f64; 3]],
    settings: &RegisterSettings,
) -> Result<Registration> {
    settings.validate()?;
    surface.validate()?;
    check_points(measured_mm, settings)?;
    let probe = settings.probe_radius_mm;
    let mut m = Isometry3::identity();
    let mut feet: Vec<[f64; 2]> = measured_mm.iter().map(|q| [q[0], q[1]]).collect();
    let mut corr = correspond(surface, measured_mm, &m, &mut feet, probe)?;
    let mut cost = robust_cost(&corr, settings.robust);
    let mut iterations = 0;
    let mut converged = false;
    while iterations < settings.max_iterations {
        let weights = weights(&corr, settings.robust);
        let step = gauss_newton_step(&corr, &weights, &m, settings)?;
        // The linearised step along a weakly determined motion can be long enough for the
        // surface's curvature to raise the cost: it is halved until the cost does not rise. Where
        // no fraction of it lowers the cost, the iterate is a minimum along the step: stop there.
        let mut alpha = 1.0;
        let mut accepted = None;
        for _ in 0..=MAX_HALVINGS {
            let trial_m = held_at_zero(step.isometry(alpha) * m, &settings.lock);
            let mut trial_feet = feet.clone();
            let trial = correspond(surface, measured_mm, &trial_m, &mut trial_feet, probe)?;
            let trial_cost = robust_cost(&trial, settings.robust);
            if trial_cost <= cost * (1.0 + COST_RISE_TOL) {
                accepted = Some((trial_m, trial, trial_feet, trial_cost));
                break;
            }
            alpha *= 0.5;
        }
        iterations += 1;
        let Some((trial_m, trial_corr, trial_feet, new_cost)) = accepted else {
            converged = true;
            break;
        };
        m = trial_m;
        corr = trial_corr;
        feet = trial_feet;
        // A step that lowers the cost by no more than the tolerance (or raises it within rounding)
        // ends the iteration: the iterate is a minimum to the precision of the foot points.
        let cost_decrease = cost - new_cost;
        cost = new_cost;
        if step.size_mm(alpha) <= settings.step_tol_mm
            || cost_decrease <= settings.cost_rel_tol * cost.max(f64::MIN_POSITIVE)
        {
            converged = true;
            break;
        }
    }
    let w = weights(&corr, settings.robust);
    let analysis = analyse(&corr, &w, &m, settings)?;
    let form_error_nm: Vec<f64> = corr.iter().map(|c| c.r * NM_PER_MM).collect();
    let ss: f64 = form_error_nm.iter().map(|r| r * r).sum();
    Ok(Registration {
        transform: m,
        iterations,
        status: if converged {
            Status::Converged
        } else {
            Status::MaxIterations
        },
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
        weights: w,
        form_error_nm,
        information_eigenvalues: analysis.eigenvalues,
        condition_number: analysis.condition_number,
        dof_sigma: analysis.dof_sigma,
        locked: analysis.locked,
        form_correlation: analysis.form_correlation,
    })
}

/// Refuses point sets that cannot determine the free DOFs: fewer points than free DOFs (at least
/// 3), non-finite coordinates, and points on one line in space or in the x-y plane (rotation
/// about that line and translation across it are then undetermined).
fn check_points(q: &[[f64; 3]], settings: &RegisterSettings) -> Result<()> {
    let free = settings.lock.iter().filter(|&&l| !l).count();
    let need = free.max(3);
    if q.len() < need {
        return Err(Error::Geometry(format!(
            "registration needs at least {need} points to determine {free} free degrees of \
             freedom, got {}",
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
    let eig = SymmetricEigen::new(cov);
    let mut order: Vec<usize> = (0..3).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
    if !(l0 > 0.0) || l1 <= COLLINEAR_REL * l0 {
        let d = eig.eigenvectors.column(order[0]);
        return Err(Error::Geometry(format!(
            "the measured points lie on one line (direction [{:.4}, {:.4}, {:.4}]): rotation \
             about it and translation along it are undetermined (undetermined motions: {})",
            d[0],
            d[1],
            d[2],
            motion_label(&line_motions(&Vector3::new(d[0], d[1], d[2])))
        )));
    }
    let cxy = nalgebra::Matrix2::new(cov[(0, 0)], cov[(0, 1)], cov[(1, 0)], cov[(1, 1)]);
    let exy = SymmetricEigen::new(cxy);
    let (a, b) = (exy.eigenvalues[0], exy.eigenvalues[1]);
    let (big, small, k) = if a >= b { (a, b, 0) } else { (b, a, 1) };
    if !(big > 0.0) || small <= COLLINEAR_REL * big {
        let d = exy.eigenvectors.column(k);
        return Err(Error::Geometry(format!(
            "the measured points lie on one line in x-y (direction [{:.4}, {:.4}]): rotation \
             about it and translation across it are undetermined by a single profile \
             (undetermined motions: {}); measure an area",
            d[0],
            d[1],
            motion_label(&line_motions(&Vector3::new(d[0], d[1], 0.0)))
        )));
    }
    Ok(())
}

/// Names of the motions a line of direction `d` leaves free: rotation about it (its dominant
/// axis) and translation along it.
fn line_motions(d: &Vector3<f64>) -> Vec<Dof> {
    let k = d.iamax();
    vec![Dof::ALL[k], Dof::ALL[3 + k]]
}

fn motion_label(d: &[Dof]) -> String {
    d.iter().map(|d| d.name()).collect::<Vec<_>>().join(", ")
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

/// The scaled parameter frame of a step: centroid `c` and RMS radius `len` of the points.
struct Frame {
    c: Vector3<f64>,
    len: f64,
}

fn frame(corr: &[Corr]) -> Frame {
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
    Frame {
        c,
        len: (l2 / n).sqrt().max(f64::MIN_POSITIVE),
    }
}

/// `theta = T y`: the design-frame DOFs (rotation about the origin, rad; translation, mm) of a
/// scaled step `y = [L omega, tau]` about the centroid, since
/// `c + tau + Exp(omega)(p - c) ~ p + (tau + c x omega) + omega x p`.
fn to_dofs(f: &Frame) -> Matrix6<f64> {
    let mut t = Matrix6::zeros();
    let cx = f.c.cross_matrix();
    for i in 0..3 {
        t[(i, i)] = 1.0 / f.len;
        t[(3 + i, 3 + i)] = 1.0;
        for j in 0..3 {
            t[(3 + i, j)] = cx[(i, j)] / f.len;
        }
    }
    t
}

/// `A = sum w g g^T`, `b = sum w r g` with `g = [((p - c) x n) / L, n]`, summed in fixed chunks.
fn normal_equations(corr: &[Corr], w: &[f64], f: &Frame) -> (Matrix6<f64>, Vector6<f64>) {
    let partial: Vec<(Matrix6<f64>, Vector6<f64>)> = corr
        .par_chunks(CHUNK)
        .zip(w.par_chunks(CHUNK))
        .map(|(cs, ws)| {
            let mut a = Matrix6::zeros();
            let mut b = Vector6::zeros();
            for (k, &wk) in cs.iter().zip(ws) {
                let nv = Vector3::from(k.n);
                let rot = (Vector3::from(k.p) - f.c).cross(&nv) / f.len;
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
    (a, b)
}

/// A linear constraint `row . y = rhs` on the scaled step.
struct Constraint {
    row: Vector6<f64>,
    rhs: f64,
    dof: Dof,
    source: LockSource,
}

/// A constrained step: `y`, the estimated eigen-directions `(v, mu)` of the information over
/// the free motions, and the motions held because the data do not determine them.
struct Solved {
    delta: Vector6<f64>,
    /// The part of `delta` that meets the constraints (user locks at zero, bounds): the rest is
    /// the step within the space they leave free.
    restore: Vector6<f64>,
    kept: Vec<(Vector6<f64>, f64)>,
    weak: Vec<Weak>,
}

/// A motion (a coordinate of the scaled parameters) held because the data do not determine it.
struct Weak {
    /// Index of the motion: `rx, ry, rz` about the centroid, `tx, ty, tz` of the centroid.
    k: usize,
    /// Its standard deviation when it was held, scaled mm (infinite when the points and the
    /// surface leave it undetermined).
    sigma: f64,
    /// Its installation range, scaled mm.
    range: f64,
}

/// What decides whether a motion is estimated: the residual variance `s^2` and the installation
/// range of each motion in the scaled parameters (`L * range_rad` for a rotation about the
/// centroid, `range_mm` for a translation of it).
struct Determinacy {
    s2: f64,
    range: Vector6<f64>,
}

impl Determinacy {
    fn new(corr: &[Corr], w: &[f64], f: &Frame, settings: &RegisterSettings) -> Self {
        let ss: f64 = corr.iter().zip(w).map(|(c, wk)| wk * c.r * c.r).sum();
        let s2 = ss / corr.len().saturating_sub(6).max(1) as f64;
        let rot = f.len * settings.installation_range_deg.to_radians();
        let tr = settings.installation_range_mm;
        Self {
            s2,
            range: Vector6::new(rot, rot, rot, tr, tr, tr),
        }
    }
}

/// The particular solution `y_p` of the constraints `C y = d` (minimum norm) and an orthonormal
/// basis of their null space.
fn constraint_space(cons: &[(Vector6<f64>, f64)]) -> (Vector6<f64>, Vec<Vector6<f64>>) {
    let mut ctc = Matrix6::zeros();
    let mut ctd = Vector6::zeros();
    for (row, rhs) in cons {
        let norm = row.norm();
        if norm > 0.0 {
            let r = row / norm;
            ctc += r * r.transpose();
            ctd += r * (rhs / norm);
        }
    }
    let e = SymmetricEigen::new(ctc);
    let emax = e.eigenvalues.iter().copied().fold(0.0, f64::max);
    let mut null: Vec<Vector6<f64>> = Vec::with_capacity(6);
    let mut delta = Vector6::zeros();
    for k in 0..6 {
        let v: Vector6<f64> = e.eigenvectors.column(k).into_owned();
        let l = e.eigenvalues[k];
        if emax <= 0.0 || l <= NULL_TOL * emax {
            null.push(v);
        } else {
            delta += v * (v.dot(&ctd) / l);
        }
    }
    (delta, null)
}

/// The standard deviation (scaled mm) of each motion not fixed by the constraints, given the
/// eigen-decomposition `(v, mu)` of the information over the free space: `s sqrt(sum v_k^2 / mu)`
/// over the eigen-directions above the rank floor; unbounded where a numerically zero one moves
/// the motion. With it, the size of that zero direction's component on the motion (to choose
/// among unbounded motions). `None` for a motion the constraints fix.
fn motion_sigmas(
    z: &[Vector6<f64>],
    eig: &[(Vector6<f64>, f64)],
    s2: f64,
    floor: f64,
) -> [Option<(f64, f64)>; 6] {
    std::array::from_fn(|k| {
        let free = z.iter().map(|v| v[k] * v[k]).sum::<f64>().sqrt();
        if free <= FREE_COMPONENT {
            return None;
        }
        let mut var = 0.0;
        let mut zero_component: f64 = 0.0;
        for (v, mu) in eig {
            if *mu > floor {
                var += v[k] * v[k] / mu;
            } else if v[k].abs() > FREE_COMPONENT {
                zero_component = zero_component.max(v[k].abs());
            }
        }
        if zero_component > 0.0 {
            Some((f64::INFINITY, zero_component))
        } else {
            Some(((s2 * var).sqrt(), 0.0))
        }
    })
}

/// Minimises `|J y + r|^2` subject to `C y = d`: `y = y_p + Z u` with `y_p` the minimum-norm
/// solution of the constraints and `Z` an orthonormal basis of their null space; then
/// `Z^T A Z u = -Z^T (b + A y_p)` by eigen-decomposition. Before the step, motions are held one
/// at a time while a free motion's standard deviation exceeds its installation range, or the
/// free motions' deviations in units of their ranges exceed 1 in some direction (the largest
/// multiple of its range first; an undetermined motion, the largest zero-information component
/// against its range first), each hold an added constraint `y_k = 0`.
fn solve_constrained(
    a: &Matrix6<f64>,
    b: &Vector6<f64>,
    cons: &[Constraint],
    det: &Determinacy,
    lam_max: f64,
) -> Solved {
    let floor = RANK_FLOOR * lam_max;
    let mut weak: Vec<Weak> = Vec::new();
    loop {
        let mut rows: Vec<(Vector6<f64>, f64)> = cons.iter().map(|c| (c.row, c.rhs)).collect();
        rows.extend(weak.iter().map(|w| (Vector6::ith(w.k, 1.0), 0.0)));
        let (delta, null) = constraint_space(&rows);
        if null.is_empty() {
            return Solved {
                delta,
                restore: delta,
                kept: Vec::new(),
                weak,
            };
        }
        let z = DMatrix::from_fn(6, null.len(), |i, j| null[j][i]);
        let a_d = DMatrix::from_fn(6, 6, |i, j| a[(i, j)]);
        let ar = z.transpose() * &a_d * &z;
        let er = SymmetricEigen::new(ar);
        let eig: Vec<(Vector6<f64>, f64)> = (0..null.len())
            .map(|j| {
                let vz = &z * er.eigenvectors.column(j);
                (Vector6::from_column_slice(vz.as_slice()), er.eigenvalues[j])
            })
            .collect();
        let sigmas = motion_sigmas(&null, &eig, det.s2, floor);
        // Whether the free motions' deviation, in units of their ranges, exceeds 1 in some
        // direction (a combination of motions each within its range can be beyond it together).
        let beyond = {
            let mut p = Matrix6::zeros();
            for (v, mu) in eig.iter().filter(|(_, mu)| *mu > floor) {
                let u = v.component_div(&det.range);
                p += u * u.transpose() / *mu;
            }
            let worst = SymmetricEigen::new(p * det.s2)
                .eigenvalues
                .iter()
                .copied()
                .fold(0.0, f64::max);
            worst > 1.0
        };
        // The motion furthest beyond its range: the largest multiple of its range, ties (the
        // undetermined motions) by the zero direction's component against the range.
        let worst = (0..6)
            .filter_map(|k| sigmas[k].map(|(sig, zc)| (k, sig, zc / det.range[k])))
            .filter(|&(k, sig, _)| sig > det.range[k] || (beyond && sig > 0.0))
            .max_by(|x, y| {
                (x.1 / det.range[x.0])
                    .total_cmp(&(y.1 / det.range[y.0]))
                    .then(x.2.total_cmp(&y.2))
                    .then(y.0.cmp(&x.0))
            });
        if let Some((k, sigma, _)) = worst {
            weak.push(Weak {
                k,
                sigma,
                range: det.range[k],
            });
            continue;
        }
        let rhs = b + a * delta;
        let mut out = Solved {
            delta,
            restore: delta,
            kept: Vec::new(),
            weak,
        };
        for (v, mu) in eig {
            if mu > floor {
                out.delta += v * (-v.dot(&rhs) / mu);
                out.kept.push((v, mu));
            }
        }
        return out;
    }
}

/// `m` with the DOFs the user locked set to zero exactly (the linearised step holds them to
/// first order only; its second-order part would otherwise let a lock drift, step by step).
fn held_at_zero(m: Isometry3<f64>, lock: &[bool; 6]) -> Isometry3<f64> {
    if !lock.iter().any(|&l| l) {
        return m;
    }
    let mut theta = dofs_of(&m);
    for (k, &l) in lock.iter().enumerate() {
        if l {
            theta[k] = 0.0;
        }
    }
    Isometry3::new(
        Vector3::new(theta[3], theta[4], theta[5]),
        Vector3::new(theta[0], theta[1], theta[2]),
    )
}

/// Current DOFs of `m`: rotation vector (rad) and translation (mm).
fn dofs_of(m: &Isometry3<f64>) -> Vector6<f64> {
    let w = m.rotation.scaled_axis();
    let t = m.translation.vector;
    Vector6::new(w.x, w.y, w.z, t.x, t.y, t.z)
}

/// Bounds of the DOFs in rad and mm.
fn bounds(settings: &RegisterSettings) -> [Option<f64>; 6] {
    let r = settings.max_rotation_arcsec.map(|a| a / ARCSEC_PER_RAD);
    let t = settings.max_translation_um.map(|u| u * 1e-3);
    [r, r, r, t, t, t]
}

/// The state of a step: frame, information matrix, its largest eigenvalue, the DOF map, the
/// constraints in force and the constrained solution.
struct StepState {
    f: Frame,
    a: Matrix6<f64>,
    lam_max: f64,
    t: Matrix6<f64>,
    cons: Vec<Constraint>,
    solved: Solved,
}

/// One constrained Gauss-Newton step: user locks hold their DOF at zero; a bound the step would
/// cross is made an equality at the bound and the step solved again (an active set that only
/// grows within a step; the next step starts afresh, so a bound is released when the data pull
/// the DOF back inside).
fn constrained_step(
    corr: &[Corr],
    w: &[f64],
    m: &Isometry3<f64>,
    settings: &RegisterSettings,
) -> Result<StepState> {
    let f = frame(corr);
    let (a, b) = normal_equations(corr, w, &f);
    let lam_max = SymmetricEigen::new(a)
        .eigenvalues
        .iter()
        .copied()
        .fold(0.0, f64::max);
    if !(lam_max > 0.0) || !lam_max.is_finite() {
        return Err(Error::Numerical {
            stage: "registration",
            why: "the normal equations are zero or not finite".into(),
        });
    }
    let t = to_dofs(&f);
    let det = Determinacy::new(corr, w, &f, settings);
    let theta = dofs_of(m);
    let bound = bounds(settings);
    let mut held = settings.lock;
    let mut cons: Vec<Constraint> = Dof::ALL
        .iter()
        .filter(|d| settings.lock[d.index()])
        .map(|&d| Constraint {
            row: t.row(d.index()).transpose(),
            rhs: -theta[d.index()],
            dof: d,
            source: LockSource::User,
        })
        .collect();
    loop {
        let solved = solve_constrained(&a, &b, &cons, &det, lam_max);
        let new = theta + t * solved.delta;
        let mut added = false;
        for d in Dof::ALL {
            let k = d.index();
            if held[k] {
                continue;
            }
            if let Some(bk) = bound[k] {
                if new[k].abs() > bk {
                    cons.push(Constraint {
                        row: t.row(k).transpose(),
                        rhs: bk.copysign(new[k]) - theta[k],
                        dof: d,
                        source: LockSource::Bound,
                    });
                    held[k] = true;
                    added = true;
                }
            }
        }
        if !added {
            return Ok(StepState {
                f,
                a,
                lam_max,
                t,
                cons,
                solved,
            });
        }
    }
}

/// A Gauss-Newton step in the scaled parameters about the centroid `c` (RMS radius `len`):
/// `restore`, the part that meets the constraints, plus `free`, the step within the space they
/// leave free.
struct Step {
    full: Vector6<f64>,
    restore: Vector6<f64>,
    free: Vector6<f64>,
    c: Vector3<f64>,
    len: f64,
}

impl Step {
    /// The constraints' part and the fraction `alpha` of the free step as an isometry: with
    /// `y = restore + alpha free = [L omega, tau]`, `p -> c + tau + Exp(omega) (p - c)`.
    fn isometry(&self, alpha: f64) -> Isometry3<f64> {
        let y = if alpha == 1.0 {
            self.full
        } else {
            self.restore + self.free * alpha
        };
        let omega = Vector3::new(y[0], y[1], y[2]) / self.len;
        let tau = Vector3::new(y[3], y[4], y[5]);
        let rot = nalgebra::Rotation3::new(omega);
        Isometry3::new(self.c + tau - rot * self.c, omega)
    }

    /// Length of that step, mm (rotation scaled by `L`).
    fn size_mm(&self, alpha: f64) -> f64 {
        (self.restore + self.free * alpha).norm()
    }
}

fn gauss_newton_step(
    corr: &[Corr],
    w: &[f64],
    m: &Isometry3<f64>,
    settings: &RegisterSettings,
) -> Result<Step> {
    let st = constrained_step(corr, w, m, settings)?;
    Ok(Step {
        full: st.solved.delta,
        restore: st.solved.restore,
        free: st.solved.delta - st.solved.restore,
        c: st.f.c,
        len: st.f.len,
    })
}

/// Conditioning and uncertainty at the solution.
struct Analysis {
    eigenvalues: [f64; 6],
    condition_number: Option<f64>,
    dof_sigma: [f64; 6],
    locked: Vec<LockedMotion>,
    form_correlation: [f64; 6],
}

fn analyse(
    corr: &[Corr],
    w: &[f64],
    m: &Isometry3<f64>,
    settings: &RegisterSettings,
) -> Result<Analysis> {
    let st = constrained_step(corr, w, m, settings)?;
    let mut ev: Vec<f64> = SymmetricEigen::new(st.a)
        .eigenvalues
        .iter()
        .copied()
        .collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    let eigenvalues: [f64; 6] = std::array::from_fn(|k| ev[k].max(0.0));
    let condition_number = (eigenvalues[5] > 0.0).then(|| eigenvalues[0] / eigenvalues[5]);
    let ss: f64 = corr.iter().zip(w).map(|(c, wk)| wk * c.r * c.r).sum();
    let dof = corr.len().saturating_sub(st.solved.kept.len()).max(1);
    let s2 = ss / dof as f64;
    // `P = sum v v^T / mu` over the estimated directions: the estimate's covariance is `s^2 P`.
    let mut pinv = Matrix6::zeros();
    for (v, mu) in &st.solved.kept {
        pinv += v * v.transpose() / *mu;
    }
    // A held motion `k` is somewhere within its range `rho_k` (held at the current value, its
    // error is up to the range); the estimated motions absorb what they can of it, moving by
    // `-P A e_k` per unit: its share of the covariance is `rho_k^2 g g^T`, `g = e_k - P A e_k`.
    let mut cov = pinv * s2;
    for weak in &st.solved.weak {
        let e = Vector6::ith(weak.k, 1.0);
        let g = e - pinv * (st.a * e);
        cov += g * g.transpose() * (weak.range * weak.range);
    }
    let cov = st.t * cov * st.t.transpose();
    let held: Vec<usize> = st.cons.iter().map(|c| c.dof.index()).collect();
    let dof_sigma: [f64; 6] = std::array::from_fn(|k| {
        let unit = if k < 3 { ARCSEC_PER_RAD } else { 1e3 };
        if held.contains(&k) {
            0.0
        } else {
            cov[(k, k)].max(0.0).sqrt() * unit
        }
    });
    let rel = |v: &Vector6<f64>| (v.transpose() * st.a * v)[(0, 0)] / st.lam_max;
    let mut locked = Vec::new();
    for c in &st.cons {
        let v = c.row.normalize();
        locked.push(LockedMotion {
            source: c.source,
            label: c.dof.name().to_string(),
            direction: std::array::from_fn(|k| v[k]),
            relative_eigenvalue: rel(&v),
            reason: match c.source {
                LockSource::User => "held at zero by the user".to_string(),
                LockSource::Bound => "held at its prior bound".to_string(),
                LockSource::Weak => String::new(),
            },
            undetermined: false,
        });
    }
    for weak in &st.solved.weak {
        let v = Vector6::ith(weak.k, 1.0);
        locked.push(LockedMotion {
            source: LockSource::Weak,
            label: Dof::ALL[weak.k].name().to_string(),
            direction: std::array::from_fn(|k| v[k]),
            relative_eigenvalue: rel(&v).max(0.0),
            reason: weak_reason(weak, st.f.len),
            undetermined: !weak.sigma.is_finite(),
        });
    }
    // The form correlation of a motion held about the centroid is that of its design-frame DOF.
    let mut held_all = held;
    held_all.extend(st.solved.weak.iter().map(|w| w.k));
    Ok(Analysis {
        eigenvalues,
        condition_number,
        dof_sigma,
        locked,
        form_correlation: form_correlation(corr, w, &held_all),
    })
}

/// Why a motion is held: its standard deviation against its installation range, in arcsec (a
/// rotation about the points' centroid) or um (a translation of the centroid); `len` is the
/// scaled parameters' length, mm.
fn weak_reason(weak: &Weak, len: f64) -> String {
    let (unit, name, what) = if weak.k < 3 {
        (
            ARCSEC_PER_RAD / len,
            "arcsec",
            "rotation about the points' centroid",
        )
    } else {
        (1e3, "um", "translation of the points' centroid")
    };
    if weak.sigma.is_finite() {
        format!(
            "the data do not determine it: its standard deviation from the residual's scatter \
             ({:.4} {name}, {what}) exceeds the installation range ({:.4} {name}); held within \
             that range",
            weak.sigma * unit,
            weak.range * unit
        )
    } else {
        format!(
            "the points and the surface leave it undetermined (zero information; {what}); held \
             within the installation range ({:.4} {name})",
            weak.range * unit
        )
    }
}

/// [`Registration::form_correlation`](super::Registration::form_correlation): with the
/// design-frame patterns `h_i = [p_i x n_i, n_i]`, their weighted Gram matrix `G` and
/// `c = sum w h e`, the unique signature `u` of DOF `k` against the free set `J` (the DOFs not
/// held, `k` excluded) has
/// `|u|^2 = G_kk - G_kJ G_JJ^+ G_Jk` and `u . e = c_k - G_kJ G_JJ^+ c_J`.
fn form_correlation(corr: &[Corr], w: &[f64], held: &[usize]) -> [f64; 6] {
    let partial: Vec<(Matrix6<f64>, Vector6<f64>, f64)> = corr
        .par_chunks(CHUNK)
        .zip(w.par_chunks(CHUNK))
        .map(|(cs, ws)| {
            let mut g = Matrix6::zeros();
            let mut c = Vector6::zeros();
            let mut ee = 0.0;
            for (k, &wk) in cs.iter().zip(ws) {
                let nv = Vector3::from(k.n);
                let rot = Vector3::from(k.p).cross(&nv);
                let h = Vector6::new(rot.x, rot.y, rot.z, nv.x, nv.y, nv.z);
                g += wk * h * h.transpose();
                c += (wk * k.r) * h;
                ee += wk * k.r * k.r;
            }
            (g, c, ee)
        })
        .collect();
    let (mut g, mut c, mut ee) = (Matrix6::zeros(), Vector6::zeros(), 0.0);
    for (pg, pc, pe) in partial {
        g += pg;
        c += pc;
        ee += pe;
    }
    std::array::from_fn(|k| {
        let others: Vec<usize> = (0..6).filter(|&j| j != k && !held.contains(&j)).collect();
        let gjj = DMatrix::from_fn(others.len(), others.len(), |a, b| g[(others[a], others[b])]);
        let gjk = DVector::from_fn(others.len(), |a, _| g[(others[a], k)]);
        let cj = DVector::from_fn(others.len(), |a, _| c[others[a]]);
        let beta = if others.is_empty() {
            DVector::zeros(0)
        } else {
            let svd = gjj.svd(true, true);
            let tol = RANK_FLOOR * svd.singular_values.max();
            svd.solve(&gjk, tol)
                .unwrap_or_else(|_| DVector::zeros(others.len()))
        };
        let uu = g[(k, k)] - gjk.dot(&beta);
        if !(uu > RANK_FLOOR * g[(k, k)]) {
            return 0.0;
        }
        let ue = c[k] - cj.dot(&beta);
        if !(ee > 0.0) {
            return 0.0;
        }
        (ue / (uu.sqrt() * ee.sqrt())).abs().min(1.0)
    })
}
