//! `preston solve` end to end: the sample job, and bad input that must fail cleanly.

mod common;

use common::{data, expect_failure, preston_cmd, write_arg};

#[test]
fn sample_job_end_to_end() {
    let out = tempfile::tempdir().unwrap();
    let status = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("report.json")).unwrap())
            .unwrap();
    for key in [
        "m",
        "n",
        "nnz",
        "skipped_rows",
        "rms_before_nm",
        "pv_before_nm",
        "rms_after_nm",
        "pv_after_nm",
        "total_dwell_s",
        "piston_nm",
        "objective",
        "max_bound_violation_s",
        "min_feed_mm_per_min",
        "max_feed_mm_per_min",
        "build_seconds",
        "solve_seconds",
        "solver",
        "iterations",
        "status",
    ] {
        assert!(report.get(key).is_some(), "report.json lacks {key}");
    }
    assert_eq!(report["m"], 9672);
    assert_eq!(report["status"], "converged");
    let before = report["rms_before_nm"].as_f64().unwrap();
    // `rms_after_nm` is the program's as executed (`residual.csv`); the model's residual at the
    // programmed feeds is `model` (`residual_model.csv`).
    let after = report["rms_after_nm"].as_f64().unwrap();
    let model = report["model"]["rms_nm"].as_f64().unwrap();
    assert_eq!(report["rms_after_nm"], report["executed"]["rms_after_nm"]);
    assert!(model < 0.05 * before, "RMS {before} -> {model}");
    assert!(report["max_feed_mm_per_min"].as_f64().unwrap() <= 3000.0 * (1.0 + 1e-9));

    // dwell.csv: feed = ds / dwell * 60 on every row; residual.csv consistent with report.
    let dwell = std::fs::read_to_string(out.path().join("dwell.csv")).unwrap();
    let mut lines = dwell.lines();
    assert_eq!(
        lines.next(),
        Some("x_mm,y_mm,ds_mm,dwell_s,feed_mm_per_min")
    );
    let mut rows = 0;
    for l in lines {
        let v: Vec<f64> = l.split(',').map(|c| c.parse().unwrap()).collect();
        assert!((v[4] - v[2] / v[3] * 60.0).abs() <= 1e-9 * v[4].abs().max(1.0));
        rows += 1;
    }
    assert_eq!(rows, report["n"].as_u64().unwrap() as usize);
    for (file, reported) in [("residual.csv", after), ("residual_model.csv", model)] {
        let residual = std::fs::read_to_string(out.path().join(file)).unwrap();
        assert!(residual.starts_with("x_mm,y_mm,z_nm,removal_nm,residual_nm\n"));
        let res: Vec<f64> = residual
            .lines()
            .skip(1)
            .map(|l| l.rsplit(',').next().unwrap().parse().unwrap())
            .collect();
        let mean = res.iter().sum::<f64>() / res.len() as f64;
        let rms = (res.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / res.len() as f64).sqrt();
        assert!((rms - reported).abs() < 1e-9 * reported, "{file}: {rms} nm");
    }
}

