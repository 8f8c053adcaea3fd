//! Conditioning-aware registration: information-matrix eigenvalues against closed forms, weak
//! motions of a weakly curved freeform locked instead of eating the form error, a known
//! installation error recovered within its standard deviations, priors and degenerate sets.

use nalgebra::{Isometry3, Matrix3, Point3, SymmetricEigen, Vector3};
use preston::io::surface::read_surface;
use preston::solver::iterate::{FormErrorModel, SplitMix64};
use preston::solver::map::BoundingBox;
use preston::solver::registration::{register, Dof, LockSource, RegisterSettings, ARCSEC_PER_RAD};
use preston::solver::surface::{Conic, Plane, Surface};
use preston::solver::Error;

/// Relative tolerance of eigenvalues computed two ways.
const EIG_REL_TOL: f64 = 1e-9;
/// What the freeform's locked weak directions take of a 40 arcsec rx (their rx share is 0.024,
/// squared times 40 arcsec is 0.023 arcsec), arcsec.
const LOCKED_SHARE_ARCSEC: f64 = 0.05;

fn freeform() -> Surface {
    let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/design_freeform.json");
    read_surface(&p).unwrap()
}

fn aperture() -> BoundingBox {
    BoundingBox {
        x_min_mm: -25.0,
        x_max_mm: 25.0,
        y_min_mm: -25.0,
        y_max_mm: 25.0,
    }
}

/// Grid `x`, `y` (mm), design points and normals.
type Design = (Vec<f64>, Vec<f64>, Vec<[f64; 3]>, Vec<[f64; 3]>);

/// Grid design points and normals over the aperture.
fn design(s: &Surface, n: usize) -> Design {
    let a = aperture();
    let (mut x, mut y, mut p, mut nn) = (vec![], vec![], vec![], vec![]);
    for j in 0..n {
        for i in 0..n {
            let xi = a.x_min_mm + (a.x_max_mm - a.x_min_mm) * i as f64 / (n - 1) as f64;
            let yj = a.y_min_mm + (a.y_max_mm - a.y_min_mm) * j as f64 / (n - 1) as f64;
            let d = s.derivs(xi, yj).unwrap();
            x.push(xi);
            y.push(yj);
            p.push([xi, yj, d.z]);
            nn.push(d.normal());
        }
    }
    (x, y, p, nn)
}

/// `M^-1 (s + e n)`: measured points of a part with normal form error `e_nm` (nm) mounted with
/// `p_design = M p_measured`.
fn measure(m: &Isometry3<f64>, p: &[[f64; 3]], n: &[[f64; 3]], e_nm: &[f64]) -> Vec<[f64; 3]> {
    let inv = m.inverse();
    p.iter()
        .zip(n)
        .zip(e_nm)
        .map(|((s, n), e)| {
            let d = e * 1e-6;
            let q = inv * Point3::new(s[0] + d * n[0], s[1] + d * n[1], s[2] + d * n[2]);
            [q.x, q.y, q.z]
        })
        .collect()
}

/// Normal-displacement patterns `g_i = [(p_i - c) x n_i, n_i]` of the six DOFs about the
/// centroid (unscaled), as columns.
fn patterns(p: &[[f64; 3]], n: &[[f64; 3]]) -> nalgebra::DMatrix<f64> {
    let mut c = Vector3::zeros();
    for q in p {
        c += Vector3::from(*q);
    }
    c /= p.len() as f64;
    nalgebra::DMatrix::from_fn(p.len(), 6, |i, k| {
        let nv = Vector3::from(n[i]);
        let r = (Vector3::from(p[i]) - c).cross(&nv);
        if k < 3 {
            r[k]
        } else {
            nv[k - 3]
        }
    })
}

/// `e` minus its least-squares fit by the columns of `g`.
fn remove_fit(g: &nalgebra::DMatrix<f64>, e: &[f64]) -> Vec<f64> {
    let v = nalgebra::DVector::from_column_slice(e);
    let coef = g.clone().svd(true, true).solve(&v, 1e-12).unwrap();
    (v - g * coef).iter().copied().collect()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|a| a * a).sum::<f64>() / v.len() as f64).sqrt()
}

