//! `preston simulate` and `preston iterate` end to end: discrete simulation reproduces
//! the solver's residual, continuous simulation converges as the sampling is refined, the virtual
//! loop converges and writes its table and plots, a real part's map plans one run.

mod common;

use common::{ok, png_size, preston, report, s};
use std::path::Path;

/// A smooth 26 x 26 map over 25 x 25 mm.
fn write_map(path: &Path) {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..26 {
        for ix in 0..26 {
            let (x, y) = (ix as f64, iy as f64);
            t.push_str(&format!(
                "{x},{y},{}\n",
                40.0 + 25.0 * (0.25 * x).sin() * (0.2 * y).cos()
            ));
        }
    }
    std::fs::write(path, t).unwrap();
}

const GAUSSIAN: [&str; 4] = ["--gaussian-sigma-mm", "2", "--gaussian-peak-nm-per-s", "10"];

#[test]
fn simulate_reproduces_the_solver_and_converges_in_continuous_mode() {
    let d = tempfile::tempdir().unwrap();
    let map = d.path().join("map.csv");
    write_map(&map);
    let solved = d.path().join("solved");
    // rho > 0 keeps the free piston (and the dwell) small, as in practice.
    let mut args = vec![
        "solve",
        "--map",
        s(&map),
        "--raster-pitch-mm",
        "1.5",
        "--v-max",
        "2000",
        "--rho",
        "0.01",
        // The discrete simulation below models the TIF at the dwell points.
        "--influence",
        "point",
    ];
    args.extend(GAUSSIAN);
    args.extend(["--out", s(&solved)]);
    ok(&preston(&args));
    let dwell = solved.join("dwell.csv");
    let sim = |extra: &[&str], out: &Path| {
        let mut a = vec!["simulate", "--map", s(&map), "--dwell", s(&dwell)];
        a.extend(GAUSSIAN);
        a.extend_from_slice(extra);
        a.extend(["--out", s(out)]);
        ok(&preston(&a));
        report(out)
    };
    // Discrete: the point model's solver's own prediction, to the last byte.
    let discrete = d.path().join("discrete");
    let r = sim(&["--plots", "--motion", "discrete"], &discrete);
    assert_eq!(
        std::fs::read(solved.join("residual.csv")).unwrap(),
        std::fs::read(discrete.join("residual.csv")).unwrap()
    );
    let solve_report = report(&solved);
    // The same schema, less `raster` (the solve generated its raster, the simulation reads
    // the dwell points it is given), the expected reading (what a plan predicts the next
    // measurement to read, which `solve` states for its plan) and what the plan corrects.
    let solve_only = |k: &str| {
        k == "raster"
            || k == "run_pays"
            || k.starts_with("expected")
            || k == "plan_scope"
            || k == "plan_rho_nm2_per_s"
            || k.starts_with("map_plan_")
    };
    let keys = |v: &serde_json::Value| {
        let mut k: Vec<String> = v
            .as_object()
            .unwrap()
            .keys()
            .filter(|k| !solve_only(k))
            .cloned()
            .collect();
        k.sort();
        k
    };
    assert_eq!(
        keys(&r),
        keys(&solve_report),
        "report keys differ from preston solve"
    );
    assert_eq!(r["solver"], "simulate");
    assert_eq!(r["rms_after_nm"], solve_report["rms_after_nm"]);
    for f in ["error_before.png", "removal.png", "residual.png"] {
        assert_eq!(
            png_size(&discrete.join(f)).0,
            preston_io::plots::MAP_WIDTH_PX
        );
    }
    // Continuous: the residual settles as the samples per dwell point double.
    let rms: Vec<f64> = [1, 2, 4, 8, 16]
        .iter()
        .map(|k| {
            let out = d.path().join(format!("c{k}"));
            sim(
                &[
                    "--motion",
                    "continuous",
                    "--samples-per-point",
                    &k.to_string(),
                ],
                &out,
            )["rms_after_nm"]
                .as_f64()
                .unwrap()
        })
        .collect();
    let steps: Vec<f64> = rms.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    assert!(
        steps[3] < steps[1] && steps[2] < steps[0],
        "continuous RMS {rms:?} does not settle"
    );
    assert!(steps[3] < 0.02 * rms[4] + 1e-9, "{rms:?}");
}