#[test]
fn bad_input_fails_cleanly() {
    let d = tempfile::tempdir().unwrap();
    let tif = data("tif_fluid_jet_10mm.csv").to_string_lossy().to_string();
    let good_map = write_arg(
        d.path(),
        "map.csv",
        "x_mm,y_mm,z_nm\n0,0,1\n1,0,2\n0,1,3\n1,1,4\n",
    );
    let common = ["--raster-pitch-mm", "1"];

    let missing = write_arg(d.path(), "missing.csv", "x_mm,z_nm\n0,1\n");
    expect_failure(
        &[
            &["--map", &missing, "--tif", &tif, "--v-max", "3000"][..],
            &common,
        ]
        .concat(),
        &["missing.csv", "missing column `y_mm`"],
    );
    let nonnum = write_arg(d.path(), "nonnum.csv", "x_mm,y_mm,z_nm\n0,0,1\n1,0,abc\n");
    expect_failure(
        &[
            &["--map", &nonnum, "--tif", &tif, "--v-max", "3000"][..],
            &common,
        ]
        .concat(),
        &["nonnum.csv", "line 3", "z_nm", "not a number"],
    );
    let irregular = write_arg(
        d.path(),
        "tif.csv",
        "x_mm,y_mm,rate_nm_per_s\n0,0,1\n1,0,1\n3,0,1\n0,1,1\n1,1,1\n3,1,1\n",
    );
    expect_failure(
        &[
            &["--map", &good_map, "--tif", &irregular, "--v-max", "3000"][..],
            &common,
        ]
        .concat(),
        &["tif.csv", "regular grid"],
    );
    let empty = write_arg(d.path(), "empty.csv", "x_mm,y_mm,z_nm\n");
    expect_failure(
        &[
            &["--map", &empty, "--tif", &tif, "--v-max", "3000"][..],
            &common,
        ]
        .concat(),
        &["empty.csv", "no data rows"],
    );
    expect_failure(
        &[
            &["--map", &good_map, "--tif", &tif, "--v-max", "0"][..],
            &common,
        ]
        .concat(),
        &["v_max_mm_per_min", "positive"],
    );
    expect_failure(
        &[
            &["--map", &good_map, "--tif", &tif, "--v-max=-5"][..],
            &common,
        ]
        .concat(),
        &["v_max_mm_per_min"],
    );
    expect_failure(
        &[
            &[
                "--map", &good_map, "--tif", &tif, "--v-max", "100", "--v-min", "200",
            ][..],
            &common,
        ]
        .concat(),
        &["v_min_mm_per_min", "exceeds"],
    );
    expect_failure(
        &[
            &[
                "--map",
                &good_map,
                "--tif",
                &tif,
                "--v-max",
                "3000",
                "--lbfgs-memory",
                "0",
            ][..],
            &common,
        ]
        .concat(),
        &["lbfgs_memory", "1 to 100"],
    );
    let job = write_arg(
        d.path(),
        "job.toml",
        "[machine]\nv_max_mm_per_min = 1\nspeed = 2\n",
    );
    expect_failure(&["--job", &job], &["job.toml", "speed"]);
}

/// The sample job as shipped (Gerchberg-Papoulis edge extension, its own acceleration limit): no dwell point
/// outside the map's extent holds more than twice the 95th percentile of the dwell on the map,
/// the acceleration stays within the limit and the program executed at that limit reproduces
/// the planned RMS within 10%; `--edge none` on the same job breaks the first target.
#[test]
fn sample_job_edge_and_machinability_targets() {
    let run = |extra: &[&str]| {
        let out = tempfile::tempdir().unwrap();
        let o = preston_cmd()
            .args(["solve", "--job"])
            .arg(data("job_point_1mm.toml"))
            .args(extra)
            .arg("--out")
            .arg(out.path())
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.path().join("report.json")).unwrap())
                .unwrap();
        let text = std::fs::read_to_string(out.path().join("dwell.csv")).unwrap();
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
        let (cx, cy, ct) = (col("x_mm"), col("y_mm"), col("dwell_s"));
        let rows: Vec<[f64; 3]> = lines
            .map(|l| {
                let v: Vec<f64> = l.split(',').map(|f| f.parse().unwrap()).collect();
                [v[cx], v[cy], v[ct]]
            })
            .collect();
        (r, rows, out)
    };
    // The map's extent: x 0 .. 118.08 mm, y 0 .. 8 mm (0.32 mm grid), read from the map itself.
    let map = std::fs::read_to_string(data("mirror_error_118x8mm.csv")).unwrap();
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for l in map.lines().skip(1) {
        let v: Vec<f64> = l.split(',').map(|f| f.parse().unwrap()).collect();
        x0 = x0.min(v[0]);
        x1 = x1.max(v[0]);
        y0 = y0.min(v[1]);
        y1 = y1.max(v[1]);
    }
    let spike_ratio = |rows: &[[f64; 3]]| {
        let inside = |r: &[f64; 3]| r[0] >= x0 && r[0] <= x1 && r[1] >= y0 && r[1] <= y1;
        let mut on: Vec<f64> = rows.iter().filter(|r| inside(r)).map(|r| r[2]).collect();
        on.sort_by(f64::total_cmp);
        let p95 = on[(0.95 * (on.len() - 1) as f64) as usize];
        let off = rows
            .iter()
            .filter(|r| !inside(r))
            .map(|r| r[2])
            .fold(0.0, f64::max);
        off / p95
    };
    let (r, rows, out) = run(&[]);
    // The limit is the job's own, as shipped.
    let job_text = std::fs::read_to_string(data("job_point_1mm.toml")).unwrap();
    let job_a_max: f64 = job_text
        .lines()
        .find_map(|l| l.trim().strip_prefix("a_max_mm_per_s2"))
        .and_then(|v| v.trim().trim_start_matches('=').trim().parse().ok())
        .expect("the sample job sets a_max_mm_per_s2");
    assert_eq!(r["a_max_mm_per_s2"].as_f64(), Some(job_a_max));
    // The planned residual is what R applied to the written dwell.csv leaves: `preston
    // simulate` of the same map, TIF and dwell file under the job's point model gives the same
    // RMS.
    let sim = out.path().join("simulated");
    let o = preston_cmd()
        .args(["simulate", "--map"])
        .arg(data("mirror_error_118x8mm.csv"))
        .arg("--tif")
        .arg(data("tif_fluid_jet_10mm.csv"))
        .arg("--dwell")
        .arg(out.path().join("dwell.csv"))
        .args(["--motion", "discrete"])
        .arg("--out")
        .arg(&sim)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let simulated: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sim.join("report.json")).unwrap()).unwrap();
    let (planned, applied) = (
        r["model"]["rms_nm"].as_f64().unwrap(),
        simulated["rms_after_nm"].as_f64().unwrap(),
    );
    assert!(
        (planned - applied).abs() <= 1e-9 * planned,
        "planned RMS {planned} nm, R applied to dwell.csv {applied} nm"
    );
    assert_eq!(r["edge"], "gerchberg-papoulis");
    assert!(r["edge_points"].as_u64().unwrap() > 0);
    assert_eq!(r["m"], 9672);
    let ratio = spike_ratio(&rows);
    assert!(
        ratio <= 2.0,
        "largest dwell off the map / p95 on it = {ratio}"
    );
    let a_max = r["a_max_mm_per_s2"].as_f64().unwrap();
    assert!(r["max_accel_mm_per_s2"].as_f64().unwrap() <= a_max * 1.01);
    let executed = r["executed"]["rms_ratio_to_plan"].as_f64().unwrap();
    assert!(
        (executed - 1.0).abs() <= 0.10,
        "executed / planned RMS = {executed}"
    );

    let (r, rows, _) = run(&["--edge", "none"]);
    assert_eq!(r["edge_points"], 0);
    let ratio = spike_ratio(&rows);
    assert!(ratio > 2.0, "without edge handling the ratio is {ratio}");
}