/// `e` minus its least-squares plane `a + b x + c y` (piston and tilt).
fn remove_piston_tilt(x: &[f64], y: &[f64], e: &[f64]) -> Vec<f64> {
    let g = nalgebra::DMatrix::from_fn(e.len(), 3, |i, k| [1.0, x[i], y[i]][k]);
    remove_fit(&g, e)
}

#[test]
fn plane_information_eigenvalues_match_the_closed_form() {
    // A plane z = 0 sampled on a centred 41 x 21 grid over 40 x 20 mm: rows
    // g = [(y, -x, 0) / L, (0, 0, 1)], so A = diag(Sy2 / L^2, Sx2 / L^2, 0, 0, 0, N) with
    // L^2 = (Sx2 + Sy2) / N; tx, ty and rz are undetermined and locked.
    let (mut q, mut sx2, mut sy2) = (vec![], 0.0, 0.0);
    for j in 0..21 {
        for i in 0..41 {
            let (x, y) = (-20.0 + i as f64, -10.0 + j as f64);
            q.push([x, y, 0.0]);
            sx2 += x * x;
            sy2 += y * y;
        }
    }
    let nn = q.len() as f64;
    let l2 = (sx2 + sy2) / nn;
    let reg = register(&Surface::Plane(Plane {}), &q, &RegisterSettings::default()).unwrap();
    let want = [nn, sx2 / l2, sy2 / l2, 0.0, 0.0, 0.0];
    for (g, w) in reg.information_eigenvalues.iter().zip(want) {
        assert!(
            (g - w).abs() <= EIG_REL_TOL * nn,
            "{:?} vs {want:?}",
            reg.information_eigenvalues
        );
    }
    assert_eq!(reg.condition_number, None);
    let weak: Vec<_> = reg
        .locked
        .iter()
        .filter(|l| l.source == LockSource::Weak)
        .collect();
    assert_eq!(weak.len(), 3, "{:?}", reg.locked);
    // The weak directions span {rz, tx, ty}: no rx, ry, tz component.
    for l in &weak {
        for k in [0, 1, 5] {
            assert!(l.direction[k].abs() < 1e-9, "{l:?}");
        }
    }
    // Their sigmas are zero (held), the others positive (zero residual: zero sigma too here).
    for k in [2, 3, 4] {
        assert_eq!(reg.dof_sigma[k], 0.0);
    }
}

#[test]
fn sphere_information_eigenvalues_match_the_closed_form() {
    // A sphere of radius R (centre C = (0, 0, R)) sampled on a cap: n_i = (C - p_i) / R, so
    // (p - c) x n = d x n with d = C - c and g = [[d]x / L; I] n. Hence A = K S K^T with
    // S = sum n n^T, K = [[d]x / L; I]: three zero eigenvalues (rotations about C) and the
    // eigenvalues of S^(1/2) K^T K S^(1/2), K^T K = (1 + |d|^2 / L^2) I - d d^T / L^2.
    let r = 150.0;
    let s = Surface::Conic(Conic {
        curvature_per_mm: 1.0 / r,
        conic: 0.0,
    });
    let mut q = vec![];
    let mut nrm = vec![];
    for j in 0..25 {
        for i in 0..31 {
            let (x, y) = (-30.0 + 2.0 * i as f64, -12.0 + j as f64 + 5.0);
            let d = s.derivs(x, y).unwrap();
            q.push([x, y, d.z]);
            nrm.push(d.normal());
        }
    }
    let nn = q.len() as f64;
    let mut c = Vector3::zeros();
    for p in &q {
        c += Vector3::from(*p);
    }
    c /= nn;
    let l2 = q
        .iter()
        .map(|p| (Vector3::from(*p) - c).norm_squared())
        .sum::<f64>()
        / nn;
    let d = Vector3::new(0.0, 0.0, r) - c;
    let mut sm = Matrix3::zeros();
    for n in &nrm {
        let v = Vector3::from(*n);
        sm += v * v.transpose();
    }
    let ktk = Matrix3::identity() * (1.0 + d.norm_squared() / l2) - d * d.transpose() / l2;
    let sh = SymmetricEigen::new(sm);
    let s_half = sh.eigenvectors
        * Matrix3::from_diagonal(&sh.eigenvalues.map(|v| v.sqrt()))
        * sh.eigenvectors.transpose();
    let mut want: Vec<f64> = SymmetricEigen::new(s_half * ktk * s_half)
        .eigenvalues
        .iter()
        .copied()
        .collect();
    want.sort_by(|a, b| b.total_cmp(a));
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    let got = reg.information_eigenvalues;
    for k in 0..3 {
        assert!(
            (got[k] - want[k]).abs() <= EIG_REL_TOL * want[0],
            "{got:?} vs {want:?}"
        );
        assert!(got[3 + k] <= EIG_REL_TOL * want[0], "{got:?}");
    }
    // Exactly the three rotations about the centre are held.
    let weak = reg
        .locked
        .iter()
        .filter(|l| l.source == LockSource::Weak)
        .count();
    assert_eq!(weak, 3, "{:?}", reg.locked);
}