/// Measured RMS below which the loop with 0.3 nm of measurement noise, a 3 % TIF rate error and
/// 20 um of positioning noise is at its floor and a run need not improve on the last, nm.
const DISTURBANCE_FLOOR_NM: f64 = 1.0;

#[test]
fn virtual_loop_converges_and_writes_table_and_plots() {
    let d = tempfile::tempdir().unwrap();
    let surface = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/design_freeform.json");
    let out = d.path().join("loop");
    let mut args = vec![
        "iterate",
        "--surface",
        s(&surface),
        "--aperture-x-mm=-12,12",
        "--aperture-y-mm=-10,10",
        "--grid",
        "17,15",
        "--pitch-mm",
        "1.5",
        "--iterations",
        "3",
        "--form-error-rms-nm",
        "50",
        "--rotation-arcsec=20,-15,30",
        "--translation-um=5,-8,3",
        "--noise-nm",
        "0.3",
        "--tif-rate-error",
        "0.03",
        "--positioning-noise-mm",
        "0.02",
        "--plots",
    ];
    args.extend(GAUSSIAN);
    args.extend(["--out", s(&out)]);
    ok(&preston(&args));
    let table = std::fs::read_to_string(out.join("convergence.csv")).unwrap();
    let mut lines = table.lines();
    assert!(lines
        .next()
        .unwrap()
        .starts_with("iteration,pv_nm,rms_nm,max_abs_nm,mean_abs_nm,time_s"));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').take(6).map(|c| c.parse().unwrap()).collect())
        .collect();
    // Three runs at most; the loop stops earlier once a run cannot gain 0.05 nm.
    assert!((2..=4).contains(&rows.len()), "{rows:?}");
    let last = rows.len() - 1;
    // The registered form error starts near the generated 50 nm RMS (the installation error of
    // tens of micrometres is taken out) and decreases run after run.
    assert!((rows[0][2] - 50.0).abs() < 25.0, "{rows:?}");
    for w in rows.windows(2) {
        assert!(
            w[1][2] < w[0][2] || w[0][2] < DISTURBANCE_FLOOR_NM,
            "RMS does not decrease: {rows:?}"
        );
    }
    assert!(rows[1][2] < 0.2 * rows[0][2], "{rows:?}");
    assert!(rows[last][2] < DISTURBANCE_FLOOR_NM, "{rows:?}");
    assert!(rows[0][5] > 0.0 && rows[last][5] == 0.0);
    assert_eq!(
        png_size(&out.join("convergence.png")),
        preston_io::plots::PLOT_SIZE_PX
    );
    // Maps and the path: as wide as the layout's canvas, as tall as the part's aspect gives.
    for f in [
        "error_before.png",
        "removal.png",
        "residual.png",
        "dwell.png",
        "feed.png",
        "path.png",
        "final_error.png",
    ] {
        let (w, h) = png_size(&out.join(f));
        assert_eq!(w, preston_io::plots::MAP_WIDTH_PX, "{f}");
        assert!(h > 100 && h < 1000, "{f}: height {h}");
    }
}

#[test]
fn a_measured_map_plans_one_run_and_bad_input_writes_nothing() {
    let d = tempfile::tempdir().unwrap();
    let map = d.path().join("map.csv");
    write_map(&map);
    let out = d.path().join("real");
    let mut args = vec![
        "iterate",
        "--map",
        s(&map),
        "--pitch-mm",
        "1.5",
        "--iteration",
        "1",
    ];
    args.extend(GAUSSIAN);
    args.extend(["--out", s(&out)]);
    ok(&preston(&args));
    let table = std::fs::read_to_string(out.join("convergence.csv")).unwrap();
    assert_eq!(table.lines().count(), 3);
    // Iteration 1 runs along y: the first two dwell points share x.
    let dwell = std::fs::read_to_string(out.join("dwell.csv")).unwrap();
    let first: Vec<Vec<f64>> = dwell
        .lines()
        .skip(1)
        .take(2)
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert_eq!(first[0][0], first[1][0]);
    // No TIF: exit 2, no output directory.
    let bad = d.path().join("bad");
    let o = preston(&["iterate", "--map", s(&map), "--out", s(&bad)]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("no TIF"));
    assert!(!bad.exists());
}