/// `preston solve --job data/job.toml` reads and parses the job file once, checks the job's
/// choices once and validates the solver settings once (the binary's debug counts, printed
/// with `PRESTON_DEBUG_COUNTS` set).
#[test]
fn the_sample_job_is_read_once_and_its_settings_validated_once() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .env("PRESTON_DEBUG_COUNTS", "1")
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let line = stderr
        .lines()
        .find_map(|l| l.strip_prefix("debug counts: "))
        .unwrap_or_else(|| panic!("no debug counts: {stderr}"));
    let counts: Vec<(&str, &str)> = line
        .split(' ')
        .map(|kv| kv.split_once('=').unwrap())
        .collect();
    assert_eq!(
        counts,
        vec![
            ("job_parsed", "1"),
            ("settings_validated", "1"),
            ("choices_checked", "1"),
        ]
    );
    // Without the variable nothing is printed.
    let quiet = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    assert!(!String::from_utf8_lossy(&quiet.stderr).contains("debug counts"));
}

/// Relative margin by which the default plan's executed residual may exceed the squared-speed
/// plan's on the same part.
const DEFAULT_TO_SQUARED_SPEED: f64 = 0.05;

/// Relative rounding of a limit held in the written dwell file (`t = ds / sqrt(u)` printed).
const LIMIT_ROUNDING_REL: f64 = 1e-6;

