//! `preston solve --a-max-mm-per-s2` with the first-order method on rasters: the constraint
//! recomputed segment by segment from the written `dwell.csv`, with the assembled sparse `R`, the
//! matrix-free FFT operator and on a curved part, and the SCP-QP reference on the same case.

use std::path::{Path, PathBuf};
use std::process::Command;

/// Relative tolerance of the constraint recomputed from the written file (the methods' own is 1%).
const ACCEL_TOL: f64 = 1.01;
/// First-order objective against the SCP-QP reference's, relative.
const OBJECTIVE_VS_REFERENCE: f64 = 0.01;

fn preston() -> Command {
    Command::new(env!("CARGO_BIN_EXE_preston"))
}

/// A 16 x 8 mm map at 0.5 mm pitch with a trench across x = 8 mm on a tilted base.
fn map(dir: &Path) -> PathBuf {
    let mut text = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..17 {
        for ix in 0..33 {
            let (x, y) = (ix as f64 * 0.5, iy as f64 * 0.5);
            let z = 50.0 + 5.0 * y + 300.0 * (-(x - 8.0f64).powi(2) / 2.0).exp();
            text.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    let p = dir.join("map.csv");
    std::fs::write(&p, text).unwrap();
    p
}

/// Runs `preston solve` on the map with a 1 mm raster (operator and extra arguments given) and
/// returns the report and the rows `(x, y, ds, dwell)` of `dwell.csv`.
fn solve(dir: &Path, name: &str, extra: &[&str]) -> (serde_json::Value, Vec<[f64; 4]>) {
    let out = dir.join(name);
    let o = preston()
        .args(["solve", "--map"])
        .arg(map(dir))
        .args([
            "--raster-pitch-mm",
            "1",
            "--gaussian-sigma-mm",
            "1",
            "--gaussian-peak-nm-per-s",
            "100",
            "--gaussian-truncation-mm",
            "3",
            "--v-max",
            "600",
            "--out",
        ])
        .arg(&out)
        .args(extra)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
        .unwrap();
    let text = std::fs::read_to_string(out.join("dwell.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next().unwrap(),
        "x_mm,y_mm,ds_mm,dwell_s,feed_mm_per_min"
    );
    let rows = lines
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|c| c.parse().unwrap()).collect();
            [v[0], v[1], v[2], v[3]]
        })
        .collect();
    (report, rows)
}

/// Turn angle at each point, degrees (0 at the ends).
fn turns(rows: &[[f64; 4]]) -> Vec<f64> {
    let mut out = vec![0.0; rows.len()];
    for j in 1..rows.len().saturating_sub(1) {
        let (a, b, c) = (rows[j - 1], rows[j], rows[j + 1]);
        let (ax, ay, bx, by) = (b[0] - a[0], b[1] - a[1], c[0] - b[0], c[1] - b[1]);
        let cos = (ax * bx + ay * by) / (ax.hypot(ay) * bx.hypot(by));
        out[j] = cos.clamp(-1.0, 1.0).acos().to_degrees();
    }
    out
}

/// `|v_{j+1}^2 - v_j^2| / (2 s_j)` of every segment on a line (both ends turn by at most 60
/// degrees or one of them does), `v = ds / t`, recomputed from the rows.
fn line_accels(rows: &[[f64; 4]]) -> Vec<f64> {
    let turn = turns(rows);
    rows.windows(2)
        .enumerate()
        .filter(|(j, _)| !(turn[*j] > 60.0 && turn[j + 1] > 60.0))
        .map(|(_, w)| {
            let (v0, v1) = (w[0][2] / w[0][3], w[1][2] / w[1][3]);
            let s = (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]);
            (v1 * v1 - v0 * v0).abs() / (2.0 * s)
        })
        .collect()
}

/// The limit holds on every constrained segment and binds on some.
fn check_limit(rows: &[[f64; 4]], a_max: f64, what: &str) {
    let acc = line_accels(rows);
    for (j, a) in acc.iter().enumerate() {
        assert!(*a <= ACCEL_TOL * a_max, "{what}: segment {j}: {a} > {a_max}");
    }
    let top = acc.iter().copied().fold(0.0, f64::max);
    assert!(top > 0.9 * a_max, "{what}: the limit does not bind ({top})");
}

#[test]
fn first_order_method_meets_the_limit_and_the_reference() {
    let d = tempfile::tempdir().unwrap();
    let (free, free_rows) = solve(d.path(), "free", &["--operator", "sparse"]);
    let a_free = line_accels(&free_rows).into_iter().fold(0.0, f64::max);
    let a_max = 0.1 * a_free;
    let a = a_max.to_string();
    let (fo, rows) = solve(
        d.path(),
        "fo",
        &["--operator", "sparse", "--a-max-mm-per-s2", &a],
    );
    check_limit(&rows, a_max, "first-order, sparse");
    assert_eq!(fo["accel"]["method"], "first-order");
    assert_eq!(fo["status"], "converged");
    let (qp, qp_rows) = solve(
        d.path(),
        "qp",
        &["--a-max-mm-per-s2", &a, "--accel-method", "scp-qp"],
    );
    check_limit(&qp_rows, a_max, "scp-qp");
    assert_eq!(qp["accel"]["method"], "scp-qp");
    let (f, f_ref) = (
        fo["objective"].as_f64().unwrap(),
        qp["objective"].as_f64().unwrap(),
    );
    assert!(
        f <= f_ref * (1.0 + OBJECTIVE_VS_REFERENCE),
        "first-order {f} vs scp-qp {f_ref}"
    );
    assert!(f >= free["objective"].as_f64().unwrap() * (1.0 - 1e-6));

    // The matrix-free FFT operator (map and raster on one lattice).
    let (fft, fft_rows) = solve(
        d.path(),
        "fft",
        &["--operator", "fft", "--a-max-mm-per-s2", &a],
    );
    assert_eq!(fft["operator"], "fft");
    check_limit(&fft_rows, a_max, "first-order, fft");
    let f_fft = fft["objective"].as_f64().unwrap();
    assert!(
        f_fft <= f_ref * (1.0 + OBJECTIVE_VS_REFERENCE),
        "fft {f_fft} vs scp-qp {f_ref}"
    );
}

#[test]
fn first_order_method_on_a_curved_part() {
    let d = tempfile::tempdir().unwrap();
    let sphere = d.path().join("sphere.json");
    std::fs::write(
        &sphere,
        "{\"type\":\"conic\",\"curvature_per_mm\":0.02,\"conic\":0}",
    )
    .unwrap();
    let s = sphere.to_str().unwrap();
    let (_, free_rows) = solve(d.path(), "free", &["--surface", s]);
    let a_free = line_accels(&free_rows).into_iter().fold(0.0, f64::max);
    let a_max = 0.1 * a_free;
    let (r, rows) = solve(
        d.path(),
        "curved",
        &["--surface", s, "--a-max-mm-per-s2", &a_max.to_string()],
    );
    assert_eq!(r["accel"]["method"], "first-order");
    check_limit(&rows, a_max, "first-order, sphere");
}
