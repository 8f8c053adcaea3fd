//! `preston solve --tif-model hertz [--curvature-dependent]` end to end: the removal rate at the
//! centre of each dwell point's contact patch and the patch's extent follow Hertz theory for the
//! design surface's local curvature there, against a hand calculation; the shift-invariant Hertz
//! TIF is the one `preston tif hertz` writes; the job file's `[tif] hertz` is the same solve; bad
//! combinations exit 2 with nothing written.

mod common;

use common::{csv_columns, expect_failure, ok, preston, report, s, write};
use std::path::{Path, PathBuf};

/// Hertz rate at the patch centre from the outputs (`removal / dwell`, both written with the
/// shortest round-trip decimal) against the closed form evaluated here in another order.
const RATE_REL_TOL: f64 = 1e-9;
/// Map pitch, mm: the patch radius is bracketed by the last map point inside it and the next.
const MAP_PITCH_MM: f64 = 0.1;
/// Off-plane part of a map point's tangent-frame offset, mm: the column through a dwell point
/// meets the patch within `dy` of `w` (the `u` offset is `dz z_x`, below 1e-3 mm here).
const TANGENT_SLACK_MM: f64 = 1e-3;

/// The tool: the published case of `preston tif hertz` with K = 1e-7 mm^2/N.
const FORCE_N: f64 = 10.0;
const TOOL_RADIUS_MM: f64 = 16.0;
const SPINDLE_RAD_S: f64 = 104.72;
const TILT_DEG: f64 = 15.0;
const TOOL_E_GPA: f64 = 0.005;
const TOOL_NU: f64 = 0.4;
const PART_E_GPA: f64 = 72.0;
const PART_NU: f64 = 0.2;
const PRESTON_K: f64 = 1e-7;
const TIF_PITCH_MM: f64 = 0.1;

/// Dwell points on the x axis, 6 mm apart: farther than two contact radii, so the removal at a
/// dwell point comes from that point alone.
const DWELL_X_MM: [f64; 3] = [0.0, 6.0, 12.0];

fn hertz_flags() -> Vec<String> {
    [
        ("--tif-model", "hertz".to_string()),
        ("--force-n", FORCE_N.to_string()),
        ("--tool-radius-mm", TOOL_RADIUS_MM.to_string()),
        ("--spindle-rad-s", SPINDLE_RAD_S.to_string()),
        ("--tilt-deg", TILT_DEG.to_string()),
        ("--tool-e-gpa", TOOL_E_GPA.to_string()),
        ("--tool-nu", TOOL_NU.to_string()),
        ("--part-e-gpa", PART_E_GPA.to_string()),
        ("--part-nu", PART_NU.to_string()),
        ("--preston-k", PRESTON_K.to_string()),
        ("--tif-pitch-mm", TIF_PITCH_MM.to_string()),
    ]
    .into_iter()
    .flat_map(|(f, v)| [f.to_string(), v])
    .collect()
}

/// The flat part's Hertz TIF of [`hertz_flags`] as `preston tif hertz` writes it, in `dir`.
fn flat_hertz_tif(dir: &Path) -> PathBuf {
    let tif = dir.join("tif.csv");
    let hertz = hertz_flags();
    let mut args: Vec<&str> = vec!["tif", "hertz"];
    // `preston tif hertz` names the grid pitch --pitch-mm and takes no --tif-model.
    for pair in hertz[2..].chunks(2) {
        args.push(if pair[0] == "--tif-pitch-mm" {
            "--pitch-mm"
        } else {
            &pair[0]
        });
        args.push(&pair[1]);
    }
    args.extend(["--out", s(&tif)]);
    ok(&preston(&args));
    tif
}

