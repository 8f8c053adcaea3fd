//! Geometry integration tests with known answers: fitting, closest point, probe compensation
//! and registration on an off-axis freeform.

#[path = "support/geometry_cases.rs"]
mod cases;

use cases::{design_points, grid, off_axis_freeform, order10_polynomial, Rng};
use nalgebra::{Isometry3, Matrix6, Point3, Vector3, Vector6};
use preston::solver::fit::{fit_xy_polynomial, ConicBase, FitSettings};
use preston::solver::registration::{compensate_probe, register, RegisterSettings, Robust};
use preston::solver::surface::{Conic, Surface, XyPolynomial, XyTerm};
use preston::solver::Error;

/// Coefficient tolerance of a noise-free fit, mm.
const COEF_TOL_MM: f64 = 1e-10;
/// Noise-free registration: translation tolerance, mm, and rotation tolerance, rad.
const TRANSLATION_TOL_MM: f64 = 1e-6;
const ROTATION_TOL_RAD: f64 = 1e-9;
/// Probe compensation: distance of the compensated point from the surface, mm.
const ON_SURFACE_TOL_MM: f64 = 1e-9;

fn sag_all(s: &XyPolynomial, x: &[f64], y: &[f64]) -> Vec<f64> {
    let s = Surface::XyPolynomial(s.clone());
    x.iter()
        .zip(y)
        .map(|(a, b)| s.sag_mm(*a, *b).unwrap())
        .collect()
}

#[test]
fn order10_coefficients_are_recovered_exactly() {
    let truth = order10_polynomial(1.0 / 400.0, -0.8, 60.0);
    let (x, y) = grid(41, 41, (-50.0, 50.0), (-45.0, 45.0));
    let z = sag_all(&truth, &x, &y);
    let settings = FitSettings {
        order: 10,
        norm_radius_mm: 60.0,
        base: ConicBase::Fixed {
            curvature_per_mm: 1.0 / 400.0,
            conic: -0.8,
        },
        ..FitSettings::default()
    };
    let f = fit_xy_polynomial(&x, &y, &z, &settings).unwrap();
    eprintln!(
        "order 10: condition {:.3e}, rms {} nm",
        f.condition_number, f.rms_nm
    );
    assert_eq!(f.surface.terms.len(), 65);
    for (got, want) in f.surface.terms.iter().zip(&truth.terms) {
        assert_eq!((got.m, got.n), (want.m, want.n));
        assert!(
            (got.coef_mm - want.coef_mm).abs() < COEF_TOL_MM,
            "m={} n={}: {} vs {}",
            got.m,
            got.n,
            got.coef_mm,
            want.coef_mm
        );
    }
    assert!(
        f.rms_nm < 1e-4 && f.pv_nm < 1e-3,
        "rms {} pv {}",
        f.rms_nm,
        f.pv_nm
    );
    assert!(
        f.condition_number > 1.0 && f.condition_number < 1e8,
        "{}",
        f.condition_number
    );
}

