//! The program the machine runs delivers the plan: `preston nc` timed from the G-code text alone,
//! `preston simulate --program` against the swept plan, dialects, feed modes and output files.

mod common;

use common::{csv_rows, data, ok, preston, read_json, s};
use std::path::{Path, PathBuf};

/// An independent reading of an ISO per-minute program: for every `(DWELL j ...)` marker, the
/// time of the `G01` blocks up to the next marker, as block length / F (absolute XYZ words).
fn stretch_times_from_text(text: &str) -> Vec<f64> {
    let mut pos: Option<[f64; 3]> = None;
    let mut times: Vec<f64> = Vec::new();
    let mut in_dwell = false;
    for line in text.lines() {
        if line.starts_with("(DWELL ") {
            times.push(0.0);
            in_dwell = true;
            continue;
        }
        if line.starts_with("(END DWELL") {
            in_dwell = false;
            continue;
        }
        if line.starts_with('(') || line.starts_with('%') {
            continue;
        }
        let mut p = pos.unwrap_or([0.0; 3]);
        let mut f = None;
        let mut linear = false;
        for w in line.split_whitespace() {
            let (k, v) = w.split_at(1);
            match k {
                "G" => linear = v == "01" || v == "1",
                "X" => p[0] = v.parse().unwrap(),
                "Y" => p[1] = v.parse().unwrap(),
                "Z" => p[2] = v.parse().unwrap(),
                "F" => f = Some(v.parse::<f64>().unwrap()),
                _ => {}
            }
        }
        if let (true, true, Some(prev), Some(f)) = (in_dwell, linear, pos, f) {
            let d =
                ((p[0] - prev[0]).powi(2) + (p[1] - prev[1]).powi(2) + (p[2] - prev[2]).powi(2))
                    .sqrt();
            *times.last_mut().unwrap() += 60.0 * d / f;
        }
        pos = Some(p);
    }
    times
}

#[test]
fn sample_job_program_delivers_every_dwell_and_simulates_like_the_plan() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("solve");
    ok(&preston(&[
        "solve",
        "--job",
        s(&data("job_point_1mm.toml")),
        "--out",
        s(&out),
    ]));
    let dwell = out.join("dwell.csv");
    let report = read_json(&out.join("report.json"));
    assert!(
        report["machining_time_s"].as_f64().unwrap() >= report["total_dwell_s"].as_f64().unwrap()
    );
    // Machinability keys, recomputed independently from dwell.csv and the map.
    let (_, plan_rows) = csv_rows(&dwell);
    let ratio = plan_rows
        .windows(2)
        .filter(|w| w[0][4] > 0.0 && w[1][4] > 0.0)
        .map(|w| (w[0][4] / w[1][4]).max(w[1][4] / w[0][4]))
        .fold(1.0, f64::max);
    let got = report["max_neighbour_feed_ratio"].as_f64().unwrap();
    assert!((got - ratio).abs() <= 1e-9 * ratio, "{got} vs {ratio}");
    let (_, map_rows) = csv_rows(&data("mirror_error_118x8mm.csv"));
    // The map is a 0.32 mm grid: a dwell point is off the map when no map point is within 0.32 mm.
    let outside: f64 = plan_rows
        .iter()
        .filter(|d| {
            map_rows
                .iter()
                .all(|m| (m[0] - d[0]).hypot(m[1] - d[1]) > 0.32 + 1e-9)
        })
        .map(|d| d[3])
        .sum();
    let got = report["dwell_outside_map_s"].as_f64().unwrap();
    assert!(
        (got - outside).abs() <= 1e-9 * outside.max(1.0),
        "{got} vs {outside}"
    );
    // `--out` into a directory that does not exist yet.
    let prog = d.path().join("nc/new/program.nc");
    let msg = ok(&preston(&["nc", "--dwell", s(&dwell), "--out", s(&prog)]));
    assert!(msg.contains("program as written"), "{msg}");
    let text = std::fs::read_to_string(&prog).unwrap();
    let (_, plan) = csv_rows(&dwell);
    let got = stretch_times_from_text(&text);
    assert_eq!(got.len(), plan.len());
    let mut total = (0.0, 0.0);
    for (j, (t, row)) in got.iter().zip(&plan).enumerate() {
        let want = row[3];
        assert!(
            (t - want).abs() <= 0.005 * want + 1e-3,
            "stretch {j}: {t} s in the program for {want} s planned"
        );
        total.0 += t;
        total.1 += want;
    }
    assert!((total.0 - total.1).abs() <= 1e-3 * total.1, "{total:?}");

    // The program as the machine runs it against the plan swept continuously.
    let (map, tif) = (
        data("mirror_error_118x8mm.csv"),
        data("tif_fluid_jet_10mm.csv"),
    );
    let sim = |extra: &[&str], dir: &str| {
        let o = d.path().join(dir);
        let mut a = vec![
            "simulate",
            "--map",
            s(&map),
            "--tif",
            s(&tif),
            "--out",
            s(&o),
        ];
        a.extend_from_slice(extra);
        ok(&preston(&a));
        o
    };
    let p = sim(&["--program", s(&prog)], "simprog");
    let c = sim(&["--dwell", s(&dwell), "--motion", "continuous"], "simcont");
    let (rp, rc) = (
        read_json(&p.join("report.json")),
        read_json(&c.join("report.json")),
    );
    let (a, b) = (
        rp["rms_after_nm"].as_f64().unwrap(),
        rc["rms_after_nm"].as_f64().unwrap(),
    );
    assert!(
        (a - b).abs() <= 0.02 * b,
        "program {a} nm vs plan swept {b} nm"
    );
    for key in ["rms_before_nm", "pv_after_nm", "total_dwell_s", "m", "n"] {
        assert!(rp.get(key).is_some(), "report.json lacks {key}");
    }
    let (header, ex) = csv_rows(&p.join("executed_dwell.csv"));
    assert_eq!(header, "x_mm,y_mm,planned_dwell_s,executed_dwell_s");
    assert_eq!(ex.len(), plan.len());
    for (e, row) in ex.iter().zip(&plan) {
        // The markers carry the point to the program's 4 decimals and the dwell to 7
        // significant digits.
        assert!((e[0] - row[0]).abs() <= 0.5e-4 && (e[1] - row[1]).abs() <= 0.5e-4);
        assert!(
            (e[2] - row[3]).abs() <= 5e-7 * row[3] + 5e-10,
            "{} vs {}",
            e[2],
            row[3]
        );
        assert!((e[3] - e[2]).abs() <= 0.005 * e[2] + 1e-3);
    }
}