/// Hand calculation (Johnson, *Contact Mechanics*, 4.22-4.23 and 4.31): for part principal
/// curvatures `k1, k2` (1/mm, positive concave) the contact radius `a`, mm, and the Preston rate
/// at the patch centre, nm/s: `K p0 v0` with `p0 = 3F / (2 pi a^2)` and `v0 = omega R sin(tilt)`.
fn hertz_by_hand(k1: f64, k2: f64) -> (f64, f64) {
    let r_eff = 1.0 / ((1.0 / TOOL_RADIUS_MM - k1) * (1.0 / TOOL_RADIUS_MM - k2)).sqrt();
    let e_star_mpa = 1.0
        / ((1.0 - TOOL_NU.powi(2)) / (TOOL_E_GPA * 1e3)
            + (1.0 - PART_NU.powi(2)) / (PART_E_GPA * 1e3));
    let a = (3.0 * FORCE_N * r_eff / (4.0 * e_star_mpa)).cbrt();
    let p0 = 3.0 * FORCE_N / (2.0 * std::f64::consts::PI * a * a);
    let v0 = SPINDLE_RAD_S * TOOL_RADIUS_MM * TILT_DEG.to_radians().sin();
    (a, PRESTON_K * p0 * v0 * 1e6)
}

/// An even asphere `z = c r^2 / (1 + sqrt(1 - (1+k) c^2 r^2)) + A4 r^4` (convex: c, A4 < 0).
const ASPHERE_C: f64 = -1.0 / 40.0;
const ASPHERE_K: f64 = -0.5;
const ASPHERE_A4: f64 = -1e-5;
/// A convex sphere of radius 30 mm.
const SPHERE_C: f64 = -1.0 / 30.0;

/// Principal curvatures of the asphere at radius `r` (a surface of revolution): meridional
/// `z'' / (1 + z'^2)^(3/2)` and sagittal `z' / (r sqrt(1 + z'^2))` (`z''` at the vertex), from
/// `z' = c r / sqrt(1 - (1+k) c^2 r^2) + 4 A4 r^3`, `z'' = c / (1 - (1+k) c^2 r^2)^(3/2) + 12 A4 r^2`.
fn asphere_curvatures(r: f64) -> (f64, f64) {
    let q = 1.0 - (1.0 + ASPHERE_K) * ASPHERE_C * ASPHERE_C * r * r;
    let z1 = ASPHERE_C * r / q.sqrt() + 4.0 * ASPHERE_A4 * r.powi(3);
    let z2 = ASPHERE_C / q.powf(1.5) + 12.0 * ASPHERE_A4 * r * r;
    let w = 1.0 + z1 * z1;
    let meridional = z2 / w.powf(1.5);
    let sagittal = if r == 0.0 { z2 } else { z1 / (r * w.sqrt()) };
    (meridional, sagittal)
}

