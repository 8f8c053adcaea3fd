//! `preston fit`, `preston register` and `preston surface` end to end, through files, with known
//! answers: coefficients that generated the points, a rigid transform that displaced them, and
//! the closed-form sag of a sphere.

mod common;

use common::{ok, preston, s, SENSITIVITY_KEYS};
use std::fmt::Write as _;
use std::path::Path;

/// Coefficients recovered from noise-free points, relative to the largest coefficient.
const FIT_COEF_TOL: f64 = 1e-9;
/// Translations of a noise-free registration, um (the issue asks 1e-6 mm).
const TRANSLATION_TOL_UM: f64 = 1e-3;
/// Rotations of a noise-free registration, arcsec (1e-8 rad = 2e-3 arcsec).
const ROTATION_TOL_ARCSEC: f64 = 2e-3;
/// Sag written by `preston surface` against the closed form, mm.
const SAG_TOL_MM: f64 = 1e-12;

/// Sag of the test freeform: a conic (c, k) plus `sum coef (x/R)^m (y/R)^n`.
const C: f64 = 1.0 / 800.0;
const K: f64 = -0.5;
const R_NORM: f64 = 40.0;
const TERMS: [(u32, u32, f64); 6] = [
    (1, 1, 0.02),
    (2, 1, -0.015),
    (0, 3, 0.01),
    (3, 0, 0.008),
    (2, 2, -0.004),
    (1, 3, 0.003),
];

fn sag(x: f64, y: f64) -> f64 {
    let r2 = x * x + y * y;
    let conic = C * r2 / (1.0 + (1.0 - (1.0 + K) * C * C * r2).sqrt());
    conic
        + TERMS
            .iter()
            .map(|&(m, n, a)| a * (x / R_NORM).powi(m as i32) * (y / R_NORM).powi(n as i32))
            .sum::<f64>()
}

