//! Robustness of `preston solve`: every class of bad input fails with a message naming
//! file, line and column, and writes nothing; accepted oddities (BOM, CRLF) give the same answer;
//! unreachable dwell points are reported; results do not depend on the thread count; a killed run
//! leaves no partial file.

mod common;

use common::{data_arg, expect_failure, preston_cmd, report, write_arg};
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

fn solve(args: &[&str], out: &Path) -> Output {
    preston_cmd()
        .arg("solve")
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

/// A smooth 21 x 21 map over 20 x 20 mm (1 mm pitch), as CSV text with the given line end.
fn smooth_map(eol: &str) -> String {
    let mut s = format!("x_mm,y_mm,z_nm{eol}");
    for iy in 0..21 {
        for ix in 0..21 {
            let (x, y) = (ix as f64, iy as f64);
            let z = 50.0 + 20.0 * (0.3 * x).sin() * (0.2 * y).cos();
            s.push_str(&format!("{x},{y},{z}{eol}"));
        }
    }
    s
}

const GAUSSIAN: [&str; 6] = [
    "--gaussian-sigma-mm",
    "2",
    "--gaussian-peak-nm-per-s",
    "10",
    "--v-max",
    "2000",
];

#[test]
fn csv_errors_name_file_line_and_column() {
    let d = tempfile::tempdir().unwrap();
    let p = d.path();
    let raster = ["--raster-pitch-mm", "2"];
    let with = |map: &str| -> Vec<String> {
        let mut v = vec!["--map".to_string(), map.to_string()];
        v.extend(GAUSSIAN.iter().map(|s| s.to_string()));
        v.extend(raster.iter().map(|s| s.to_string()));
        v
    };
    let run = |map: &str, needles: &[&str]| {
        let args = with(map);
        let args: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        expect_failure(&args, needles);
    };
    // Misspelt header, unknown unit, infinity, duplicate point, empty file (a map in um or m is
    // converted: `cli/tests/metrology_cli.rs`).
    run(
        &write_arg(p, "misspelt.csv", "x_mm,y_nm,z_nm\n0,0,1\n"),
        &["misspelt.csv", "line 1", "missing column `y_mm`"],
    );
    run(
        &write_arg(p, "units.csv", "x_mm,y_mm,z_pm\n0,0,1\n"),
        &["units.csv", "missing column `z_nm`", "found `z_pm`"],
    );
    run(
        &write_arg(p, "inf.csv", "x_mm,y_mm,z_nm\n0,0,1\n1,0,inf\n"),
        &["inf.csv", "line 3", "z_nm"],
    );
    run(
        &write_arg(p, "dup.csv", "x_mm,y_mm,z_nm\n0,0,1\n1,0,2\n0,0,3\n"),
        &["dup.csv", "line 4", "line 2"],
    );
    run(&write_arg(p, "blank.csv", ""), &["blank.csv", "empty"]);
    run(
        &write_arg(p, "ragged.csv", "x_mm,y_mm,z_nm\n0,0,1\n1,0\n"),
        &["ragged.csv", "line 3"],
    );
    // TIF: negative rate and all-zero rates.
    let map = write_arg(p, "map.csv", &smooth_map("\n"));
    for (name, text, needle) in [
        (
            "neg_tif.csv",
            "x_mm,y_mm,rate_nm_per_s\n0,0,1\n1,0,-1\n0,1,1\n1,1,1\n",
            "negative rate",
        ),
        (
            "zero_tif.csv",
            "x_mm,y_mm,rate_nm_per_s\n0,0,0\n1,0,0\n0,1,0\n1,1,0\n",
            "all rates are zero",
        ),
    ] {
        let tif = write_arg(p, name, text);
        expect_failure(
            &[
                "--map",
                &map,
                "--tif",
                &tif,
                "--v-max",
                "2000",
                "--raster-pitch-mm",
                "1",
            ],
            &[name, needle],
        );
    }
}

#[test]
fn bom_and_crlf_give_the_same_answer() {
    let d = tempfile::tempdir().unwrap();
    let unix = write_arg(d.path(), "unix.csv", &smooth_map("\n"));
    let windows = write_arg(
        d.path(),
        "windows.csv",
        &format!("\u{feff}{}", smooth_map("\r\n")),
    );
    let mut outs = Vec::new();
    for (k, map) in [unix, windows].iter().enumerate() {
        let out = d.path().join(format!("out{k}"));
        let mut args = vec!["--map", map.as_str(), "--raster-pitch-mm", "2"];
        args.extend(GAUSSIAN);
        let o = solve(&args, &out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        outs.push(out);
    }
    for f in ["dwell.csv", "residual.csv"] {
        assert_eq!(
            std::fs::read(outs[0].join(f)).unwrap(),
            std::fs::read(outs[1].join(f)).unwrap(),
            "{f} differs between LF and BOM+CRLF input"
        );
    }
}

/// Preston's own raster covers the map plus the TIF's radius, so the corners of its margin lie
/// beyond the footprint of every map point: they are counted in report.json and said as a note,
/// not warned about as a dwell file's stray points are.
#[test]
fn a_generated_raster_s_margin_corners_are_a_note_not_a_warning() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &smooth_map("\n"));
    let out = d.path().join("out");
    let mut args = vec!["--map", map.as_str(), "--raster-pitch-mm", "1"];
    args.extend(GAUSSIAN);
    let o = solve(&args, &out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let r = report(&out);
    let n = r["unreachable_dwell_points"].as_u64().unwrap();
    assert!(n > 0, "{r}");
    assert!(
        stderr.contains(&format!("note: {n} points of the raster's margin")),
        "{stderr}"
    );
    assert!(!stderr.contains("have no map point"), "{stderr}");
}

#[test]
fn unreachable_dwell_points_are_reported_at_their_lower_bound() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &smooth_map("\n"));
    // A raster over the map at 2 mm pitch, then two points 500 mm away (out of the 6 mm reach).
    let mut text = String::from("x_mm,y_mm\n");
    let mut n = 0;
    for iy in 0..11 {
        for k in 0..11 {
            let ix = if iy % 2 == 0 { k } else { 10 - k };
            text.push_str(&format!("{},{}\n", 2 * ix, 2 * iy));
            n += 1;
        }
    }
    text.push_str("520,20\n540,20\n");
    let dwell = write_arg(d.path(), "dwell.csv", &text);
    let out = d.path().join("out");
    let mut args = vec!["--map", map.as_str(), "--dwell", dwell.as_str()];
    args.extend(GAUSSIAN);
    let o = solve(&args, &out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(
        stderr.contains("2 dwell points have no map point"),
        "{stderr}"
    );
    let r = report(&out);
    assert_eq!(r["unreachable_dwell_points"], 2);
    assert_eq!(
        r["unreachable_dwell_indices"],
        serde_json::json!([n, n + 1])
    );
    // Their dwell is the lower bound ds / (v_max / 60).
    let rows: Vec<Vec<f64>> = std::fs::read_to_string(out.join("dwell.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    for row in &rows[n..] {
        let lower = row[2] / (2000.0 / 60.0);
        assert!((row[3] - lower).abs() <= 1e-9 * lower, "{row:?}");
    }
}

#[test]
fn tif_wider_than_map_is_a_warning() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &smooth_map("\n"));
    let out = d.path().join("out");
    // Truncation radius 15 mm: a 30 mm footprint on a 20 mm map.
    let o = solve(
        &[
            "--map",
            &map,
            "--gaussian-sigma-mm",
            "5",
            "--gaussian-peak-nm-per-s",
            "10",
            "--gaussian-truncation-mm",
            "15",
            "--v-max",
            "2000",
            "--raster-pitch-mm",
            "3",
        ],
        &out,
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert!(stderr.contains("wider than the map"), "{stderr}");
    let r = report(&out);
    assert_eq!(r["warnings"].as_array().unwrap().len(), 1);
    // A 3 sigma = 6 mm footprint of 12 mm does not warn.
    let out2 = d.path().join("out2");
    let mut args = vec!["--map", map.as_str(), "--raster-pitch-mm", "2"];
    args.extend(GAUSSIAN);
    let o = solve(&args, &out2);
    assert!(o.status.success());
    assert!(report(&out2)["warnings"].as_array().unwrap().is_empty());
}

