//! Never a wrong answer with exit 0: what `preston` reports as held holds in the files it
//! writes, approximations say so, inputs that cannot be meant are refused or warned about, and a
//! closed pipe ends the printing, not the process.
//!
//! Every figure is recomputed here from the written files (`dwell.csv`, `residual.csv`) with an
//! independent implementation of the Gaussian TIF, the feed formula and the segment
//! acceleration, not read back from the library.

mod common;

use common::{csv_columns, preston_cmd, report, s, write};
use proptest::prelude::*;
use std::path::Path;
use std::process::{Output, Stdio};

/// Relative rounding allowed on a limit reported as held (dwell times written in full
/// precision; the feed and acceleration recomputed from them).
const LIMIT_REL: f64 = 1e-9;
/// Relative agreement of a reported residual RMS with the exact `R` applied to the written
/// dwell (sums in another order, the piston about the mean).
const RESIDUAL_REL: f64 = 1e-7;
/// Absolute floor of that agreement, nm (a residual of a few pm).
const RESIDUAL_ABS_NM: f64 = 1e-6;

fn solve(args: &[&str], out: &Path) -> Output {
    preston_cmd()
        .arg("solve")
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A smooth map on an `n x n` grid at `pitch` mm, heights of tens of nm.
fn map_text(n: usize, pitch: f64, phase: f64) -> String {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..n {
        for ix in 0..n {
            let (x, y) = (ix as f64 * pitch, iy as f64 * pitch);
            let z = 40.0 + 25.0 * (0.31 * x + phase).sin() * (0.23 * y).cos() + 0.8 * y;
            t.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    t
}

/// The truncated Gaussian, as `preston`'s `--gaussian-*` flags define it.
#[derive(Debug, Clone, Copy)]
struct Gauss {
    sigma_mm: f64,
    peak: f64,
    trunc_mm: f64,
}

impl Gauss {
    fn rate(&self, dx: f64, dy: f64) -> f64 {
        let r2 = dx * dx + dy * dy;
        let cut = self.trunc_mm * (1.0 + 1e-6);
        if r2 > cut * cut {
            0.0
        } else {
            self.peak * (-r2 / (2.0 * self.sigma_mm * self.sigma_mm)).exp()
        }
    }

    fn args(&self) -> Vec<String> {
        vec![
            "--gaussian-sigma-mm".into(),
            self.sigma_mm.to_string(),
            "--gaussian-peak-nm-per-s".into(),
            self.peak.to_string(),
            "--gaussian-truncation-mm".into(),
            self.trunc_mm.to_string(),
        ]
    }
}

/// What the written files say, recomputed.
struct Written {
    x: Vec<f64>,
    y: Vec<f64>,
    ds: Vec<f64>,
    dwell: Vec<f64>,
    feed: Vec<f64>,
    map: [Vec<f64>; 3],
}

fn read_written(out: &Path) -> Written {
    let d = csv_columns(
        &out.join("dwell.csv"),
        &["x_mm", "y_mm", "ds_mm", "dwell_s", "feed_mm_per_min"],
    );
    let r = csv_columns(&out.join("residual.csv"), &["x_mm", "y_mm", "z_nm"]);
    let mut d = d.into_iter();
    let mut r = r.into_iter();
    let next = |i: &mut std::vec::IntoIter<Vec<f64>>| i.next().unwrap();
    Written {
        x: next(&mut d),
        y: next(&mut d),
        ds: next(&mut d),
        dwell: next(&mut d),
        feed: next(&mut d),
        map: [next(&mut r), next(&mut r), next(&mut r)],
    }
}

/// The exact `R t - z` at the map points, `R` summed directly from the Gaussian.
fn exact_misfit_nm(w: &Written, tif: &Gauss) -> Vec<f64> {
    let [mx, my, mz] = &w.map;
    (0..mx.len())
        .map(|i| {
            let h: f64 = (0..w.x.len())
                .map(|j| tif.rate(mx[i] - w.x[j], my[i] - w.y[j]) * w.dwell[j])
                .sum();
            h - mz[i]
        })
        .collect()
}

/// The free piston `c = mean(R t - z)`, nm, and the RMS of the residual about it.
fn exact_piston_and_rms_nm(w: &Written, tif: &Gauss) -> (f64, f64) {
    let d = exact_misfit_nm(w, tif);
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    let rms = (d.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / d.len() as f64).sqrt();
    (mean, rms)
}

/// RMS about the mean of `z - R t`, nm.
fn exact_rms_nm(w: &Written, tif: &Gauss) -> f64 {
    exact_piston_and_rms_nm(w, tif).1
}

/// `ds_j` from the path: half of each neighbouring segment, the full one at the ends.
fn ds_of(x: &[f64], y: &[f64]) -> Vec<f64> {
    let seg: Vec<f64> = (1..x.len())
        .map(|j| (x[j] - x[j - 1]).hypot(y[j] - y[j - 1]))
        .collect();
    let n = x.len();
    (0..n)
        .map(|j| match (j, n) {
            (_, 1) => 0.0,
            (0, _) => seg[0],
            (j, n) if j == n - 1 => seg[n - 2],
            (j, _) => 0.5 * (seg[j - 1] + seg[j]),
        })
        .collect()
}

/// Largest `|v_{j+1}^2 - v_j^2| / (2 s_j)` over segments that are not connecting moves (the
/// path turns by more than 60 degrees at both ends), `v = ds / t`, mm/s^2.
fn max_accel(w: &Written) -> f64 {
    let (x, y) = (&w.x, &w.y);
    let n = x.len();
    let turn = |j: usize| -> f64 {
        if j == 0 || j + 1 >= n {
            return 0.0;
        }
        let (ax, ay) = (x[j] - x[j - 1], y[j] - y[j - 1]);
        let (bx, by) = (x[j + 1] - x[j], y[j + 1] - y[j]);
        let (la, lb) = (ax.hypot(ay), bx.hypot(by));
        if la > 0.0 && lb > 0.0 {
            ((ax * bx + ay * by) / (la * lb))
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees()
        } else {
            0.0
        }
    };
    let mut worst: f64 = 0.0;
    for j in 0..n.saturating_sub(1) {
        let seg = (x[j + 1] - x[j]).hypot(y[j + 1] - y[j]);
        if seg <= 0.0 || (turn(j) > 60.0 && turn(j + 1) > 60.0) {
            continue;
        }
        if w.dwell[j] <= 0.0 || w.dwell[j + 1] <= 0.0 {
            continue;
        }
        let v0 = w.ds[j] / w.dwell[j];
        let v1 = w.ds[j + 1] / w.dwell[j + 1];
        worst = worst.max((v1 * v1 - v0 * v0).abs() / (2.0 * seg));
    }
    worst
}

/// Checks every figure of a run that exited 0 against the written files.
fn check_exit_zero(out: &Path, tif: &Gauss, v_max: f64, a_max: Option<f64>) {
    let w = read_written(out);
    let r = report(out);
    let all = w.dwell.iter().chain(&w.feed).chain(&w.ds).chain(&w.map[2]);
    assert!(all.clone().all(|v| v.is_finite()), "a non-finite number");
    for key in ["rms_after_nm", "total_dwell_s", "piston_nm", "objective"] {
        let v = r[key].as_f64().unwrap_or(f64::NAN);
        assert!(v.is_finite(), "{key} = {v}");
    }
    // ds and the feed formula, recomputed from the path.
    let ds = ds_of(&w.x, &w.y);
    for (j, &d) in ds.iter().enumerate() {
        assert!((d - w.ds[j]).abs() <= 1e-9 * d.max(1.0), "ds at {j}");
        let f = if d > 0.0 && w.dwell[j] > 0.0 {
            d / w.dwell[j] * 60.0
        } else {
            0.0
        };
        assert!(
            (f - w.feed[j]).abs() <= 1e-9 * f.max(1.0),
            "feed at {j}: {} written, {f} recomputed",
            w.feed[j]
        );
        assert!(
            f <= v_max * (1.0 + LIMIT_REL),
            "feed {f} > v_max {v_max} at {j}"
        );
        assert!(w.dwell[j] >= 0.0);
    }
    if let Some(a) = a_max {
        let got = max_accel(&w);
        assert!(got <= a * (1.0 + LIMIT_REL), "acceleration {got} > {a}");
        let reported = r["max_accel_mm_per_s2"].as_f64().unwrap();
        assert!((reported - got).abs() <= 1e-6 * a, "{reported} vs {got}");
    }
    let (piston, exact) = exact_piston_and_rms_nm(&w, tif);
    // Where the program is executed, `rms_after_nm` is its residual and `model` the plan's.
    let reported = match r.get("executed") {
        Some(e) if !e.is_null() => {
            assert_eq!(r["rms_after_nm"], e["rms_after_nm"]);
            r["model"]["rms_nm"].as_f64().unwrap()
        }
        _ => r["rms_after_nm"].as_f64().unwrap(),
    };
    assert!(
        (reported - exact).abs() <= RESIDUAL_REL * exact + RESIDUAL_ABS_NM,
        "reported RMS {reported} nm, exact R on dwell.csv {exact} nm"
    );
    let reported_piston = r["piston_nm"].as_f64().unwrap();
    assert!(
        (reported_piston - piston).abs() <= RESIDUAL_REL * piston.abs() + RESIDUAL_ABS_NM,
        "reported piston {reported_piston} nm, exact {piston} nm"
    );
    // The objective 0.5 ||R t - z - c||^2 of the contract, from the same residual.
    let objective = 0.5 * w.map[0].len() as f64 * exact * exact;
    let reported_objective = r["objective"].as_f64().unwrap();
    assert!(
        (reported_objective - objective).abs() <= 1e-6 * objective + 1e-9,
        "reported objective {reported_objective}, exact {objective}"
    );
}

#[derive(Debug, Clone)]
struct Job {
    n: usize,
    pitch: f64,
    phase: f64,
    tif: Gauss,
    raster: f64,
    aperture: Option<f64>,
    v_max: f64,
    a_max: Option<f64>,
    operator: &'static str,
    accel_method: &'static str,
}

fn jobs() -> impl Strategy<Value = Job> {
    (
        (9usize..16, prop_oneof![Just(1.0), Just(0.8)], 0.0..3.0f64),
        (0.6..1.6f64, 2.0..20.0f64, 2.0..3.5f64),
        prop_oneof![Just(1.0), Just(0.7), Just(0.5)],
        proptest::option::of(3.0..6.0f64),
        1500.0..6000.0f64,
        proptest::option::of(100.0..2000.0f64),
        prop_oneof![Just("auto"), Just("sparse"), Just("fft-spread")],
        prop_oneof![Just("squared-speed"), Just("scp-qp")],
    )
        .prop_map(
            |((n, pitch, phase), (sigma, peak, k), raster, aperture, v_max, a_max, op, am)| {
                Job {
                    n,
                    pitch,
                    phase,
                    tif: Gauss {
                        sigma_mm: sigma,
                        peak,
                        trunc_mm: k * sigma,
                    },
                    raster,
                    aperture,
                    v_max,
                    a_max,
                    operator: op,
                    // The sequential QP needs the assembled R.
                    accel_method: if op == "fft-spread" {
                        "squared-speed"
                    } else {
                        am
                    },
                }
            },
        )
}

fn run_job(job: &Job, dir: &Path) -> (Output, std::path::PathBuf) {
    let map = write(dir, "map.csv", &map_text(job.n, job.pitch, job.phase));
    let out = dir.join("out");
    let mut args: Vec<String> = vec!["--map".into(), s(&map).into()];
    args.extend(job.tif.args());
    args.extend([
        "--raster-pitch-mm".into(),
        job.raster.to_string(),
        "--v-max".into(),
        job.v_max.to_string(),
        "--operator".into(),
        job.operator.into(),
        // The reference below is the point model's `R`; the swept model's columns are checked
        // against the program run and closed forms in `solver/src/setup` and
        // `solver/src/influence/swept.rs`.
        "--influence".into(),
        "point".into(),
    ]);
    if job.operator == "fft-spread" {
        // Loose enough that the operator serves these rasters: its error must then be
        // measured and the exact residual reported.
        args.extend(["--spread-tolerance".into(), "1e-2".into()]);
    }
    if let Some(r) = job.aperture {
        let c = 0.5 * (job.n - 1) as f64 * job.pitch;
        args.extend(["--aperture".into(), format!("circle:{r}@{c},{c}")]);
    }
    if let Some(a) = job.a_max {
        args.extend([
            "--a-max-mm-per-s2".into(),
            a.to_string(),
            "--accel-method".into(),
            job.accel_method.into(),
        ]);
    }
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    (solve(&refs, &out), out)
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 24,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// Over random small jobs (maps, TIFs, rasters, apertures, feed and acceleration limits,
    /// operators, methods): exit 0 never comes with a violated limit, a non-finite number, or a
    /// residual that the exact `R` applied to `dwell.csv` does not give; any other exit writes
    /// a status or nothing.
    #[test]
    fn exit_zero_means_every_reported_figure_holds(job in jobs()) {
        let d = tempfile::tempdir().unwrap();
        let (o, out) = run_job(&job, d.path());
        match o.status.code() {
            Some(0) => check_exit_zero(&out, &job.tif, job.v_max, job.a_max),
            Some(3) => {
                let r = report(&out);
                prop_assert_ne!(r["status"].as_str(), Some("converged"));
            }
            Some(2) => prop_assert!(!out.join("report.json").exists()),
            other => prop_assert!(false, "exit {other:?}: {}", stderr(&o)),
        }
    }
}

/// The off-lattice spreading operator at a loose tolerance: the report gives the exact `R`'s
/// residual of the returned dwell, the operator's measured error, and a warning when that error
/// exceeds its tolerance.
#[test]
fn the_spreading_operator_reports_its_measured_error_and_the_exact_residual() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text(21, 1.0, 0.4));
    let tif = Gauss {
        sigma_mm: 1.0,
        peak: 10.0,
        trunc_mm: 3.0,
    };
    let out = d.path().join("out");
    let mut args: Vec<String> = vec!["--map".into(), s(&map).into()];
    args.extend(tif.args());
    args.extend(
        [
            "--raster-pitch-mm",
            "0.7",
            "--v-max",
            "3000",
            "--operator",
            "fft-spread",
            "--spread-tolerance",
            "1e-2",
            // The reference below is the point model's `R`.
            "--influence",
            "point",
        ]
        .map(String::from),
    );
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = solve(&refs, &out);
    let err = stderr(&o);
    assert!(matches!(o.status.code(), Some(0 | 3)), "{err}");
    let r = report(&out);
    let e = &r["operator_error"];
    let measured = e["relative_removal_error"]
        .as_f64()
        .expect("operator_error");
    assert_eq!(e["tolerance"].as_f64(), Some(1e-2));
    let w = read_written(&out);
    let exact = exact_rms_nm(&w, &tif);
    let reported = r["rms_after_nm"].as_f64().unwrap();
    assert!(
        (reported - exact).abs() <= RESIDUAL_REL * exact + RESIDUAL_ABS_NM,
        "reported {reported} nm, exact {exact} nm"
    );
    assert!((e["rms_after_exact_nm"].as_f64().unwrap() - reported).abs() <= 1e-12 * reported);
    let predicted = e["rms_after_operator_nm"].as_f64().unwrap();
    let misstated = (predicted - exact).abs() > 0.05 * exact;
    assert_eq!(
        measured > 1e-2 || misstated,
        err.contains("measured error"),
        "measured {measured}, predicted {predicted} nm, exact {exact} nm: {err}"
    );
    // This case: the operator's error is within its tolerance against the removal, yet it
    // dominates the residual, so the warning is given.
    assert!(misstated && err.contains("measured error"), "{err}");
}

/// The NUFFT operator on a smooth TIF (a Gaussian cut at 6 sigma) over a raster off the map
/// lattice: the residual reported is the exact `R`'s, the measured error on the returned dwell
/// is within ten times the 1e-6 design tolerance (the estimate is over columns; a dwell that
/// leans on raster points far out, where the columns hold only the Gaussian's tail, weighs
/// their larger relative error more: 3e-6 here), and the warning is given exactly when the
/// error exceeds the tolerance or misstates the residual.
#[test]
fn the_nufft_operator_reports_its_measured_error_and_the_exact_residual() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text(41, 0.5, 0.4));
    let tif = Gauss {
        sigma_mm: 1.5,
        peak: 10.0,
        trunc_mm: 9.0,
    };
    let out = d.path().join("out");
    let mut args: Vec<String> = vec!["--map".into(), s(&map).into()];
    args.extend(tif.args());
    args.extend(
        [
            "--raster-pitch-mm",
            "0.7",
            "--v-max",
            "3000",
            "--influence",
            "point",
            "--operator",
            "nufft",
        ]
        .map(String::from),
    );
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = solve(&refs, &out);
    let err = stderr(&o);
    assert!(matches!(o.status.code(), Some(0 | 3)), "{err}");
    let r = report(&out);
    assert_eq!(r["operator"].as_str(), Some("nufft"), "{err}");
    let e = &r["operator_error"];
    let measured = e["relative_removal_error"]
        .as_f64()
        .expect("operator_error");
    assert_eq!(e["tolerance"].as_f64(), Some(1e-6));
    assert!(measured <= 1e-5, "measured {measured:.2e}: {err}");
    let w = read_written(&out);
    let exact = exact_rms_nm(&w, &tif);
    let reported = r["rms_after_nm"].as_f64().unwrap();
    assert!(
        (reported - exact).abs() <= RESIDUAL_REL * exact + RESIDUAL_ABS_NM,
        "reported {reported} nm, exact {exact} nm"
    );
    assert!((e["rms_after_exact_nm"].as_f64().unwrap() - reported).abs() <= 1e-12 * reported);
    let predicted = e["rms_after_operator_nm"].as_f64().unwrap();
    let misstated = (predicted - exact).abs() > 0.05 * exact;
    assert_eq!(
        measured > 1e-6 || misstated,
        err.contains("measured error"),
        "measured {measured}, predicted {predicted} nm, exact {exact} nm: {err}"
    );
}