/// A 21 x 5 serpentine at 1 mm pitch over a 30 x 14 mm map, Gaussian TIF sigma 2 mm.
fn raster_case(dir: &Path, dwell_of: impl Fn(usize) -> f64) -> (PathBuf, PathBuf) {
    let mut m = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..15 {
        for ix in 0..31 {
            m.push_str(&format!(
                "{},{},{}\n",
                ix as f64 - 5.0,
                iy as f64 - 5.0,
                50.0
            ));
        }
    }
    let map = dir.join("map.csv");
    std::fs::write(&map, m).unwrap();
    let mut t = String::from("x_mm,y_mm,dwell_s\n");
    let mut j = 0;
    for r in 0..5 {
        for c in 0..21 {
            let c = if r % 2 == 0 { c } else { 20 - c };
            t.push_str(&format!("{c},{},{}\n", 2 * r, dwell_of(j)));
            j += 1;
        }
    }
    let dwell = dir.join("dwell.csv");
    std::fs::write(&dwell, t).unwrap();
    (map, dwell)
}

const GAUSSIAN: [&str; 4] = ["--gaussian-sigma-mm", "2", "--gaussian-peak-nm-per-s", "10"];

#[test]
fn simulated_constant_feed_program_equals_the_continuous_sweep() {
    let d = tempfile::tempdir().unwrap();
    // Constant feed along the lines (1 mm in 0.5 s); the 2 mm line changes carry 1 s.
    let (map, dwell) = raster_case(d.path(), |_| 0.5);
    let prog = d.path().join("p.nc");
    ok(&preston(&["nc", "--dwell", s(&dwell), "--out", s(&prog)]));
    let run = |extra: &[&str], name: &str| {
        let o = d.path().join(name);
        let mut a = vec!["simulate", "--map", s(&map), "--out", s(&o)];
        a.extend_from_slice(&GAUSSIAN);
        a.extend_from_slice(extra);
        ok(&preston(&a));
        csv_rows(&o.join("residual.csv")).1
    };
    let p = run(&["--program", s(&prog), "--sample-step-mm", "0.02"], "p");
    let c = run(
        &[
            "--dwell",
            s(&dwell),
            "--motion",
            "continuous",
            "--samples-per-point",
            "64",
        ],
        "c",
    );
    assert_eq!(p.len(), c.len());
    // residual.csv: x_mm,y_mm,z_nm,removal_nm,residual_nm.
    let peak = c.iter().map(|r| r[3]).fold(0.0, f64::max);
    assert!(peak > 1.0);
    for (a, b) in p.iter().zip(&c) {
        assert!(
            (a[3] - b[3]).abs() <= 1e-4 * peak,
            "at ({}, {}): {} vs {}",
            a[0],
            a[1],
            a[3],
            b[3]
        );
    }
    // With an acceleration limit the corners take longer than planned; the stretch times say so.
    let o = d.path().join("acc");
    let mut a = vec![
        "simulate",
        "--map",
        s(&map),
        "--program",
        s(&prog),
        "--a-max-mm-per-s2",
        "5",
        "--out",
        s(&o),
    ];
    a.extend_from_slice(&GAUSSIAN);
    ok(&preston(&a));
    let (_, ex) = csv_rows(&o.join("executed_dwell.csv"));
    assert!(ex.iter().all(|r| r[3] >= r[2] * (1.0 - 1e-9)));
    // A start from rest to 2 mm/s at 5 mm/s^2 over the first stretch: 0.4 mm of ramp take 0.4 s
    // instead of 0.2 s.
    assert!((ex[0][3] - ex[0][2] - 0.2).abs() < 1e-6, "{:?}", ex[0]);
}

