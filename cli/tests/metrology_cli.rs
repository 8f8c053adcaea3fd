//! Measured maps in, end to end: one synthetic surface with NaN pixels written in every format
//! Preston reads gives the same points and statistics; form-term removal against an independent
//! least-squares solution; Zernike fits against the coefficients that built the map; broken
//! binary files exit 2 naming file, place and cause.

mod common;

use common::{ok, preston, s, stdout_json};
use preston_io::metrology::{
    write_4d_h5, write_npy, write_zygo_dat, write_zygo_datx, DatHeader, DatxUnit, DAT_NO_DATA,
};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// Heights and statistics that every reader must agree on, relative.
const READER_REL_TOL: f64 = 1e-9;
/// Lateral positions, mm.
const POSITION_TOL_MM: f64 = 1e-9;
/// Detrended heights against the independent least-squares residual, nm.
const DETREND_TOL_NM: f64 = 1e-9;
/// Recovered Zernike coefficient, relative.
const ZERNIKE_REL_TOL: f64 = 1e-9;

/// `x_mm,y_mm,z_nm` rows of a CSV written by Preston, keyed by position (1e-6 mm bins).
fn read_points(path: &Path) -> BTreeMap<(i64, i64), (f64, f64, f64)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("x_mm,y_mm,z_nm"));
    lines
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|c| c.parse().unwrap()).collect();
            (
                ((v[0] * 1e6).round() as i64, (v[1] * 1e6).round() as i64),
                (v[0], v[1], v[2]),
            )
        })
        .collect()
}

/// The MetroPro header of the synthetic surface: 0.25 mm pixels, 632.8 nm, phase code 1.
const NX: usize = 60;
const NY: usize = 50;
fn header() -> DatHeader {
    DatHeader {
        nx: NX as u16,
        ny: NY as u16,
        lateral_resolution_m: 2.5e-4,
        wavelength_m: 632.8e-9,
        scale_factor: 0.5,
        obliquity: 1.0,
        phase_res: 1,
    }
}

/// Phase counts of the surface (row-major, first row on top), with 5% no-data pixels.
fn counts() -> Vec<Option<i32>> {
    (0..NX * NY)
        .map(|k| {
            let (i, j) = ((k / NX) as f64, (k % NX) as f64);
            // A deterministic scatter of 150 holes (5% of 3000 pixels).
            if (k * 7919) % 20 == 3 {
                None
            } else {
                Some((3000.0 * (0.21 * j).sin() + 2000.0 * (0.13 * i).cos() + 40.0 * j) as i32)
            }
        })
        .collect()
}