#[test]
fn conic_curvature_and_constant_are_recovered() {
    // Conic with tilts (order 1) and with order-3 terms: c and k enter nonlinearly.
    for order in [1u32, 3] {
        let (c, k) = (1.0 / 250.0, -0.65);
        let mut terms = vec![
            XyTerm {
                m: 1,
                n: 0,
                coef_mm: 0.02,
            },
            XyTerm {
                m: 0,
                n: 1,
                coef_mm: -0.03,
            },
        ];
        if order == 3 {
            terms.push(XyTerm {
                m: 2,
                n: 1,
                coef_mm: 0.01,
            });
            terms.push(XyTerm {
                m: 0,
                n: 3,
                coef_mm: -0.005,
            });
        }
        let truth = XyPolynomial {
            curvature_per_mm: c,
            conic: k,
            norm_radius_mm: 80.0,
            terms,
        };
        let (x, y) = grid(41, 41, (-80.0, 80.0), (-80.0, 80.0));
        let z = sag_all(&truth, &x, &y);
        let settings = FitSettings {
            order,
            norm_radius_mm: 80.0,
            base: ConicBase::Fitted,
            ..FitSettings::default()
        };
        let f = fit_xy_polynomial(&x, &y, &z, &settings).unwrap();
        eprintln!(
            "order {order} conic fit: c err {:e}, k err {:e}, {} iterations, condition {:.3e}",
            f.surface.curvature_per_mm - c,
            f.surface.conic - k,
            f.iterations,
            f.condition_number
        );
        assert!(
            (f.surface.curvature_per_mm - c).abs() < 1e-12 * c,
            "order {order}: c {} vs {c}",
            f.surface.curvature_per_mm
        );
        assert!(
            (f.surface.conic - k).abs() < 1e-6,
            "order {order}: k {}",
            f.surface.conic
        );
        for t in &truth.terms {
            let got = f
                .surface
                .terms
                .iter()
                .find(|g| (g.m, g.n) == (t.m, t.n))
                .unwrap();
            assert!((got.coef_mm - t.coef_mm).abs() < 1e-8, "{t:?} vs {got:?}");
        }
        assert!(f.rms_nm < 1e-3, "order {order}: rms {}", f.rms_nm);
    }
}

#[test]
fn fit_rejects_conic_outside_domain() {
    let (x, y) = grid(11, 11, (-60.0, 60.0), (-60.0, 60.0));
    let z = vec![0.0; x.len()];
    let settings = FitSettings {
        order: 2,
        norm_radius_mm: 60.0,
        base: ConicBase::Fixed {
            curvature_per_mm: 1.0 / 50.0,
            conic: 0.0,
        },
        ..FitSettings::default()
    };
    assert!(matches!(
        fit_xy_polynomial(&x, &y, &z, &settings),
        Err(Error::Geometry(_))
    ));
}

/// Brute force: the smallest distance from `p` to surface samples on ever finer grids around the
/// best sample (window 40 mm at 0.5 mm, then 1.5 mm at 0.01 mm, then 0.03 mm at 2e-4 mm).
fn brute_force_closest(s: &Surface, p: [f64; 3]) -> ([f64; 3], f64) {
    let mut centre = [p[0], p[1]];
    let mut best = ([0.0; 3], f64::INFINITY);
    for (half, step) in [(20.0, 0.5), (0.75, 0.01), (0.015, 2e-4), (3e-4, 4e-6)] {
        let n = (2.0 * half / step) as i64;
        let c0 = centre;
        for i in 0..=n {
            for j in 0..=n {
                let x = c0[0] - half + i as f64 * step;
                let y = c0[1] - half + j as f64 * step;
                if let Ok(z) = s.sag_mm(x, y) {
                    let d = ((x - p[0]).powi(2) + (y - p[1]).powi(2) + (z - p[2]).powi(2)).sqrt();
                    if d < best.1 {
                        best = ([x, y, z], d);
                        centre = [x, y];
                    }
                }
            }
        }
    }
    best
}

#[test]
fn closest_point_matches_brute_force_on_freeform() {
    let s = off_axis_freeform();
    let mut rng = Rng::new(11);
    for _ in 0..12 {
        let x = -150.0 + 300.0 * rng.uniform();
        let y = 290.0 + 100.0 * rng.uniform();
        let d = s.derivs(x, y).unwrap();
        let n = d.normal();
        let h = -8.0 + 16.0 * rng.uniform();
        // Off the normal too, so the foot is not the generating point.
        let p = [x + h * n[0] + 1.3, y + h * n[1] - 0.7, d.z + h * n[2]];
        let cp = s.closest_point(p).unwrap();
        let (foot, dist) = brute_force_closest(&s, p);
        let newton_dist = cp.signed_distance_mm.abs();
        // Newton finds the true minimum: never worse than the samples, and within their resolution.
        assert!(newton_dist <= dist + 1e-12, "{newton_dist} vs {dist}");
        assert!(dist - newton_dist < 1e-8, "{newton_dist} vs {dist}");
        for k in 0..3 {
            assert!(
                (cp.point_mm[k] - foot[k]).abs() < 1e-4,
                "{:?} vs {foot:?}",
                cp.point_mm
            );
        }
    }
}