#[test]
fn dialects_feed_modes_and_program_checks() {
    let d = tempfile::tempdir().unwrap();
    let (_, dwell) = raster_case(d.path(), |j| 0.2 + 0.05 * (j % 7) as f64);
    let sin = d.path().join("sin.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        s(&dwell),
        "--dialect",
        "sinumerik",
        "--out",
        s(&sin),
    ]));
    let text = std::fs::read_to_string(&sin).unwrap();
    assert!(!text.contains('('));
    assert!(text.contains("G71") && text.contains("; DWELL 0 0.2000000 S AT 0.0000 0.0000"));
    let inv = d.path().join("inv.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        s(&dwell),
        "--dialect",
        "fanuc",
        "--feed-mode",
        "inverse-time",
        "--out",
        s(&inv),
    ]));
    let text = std::fs::read_to_string(&inv).unwrap();
    assert!(text.contains("G93") && text.contains("O1000"));
    // Inverse time: each feed block lasts 60 / F s; together they make the machining time.
    let sum: f64 = text
        .lines()
        .filter(|l| l.contains(" G01 "))
        .map(|l| {
            let f = l.split_whitespace().find(|w| w.starts_with('F')).unwrap();
            60.0 / f[1..].parse::<f64>().unwrap()
        })
        .sum();
    let stated: f64 = text
        .lines()
        .find(|l| l.starts_with("(MACHINING TIME"))
        .unwrap()
        .split_whitespace()
        .nth(2)
        .unwrap()
        .parse()
        .unwrap();
    assert!((sum - stated).abs() <= 1e-3 * stated, "{sum} vs {stated}");
    // Both read back by the simulator with the dialect from the header.
    let (map, _) = raster_case(d.path(), |_| 0.5);
    for p in [&sin, &inv] {
        let o = d
            .path()
            .join(format!("sim-{}", p.file_name().unwrap().to_str().unwrap()));
        let mut a = vec![
            "simulate",
            "--map",
            s(&map),
            "--program",
            s(p),
            "--out",
            s(&o),
        ];
        a.extend_from_slice(&GAUSSIAN);
        ok(&preston(&a));
        let (_, ex) = csv_rows(&o.join("executed_dwell.csv"));
        assert_eq!(ex.len(), 105);
        assert!(ex.iter().all(|r| (r[3] - r[2]).abs() <= 2e-4 * r[2]));
    }
    // Files are created with the umask, like any other file the user creates.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let plain = d.path().join("plain");
        std::fs::File::create(&plain).unwrap();
        let mode = |q: &Path| std::fs::metadata(q).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&sin), mode(&plain));
        assert_eq!(mode(&sin.with_extension("csv")), mode(&plain));
    }
    // Blocks faster than the controller's block rate are merged along the straight lines and
    // refused at the first corner (point 20, the end of the first line), naming it; nothing is
    // written.
    let bad = d.path().join("bad.nc");
    let o = preston(&[
        "nc",
        "--dwell",
        s(&dwell),
        "--min-block-time-ms",
        "500",
        "--out",
        s(&bad),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("dwell point 20") && e.contains("500 ms"), "{e}");
    assert!(!bad.exists());
    // A program with no feed move and no pause touches nothing (a program without dwell
    // markers is otherwise simulated as written, `shop_cli.rs`).
    let plain_prog = d.path().join("plain.nc");
    std::fs::write(&plain_prog, "G0 X0 Y0 Z0\nG0 X5\nM30\n").unwrap();
    let mut a = vec![
        "simulate",
        "--map",
        s(&map),
        "--program",
        s(&plain_prog),
        "--out",
    ];
    let out = d.path().join("nomark");
    a.push(s(&out));
    a.extend_from_slice(&GAUSSIAN);
    let o = preston(&a);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("nothing touches the part"));
}
