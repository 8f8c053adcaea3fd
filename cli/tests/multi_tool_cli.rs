//! `preston solve` with two tools (repeated --tif/--dwell/--v-max): dwell_tool1.csv and
//! dwell_tool2.csv read back and the removal recomputed here from the TIF grids.

mod common;

use common::preston_cmd;
use std::fmt::Write as _;
use std::path::Path;

/// Relative agreement of the recomputed residual RMS with report.json: two quadratures of the
/// swept integral (the solver's at 1/64 of the TIF's radius, this test's midpoint samples).
const RMS_TOL: f64 = 1e-3;
/// Midpoint samples per half stretch in the test's own sweep.
const SWEEP_SAMPLES: usize = 32;

fn gaussian(sigma: f64, peak: f64, x: f64, y: f64) -> f64 {
    peak * (-(x * x + y * y) / (2.0 * sigma * sigma)).exp()
}

/// TIF grid CSV at `pitch` over `[-half, half]^2`, zero at the border.
fn write_tif(path: &Path, sigma: f64, peak: f64, half: f64, pitch: f64) {
    let k = (half / pitch).round() as i64;
    let mut s = String::from("x_mm,y_mm,rate_nm_per_s\n");
    for j in -k..=k {
        for i in -k..=k {
            let (x, y) = (i as f64 * pitch, j as f64 * pitch);
            let v = if i.abs() == k || j.abs() == k {
                0.0
            } else {
                gaussian(sigma, peak, x, y)
            };
            writeln!(s, "{x},{y},{v}").unwrap();
        }
    }
    std::fs::write(path, s).unwrap();
}

/// Bilinear interpolation of the grid written by `write_tif` (the TIF contract).
fn tif_rate(sigma: f64, peak: f64, half: f64, pitch: f64, dx: f64, dy: f64) -> f64 {
    let k = (half / pitch).round() as i64;
    let (u, v) = (dx / pitch, dy / pitch);
    let (i, j) = (u.floor() as i64, v.floor() as i64);
    let (fu, fv) = (u - i as f64, v - j as f64);
    let at = |a: i64, b: i64| {
        if a.abs() >= k || b.abs() >= k {
            0.0
        } else {
            gaussian(sigma, peak, a as f64 * pitch, b as f64 * pitch)
        }
    };
    if i < -k || j < -k || i >= k || j >= k {
        return 0.0;
    }
    at(i, j) * (1.0 - fu) * (1.0 - fv)
        + at(i + 1, j) * fu * (1.0 - fv)
        + at(i, j + 1) * (1.0 - fu) * fv
        + at(i + 1, j + 1) * fu * fv
}

fn read_dwell(path: &Path) -> Vec<(f64, f64, f64, f64)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let (x, y, t, f) = (
        col("x_mm"),
        col("y_mm"),
        col("dwell_s"),
        col("feed_mm_per_min"),
    );
    lines
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|s| s.parse().unwrap()).collect();
            (v[x], v[y], v[t], v[f])
        })
        .collect()
}

