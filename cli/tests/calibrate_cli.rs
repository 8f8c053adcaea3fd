//! The shop loop through the binary: a plan, its program, a run in the virtual shop with a tool
//! that is not the spot test, `preston calibrate` learning that tool from the measured change, and
//! `preston solve --calibration` planning the next run with it and stating what the
//! interferometer is expected to read. The calibrated figures are checked against the shop's true
//! tool (its footprint's moments, which `shop.json` states), the calibrated TIF against the
//! Gaussian's closed-form volume, centroid and second moment. Bad inputs end with exit 2, a
//! message naming the file and nothing written.

mod common;
use common::*;
use preston_solver::iterate::learned::RUN_TO_RUN_RATE_SIGMA;
use std::path::{Path, PathBuf};

/// The spot test: a Gaussian of this sigma, peak and truncation radius.
const SIGMA_MM: f64 = 1.4;
const PEAK_NM_PER_S: f64 = 12.0;
const TRUNCATION_MM: f64 = 6.0;

/// The shop's true tool.
const TRUE_RATE: f64 = 1.06;
const TRUE_WIDTH: f64 = 1.03;
const TRUE_OFFSET_MM: (f64, f64) = (0.1, -0.08);
const NOISE_RMS_NM: f64 = 0.3;

/// The rate factor is recovered within this (relative).
const RATE_TOL: f64 = 0.005;
/// The width factor within this (relative).
const WIDTH_TOL: f64 = 0.01;
/// The centroid offset within this, mm.
const OFFSET_TOL_MM: f64 = 0.02;
/// The shop's footprint figures are the tool's as set within this: its moments summed on a grid
/// of a fortieth of the footprint radius.
const FIGURES_TOL: f64 = 1e-3;
/// The calibrated TIF's volume, second-moment radius and centroid agree with the figures applied
/// to the Gaussian within these (the free-form correction, where applied, adds a little).
const TIF_VOLUME_TOL: f64 = 0.01;
const TIF_RADIUS_TOL: f64 = 0.01;
const TIF_CENTROID_TOL_MM: f64 = 0.02;
/// The next run's reading within this of what its plan expected (relative): one draw of the
/// interferometer's noise against the expectation over draws.
const EXPECTED_READING_TOL: f64 = 0.1;

/// The map: 30 x 16 mm at 0.5 mm.
const PITCH_MM: f64 = 0.5;
const NX: usize = 61;
const NY: usize = 33;

/// The form error, nm: smooth terms the run corrects and ripples of periods 4.0 to 4.2 mm (eight
/// pixels or more) it partly cannot, as measured maps carry.
fn form_nm(x: f64, y: f64) -> f64 {
    let (u, v) = (x - 15.0, y - 8.0);
    60.0 * (0.21 * u).sin() * (0.33 * v + 0.4).cos()
        + 40.0 * (0.13 * u + 0.17 * v).cos()
        + 0.08 * u * u
        + 3.0 * (1.5 * u + 0.6 * v).sin()
        + 2.0 * (1.0 * u - 1.2 * v + 0.7).cos()
        + 1.5 * (1.5 * v + 0.3 * u).sin()
}

/// Writes the map as `x_mm,y_mm,z_nm`, shifted by `dx_mm` along x.
fn write_map(dir: &Path, name: &str, dx_mm: f64) -> PathBuf {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for j in 0..NY {
        for i in 0..NX {
            let (x, y) = (i as f64 * PITCH_MM, j as f64 * PITCH_MM);
            t.push_str(&format!("{},{},{:.6}\n", x + dx_mm, y, form_nm(x, y)));
        }
    }
    write(dir, name, &t)
}

fn gaussian_args() -> Vec<String> {
    [
        ("--gaussian-sigma-mm", SIGMA_MM),
        ("--gaussian-peak-nm-per-s", PEAK_NM_PER_S),
        ("--gaussian-truncation-mm", TRUNCATION_MM),
    ]
    .iter()
    .flat_map(|(k, v)| [k.to_string(), v.to_string()])
    .collect()
}