fn surface_json() -> String {
    let terms: Vec<String> = TERMS
        .iter()
        .map(|(m, n, a)| format!(r#"{{"m":{m},"n":{n},"coef_mm":{a}}}"#))
        .collect();
    format!(
        r#"{{"type":"xy_polynomial","curvature_per_mm":{C},"conic":{K},"norm_radius_mm":{R_NORM},"terms":[{}]}}"#,
        terms.join(",")
    )
}

/// Grid points `(x, y, sag)` over a 60 x 60 mm aperture.
fn design_points() -> Vec<[f64; 3]> {
    let mut p = Vec::new();
    for j in 0..21 {
        for i in 0..21 {
            let (x, y) = (-30.0 + 3.0 * i as f64, -30.0 + 3.0 * j as f64);
            p.push([x, y, sag(x, y)]);
        }
    }
    p
}

fn write_points(path: &Path, pts: &[[f64; 3]]) {
    let mut text = String::from("x_mm,y_mm,z_mm\n");
    for p in pts {
        writeln!(text, "{:.17e},{:.17e},{:.17e}", p[0], p[1], p[2]).unwrap();
    }
    std::fs::write(path, text).unwrap();
}

/// Rotation matrix of the rotation vector `w` (rad), Rodrigues' formula.
fn rotation(w: [f64; 3]) -> [[f64; 3]; 3] {
    let th = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    let k = [w[0] / th, w[1] / th, w[2] / th];
    let (s, c) = th.sin_cos();
    let mut r = [[0.0; 3]; 3];
    let kx = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    for a in 0..3 {
        for b in 0..3 {
            let kk: f64 = (0..3).map(|q| kx[a][q] * kx[q][b]).sum();
            r[a][b] = f64::from(u8::from(a == b)) + s * kx[a][b] + (1.0 - c) * kk;
        }
    }
    r
}

#[test]
fn fit_recovers_generating_coefficients() {
    let dir = tempfile::tempdir().unwrap();
    let pts_path = dir.path().join("points.csv");
    write_points(&pts_path, &design_points());
    let out = dir.path().join("surface.json");
    let c = C.to_string();
    let k = K.to_string();
    let r = preston(&[
        "fit",
        "--points",
        s(&pts_path),
        "--order",
        "4",
        "--norm-radius-mm",
        "40",
        "--curvature-per-mm",
        &c,
        "--conic",
        &k,
        "--out",
        s(&out),
    ]);
    ok(&r);
    let summary: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert!(summary["rms_nm"].as_f64().unwrap() < 1e-3, "{summary}");
    assert!(summary["pv_nm"].as_f64().unwrap() < 1e-2, "{summary}");
    let surface: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(surface["type"], "xy_polynomial");
    let terms = surface["terms"].as_array().unwrap();
    // Order 4 has 14 monomials with 1 <= m + n <= 4.
    assert_eq!(terms.len(), 14);
    let scale = TERMS.iter().map(|t| t.2.abs()).fold(0.0, f64::max);
    for t in terms {
        let (m, n) = (t["m"].as_u64().unwrap(), t["n"].as_u64().unwrap());
        let want = TERMS
            .iter()
            .find(|&&(tm, tn, _)| u64::from(tm) == m && u64::from(tn) == n)
            .map_or(0.0, |t| t.2);
        let got = t["coef_mm"].as_f64().unwrap();
        assert!(
            (got - want).abs() < FIT_COEF_TOL * scale,
            "x^{m} y^{n}: {got} vs {want}"
        );
    }
}

#[test]
fn register_extracts_a_known_transform_and_feeds_solve() {
    let dir = tempfile::tempdir().unwrap();
    let surface = dir.path().join("design.json");
    std::fs::write(&surface, surface_json()).unwrap();
    // The true installation error M: p_design = Rot p_measured + t.
    let arcsec = std::f64::consts::PI / (180.0 * 3600.0);
    let w_arcsec = [40.0, -25.0, 60.0];
    let t_um = [12.0, -30.0, 8.0];
    let rot = rotation([
        w_arcsec[0] * arcsec,
        w_arcsec[1] * arcsec,
        w_arcsec[2] * arcsec,
    ]);
    // A form error of 80 nm along z with zero mean over the grid (three periods per side),
    // then the measured points p = Rot^T (p_design + e - t).
    let form_nm = |x: f64, y: f64| {
        80.0 * (2.0 * std::f64::consts::PI * x / 20.0).cos()
            * (2.0 * std::f64::consts::PI * y / 20.0).cos()
    };
    let measured: Vec<[f64; 3]> = design_points()
        .iter()
        .map(|p| {
            let q = [
                p[0] - t_um[0] * 1e-3,
                p[1] - t_um[1] * 1e-3,
                p[2] + form_nm(p[0], p[1]) * 1e-6 - t_um[2] * 1e-3,
            ];
            let mut m = [0.0; 3];
            for (a, ma) in m.iter_mut().enumerate() {
                *ma = (0..3).map(|b| rot[b][a] * q[b]).sum();
            }
            m
        })
        .collect();
    let pts = dir.path().join("measured.csv");
    write_points(&pts, &measured);

    // Noise-free and without form error first: the transform to rounding.
    let exact: Vec<[f64; 3]> = design_points()
        .iter()
        .map(|p| {
            let q = [
                p[0] - t_um[0] * 1e-3,
                p[1] - t_um[1] * 1e-3,
                p[2] - t_um[2] * 1e-3,
            ];
            let mut m = [0.0; 3];
            for (a, ma) in m.iter_mut().enumerate() {
                *ma = (0..3).map(|b| rot[b][a] * q[b]).sum();
            }
            m
        })
        .collect();
    let exact_pts = dir.path().join("exact.csv");
    write_points(&exact_pts, &exact);
    let out_exact = dir.path().join("reg_exact");
    ok(&preston(&[
        "register",
        "--surface",
        s(&surface),
        "--points",
        s(&exact_pts),
        "--out",
        s(&out_exact),
    ]));
    let tf: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_exact.join("transform.json")).unwrap())
            .unwrap();
    for a in 0..3 {
        let t = tf["translation_um"][a].as_f64().unwrap();
        let w = tf["rotation_arcsec"][a].as_f64().unwrap();
        assert!((t - t_um[a]).abs() < TRANSLATION_TOL_UM, "t[{a}] = {t} um");
        assert!(
            (w - w_arcsec[a]).abs() < ROTATION_TOL_ARCSEC,
            "w[{a}] = {w} arcsec"
        );
    }
    assert!(tf["rms_nm"].as_f64().unwrap() < 1e-3, "{tf}");
    assert!(tf["iterations"].as_u64().unwrap() <= 10);
    // The matrix maps measured points onto the design surface.
    let m = &tf["matrix"];
    let p = exact[100];
    let mapped: Vec<f64> = (0..3)
        .map(|a| {
            (0..3)
                .map(|b| m[a][b].as_f64().unwrap() * p[b])
                .sum::<f64>()
                + m[a][3].as_f64().unwrap()
        })
        .collect();
    assert!((mapped[2] - sag(mapped[0], mapped[1])).abs() < 1e-9);

    // With the form error: the map written is the form error, and `preston solve` reads it.
    // (This surface's in-plane slide is weakly determined; the 80 nm error here is orthogonal
    // enough to every motion that all six are estimated.)
    let out = dir.path().join("reg");
    ok(&preston(&[
        "register",
        "--surface",
        s(&surface),
        "--points",
        s(&pts),
        "--out",
        s(&out),
    ]));
    let text = std::fs::read_to_string(out.join("form_error.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("x_mm,y_mm,z_nm"));
    let mut sum_sq = 0.0;
    let mut max_dev: f64 = 0.0;
    let mut count = 0usize;
    for line in lines {
        let v: Vec<f64> = line.split(',').map(|c| c.parse().unwrap()).collect();
        // Along the normal the 80 nm z error shrinks by the cosine of the slope (< 5 %).
        max_dev = max_dev.max((v[2] - form_nm(v[0], v[1])).abs());
        sum_sq += v[2] * v[2];
        count += 1;
    }
    assert_eq!(count, 441);
    assert!(max_dev < 6.0, "form error off by {max_dev} nm");
    let rms_written = (sum_sq / count as f64).sqrt();

    let solve_out = dir.path().join("solve");
    let r = preston(&[
        "solve",
        "--map",
        s(&out.join("form_error.csv")),
        "--gaussian-sigma-mm",
        "3",
        "--gaussian-peak-nm-per-s",
        "20",
        "--raster-pitch-mm",
        "3",
        "--v-max",
        "3000",
        "--out",
        s(&solve_out),
    ]);
    ok(&r);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(solve_out.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(report["m"], 441);
    // The solver's RMS is about the mean; the written map has (nearly) zero mean.
    let rms_before = report["rms_before_nm"].as_f64().unwrap();
    assert!((rms_before - rms_written).abs() < 0.05 * rms_written);
    assert!(report["rms_after_nm"].as_f64().unwrap() < rms_before);
}

#[test]
fn surface_grid_matches_the_closed_form_sphere() {
    let dir = tempfile::tempdir().unwrap();
    let surface = dir.path().join("sphere.json");
    let radius = 250.0;
    std::fs::write(
        &surface,
        format!(
            r#"{{"type":"conic","curvature_per_mm":{},"conic":0.0}}"#,
            1.0 / radius
        ),
    )
    .unwrap();
    let out = dir.path().join("grid.csv");
    ok(&preston(&[
        "surface",
        "--surface",
        s(&surface),
        "--x-min-mm",
        "-20",
        "--x-max-mm",
        "20",
        "--y-min-mm",
        "-10",
        "--y-max-mm",
        "10",
        "--step-mm",
        "5",
        "--out",
        s(&out),
    ]));
    let text = std::fs::read_to_string(&out).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("x_mm,y_mm,z_mm,nx,ny,nz,k1_per_mm,k2_per_mm")
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 9 * 5);
    for v in rows {
        let (x, y) = (v[0], v[1]);
        let z = radius - (radius * radius - x * x - y * y).sqrt();
        assert!((v[2] - z).abs() < SAG_TOL_MM, "sag at ({x},{y})");
        // The normal of a sphere points from the surface point to the centre (0, 0, R).
        let n = [-x / radius, -y / radius, (radius - z) / radius];
        for a in 0..3 {
            assert!((v[3 + a] - n[a]).abs() < 1e-12);
        }
        // Both principal curvatures are 1/R.
        assert!((v[6] - 1.0 / radius).abs() < 1e-12 && (v[7] - 1.0 / radius).abs() < 1e-12);
    }
}

#[test]
fn geometry_commands_reject_bad_input_without_output() {
    let dir = tempfile::tempdir().unwrap();
    // Three collinear points cannot determine an order-2 polynomial.
    let pts = dir.path().join("few.csv");
    std::fs::write(&pts, "x_mm,y_mm,z_mm\n0,0,0\n1,1,0\n2,2,0\n").unwrap();
    let out = dir.path().join("s.json");
    let r = preston(&["fit", "--points", s(&pts), "--order", "2", "--out", s(&out)]);
    assert_eq!(r.status.code(), Some(2));
    assert!(!out.exists());
    // A surface file with an unknown type names the problem.
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, r#"{"type":"torus","radius_mm":3}"#).unwrap();
    let grid = dir.path().join("g.csv");
    let r = preston(&[
        "surface",
        "--surface",
        s(&bad),
        "--points",
        s(&pts),
        "--out",
        s(&grid),
    ]);
    assert_eq!(r.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&r.stderr).contains("bad.json"));
    assert!(!grid.exists());
    // A point outside the conic's domain (r > R for a sphere) is an error, not a NaN.
    let sphere = dir.path().join("sphere.json");
    std::fs::write(&sphere, r#"{"type":"conic","curvature_per_mm":0.1}"#).unwrap();
    let far = dir.path().join("far.csv");
    std::fs::write(&far, "x_mm,y_mm\n0,0\n20,0\n").unwrap();
    let r = preston(&[
        "surface",
        "--surface",
        s(&sphere),
        "--points",
        s(&far),
        "--out",
        s(&grid),
    ]);
    assert_eq!(r.status.code(), Some(2));
    assert!(!grid.exists());
}

/// `preston solve --surface`: on the plane `z = 0` with the machine-x frame the curved-part
/// assembly is the flat one, so every output byte agrees; on a sphere of radius 60 mm the TIF acts
/// in tangent planes and the influence matrix (hence the dwell) changes.
#[test]
fn solve_on_a_surface_reduces_to_the_flat_solve_on_a_plane() {
    let d = tempfile::tempdir().unwrap();
    let map = d.path().join("map.csv");
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..16 {
        for ix in 0..16 {
            let (x, y) = (ix as f64 - 7.5, iy as f64 - 7.5);
            let _ = writeln!(
                text,
                "{x},{y},{}",
                30.0 + 10.0 * (0.4 * x).cos() * (0.3 * y).sin()
            );
        }
    }
    std::fs::write(&map, text).unwrap();
    let plane = d.path().join("plane.json");
    std::fs::write(&plane, r#"{"type":"plane"}"#).unwrap();
    let sphere = d.path().join("sphere.json");
    std::fs::write(
        &sphere,
        r#"{"type":"conic","curvature_per_mm":0.016666666666666666}"#,
    )
    .unwrap();
    let base = [
        "solve",
        "--map",
        s(&map),
        "--gaussian-sigma-mm",
        "1.5",
        "--gaussian-peak-nm-per-s",
        "10",
        "--raster-pitch-mm",
        "1.5",
        "--v-max",
        "2000",
    ];
    let run = |extra: &[&str], out: &str| {
        let out = d.path().join(out);
        let mut args = base.to_vec();
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--out", s(&out)]);
        ok(&preston(&args));
        out
    };
    // The swept model in the tangent frame: on a plane, with the machine-x frame, the flat swept
    // solve on the assembled R, byte for byte.
    let flat = run(&["--operator", "sparse"], "flat");
    let on_plane = run(
        &["--surface", s(&plane), "--tif-frame", "machine-x"],
        "plane",
    );
    let on_sphere = run(&["--surface", s(&sphere)], "sphere");
    for f in ["dwell.csv", "residual.csv"] {
        assert_eq!(
            std::fs::read(flat.join(f)).unwrap(),
            std::fs::read(on_plane.join(f)).unwrap(),
            "{f}: plane surface differs from the flat solve"
        );
    }
    assert_ne!(
        std::fs::read(flat.join("dwell.csv")).unwrap(),
        std::fs::read(on_sphere.join("dwell.csv")).unwrap()
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(on_sphere.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(report["status"], "converged");
    assert_eq!(report["influence"], "swept", "{}", report["warnings"]);
}

/// The shipped freeform's design points on a 2.5 mm grid over +-25 mm, raised by 2 um (a
/// piston: tz = -2 um) with a smooth 40 nm error, written to `p.csv` in `dir`: the design
/// surface's file, the points and their file.
fn freeform_points(dir: &Path) -> (std::path::PathBuf, Vec<[f64; 3]>, std::path::PathBuf) {
    let design = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/design_freeform.json");
    let grid = dir.join("grid.csv");
    ok(&preston(&[
        "surface",
        "--surface",
        s(&design),
        "--x-min-mm",
        "-25",
        "--x-max-mm",
        "25",
        "--y-min-mm",
        "-25",
        "--y-max-mm",
        "25",
        "--step-mm",
        "2.5",
        "--out",
        s(&grid),
    ]));
    // The design points raised by 2 um (a piston: tz = -2 um) and a smooth 40 nm error.
    let text = std::fs::read_to_string(&grid).unwrap();
    let mut pts = Vec::new();
    for line in text.lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|c| c.parse().unwrap()).collect();
        let e_mm = 40e-6 * (0.1 * v[0]).sin() * (0.08 * v[1]).cos();
        pts.push([v[0], v[1], v[2] + 2e-3 + e_mm]);
    }
    let pfile = dir.join("p.csv");
    write_points(&pfile, &pts);
    (design, pts, pfile)
}

/// The `transform.json` that `preston register` wrote to `out`.
fn transform_json(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("transform.json")).unwrap()).unwrap()
}

/// `preston register` on the shipped freeform: conditioning in `transform.json` (eigenvalues
/// in order, the piston's the largest, the condition number their ratio), every motion
/// estimated by default without a warning, the piston recovered.
#[test]
fn register_reports_conditioning() {
    let dir = tempfile::tempdir().unwrap();
    let (design, pts, pfile) = freeform_points(dir.path());
    let out = dir.path().join("reg");
    let r = preston(&[
        "register",
        "--surface",
        s(&design),
        "--points",
        s(&pfile),
        "--out",
        s(&out),
    ]);
    ok(&r);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!err.contains("warning"), "{err}");
    let tf = transform_json(&out);
    let ev: Vec<f64> = tf["information_eigenvalues"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(ev.len(), 6);
    assert!(ev.windows(2).all(|w| w[0] >= w[1]), "{ev:?}");
    // The largest is the piston: sum of n_z^2 ~ N points.
    assert!(
        (ev[0] - pts.len() as f64).abs() < 0.01 * pts.len() as f64,
        "{ev:?}"
    );
    let cond = tf["condition_number"].as_f64().unwrap();
    assert!((cond - ev[0] / ev[5]).abs() < 1e-6 * cond);
    assert_eq!(tf["dof_sigma"].as_array().unwrap().len(), 6);
    assert_eq!(tf["locked"].as_array().unwrap().len(), 0, "{tf}");
    assert_eq!(tf["form_correlation"].as_array().unwrap().len(), 6);
    assert_eq!(tf["installation_range_mm"].as_f64(), Some(0.5));
    let t = tf["translation_um"][2].as_f64().unwrap();
    assert!((t + 2.0).abs() < 0.01, "tz {t} um");
    for k in 0..2 {
        let w = tf["rotation_arcsec"][k].as_f64().unwrap();
        assert!(w.abs() < 5.0, "rotation {k}: {w} arcsec");
    }
}

/// `preston register` on a mount tighter than the weakly determined motions' uncertainty: they
/// are held, with a warning and its reason.
#[test]
fn register_holds_weak_motions_on_a_tight_mount() {
    let dir = tempfile::tempdir().unwrap();
    let (design, _, pfile) = freeform_points(dir.path());
    // On a mount known to 0.1 um and 0.01 arcsec the 40 nm error leaves the slides uncertain
    // by more than that: held, with a warning giving the comparison.
    let tight = dir.path().join("reg_tight");
    let r = preston(&[
        "register",
        "--surface",
        s(&design),
        "--points",
        s(&pfile),
        "--installation-range-mm",
        "0.0001",
        "--installation-range-deg",
        "0.000003",
        "--out",
        s(&tight),
    ]);
    ok(&r);
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        err.contains("warning: motion") && err.contains("installation range"),
        "{err}"
    );
    let tf = transform_json(&tight);
    let locked = tf["locked"].as_array().unwrap();
    assert!(
        !locked.is_empty() && locked.iter().all(|l| l["source"] == "weak"),
        "{locked:?}"
    );
    assert!(locked
        .iter()
        .all(|l| l["reason"].as_str().unwrap().contains("standard deviation")));
}

