//! `preston solve` plans a run that pays: where the plan of the whole map is not expected to
//! improve the part by more than its risk (the tool known only to a spot test's uncertainty),
//! the correctable band is planned alone; where no plan pays, the run says so with the floor's
//! cause, and the plan is still written.

mod common;

use common::{preston_cmd, report, run_ok, s, write};
use std::f64::consts::PI;
use std::fmt::Write as _;

/// A 20 x 20 mm map at 0.5 mm: `smooth_nm` of low-order form, `ripple_nm` of a 4 x 5.2 mm
/// ripple (beyond what a sigma 2 mm tool reaches: its transfer there is below 1%) and
/// deterministic pseudo-noise of `noise_nm` RMS.
fn map_text(smooth_nm: f64, ripple_nm: f64, noise_nm: f64) -> String {
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    let mut rng = preston_solver::rng::SplitMix64::new(11);
    for j in 0..41 {
        for i in 0..41 {
            let (x, y) = (i as f64 * 0.5 - 10.0, j as f64 * 0.5 - 10.0);
            let (u, v) = (x / 10.0, y / 10.0);
            let z = smooth_nm * (0.8 * (2.0 * u * u - 1.0) + 0.5 * u * v + 0.6 * v * v)
                + ripple_nm * (2.0 * PI * x / 4.0).sin() * (2.0 * PI * y / 5.2).cos()
                + noise_nm * rng.normal();
            writeln!(text, "{x},{y},{z}").unwrap();
        }
    }
    text
}

fn solve(dir: &std::path::Path, map: &std::path::Path) -> std::process::Output {
    run_ok(preston_cmd().args([
        "solve",
        "--map",
        s(map),
        "--gaussian-sigma-mm",
        "2",
        "--gaussian-peak-nm-per-s",
        "10",
        "--raster-pitch-mm",
        "0.5",
        "--v-max",
        "3000",
        "--v-min",
        "1",
        "--out",
        s(&dir.join("out")),
    ]))
}

fn num(r: &serde_json::Value, key: &str) -> f64 {
    r[key].as_f64().unwrap_or_else(|| panic!("{key} in {r:#}"))
}

/// A ripple the tool cannot size or place well enough: the whole map's plan chases it and its
/// reading's 95th percentile is not below the part's measurement (the plan is a band plan only
/// then); the band plan leaves the ripple (and the noise) alone, corrects the form, and is
/// expected to read below the whole map's plan and, at its 95th percentile, below the
/// measurement.
#[test]
fn the_band_is_planned_alone_where_the_whole_map_would_not_pay() {
    let dir = tempfile::tempdir().unwrap();
    let map = write(dir.path(), "map.csv", &map_text(2.0, 2.0, 0.3));
    solve(dir.path(), &map);
    let r = report(&dir.path().join("out"));
    assert_eq!(r["plan_scope"]["kind"], "band", "{:#}", r["plan_scope"]);
    let measured = num(&r["expected"], "measured_rms_nm");
    let whole = num(&r, "map_plan_expected_rms_nm");
    let expected = num(&r, "expected_rms_nm");
    assert!(expected < whole, "band {expected} against whole {whole}");
    assert_eq!(r["run_pays"], true);
    let high = r["expected_rms_range_nm"][1].as_f64().unwrap();
    assert!(high < measured, "95th percentile {high} against {measured}");
    // The band plan leaves out the ripple and the noise: the nominal tool's residual on the
    // measured map is at least what the band leaves out (less what the form's fit shares).
    let left_out = num(&r["plan_scope"], "left_out_rms_nm");
    let ripple_rms = 2.0 / 2.0;
    assert!(
        left_out > 0.9 * (ripple_rms * ripple_rms + 0.09f64).sqrt(),
        "{left_out}"
    );
    assert!(num(&r, "rms_after_nm") >= 0.9 * left_out, "{r:#}");
}

/// Noise alone: nothing the tool can correct, so no run pays; `solve` says so with the floor's
/// cause and still writes the plan.
#[test]
fn a_map_of_noise_pays_no_run_and_says_why() {
    let dir = tempfile::tempdir().unwrap();
    let map = write(dir.path(), "map.csv", &map_text(0.0, 0.0, 0.5));
    let out = solve(dir.path(), &map);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no run is expected to improve the part"),
        "{stderr}"
    );
    let r = report(&dir.path().join("out"));
    assert_eq!(r["run_pays"], false, "{r:#}");
    assert!(r["expected_floor_cause"].is_string());
    // Two measurements' noise at least: the map's own and the next one's.
    let measured = num(&r["expected"], "measured_rms_nm");
    assert!(num(&r, "expected_rms_nm") > measured, "{r:#}");
    assert!(dir.path().join("out/dwell.csv").is_file());
}
