//! The sample job in a virtual shop whose tool is not the spot test (the tool of
//! `scripts/virtual-shop.sh`: rate 1.08, width 1.05, offset (0.15, -0.12) mm, a linear skew of
//! 0.1 at 30 degrees, a drift of 3% per run; interferometer noise 0.3 nm, piston and tilt
//! dropped): plan, program, run, measure, calibrate, plan the next run with the calibration, run
//! and measure it.
//!
//! Run 1 removes most of the 118 x 8 mm map's structure, so a shift of the after map changes the
//! measured removal nearly as an offset of the tool does: the calibration keeps no shift the data
//! do not demand (the shop made none) and finds the tool's offset. The second run then measures
//! at the floor the tool's uncertainty and the noise allow, as its plan expected.

mod common;
use common::*;
use std::path::{Path, PathBuf};

/// The shop's true tool at run 1 (the script's), its rate one per cent lower at run 2.
const TRUE_RATE: [f64; 2] = [1.08, 1.07];
const TOOL_ARGS: [&str; 10] = [
    "--tool-width-factor",
    "1.05",
    "--tool-offset-mm=0.15,-0.12",
    "--tool-skew",
    "0.1",
    "--tool-skew-angle-deg",
    "30",
    "--tool-drift-per-run",
    "0.03",
    "--a-max-mm-per-s2=1000",
];

/// The rate factor is recovered within this (relative).
const RATE_TOL: f64 = 0.005;
/// The width factor within this (relative).
const WIDTH_TOL: f64 = 0.01;
/// The centroid offset within this, mm.
const OFFSET_TOL_MM: f64 = 0.02;
/// The truth lies within this many standard deviations.
const SIGMAS: f64 = 3.0;
/// Run 2, planned with run 1's calibration, measures at most this, nm RMS.
const RUN2_MEASURED_MAX_NM: f64 = 1.5;
/// The expected reading is within this fraction of the measured RMS.
const EXPECTED_REL_TOL: f64 = 0.3;
/// Run 2's dwell is at most this fraction of run 1's.
const RUN2_DWELL_FRACTION_MAX: f64 = 0.5;

fn shop(dir: &Path, surface: &Path, program: Option<&Path>, rate: f64, seed: u32) -> PathBuf {
    let out = dir.to_path_buf();
    let mut cmd = preston_cmd();
    cmd.args(["shop", "--quiet", "--surface", s(surface)])
        .args(["--tif", &data_arg("tif_fluid_jet_10mm.csv")])
        .args(["--seed", &seed.to_string(), "--out", s(&out)]);
    if let Some(p) = program {
        cmd.args(["--program", s(p)])
            .args(["--tool-rate-factor", &rate.to_string()])
            .args(TOOL_ARGS);
    }
    ok(&cmd.output().unwrap());
    out
}

/// Plans a run on `measured` (with `calibration`), writes its program and returns its folder.
fn plan(dir: &Path, measured: &Path, calibration: Option<&Path>) -> PathBuf {
    let mut cmd = preston_cmd();
    cmd.args(["solve", "--quiet", "--job", &data_arg("job.toml")])
        .args(["--map", s(measured), "--out", s(dir)]);
    if let Some(c) = calibration {
        cmd.args(["--calibration", s(c)]);
    }
    ok(&cmd.output().unwrap());
    ok(&preston_cmd()
        .args(["nc", "--quiet", "--job", &data_arg("job.toml")])
        .args(["--dwell", s(&dir.join("dwell.csv"))])
        .args(["--out", s(&dir.join("prog.nc"))])
        .output()
        .unwrap());
    dir.to_path_buf()
}

fn calibrate(dir: &Path, before: &Path, after: &Path, program: &Path) -> String {
    ok(&preston_cmd()
        .args(["calibrate", "--before", s(before), "--after", s(after)])
        .args(["--program", s(program)])
        .args(["--tif", &data_arg("tif_fluid_jet_10mm.csv")])
        .args(["--a-max-mm-per-s2", "1000", "--out", s(dir)])
        .output()
        .unwrap())
}

fn num(v: &serde_json::Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} missing in {v}"))
}

/// `key` within `tol` of the truth, and the truth within 3 standard deviations.
fn check(c: &serde_json::Value, truth: &serde_json::Value, key: &str, tol: f64) {
    let (value, sigma, t) = (
        num(c, key),
        num(c, &format!("{key}_sigma")),
        num(truth, key),
    );
    assert!(
        (value - t).abs() <= tol,
        "{key}: {value} against the true {t} (tolerance {tol})"
    );
    assert!(
        (value - t).abs() <= SIGMAS * sigma,
        "{key}: {value} +- {sigma} leaves the true {t} beyond {SIGMAS} sigma"
    );
}