/// Largest `|v_{j+1}^2 - v_j^2| / (2 s_j)` (mm/s^2) over the rows of `dwell.csv`
/// (`x_mm,y_mm,ds_mm,dwell_s,...`), `v = ds / t`, skipping connecting moves (the path turns by
/// more than 60 degrees at both ends of the segment).
fn max_accel_between_feeds(rows: &[Vec<f64>]) -> f64 {
    const CORNER_DEG: f64 = 60.0;
    let n = rows.len();
    let turn = |j: usize| -> f64 {
        if j == 0 || j + 1 >= n {
            return 0.0;
        }
        let (ax, ay) = (rows[j][0] - rows[j - 1][0], rows[j][1] - rows[j - 1][1]);
        let (bx, by) = (rows[j + 1][0] - rows[j][0], rows[j + 1][1] - rows[j][1]);
        let c = (ax * bx + ay * by) / (ax.hypot(ay) * bx.hypot(by));
        c.clamp(-1.0, 1.0).acos().to_degrees()
    };
    (0..n.saturating_sub(1))
        .filter(|&j| !(turn(j) > CORNER_DEG && turn(j + 1) > CORNER_DEG))
        .map(|j| {
            let (v0, v1) = (rows[j][2] / rows[j][3], rows[j + 1][2] / rows[j + 1][3]);
            let s = (rows[j + 1][0] - rows[j][0]).hypot(rows[j + 1][1] - rows[j][1]);
            (v1 * v1 - v0 * v0).abs() / (2.0 * s)
        })
        .fold(0.0, f64::max)
}

/// A map on a lattice rotated by 30 degrees at a low acceleration limit (200 mm/s^2, ramps of
/// 6 mm at the fastest feed, wider than the TIF): the default plan exits 0 (one feed everywhere
/// meets the limit, so a converged plan exists), the program it writes holds the limit, and it
/// executes within [`DEFAULT_TO_SQUARED_SPEED`] of the squared-speed plan, each figure the
/// program as executed at the limit.
#[test]
fn the_default_plan_on_a_rotated_grid_at_a_low_limit_executes_as_well_as_the_best() {
    const A_MAX: f64 = 200.0;
    // Enough for the squared-speed plan's solves, too few for correction passes that do not
    // settle at this limit (the ramps, v_max^2 / 2a = 6.25 mm, are wider than the TIF): the
    // default must still return a converged plan, the better of the two as executed.
    const MAX_ITERATIONS: &str = "2000";
    let d = tempfile::tempdir().unwrap();
    let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
    let mut csv = String::from("x_mm,y_mm,z_nm\n");
    for j in 0..40 {
        for i in 0..60 {
            let (u, v) = (0.5 * i as f64, 0.5 * j as f64);
            let z = 50.0 * (u / 5.0).sin() + 30.0 * (v / 3.0).cos() + 10.0 * ((u + v) / 2.0).sin();
            csv.push_str(&format!(
                "{:.6},{:.6},{z:.6}\n",
                u * c - v * s,
                u * s + v * c
            ));
        }
    }
    let map = write_arg(d.path(), "rot.csv", &csv);
    let run = |extra: &[&str], name: &str| {
        let out = d.path().join(name);
        let o = preston_cmd()
            .args(["solve", "--map", &map, "--gaussian-sigma-mm", "1.5"])
            .args(["--gaussian-peak-nm-per-s", "10", "--raster-pitch-mm", "0.5"])
            .args(["--v-max", "3000", "--a-max-mm-per-s2", "200"])
            .args(["--max-iterations", MAX_ITERATIONS])
            .args(extra)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr).to_string();
        assert_eq!(o.status.code(), Some(0), "{name}: {err}");
        (common::report(&out), out, err)
    };
    let (r, out, err) = run(&[], "default");
    assert_eq!(r["status"], "converged", "{err}");
    assert_eq!(r["executed"]["a_max_mm_per_s2"].as_f64(), Some(A_MAX));
    // The programmed feeds, recomputed from the written dwell times, meet the limit: the
    // controller runs the program as written, without ramps of its own.
    let (_, rows) = common::csv_rows(&out.join("dwell.csv"));
    let a = max_accel_between_feeds(&rows);
    assert!(a <= A_MAX * (1.0 + LIMIT_ROUNDING_REL), "{a} mm/s^2: {err}");
    let (ss, _, _) = run(&["--accel-method", "squared-speed"], "squared-speed");
    let default_nm = r["executed"]["rms_after_nm"].as_f64().unwrap();
    let ss_nm = ss["executed"]["rms_after_nm"].as_f64().unwrap();
    eprintln!("executed RMS: default {default_nm} nm, squared speed {ss_nm} nm");
    assert!(
        default_nm <= ss_nm * (1.0 + DEFAULT_TO_SQUARED_SPEED),
        "the default executes to {default_nm} nm RMS, the squared-speed plan to {ss_nm} nm: {err}"
    );
}