#[test]
fn every_reader_gives_the_same_points_and_rms() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let q_nm = 0.5 * 632.8e-9 / 32768.0 * 1e9;
    let c = counts();
    assert_eq!(c.iter().filter(|v| v.is_none()).count(), NX * NY / 20);
    let z_nm: Vec<f64> = c
        .iter()
        .map(|v| v.map_or(f64::NAN, |n| f64::from(n) * q_nm))
        .collect();
    let pitch = 0.25;
    let pos = |k: usize| {
        let (i, j) = ((k / NX) as f64, (k % NX) as f64);
        (
            (j - 0.5 * (NX as f64 - 1.0)) * pitch,
            (0.5 * (NY as f64 - 1.0) - i) * pitch,
        )
    };
    // The reference: valid points and the NaN-aware population standard deviation.
    let valid: Vec<(f64, f64, f64)> = (0..NX * NY)
        .filter(|&k| z_nm[k].is_finite())
        .map(|k| (pos(k).0, pos(k).1, z_nm[k]))
        .collect();
    let n = valid.len() as f64;
    let mean = valid.iter().map(|p| p.2).sum::<f64>() / n;
    let std = (valid.iter().map(|p| (p.2 - mean).powi(2)).sum::<f64>() / n).sqrt();

    let dat = d.join("s.dat");
    let phase: Vec<i32> = c.iter().map(|v| v.unwrap_or(DAT_NO_DATA)).collect();
    write_zygo_dat(&dat, &header(), &phase).unwrap();
    let datx_nm = d.join("nm.datx");
    write_zygo_datx(&datx_nm, NX, NY, pitch, &z_nm, DatxUnit::NanoMeters).unwrap();
    let datx_fr = d.join("fringes.datx");
    let fr = DatxUnit::Fringes {
        wavelength_m: 632.8e-9,
        scale: 0.5,
        obliquity: 1.0,
    };
    write_zygo_datx(&datx_fr, NX, NY, pitch, &z_nm, fr).unwrap();
    let h5 = d.join("m.h5");
    write_4d_h5(&h5, NX, NY, Some(pitch), &z_nm, 632.8).unwrap();
    let npy = d.join("g.npy");
    write_npy(&npy, NX, NY, &z_nm).unwrap();
    // Whitespace XYZ without a header (mm, mm, nm), NaN rows included.
    let xyz = d.join("s.xyz");
    let mut t = String::new();
    for (k, z) in z_nm.iter().enumerate() {
        let (x, y) = pos(k);
        writeln!(t, "{x}\t{y}   {z}").unwrap();
    }
    std::fs::write(&xyz, t).unwrap();
    // CSV in micrometres.
    let csv_um = d.join("um.csv");
    let mut t = String::from("x_um,y_um,z_um\n");
    for (k, zk) in z_nm.iter().enumerate() {
        let (x, y) = pos(k);
        let z = if zk.is_nan() {
            String::new()
        } else {
            format!("{}", zk / 1e3)
        };
        writeln!(t, "{},{},{z}", x * 1e3, y * 1e3).unwrap();
    }
    std::fs::write(&csv_um, t).unwrap();

    let cases: Vec<(&Path, Vec<&str>, &str)> = vec![
        (&dat, vec![], "zygo-dat"),
        (&datx_nm, vec![], "zygo-datx"),
        (&datx_fr, vec![], "zygo-datx"),
        (&h5, vec![], "four-d"),
        (&npy, vec!["--pitch-mm", "0.25"], "npy"),
        (&xyz, vec![], "xyz"),
        (&csv_um, vec![], "csv"),
    ];
    for (file, extra, format) in cases {
        let out_csv = d.join(format!(
            "{}.csv",
            file.file_name().unwrap().to_str().unwrap()
        ));
        let mut args = vec!["map", "convert", "--map", s(file), "--out", s(&out_csv)];
        args.extend(extra);
        let out = preston(&args);
        ok(&out);
        let j = stdout_json(&out);
        let name = file.display().to_string();
        assert_eq!(j["format"], format, "{name}");
        assert_eq!(j["points"], valid.len(), "{name}");
        assert_eq!(j["invalid_points"], NX * NY - valid.len(), "{name}");
        let rms = j["rms_nm"].as_f64().unwrap();
        eprintln!(
            "{format}: {} points, rms {rms} nm vs NaN-aware std {std} nm (relative {:.1e})",
            j["points"],
            (rms - std).abs() / std
        );
        assert!(
            (rms - std).abs() <= READER_REL_TOL * std,
            "{name}: rms {rms} vs {std}"
        );
        if let Some(p) = j["pitch_mm"].as_f64() {
            assert!((p - pitch).abs() < POSITION_TOL_MM, "{name}: pitch {p}");
        }
        let pts = read_points(&out_csv);
        assert_eq!(pts.len(), valid.len(), "{name}");
        for &(x, y, z) in &valid {
            let key = ((x * 1e6).round() as i64, (y * 1e6).round() as i64);
            let (px, py, pz) = pts[&key];
            assert!((px - x).abs() < POSITION_TOL_MM && (py - y).abs() < POSITION_TOL_MM);
            assert!(
                (pz - z).abs() <= READER_REL_TOL * z.abs().max(std),
                "{name}: z {pz} vs {z} at ({x}, {y})"
            );
        }
        let stderr = String::from_utf8_lossy(&out.stderr);
        if file == csv_um.as_path() {
            assert!(stderr.contains("x_um converted from um to mm"), "{stderr}");
        }
    }

    // The same .datx through `preston solve`: rms_before_nm is the NaN-aware standard deviation
    // and the map input is reported.
    let out_dir = d.join("solve");
    let out = preston(&[
        "solve",
        "--map",
        s(&datx_fr),
        "--gaussian-sigma-mm",
        "0.8",
        "--gaussian-peak-nm-per-s",
        "10",
        "--raster-pitch-mm",
        "1",
        "--v-max",
        "3000",
        "--accept-best-iterate",
        "--out",
        s(&out_dir),
    ]);
    ok(&out);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("report.json")).unwrap())
            .unwrap();
    let rms = report["rms_before_nm"].as_f64().unwrap();
    assert!((rms - std).abs() <= READER_REL_TOL * std, "{rms} vs {std}");
    assert_eq!(report["skipped_rows"], NX * NY - valid.len());
    assert_eq!(report["map_input"]["format"], "zygo-datx");
}

