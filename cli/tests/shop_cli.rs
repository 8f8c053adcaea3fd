//! The machine side as a shop uses it: a machine profile shared by jobs, any G-code program
//! simulated as written, the `--json`/`--quiet` conventions, shell completions and writers that
//! keep to their formats.

mod common;
use common::*;
use std::path::Path;

/// A flat 100 nm map on a 1 mm grid over [-12, 12]^2 mm.
fn flat_map(dir: &Path) -> String {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for j in -12..=12 {
        for i in -12..=12 {
            t.push_str(&format!("{i},{j},100\n"));
        }
    }
    write_arg(dir, "map.csv", &t)
}

const SIGMA_MM: f64 = 1.5;
const PEAK_NM_PER_S: f64 = 10.0;
/// Six sigma: the truncation changes the rate by less than 2e-8 of the peak.
const TRUNCATION_MM: f64 = 9.0;

/// A hand-written LinuxCNC-style program without DWELL markers: a plunge, a straight feed, a
/// counter-clockwise quarter circle, a pause, an inverse-time clockwise three-quarter circle and
/// straight move, a feed per minute again, a retract.
const HAND_WRITTEN: &str = "%
(A PROGRAM FROM ANOTHER CAM SYSTEM)
N10 G17 G21 G40 G49 G80 G90 G94
N20 G54
N30 G0 Z5
N40 G0 X-6 Y-4
N50 G1 Z0 F300
N60 G1 X2 Y-4 F240
N70 G3 X6 Y0 I0 J4 F120
N80 G4 P1.5
N90 G93
N100 G2 X2 Y4 I-4 J0 F20
N110 G1 X-4 Y4 F10
N120 G94
N130 G1 X-4 Y-2 F300
N140 G0 Z5
N150 M2
%
";

/// One move of the reference: the tool centre's (x, y) at the fraction `f` of the move, and the
/// move's duration, s.
type Move = (Box<dyn Fn(f64) -> (f64, f64)>, f64);

/// The moves of [`HAND_WRITTEN`] in contact, timed from the G-code rules (G94: 60 L / F,
/// G93: 60 / F, G4 P seconds), written out by hand.
fn reference_moves() -> Vec<Move> {
    use std::f64::consts::PI;
    let line = |a: (f64, f64), b: (f64, f64)| {
        Box::new(move |f: f64| (a.0 + f * (b.0 - a.0), a.1 + f * (b.1 - a.1)))
            as Box<dyn Fn(f64) -> (f64, f64)>
    };
    vec![
        // Plunge 5 mm at 300 mm/min at (-6, -4).
        (line((-6.0, -4.0), (-6.0, -4.0)), 1.0), // 60 * 5 / 300 s
        // 8 mm at 240 mm/min.
        (line((-6.0, -4.0), (2.0, -4.0)), 60.0 * 8.0 / 240.0),
        // Quarter circle about (2, 0), radius 4, from -90 to 0 degrees, at 120 mm/min.
        (
            Box::new(|f: f64| {
                let a = -PI / 2.0 + f * PI / 2.0;
                (2.0 + 4.0 * a.cos(), 4.0 * a.sin())
            }),
            60.0 * (PI / 2.0 * 4.0) / 120.0,
        ),
        // Pause 1.5 s at (6, 0).
        (line((6.0, 0.0), (6.0, 0.0)), 1.5),
        // Clockwise from 0 down through -90, -180 to -270 (= 90) degrees: G93 F20 = 3 s.
        (
            Box::new(|f: f64| {
                let a = -f * 1.5 * PI;
                (2.0 + 4.0 * a.cos(), 4.0 * a.sin())
            }),
            60.0 / 20.0,
        ),
        // G93 F10: 6 s.
        (line((2.0, 4.0), (-4.0, 4.0)), 60.0 / 10.0),
        // G94 again: 6 mm at 300 mm/min.
        (line((-4.0, 4.0), (-4.0, -2.0)), 60.0 * 6.0 / 300.0),
    ]
}