/// `preston register --lock` by name: the locked motions held at zero, the piston kept in the
/// form error.
#[test]
fn register_locks_motions_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (design, _, pfile) = freeform_points(dir.path());
    // --lock tz with the slides keeps the piston in the form error (with tz alone held, the
    // weakly determined rx + ty combination mimics part of a piston on this surface).
    let out2 = dir.path().join("reg2");
    ok(&preston(&[
        "register",
        "--surface",
        s(&design),
        "--points",
        s(&pfile),
        "--lock",
        "tz,rz,tx,ty",
        "--out",
        s(&out2),
    ]));
    let tf = transform_json(&out2);
    assert!(tf["translation_um"][2].as_f64().unwrap().abs() < 1e-6);
    assert_eq!(tf["dof_sigma"][5].as_f64().unwrap(), 0.0);
    let users: Vec<&str> = tf["locked"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|l| l["source"] == "user")
        .map(|l| l["label"].as_str().unwrap())
        .collect();
    assert_eq!(users, ["rz", "tx", "ty", "tz"]);
    assert!(
        (tf["rms_nm"].as_f64().unwrap() - 2000.0).abs() < 50.0,
        "{tf}"
    );
}

/// `preston register` refuses a single profile line (exit 2, the undetermined motions named,
/// nothing written) and unknown motion names.
#[test]
fn register_refuses_lines_and_unknown_motions() {
    let dir = tempfile::tempdir().unwrap();
    let (design, pts, pfile) = freeform_points(dir.path());
    // A single profile line: exit 2, the undetermined motions named, nothing written.
    let line: Vec<[f64; 3]> = pts.iter().filter(|p| p[1] == 0.0).copied().collect();
    assert!(line.len() > 10);
    let lfile = dir.path().join("line.csv");
    write_points(&lfile, &line);
    let out3 = dir.path().join("reg3");
    let r = preston(&[
        "register",
        "--surface",
        s(&design),
        "--points",
        s(&lfile),
        "--out",
        s(&out3),
    ]);
    assert_eq!(r.status.code(), Some(2));
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(err.contains("one line") && err.contains("rx, tx"), "{err}");
    assert!(!out3.exists());
    // Unknown DOF names are refused by the parser.
    let r = preston(&[
        "register",
        "--surface",
        s(&design),
        "--points",
        s(&pfile),
        "--lock",
        "rw",
        "--out",
        s(&out3),
    ]);
    assert_eq!(r.status.code(), Some(2));
}