#[test]
fn not_converging_is_a_status_and_an_exit_code() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &smooth_map("\n"));
    let mut args = vec![
        "--map",
        map.as_str(),
        "--raster-pitch-mm",
        "2",
        "--max-iterations",
        "2",
    ];
    args.extend(GAUSSIAN);
    let out = d.path().join("out");
    let o = solve(&args, &out);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("did not converge"), "{stderr}");
    assert_ne!(report(&out)["status"], "converged");
    args.push("--accept-best-iterate");
    let o = solve(&args, &d.path().join("out2"));
    assert!(o.status.success());
}

/// Report keys that are wall-clock times and may differ between runs.
const TIMING_KEYS: [&str; 2] = ["build_seconds", "solve_seconds"];

#[test]
fn results_do_not_depend_on_the_thread_count() {
    assert_independent_of_the_thread_count("job_point_1mm.toml");
}

/// The sample job (the executed program, its correction passes, the resolution and the
/// sensitivity run side by side): the same outputs on one thread and on two.
#[test]
fn the_sample_does_not_depend_on_the_thread_count() {
    assert_independent_of_the_thread_count("job.toml");
}

/// `preston solve --job data/JOB` writes the same `dwell.csv`, `residual.csv` and report (but
/// for its timings) on one thread and on two.
fn assert_independent_of_the_thread_count(job: &str) {
    let d = tempfile::tempdir().unwrap();
    let mut outs: Vec<PathBuf> = Vec::new();
    for threads in ["1", "2"] {
        let out = d.path().join(format!("t{threads}"));
        let o = preston_cmd()
            .env("RAYON_NUM_THREADS", threads)
            .args(["solve", "--job", &data_arg(job), "--out"])
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        outs.push(out);
    }
    for f in ["dwell.csv", "residual.csv"] {
        assert!(
            std::fs::read(outs[0].join(f)).unwrap() == std::fs::read(outs[1].join(f)).unwrap(),
            "{f} differs between 1 and 2 threads"
        );
    }
    let (mut a, mut b) = (report(&outs[0]), report(&outs[1]));
    for k in TIMING_KEYS {
        a.as_object_mut().unwrap().remove(k);
        b.as_object_mut().unwrap().remove(k);
    }
    assert_eq!(a, b);
}