/// The removal at `(x, y)` of the reference moves: the Gaussian TIF integrated over time by the
/// midpoint rule with 20,000 steps per move (0.002 mm at most along the path).
fn reference_removal_nm(moves: &[Move], x: f64, y: f64) -> f64 {
    const STEPS: usize = 20_000;
    let mut h = 0.0;
    for (at, t) in moves {
        let dt = t / STEPS as f64;
        for k in 0..STEPS {
            let (px, py) = at((k as f64 + 0.5) / STEPS as f64);
            let r2 = (x - px).powi(2) + (y - py).powi(2);
            if r2 <= TRUNCATION_MM * TRUNCATION_MM {
                h += PEAK_NM_PER_S * (-r2 / (2.0 * SIGMA_MM * SIGMA_MM)).exp() * dt;
            }
        }
    }
    h
}

/// Largest removal difference allowed, relative to the largest removal.
const REMOVAL_TOL: f64 = 0.005;

#[test]
fn a_hand_written_program_with_arcs_and_inverse_time_simulates_as_written() {
    let d = tempfile::tempdir().unwrap();
    let map = flat_map(d.path());
    let prog = write_arg(d.path(), "cam.ngc", HAND_WRITTEN);
    let out = d.path().join("sim");
    let o = preston(&[
        "simulate",
        "--map",
        &map,
        "--gaussian-sigma-mm",
        "1.5",
        "--gaussian-peak-nm-per-s",
        "10",
        "--gaussian-truncation-mm",
        "9",
        "--program",
        &prog,
        "--out",
        s(&out),
        "--json",
        "--quiet",
    ]);
    assert!(ok(&o).is_empty(), "--quiet printed on stderr");
    let summary = stdout_json(&o);
    let moves = reference_moves();
    let total: f64 = moves.iter().map(|m| m.1).sum();
    let executed = summary["executed_time_s"].as_f64().unwrap();
    assert!(
        (executed - total).abs() < 1e-9 * total,
        "{executed} vs {total}"
    );
    assert!(summary["stretch_check"].is_null());
    assert!(!out.join("executed_dwell.csv").exists());
    let c = csv_columns(&out.join("residual.csv"), &["x_mm", "y_mm", "removal_nm"]);
    let reference: Vec<f64> = (0..c[0].len())
        .map(|k| reference_removal_nm(&moves, c[0][k], c[1][k]))
        .collect();
    let peak = reference.iter().cloned().fold(0.0, f64::max);
    assert!(peak > 10.0, "{peak}");
    let worst = (0..reference.len())
        .map(|k| (c[2][k] - reference[k]).abs())
        .fold(0.0, f64::max);
    assert!(
        worst <= REMOVAL_TOL * peak,
        "largest difference {worst} nm against a peak of {peak} nm"
    );
    let (vol_sim, vol_ref): (f64, f64) = (c[2].iter().sum(), reference.iter().sum());
    assert!((vol_sim - vol_ref).abs() <= REMOVAL_TOL * vol_ref);

    // The same from a job: map, TIF and machine (here the dialect) from the job file.
    let job = write_arg(
        d.path(),
        "job.toml",
        "[map]\nfile = 'map.csv'\n[tif]\ngaussian = { sigma_mm = 1.5, peak_rate_nm_per_s = 10.0, \
         truncation_radius_mm = 9.0 }\n[nc]\ndialect = 'linuxcnc'\n",
    );
    let out2 = d.path().join("sim2");
    ok(&preston(&[
        "simulate",
        "--job",
        &job,
        "--program",
        &prog,
        "--out",
        s(&out2),
        "--quiet",
    ]));
    let c2 = csv_columns(&out2.join("residual.csv"), &["removal_nm"]);
    assert_eq!(c2[0], c[2]);
}