#[test]
fn aperture_and_removal_reach_solve_and_its_report() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // A 21 x 21 grid at 1 mm with a tilt of 0.5 nm/mm in x and a bump.
    let map = d.join("m.csv");
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    let mut inside = 0;
    for i in -10..=10 {
        for j in -10..=10 {
            let (x, y) = (f64::from(i), f64::from(j));
            let z = 0.5 * x + 4.0 * (-(x * x + y * y) / 20.0).exp();
            if (x - 1.0).powi(2) + y * y <= 64.0 {
                inside += 1;
            }
            writeln!(t, "{x},{y},{z}").unwrap();
        }
    }
    std::fs::write(&map, t).unwrap();
    let out_dir = d.join("o");
    let out = preston(&[
        "solve",
        "--map",
        s(&map),
        "--aperture",
        "circle:8@1,0",
        "--remove",
        "piston,tilt",
        "--gaussian-sigma-mm",
        "1",
        "--gaussian-peak-nm-per-s",
        "10",
        "--raster-pitch-mm",
        "1",
        "--v-max",
        "3000",
        // The discrete simulation below models the TIF at the dwell points.
        "--influence",
        "point",
        "--accept-best-iterate",
        "--out",
        s(&out_dir),
    ]);
    ok(&out);
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(r["m"], inside);
    assert_eq!(r["map_input"]["outside_aperture"], 441 - inside);
    let terms = r["map_input"]["removed"]["terms"].as_array().unwrap();
    assert_eq!(terms.len(), 3);
    let noll: Vec<u64> = terms.iter().map(|t| t["noll"].as_u64().unwrap()).collect();
    assert_eq!(noll, vec![1, 2, 3]);
    // The map is symmetric about y = 0, so the y tilt (Noll Z3) is zero.
    assert!(terms[2]["coefficient_nm"].as_f64().unwrap().abs() < 1e-9);
    let residual = std::fs::read_to_string(out_dir.join("residual.csv")).unwrap();
    assert_eq!(residual.lines().count(), inside + 1);
    // `simulate` with the same map flags reads the same map: the discrete simulation of the
    // solve's dwell program reproduces its residual statistics.
    let sim_dir = d.join("sim");
    let out = preston(&[
        "simulate",
        "--map",
        s(&map),
        "--aperture",
        "circle:8@1,0",
        "--remove",
        "piston,tilt",
        "--gaussian-sigma-mm",
        "1",
        "--gaussian-peak-nm-per-s",
        "10",
        "--dwell",
        s(&out_dir.join("dwell.csv")),
        "--motion",
        "discrete",
        "--out",
        s(&sim_dir),
    ]);
    ok(&out);
    let sim: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sim_dir.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(sim["m"], inside);
    for key in ["rms_before_nm", "rms_after_nm"] {
        let (a, b) = (r[key].as_f64().unwrap(), sim[key].as_f64().unwrap());
        assert!(
            (a - b).abs() <= 1e-9 * a.abs().max(1.0),
            "{key}: {a} vs {b}"
        );
    }
    assert_eq!(sim["map_input"]["removed"], r["map_input"]["removed"]);
    // Bad aperture text exits 2 with the accepted forms.
    let out = preston(&[
        "map",
        "convert",
        "--map",
        s(&map),
        "--aperture",
        "hexagon:3",
        "--out",
        s(&d.join("x.csv")),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("circle"));
}