/// Design-frame DOFs of `m`: rotation vector (arcsec), translation (um).
fn dofs(m: &Isometry3<f64>) -> [f64; 6] {
    let w = m.rotation.scaled_axis() * ARCSEC_PER_RAD;
    let t = m.translation.vector * 1e3;
    [w.x, w.y, w.z, t.x, t.y, t.z]
}

#[test]
fn freeform_with_form_error_keeps_weak_motions_locked_and_the_form_error() {
    // The shipped freeform with 43 nm RMS of smooth form error, 3 nm of measurement noise and no
    // installation error: the motions it barely determines are locked (not slid along to eat
    // the form error) and the recovered form error is the true one, piston and tilt aside.
    let s = freeform();
    let (x, y, p, n) = design(&s, 51);
    let form = FormErrorModel {
        rms_nm: 43.0,
        ..FormErrorModel::default()
    }
    .sample(&aperture(), &x, &y)
    .unwrap();
    let mut rng = SplitMix64::new(11);
    let meas: Vec<f64> = form.iter().map(|e| e + 3.0 * rng.normal()).collect();
    let q = measure(&Isometry3::identity(), &p, &n, &meas);
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    eprintln!(
        "{:?} {:?} {:?}",
        reg.information_eigenvalues,
        reg.locked,
        dofs(&reg.transform)
    );
    assert!(reg.status.is_converged());
    let weak: Vec<_> = reg
        .locked
        .iter()
        .filter(|l| l.source == LockSource::Weak)
        .collect();
    assert_eq!(weak.len(), 3, "{:?}", reg.locked);
    let got = dofs(&reg.transform);
    // Weak motions: rz, tx, ty below 5 arcsec / 5 um.
    for (k, lim) in [(2, 5.0), (3, 5.0), (4, 5.0)] {
        assert!(got[k].abs() < lim, "{:?}", got);
    }
    let (fx, fy): (Vec<f64>, Vec<f64>) = reg.design_xy_mm.iter().map(|p| (p[0], p[1])).unzip();
    let rec = remove_piston_tilt(&fx, &fy, &reg.form_error_nm);
    let tru = remove_piston_tilt(&x, &y, &form);
    let diff: Vec<f64> = rec.iter().zip(&tru).map(|(a, b)| a - b).collect();
    assert!(
        rms(&diff) < 0.1 * rms(&tru),
        "{} vs {}",
        rms(&diff),
        rms(&tru)
    );
    // Without the lock (threshold 0) the same data slide much further.
    let free = register(
        &s,
        &q,
        &RegisterSettings {
            weak_eigenvalue_rel: 0.0,
            ..RegisterSettings::default()
        },
    )
    .unwrap();
    let g = dofs(&free.transform);
    assert!(g[2].abs().max(g[3].abs()).max(g[4].abs()) > 5.0, "{g:?}");
}