/// A hand-written program with radius-form arcs: a counter-clockwise quarter circle (`R4`, the
/// arc of at most 180 degrees) and a clockwise three-quarter circle (`R-4`, the arc of more),
/// both about (2, 0).
const RADIUS_FORM: &str = "%
N10 G17 G21 G40 G49 G80 G90 G94
N20 G0 Z5
N30 G0 X-6 Y-4
N40 G1 Z0 F300
N50 G1 X2 Y-4 F240
N60 G3 X6 Y0 R4 F120
N70 G2 X2 Y4 R-4 F60
N80 G1 X-4 Y4 F100
N90 G0 Z5
N100 M2
%
";

/// The moves of [`RADIUS_FORM`] in contact with their centres worked out by hand.
fn radius_form_moves() -> Vec<Move> {
    use std::f64::consts::PI;
    let line = |a: (f64, f64), b: (f64, f64)| {
        Box::new(move |f: f64| (a.0 + f * (b.0 - a.0), a.1 + f * (b.1 - a.1)))
            as Box<dyn Fn(f64) -> (f64, f64)>
    };
    vec![
        // Plunge 5 mm at 300 mm/min: 60 * 5 / 300 s.
        (line((-6.0, -4.0), (-6.0, -4.0)), 1.0),
        (line((-6.0, -4.0), (2.0, -4.0)), 60.0 * 8.0 / 240.0),
        // From -90 to 0 degrees about (2, 0), radius 4, at 120 mm/min.
        (
            Box::new(|f: f64| {
                let a = -PI / 2.0 + f * PI / 2.0;
                (2.0 + 4.0 * a.cos(), 4.0 * a.sin())
            }),
            60.0 * (PI / 2.0 * 4.0) / 120.0,
        ),
        // Clockwise from 0 through -90 and -180 to -270 degrees, at 60 mm/min.
        (
            Box::new(|f: f64| {
                let a = -f * 1.5 * PI;
                (2.0 + 4.0 * a.cos(), 4.0 * a.sin())
            }),
            60.0 * (1.5 * PI * 4.0) / 60.0,
        ),
        (line((2.0, 4.0), (-4.0, 4.0)), 60.0 * 6.0 / 100.0),
    ]
}

/// Largest removal difference between the simulated radius-form program and the reference
/// integration, relative to the largest removal.
const RADIUS_FORM_TOL: f64 = 1e-3;

#[test]
fn radius_form_arcs_simulate_as_their_centre_form() {
    let d = tempfile::tempdir().unwrap();
    let map = flat_map(d.path());
    let run = |name: &str, text: &str| {
        let prog = write_arg(d.path(), &format!("{name}.ngc"), text);
        let out = d.path().join(name);
        let o = preston(&[
            "simulate",
            "--map",
            &map,
            "--gaussian-sigma-mm",
            "1.5",
            "--gaussian-peak-nm-per-s",
            "10",
            "--gaussian-truncation-mm",
            "9",
            "--program",
            &prog,
            "--dialect",
            "linuxcnc",
            "--out",
            s(&out),
            "--json",
            "--quiet",
        ]);
        let summary = stdout_json(&o);
        let c = csv_columns(&out.join("residual.csv"), &["x_mm", "y_mm", "removal_nm"]);
        (summary["executed_time_s"].as_f64().unwrap(), c)
    };
    let (t_r, c) = run("radius", RADIUS_FORM);
    let centre_form = RADIUS_FORM
        .replace("X6 Y0 R4", "X6 Y0 I0 J4")
        .replace("X2 Y4 R-4", "X2 Y4 I-4 J0");
    let (t_ij, c_ij) = run("centre", &centre_form);
    let moves = radius_form_moves();
    let total: f64 = moves.iter().map(|m| m.1).sum();
    assert!((t_r - total).abs() < 1e-9 * total, "{t_r} vs {total}");
    assert!((t_ij - total).abs() < 1e-9 * total, "{t_ij} vs {total}");
    let reference: Vec<f64> = (0..c[0].len())
        .map(|k| reference_removal_nm(&moves, c[0][k], c[1][k]))
        .collect();
    let peak = reference.iter().cloned().fold(0.0, f64::max);
    assert!(peak > 10.0, "{peak}");
    for (name, removal) in [("radius form", &c[2]), ("centre form", &c_ij[2])] {
        let worst = (0..reference.len())
            .map(|k| (removal[k] - reference[k]).abs())
            .fold(0.0, f64::max);
        assert!(
            worst <= RADIUS_FORM_TOL * peak,
            "{name}: largest difference {worst} nm against a peak of {peak} nm"
        );
    }
    // The two forms are one motion: the removals agree to rounding.
    let worst = (0..c[2].len())
        .map(|k| (c[2][k] - c_ij[2][k]).abs())
        .fold(0.0, f64::max);
    assert!(worst <= 1e-9 * peak, "{worst}");
}