#[test]
fn two_tools_on_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Map 21 x 21 at 1 mm: a broad bump and a 5 mm ripple.
    let mut map = String::from("x_mm,y_mm,z_nm\n");
    let mut pts = Vec::new();
    for j in 0..21 {
        for i in 0..21 {
            let (x, y) = (i as f64, j as f64);
            let z = 30.0 * (-((x - 10.0).powi(2) + (y - 10.0).powi(2)) / 80.0).exp()
                + 4.0
                    * (std::f64::consts::TAU * x / 5.0).sin()
                    * (std::f64::consts::TAU * y / 7.0).cos();
            writeln!(map, "{x},{y},{z}").unwrap();
            pts.push((x, y, z));
        }
    }
    std::fs::write(d.join("map.csv"), map).unwrap();
    let tools = [(3.0, 2.0, 9.0, 0.5), (0.7, 1.0, 2.5, 0.25)];
    write_tif(
        &d.join("t1.csv"),
        tools[0].0,
        tools[0].1,
        tools[0].2,
        tools[0].3,
    );
    write_tif(
        &d.join("t2.csv"),
        tools[1].0,
        tools[1].1,
        tools[1].2,
        tools[1].3,
    );
    let raster = |x0: f64, pitch: f64, n: usize| {
        let mut s = String::from("x_mm,y_mm\n");
        for j in 0..n {
            for k in 0..n {
                let i = if j % 2 == 0 { k } else { n - 1 - k };
                writeln!(s, "{},{}", x0 + pitch * i as f64, x0 + pitch * j as f64).unwrap();
            }
        }
        s
    };
    std::fs::write(d.join("d1.csv"), raster(-4.0, 2.0, 15)).unwrap();
    std::fs::write(d.join("d2.csv"), raster(0.0, 1.0, 21)).unwrap();
    let out = d.join("out");
    let v_max = [2000.0, 6000.0];
    let run = preston_cmd()
        .arg("solve")
        .arg("--map")
        .arg(d.join("map.csv"))
        .arg("--tif")
        .arg(d.join("t1.csv"))
        .arg("--dwell")
        .arg(d.join("d1.csv"))
        .args(["--v-max", "2000"])
        .arg("--tif")
        .arg(d.join("t2.csv"))
        .arg("--dwell")
        .arg(d.join("d2.csv"))
        .args([
            "--v-max", "6000", "--solver", "qp", "--edge", "none", "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(!out.join("dwell.csv").exists());
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["influence"], "swept");
    // Every tool's TIF perturbed alike: the widths and offsets leave more than the plan.
    let rms = report["rms_after_nm"].as_f64().unwrap();
    for key in ["tif_wider_3pct", "tif_narrower_3pct", "offset_x_0p05mm"] {
        let f = report["sensitivity"][key]["rms_nm"].as_f64().unwrap();
        assert!(f > rms, "{key}: {f} against {rms}");
    }
    let listed = report["tools"].as_array().unwrap();
    assert_eq!(listed.len(), 2);
    let mut removal = vec![0.0; pts.len()];
    for (k, tool) in tools.iter().enumerate() {
        let dwell = read_dwell(&out.join(format!("dwell_tool{}.csv", k + 1)));
        assert_eq!(listed[k]["n"].as_u64().unwrap() as usize, dwell.len());
        let total: f64 = dwell.iter().map(|p| p.2).sum();
        let reported = listed[k]["total_dwell_s"].as_f64().unwrap();
        assert!(
            (total - reported).abs() <= 1e-6 * total.max(1.0),
            "tool {k}: {total} vs {reported}"
        );
        // Each tool's own feed limit.
        assert!(
            dwell.iter().all(|p| p.3 <= v_max[k] * (1.0 + 1e-6)),
            "tool {k} over its v_max"
        );
        // The tool swept at constant feed along each dwell point's stretch (from the midpoint
        // of the segment before to that of the segment after; the path's ends mirrored), as
        // its program runs: `SWEEP_SAMPLES` midpoint samples per stretch.
        let mut own = vec![0.0; pts.len()];
        for (j, &(x, y, t, _)) in dwell.iter().enumerate() {
            let half = |k: usize| (0.5 * (dwell[k].0 - x), 0.5 * (dwell[k].1 - y));
            let (a, b) = match (j.checked_sub(1), (j + 1 < dwell.len()).then_some(j + 1)) {
                (Some(p), Some(q)) => (half(p), half(q)),
                (Some(p), None) => (half(p), (-half(p).0, -half(p).1)),
                (None, Some(q)) => ((-half(q).0, -half(q).1), half(q)),
                (None, None) => ((0.0, 0.0), (0.0, 0.0)),
            };
            let (la, lb) = (a.0.hypot(a.1), b.0.hypot(b.1));
            let mut samples = Vec::new();
            for (from, to, len) in [(a, (0.0, 0.0), la), ((0.0, 0.0), b, lb)] {
                for s in 0..SWEEP_SAMPLES {
                    let f = (s as f64 + 0.5) / SWEEP_SAMPLES as f64;
                    let p = (from.0 + f * (to.0 - from.0), from.1 + f * (to.1 - from.1));
                    samples.push((x + p.0, y + p.1, len / SWEEP_SAMPLES as f64 / (la + lb)));
                }
            }
            for (i, &(mx, my, _)) in pts.iter().enumerate() {
                own[i] += t * samples
                    .iter()
                    .map(|&(sx, sy, w)| {
                        w * tif_rate(tool.0, tool.1, tool.2, tool.3, mx - sx, my - sy)
                    })
                    .sum::<f64>();
            }
        }
        // RMS about the mean (as HeightStats reports it).
        let mean = own.iter().sum::<f64>() / own.len() as f64;
        let rms = (own.iter().map(|h| (h - mean).powi(2)).sum::<f64>() / own.len() as f64).sqrt();
        let reported = listed[k]["removal_rms_nm"].as_f64().unwrap();
        assert!(
            (rms / reported - 1.0).abs() < RMS_TOL,
            "tool {k}: RMS {rms} vs {reported}"
        );
        for (a, b) in removal.iter_mut().zip(&own) {
            *a += b;
        }
    }
    // The residual after both tools, centred (free piston), against report.json.
    let m = pts.len() as f64;
    let c = pts.iter().zip(&removal).map(|(p, h)| h - p.2).sum::<f64>() / m;
    let rms = (pts
        .iter()
        .zip(&removal)
        .map(|(p, h)| (p.2 - h + c).powi(2))
        .sum::<f64>()
        / m)
        .sqrt();
    let reported = report["rms_after_nm"].as_f64().unwrap();
    let before = report["rms_before_nm"].as_f64().unwrap();
    assert!(
        (rms - reported).abs() <= RMS_TOL * before,
        "{rms} vs {reported}"
    );
    assert!(rms < 0.2 * before, "{rms} of {before}");
}

#[test]
fn mismatched_tool_flags_are_refused() {
    let run = preston_cmd()
        .args([
            "solve", "--map", "m.csv", "--tif", "a.csv", "--tif", "b.csv", "--dwell", "d.csv",
            "--v-max", "100", "--out", "x",
        ])
        .output()
        .unwrap();
    assert_eq!(
        run.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(String::from_utf8_lossy(&run.stderr).contains("--dwell"));
}
