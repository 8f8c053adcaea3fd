//! `preston solve --solver first-order`, `--warm-start`, and `preston bench` end to end.

mod common;

use common::{data, preston_cmd, report};
use std::path::{Path, PathBuf};

/// A first-order solve of the sample job warm-started from the cold solve's dwell ends at most
/// this fraction above the cold solve's objective (both stop at the same relative KKT
/// tolerance, so either may end slightly above the other; no QP is run here).
const SAMPLE_REL_TOL: f64 = 1e-3;

/// The sample job without its acceleration limit (these tests are about the feed-limited
/// solvers and warm starts, which an acceleration limit refuses), written into `out`'s parent
/// with absolute input paths.
fn feed_limited_job(out: &Path) -> PathBuf {
    let text = std::fs::read_to_string(data("job_point_1mm.toml")).unwrap();
    let dir = data("job_point_1mm.toml").parent().unwrap().to_path_buf();
    let job: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with("a_max_mm_per_s2"))
        .map(|l| l.replace("file = \"", &format!("file = \"{}/", dir.display())))
        .collect::<Vec<_>>()
        .join("\n");
    let p = out.parent().unwrap().join(format!(
        "{}-job.toml",
        out.file_name().unwrap().to_string_lossy()
    ));
    std::fs::write(&p, job).unwrap();
    p
}