/// The holed 100 mm disk of the form-removal target: 1 mm pixels inside r <= 50 mm, less a
/// 12 mm hole and a scatter of dropouts.
fn holed_disk_csv(path: &Path, z: impl Fn(f64, f64) -> f64) -> Vec<(f64, f64, f64)> {
    let mut pts = Vec::new();
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for i in -50..=50 {
        for j in -50..=50 {
            let (x, y) = (f64::from(i), f64::from(j));
            let hole = (x - 10.0).hypot(y + 15.0) < 6.0 || (i * 7 + j * 3_i32).rem_euclid(23) == 0;
            if x.hypot(y) <= 50.0 {
                if hole {
                    writeln!(t, "{x},{y},nan").unwrap();
                } else {
                    let v = z(x, y);
                    pts.push((x, y, v));
                    writeln!(t, "{x},{y},{v}").unwrap();
                }
            }
        }
    }
    std::fs::write(path, t).unwrap();
    pts
}

/// `5^(1/2) (6 rho^4 - 6 rho^2 + 1)`, Noll Z11 on a 50 mm radius.
fn z11(x: f64, y: f64) -> f64 {
    let r2 = (x * x + y * y) / 2500.0;
    5f64.sqrt() * (6.0 * r2 * r2 - 6.0 * r2 + 1.0)
}

/// Least squares by the normal equations of `[1, x, y, x^2 + y^2]` and Gaussian elimination with
/// partial pivoting: an independent reference for the detrended heights.
fn plane_power_residual(pts: &[(f64, f64, f64)]) -> Vec<f64> {
    let basis = |x: f64, y: f64| [1.0, x, y, x * x + y * y];
    let mut a = [[0.0f64; 5]; 4];
    for &(x, y, z) in pts {
        let b = basis(x, y);
        for r in 0..4 {
            for c in 0..4 {
                a[r][c] += b[r] * b[c];
            }
            a[r][4] += b[r] * z;
        }
    }
    for col in 0..4 {
        let piv = (col..4)
            .max_by(|&p, &q| a[p][col].abs().total_cmp(&a[q][col].abs()))
            .unwrap();
        a.swap(col, piv);
        for r in 0..4 {
            if r != col {
                let f = a[r][col] / a[col][col];
                let pivot_row = a[col];
                for (v, p) in a[r].iter_mut().zip(pivot_row).skip(col) {
                    *v -= f * p;
                }
            }
        }
    }
    let coef: Vec<f64> = (0..4).map(|r| a[r][4] / a[r][r]).collect();
    pts.iter()
        .map(|&(x, y, z)| {
            let b = basis(x, y);
            z - (0..4).map(|k| coef[k] * b[k]).sum::<f64>()
        })
        .collect()
}