#[test]
fn installation_error_on_the_freeform_is_recovered_within_three_sigma() {
    // Installation error in the DOFs the freeform determines (tilts and piston) plus a 43 nm
    // form error orthogonal to every rigid motion (its rigid part is installation error by
    // definition) and 5 nm of white noise: rx, ry and tz are recovered within 3 sigma of the
    // truth; the locked weak motions stay below 5 arcsec / 5 um.
    let s = freeform();
    let (x, y, p, n) = design(&s, 51);
    let form = FormErrorModel {
        rms_nm: 43.0,
        seed: 5,
        ..FormErrorModel::default()
    }
    .sample(&aperture(), &x, &y)
    .unwrap();
    let form = remove_fit(&patterns(&p, &n), &form);
    let mut rng = SplitMix64::new(3);
    let meas: Vec<f64> = form.iter().map(|e| e + 5.0 * rng.normal()).collect();
    let truth = [12.0, -8.0, 0.0, 0.0, 0.0, 3.0];
    let rot = Vector3::new(truth[0], truth[1], truth[2]) / ARCSEC_PER_RAD;
    let tr = Vector3::new(truth[3], truth[4], truth[5]) * 1e-3;
    let m = Isometry3::new(tr, rot);
    let q = measure(&m, &p, &n, &meas);
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    let got = dofs(&reg.transform);
    eprintln!("got {got:?} sigma {:?}", reg.dof_sigma);
    assert!(reg.status.is_converged());
    for k in [0, 1, 5] {
        let sig = reg.dof_sigma[k];
        assert!(sig > 0.0);
        assert!(
            (got[k] - truth[k]).abs() <= 3.0 * sig,
            "{} {got:?} {:?}",
            Dof::ALL[k].name(),
            reg.dof_sigma
        );
    }
    for k in [2, 3, 4] {
        assert!(got[k].abs() < 5.0, "{got:?}");
    }
    // The residual variance is the noise (plus the unexplained form error): s ~ 43 nm here,
    // and the sigma of tz is s / sqrt(N) to within the pattern's n_z ~ 1.
    let s_nm = rms(&reg.form_error_nm);
    let expect = s_nm / (p.len() as f64).sqrt() * 1e-3;
    assert!(
        (reg.dof_sigma[5] - expect).abs() < 0.05 * expect,
        "{} vs {expect}",
        reg.dof_sigma[5]
    );
}

#[test]
fn user_locks_and_prior_bounds_hold_their_dofs() {
    let s = freeform();
    let (_, _, p, n) = design(&s, 31);
    let truth = Isometry3::new(
        Vector3::new(0.0, 0.0, 0.004),
        Vector3::new(40.0, -30.0, 0.0) / ARCSEC_PER_RAD,
    );
    let q = measure(&truth, &p, &n, &vec![0.0; p.len()]);
    // Lock tz: the piston stays in the form error (4 um) and tz stays zero.
    let mut lock = [false; 6];
    lock[Dof::Tz.index()] = true;
    let reg = register(
        &s,
        &q,
        &RegisterSettings {
            lock,
            ..RegisterSettings::default()
        },
    )
    .unwrap();
    let got = dofs(&reg.transform);
    assert!(got[5].abs() < 1e-6, "{got:?}");
    assert_eq!(reg.dof_sigma[5], 0.0);
    assert!(reg
        .locked
        .iter()
        .any(|l| l.source == LockSource::User && l.label == "tz"));
    let mean = reg.form_error_nm.iter().sum::<f64>() / reg.form_error_nm.len() as f64;
    assert!((mean.abs() - 4000.0).abs() < 100.0, "mean {mean} nm");
    // A rotation bound of 20 arcsec holds rx at +20 (truth 40) and ry at -20 (truth -30).
    let reg = register(
        &s,
        &q,
        &RegisterSettings {
            max_rotation_arcsec: Some(20.0),
            ..RegisterSettings::default()
        },
    )
    .unwrap();
    let got = dofs(&reg.transform);
    assert!(
        (got[0] - 20.0).abs() < 1e-3 && (got[1] + 20.0).abs() < 1e-3,
        "{got:?}"
    );
    assert!((got[5] - 4.0).abs() < 1.0, "{got:?}");
    let bound: Vec<_> = reg
        .locked
        .iter()
        .filter(|l| l.source == LockSource::Bound)
        .map(|l| l.label.as_str())
        .collect();
    assert_eq!(bound, ["rx", "ry"]);
    // Within the bounds nothing is held and the truth is recovered.
    let reg = register(
        &s,
        &q,
        &RegisterSettings {
            max_rotation_arcsec: Some(60.0),
            max_translation_um: Some(10.0),
            ..RegisterSettings::default()
        },
    )
    .unwrap();
    let got = dofs(&reg.transform);
    // (The locked weak directions carry a 0.024 share of rx: 40 arcsec leaves ~0.02 arcsec.)
    assert!(
        (got[0] - 40.0).abs() < LOCKED_SHARE_ARCSEC && (got[5] - 4.0).abs() < 1e-3,
        "{got:?}"
    );
    assert!(reg.locked.iter().all(|l| l.source != LockSource::Bound));
}