#[test]
fn probe_compensation_lands_on_tilted_sphere_and_freeform() {
    let probe = 3.0;
    // Sphere of radius 120 mm sampled up to r = 85 mm: normals tilted by up to 45 degrees.
    let r = 120.0;
    let sphere = Surface::Conic(Conic {
        curvature_per_mm: 1.0 / r,
        conic: 0.0,
    });
    let (x, y) = grid(15, 15, (-60.0, 60.0), (-60.0, 60.0));
    let mut tips = Vec::new();
    for (&xi, &yi) in x.iter().zip(&y) {
        let d = sphere.derivs(xi, yi).unwrap();
        let n = d.normal();
        tips.push([xi + probe * n[0], yi + probe * n[1], d.z + probe * n[2]]);
    }
    let pts = compensate_probe(&sphere, &tips, probe).unwrap();
    for p in &pts {
        let dist = ((p[0] * p[0] + p[1] * p[1] + (p[2] - r).powi(2)).sqrt() - r).abs();
        assert!(dist < ON_SURFACE_TOL_MM, "{dist}");
    }
    let ff = off_axis_freeform();
    let (design, normals) = design_points(&ff, 21, 9);
    let tips: Vec<[f64; 3]> = design
        .iter()
        .zip(&normals)
        .map(|(s, n)| {
            [
                s[0] + probe * n[0],
                s[1] + probe * n[1],
                s[2] + probe * n[2],
            ]
        })
        .collect();
    let pts = compensate_probe(&ff, &tips, probe).unwrap();
    for (p, s) in pts.iter().zip(&design) {
        let cp = ff.closest_point(*p).unwrap();
        assert!(cp.signed_distance_mm.abs() < ON_SURFACE_TOL_MM);
        let e = ((p[0] - s[0]).powi(2) + (p[1] - s[1]).powi(2) + (p[2] - s[2]).powi(2)).sqrt();
        assert!(e < ON_SURFACE_TOL_MM, "{e}");
    }
}

/// A known installation error: rotation of 0.2 degree and translation of 0.5 mm.
fn true_transform() -> Isometry3<f64> {
    let axis = Vector3::new(1.0, -2.0, 1.5).normalize();
    let t = Vector3::new(0.3, -1.0, 0.6).normalize() * 0.5;
    Isometry3::new(t, axis * 0.2f64.to_radians())
}

/// Measured points `T^-1 (s + e n)` for design points `s`, normal noise `e`.
fn measured(design: &[[f64; 3]], normals: &[[f64; 3]], noise: &[f64]) -> Vec<[f64; 3]> {
    let inv = true_transform().inverse();
    design
        .iter()
        .zip(normals)
        .zip(noise)
        .map(|((s, n), e)| {
            let p = Point3::new(s[0] + e * n[0], s[1] + e * n[1], s[2] + e * n[2]);
            let q = inv * p;
            [q.x, q.y, q.z]
        })
        .collect()
}

