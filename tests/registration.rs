//! Conditioning-aware registration: information-matrix eigenvalues against closed forms, every
//! motion the data determine estimated (exactly on noise-free points, within its standard
//! deviation on noisy ones) and only those the noise leaves undetermined within the installation
//! range held, a known installation error recovered within its standard deviations, priors and
//! degenerate sets.

use nalgebra::{Isometry3, Matrix3, Point3, SymmetricEigen, Vector3};
use preston::io::surface::read_surface;
use preston::solver::iterate::{FormErrorModel, SplitMix64};
use preston::solver::map::BoundingBox;
use preston::solver::registration::{register, Dof, LockSource, RegisterSettings, ARCSEC_PER_RAD};
use preston::solver::surface::{Conic, Plane, Surface};
use preston::solver::Error;

/// Relative tolerance of eigenvalues computed two ways.
const EIG_REL_TOL: f64 = 1e-9;
/// Noise-free recovery of a rotation, arcsec (1e-9 rad is 2e-4 arcsec).
const EXACT_ARCSEC: f64 = 2e-4;
/// Noise-free recovery of a translation, um.
const EXACT_UM: f64 = 1e-3;
/// How far an estimate may be from the truth, in its reported standard deviations.
const SIGMAS: f64 = 3.0;

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
    // Each held motion is uncertain by the range it was held within: 0.2 deg = 720 arcsec for
    // rz, 0.5 mm = 500 um for tx and ty (the points' centroid is the design origin, so a
    // rotation about it moves no translation); the estimated ones by the noise, here none.
    let range = RegisterSettings::default();
    let want = [
        (2, range.installation_range_deg * 3600.0),
        (3, range.installation_range_mm * 1e3),
        (4, range.installation_range_mm * 1e3),
    ];
    for (k, w) in want {
        assert!(
            (reg.dof_sigma[k] - w).abs() <= EIG_REL_TOL * w,
            "{:?}",
            reg.dof_sigma
        );
    }
    for k in [0, 1, 5] {
        assert!(reg.dof_sigma[k] < EXACT_UM, "{:?}", reg.dof_sigma);
    }
    let mut undetermined = reg.undetermined();
    undetermined.sort();
    assert_eq!(undetermined, ["rz", "tx", "ty"]);
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

/// Design-frame DOFs `[rx, ry, rz]` arcsec, `[tx, ty, tz]` um as an isometry.
fn isometry(d: [f64; 6]) -> Isometry3<f64> {
    Isometry3::new(
        Vector3::new(d[3], d[4], d[5]) * 1e-3,
        Vector3::new(d[0], d[1], d[2]) / ARCSEC_PER_RAD,
    )
}

/// `rms(recovered - true) / rms(true)` of the form error, piston and tilt removed from both.
fn form_change(
    reg: &preston::solver::registration::Registration,
    x: &[f64],
    y: &[f64],
    form: &[f64],
) -> f64 {
    let (fx, fy): (Vec<f64>, Vec<f64>) = reg.design_xy_mm.iter().map(|p| (p[0], p[1])).unzip();
    let rec = remove_piston_tilt(&fx, &fy, &reg.form_error_nm);
    let tru = remove_piston_tilt(x, y, form);
    let diff: Vec<f64> = rec.iter().zip(&tru).map(|(a, b)| a - b).collect();
    rms(&diff) / rms(&tru)
}

#[test]
fn weakly_determined_motions_are_recovered_exactly_from_noise_free_points() {
    // The shipped freeform's three sliding motions have relative eigenvalues of about 1e-6, yet
    // noise-free points fix them: the installation error comes back exactly and a perfect part
    // shows no form error.
    let s = freeform();
    let (_, _, p, n) = design(&s, 51);
    let truth = [30.0, -20.0, 40.0, 50.0, -30.0, 20.0];
    let q = measure(&isometry(truth), &p, &n, &vec![0.0; p.len()]);
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    assert!(reg.status.is_converged());
    assert!(reg.locked.is_empty(), "{:?}", reg.locked);
    let got = dofs(&reg.transform);
    for k in 0..6 {
        let tol = if k < 3 { EXACT_ARCSEC } else { EXACT_UM };
        assert!((got[k] - truth[k]).abs() < tol, "{got:?} vs {truth:?}");
    }
    assert!(reg.rms_nm < 1e-3, "{} nm", reg.rms_nm);
}