/// Points of a conic of curvature `c` (1/mm) and conic constant `k` over a disc of radius
/// `radius_mm` (41 x 41 grid), plus `tilt_mm_per_mm2 * x y` and `noise_mm` times uniform noise
/// in [-0.5, 0.5) from xorshift64 seeded with `seed` (the same on every machine).
fn conic_points(
    c: f64,
    k: f64,
    radius_mm: f64,
    tilt_mm_per_mm2: f64,
    noise_mm: f64,
    seed: u64,
) -> String {
    let mut state = seed;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    };
    let mut text = String::from("x_mm,y_mm,z_mm\n");
    for j in 0..41 {
        for i in 0..41 {
            let x = -radius_mm + 2.0 * radius_mm * i as f64 / 40.0;
            let y = -radius_mm + 2.0 * radius_mm * j as f64 / 40.0;
            let r2 = x * x + y * y;
            if r2 > radius_mm * radius_mm {
                continue;
            }
            let sag = c * r2 / (1.0 + (1.0 - (1.0 + k) * c * c * r2).sqrt());
            let z = sag + tilt_mm_per_mm2 * x * y + noise_mm * uniform();
            writeln!(text, "{x},{y},{z}").unwrap();
        }
    }
    text
}

/// `fit --fit-conic`: points on a conic (plus an x y term) are fitted to round-off with the
/// status converged and exit 0 (an exact fit is not a stall); on a shallow part with 10 nm of
/// noise, whose conic constant the data do not determine (the conic overlaps the polynomial's
/// second-order terms; the condition estimate says so and a warning names it), the fit stops
/// at its iteration limit, exits 3 with the status and a warning, and still writes its outputs.
#[test]
fn conic_fit_converges_on_exact_data_and_exits_3_when_it_stalls() {
    let dir = tempfile::tempdir().unwrap();
    let exact = dir.path().join("exact.csv");
    std::fs::write(&exact, conic_points(1.0 / 50.0, -2.0, 10.0, 1e-6, 0.0, 1)).unwrap();
    let r = preston(&["fit", "--points", s(&exact), "--fit-conic", "--order", "4"]);
    assert_eq!(
        r.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&r.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(summary["status"], "converged", "{summary}");
    assert!(summary["rms_nm"].as_f64().unwrap() < 1e-6, "{summary}");
    let stalled = dir.path().join("shallow.csv");
    std::fs::write(&stalled, conic_points(1e-3, 0.0, 30.0, 1e-6, 2e-5, 2)).unwrap();
    let out = dir.path().join("surface.json");
    let r = preston(&[
        "fit",
        "--points",
        s(&stalled),
        "--fit-conic",
        "--order",
        "4",
        "--out",
        s(&out),
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    assert_eq!(r.status.code(), Some(3), "{err}");
    assert!(err.contains("stopped before converging"), "{err}");
    let summary: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert_eq!(summary["status"], "max_iterations", "{summary}");
    assert!(out.is_file(), "the last iterate is written");
    // At order 10 the polynomial's r^2 and r^4 terms overlap the conic outright: the condition
    // estimate is beyond what a fixed base accepts, and the warning says what is not determined.
    let r = preston(&[
        "fit",
        "--points",
        s(&stalled),
        "--fit-conic",
        "--order",
        "10",
    ]);
    let err = String::from_utf8_lossy(&r.stderr);
    let summary: serde_json::Value = serde_json::from_slice(&r.stdout).unwrap();
    assert!(
        summary["condition_number"].as_f64().unwrap() > 1e13,
        "{summary}"
    );
    assert!(err.contains("not determined separately"), "{err}");
}

/// A 17 x 17 map at 1 mm (a smooth 12 nm error on 40 nm) on a sphere of radius 40 mm: the map
/// and the sphere's file in `dir`.
fn curved_part(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let map = dir.join("map.csv");
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..17 {
        for ix in 0..17 {
            let (x, y) = (ix as f64 - 8.0, iy as f64 - 8.0);
            let _ = writeln!(
                text,
                "{x},{y},{}",
                40.0 + 12.0 * (0.45 * x).cos() * (0.3 * y).sin()
            );
        }
    }
    std::fs::write(&map, text).unwrap();
    let sphere = dir.join("sphere.json");
    std::fs::write(&sphere, r#"{"type":"conic","curvature_per_mm":0.025}"#).unwrap();
    (map, sphere)
}

/// The TIF of the curved-part tests: a Gaussian of sigma 1.5 mm, 10 nm/s.
const CURVED_PART_TIF: [&str; 4] = [
    "--gaussian-sigma-mm",
    "1.5",
    "--gaussian-peak-nm-per-s",
    "10",
];

/// The shop's check on a curved part: with an acceleration limit the solve executes its program
/// on the sphere (the tool following the surface, each contact sample applying the TIF in its
/// tangent frame) and reports that as its residual, with the sensitivity; the program `nc`
/// writes for the plan, run by `simulate --program` on the same surface, leaves the residual
/// the report predicts. On a plane with the machine-x frame the executed run is the flat one.
#[test]
fn a_curved_part_reports_the_program_it_runs() {
    /// The solve's program and `nc`'s differ only in their number formatting.
    const PROGRAM_REL_TOL: f64 = 1e-3;
    /// The tangent-frame sum on a plane against the plan's: the same terms, another order.
    const ORDER_REL_TOL: f64 = 1e-9;
    let d = tempfile::tempdir().unwrap();
    let (map, sphere) = curved_part(d.path());
    let plane = d.path().join("plane.json");
    std::fs::write(&plane, r#"{"type":"plane"}"#).unwrap();
    let tif = CURVED_PART_TIF;
    let solve = |surface: Option<&[&str]>, out: &str| {
        let out = d.path().join(out);
        let mut args = vec!["solve", "--map", s(&map)];
        args.extend_from_slice(&tif);
        args.extend_from_slice(&[
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "2000",
            "--a-max-mm-per-s2",
            "200",
            "--operator",
            "sparse",
            "--out",
            s(&out),
        ]);
        if let Some(extra) = surface {
            args.extend_from_slice(extra);
        }
        ok(&preston(&args));
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                .unwrap();
        (out, report)
    };
    let (out, report) = solve(Some(&["--surface", s(&sphere)]), "sphere");
    let executed = &report["executed"];
    assert!(
        executed.is_object(),
        "no executed run: {}",
        report["warnings"]
    );
    let rms = report["rms_after_nm"].as_f64().unwrap();
    assert_eq!(rms, executed["rms_after_nm"].as_f64().unwrap());
    assert!(report["model"]["rms_nm"].as_f64().unwrap() > 0.0);
    assert_eq!(report["influence"], "swept");
    for key in SENSITIVITY_KEYS {
        let f = &report["sensitivity"][key];
        assert!(
            f["rms_nm"].as_f64().unwrap() > rms && f["pv_nm"].as_f64().unwrap() > 0.0,
            "{key}: {f}"
        );
    }
    let prog = d.path().join("prog.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        s(&out.join("dwell.csv")),
        "--surface",
        s(&sphere),
        "--v-max",
        "2000",
        "--a-max-mm-per-s2",
        "200",
        "--out",
        s(&prog),
    ]));
    let sim = d.path().join("sim");
    let mut args = vec!["simulate", "--map", s(&map)];
    args.extend_from_slice(&tif);
    args.extend_from_slice(&[
        "--program",
        s(&prog),
        "--surface",
        s(&sphere),
        "--a-max-mm-per-s2",
        "200",
        "--out",
        s(&sim),
    ]);
    ok(&preston(&args));
    let simulated: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sim.join("report.json")).unwrap()).unwrap();
    let run = simulated["rms_after_nm"].as_f64().unwrap();
    assert!(
        (run - rms).abs() <= PROGRAM_REL_TOL * rms,
        "simulate --program {run} nm against the report's executed {rms} nm"
    );
    // The same program run as if the part were flat leaves another residual: the curvature is
    // in the executed run.
    let flat_sim = d.path().join("flat_sim");
    let mut args = vec!["simulate", "--map", s(&map)];
    args.extend_from_slice(&tif);
    args.extend_from_slice(&[
        "--program",
        s(&prog),
        "--a-max-mm-per-s2",
        "200",
        "--out",
        s(&flat_sim),
    ]);
    ok(&preston(&args));
    let flat_run: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(flat_sim.join("report.json")).unwrap())
            .unwrap();
    let flat_run = flat_run["rms_after_nm"].as_f64().unwrap();
    assert!(
        (flat_run - rms).abs() > 10.0 * PROGRAM_REL_TOL * rms,
        "flat {flat_run} against curved {rms}"
    );
    // On a plane in the machine-x frame: the flat solve's executed run and sensitivity.
    let (_, flat) = solve(None, "flat");
    let (_, on_plane) = solve(
        Some(&["--surface", s(&plane), "--tif-frame", "machine-x"]),
        "plane",
    );
    let close = |a: &serde_json::Value, b: &serde_json::Value| {
        let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
        assert!((a - b).abs() <= ORDER_REL_TOL * b.abs(), "{a} against {b}");
    };
    close(&on_plane["rms_after_nm"], &flat["rms_after_nm"]);
    close(&on_plane["pv_after_nm"], &flat["pv_after_nm"]);
    for key in ["tif_wider_3pct", "offset_x_0p05mm", "offset_y_0p05mm"] {
        close(
            &on_plane["sensitivity"][key]["rms_nm"],
            &flat["sensitivity"][key]["rms_nm"],
        );
    }
}