/// The plan's limits and settings, shared by both solves: the sample job's time weight and
/// correction passes against the executed program (the squared-speed method takes longer here).
const PLAN_ARGS: [&str; 12] = [
    "--raster-pitch-mm",
    "0.5",
    "--v-max",
    "3000",
    "--v-min",
    "1",
    "--a-max-mm-per-s2",
    "1000",
    "--rho",
    "0.01",
    "--accel-method",
    "correction-passes",
];

/// The NC program of a plan's `dwell.csv` for the shop's machine (3000 mm/min, 1000 mm/s^2).
fn write_program(dwell: &Path, program: &Path) {
    ok(&preston_cmd()
        .args(["nc", "--quiet", "--dwell", s(dwell)])
        .args(["--v-max", "3000", "--a-max-mm-per-s2", "1000"])
        .args(["--out", s(program)])
        .output()
        .unwrap());
}

/// Runs `program` on the part `surface` in the shop with its true tool, the interferometer's
/// noise seeded by `seed`, into `out`.
fn run_in_shop(surface: &Path, program: &Path, seed: u64, out: &Path) {
    ok(&preston_cmd()
        .args(["shop", "--quiet", "--surface", s(surface)])
        .args(["--program", s(program)])
        .args(gaussian_args())
        .args(["--a-max-mm-per-s2", "1000"])
        .args(["--tool-rate-factor", &TRUE_RATE.to_string()])
        .args(["--tool-width-factor", &TRUE_WIDTH.to_string()])
        .arg(format!(
            "--tool-offset-mm={},{}",
            TRUE_OFFSET_MM.0, TRUE_OFFSET_MM.1
        ))
        .args(["--noise-rms-nm", &NOISE_RMS_NM.to_string()])
        .args(["--seed", &seed.to_string(), "--out", s(out)])
        .output()
        .unwrap());
}

/// The run made once for the whole file: the measured maps, the program, the shop's record and
/// the calibration's folder.
struct Run {
    _dir: tempfile::TempDir,
    root: PathBuf,
    before: PathBuf,
    after: PathBuf,
    program: PathBuf,
    shop: serde_json::Value,
    calibration: PathBuf,
}

fn run_loop() -> Run {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_path_buf();
    let surface = write_map(&root, "surface.csv", 0.0);
    let g = gaussian_args();
    // The shop measures the part before the run (its interferometer: noise, piston and tilt).
    let v0 = root.join("v0");
    ok(&preston_cmd()
        .args(["shop", "--quiet", "--surface", s(&surface)])
        .args(&g)
        .args(["--noise-rms-nm", &NOISE_RMS_NM.to_string(), "--seed", "3"])
        .args(["--out", s(&v0)])
        .output()
        .unwrap());
    let before = v0.join("measured.csv");
    let plan = root.join("plan");
    ok(&preston_cmd()
        .args(["solve", "--quiet", "--map", s(&before)])
        .args(&g)
        .args(PLAN_ARGS)
        .args(["--out", s(&plan)])
        .output()
        .unwrap());
    let program = root.join("prog.nc");
    write_program(&plan.join("dwell.csv"), &program);
    let shop = root.join("shop");
    run_in_shop(&v0.join("surface_after.csv"), &program, 4, &shop);
    let after = shop.join("measured.csv");
    let calibration = root.join("calibration");
    ok(&preston_cmd()
        .args(["calibrate", "--quiet", "--before", s(&before)])
        .args(["--after", s(&after), "--program", s(&program)])
        .args(&g)
        .args(["--a-max-mm-per-s2", "1000", "--out", s(&calibration)])
        .output()
        .unwrap());
    Run {
        shop: read_json(&shop.join("shop.json")),
        _dir: dir,
        root,
        before,
        after,
        program,
        calibration,
    }
}

fn num(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} is not a number: {v}"))
}