/// The map (bumps under the dwell points, on a lattice through them) and the dwell file.
fn case(dir: &Path) -> (PathBuf, PathBuf) {
    let mut map = String::from("x_mm,y_mm,z_nm\n");
    for j in 0..=80 {
        for i in 0..=200 {
            let (x, y) = (
                -4.0 + i as f64 * MAP_PITCH_MM,
                -4.0 + j as f64 * MAP_PITCH_MM,
            );
            let z: f64 = DWELL_X_MM
                .iter()
                .enumerate()
                .map(|(k, &xk)| {
                    (40.0 + 10.0 * k as f64) * (-((x - xk).powi(2) + y * y) / 4.0).exp()
                })
                .sum();
            map.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    let dwell: String = std::iter::once("x_mm,y_mm\n".to_string())
        .chain(DWELL_X_MM.iter().map(|x| format!("{x},0\n")))
        .collect();
    (write(dir, "map.csv", &map), write(dir, "dwell.csv", &dwell))
}

fn solve(map: &Path, dwell: &Path, surface: &Path, extra: &[&str], out: &Path) -> String {
    let mut args: Vec<String> = [
        "solve",
        "--map",
        s(map),
        "--dwell",
        s(dwell),
        "--surface",
        s(surface),
        "--v-max",
        "3000",
        "--edge",
        "none",
        "--out",
        s(out),
    ]
    .iter()
    .map(|a| a.to_string())
    .collect();
    args.extend(hertz_flags());
    args.extend(extra.iter().map(|a| a.to_string()));
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let stderr = ok(&preston(&refs));
    for f in ["dwell.csv", "residual.csv", "report.json"] {
        assert!(out.join(f).is_file(), "{f} not written");
    }
    let r = report(out);
    assert_eq!(r["status"], "converged", "{r}");
    stderr
}

/// What the outputs say at each dwell point: (dwell s, removal rate at the patch centre nm/s,
/// patch half-width along y through the point, mm).
fn at_dwell_points(out: &Path) -> Vec<(f64, f64, f64)> {
    let d = csv_columns(&out.join("dwell.csv"), &["x_mm", "dwell_s"]);
    let r = csv_columns(&out.join("residual.csv"), &["x_mm", "y_mm", "removal_nm"]);
    DWELL_X_MM
        .iter()
        .map(|&xk| {
            let k = d[0].iter().position(|&x| x == xk).unwrap();
            let t = d[1][k];
            assert!(t > 0.0, "no dwell at x = {xk}");
            let column: Vec<(f64, f64)> = (0..r[0].len())
                .filter(|&i| (r[0][i] - xk).abs() < 1e-9)
                .map(|i| (r[1][i], r[2][i]))
                .collect();
            let centre = column.iter().find(|(y, _)| y.abs() < 1e-9).unwrap().1;
            let half_width = column
                .iter()
                .filter(|(_, h)| *h > 0.0)
                .map(|(y, _)| y.abs())
                .fold(0.0, f64::max);
            (t, centre / t, half_width)
        })
        .collect()
}

fn assert_rel(got: f64, want: f64, tol: f64, what: &str) {
    assert!(
        (got - want).abs() <= tol * want.abs(),
        "{what}: {got} against {want} (relative {:.2e})",
        (got - want).abs() / want.abs()
    );
}

/// Checks the curvature-dependent and the shift-invariant solve on `surface` against the hand
/// calculation at the curvatures `curv(x)` of each dwell point.
fn check_surface(dir: &Path, surface_json: &str, curv: impl Fn(f64) -> (f64, f64)) {
    let (map, dwell) = case(dir);
    let surface = write(dir, "surface.json", surface_json);
    let (flat_a, flat_rate) = hertz_by_hand(0.0, 0.0);
    let curved = dir.join("curved");
    // Both compared at the points: the point model (the swept model would spread each TIF
    // along its 6 mm stretch).
    solve(
        &map,
        &dwell,
        &surface,
        &["--curvature-dependent", "--influence", "point"],
        &curved,
    );
    let flat = dir.join("flat");
    solve(&map, &dwell, &surface, &["--influence", "point"], &flat);
    let curved_at = at_dwell_points(&curved);
    let flat_at = at_dwell_points(&flat);
    for (k, &x) in DWELL_X_MM.iter().enumerate() {
        let (k1, k2) = curv(x);
        let (a, rate) = hertz_by_hand(k1, k2);
        // A convex part: a smaller effective radius, a smaller patch, a higher pressure.
        assert!(a < flat_a - 2.0 * MAP_PITCH_MM, "a = {a} mm at x = {x}");
        let (_, curved_rate, half_width) = curved_at[k];
        assert_rel(
            curved_rate,
            rate,
            RATE_REL_TOL,
            &format!("centre rate at x = {x}"),
        );
        assert!(
            half_width < a && a <= half_width + MAP_PITCH_MM + TANGENT_SLACK_MM,
            "patch at x = {x}: last point inside at {half_width} mm, a = {a} mm"
        );
        // The shift-invariant Hertz TIF is the flat-part one everywhere, and the
        // curvature-dependent one differs from it by (a_flat / a)^2 = (R_tool / R_eff)^(2/3).
        let (_, flat_rate_out, _) = flat_at[k];
        assert_rel(
            flat_rate_out,
            flat_rate,
            RATE_REL_TOL,
            &format!("flat rate at x = {x}"),
        );
        assert_rel(
            curved_rate / flat_rate_out,
            (flat_a / a).powi(2),
            RATE_REL_TOL,
            &format!("curved / flat at x = {x}"),
        );
    }
}

#[test]
fn curvature_dependent_hertz_on_a_sphere_follows_the_local_contact() {
    let dir = tempfile::tempdir().unwrap();
    check_surface(
        dir.path(),
        &format!(r#"{{"type": "conic", "curvature_per_mm": {SPHERE_C}, "conic": 0}}"#),
        |_| (SPHERE_C, SPHERE_C),
    );
}

#[test]
fn curvature_dependent_hertz_on_an_even_asphere_follows_the_local_contact() {
    let dir = tempfile::tempdir().unwrap();
    check_surface(
        dir.path(),
        &format!(
            r#"{{"type": "even_asphere", "curvature_per_mm": {ASPHERE_C}, "conic": {ASPHERE_K},
                 "coefs_mm": [{ASPHERE_A4}]}}"#
        ),
        asphere_curvatures,
    );
    // The curvature varies over the asphere, and with it the TIF: the rate at 12 mm differs
    // from the vertex's by the hand-calculated ratio (checked per point above), which is not 1.
    let (_, at_vertex) = hertz_by_hand(ASPHERE_C, ASPHERE_C);
    let (k1, k2) = asphere_curvatures(12.0);
    let (_, at_12) = hertz_by_hand(k1, k2);
    assert!(
        (at_12 / at_vertex - 1.0).abs() > 0.02,
        "{at_12} vs {at_vertex}"
    );
}

#[test]
fn the_shift_invariant_hertz_tif_is_the_one_preston_tif_writes_and_the_job_file_agrees() {
    let dir = tempfile::tempdir().unwrap();
    let (map, dwell) = case(dir.path());
    let surface = write(
        dir.path(),
        "surface.json",
        &format!(r#"{{"type": "conic", "curvature_per_mm": {SPHERE_C}, "conic": 0}}"#),
    );
    // The flags' shift-invariant TIF against the grid `preston tif hertz` writes.
    let from_flags = dir.path().join("flags");
    solve(&map, &dwell, &surface, &[], &from_flags);
    let tif = flat_hertz_tif(dir.path());
    let from_file = dir.path().join("file");
    ok(&preston(&[
        "solve",
        "--map",
        s(&map),
        "--dwell",
        s(&dwell),
        "--surface",
        s(&surface),
        "--tif",
        s(&tif),
        "--v-max",
        "3000",
        "--edge",
        "none",
        "--out",
        s(&from_file),
    ]));
    let a = csv_columns(&from_flags.join("dwell.csv"), &["dwell_s"]);
    let b = csv_columns(&from_file.join("dwell.csv"), &["dwell_s"]);
    for (x, y) in a[0].iter().zip(&b[0]) {
        assert_rel(*x, *y, RATE_REL_TOL, "dwell, flags against tif file");
    }
    // The job file's [tif] hertz with curvature_dependent: the same solve as the flags.
    let job = write(
        dir.path(),
        "job.toml",
        &format!(
            "[map]\nfile = 'map.csv'\n[dwell]\nfile = 'dwell.csv'\n[machine]\n\
             v_max_mm_per_min = 3000\n[edge]\nmethod = 'none'\n[surface]\nfile = 'surface.json'\n\
             [tif]\npitch_mm = {TIF_PITCH_MM}\ncurvature_dependent = true\n\
             hertz = {{ force_n = {FORCE_N:?}, tool_radius_mm = {TOOL_RADIUS_MM:?}, \
             spindle_rad_s = {SPINDLE_RAD_S:?}, tilt_deg = {TILT_DEG:?}, \
             tool_e_gpa = {TOOL_E_GPA:?}, tool_nu = {TOOL_NU:?}, part_e_gpa = {PART_E_GPA:?}, \
             part_nu = {PART_NU:?}, preston_k_mm2_per_n = {PRESTON_K:?} }}\n"
        ),
    );
    let from_job = dir.path().join("job");
    ok(&preston(&[
        "solve",
        "--job",
        s(&job),
        "--out",
        s(&from_job),
    ]));
    let curved = dir.path().join("curved");
    solve(&map, &dwell, &surface, &["--curvature-dependent"], &curved);
    for f in ["dwell.csv", "residual.csv"] {
        assert_eq!(
            std::fs::read(from_job.join(f)).unwrap(),
            std::fs::read(curved.join(f)).unwrap(),
            "{f}: job file against flags"
        );
    }
}

#[test]
fn bad_hertz_combinations_exit_2_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (map, dwell) = case(dir.path());
    let sphere = write(
        dir.path(),
        "sphere.json",
        &format!(r#"{{"type": "conic", "curvature_per_mm": {SPHERE_C}, "conic": 0}}"#),
    );
    // Concave with a radius of 10 mm, below the tool's 16 mm: no Hertz contact.
    let bowl = write(
        dir.path(),
        "bowl.json",
        r#"{"type": "conic", "curvature_per_mm": 0.1, "conic": 0}"#,
    );
    let tif = write(dir.path(), "tif.csv", "x_mm,y_mm,rate_nm_per_s\n-1,-1,0\n0,-1,0\n1,-1,0\n-1,0,0\n0,0,5\n1,0,0\n-1,1,0\n0,1,0\n1,1,0\n");
    let hertz = hertz_flags();
    let hertz: Vec<&str> = hertz.iter().map(String::as_str).collect();
    let base = ["--map", s(&map), "--dwell", s(&dwell), "--v-max", "3000"];
    let with = |extra: &[&str]| -> Vec<String> {
        base.iter()
            .chain(extra)
            .map(|a| a.to_string())
            .collect::<Vec<_>>()
    };
    let cases: Vec<(Vec<String>, Vec<&str>)> = vec![
        // No surface for the curvature-dependent model.
        (
            with(&[&hertz[..], &["--curvature-dependent"]].concat()),
            vec!["curvature_dependent", "design surface"],
        ),
        // A TIF file is not a Hertz model.
        (
            with(&[
                "--tif",
                s(&tif),
                "--surface",
                s(&sphere),
                "--curvature-dependent",
            ]),
            vec!["curvature_dependent", "hertz"],
        ),
        // The model without its material.
        (
            with(&["--tif-model", "hertz", "--tif-pitch-mm", "0.1"]),
            vec!["--tool-e-gpa"],
        ),
        // The model without its grid.
        (
            with(&[&hertz[..hertz.len() - 2], &["--surface", s(&sphere)]].concat()),
            vec!["pitch_mm"],
        ),
        // The model and a file at once.
        (
            with(&[&hertz[..], &["--tif", s(&tif)]].concat()),
            vec!["--tif"],
        ),
        // A part more concave than the tool.
        (
            with(
                &[
                    &hertz[..],
                    &["--surface", s(&bowl), "--curvature-dependent"],
                ]
                .concat(),
            ),
            vec!["no Hertz contact"],
        ),
    ];
    for (args, needles) in &cases {
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        expect_failure(&refs, needles);
    }
    // The job file: curvature_dependent without hertz, hertz without pitch_mm.
    for (tif_section, needle) in [
        (
            "file = 'tif.csv'\ncurvature_dependent = true\n",
            "curvature_dependent",
        ),
        ("hertz = { preston_k_mm2_per_n = 1e-7 }\n", "pitch_mm"),
    ] {
        let job = write(
            dir.path(),
            "job.toml",
            &format!(
                "[map]\nfile = 'map.csv'\n[dwell]\nfile = 'dwell.csv'\n[machine]\n\
                 v_max_mm_per_min = 3000\n[surface]\nfile = 'sphere.json'\n[tif]\n{tif_section}"
            ),
        );
        expect_failure(&["--job", s(&job)], &[needle]);
    }
}

/// With the swept model a curvature-dependent plan sweeps each dwell point's own Hertz TIF along
/// its stretch, and with an acceleration limit the solve executes its program on the part, each
/// contact sample applying the Hertz TIF of the curvature where it lands: the report's residual
/// is that run, and `simulate --program --job` (the job's TIF model and surface) leaves it too.
/// The same program simulated with the flat part's Hertz TIF leaves another residual.
#[test]
fn a_curvature_dependent_plan_sweeps_and_runs_its_program() {
    /// The solve's program and `nc`'s differ only in their number formatting.
    const PROGRAM_REL_TOL: f64 = 1e-3;
    let dir = tempfile::tempdir().unwrap();
    let mut map = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..25 {
        for ix in 0..25 {
            let (x, y) = (ix as f64 * 0.5 - 6.0, iy as f64 * 0.5 - 6.0);
            map.push_str(&format!(
                "{x},{y},{}\n",
                30.0 + 8.0 * (0.5 * x).cos() * (0.35 * y).sin()
            ));
        }
    }
    write(dir.path(), "map.csv", &map);
    write(
        dir.path(),
        "surface.json",
        &format!(r#"{{"type": "conic", "curvature_per_mm": {SPHERE_C}, "conic": -0.6}}"#),
    );
    let job = write(
        dir.path(),
        "job.toml",
        &format!(
            "[map]\nfile = 'map.csv'\n[dwell]\nraster_pitch_mm = 1.0\n[machine]\n\
             v_max_mm_per_min = 3000\na_max_mm_per_s2 = 300\naccel_method = 'squared-speed'\n[edge]\nmethod = 'none'\n\
             [surface]\nfile = 'surface.json'\n\
             [tif]\npitch_mm = {TIF_PITCH_MM}\ncurvature_dependent = true\n\
             hertz = {{ force_n = {FORCE_N:?}, tool_radius_mm = {TOOL_RADIUS_MM:?}, \
             spindle_rad_s = {SPINDLE_RAD_S:?}, tilt_deg = {TILT_DEG:?}, \
             tool_e_gpa = {TOOL_E_GPA:?}, tool_nu = {TOOL_NU:?}, part_e_gpa = {PART_E_GPA:?}, \
             part_nu = {PART_NU:?}, preston_k_mm2_per_n = {PRESTON_K:?} }}\n"
        ),
    );
    let out = dir.path().join("out");
    ok(&preston(&["solve", "--job", s(&job), "--out", s(&out)]));
    let r = report(&out);
    assert_eq!(r["influence"], "swept", "{}", r["warnings"]);
    let executed = r["executed"]["rms_after_nm"].as_f64().unwrap();
    assert_eq!(r["rms_after_nm"].as_f64().unwrap(), executed);
    assert!(
        r["sensitivity"]["tif_wider_3pct"]["rms_nm"]
            .as_f64()
            .unwrap()
            > executed
    );
    // Against the point model's plan of the same job: the swept plan executes better. (The job
    // keeps the limit in the plan's feeds: correction passes against the executed program, the
    // default, correct either model's plan to the same part, 0.8747 against 0.8745 nm.)
    let point = dir.path().join("point");
    ok(&preston(&[
        "solve",
        "--job",
        s(&job),
        "--influence",
        "point",
        "--out",
        s(&point),
    ]));
    let point_executed = report(&point)["rms_after_nm"].as_f64().unwrap();
    assert!(
        executed < point_executed,
        "swept {executed} nm against point {point_executed} nm"
    );
    let prog = dir.path().join("prog.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        s(&out.join("dwell.csv")),
        "--job",
        s(&job),
        "--out",
        s(&prog),
    ]));
    let sim = dir.path().join("sim");
    ok(&preston(&[
        "simulate",
        "--job",
        s(&job),
        "--program",
        s(&prog),
        "--out",
        s(&sim),
    ]));
    let run = report(&sim)["rms_after_nm"].as_f64().unwrap();
    assert!(
        (run - executed).abs() <= PROGRAM_REL_TOL * executed,
        "simulate --program {run} nm against the report's executed {executed} nm"
    );
    // The flat part's Hertz TIF (what `preston tif hertz` writes) on the same program.
    let tif = flat_hertz_tif(dir.path());
    let flat_sim = dir.path().join("flat_sim");
    ok(&preston(&[
        "simulate",
        "--job",
        s(&job),
        "--tif",
        s(&tif),
        "--program",
        s(&prog),
        "--out",
        s(&flat_sim),
    ]));
    let flat_run = report(&flat_sim)["rms_after_nm"].as_f64().unwrap();
    assert!(
        (flat_run - executed).abs() > 10.0 * PROGRAM_REL_TOL * executed,
        "flat TIF {flat_run} nm against curvature-dependent {executed} nm"
    );
}