#[test]
fn marked_programs_still_compare_with_the_plan_and_json_is_one_object() {
    let d = tempfile::tempdir().unwrap();
    let sol = d.path().join("sol");
    let o = preston(&[
        "solve",
        "--job",
        &data_arg("job_point_1mm.toml"),
        "--out",
        s(&sol),
        "--json",
        "--quiet",
    ]);
    assert!(ok(&o).is_empty(), "--quiet printed on stderr");
    let text = String::from_utf8(o.stdout.clone()).unwrap();
    assert_eq!(text.trim_end().lines().count(), 1, "{text}");
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(v["command"], "solve");
    assert_eq!(v["report"]["n"], report(&sol)["n"]);
    let prog = d.path().join("p.nc");
    let o = preston(&[
        "nc",
        "--dwell",
        s(&sol.join("dwell.csv")),
        "--job",
        &data_arg("job_point_1mm.toml"),
        "--feed-mode",
        "inverse-time",
        "--dialect",
        "fanuc",
        "--out",
        s(&prog),
        "--json",
        "--quiet",
    ]);
    assert!(ok(&o).is_empty());
    let nc = stdout_json(&o);
    assert_eq!(nc["dialect"], "fanuc");
    let planned = nc["total_dwell_s"].as_f64().unwrap();
    let out = d.path().join("sim");
    let o = preston(&[
        "simulate",
        "--job",
        &data_arg("job_point_1mm.toml"),
        "--program",
        s(&prog),
        "--out",
        s(&out),
        "--json",
        "--quiet",
    ]);
    assert!(ok(&o).is_empty());
    let sim = stdout_json(&o);
    let check = &sim["stretch_check"];
    assert_eq!(check["stretches"], v["report"]["n"]);
    assert!((check["planned_total_s"].as_f64().unwrap() - planned).abs() < 1e-3 * planned);
    assert!(out.join("executed_dwell.csv").exists());
}