fn expected_agrees(report: &serde_json::Value, measured_nm: f64) {
    let expected = num(report, "expected_rms_nm");
    assert!(
        (expected - measured_nm).abs() <= EXPECTED_REL_TOL * measured_nm,
        "expected {expected} nm against the measured {measured_nm} nm"
    );
    let range = &report["expected_rms_range_nm"];
    let (lo, hi) = (range[0].as_f64().unwrap(), range[1].as_f64().unwrap());
    assert!(
        lo <= measured_nm && measured_nm <= hi,
        "measured {measured_nm} nm outside the expected range {lo} .. {hi}"
    );
}

#[test]
fn the_sample_in_a_shop_learns_its_tool_and_the_next_run_reads_as_expected() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let v0 = shop(
        &root.join("v0"),
        &data("mirror_error_118x8mm.csv"),
        None,
        1.0,
        100,
    );
    let measured0 = v0.join("measured.csv");

    // Run 1, planned with the spot test: its measured RMS inside the expected range.
    let run1 = plan(&root.join("run1"), &measured0, None);
    let shop1 = shop(
        &root.join("shop1"),
        &v0.join("surface_after.csv"),
        Some(&run1.join("prog.nc")),
        TRUE_RATE[0],
        101,
    );
    let r1 = report(&run1);
    let s1 = read_json(&shop1.join("shop.json"));
    let measured1_nm = num(&s1, "measured_rms_nm");
    let range = &r1["expected_rms_range_nm"];
    assert!(
        range[0].as_f64().unwrap() <= measured1_nm && measured1_nm <= range[1].as_f64().unwrap(),
        "run 1 measured {measured1_nm} nm outside {range}"
    );

    // Calibrated from run 1: the tool's figures (its footprint's moments, as the shop states
    // them) within the shop's tolerances and 3 sigma.
    let after1 = shop1.join("measured.csv");
    let program1 = run1.join("prog.nc");
    let cal = root.join("cal1");
    let printed = calibrate(&cal, &measured0, &after1, &program1);
    let c = read_json(&cal.join("calibration.json"));
    let truth = &s1["tool_figures"];
    check(
        &c,
        truth,
        "rate_factor",
        RATE_TOL * num(truth, "rate_factor"),
    );
    check(&c, truth, "width_factor", WIDTH_TOL);
    check(&c, truth, "offset_x_mm", OFFSET_TOL_MM);
    check(&c, truth, "offset_y_mm", OFFSET_TOL_MM);

    // The shop never moved the part between its measurements: a shift of the maps would change
    // the fit by less than the 5% that keeps one, and the calibration says so.
    let shift = &c["map_shift"];
    assert_eq!(shift["kept"].as_bool(), Some(false), "{shift}");
    let (with, without) = (
        num(shift, "fit_rms_with_nm"),
        num(shift, "fit_rms_without_nm"),
    );
    assert!(with > 0.95 * without, "{shift}");
    assert!(printed.contains("no shift between the maps"), "{printed}");

    // Run 2 with the calibration: at most 1.5 nm, as expected, with at most half run 1's dwell.
    let run2 = plan(
        &root.join("run2"),
        &after1,
        Some(&cal.join("calibration.json")),
    );
    let shop2 = shop(
        &root.join("shop2"),
        &shop1.join("surface_after.csv"),
        Some(&run2.join("prog.nc")),
        TRUE_RATE[1],
        102,
    );
    let r2 = report(&run2);
    // The job's TIF is the spot test the calibration was made from: the calibrated TIF plans.
    let warnings = r2["warnings"].to_string();
    assert!(!warnings.contains("not the calibrated one"), "{warnings}");
    let measured2_nm = num(&read_json(&shop2.join("shop.json")), "measured_rms_nm");
    assert!(
        measured2_nm <= RUN2_MEASURED_MAX_NM,
        "run 2 measured {measured2_nm} nm"
    );
    expected_agrees(&r2, measured2_nm);
    let dwell_ratio = num(&r2, "total_dwell_s") / num(&r1, "total_dwell_s");
    assert!(
        dwell_ratio <= RUN2_DWELL_FRACTION_MAX,
        "run 2's dwell is {dwell_ratio} of run 1's"
    );
}