#[test]
fn detrend_and_zernike_fit_on_a_holed_disk() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let map = d.join("disk.csv");
    let pts = holed_disk_csv(&map, |x, y| {
        7.0 + 0.04 * x - 0.03 * y + 30.0 * (x * x + y * y) / 2500.0 + 20.0 * z11(x, y)
    });
    let out_csv = d.join("detrended.csv");
    let out = preston(&[
        "map",
        "detrend",
        "--map",
        s(&map),
        "--remove",
        "piston,tilt,power",
        "--out",
        s(&out_csv),
    ]);
    ok(&out);
    let got = read_points(&out_csv);
    let want = plane_power_residual(&pts);
    assert_eq!(got.len(), pts.len());
    let worst = pts
        .iter()
        .zip(&want)
        .map(|(&(x, y, _), w)| {
            (got[&((x * 1e6).round() as i64, (y * 1e6).round() as i64)].2 - w).abs()
        })
        .fold(0.0, f64::max);
    eprintln!("map detrend: largest difference from the normal-equation residual {worst:.2e} nm");
    for (&(x, y, _), w) in pts.iter().zip(&want) {
        let g = got[&((x * 1e6).round() as i64, (y * 1e6).round() as i64)].2;
        assert!((g - w).abs() < DETREND_TOL_NM, "({x}, {y}): {g} vs {w}");
    }
    // What is left is pure spherical: 20 nm Z11 less its projection on power and piston.
    let out = preston(&[
        "map",
        "fit",
        "--map",
        s(&map),
        "--basis",
        "zernike-noll",
        "--terms",
        "37",
        "--norm-radius-mm",
        "50",
    ]);
    ok(&out);
    let j = stdout_json(&out);
    let c = j["coefficients_nm"].as_array().unwrap();
    assert_eq!(c.len(), 37);
    let z11c = c[10].as_f64().unwrap();
    eprintln!(
        "map fit: Z11 = {z11c} nm (relative error {:.2e}), residual rms {} nm",
        (z11c - 20.0).abs() / 20.0,
        j["rms_nm"]
    );
    assert!(
        (z11c - 20.0).abs() <= ZERNIKE_REL_TOL * 20.0,
        "Z11 = {z11c}"
    );
    assert!(j["rms_nm"].as_f64().unwrap() < 1e-9);
    assert!(j["pv_nm"].as_f64().unwrap() < 1e-8);
    // Fringe order puts spherical at Z9.
    let out = preston(&[
        "map",
        "fit",
        "--map",
        s(&map),
        "--basis",
        "zernike-fringe",
        "--terms",
        "16",
        "--norm-radius-mm",
        "50",
    ]);
    ok(&out);
    let z9 = stdout_json(&out)["coefficients_nm"][8].as_f64().unwrap();
    assert!(
        (z9 - 20.0).abs() <= ZERNIKE_REL_TOL * 20.0,
        "Fringe Z9 = {z9}"
    );
    // Detrend without --remove is refused.
    let out = preston(&["map", "detrend", "--map", s(&map), "--out", s(&out_csv)]);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn broken_binary_files_exit_2_naming_file_place_and_cause() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let phase: Vec<i32> = counts().iter().map(|v| v.unwrap_or(DAT_NO_DATA)).collect();
    let dat = d.join("cut.dat");
    write_zygo_dat(&dat, &header(), &phase).unwrap();
    let b = std::fs::read(&dat).unwrap();
    std::fs::write(&dat, &b[..b.len() - 1000]).unwrap();
    let datx = d.join("cut.datx");
    let z = vec![1.0; NX * NY];
    write_zygo_datx(&datx, NX, NY, 0.1, &z, DatxUnit::NanoMeters).unwrap();
    let b = std::fs::read(&datx).unwrap();
    std::fs::write(&datx, &b[..b.len() * 2 / 3]).unwrap();
    let h5_as_dat = d.join("foreign.dat");
    std::fs::write(&h5_as_dat, &b).unwrap();
    for (file, want) in [
        (&dat, vec!["cut.dat", "byte 834", "truncated"]),
        (&datx, vec!["cut.datx"]),
        (&h5_as_dat, vec!["foreign.dat", "magic"]),
    ] {
        let out = preston(&[
            "map",
            "convert",
            "--map",
            s(file),
            "--out",
            s(&d.join("o.csv")),
        ]);
        assert_eq!(out.status.code(), Some(2), "{}", file.display());
        let err = String::from_utf8(out.stderr).expect("stderr is text, not bytes");
        for w in want {
            assert!(err.contains(w), "{w} missing: {err}");
        }
        assert!(
            err.len() < 600 && err.chars().all(|c| !c.is_control() || c == '\n'),
            "{err}"
        );
        assert!(!d.join("o.csv").exists());
    }
    // The same bytes read as a datx with --map-format: the HDF5 reader names its cause.
    let out = preston(&[
        "map",
        "convert",
        "--map",
        s(&dat),
        "--map-format",
        "zygo-datx",
        "--out",
        s(&d.join("o.csv")),
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("HDF5"));
}

/// The spot target: 6 nm/s peak, sigma 1.2 mm, centre (0.3, -0.2) mm, 10 s dwell, 0.2 nm/mm
/// tilt between the measurements, 0.5 nm RMS noise, a NaN border.
const SPOT_PEAK: f64 = 6.0;
const SPOT_SIGMA_MM: f64 = 1.2;
/// Peak and FWHM, relative.
const SPOT_REL_TOL: f64 = 0.03;
/// Fitted sigma, relative.
const SIGMA_REL_TOL: f64 = 0.02;
/// Centroid after recentring, mm.
const CENTROID_TOL_MM: f64 = 0.02;

/// Standard normal samples from a fixed xorshift stream (Box-Muller).
fn normals(n: usize) -> Vec<f64> {
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut u = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        ((s >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let (a, b) = (u(), u());
            (-2.0 * a.ln()).sqrt() * (2.0 * std::f64::consts::PI * b).cos()
        })
        .collect()
}