/// The loop on the shipped freeform with no installation error and no disturbances: every
/// measured RMS is at most twice the previous run's prediction plus 0.01 nm (registration does
/// not slide, and the uniform layer left by the solve is not mistaken for a rigid piston).
#[test]
fn undisturbed_freeform_loop_meets_its_predictions() {
    let d = tempfile::tempdir().unwrap();
    let surface = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/design_freeform.json");
    let out = d.path().join("loop");
    let mut args = vec![
        "iterate",
        "--surface",
        s(&surface),
        "--aperture-x-mm=-25,25",
        "--aperture-y-mm=-25,25",
        "--grid",
        "21,21",
        "--pitch-mm",
        "2",
        "--iterations",
        "2",
    ];
    args.extend(GAUSSIAN);
    args.extend(["--out", s(&out)]);
    ok(&preston(&args));
    let table = std::fs::read_to_string(out.join("convergence.csv")).unwrap();
    let rows: Vec<Vec<f64>> = table
        .lines()
        .skip(1)
        .map(|l| {
            l.split(',')
                .map(|c| c.parse().unwrap_or(f64::NAN))
                .collect()
        })
        .collect();
    assert!(rows.len() >= 2, "{rows:?}");
    for w in rows.windows(2) {
        let predicted = w[0][6];
        if predicted.is_nan() {
            continue;
        }
        assert!(
            w[1][2] <= 2.0 * predicted + 0.01,
            "measured {} after a predicted {predicted}: {rows:?}",
            w[1][2]
        );
    }
    assert!(rows[rows.len() - 1][2] < 0.1, "{rows:?}");
}

/// The loop under ordinary disturbances (5 % rate error per run, 20 um positioning noise, 1 nm
/// of measurement noise, an installation error): it plans only the correctable band, learns the
/// rate from each run, spends less as the error falls and stops at the floor of the measurement
/// noise. From run 2 on the measured RMS never rises by more than 0.05 nm, it ends within 1.3x
/// of the noise floor, no later run dwells longer than the first, the last prediction is within
/// a factor 1.5 of what is then measured, and the rate learned from run 0 is the rate it had.
#[test]
fn disturbed_loop_converges_to_the_noise_floor_and_learns_the_rate() {
    let d = tempfile::tempdir().unwrap();
    let surface = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/design_freeform.json");
    let noise_nm = 1.0;
    for seed in ["7", "3"] {
        let out = d.path().join(format!("loop{seed}"));
        let o = preston(&[
            "iterate",
            "--surface",
            s(&surface),
            "--gaussian-sigma-mm",
            "2.5",
            "--gaussian-peak-nm-per-s",
            "10",
            "--tif-rate-error",
            "0.05",
            "--positioning-noise-mm",
            "0.02",
            "--noise-nm",
            "1",
            "--rotation-arcsec=20,-10,5",
            "--translation-um=3,-2,5",
            "--iterations",
            "5",
            "--seed",
            seed,
            "--form-error-seed",
            seed,
            "--out",
            s(&out),
        ]);
        ok(&o);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains("floor:"), "{err}");
        let table = std::fs::read_to_string(out.join("convergence.csv")).unwrap();
        let mut lines = table.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
        let rows: Vec<Vec<f64>> = lines
            .map(|l| {
                l.split(',')
                    .map(|c| c.parse().unwrap_or(f64::NAN))
                    .collect()
            })
            .collect();
        let (rms, time, pred) = (col("rms_nm"), col("time_s"), col("predicted_rms_nm"));
        let last = rows.len() - 1;
        for k in 2..rows.len() {
            assert!(rows[k][rms] <= rows[k - 1][rms] + 0.05, "{rows:?}");
        }
        assert!(rows[last][rms] <= 1.3 * noise_nm, "{rows:?}");
        for r in &rows[1..] {
            assert!(r[time] <= rows[0][time], "{rows:?}");
        }
        let ran: Vec<usize> = (0..last).filter(|&k| rows[k][time] > 0.0).collect();
        let k = *ran.last().unwrap();
        let ratio = rows[k + 1][rms] / rows[k][pred];
        assert!((1.0 / 1.5..=1.5).contains(&ratio), "{rows:?}");
        // The factor the second run was planned with is the first run's actual rate.
        let actual = 1.0 + rows[0][col("tif_rate_error")];
        let learned = rows[1][col("rate_factor_estimate")];
        assert!((learned - actual).abs() < 0.005, "{learned} vs {actual}");
        assert!(
            rows[last][col("uncorrectable_rms_nm")] >= 0.9 * noise_nm,
            "{rows:?}"
        );
    }
}