/// A dwell path that reaches no map point, with the default and the assembled operator, and a
/// TIF in metres under an `x_mm` header: exit 2 and nothing written (or, for the TIF, a warning
/// before the solve at least).
#[test]
fn inputs_that_cannot_be_meant_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text(21, 1.0, 0.0));
    let mut far = String::from("x_mm,y_mm\n");
    for i in 0..30 {
        far.push_str(&format!("{},{}\n", 500.0 + i as f64 * 0.5, 400.0));
    }
    let far = write(d.path(), "far.csv", &far);
    let tif = Gauss {
        sigma_mm: 1.0,
        peak: 10.0,
        trunc_mm: 3.0,
    };
    for op in ["auto", "sparse"] {
        let out = d.path().join(format!("far_{op}"));
        let mut args: Vec<String> = vec!["--map".into(), s(&map).into()];
        args.extend(tif.args());
        args.extend([
            "--dwell".into(),
            s(&far).into(),
            "--v-max".into(),
            "3000".into(),
        ]);
        args.extend(["--operator".into(), op.into()]);
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = solve(&refs, &out);
        assert_eq!(o.status.code(), Some(2), "{op}: {}", stderr(&o));
        assert!(
            stderr(&o).contains("none of the 30 dwell points"),
            "{}",
            stderr(&o)
        );
        assert!(!out.join("report.json").exists());
    }
    // A measured TIF written in metres: a footprint of micrometres.
    let mut tif_m = String::from("x_mm,y_mm,rate_nm_per_s\n");
    for iy in -5..=5 {
        for ix in -5..=5 {
            let (x, y) = (ix as f64 * 1e-3, iy as f64 * 1e-3);
            let r = 10.0 * (-(x * x + y * y) / (2.0 * 2e-3f64.powi(2))).exp();
            tif_m.push_str(&format!("{x},{y},{r}\n"));
        }
    }
    let tif_m = write(d.path(), "tif_m.csv", &tif_m);
    let out = d.path().join("metres");
    let o = solve(
        &[
            "--map",
            s(&map),
            "--tif",
            s(&tif_m),
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "3000",
        ],
        &out,
    );
    let err = stderr(&o);
    assert!(
        err.contains("narrower") || err.contains("none of the"),
        "{err}"
    );
    assert_ne!(o.status.code(), Some(101), "{err}");
}