fn solve(extra: &[&str], out: &Path) -> std::process::Output {
    preston_cmd()
        .args(["solve", "--job"])
        .arg(feed_limited_job(out))
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
    // rho = 0 and no v_min: no finite dual bound exists, and the report says so.
    match r["objective_gap_bound"].as_f64() {
        Some(bound) => assert!(bound >= 0.0 && bound < r["objective"].as_f64().unwrap()),
        None => {
            assert!(r["objective_gap_bound"].is_null());
            assert!(!r["gap_bound_reason"].as_str().unwrap().is_empty());
            assert_eq!(r["converged_by"], "kkt_residual");
        }
    }

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

/// The first-order solve on the FFT operator and on the assembled matrix give objectives within
/// this fraction of each other (same iteration; products equal to ~1e-12 relative).
const FFT_VS_SPARSE_REL_TOL: f64 = 1e-9;

/// A 30 x 20 mm map on a 0.5 mm grid (smooth error), written as CSV into `dir`.
fn grid_map(dir: &Path) -> PathBuf {
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..41 {
        for ix in 0..61 {
            let (x, y) = (ix as f64 * 0.5, iy as f64 * 0.5);
            let z = 30.0 * (0.3 * x + 0.1 * y).cos() + 20.0 * (0.2 * y).sin();
            text.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    let path = dir.join("grid_map.csv");
    std::fs::write(&path, text).unwrap();
    path
}

/// A serpentine 1 mm raster over the map extended by 2 mm (every point reaches the map).
fn grid_dwell(dir: &Path) -> PathBuf {
    let mut text = String::from("x_mm,y_mm\n");
    for (row, y) in (-2..=22).enumerate() {
        let xs: Vec<i32> = if row % 2 == 0 {
            (-2..=32).collect()
        } else {
            (-2..=32).rev().collect()
        };
        for x in xs {
            text.push_str(&format!("{x},{y}\n"));
        }
    }
    let path = dir.join("grid_dwell.csv");
    std::fs::write(&path, text).unwrap();
    path
}

/// `preston solve` of `map` with a Gaussian TIF (sigma 2 mm, 10 nm/s), `v_max` 2000 mm/min and `args`.
fn solve_gaussian(map: &Path, args: &[&str], out: &Path) -> std::process::Output {
    preston_cmd()
        .args(["solve", "--map"])
        .arg(map)
        .args([
            "--gaussian-sigma-mm",
            "2",
            "--gaussian-peak-nm-per-s",
            "10",
            "--v-max",
            "2000",
        ])
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

fn solve_grid(
    map: &Path,
    dwell: &Path,
    operator: &str,
    method: &str,
    tolerance: &str,
    out: &Path,
) -> std::process::Output {
    let dwell = dwell.to_str().unwrap();
    let args = [
        "--dwell",
        dwell,
        "--v-min",
        "100",
        "--solver",
        "first-order",
        "--operator",
        operator,
        "--first-order-method",
        method,
        "--tolerance",
        tolerance,
        // The operators' own mathematics: the point model, whose lattice kernel is exact.
        "--influence",
        "point",
    ];
    solve_gaussian(map, &args, out)
}

/// The FFT operator and the assembled matrix, end to end. FISTA takes the same iterations on
/// either (products equal to rounding, no discrete choices), so the objectives agree to
/// [`FFT_VS_SPARSE_REL_TOL`]; L-BFGS's free-set choices let rounding steer it along another
/// path, so it is compared at a tight tolerance, where both runs are at the optimum to
/// [`LBFGS_FFT_VS_SPARSE_REL_TOL`].
#[test]
fn operator_fft_matches_the_assembled_matrix_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let (map, dwell) = (grid_map(dir.path()), grid_dwell(dir.path()));
    for (method, tolerance, rel_tol) in [
        ("fista", "1e-6", FFT_VS_SPARSE_REL_TOL),
        ("lbfgs", "1e-10", LBFGS_FFT_VS_SPARSE_REL_TOL),
    ] {
        let sparse_out = dir.path().join(format!("sparse_{method}"));
        let fft_out = dir.path().join(format!("fft_{method}"));
        let o = solve_grid(&map, &dwell, "sparse", method, tolerance, &sparse_out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let o = solve_grid(&map, &dwell, "fft", method, tolerance, &fft_out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert!(String::from_utf8_lossy(&o.stderr).contains("matrix-free FFT operator"));
        let (s, f) = (report(&sparse_out), report(&fft_out));
        assert_eq!(s["operator"], "sparse");
        assert_eq!(f["operator"], "fft");
        assert_eq!(s["nnz"], f["nnz"]);
        assert_eq!(s["unreachable_dwell_points"], f["unreachable_dwell_points"]);
        let (os, of) = (
            s["objective"].as_f64().unwrap(),
            f["objective"].as_f64().unwrap(),
        );
        assert!(
            (of - os).abs() <= rel_tol * os,
            "{method}: sparse {os} vs fft {of}: {}",
            (of - os) / os
        );
        assert!(f["max_bound_violation_s"].as_f64().unwrap() <= 1e-12);
        assert!(fft_out.join("dwell.csv").exists() && fft_out.join("residual.csv").exists());
    }
}

/// L-BFGS on the FFT operator and on the assembled matrix, both at tolerance 1e-10: objectives
/// within this fraction of each other.
const LBFGS_FFT_VS_SPARSE_REL_TOL: f64 = 1e-8;

#[test]
fn operator_fft_refuses_what_it_cannot_serve() {
    let dir = tempfile::tempdir().unwrap();
    // The sample job's 1 mm raster is not on its map's 0.32 mm lattice.
    let out = dir.path().join("off_lattice");
    let o = solve(&["--solver", "first-order", "--operator", "fft"], &out);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("dwell point") && err.contains("lattice"),
        "{err}"
    );
    assert!(!out.join("report.json").exists());
    // Scattered map points fill a tiny share of any lattice through them.
    let scattered = dir.path().join("scattered.csv");
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for k in 0..200u32 {
        let (x, y) = ((k * 37 % 101) as f64 * 0.173, (k * 53 % 89) as f64 * 0.291);
        text.push_str(&format!("{x},{y},{}\n", (x * 0.3).sin() * 20.0));
    }
    std::fs::write(&scattered, text).unwrap();
    let out = dir.path().join("scattered_out");
    let args = [
        "--raster-pitch-mm",
        "1",
        "--solver",
        "first-order",
        "--operator",
        "fft",
    ];
    let o = solve_gaussian(&scattered, &args, &out);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("regular lattice"));
    assert!(!out.join("report.json").exists());
    // The QP needs R.
    let out = dir.path().join("qp");
    let o = solve(&["--solver", "qp", "--operator", "fft"], &out);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("solver = \"qp\""));
    assert!(!out.join("report.json").exists());
}

#[test]
fn operator_auto_picks_fft_when_r_would_be_large() {
    // A 20 x 20 mm map at 0.1 mm (40,401 points) and a 0.4 mm raster (6,561 dwell points) with a
    // 6 mm Gaussian: auto estimates 7.4e7 non-zeros (a full disc per dwell point; the border ones
    // see less) on a lattice of about 1e5 cells: the cost models predict FFT products far cheaper.
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..201 {
        for ix in 0..201 {
            let (x, y) = (ix as f64 * 0.1, iy as f64 * 0.1);
            text.push_str(&format!(
                "{x:.1},{y:.1},{}\n",
                25.0 * (0.4 * x).cos() * (0.3 * y).sin()
            ));
        }
    }
    let map = dir.path().join("fine_map.csv");
    std::fs::write(&map, text).unwrap();
    let out = dir.path().join("out");
    let args = ["--raster-pitch-mm", "0.4", "--tolerance", "1e-4"];
    let o = solve_gaussian(&map, &args, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("operator auto"));
    let r = report(&out);
    assert_eq!(r["operator"], "fft");
    assert_eq!(r["solver"], "first-order");
    let nnz = r["nnz"].as_u64().unwrap();
    assert!(nnz > 20_000_000, "nnz {nnz}");
    assert!(r["rms_after_nm"].as_f64().unwrap() < 0.2 * r["rms_before_nm"].as_f64().unwrap());
}

/// A 30 x 20 mm map on a 0.4 mm lattice and a serpentine 0.5 mm raster over it extended by 3 mm:
/// 3,876 map and 3,869 dwell points, at 4 x 4 distinct positions within a map cell (the
/// positions are binary fractions of the cell, so the stencils' rounded phases are exact).
fn off_lattice_case(dir: &Path) -> (PathBuf, PathBuf) {
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..51 {
        for ix in 0..76 {
            let (x, y) = (ix as f64 * 0.4, iy as f64 * 0.4);
            let z = 30.0 * (0.3 * x + 0.1 * y).cos() + 20.0 * (0.2 * y).sin();
            text.push_str(&format!("{x:.1},{y:.1},{z}\n"));
        }
    }
    let map = dir.join("map_04.csv");
    std::fs::write(&map, text).unwrap();
    let dwell = dir.join("raster_05.csv");
    std::fs::write(&dwell, serpentine_csv(53, 73, 0.5)).unwrap();
    (map, dwell)
}

/// A serpentine raster from (-3, -3) mm: `rows` lines along x of `per_row` points at `pitch_mm`,
/// as a dwell CSV.
fn serpentine_csv(rows: usize, per_row: usize, pitch_mm: f64) -> String {
    let mut text = String::from("x_mm,y_mm\n");
    for row in 0..rows {
        for k in 0..per_row {
            let i = if row % 2 == 0 { k } else { per_row - 1 - k };
            text.push_str(&format!(
                "{},{}\n",
                -3.0 + pitch_mm * i as f64,
                -3.0 + pitch_mm * row as f64
            ));
        }
    }
    text
}

/// `preston solve` of the off-lattice case with `args` (Gaussian sigma 2 mm cut at 5.905 mm, a
/// radius no lattice offset lands on, so no pair sits on the cut).
fn solve_off_lattice(dir: &Path, args: &[&str], out: &Path) -> std::process::Output {
    let (map, dwell) = off_lattice_case(dir);
    let dwell = dwell.to_str().unwrap();
    let mut all = vec!["--dwell", dwell, "--gaussian-truncation-mm", "5.905"];
    all.extend_from_slice(args);
    solve_gaussian(&map, &all, out)
}

/// The phase-stencil operator and the assembled matrix, end to end: FISTA takes the same
/// iterations on either (products equal to rounding), so the objectives agree to
/// [`FFT_VS_SPARSE_REL_TOL`]; `auto` takes the cheapest operator that reproduces `R` and says so.
#[test]
fn operator_stencil_matches_the_assembled_matrix_and_auto_takes_the_cheapest_exact_operator() {
    let dir = tempfile::tempdir().unwrap();
    let fista = [
        "--solver",
        "first-order",
        "--first-order-method",
        "fista",
        "--tolerance",
        "1e-6",
        // The operators' own mathematics: the point model, whose stencils are exact.
        "--influence",
        "point",
    ];
    let run = |operator: &str| {
        let out = dir.path().join(operator);
        let mut args = fista.to_vec();
        args.extend(["--operator", operator]);
        let o = solve_off_lattice(dir.path(), &args, &out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (report(&out), String::from_utf8_lossy(&o.stderr).to_string())
    };
    let (s, _) = run("sparse");
    let (st, err) = run("stencil");
    assert!(err.contains("phase stencils"), "{err}");
    assert_eq!(s["operator"], "sparse");
    assert_eq!(st["operator"], "stencil");
    assert_eq!(s["nnz"], st["nnz"]);
    assert_eq!(s["iterations"], st["iterations"]);
    let (os, ost) = (
        s["objective"].as_f64().unwrap(),
        st["objective"].as_f64().unwrap(),
    );
    assert!(
        (ost - os).abs() <= FFT_VS_SPARSE_REL_TOL * os,
        "sparse {os} vs stencil {ost}"
    );
    // The default operator and solver: the 16 positions are the nodes of a lattice four times
    // finer than the map's, which the spreading reproduces exactly, and its FFT products are
    // predicted cheaper than the 16 stencils: auto takes the cheapest exact operator.
    let out = dir.path().join("auto");
    let o = solve_off_lattice(dir.path(), &["--tolerance", "1e-4"], &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("oversampling 4"), "{err}");
    let r = report(&out);
    assert_eq!(r["operator"], "fft-spread");
    let error = r["operator_error"]["relative_removal_error"]
        .as_f64()
        .unwrap();
    assert!(error <= 1e-6, "{error}");
    assert_eq!(r["solver"], "first-order");
    assert!(r["rms_after_nm"].as_f64().unwrap() < 0.2 * r["rms_before_nm"].as_f64().unwrap());
    // The QP needs R: asking for both is an input error naming why, with nothing written.
    let out = dir.path().join("qp");
    let o = solve_off_lattice(
        dir.path(),
        &["--solver", "qp", "--operator", "stencil"],
        &out,
    );
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("operator = \"stencil\" cannot be used"));
    assert!(!out.join("report.json").exists());
}

/// A raster at 1.5 times the map's pitch puts every dwell point on the lattice of half cells:
/// spreading onto it (oversampling 2) reproduces `R` (bilinear weights at a node are exact), and
/// its FFT products are predicted cheaper than the 2 x 2 phase stencils, so `auto` takes it,
/// with an operator error on the returned dwell within the NUFFT's design tolerance (1e-6) and
/// a residual within 5% of the assembled `R`'s plan at the same tolerance.
#[test]
fn operator_auto_takes_the_exact_spreading_for_a_half_cell_raster() {
    let dir = tempfile::tempdir().unwrap();
    let (map, _) = off_lattice_case(dir.path());
    let dwell = dir.path().join("raster_06.csv");
    std::fs::write(&dwell, serpentine_csv(45, 61, 0.6)).unwrap();
    let dwell = dwell.to_str().unwrap();
    let run = |operator: &str| {
        let out = dir.path().join(operator);
        let args = [
            "--dwell",
            dwell,
            "--gaussian-truncation-mm",
            "5.905",
            "--tolerance",
            "1e-4",
            "--operator",
            operator,
        ];
        let o = solve_gaussian(&map, &args, &out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (report(&out), String::from_utf8_lossy(&o.stderr).to_string())
    };
    let (auto, err) = run("auto");
    assert_eq!(auto["operator"], "fft-spread", "{err}");
    assert!(err.contains("oversampling 2"), "{err}");
    let error = auto["operator_error"]["relative_removal_error"]
        .as_f64()
        .unwrap();
    assert!(error <= 1e-6, "{error}");
    let (sparse, _) = run("sparse");
    let (a, s) = (
        auto["rms_after_nm"].as_f64().unwrap(),
        sparse["rms_after_nm"].as_f64().unwrap(),
    );
    let before = sparse["rms_before_nm"].as_f64().unwrap();
    assert!(a < 0.2 * before, "{a} of {before}");
    // As good a part as the assembled R's plan (both stopped at the same tolerance).
    assert!(a <= 1.05 * s, "{a} against {s}");
}

/// On a spiral every dwell point's stretch points its own way: no shared swept kernel serves,
/// and correcting every column would cost more than the assembled `R`. `auto`, which would take
/// the NUFFT operator for the point model (estimate within 1e-6), says why and takes the
/// direction-expansion operator where its cost model predicts it cheaper than `R`, else `R`.
#[test]
fn operator_auto_assembles_r_for_a_spiral_under_the_swept_model() {
    let dir = tempfile::tempdir().unwrap();
    let (map, _) = off_lattice_case(dir.path());
    let mut text = String::from("x_mm,y_mm\n");
    let mut theta: f64 = 0.0;
    loop {
        // Archimedes spiral about (15, 10) mm, 0.7 mm between turns and along the curve.
        let r = 0.7 * theta / (2.0 * std::f64::consts::PI);
        if r > 14.0 {
            break;
        }
        text.push_str(&format!(
            "{},{}\n",
            15.0 + r * theta.cos(),
            10.0 + r * theta.sin()
        ));
        theta += 0.7 / r.max(0.7);
    }
    let dwell = dir.path().join("spiral.csv");
    std::fs::write(&dwell, text).unwrap();
    let dwell = dwell.to_str().unwrap();
    let run = |influence: &str| {
        let out = dir.path().join(influence);
        let args = [
            "--dwell",
            dwell,
            "--gaussian-truncation-mm",
            "12",
            "--tolerance",
            "1e-4",
            "--influence",
            influence,
            "--max-iterations",
            "50",
            "--accept-best-iterate",
        ];
        let o = solve_gaussian(&map, &args, &out);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (report(&out), String::from_utf8_lossy(&o.stderr).to_string())
    };
    let (point, _) = run("point");
    assert_eq!(point["operator"], "nufft");
    let (swept, err) = run("swept");
    let op = swept["operator"].as_str().unwrap();
    assert!(op == "sparse" || op == "expansion", "{err}");
    if op == "expansion" {
        // Approximate: its error on the plan is reported, the residual is the exact R's.
        assert!(swept["operator_error"].is_object(), "{swept}");
    }
    assert!(err.contains("stretches differ"), "{err}");
}

/// Dwell points far from the map make the stencils' image of the lattice huge (its clearing
/// dominates each product): `auto` assembles `R` or takes the expansion operator, which spreads
/// onto the map's own lattice (its error reported), and the far points stay unreachable.
#[test]
fn operator_auto_declines_the_stencils_when_their_image_would_dwarf_the_map() {
    let dir = tempfile::tempdir().unwrap();
    let (map, dwell) = off_lattice_case(dir.path());
    let mut text = std::fs::read_to_string(&dwell).unwrap();
    text.push_str("1500,1500.5\n1500.5,-1500\n");
    std::fs::write(&dwell, text).unwrap();
    let out = dir.path().join("far");
    let dwell = dwell.to_str().unwrap();
    let args = [
        "--dwell",
        dwell,
        "--gaussian-truncation-mm",
        "5.905",
        "--tolerance",
        "1e-4",
    ];
    let o = solve_gaussian(&map, &args, &out);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = report(&out);
    let op = r["operator"].as_str().unwrap();
    assert!(op == "sparse" || op == "expansion", "{r}");
    if op == "expansion" {
        assert!(r["operator_error"].is_object(), "{r}");
    }
    assert_eq!(r["solver"], "first-order");
    assert_eq!(r["unreachable_dwell_points"], 2);
}

/// `preston bench` carries each solve's status to its rows and exits 3 when a solve stopped
/// before its test (rows still written), 0 when every solve converged.
#[test]
fn bench_rows_carry_the_status_and_an_unconverged_solve_exits_3() {
    let run = |tolerance: &str| {
        preston_cmd()
            .args([
                "bench",
                "--sizes",
                "500",
                "--solvers",
                "first-order",
                "--job",
                "none",
            ])
            .args(["--first-order-tolerance", tolerance, "--json"])
            .output()
            .unwrap()
    };
    let row_status = |out: &std::process::Output| {
        let rows: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        rows[0]["status"].as_str().unwrap().to_string()
    };
    let loose = run("1e-4");
    assert_eq!(loose.status.code(), Some(0));
    assert_eq!(row_status(&loose), "converged");
    // A tolerance below rounding: the first-order solver runs to its iteration limit.
    let tight = run("1e-30");
    assert_eq!(
        tight.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&tight.stderr)
    );
    assert_eq!(row_status(&tight), "max_iterations");
}
