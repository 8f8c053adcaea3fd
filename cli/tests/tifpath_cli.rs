//! `preston tif` and `preston path` end to end, through files: closed-form Hertz contact, the
//! written grid's volume, intersection pattern, spiral pitch, chord-height window, and that the
//! outputs feed `preston solve`.

mod common;

use common::{ok_json, preston, read_csv, s};
use std::path::Path;

/// Closed-form contact quantities printed by the CLI (JSON round trip of f64 is exact; the
/// formula is evaluated in another order here).
const CLOSED_FORM_REL_TOL: f64 = 1e-12;
/// Model volume (polar quadrature) against the written grid's trapezoid volume at pitch a/100.
const VOLUME_REL_TOL: f64 = 5e-3;

const HERTZ: [&str; 20] = [
    "--force-n",
    "10",
    "--tool-radius-mm",
    "16",
    "--spindle-rad-s",
    "104.72",
    "--tilt-deg",
    "15",
    "--tool-e-gpa",
    "0.005",
    "--tool-nu",
    "0.4",
    "--part-e-gpa",
    "72",
    "--part-nu",
    "0.2",
    "--preston-k",
    "2e-6",
    "--pitch-mm",
    "0.05",
];

#[test]
fn hertz_tif_closed_form_volume_and_solve() {
    let dir = tempfile::tempdir().unwrap();
    let tif = dir.path().join("tif.csv");
    let mut args = vec!["tif", "hertz"];
    args.extend_from_slice(&HERTZ);
    args.extend_from_slice(&["--out", s(&tif)]);
    let j = ok_json(&preston(&args));
    let e_star = 1.0 / ((1.0 - 0.4f64 * 0.4) / 5.0 + (1.0 - 0.2f64 * 0.2) / 72_000.0);
    let a = (3.0 * 10.0 * 16.0 / (4.0 * e_star)).cbrt();
    let p0 = 3.0 * 10.0 / (2.0 * std::f64::consts::PI * a * a);
    let got_a = j["contact_radius_mm"].as_f64().unwrap();
    let got_p = j["peak_pressure_mpa"].as_f64().unwrap();
    assert!((got_a - a).abs() < CLOSED_FORM_REL_TOL * a, "{got_a} {a}");
    assert!((got_p - p0).abs() < CLOSED_FORM_REL_TOL * p0);
    // The grid: header, spacing, and its trapezoid volume is the printed grid volume; the model
    // volume agrees with it.
    let (h, rows) = read_csv(&tif);
    assert_eq!(h, ["x_mm", "y_mm", "rate_nm_per_s"]);
    let peak = rows.iter().map(|r| r[2]).fold(0.0, f64::max);
    assert_eq!(peak, j["peak_rate_nm_per_s"].as_f64().unwrap());
    // Centre rate by hand: K p0 v0 = 2e-6 * p0 * omega R sin(15 deg), mm/s -> nm/s.
    let centre = rows.iter().find(|r| r[0] == 0.0 && r[1] == 0.0).unwrap()[2];
    let want = 2e-6 * p0 * 104.72 * 16.0 * 15f64.to_radians().sin() * 1e6;
    assert!((centre - want).abs() < 1e-9 * want, "{centre} {want}");
    let pitch = 0.05;
    let vol_grid: f64 = rows.iter().map(|r| r[2]).sum::<f64>() * pitch * pitch * 1e-6 * 60.0;
    let v_model = j["volume_rate_mm3_per_min"].as_f64().unwrap();
    assert!(
        (vol_grid - v_model).abs() < VOLUME_REL_TOL * v_model,
        "{vol_grid} {v_model}"
    );
    assert!(j["fwhm_mm"].as_f64().unwrap() > 0.0);

    // The grid and a generated path feed `preston solve`.
    let map = dir.path().join("map.csv");
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..21 {
        for ix in 0..21 {
            let (x, y) = (ix as f64 * 0.5 - 5.0, iy as f64 * 0.5 - 5.0);
            text.push_str(&format!("{x},{y},{}\n", 50.0 + 5.0 * (x * 0.3).sin()));
        }
    }
    std::fs::write(&map, text).unwrap();
    let path = dir.path().join("path.csv");
    ok_json(&preston(&[
        "path",
        "raster",
        "--x-mm",
        "-6,6",
        "--y-mm",
        "-6,6",
        "--pitch-mm",
        "1.5",
        "--out",
        s(&path),
    ]));
    let out = dir.path().join("solve");
    let o = preston(&[
        "solve",
        "--map",
        s(&map),
        "--tif",
        s(&tif),
        "--dwell",
        s(&path),
        "--v-max",
        "30000",
        "--out",
        s(&out),
        "--accept-best-iterate",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("dwell.csv").exists());

    // Convex part: smaller contact radius; bad input: exit 2 and no file.
    let tif2 = dir.path().join("tif2.csv");
    let mut args = vec!["tif", "hertz"];
    args.extend_from_slice(&HERTZ);
    args.extend_from_slice(&["--part-radius-mm", "50", "--out", s(&tif2)]);
    let j2 = ok_json(&preston(&args));
    assert!(j2["contact_radius_mm"].as_f64().unwrap() < a);
    // The same convex sphere as a surface JSON (curvature -1/50 in the surface convention):
    // at any point both principal curvatures are -1/50, so the contact is the same.
    let sphere = dir.path().join("sphere.json");
    std::fs::write(
        &sphere,
        r#"{"type":"conic","curvature_per_mm":-0.02,"conic":0}"#,
    )
    .unwrap();
    let tif3 = dir.path().join("tif3.csv");
    let mut args = vec!["tif", "hertz"];
    args.extend_from_slice(&HERTZ);
    args.extend_from_slice(&[
        "--surface",
        s(&sphere),
        "--at-mm",
        "-10,15",
        "--out",
        s(&tif3),
    ]);
    let j3 = ok_json(&preston(&args));
    let (c2, c3) = (
        j2["contact_radius_mm"].as_f64().unwrap(),
        j3["contact_radius_mm"].as_f64().unwrap(),
    );
    assert!((c2 - c3).abs() < 1e-12 * c2, "{c2} {c3}");
    let bad = dir.path().join("bad.csv");
    let mut args = vec!["tif", "hertz"];
    args.extend_from_slice(&HERTZ);
    args.extend_from_slice(&["--part-radius-mm", "-8", "--out", s(&bad)]);
    let o = preston(&args);
    assert_eq!(o.status.code(), Some(2));
    assert!(!bad.exists());
}

#[test]
fn gaussian_bonnet_and_grid_tifs() {
    let dir = tempfile::tempdir().unwrap();
    let g = dir.path().join("g.csv");
    let j = ok_json(&preston(&[
        "tif",
        "gaussian",
        "--sigma-mm",
        "2",
        "--peak-nm-per-s",
        "10",
        "--pitch-mm",
        "0.1",
        "--out",
        s(&g),
    ]));
    let fwhm = 2.0 * (2.0 * 2f64.ln()).sqrt() * 2.0;
    assert!((j["fwhm_mm"].as_f64().unwrap() - fwhm).abs() < 0.1);
    assert_eq!(j["peak_rate_nm_per_s"].as_f64().unwrap(), 10.0);
    let b = dir.path().join("b.csv");
    let j = ok_json(&preston(&[
        "tif",
        "bonnet",
        "--bonnet-radius-mm",
        "20",
        "--depth-mm",
        "0.3",
        "--precession-deg",
        "20",
        "--azimuths",
        "4",
        "--force-n",
        "10",
        "--preston-k",
        "1e-6",
        "--pitch-mm",
        "0.2",
        "--out",
        s(&b),
    ]));
    let a = (2.0 * 20.0 * 0.3 - 0.09f64).sqrt();
    assert!((j["contact_radius_mm"].as_f64().unwrap() - a).abs() < 1e-12);
    // Measured grid: recentre and scale to a volume.
    let r = dir.path().join("r.csv");
    let j = ok_json(&preston(&[
        "tif",
        "grid",
        "--in",
        s(&b),
        "--pitch-mm",
        "0.1",
        "--recentre",
        "--volume-mm3-per-min",
        "0.5",
        "--out",
        s(&r),
    ]));
    assert!((j["grid_volume_rate_mm3_per_min"].as_f64().unwrap() - 0.5).abs() < 1e-12);
    let (_, rows) = read_csv(&r);
    let w: f64 = rows.iter().map(|r| r[2]).sum();
    let cx: f64 = rows.iter().map(|r| r[0] * r[2]).sum::<f64>() / w;
    let cy: f64 = rows.iter().map(|r| r[1] * r[2]).sum::<f64>() / w;
    assert!(cx.abs() < 1e-9 && cy.abs() < 1e-9);
}

/// The columns of every `preston path` CSV.
const PATH_HEADER: [&str; 7] = ["x_mm", "y_mm", "z_mm", "tx", "ty", "tz", "ds_mm"];

/// An ellipsoid (`c = 0.01 /mm`, conic 0.6) written as a surface file in `dir`.
fn ellipsoid(dir: &Path) -> std::path::PathBuf {
    let surf = dir.join("ell.json");
    std::fs::write(
        &surf,
        r#"{"type":"conic","curvature_per_mm":0.01,"conic":0.6}"#,
    )
    .unwrap();
    surf
}

/// `preston path intersection`: the first line along x or y by iteration, offset by half the
/// pitch from iteration 2, on the plane.
#[test]
fn path_intersection_alternates_axis_and_offset() {
    let dir = tempfile::tempdir().unwrap();
    let p = 2.0;
    let mut ys0 = Vec::new();
    for k in 0..4 {
        let out = dir.path().join(format!("i{k}.csv"));
        let j = ok_json(&preston(&[
            "path",
            "intersection",
            "--x-mm",
            "-10,10",
            "--y-mm",
            "-5,5",
            "--pitch-mm",
            "2",
            "--iteration",
            &k.to_string(),
            "--out",
            s(&out),
        ]));
        assert_eq!(j["along"], if k & 1 == 0 { "x" } else { "y" });
        let (h, rows) = read_csv(&out);
        assert_eq!(h, PATH_HEADER);
        // The first line runs along its axis: the tangent of the first point.
        let t = (rows[0][3], rows[0][4]);
        assert_eq!(t, if k & 1 == 0 { (1.0, 0.0) } else { (0.0, 1.0) });
        // Cross-line coordinate of the first line: lo (K < 2) or lo - P/2 (K >= 2).
        let c = if k & 1 == 0 { rows[0][1] } else { rows[0][0] };
        let lo = if k & 1 == 0 { -5.0 } else { -10.0 };
        let want = if k >= 2 { lo - 0.5 * p } else { lo };
        assert!((c - want).abs() < 1e-12, "k={k} {c}");
        if k == 0 {
            ys0 = rows.iter().map(|r| r[1]).collect();
        }
        assert!(rows.iter().all(|r| r[2] == 0.0));
    }
    assert!(!ys0.is_empty());
}

/// `preston path spiral`: the last point on the radius; a negative pitch refused (exit 2, no
/// file).
#[test]
fn path_spiral_ends_on_the_radius_and_refuses_bad_pitch() {
    let dir = tempfile::tempdir().unwrap();
    // Spiral: every point on r = P theta / (2 pi) modulo turns; last point on the radius.
    let sp = dir.path().join("s.csv");
    ok_json(&preston(&[
        "path",
        "spiral",
        "--radius-mm",
        "20",
        "--pitch-mm",
        "1",
        "--out",
        s(&sp),
    ]));
    let (_, rows) = read_csv(&sp);
    let last = rows.last().unwrap();
    assert!((last[0].hypot(last[1]) - 20.0).abs() < 1e-9);
    // Bad input: exit 2, no file.
    let bad = dir.path().join("bad.csv");
    let o = preston(&[
        "path",
        "spiral",
        "--radius-mm",
        "20",
        "--pitch-mm",
        "-1",
        "--out",
        s(&bad),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(!bad.exists());
}

/// `preston path chord-height` on an ellipsoid: chord heights within the published window and
/// every point on the surface.
#[test]
fn path_chord_height_on_an_ellipsoid() {
    let dir = tempfile::tempdir().unwrap();
    let surf = ellipsoid(dir.path());
    let ch = dir.path().join("c.csv");
    let j = ok_json(&preston(&[
        "path",
        "chord-height",
        "--surface",
        s(&surf),
        "--line-x-mm",
        "10",
        "--y-mm",
        "-30,30",
        "--tool-radius-mm",
        "10",
        "--eps-um",
        "3.0,3.2",
        "--grow-mm",
        "0.1",
        "--shrink-mm",
        "0.02",
        "--out",
        s(&ch),
    ]));
    assert!(j["min_chord_height_um"].as_f64().unwrap() >= 3.0);
    assert!(j["max_chord_height_um"].as_f64().unwrap() <= 3.2);
    let (_, rows) = read_csv(&ch);
    assert_eq!(rows.len() as u64, j["points"].as_u64().unwrap());
    // z is the ellipsoid sag.
    for r in &rows {
        let rho2 = r[0] * r[0] + r[1] * r[1];
        let z = 0.01 * rho2 / (1.0 + (1.0 - 1.6 * 1e-4 * rho2).sqrt());
        assert!((r[2] - z).abs() < 1e-12);
    }
}

/// `preston path edge-offset` on a round part projected onto an ellipsoid, and on a square edge.
#[test]
fn path_edge_offset_round_and_square() {
    let dir = tempfile::tempdir().unwrap();
    let surf = ellipsoid(dir.path());
    // Edge offset on a round part, projected onto the ellipsoid.
    let eo = dir.path().join("e.csv");
    let j = ok_json(&preston(&[
        "path",
        "edge-offset",
        "--edge-radius-mm",
        "40",
        "--bonnet-radius-mm",
        "20",
        "--spot-max-mm",
        "6",
        "--spot-min-mm",
        "1.5",
        "--ratio",
        "0.8",
        "--residual-um",
        "1",
        "--surface",
        s(&surf),
        "--out",
        s(&eo),
    ]));
    let lines = j["lines"].as_array().unwrap();
    assert!(lines.len() >= 5);
    let (h, _) = read_csv(&eo);
    assert_eq!(h, PATH_HEADER);
    // The 4-corner 60 mm square, bonnet R 40 mm, 0.5 mm overhang: 4 straight Bezier segments,
    // every point inside the edge by at least r_min - overhang, none repeated.
    let sq = dir.path().join("square.csv");
    std::fs::write(&sq, "x_mm,y_mm\n-30,-30\n30,-30\n30,30\n-30,30\n").unwrap();
    let so = dir.path().join("sq_path.csv");
    let j = ok_json(&preston(&[
        "path",
        "edge-offset",
        "--edge",
        s(&sq),
        "--bonnet-radius-mm",
        "40",
        "--spot-max-mm",
        "6",
        "--spot-min-mm",
        "1.5",
        "--ratio",
        "0.8",
        "--residual-um",
        "1",
        "--overhang-mm",
        "0.5",
        "--out",
        s(&so),
    ]));
    assert_eq!(j["corners"].as_u64(), Some(4));
    assert!(j["bezier_max_error_mm"].as_f64().unwrap() < 1e-9);
    let (_, rows) = read_csv(&so);
    let mut prev: Option<(f64, f64)> = None;
    for r in &rows {
        let inside_by = 30.0 - r[0].abs().max(r[1].abs());
        assert!(inside_by >= 1.5 - 0.5 - 1e-9, "{r:?}");
        if let Some(p) = prev {
            assert!(
                (r[0] - p.0).hypot(r[1] - p.1) > 1e-6,
                "repeated point {r:?}"
            );
        }
        prev = Some((r[0], r[1]));
    }
}

/// `preston path random`: the CSV contract of the other paths, every node of the even grid once
/// in unit steps, straight runs within `--max-run`, reproducible from the seed, and bad settings
/// refused with exit 2 and no file.
#[test]
fn random_path_is_unicursal_and_reproducible() {
    let dir = tempfile::tempdir().unwrap();
    let run = |seed: &str, out: &Path| {
        ok_json(&preston(&[
            "path",
            "random",
            "--x-mm=-10,10",
            "--y-mm=-8,8",
            "--pitch-mm",
            "1",
            "--seed",
            seed,
            "--max-run",
            "6",
            "--out",
            s(out),
        ]))
    };
    let a = dir.path().join("a.csv");
    let summary = run("4", &a);
    // 21 x 17 region nodes: the last column and row (odd counts) are left out.
    assert_eq!(summary["nodes"], serde_json::json!([20, 16]));
    assert_eq!(summary["region_nodes"], serde_json::json!([21, 17]));
    assert!(summary["longest_run"].as_u64().unwrap() <= 6);
    let (header, rows) = read_csv(&a);
    assert_eq!(header, ["x_mm", "y_mm", "z_mm", "tx", "ty", "tz", "ds_mm"]);
    assert_eq!(rows.len(), 320);
    let mut seen = std::collections::HashSet::new();
    for r in &rows {
        assert!(seen.insert(((r[0] + 10.0) as i64, (r[1] + 8.0) as i64)));
        assert!((r[6] - 1.0).abs() < 1e-12, "ds {}", r[6]);
    }
    let mut run_len = 0;
    for w in rows.windows(3) {
        let d1 = (w[1][0] - w[0][0], w[1][1] - w[0][1]);
        let d2 = (w[2][0] - w[1][0], w[2][1] - w[1][1]);
        assert!((d1.0.abs() + d1.1.abs() - 1.0).abs() < 1e-12);
        run_len = if d1 == d2 { run_len + 1 } else { 0 };
        assert!(run_len < 6);
    }
    let b = dir.path().join("b.csv");
    run("4", &b);
    assert_eq!(
        std::fs::read_to_string(&a).unwrap(),
        std::fs::read_to_string(&b).unwrap()
    );
    let c = dir.path().join("c.csv");
    run("5", &c);
    assert_ne!(
        std::fs::read_to_string(&a).unwrap(),
        std::fs::read_to_string(&c).unwrap()
    );
    let bad = dir.path().join("bad.csv");
    let r = preston(&[
        "path",
        "random",
        "--x-mm=0,10",
        "--y-mm=0,10",
        "--pitch-mm",
        "1",
        "--max-run",
        "2",
        "--out",
        s(&bad),
    ]);
    assert_eq!(r.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&r.stderr).contains("max_run"));
    assert!(!bad.exists());
}

/// `path raster --arc-radius-mm`: arc turns are sampled to `--arc-tolerance-um` whatever the
/// step: every chord's sagitta `r (1 - cos(phi / 2))` (phi its turn) within the tolerance.
#[test]
fn arc_turns_meet_the_chord_tolerance_with_a_long_step() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("arcs.csv");
    ok_json(&preston(&[
        "path",
        "raster",
        "--x-mm=0,20",
        "--y-mm=0,6",
        "--pitch-mm",
        "2",
        "--step-mm",
        "5",
        "--arc-radius-mm",
        "1",
        "--arc-tolerance-um",
        "0.5",
        "--out",
        s(&out),
    ]));
    let (_, rows) = read_csv(&out);
    let mut worst: f64 = 0.0;
    for w in rows.windows(3) {
        let a = (w[1][0] - w[0][0], w[1][1] - w[0][1]);
        let b = (w[2][0] - w[1][0], w[2][1] - w[1][1]);
        worst = worst.max((a.0 * b.1 - a.1 * b.0).atan2(a.0 * b.0 + a.1 * b.1).abs());
    }
    let sagitta_um = 1.0 * (1.0 - (0.5 * worst).cos()) * 1e3;
    assert!(sagitta_um <= 0.5 + 1e-9, "{sagitta_um} um");
    assert!(worst > 0.0);
}