/// Estimation error of `m` as (rotation vector, translation at the centroid `c`) and the
/// statistical standard deviations of those parameters for normal noise `sigma` (mm):
/// `sigma^2 (J^T J)^-1`, `J` rows `[(s - c) x n, n]` at the true design points.
fn errors_and_sigmas(
    m: &Isometry3<f64>,
    design: &[[f64; 3]],
    normals: &[[f64; 3]],
    sigma: f64,
) -> ([f64; 6], [f64; 6]) {
    let mut c = Vector3::zeros();
    for s in design {
        c += Vector3::from(*s);
    }
    c /= design.len() as f64;
    let e = m * true_transform().inverse();
    let w = e.rotation.scaled_axis();
    let tc = (e * Point3::from(c)).coords - c;
    let mut jtj = Matrix6::zeros();
    for (s, n) in design.iter().zip(normals) {
        let nv = Vector3::from(*n);
        let r = (Vector3::from(*s) - c).cross(&nv);
        let row = Vector6::new(r.x, r.y, r.z, nv.x, nv.y, nv.z);
        jtj += row * row.transpose();
    }
    let cov = jtj.try_inverse().unwrap() * (sigma * sigma);
    let sig: [f64; 6] = std::array::from_fn(|k| cov[(k, k)].sqrt());
    ([w.x, w.y, w.z, tc.x, tc.y, tc.z], sig)
}

/// The default settings: this mirror's three sliding motions have relative eigenvalues of 2e-10
/// to 4e-8, yet noise-free points determine them exactly and white noise disturbs them only by
/// their statistical error, so the default estimates all six.
fn unlocked() -> RegisterSettings {
    RegisterSettings::default()
}

#[test]
fn registration_noise_free_recovers_transform() {
    let s = off_axis_freeform();
    let (design, normals) = design_points(&s, 51, 51);
    let q = measured(&design, &normals, &vec![0.0; design.len()]);
    let reg = register(&s, &q, &unlocked()).unwrap();
    eprintln!(
        "noise-free: {} iterations, rms {} nm",
        reg.iterations, reg.rms_nm
    );
    assert!(
        reg.status.is_converged() && reg.iterations <= 10,
        "{} iterations",
        reg.iterations
    );
    // Every motion is determined by noise-free points, however weakly: none is held.
    assert!(reg.locked.is_empty(), "{:?}", reg.locked);
    let truth = true_transform();
    let rt = truth.translation.vector;
    let t = reg.translation_mm();
    for k in 0..3 {
        assert!(
            (t[k] - rt[k]).abs() < TRANSLATION_TOL_MM,
            "t {t:?} vs {rt:?}"
        );
    }
    let w_err = (reg.transform.rotation * truth.rotation.inverse()).scaled_axis();
    assert!(w_err.amax() < ROTATION_TOL_RAD, "rotation error {w_err:?}");
    let wt = truth.rotation.scaled_axis();
    let w = reg.rotation_rad();
    for k in 0..3 {
        assert!((w[k] - wt[k]).abs() < ROTATION_TOL_RAD);
        assert!(
            (reg.rotation_arcsec()[k] - wt[k] * 180.0 * 3600.0 / std::f64::consts::PI).abs() < 1e-3
        );
    }
    assert!(reg.rms_nm < 1e-3, "rms {} nm", reg.rms_nm);
    // The 4x4 matrix maps measured points onto the design surface.
    let mtx = reg.matrix();
    for (qi, si) in q.iter().zip(&design).step_by(97) {
        for r in 0..3 {
            let v = mtx[r][0] * qi[0] + mtx[r][1] * qi[1] + mtx[r][2] * qi[2] + mtx[r][3];
            assert!((v - si[r]).abs() < 1e-6);
        }
    }
    assert_eq!(mtx[3], [0.0, 0.0, 0.0, 1.0]);
}