/// Volume (nm mm^2 / s), centroid (mm) and second-moment radius (mm) of a TIF CSV.
fn tif_moments(path: &Path) -> (f64, (f64, f64), f64) {
    let c = csv_columns(path, &["x_mm", "y_mm", "rate_nm_per_s"]);
    let (x, y, r) = (&c[0], &c[1], &c[2]);
    let step = |v: &[f64]| {
        let mut u: Vec<f64> = v.to_vec();
        u.sort_by(f64::total_cmp);
        u.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        u[1] - u[0]
    };
    let cell = step(x) * step(y);
    let sum: f64 = r.iter().sum();
    let cx = x.iter().zip(r).map(|(x, r)| x * r).sum::<f64>() / sum;
    let cy = y.iter().zip(r).map(|(y, r)| y * r).sum::<f64>() / sum;
    let m2 = (0..r.len())
        .map(|k| ((x[k] - cx).powi(2) + (y[k] - cy).powi(2)) * r[k])
        .sum::<f64>()
        / sum;
    (sum * cell, (cx, cy), m2.sqrt())
}

/// The truncated Gaussian's volume, nm mm^2 / s, and second-moment radius, mm (closed forms).
fn gaussian_moments() -> (f64, f64) {
    let a = TRUNCATION_MM * TRUNCATION_MM / (2.0 * SIGMA_MM * SIGMA_MM);
    let kept = 1.0 - (-a).exp();
    let volume = 2.0 * std::f64::consts::PI * SIGMA_MM * SIGMA_MM * PEAK_NM_PER_S * kept;
    // E[r^2] of the 2-D Gaussian restricted to r <= R.
    let m2 = 2.0 * SIGMA_MM * SIGMA_MM * (1.0 - a * (-a).exp() / kept);
    (volume, m2.sqrt())
}