#[test]
fn a_machine_profile_is_shared_and_the_job_and_flags_override_it() {
    let d = tempfile::tempdir().unwrap();
    write(
        d.path(),
        "mill.toml",
        "[machine]\nv_max_mm_per_min = 2000.0\n[nc]\ndialect = 'fanuc'\nfeed_mode = 'inverse-time'\n\
         work_offset = 'g55'\nstart_blocks = ['G17 G21 G40 G49 G80 G90', 'T1 M6']\n\
         spindle_rpm = 800\ncoolant = 'flood'\nprogram_number = 77\ndecimals = 3\n",
    );
    let dwell = write_arg(
        d.path(),
        "dwell.csv",
        "x_mm,y_mm,dwell_s\n0,0,1\n1,0,0.5\n2,0,2\n",
    );
    // The job names the profile and sets its own work offset.
    let job = write_arg(
        d.path(),
        "job.toml",
        "[machine]\nprofile = 'mill.toml'\n[nc]\nwork_offset = 'g56'\n",
    );
    let prog = d.path().join("p.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        &dwell,
        "--job",
        &job,
        "--out",
        s(&prog),
        "--quiet",
    ]));
    let text = std::fs::read_to_string(&prog).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(&lines[..2], &["%", "O0077"], "{text}");
    for want in [
        "N1 G17 G21 G40 G49 G80 G90",
        "N2 T1 M6",
        "N3 G17 G21 G56 G90 G93",
        "N4 S800 M3",
        "N5 M8",
    ] {
        assert!(lines.contains(&want), "{want} missing:\n{text}");
    }
    assert!(text.contains("X0.000 Y0.000"), "3 decimals:\n{text}");
    // --machine names the profile for a run without a job; flags win over it.
    let prog2 = d.path().join("q.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        &dwell,
        "--machine",
        s(&d.path().join("mill.toml")),
        "--dialect",
        "sinumerik",
        "--work-offset",
        "g54",
        "--out",
        s(&prog2),
        "--quiet",
    ]));
    let text = std::fs::read_to_string(&prog2).unwrap();
    assert!(text.starts_with("%_N_PRESTON_MPF\n"), "{text}");
    assert!(
        text.contains("G17 G71 G54 G90 G93") && text.contains("G94\n"),
        "{text}"
    );
    // A bad profile is refused before anything is written, naming the file and the field.
    write(
        d.path(),
        "bad.toml",
        "[nc]\ndialect = 'sinumerik'\nwork_offset = 'g59'\n",
    );
    let o = preston(&[
        "nc",
        "--dwell",
        &dwell,
        "--machine",
        s(&d.path().join("bad.toml")),
        "--out",
        s(&d.path().join("r.nc")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("bad.toml") && err.contains("work_offset"),
        "{err}"
    );
    assert!(!d.path().join("r.nc").exists());
}

#[test]
fn completions_generate_for_every_shell() {
    for shell in ["bash", "zsh", "fish", "powershell"] {
        let o = preston(&["completions", shell]);
        ok(&o);
        let text = String::from_utf8(o.stdout).unwrap();
        assert!(
            text.contains("preston") && text.contains("simulate"),
            "{shell}"
        );
    }
    assert_eq!(preston(&["completions", "tcsh"]).status.code(), Some(2));
}

#[test]
fn maps_are_written_as_npy_for_npy_names_and_other_extensions_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for j in 0..3 {
        for i in 0..4 {
            t.push_str(&format!(
                "{},{},{}\n",
                10.0 + 0.5 * i as f64,
                -2.0 + 0.5 * j as f64,
                i * 10 + j
            ));
        }
    }
    let map = write_arg(d.path(), "m.csv", &t);
    let npy = d.path().join("m.npy");
    ok(&preston(&[
        "map",
        "convert",
        "--map",
        &map,
        "--out",
        s(&npy),
    ]));
    let bytes = std::fs::read(&npy).unwrap();
    assert!(bytes.starts_with(b"\x93NUMPY"));
    assert_eq!(bytes.len() % 64, (12 * 8) % 64);
    let back = d.path().join("back.csv");
    ok(&preston(&[
        "map",
        "convert",
        "--map",
        s(&npy),
        "--pitch-mm",
        "0.5",
        "--out",
        s(&back),
    ]));
    let a = csv_columns(&back, &["z_nm"]);
    let mut got = a[0].clone();
    got.sort_by(f64::total_cmp);
    let mut want: Vec<f64> = (0..4)
        .flat_map(|i| (0..3).map(move |j| (i * 10 + j) as f64))
        .collect();
    want.sort_by(f64::total_cmp);
    assert_eq!(got, want);
    let o = preston(&[
        "map",
        "convert",
        "--map",
        &map,
        "--out",
        s(&d.path().join("m.xyz")),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains(".csv"), "{err}");
    assert!(!d.path().join("m.xyz").exists());
}