#[test]
fn registration_with_noise_and_outliers_is_within_statistical_error() {
    let s = off_axis_freeform();
    let (design, normals) = design_points(&s, 51, 51);
    let sigma = 2e-4; // 0.2 um
    let mut rng = Rng::new(5);
    let noise: Vec<f64> = (0..design.len()).map(|_| sigma * rng.normal()).collect();
    let q = measured(&design, &normals, &noise);
    let reg = register(&s, &q, &unlocked()).unwrap();
    assert!(
        reg.status.is_converged() && reg.iterations <= 10,
        "{} iterations",
        reg.iterations
    );
    let (err, sig) = errors_and_sigmas(&reg.transform, &design, &normals, sigma);
    eprintln!(
        "noisy: {} iterations, errors {err:?}, sigmas {sig:?}",
        reg.iterations
    );
    for k in 0..6 {
        assert!(
            err[k].abs() <= 3.0 * sig[k],
            "parameter {k}: error {} sigma {}",
            err[k],
            sig[k]
        );
    }
    // Form error is the injected noise.
    for (f, e) in reg.form_error_nm.iter().zip(&noise) {
        assert!(
            (f - e * 1e6).abs() < 0.2 * sigma * 1e6,
            "{f} vs {}",
            e * 1e6
        );
    }
    assert!((reg.rms_nm - 200.0).abs() < 20.0, "rms {}", reg.rms_nm);

    // 2 % gross outliers of 20 to 60 um, both signs.
    let mut noisy = noise.clone();
    let mut count = 0;
    for (i, e) in noisy.iter_mut().enumerate() {
        if rng.uniform() < 0.02 {
            let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
            *e += sign * (0.02 + 0.04 * rng.uniform());
            count += 1;
        }
    }
    assert!(count > 30);
    let q = measured(&design, &normals, &noisy);
    let plain = register(&s, &q, &unlocked()).unwrap();
    let robust = register(
        &s,
        &q,
        &RegisterSettings {
            robust: Robust::HUBER,
            ..unlocked()
        },
    )
    .unwrap();
    assert!(
        robust.status.is_converged(),
        "{} iterations",
        robust.iterations
    );
    let (err_r, _) = errors_and_sigmas(&robust.transform, &design, &normals, sigma);
    let (err_p, _) = errors_and_sigmas(&plain.transform, &design, &normals, sigma);
    eprintln!(
        "outliers: robust {} iterations, errors {err_r:?}; plain errors {err_p:?}",
        robust.iterations
    );
    let norm = |e: &[f64; 6]| (0..6).map(|k| (e[k] / sig[k]).powi(2)).sum::<f64>().sqrt();
    for k in 0..6 {
        assert!(
            err_r[k].abs() <= 10.0 * sig[k],
            "parameter {k}: robust error {} sigma {}",
            err_r[k],
            sig[k]
        );
    }
    // The weights help: the robust estimate is closer than plain least squares.
    assert!(
        norm(&err_r) < norm(&err_p),
        "{} vs {}",
        norm(&err_r),
        norm(&err_p)
    );
    // The outliers are down-weighted.
    let low = robust.weights.iter().filter(|w| **w < 0.1).count();
    assert!(low >= count * 9 / 10, "{low} of {count}");
}

#[test]
fn registration_with_probe_radius_and_degenerate_inputs() {
    let s = off_axis_freeform();
    let (design, normals) = design_points(&s, 25, 11);
    let probe = 1.5;
    let tips: Vec<f64> = vec![probe; design.len()];
    let q = measured(&design, &normals, &tips);
    let reg = register(
        &s,
        &q,
        &RegisterSettings {
            probe_radius_mm: probe,
            ..unlocked()
        },
    )
    .unwrap();
    let rt = true_transform().translation.vector;
    let t = reg.translation_mm();
    for k in 0..3 {
        assert!((t[k] - rt[k]).abs() < TRANSLATION_TOL_MM);
    }
    assert!(reg.rms_nm < 1e-3);
    for (p, d) in reg.surface_points_mm.iter().zip(&design) {
        for k in 0..3 {
            assert!((p[k] - d[k]).abs() < 1e-8);
        }
    }
    // Too few and collinear points.
    assert!(matches!(
        register(&s, &q[..5], &RegisterSettings::default()),
        Err(Error::Geometry(_))
    ));
    let line: Vec<[f64; 3]> = (0..20).map(|i| [i as f64, 300.0, 40.0]).collect();
    assert!(matches!(
        register(&s, &line, &RegisterSettings::default()),
        Err(Error::Geometry(_))
    ));
}
