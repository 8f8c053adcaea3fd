//! `preston solve --robust`: one plan for the mean residual over the TIF-uncertainty scenarios,
//! reported against the nominal plan of the same job.

mod common;

use common::{data, expect_failure, preston_cmd, report, s, write};
use std::fmt::Write as _;

/// A 20 x 20 mm map at 0.5 mm with error at 4.5 to 7 mm periods, tens of nm.
fn map_text() -> String {
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for j in 0..41 {
        for i in 0..41 {
            let (x, y) = (i as f64 * 0.5, j as f64 * 0.5);
            let z = 40.0
                + 15.0 * (2.0 * std::f64::consts::PI * x / 7.0).sin()
                + 10.0 * (2.0 * std::f64::consts::PI * y / 4.5).cos()
                + 5.0 * (2.0 * std::f64::consts::PI * (x + y) / 5.0).sin();
            writeln!(text, "{x},{y},{z}").unwrap();
        }
    }
    text
}

fn rms_list(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn worst(v: &[f64]) -> f64 {
    v.iter().copied().fold(0.0, f64::max)
}

/// Without an acceleration limit the comparison is the plans' model (`planned`): the robust
/// plan's worst scenario and mean square over the scenarios are better than the nominal plan's,
/// its nominal no better (the nominal plan is the nominal optimum), the report's cost and saving are those differences, and the
/// robust plan's nominal RMS is `rms_after_nm`. The FFT and spreading operators' stacked
/// scenarios give the same plan.
#[test]
fn robust_plan_trades_nominal_for_the_worst_scenario() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text());
    let args = [
        "--map",
        s(&map),
        "--gaussian-sigma-mm",
        "1.5",
        "--gaussian-peak-nm-per-s",
        "20",
        "--gaussian-truncation-mm",
        "5",
        "--raster-pitch-mm",
        "1",
        "--v-max",
        "3000",
        "--v-min",
        "1",
        "--rho",
        "0.01",
        "--edge",
        "none",
        "--robust",
    ];
    let out = d.path().join("robust");
    let o = preston_cmd()
        .arg("solve")
        .args(args)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    let robust = &r["robust"];
    assert_eq!(robust["basis"], "planned", "{robust}");
    assert_eq!(robust["scenarios"][0], "nominal");
    let (rob, nom) = (
        rms_list(&robust["robust_plan_rms_nm"]),
        rms_list(&robust["nominal_plan_rms_nm"]),
    );
    assert_eq!((rob.len(), nom.len()), (7, 7));
    assert!(worst(&rob) < worst(&nom), "{rob:?} against {nom:?}");
    // What it minimises: the mean over the scenarios of the squared residual.
    let mean_sq = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64;
    assert!(mean_sq(&rob) < mean_sq(&nom), "{rob:?} against {nom:?}");
    assert_eq!(
        r["edge_points"], 0,
        "the scenario blocks are not edge points"
    );
    assert!(rob[0] >= nom[0] * (1.0 - 1e-3), "{rob:?} against {nom:?}");
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0);
    assert!(close(
        robust["nominal_cost_nm"].as_f64().unwrap(),
        rob[0] - nom[0]
    ));
    assert!(close(
        robust["worst_scenario_saving_nm"].as_f64().unwrap(),
        worst(&nom) - worst(&rob)
    ));
    assert!(close(r["rms_after_nm"].as_f64().unwrap(), rob[0]), "{r}");
    assert!(close(
        robust["nominal_plan_rms_after_nm"].as_f64().unwrap(),
        nom[0]
    ));
    assert_eq!(robust["weighting"], "mean");
    assert_eq!(rms_list(&robust["scenario_weights"]), vec![1.0; 7]);
    // The scenarios are one standard deviation of a spot test's uncertainty (no job figures).
    let warned = r["warnings"].to_string();
    assert!(
        warned.contains("TIF 5.0% wider and narrower, tool 0.200 mm off either way in x"),
        "{warned}"
    );

    // The scenarios' FFT operators, or their spreading operators (exact with the dwell points
    // on the map's lattice), stacked matrix-free: the same plan as the stacked matrices.
    for operator in ["fft", "fft-spread"] {
        let out_op = d.path().join(format!("robust_{operator}"));
        let o = preston_cmd()
            .arg("solve")
            .args(args)
            .args(["--operator", operator, "--out"])
            .arg(&out_op)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let rf = report(&out_op);
        assert_eq!(rf["operator"], operator, "{rf}");
        assert!(
            rf["warnings"].to_string().contains("matrix-free"),
            "{}",
            rf["warnings"]
        );
        let lattice = rms_list(&rf["robust"]["robust_plan_rms_nm"]);
        for (a, b) in rob.iter().zip(&lattice) {
            assert!(
                (a - b).abs() <= 1e-3 * a.max(1e-3),
                "{operator}: {rob:?} against {lattice:?}"
            );
        }
    }

    // Minimax weights: the worst scenario as planned no higher than the mean plan's (the rounds
    // keep the best; here the two width scenarios pull against each other and the mean plan is
    // close to the minimax one), the weights summing to the scenario count, the rounds
    // reported. Without --robust the weighting is refused.
    let out = d.path().join("minimax");
    let o = preston_cmd()
        .arg("solve")
        .args(args)
        .args(["--robust-weighting", "minimax", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    let minimax = &r["robust"];
    assert_eq!(minimax["weighting"], "minimax", "{minimax}");
    let mm = rms_list(&minimax["robust_plan_rms_nm"]);
    assert!(
        worst(&mm) <= worst(&rob) * (1.0 + 1e-9),
        "{mm:?} against {rob:?}"
    );
    let w = rms_list(&minimax["scenario_weights"]);
    assert!((w.iter().sum::<f64>() - 7.0).abs() < 1e-9, "{w:?}");
    assert!(close(r["rms_after_nm"].as_f64().unwrap(), mm[0]), "{r}");
    let warned = r["warnings"].to_string();
    assert!(warned.contains("robust minimax"), "{warned}");
    let mut no_robust: Vec<&str> = args.iter().copied().filter(|a| *a != "--robust").collect();
    no_robust.extend(["--robust-weighting", "minimax"]);
    expect_failure(&no_robust, &["robust_weighting"]);
}

/// The shipped job with its tool known to 3% in width and 0.05 mm in place (job `[tif]
/// width_sigma`, `offset_sigma_mm`: the sensitivity's sizes), written beside `dir`.
fn sample_job_known_to_3pct(dir: &std::path::Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(data("job.toml")).unwrap();
    let mut job = String::new();
    for line in text.lines() {
        match line.strip_prefix("file = \"") {
            Some(rest) => {
                let name = rest.trim_end_matches('"');
                job.push_str(&format!("file = {:?}\n", data(name).display().to_string()));
            }
            None => {
                job.push_str(line);
                job.push('\n');
            }
        }
        if line.trim() == "[tif]" {
            job.push_str("width_sigma = 0.03\noffset_sigma_mm = 0.05\n");
        }
    }
    let path = dir.join("job.toml");
    std::fs::write(&path, job).unwrap();
    path
}

/// The shipped job with `--robust`, its tool known to 3% in width and 0.05 mm in place: both
/// programs executed at the job's acceleration limit. The robust plan lowers what it minimises,
/// the mean square over the seven scenarios, pays for it with at most 0.5 nm nominal, and at
/// least halves the width scenarios. A tool off by `d` leaves `r + d dh/dx`, `h` the removal,
/// which any plan correcting the map shares: neither plan is more than 10% below the other in an
/// offset scenario. The nominal plan's executed residual is the one the sample job reports
/// without `--robust`; the scenarios' executed figures are the sensitivity's for the same tool
/// (an independent integration of the same executed motion).
#[test]
fn robust_sample_job_halves_the_width_scenarios_and_shares_the_offset_floor() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("robust");
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(sample_job_known_to_3pct(d.path()))
        .args(["--robust", "--quiet", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    let robust = &r["robust"];
    assert_eq!(robust["basis"], "executed", "{robust}");
    let (rob, nom) = (
        rms_list(&robust["robust_plan_rms_nm"]),
        rms_list(&robust["nominal_plan_rms_nm"]),
    );
    let mean_square = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64;
    assert!(
        mean_square(&rob) < mean_square(&nom),
        "{rob:?} against {nom:?}"
    );
    assert!(rob[0] <= 0.5, "{rob:?}");
    for s in [1, 2] {
        assert!(rob[s] <= 0.5 * nom[s], "{rob:?} against {nom:?}");
    }
    for s in 3..7 {
        assert!(
            rob[s] >= 0.9 * nom[s] && nom[s] >= 0.9 * rob[s],
            "{rob:?} against {nom:?}"
        );
    }
    assert_eq!(
        robust["nominal_plan_rms_after_nm"].as_f64().unwrap(),
        nom[0]
    );
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs());
    for (key, s) in [
        ("tif_wider_3pct", 1),
        ("tif_narrower_3pct", 2),
        ("offset_x_0p05mm", 3),
    ] {
        let sensitivity = r["sensitivity"][key]["rms_nm"].as_f64().unwrap();
        assert!(
            close(sensitivity, rob[s]),
            "{key}: {sensitivity} against {rob:?}"
        );
    }
    assert_eq!(robust["scenarios"][3], "offset_x_plus_1sigma");
}

/// The shipped job with minimax weights: the report's figures are the nominal scenario's own
/// (the error before is the map's, the plan's model residual is the executed one within 5%: the
/// plan is the part), the weights sum to the scenario count, and the worst executed scenario is
/// no worse than the nominal plan's (the rounds keep the plan with the smallest worst scenario;
/// here the worst is an x offset, which no plan can help).
#[test]
fn minimax_sample_job_reports_the_nominal_scenario_unweighted() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("minimax");
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(sample_job_known_to_3pct(d.path()))
        .args([
            "--robust",
            "--robust-weighting",
            "minimax",
            "--quiet",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    assert_eq!(r["operator"], "fft", "{}", r["warnings"]);
    let w = rms_list(&r["robust"]["scenario_weights"]);
    assert!((w.iter().sum::<f64>() - 7.0).abs() < 1e-9, "{w:?}");
    assert!(w.iter().all(|w| *w > 0.0), "{w:?}");
    let before = r["rms_before_nm"].as_f64().unwrap();
    assert!((before - 922.373).abs() < 1e-3, "{before}");
    let executed = r["executed"]["rms_after_nm"].as_f64().unwrap();
    let model = r["model"]["rms_nm"].as_f64().unwrap();
    assert!(
        (model - executed).abs() <= 0.05 * executed,
        "{model} vs {executed}"
    );
    let rob = rms_list(&r["robust"]["robust_plan_rms_nm"]);
    let nom = rms_list(&r["robust"]["nominal_plan_rms_nm"]);
    assert!(worst(&rob) <= 1.02 * worst(&nom), "{rob:?} against {nom:?}");
}