#[test]
fn tif_from_a_measured_spot_meets_the_targets_and_solves_the_sample_job() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (before, after) = (d.join("before.xyz"), d.join("after.xyz"));
    let n = 121; // 0.1 mm pixels over +-6 mm
    let noise = normals(2 * n * n);
    let (mut tb, mut ta) = (String::new(), String::new());
    for i in 0..n {
        for j in 0..n {
            let (x, y) = (-6.0 + 0.1 * j as f64, -6.0 + 0.1 * i as f64);
            let border = i < 3 || j < 3 || i >= n - 3 || j >= n - 3;
            let g = SPOT_PEAK
                * (-((x - 0.3).powi(2) + (y + 0.2).powi(2)) / (2.0 * SPOT_SIGMA_MM.powi(2))).exp();
            let figure = 4.0 * (0.5 * x).sin() * (0.3 * y).cos();
            let k = i * n + j;
            let zb = figure + 0.5 * noise[2 * k];
            let za = figure - 10.0 * g + 0.2 * x + 0.5 * noise[2 * k + 1];
            writeln!(tb, "{x} {y} {zb}").unwrap();
            if border {
                writeln!(ta, "{x} {y} nan").unwrap();
            } else {
                writeln!(ta, "{x} {y} {za}").unwrap();
            }
        }
    }
    std::fs::write(&before, tb).unwrap();
    std::fs::write(&after, ta).unwrap();
    let tif = d.join("tif.csv");
    let out = preston(&[
        "tif",
        "spot",
        "--before",
        s(&before),
        "--after",
        s(&after),
        "--dwell-s",
        "10",
        "--remove",
        "tilt",
        "--crop-radius-mm",
        "4.5",
        "--recentre",
        "--fit",
        "gaussian",
        "--out",
        s(&tif),
    ]);
    ok(&out);
    let j = stdout_json(&out);
    eprintln!("tif spot summary: {j}");
    let peak = j["peak_rate_nm_per_s"].as_f64().unwrap();
    let fwhm = j["fwhm_mm"].as_f64().unwrap();
    let fwhm_true = 2.0 * (2.0 * 2f64.ln()).sqrt() * SPOT_SIGMA_MM; // 2.826 mm
    assert!(
        (peak - SPOT_PEAK).abs() <= SPOT_REL_TOL * SPOT_PEAK,
        "peak {peak}"
    );
    assert!(
        (fwhm - fwhm_true).abs() <= SPOT_REL_TOL * fwhm_true,
        "fwhm {fwhm} vs {fwhm_true}"
    );
    let c = &j["centroid_mm"];
    let (cx, cy) = (c[0].as_f64().unwrap(), c[1].as_f64().unwrap());
    assert!(cx.hypot(cy) < CENTROID_TOL_MM, "centroid ({cx}, {cy})");
    let sc = &j["spot_centroid_mm"];
    assert!((sc[0].as_f64().unwrap() - 0.3).abs() < 0.05, "{sc}");
    assert!((sc[1].as_f64().unwrap() + 0.2).abs() < 0.05, "{sc}");
    for key in ["sigma_x_mm", "sigma_y_mm"] {
        let v = j[key].as_f64().unwrap();
        assert!(
            (v - SPOT_SIGMA_MM).abs() <= SIGMA_REL_TOL * SPOT_SIGMA_MM,
            "{key} {v}"
        );
    }
    // Volume of the Gaussian: 2 pi A sigma^2 nm mm^2/s = 2 pi 6 1.44 1e-6 mm^3/s, x 60 per min.
    let vol = j["volume_rate_mm3_per_min"].as_f64().unwrap();
    let vol_true = 2.0 * std::f64::consts::PI * SPOT_PEAK * SPOT_SIGMA_MM.powi(2) * 1e-6 * 60.0;
    assert!(
        (vol - vol_true).abs() < 0.05 * vol_true,
        "{vol} vs {vol_true}"
    );

    // The TIF solves the sample job.
    let job = concat!(env!("CARGO_MANIFEST_DIR"), "/../data/job_point_1mm.toml");
    let out_dir = d.join("job");
    let out = preston(&[
        "solve",
        "--job",
        job,
        "--tif",
        s(&tif),
        "--out",
        s(&out_dir),
    ]);
    ok(&out);
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("report.json")).unwrap())
            .unwrap();
    assert_eq!(r["status"], "converged");
    assert!(r["rms_after_nm"].as_f64().unwrap() < r["rms_before_nm"].as_f64().unwrap());
}