#[test]
fn freeform_with_form_error_estimates_every_motion_the_data_determine() {
    // The shipped freeform with a smooth 40 nm form error, 2 nm of measurement noise and an
    // installation error of (30, -20, 40) arcsec and (50, -30, 20) um. A 40 arcsec rz on slopes
    // of 0.024 moves the surface by tens of nm, far above the noise: every motion is estimated
    // (none held), each within its reported standard deviations of the truth, and the form error
    // is recovered as well as six-DOF least squares can (the weak slides take a share of the
    // smooth form error: plain least squares changes it by about 15 %; holding them at zero
    // changed it by over 100 %).
    let s = freeform();
    let (x, y, p, n) = design(&s, 51);
    let form = FormErrorModel {
        rms_nm: 40.0,
        ..FormErrorModel::default()
    }
    .sample(&aperture(), &x, &y)
    .unwrap();
    let mut rng = SplitMix64::new(11);
    let meas: Vec<f64> = form.iter().map(|e| e + 2.0 * rng.normal()).collect();
    let truth = [30.0, -20.0, 40.0, 50.0, -30.0, 20.0];
    let q = measure(&isometry(truth), &p, &n, &meas);
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    eprintln!(
        "got {:?} sigma {:?} corr {:?} change {}",
        dofs(&reg.transform),
        reg.dof_sigma,
        reg.form_correlation,
        form_change(&reg, &x, &y, &form)
    );
    assert!(reg.status.is_converged());
    assert!(reg.locked.is_empty(), "{:?}", reg.locked);
    // The linearised six-DOF least-squares fit of the measured deviation, computed
    // independently from the design points and normals: the registration changes the form error
    // by no more than it does.
    let g = patterns(&p, &n);
    let lsq = remove_fit(&g, &meas);
    let lsq_form: Vec<f64> = lsq.clone();
    let tru = remove_piston_tilt(&x, &y, &form);
    let lsq_pt = remove_piston_tilt(&x, &y, &lsq_form);
    let lsq_change = rms(&lsq_pt
        .iter()
        .zip(&tru)
        .map(|(a, b)| a - b)
        .collect::<Vec<_>>())
        / rms(&tru);
    let change = form_change(&reg, &x, &y, &form);
    eprintln!("change {change}, least squares {lsq_change}");
    assert!(
        change <= lsq_change * 1.01 + 1e-3,
        "{change} vs least squares {lsq_change}"
    );
    // Every motion is estimated, so none could absorb more of the form error.
    assert!(
        reg.form_correlation.iter().all(|c| *c < 1e-6),
        "{:?}",
        reg.form_correlation
    );
}

#[test]
fn motions_the_noise_leaves_undetermined_are_held_with_their_reason() {
    // The freeform's three slides have relative eigenvalues of about 1e-6: on a kinematic mount
    // known to 5 um and 2 arcsec, 5 nm of noise determines them well within that range (all six
    // estimated), while 1 um of noise leaves them uncertain by more than the range: they are
    // held, each with its standard deviation against the range as the reason, and the
    // well-determined tilts and piston are still estimated.
    let s = freeform();
    let (_, _, p, n) = design(&s, 51);
    let tight = RegisterSettings {
        installation_range_mm: 0.005,
        installation_range_deg: 2.0 / 3600.0,
        ..RegisterSettings::default()
    };
    for (noise_nm, held) in [(5.0, 0), (1000.0, 3)] {
        let mut rng = SplitMix64::new(4);
        let e: Vec<f64> = (0..p.len()).map(|_| noise_nm * rng.normal()).collect();
        let q = measure(&Isometry3::identity(), &p, &n, &e);
        let reg = register(&s, &q, &tight).unwrap();
        let weak: Vec<_> = reg
            .locked
            .iter()
            .filter(|l| l.source == LockSource::Weak)
            .collect();
        assert_eq!(weak.len(), held, "noise {noise_nm} nm: {:?}", reg.locked);
        for l in &weak {
            assert!(
                l.reason.contains("standard deviation") && l.reason.contains("installation range"),
                "{l:?}"
            );
            // A held slide has no rx, ry or tz component to speak of.
            assert!(
                l.direction[0].abs().max(l.direction[1].abs()) < 0.1,
                "{l:?}"
            );
        }
        for k in [0, 1, 5] {
            assert!(reg.dof_sigma[k] > 0.0, "{:?}", reg.dof_sigma);
        }
    }
}

