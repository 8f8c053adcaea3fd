//! The sample part job (`data/job_part.toml`) as a shop checks it: solved, written as a program by `preston nc` and run
//! by `preston simulate --program` at the job's acceleration limit with look-ahead. The part it
//! gives is pinned (`docs/part_quality.md`).

mod common;
use common::*;

/// Largest executed residual RMS of the job, nm.
const EXECUTED_RMS_MAX_NM: f64 = 0.5;
/// Largest executed residual PV, nm.
const EXECUTED_PV_MAX_NM: f64 = 6.0;
/// Largest total dwell, s.
const TOTAL_DWELL_MAX_S: f64 = 50_000.0;
/// Largest dwell on one point, s.
const POINT_DWELL_MAX_S: f64 = 120.0;
/// Largest relative difference between the report's planned residual and the program's run.
const PLANNED_VS_EXECUTED: f64 = 0.03;

#[test]
fn the_sample_part_job_delivers_its_part_as_executed() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("sample");
    let job = data_arg("job_part.toml");
    ok(&preston(&["solve", "--job", &job, "--out", s(&out)]));
    let r = report(&out);
    assert_eq!(r["influence"], "swept");
    let planned_rms = r["rms_after_nm"].as_f64().unwrap();
    // The correction passes against the executed program are what bring the part down: the
    // model's own residual is far above the executed one.
    assert!(r["executed"]["correction_passes"].as_u64().unwrap() >= 1);
    assert!(r["model"]["rms_nm"].as_f64().unwrap() > 2.0 * planned_rms);
    let total = r["total_dwell_s"].as_f64().unwrap();
    assert!(total <= TOTAL_DWELL_MAX_S, "total dwell {total} s");
    let dwell = csv_columns(&out.join("dwell.csv"), &["dwell_s"]);
    let most = dwell[0].iter().fold(0.0f64, |a, &b| a.max(b));
    assert!(most <= POINT_DWELL_MAX_S, "{most} s on one point");

    // The program as written, run at the job's limit by the simulator.
    let prog = d.path().join("prog.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        s(&out.join("dwell.csv")),
        "--job",
        &job,
        "--out",
        s(&prog),
    ]));
    let sim = d.path().join("sim");
    ok(&preston(&[
        "simulate",
        "--map",
        &data_arg("mirror_error_118x8mm.csv"),
        "--tif",
        &data_arg("tif_fluid_jet_10mm.csv"),
        "--program",
        s(&prog),
        "--a-max-mm-per-s2",
        "1000",
        "--out",
        s(&sim),
    ]));
    let e = report(&sim);
    let (rms, pv) = (
        e["rms_after_nm"].as_f64().unwrap(),
        e["pv_after_nm"].as_f64().unwrap(),
    );
    assert!(rms <= EXECUTED_RMS_MAX_NM, "executed RMS {rms} nm");
    assert!(pv <= EXECUTED_PV_MAX_NM, "executed PV {pv} nm");
    assert!(
        (planned_rms - rms).abs() <= PLANNED_VS_EXECUTED * rms,
        "planned {planned_rms} nm vs executed {rms} nm"
    );
}