/// Each file written by `preston solve` is whole: `report.json` parses, and each CSV has a final
/// newline and the header's number of fields on every row. (The outputs are staged whole and
/// then renamed one after another: a kill before the first rename leaves the old outputs, one
/// between two renames an old and a new file side by side, each of them whole;
/// `a_kill_injected_in_the_commit_leaves_whole_files` injects both.)
fn assert_complete(out: &Path) {
    report(out);
    for f in ["dwell.csv", "residual.csv"] {
        let text = std::fs::read_to_string(out.join(f)).unwrap();
        assert!(text.ends_with('\n'), "{f} truncated");
        let mut lines = text.lines();
        let fields = lines.next().unwrap().split(',').count();
        let mut rows = 0;
        for l in lines {
            assert_eq!(l.split(',').count(), fields, "{f}: short row {l}");
            for c in l.split(',') {
                c.parse::<f64>().unwrap();
            }
            rows += 1;
        }
        assert!(rows > 0, "{f} has no rows");
    }
}

#[test]
fn a_killed_solve_leaves_no_partial_output() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let job = data_arg("job_point_1mm.toml");
    // A complete first run, and its duration.
    let start = Instant::now();
    let o = solve(&["--job", &job], &out);
    let full = start.elapsed();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let first = std::fs::read(out.join("dwell.csv")).unwrap();
    // Runs with another pitch, killed at fractions of the full duration (the last ones during
    // or just before writing): each output is the old file or a whole new one, never a part.
    for fraction in [0.3, 0.8, 0.95, 1.0] {
        let mut child = preston_cmd()
            .args(["solve", "--job", &job, "--raster-pitch-mm", "1.3", "--out"])
            .arg(&out)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_secs_f64(full.as_secs_f64() * fraction));
        let _ = child.kill();
        let _ = child.wait();
        assert_complete(&out);
        let now = std::fs::read(out.join("dwell.csv")).unwrap();
        // Either the first run's file or the new raster's (a different number of rows).
        let rows = |b: &[u8]| String::from_utf8_lossy(b).lines().count();
        assert!(now == first || rows(&now) != rows(&first));
    }
    // No stray files with the final names' prefixes other than hidden temporaries.
    for e in std::fs::read_dir(&out).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().to_string();
        assert!(
            [
                "dwell.csv",
                "residual.csv",
                "residual_model.csv",
                "report.json"
            ]
            .contains(&name.as_str())
                || (name.starts_with('.') && name.ends_with(".tmp")),
            "unexpected file {name}"
        );
    }
}

/// A kill injected at each step of the commit (`PRESTON_KILL_AT_COMMIT`): after staging and
/// before any rename, the previous run's outputs are left byte for byte and no temporary is
/// visible under an output's name; between renames, each output is whole (the old or the new
/// one); the next run removes the dead run's temporaries and commits all of its outputs.
#[test]
fn a_kill_injected_in_the_commit_leaves_whole_files() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let map = write_arg(d.path(), "m.csv", &smooth_map("\n"));
    let base = [
        "--map",
        &map,
        "--gaussian-sigma-mm",
        "1",
        "--gaussian-peak-nm-per-s",
        "10",
        "--gaussian-truncation-mm",
        "3",
        "--v-max",
        "3000",
    ];
    let with_pitch = |p: &str| {
        let mut a = base.to_vec();
        a.extend(["--raster-pitch-mm", p]);
        a.iter().map(|s| s.to_string()).collect::<Vec<String>>()
    };
    let run = |args: &[String], kill_at: Option<usize>| {
        let mut c = preston_cmd();
        c.arg("solve").args(args).arg("--out").arg(&out);
        if let Some(k) = kill_at {
            c.env("PRESTON_KILL_AT_COMMIT", k.to_string());
        }
        c.output().unwrap()
    };
    let first = run(&with_pitch("1"), None);
    assert!(
        first.status.success(),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let names = ["dwell.csv", "residual.csv", "report.json"];
    let snapshot = || -> Vec<Vec<u8>> {
        names
            .iter()
            .map(|n| std::fs::read(out.join(n)).unwrap())
            .collect()
    };
    for kill_at in 0..names.len() {
        let before = snapshot();
        let o = run(&with_pitch("0.7"), Some(kill_at));
        assert!(!o.status.success(), "the injected kill did not happen");
        assert_complete(&out);
        if kill_at == 0 {
            assert_eq!(
                snapshot(),
                before,
                "a kill before the first rename changed an output"
            );
        }
        // Restore the first run's outputs for the next step.
        let o = run(&with_pitch("1"), None);
        assert!(o.status.success());
    }
    // The dead runs' temporaries are gone after the next commit.
    for e in std::fs::read_dir(&out).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().to_string();
        assert!(names.contains(&name.as_str()), "left behind: {name}");
    }
}