#[test]
fn installation_error_on_the_freeform_is_recovered_within_three_sigma() {
    // Installation error in the DOFs the freeform determines (tilts and piston) plus a 43 nm
    // form error orthogonal to every rigid motion (its rigid part is installation error by
    // definition) and 5 nm of white noise: all six motions are recovered within 3 sigma of the
    // truth, the weakly determined slides included.
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
    assert!(reg.locked.is_empty(), "{:?}", reg.locked);
    for k in 0..6 {
        let sig = reg.dof_sigma[k];
        assert!(sig > 0.0);
        assert!(
            (got[k] - truth[k]).abs() <= SIGMAS * sig,
            "{} {got:?} {:?}",
            Dof::ALL[k].name(),
            reg.dof_sigma
        );
    }
    // The standard deviations are Gauss-Markov's, `s^2 (H^T H)^-1` with the design-frame
    // patterns `h = [p x n, n]` and `s^2 = sum r^2 / (N - 6)`, computed here independently.
    let mut hth = nalgebra::Matrix6::<f64>::zeros();
    for (pi, ni) in p.iter().zip(&n) {
        let nv = Vector3::from(*ni);
        let r = Vector3::from(*pi).cross(&nv);
        let h = nalgebra::Vector6::new(r.x, r.y, r.z, nv.x, nv.y, nv.z);
        hth += h * h.transpose();
    }
    let s2_mm2 = reg
        .form_error_nm
        .iter()
        .map(|r| (r * 1e-6).powi(2))
        .sum::<f64>()
        / (p.len() - 6) as f64;
    let cov = hth.try_inverse().unwrap() * s2_mm2;
    for k in 0..6 {
        let unit = if k < 3 { ARCSEC_PER_RAD } else { 1e3 };
        let expect = cov[(k, k)].sqrt() * unit;
        assert!(
            (reg.dof_sigma[k] - expect).abs() < 0.05 * expect,
            "{}: {} vs {expect}",
            Dof::ALL[k].name(),
            reg.dof_sigma[k]
        );
    }
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
    // Lock tz with the in-plane motions: the piston stays in the form error (4 um) and tz stays
    // zero. (With tz alone held, the 4 um piston swamps rz, which is held, and ty, then
    // determined, takes a share of the piston through the surface's curvature, as the CLI's
    // `register_locks_motions_by_name` says of this surface.)
    let mut lock = [false; 6];
    for d in [Dof::Tz, Dof::Rz, Dof::Tx, Dof::Ty] {
        lock[d.index()] = true;
    }
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
    // rx and ry at their bounds; the misfit they leave may push rz to its bound as well.
    assert_eq!(bound[..2], ["rx", "ry"], "{bound:?}");
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
    assert!(
        (got[0] - 40.0).abs() < EXACT_ARCSEC && (got[5] - 4.0).abs() < EXACT_UM,
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
    // The tilts stay small; the weakly determined slides take what they can of the offset
    // surface's departure from a rigid copy of the design.
    for k in 0..2 {
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

/// A part of local shape `f(u, v) = sum c u^m v^n` (mm) whose centre sits at `x = x0` of the
/// design: `z(x, y) = f(x - x0, y)` as an XY polynomial in `x` (binomial expansion, exact; the
/// constant, a piston of the design, dropped), on `base` (curvature, conic) about the origin.
fn shifted_part(terms: &[(u32, u32, f64)], x0: f64, base: (f64, f64)) -> Surface {
    let mut coef = std::collections::BTreeMap::<(u32, u32), f64>::new();
    for &(m, n, c) in terms {
        let mut binom = 1.0;
        for j in 0..=m {
            // C(m, j) x^j (-x0)^(m - j)
            if j > 0 {
                binom *= (m - j + 1) as f64 / j as f64;
            }
            if j + n > 0 {
                *coef.entry((j, n)).or_insert(0.0) += c * binom * (-x0).powi((m - j) as i32);
            }
        }
    }
    let terms: Vec<serde_json::Value> = coef
        .into_iter()
        .filter(|(_, c)| *c != 0.0)
        .map(|((m, n), c)| serde_json::json!({"m": m, "n": n, "coef_mm": c}))
        .collect();
    serde_json::from_value(serde_json::json!({
        "type": "xy_polynomial",
        "curvature_per_mm": base.0,
        "conic": base.1,
        "norm_radius_mm": 1.0,
        "terms": terms,
    }))
    .unwrap()
}

/// Design points and normals on an `n x n` grid over a 50 x 50 mm aperture centred at `(x0, 0)`.
fn off_axis_design(s: &Surface, n: usize, x0: f64) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let (mut p, mut nn) = (vec![], vec![]);
    for j in 0..n {
        for i in 0..n {
            let x = x0 - 25.0 + 50.0 * i as f64 / (n - 1) as f64;
            let y = -25.0 + 50.0 * j as f64 / (n - 1) as f64;
            let d = s.derivs(x, y).unwrap();
            p.push([x, y, d.z]);
            nn.push(d.normal());
        }
    }
    (p, nn)
}

/// The local shape of the off-axis tests: a toric cap of radii 1000 mm in x and 800 mm in y
/// (nearly spherical: its two slides are weakly determined, relative eigenvalues about 1e-11).
const TORIC: [(u32, u32, f64); 2] = [(2, 0, 1.0 / 2000.0), (0, 2, 1.0 / 1600.0)];
/// Centre of the off-axis aperture, mm.
const OFF_AXIS_MM: f64 = 300.0;
/// Relative agreement of figures that do not depend on where the design origin is.
const FRAME_REL_TOL: f64 = 1e-6;

/// Points of the toric part centred at `(x0, 0)`, with `noise_nm` of white noise along the
/// normal, mounted with the installation error `truth` ([rx, ry, rz] arcsec about the part's
/// centre, [tx, ty, tz] um): the design, the measured points and the design points.
fn toric_case(x0: f64, noise_nm: f64, truth: [f64; 6]) -> (Surface, Vec<[f64; 3]>) {
    let s = shifted_part(&TORIC, x0, (0.0, 0.0));
    let (p, n) = off_axis_design(&s, 41, x0);
    let mut rng = SplitMix64::new(7);
    let e: Vec<f64> = (0..p.len()).map(|_| noise_nm * rng.normal()).collect();
    // A rotation about the part's centre `c`: `p -> c + R (p - c) + t`.
    let c = Vector3::new(x0, 0.0, s.sag_mm(x0, 0.0).unwrap());
    let rot = nalgebra::Rotation3::new(Vector3::new(truth[0], truth[1], truth[2]) / ARCSEC_PER_RAD);
    let t = Vector3::new(truth[3], truth[4], truth[5]) * 1e-3 + c - rot * c;
    let m = Isometry3::from_parts(t.into(), rot.into());
    (s, measure(&m, &p, &n, &e))
}

fn weak_labels(reg: &preston::solver::registration::Registration) -> Vec<String> {
    let mut v: Vec<String> = reg
        .locked
        .iter()
        .filter(|l| l.source == LockSource::Weak)
        .map(|l| l.label.clone())
        .collect();
    v.sort();
    v
}

#[test]
fn a_weak_motion_is_held_by_its_noise_against_its_range_not_refused_by_its_eigenvalue() {
    // The toric part 300 mm off axis with 0.5 um of noise: its slides have relative
    // eigenvalues of about 1e-11, below the 1e-10 at which an eigenvalue test called the
    // registration rank-deficient (and that refusal came and went with the installation range).
    // The slides carry information, only too little for the noise: they are held, each with
    // its standard deviation against its range, at 0.2 and at 0.25 degrees alike, and nothing
    // is refused.
    let (s, q) = toric_case(OFF_AXIS_MM, 500.0, [0.0; 6]);
    let mut held = Vec::new();
    for deg in [0.2, 0.25] {
        let set = RegisterSettings {
            installation_range_deg: deg,
            ..RegisterSettings::default()
        };
        let reg = register(&s, &q, &set).unwrap();
        let ev = reg.information_eigenvalues;
        assert!(ev[5] > 0.0 && ev[5] / ev[0] < 1e-10, "{ev:?}");
        assert!(
            reg.refuse_undetermined("--lock").is_ok(),
            "{:?}",
            reg.locked
        );
        assert!(reg.undetermined().is_empty());
        for l in reg.locked.iter().filter(|l| l.source == LockSource::Weak) {
            assert!(
                l.reason.contains("standard deviation") && l.reason.contains("exceeds"),
                "{l:?}"
            );
        }
        held.push(weak_labels(&reg));
    }
    assert_eq!(held[0], ["tx", "ty"], "{held:?}");
    assert_eq!(held[0], held[1]);
}

#[test]
fn a_held_motion_is_as_uncertain_as_the_range_it_was_held_within() {
    // On a mount known to 0.01 deg (36 arcsec), 0.5 um of noise leaves the toric part's rz
    // uncertain by about 46 arcsec: it is held, and its reported standard deviation is the
    // 36 arcsec it was held within, so the 30 arcsec the part was really turned by is within
    // it (the estimated motions' deviations, of the noise, are about an arcsecond or less).
    let truth = [0.0, 0.0, 30.0, 0.0, 0.0, 0.0];
    let (s, q) = toric_case(0.0, 500.0, truth);
    let set = RegisterSettings {
        installation_range_deg: 0.01,
        ..RegisterSettings::default()
    };
    let reg = register(&s, &q, &set).unwrap();
    assert!(
        weak_labels(&reg).contains(&"rz".to_string()),
        "{:?}",
        reg.locked
    );
    let range_arcsec = set.installation_range_deg * 3600.0;
    assert!(
        (reg.dof_sigma[2] - range_arcsec).abs() <= FRAME_REL_TOL * range_arcsec,
        "{:?}",
        reg.dof_sigma
    );
    let got = dofs(&reg.transform);
    assert!(
        (got[2] - truth[2]).abs() <= reg.dof_sigma[2],
        "{got:?} {:?}",
        reg.dof_sigma
    );
}

#[test]
fn held_motions_are_rigid_body_motions_the_user_can_read() {
    // Each held motion is one of rx .. tz (about the points' centroid), its direction that
    // coordinate alone, not a mixture of eigen-directions such as `0.998 tx + 0.062 ry`.
    let (s, q) = toric_case(OFF_AXIS_MM, 500.0, [0.0; 6]);
    let reg = register(&s, &q, &RegisterSettings::default()).unwrap();
    let weak: Vec<_> = reg
        .locked
        .iter()
        .filter(|l| l.source == LockSource::Weak)
        .collect();
    assert!(!weak.is_empty());
    for l in weak {
        let k = Dof::ALL
            .iter()
            .position(|d| d.name() == l.label)
            .unwrap_or_else(|| panic!("{l:?}"));
        for (j, c) in l.direction.iter().enumerate() {
            assert_eq!(*c, if j == k { 1.0 } else { 0.0 }, "{l:?}");
        }
    }
}

#[test]
fn the_installation_range_is_about_the_part_not_the_design_origin() {
    // The same part, the same noise (5 um) and the same installation error (a 200 arcsec turn
    // about the part's own centre), with the part at the design origin and 300 mm off axis:
    // the registration holds the same motions, estimates the same rotations with the same
    // standard deviations, and finds the same form error. A range taken about the design origin
    // counted the off-axis turn as a 300 mm x angle translation and held it.
    let truth = [0.0, 0.0, 200.0, 0.0, 0.0, 0.0];
    let regs: Vec<_> = [0.0, OFF_AXIS_MM]
        .iter()
        .map(|&x0| {
            let (s, q) = toric_case(x0, 5000.0, truth);
            register(&s, &q, &RegisterSettings::default()).unwrap()
        })
        .collect();
    assert_eq!(weak_labels(&regs[0]), weak_labels(&regs[1]));
    assert!(
        !weak_labels(&regs[1]).contains(&"rz".to_string()),
        "{:?}",
        regs[1].locked
    );
    let (a, b) = (dofs(&regs[0].transform), dofs(&regs[1].transform));
    for k in 0..3 {
        let (sa, sb) = (regs[0].dof_sigma[k], regs[1].dof_sigma[k]);
        assert!((sa - sb).abs() <= FRAME_REL_TOL * sa, "{k}: {sa} vs {sb}");
        assert!((a[k] - b[k]).abs() <= FRAME_REL_TOL * sa, "{a:?} vs {b:?}");
    }
    assert!(
        (b[2] - truth[2]).abs() <= SIGMAS * regs[1].dof_sigma[2],
        "{b:?}"
    );
    let diff = regs[0]
        .form_error_nm
        .iter()
        .zip(&regs[1].form_error_nm)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max);
    assert!(
        diff <= FRAME_REL_TOL * rms(&regs[0].form_error_nm),
        "{diff} nm"
    );
}