/// The whole loop in one test (each step needs the one before; the run is made once).
#[test]
fn calibrate_learns_the_shop_tool_and_solve_plans_with_it() {
    let run = run_loop();

    // The shop's true footprint is the tool as set (its own moments against the spot test's).
    let truth = &run.shop["tool_figures"];
    for (key, set) in [
        ("rate_factor", TRUE_RATE),
        ("width_factor", TRUE_WIDTH),
        ("offset_x_mm", TRUE_OFFSET_MM.0),
        ("offset_y_mm", TRUE_OFFSET_MM.1),
    ] {
        assert!(
            (num(truth, key) - set).abs() < FIGURES_TOL,
            "shop.json tool_figures {key} {} against {set}",
            num(truth, key)
        );
    }

    // calibration.json has every key the interface promises, and the figures are the tool's.
    let c = read_json(&run.calibration.join("calibration.json"));
    for key in [
        "rate_factor",
        "width_factor",
        "offset_x_mm",
        "offset_y_mm",
        "drift_per_hour",
    ] {
        let v = num(&c, key);
        let sigma = num(&c, &format!("{key}_sigma"));
        assert!(v.is_finite(), "{key} = {v}");
        assert!(sigma.is_finite() && sigma >= 0.0, "{key}_sigma = {sigma}");
    }
    for key in ["fit_rms_nm", "noise_rms_nm"] {
        let v = num(&c, key);
        assert!(v.is_finite() && v >= 0.0, "{key} = {v}");
    }
    assert_eq!(c["tif_file"].as_str(), Some("tif.csv"), "{c}");
    let rel = |key: &str| (num(&c, key) - num(truth, key)).abs() / num(truth, key);
    assert!(rel("rate_factor") < RATE_TOL, "rate: {c}");
    assert!(rel("width_factor") < WIDTH_TOL, "width: {c}");
    for key in ["offset_x_mm", "offset_y_mm"] {
        let e = (num(&c, key) - num(truth, key)).abs();
        assert!(e < OFFSET_TOL_MM, "{key} off by {e} mm: {c}");
    }
    // Both maps carry the interferometer's noise: the fit's residual cannot fall below it, and
    // the noise estimated per map is the shop's.
    let noise = num(&c, "noise_rms_nm");
    assert!(
        (noise - NOISE_RMS_NM).abs() < 0.3 * NOISE_RMS_NM,
        "noise {noise} nm against {NOISE_RMS_NM}"
    );
    assert!(num(&c, "fit_rms_nm") >= NOISE_RMS_NM, "{c}");

    // tif.csv reads as a TIF: the Gaussian with the calibrated figures applied.
    let tif = run.calibration.join("tif.csv");
    let (volume, centroid, radius) = tif_moments(&tif);
    let (g_volume, g_radius) = gaussian_moments();
    let volume_ratio = volume / g_volume;
    assert!(
        (volume_ratio / num(&c, "rate_factor") - 1.0).abs() < TIF_VOLUME_TOL,
        "tif.csv volume {volume} against {} x {g_volume}",
        num(&c, "rate_factor")
    );
    assert!(
        (radius / g_radius / num(&c, "width_factor") - 1.0).abs() < TIF_RADIUS_TOL,
        "tif.csv radius {radius} mm against {} x {g_radius}",
        num(&c, "width_factor")
    );
    assert!(
        (centroid.0 - num(&c, "offset_x_mm")).abs() < TIF_CENTROID_TOL_MM
            && (centroid.1 - num(&c, "offset_y_mm")).abs() < TIF_CENTROID_TOL_MM,
        "tif.csv centroid {centroid:?}: {c}"
    );
    let removal = csv_columns(
        &run.calibration.join("removal.csv"),
        &[
            "measured_removal_nm",
            "simulated_removal_nm",
            "difference_nm",
        ],
    );
    assert_eq!(removal[0].len(), c["points"].as_u64().unwrap() as usize);

    // The next plan with the calibrated tool: what the interferometer is expected to read.
    let next = run.root.join("next");
    ok(&preston_cmd()
        .args(["solve", "--quiet", "--map", s(&run.after)])
        .args(["--tif", s(&tif)])
        .args([
            "--calibration",
            s(&run.calibration.join("calibration.json")),
        ])
        .args(PLAN_ARGS)
        .args(["--out", s(&next)])
        .output()
        .unwrap());
    let r = report(&next);
    let expected = num(&r, "expected_rms_nm");
    let range = r["expected_rms_range_nm"].as_array().expect("a range");
    let (lo, hi) = (range[0].as_f64().unwrap(), range[1].as_f64().unwrap());
    assert!(
        lo <= expected && expected <= hi,
        "expected {expected} nm outside its range [{lo}, {hi}]"
    );
    // The reading carries the measurement's noise, piston and tilt dropped: it cannot be below
    // what the noise alone leaves.
    assert!(lo > 0.0 && expected >= 0.9 * noise, "{r}");
    assert!(num(&r, "expected_pv_nm") > expected, "{r}");
    assert_eq!(
        r["run_pays"].as_bool(),
        Some(expected < num(&r, "rms_before_nm")),
        "{r}"
    );

    // The shop runs the next plan with the same tool and reads the part: the reading is what the
    // plan expected. The plan corrects the map to below its noise, so it follows part of the
    // noise and leaves that on the part; the reading is neither the noise alone nor the noise
    // counted twice.
    let program2 = run.root.join("prog2.nc");
    write_program(&next.join("dwell.csv"), &program2);
    let shop2 = run.root.join("shop2");
    run_in_shop(
        &run.root.join("shop").join("surface_after.csv"),
        &program2,
        5,
        &shop2,
    );
    let read = num(&read_json(&shop2.join("shop.json")), "measured_rms_nm");
    assert!(
        (read - expected).abs() <= EXPECTED_READING_TOL * read,
        "the shop read {read} nm, the plan expected {expected} nm"
    );

    // The TIF given is the calibrated one: no warning that it is not. A copy with one rate
    // changed by more than the file's printed precision is not, and is warned about.
    let not_calibrated = |r: &serde_json::Value| {
        r["warnings"]
            .as_array()
            .expect("warnings")
            .iter()
            .any(|w| w.as_str().unwrap_or("").contains("not the calibrated one"))
    };
    assert!(!not_calibrated(&r), "{}", r["warnings"]);
    let text = std::fs::read_to_string(&tif).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    let middle = lines.len() / 2;
    let mut fields: Vec<f64> = lines[middle]
        .split(',')
        .map(|v| v.parse().unwrap())
        .collect();
    fields[2] += 1e-3;
    lines[middle] = format!("{},{},{:.9}", fields[0], fields[1], fields[2]);
    let other_tif = write(&run.root, "other_tif.csv", &(lines.join("\n") + "\n"));
    let other = run.root.join("other");
    ok(&preston_cmd()
        .args(["solve", "--quiet", "--map", s(&run.after)])
        .args(["--tif", s(&other_tif)])
        .args([
            "--calibration",
            s(&run.calibration.join("calibration.json")),
        ])
        .args(PLAN_ARGS)
        .args(["--out", s(&other)])
        .output()
        .unwrap());
    assert!(
        not_calibrated(&report(&other)),
        "{}",
        report(&other)["warnings"]
    );

    // iterate plans one run on the real part with the calibration: its TIF, and its rate's
    // uncertainty (with the run-to-run wander) behind the prediction.
    let it = run.root.join("iterate");
    let o = preston_cmd()
        .args(["iterate", "--map", s(&run.after)])
        .args([
            "--calibration",
            s(&run.calibration.join("calibration.json")),
        ])
        .args(["--out", s(&it)])
        .output()
        .unwrap();
    ok(&o);
    let said = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(said.contains("calibrated tool: rate"), "{said}");
    assert!(!said.contains("not the calibrated one"), "{said}");
    // The first row is the run planned (the second, the prediction, leaves its plan's columns
    // empty).
    let text = std::fs::read_to_string(it.join("convergence.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let first: Vec<&str> = lines.next().unwrap().split(',').collect();
    let field = |name: &str| -> f64 {
        let k = header.iter().position(|h| *h == name).unwrap();
        first[k].parse().unwrap()
    };
    let rate_sigma =
        (num(&c, "rate_factor_sigma") / num(&c, "rate_factor")).hypot(RUN_TO_RUN_RATE_SIGMA);
    assert!(
        (field("rate_factor_sigma") - rate_sigma).abs() < 1e-12,
        "rate sigma {} against the calibration's {rate_sigma}",
        field("rate_factor_sigma")
    );
    // The prediction carries the map's noise (outside the band): not below it, and a gain.
    let (measured, predicted) = (field("rms_nm"), field("predicted_rms_nm"));
    assert!(
        predicted >= 0.9 * noise && predicted < measured,
        "predicted {predicted} nm, measured {measured} nm"
    );
    // The calibration is for a real part's map: refused without one.
    let o = preston_cmd()
        .args([
            "iterate",
            "--calibration",
            s(&run.calibration.join("calibration.json")),
        ])
        .args(["--out", s(&run.root.join("iterate_virtual"))])
        .output()
        .unwrap();
    assert_eq!(
        o.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );

    // Bad input: an after map with no point over the before map.
    let far = write_map(&run.root, "far.csv", 100.0);
    let out = run.root.join("bad_calibration");
    let o = preston_cmd()
        .args(["calibrate", "--before", s(&run.before)])
        .args(["--after", s(&far), "--program", s(&run.program)])
        .args(gaussian_args())
        .args(["--a-max-mm-per-s2", "1000", "--out", s(&out)])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("far.csv"), "{stderr}");
    assert!(!out.exists(), "outputs written despite the error");

    // Bad input: a calibration whose standard deviation is negative.
    let mut bad = c.clone();
    bad["rate_factor_sigma"] = serde_json::json!(-0.01);
    let bad_file = run.calibration.join("negative_sigma.json");
    std::fs::write(&bad_file, serde_json::to_string(&bad).unwrap()).unwrap();
    let mut args: Vec<String> = vec![
        "--map".into(),
        s(&run.after).into(),
        "--tif".into(),
        s(&tif).into(),
        "--calibration".into(),
        s(&bad_file).into(),
    ];
    args.extend(PLAN_ARGS.iter().map(|a| a.to_string()));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    expect_failure(&args, &["negative_sigma.json", "rate_factor_sigma"]);
}