/// The robust plan on a curved part: each scenario's matrix in the tangent frames (the tool's
/// offset moving the dwell points), and the plan lowers the mean square over the scenarios
/// below the nominal plan's.
#[test]
fn a_curved_part_takes_the_robust_plan() {
    let d = tempfile::tempdir().unwrap();
    let (map, sphere) = curved_part(d.path());
    let out = d.path().join("robust");
    let mut args = vec!["solve", "--map", s(&map)];
    args.extend_from_slice(&CURVED_PART_TIF);
    args.extend_from_slice(&[
        "--raster-pitch-mm",
        "1.5",
        "--v-max",
        "2000",
        "--surface",
        s(&sphere),
        "--robust",
        "--out",
        s(&out),
    ]);
    ok(&preston(&args));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let robust = &r["robust"];
    assert_eq!(robust["basis"], "planned", "{robust}");
    let list = |v: &serde_json::Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect()
    };
    let (rob, nom) = (
        list(&robust["robust_plan_rms_nm"]),
        list(&robust["nominal_plan_rms_nm"]),
    );
    let mean_sq = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64;
    assert_eq!(rob.len(), 7);
    assert!(mean_sq(&rob) < mean_sq(&nom), "{rob:?} against {nom:?}");
    assert!(rob[0] >= nom[0] * (1.0 - 1e-3), "{rob:?} against {nom:?}");
    assert!(r["sensitivity"].is_object(), "{r}");
}