/// `--max-iterations` bounds the acceleration-limited stage too: the run stops within it and
/// does not report convergence it did not reach.
#[test]
fn max_iterations_bounds_the_acceleration_limited_solve() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text(25, 1.0, 0.2));
    let tif = Gauss {
        sigma_mm: 1.0,
        peak: 10.0,
        trunc_mm: 3.0,
    };
    let out = d.path().join("out");
    let mut args: Vec<String> = vec!["--map".into(), s(&map).into()];
    args.extend(tif.args());
    args.extend(
        [
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "3000",
            "--a-max-mm-per-s2",
            "50",
            "--max-iterations",
            "3",
        ]
        .map(String::from),
    );
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    let o = solve(&refs, &out);
    let r = report(&out);
    let iterations = r["iterations"].as_u64().unwrap();
    // The feed-limited start and the limited stage, each at most 3.
    assert!(iterations <= 6, "{iterations} iterations: {}", stderr(&o));
    if o.status.code() == Some(0) {
        check_exit_zero(&out, &tif, 3000.0, Some(50.0));
    } else {
        assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
        assert_ne!(r["status"].as_str(), Some("converged"));
    }
}

/// A closed stdout and stderr end the printing, never the process: every subcommand run with
/// both pipes closed exits as it would with them open (never 101, a panic), and writes its
/// outputs.
#[test]
fn closed_pipes_end_the_printing_not_the_run() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text(15, 1.0, 0.0));
    let out = d.path().join("solved");
    let tif_out = d.path().join("tif.csv");
    let conv = d.path().join("conv.csv");
    let runs: Vec<(Vec<String>, i32, Option<std::path::PathBuf>)> = vec![
        (
            [
                "solve",
                "--map",
                s(&map),
                "--gaussian-sigma-mm",
                "1",
                "--gaussian-peak-nm-per-s",
                "10",
                "--gaussian-truncation-mm",
                "3",
                "--raster-pitch-mm",
                "1",
                "--v-max",
                "3000",
                "--out",
                s(&out),
            ]
            .map(String::from)
            .to_vec(),
            0,
            Some(out.join("report.json")),
        ),
        (
            [
                "tif",
                "gaussian",
                "--sigma-mm",
                "1",
                "--peak-nm-per-s",
                "10",
                "--pitch-mm",
                "0.25",
                "--out",
                s(&tif_out),
            ]
            .map(String::from)
            .to_vec(),
            0,
            Some(tif_out.clone()),
        ),
        (
            ["map", "convert", "--map", s(&map), "--out", s(&conv)]
                .map(String::from)
                .to_vec(),
            0,
            Some(conv.clone()),
        ),
        (
            ["solve", "--map", "/nonexistent/m.csv", "--out", s(&out)]
                .map(String::from)
                .to_vec(),
            2,
            None,
        ),
    ];
    for (args, code, written) in runs {
        let mut child = preston_cmd()
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Both read ends closed before the process prints anything.
        drop(child.stdout.take());
        drop(child.stderr.take());
        let status = child.wait().unwrap();
        assert_eq!(status.code(), Some(code), "{args:?}");
        if let Some(w) = written {
            assert!(w.exists(), "{args:?}: {} not written", w.display());
        }
    }
}