#[test]
fn degenerate_sets_are_refused_naming_the_motions() {
    let s = freeform();
    // Points on one straight line in x-y (a profile across a curved part).
    let line: Vec<[f64; 3]> = (0..40)
        .map(|i| {
            let x = -20.0 + i as f64;
            [x, 0.5 * x, s.sag_mm(x, 0.5 * x).unwrap()]
        })
        .collect();
    match register(&s, &line, &RegisterSettings::default()) {
        Err(Error::Geometry(m)) => assert!(m.contains("one line") && m.contains("rx"), "{m}"),
        other => panic!("{other:?}"),
    }
    // Collinear in space.
    let l3: Vec<[f64; 3]> = (0..20)
        .map(|i| [0.1 * i as f64, 0.2 * i as f64, 0.3 * i as f64])
        .collect();
    assert!(matches!(
        register(&s, &l3, &RegisterSettings::default()),
        Err(Error::Geometry(_))
    ));
    // Too few for six DOFs, enough for three.
    let (_, _, p, _) = design(&s, 3);
    assert!(matches!(
        register(&s, &p[..5], &RegisterSettings::default()),
        Err(Error::Geometry(_))
    ));
    let mut lock = [false; 6];
    for d in [Dof::Rz, Dof::Tx, Dof::Ty] {
        lock[d.index()] = true;
    }
    assert!(register(
        &s,
        &p[..5],
        &RegisterSettings {
            lock,
            ..RegisterSettings::default()
        }
    )
    .is_ok());
}

#[test]
fn probe_centres_without_probe_radius_fit_an_offset_instead_of_diverging() {
    // Tip centres of a 1 mm probe registered as if they were surface points: the parallel
    // surface at 1 mm is the design moved by about 1 mm along z, so the registration converges
    // to tz ~ -1 mm with small rotations rather than sliding away.
    let s = freeform();
    let (_, _, p, n) = design(&s, 31);
    let q = measure(&Isometry3::identity(), &p, &n, &vec![1e6; p.len()]);
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    let got = dofs(&reg.transform);
    eprintln!("{got:?} rms {} nm", reg.rms_nm);
    assert!(reg.status.is_converged());
    assert!((got[5] + 1000.0).abs() < 5.0, "{got:?}");
    for k in 0..5 {
        assert!(got[k].abs() < 60.0, "{got:?}");
    }
    // With the probe radius the points are the design surface.
    let comp = register(
        &s,
        &q,
        &RegisterSettings {
            probe_radius_mm: 1.0,
            ..RegisterSettings::default()
        },
    )
    .unwrap();
    assert!(comp.rms_nm < 1e-3, "{}", comp.rms_nm);
}