/// A raster on the map's lattice with two dwell points 6 m out: `auto` does not build the mostly
/// empty FFT lattice (a warning says so, and the solve is the assembled `R`'s), and
/// `--operator fft`, which does, ends with exit 2 and a message naming the lattice where its
/// buffers cannot be had (here an address space capped at 2 GiB with `ulimit -v`), never an
/// abort, and writes nothing.
#[test]
fn a_mostly_empty_fft_lattice_is_not_chosen_and_one_that_cannot_be_had_is_exit_2() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_text(21, 1.0, 0.0));
    let mut path = String::from("x_mm,y_mm\n-6000,-6000\n");
    for j in 0..21 {
        for k in 0..21 {
            let i = if j % 2 == 0 { k } else { 20 - k };
            path.push_str(&format!("{i},{j}\n"));
        }
    }
    path.push_str("6000,6000\n");
    let path = write(d.path(), "far.csv", &path);
    let tif = Gauss {
        sigma_mm: 1.0,
        peak: 10.0,
        trunc_mm: 3.0,
    };
    let args = |operator: &str| -> Vec<String> {
        let mut a: Vec<String> = vec!["solve".into(), "--map".into(), s(&map).into()];
        a.extend(tif.args());
        a.extend(
            [
                "--dwell",
                s(&path),
                "--v-max",
                "3000",
                "--operator",
                operator,
            ]
            .map(String::from),
        );
        a
    };
    let auto_out = d.path().join("auto");
    let o = preston_cmd()
        .args(args("auto"))
        .arg("--out")
        .arg(&auto_out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("mostly empty"), "{}", stderr(&o));
    assert_eq!(report(&auto_out)["operator"], "sparse");
    let fft_out = d.path().join("fft");
    let mut script = String::from("ulimit -v 2097152 && exec \"$0\"");
    for k in 1..=args("fft").len() + 2 {
        script.push_str(&format!(" \"${{{k}}}\""));
    }
    let o = std::process::Command::new("bash")
        .arg("-c")
        .arg(&script)
        .arg(env!("CARGO_BIN_EXE_preston"))
        .args(args("fft"))
        .arg("--out")
        .arg(&fft_out)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("FFT lattice") && stderr(&o).contains("could not be allocated"),
        "{}",
        stderr(&o)
    );
    assert!(!fft_out.join("report.json").exists());
}
