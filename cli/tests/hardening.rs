//! Hardening: every class of hostile or mistaken input is refused with exit 2, a short message and
//! little memory, before any output is touched; outputs are committed all together or not at all,
//! under a lock on their directory.
//!
//! Memory: on Linux each refused command runs with its address space capped
//! ([`ADDRESS_SPACE_KIB`], `ulimit -v`), so an allocation of the size the input implies would
//! abort the process (exit 134) instead of passing; the test then fails on the exit code.

mod common;

use common::{exe, preston, s, snapshot, write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Address-space cap for refused commands, KiB: 1 GiB of virtual memory (threads' stacks and
/// allocator arenas included), so the resident peak stays well under 512 MB.
const ADDRESS_SPACE_KIB: u64 = 1 << 20;
/// Largest stderr accepted for a refusal, bytes.
const MAX_STDERR: usize = 64 * 1024;

/// Runs preston with `args`, under the address-space cap on Linux.
fn capped(args: &[&str]) -> Output {
    capped_env(args, &[])
}

fn capped_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = if cfg!(target_os = "linux") {
        let mut c = Command::new("sh");
        c.arg("-c")
            .arg(format!(
                "ulimit -v {ADDRESS_SPACE_KIB} && exec \"$0\" \"$@\""
            ))
            .arg(exe());
        c
    } else {
        Command::new(exe())
    };
    c.args(args);
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// Asserts a refusal: exit 2 (not an abort), a short stderr holding every needle, no panic.
fn refused(o: &Output, needles: &[&str]) -> String {
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert_eq!(o.status.code(), Some(2), "exit {:?}: {err}", o.status);
    assert!(err.len() < MAX_STDERR, "stderr of {} bytes", err.len());
    assert!(!err.contains("panicked"), "{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks `{n}`: {err}");
    }
    err
}

/// A smooth 21 x 21 map over 20 x 20 mm (1 mm pitch).
fn smooth_map() -> String {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..21 {
        for ix in 0..21 {
            let (x, y) = (ix as f64, iy as f64);
            let z = 50.0 + 20.0 * (0.3 * x).sin() * (0.2 * y).cos();
            t.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    t
}

const GAUSSIAN: [&str; 6] = [
    "--gaussian-sigma-mm",
    "2",
    "--gaussian-peak-nm-per-s",
    "10",
    "--v-max",
    "2000",
];

fn solve_args<'a>(map: &'a str, extra: &[&'a str], out: &'a str) -> Vec<&'a str> {
    let mut a = vec!["solve", "--map", map];
    a.extend(GAUSSIAN);
    a.extend(extra);
    a.extend(["--out", out]);
    a
}

/// Sizes implied by arguments are checked against the memory budget before anything is
/// allocated: each argument is named with the size it implies and the limit.
#[test]
fn oversized_arguments_are_refused_before_allocating() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "m.csv", &smooth_map());
    let out = d.path().join("out");
    let o = out.to_str().unwrap();
    let dwell = write(
        d.path(),
        "d.csv",
        "x_mm,y_mm,dwell_s\n0,0,1\n1,0,1\n2,0,1\n",
    );
    let gauss = ["--gaussian-sigma-mm", "2", "--gaussian-peak-nm-per-s", "10"];
    let mut sim = vec!["simulate", "--map", s(&map), "--dwell", s(&dwell)];
    sim.extend(gauss);
    sim.extend([
        "--motion",
        "continuous",
        "--samples-per-point",
        "4000000000",
        "--out",
        o,
    ]);
    refused(
        &capped(&sim),
        &["--samples-per-point", "GB", "--max-memory-gb"],
    );
    let it = |extra: &[&str]| {
        let mut a = vec![
            "iterate",
            "--aperture-x-mm=0,10",
            "--aperture-y-mm=0,10",
            "--out",
            o,
        ];
        a.extend(gauss);
        a.extend(extra.iter().copied());
        capped(&a)
    };
    refused(
        &it(&["--grid", "100000,100000"]),
        &["--grid", "100000 x 100000"],
    );
    refused(
        &it(&["--pitch-mm", "1e-7"]),
        &["--pitch-mm", "over the limit"],
    );
    refused(
        &capped(&solve_args(s(&map), &["--raster-pitch-mm", "1e-5"], o)),
        &["--raster-pitch-mm", "over the limit"],
    );
    refused(
        &capped(&[
            "path",
            "raster",
            "--x-mm",
            "0,118",
            "--y-mm",
            "0,8",
            "--pitch-mm",
            "1e-6",
            "--out",
            &format!("{o}/p.csv"),
        ]),
        &["--pitch-mm", "over the limit"],
    );
    refused(
        &capped(&[
            "map",
            "fit",
            "--map",
            s(&map),
            "--basis",
            "legendre",
            "--terms",
            "1000000000000",
        ]),
        &["--terms", "over the limit"],
    );
    // Two stray dwell points 5 m away stretch the FFT operator's lattice to 5000 x 5000 cells of
    // 1 mm: refused under a 0.5 GB budget, naming the lattice.
    let mut stray = String::from("x_mm,y_mm\n");
    for k in 0..21 {
        stray.push_str(&format!("{k},10\n"));
    }
    stray.push_str("5000,10\n5000,5000\n");
    let stray = write(d.path(), "stray.csv", &stray);
    refused(
        &capped(&solve_args(
            s(&map),
            &[
                "--dwell",
                s(&stray),
                "--solver",
                "first-order",
                "--operator",
                "fft",
                "--max-memory-gb",
                "0.5",
            ],
            o,
        )),
        &["FFT", "cells", "over the limit of 0.500 GB"],
    );
    // The flag is global and checked itself.
    refused(
        &capped(&solve_args(
            s(&map),
            &["--raster-pitch-mm", "1", "--max-memory-gb", "-1"],
            o,
        )),
        &["--max-memory-gb"],
    );
    assert!(!out.exists(), "nothing may be written");
}

/// Text inputs: lines over the line limit and rows over the field limit are refused at their
/// line without being held whole; messages quote at most 80 characters of the input;
/// directories, devices and FIFOs are refused where a regular file is needed.
/// The assembled influence matrix is counted (one cheap pass over the dwell points) and checked
/// against the budget before its arrays exist: the sample job's R (about 2e6 candidate non-zeros,
/// 60 MB) under a 10 MB limit is refused naming it, and nothing is written.
#[test]
fn the_influence_matrix_is_budgeted_before_assembly() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let job = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/job_point_1mm.toml");
    let o = capped(&[
        "--max-memory-gb",
        "0.01",
        "solve",
        "--job",
        s(&job),
        "--out",
        out.to_str().unwrap(),
    ]);
    refused(&o, &["influence matrix R", "non-zeros", "--max-memory-gb"]);
    assert!(!out.join("dwell.csv").exists());
}

#[test]
fn hostile_files_are_refused_cheaply_with_short_messages() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("out");
    let o = out.to_str().unwrap();
    let long = "7".repeat(3 << 20);
    let cases: Vec<(PathBuf, Vec<&str>)> = vec![
        (
            write(
                d.path(),
                "long.csv",
                &format!("x_mm,y_mm,z_nm\n0,0,{long}\n"),
            ),
            vec!["line 2", "longer than 1048576 bytes"],
        ),
        (
            write(d.path(), "longhead.csv", &format!("x_mm,y_mm,z_nm{long}\n")),
            vec!["line 1", "longer than"],
        ),
        (
            write(
                d.path(),
                "commas.csv",
                &format!("x_mm,y_mm,z_nm\n0,0,1{}\n", ",".repeat(200_000)),
            ),
            vec!["line 2", "more than 1000 fields"],
        ),
        (
            write(d.path(), "long.xyz", &format!("0 0 1\n0 1 {long}\n")),
            vec!["line 2", "longer than"],
        ),
        (
            write(
                d.path(),
                "cell.csv",
                &format!("x_mm,y_mm,z_nm\n0,0,a{}\n", "b".repeat(5000)),
            ),
            vec!["line 2", "not a number"],
        ),
    ];
    for (file, needles) in &cases {
        let err = refused(
            &capped(&solve_args(s(file), &["--raster-pitch-mm", "1"], o)),
            needles,
        );
        for run in ["7".repeat(81), "b".repeat(81), ",".repeat(81)] {
            assert!(
                !err.contains(&run),
                "more than 80 characters quoted: {}",
                err.len()
            );
        }
    }
    // A lower line limit, given on the command line, applies.
    let short = write(d.path(), "short.csv", &smooth_map());
    refused(
        &capped(&solve_args(
            s(&short),
            &["--raster-pitch-mm", "1", "--max-line-bytes", "8"],
            o,
        )),
        &["line 1", "longer than 8 bytes"],
    );
    // A job file with a huge line, and one with a TOML error on a long line.
    let job = write(d.path(), "job.toml", &format!("[map]\nfile = \"{long}\"\n"));
    refused(
        &capped(&["solve", "--job", s(&job), "--out", o]),
        &["job.toml", "line 2", "longer than"],
    );
    let job = write(
        d.path(),
        "bad.toml",
        &format!("[map]\nfile = 1{}\n", "x".repeat(100_000)),
    );
    let err = refused(
        &capped(&["solve", "--job", s(&job), "--out", o]),
        &["bad.toml"],
    );
    assert!(!err.contains(&"x".repeat(81)), "{}", err.len());
    // Not regular files.
    refused(
        &capped(&solve_args("/dev/zero", &["--raster-pitch-mm", "1"], o)),
        &["/dev/zero", "a device", "regular file"],
    );
    refused(
        &capped(&solve_args(s(d.path()), &["--raster-pitch-mm", "1"], o)),
        &["a directory"],
    );
    let tif_dir = d.path().join("tif_dir");
    std::fs::create_dir(&tif_dir).unwrap();
    refused(
        &capped(&[
            "solve",
            "--map",
            s(&short),
            "--tif",
            s(&tif_dir),
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "2000",
            "--out",
            o,
        ]),
        &["a directory"],
    );
    for format in ["npy", "zygo-dat", "zygo-datx", "four-d", "xyz"] {
        refused(
            &capped(&[
                "map",
                "convert",
                "--map",
                "/dev/zero",
                "--map-format",
                format,
                "--pitch-mm",
                "1",
                "--out",
                o,
            ]),
            &["/dev/zero"],
        );
    }
    #[cfg(unix)]
    {
        let fifo = d.path().join("fifo.csv");
        let st = Command::new("mkfifo").arg(&fifo).status().unwrap();
        assert!(st.success());
        // Refused at once: opening a FIFO with no writer would block.
        refused(
            &capped(&solve_args(s(&fifo), &["--raster-pitch-mm", "1"], o)),
            &["FIFO"],
        );
    }
    assert!(!out.exists(), "nothing may be written");
}

/// Messages that say what is wrong: a semicolon-separated file is told about its delimiter (not
/// units); a duplicated TIF node names its line.
#[test]
fn wrong_delimiters_and_duplicate_tif_nodes_are_named() {
    let d = tempfile::tempdir().unwrap();
    let o = d.path().join("out");
    let semi = write(d.path(), "semi.csv", &smooth_map().replace(',', ";"));
    let err = refused(
        &capped(&solve_args(s(&semi), &["--raster-pitch-mm", "1"], s(&o))),
        &["semicolons", "comma-separated"],
    );
    assert!(!err.contains("convert"), "{err}");
    // A whitespace-separated file given as CSV is told to read it as XYZ, not to convert units.
    for sep in [" ", "\t", "  "] {
        let spaced = write(d.path(), "spaced.csv", &smooth_map().replace(',', sep));
        let err = refused(
            &capped(&solve_args(s(&spaced), &["--raster-pitch-mm", "1"], s(&o))),
            &["--map-format xyz"],
        );
        assert!(!err.contains("convert"), "{err}");
    }
    // The same with a comma header but semicolons in the rows.
    let mixed = write(
        d.path(),
        "mixed.csv",
        &format!(
            "x_mm,y_mm,z_nm\n{}",
            smooth_map().replace(',', ";").split_once('\n').unwrap().1
        ),
    );
    refused(
        &capped(&solve_args(s(&mixed), &["--raster-pitch-mm", "1"], s(&o))),
        &["line 2"],
    );
    let map = write(d.path(), "m.csv", &smooth_map());
    let tif = write(
        d.path(),
        "tif.csv",
        "x_mm,y_mm,rate_nm_per_s\n-1,-1,1\n0,-1,2\n1,-1,1\n-1,0,2\n0,0,4\n1,0,2\n-1,1,1\n0,1,2\n0,0,4\n1,1,1\n",
    );
    refused(
        &capped(&[
            "solve",
            "--map",
            s(&map),
            "--tif",
            s(&tif),
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "2000",
            "--out",
            s(&o),
        ]),
        &["tif.csv", "line 10", "line 6"],
    );
}

/// Values beyond the model's physical ranges are input errors naming their line, and leave the
/// previous outputs as they were; zero-length paths and zero feeds are refused before solving.
#[test]
fn values_beyond_the_physical_ranges_are_refused_at_their_line() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "m.csv", &smooth_map());
    let out = d.path().join("out");
    let o = out.to_str().unwrap();
    let first = preston(&solve_args(s(&map), &["--raster-pitch-mm", "1"], o));
    assert_eq!(
        first.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let before = snapshot(&out);
    let text = smooth_map();
    let mut lines: Vec<&str> = text.lines().collect();
    for (bad, needles) in [
        ("3,0,1e308", vec!["line 5", "z_nm", "physical range"]),
        ("3,0,-2e7", vec!["line 5", "z_nm"]),
        ("1e6,0,1", vec!["line 5", "x_mm"]),
        ("3,-1e300,1", vec!["line 5", "y_mm"]),
    ] {
        lines[4] = bad;
        let f = write(d.path(), "bad.csv", &(lines.join("\n") + "\n"));
        refused(
            &capped(&solve_args(s(&f), &["--raster-pitch-mm", "1"], o)),
            &needles,
        );
        assert_eq!(snapshot(&out), before, "{bad}: previous outputs changed");
    }
    // The same through the delimited-text reader (an .xyz file in um and nm).
    let xyz = write(
        d.path(),
        "m.xyz",
        "x_um y_um z_nm\n0 0 1\n1000 0 2\n0 1000 1e9\n",
    );
    refused(
        &capped(&["map", "convert", "--map", s(&xyz), "--out", o]),
        &["m.xyz", "line 4", "physical range"],
    );
    // Rates.
    let tif = write(
        d.path(),
        "tif.csv",
        "x_mm,y_mm,rate_nm_per_s\n0,0,1\n1,0,1e12\n0,1,1\n1,1,1\n",
    );
    refused(
        &capped(&[
            "solve",
            "--map",
            s(&map),
            "--tif",
            s(&tif),
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "2000",
            "--out",
            o,
        ]),
        &["line 3", "rate_nm_per_s"],
    );
    // Zero-length paths and zero feeds.
    let one = write(d.path(), "one.csv", "x_mm,y_mm\n5,5\n");
    refused(
        &capped(&solve_args(s(&map), &["--dwell", s(&one)], o)),
        &["one.csv", "length zero"],
    );
    let rep = write(d.path(), "rep.csv", "x_mm,y_mm\n0,0\n1,0\n1,0\n2,0\n");
    refused(
        &capped(&solve_args(s(&map), &["--dwell", s(&rep)], o)),
        &["rep.csv", "line 4", "line 3", "length zero"],
    );
    let rep = write(
        d.path(),
        "repd.csv",
        "x_mm,y_mm,dwell_s\n0,0,1\n1,0,1\n1,0,1\n",
    );
    refused(
        &capped(&[
            "nc",
            "--dwell",
            s(&rep),
            "--v-max",
            "2000",
            "--out",
            &format!("{o}/p.nc"),
        ]),
        &["repd.csv", "line 4", "line 3", "length zero"],
    );
    assert_eq!(snapshot(&out), before);
}

/// A flat map needs no dwell: the first-order solver's certificate stays finite and small, so
/// "converged" is never reported with an overflowing residual.
#[test]
fn a_flat_map_gets_a_finite_certificate() {
    let d = tempfile::tempdir().unwrap();
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..21 {
        for ix in 0..21 {
            t.push_str(&format!("{ix},{iy},25\n"));
        }
    }
    let map = write(d.path(), "flat.csv", &t);
    let out = d.path().join("out");
    let r = preston(&solve_args(
        s(&map),
        &[
            "--raster-pitch-mm",
            "1",
            "--solver",
            "first-order",
            "--rho",
            "0",
        ],
        s(&out),
    ));
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(matches!(r.status.code(), Some(0) | Some(3)), "{err}");
    let rep: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let text = rep.to_string();
    let kkt = text
        .split("\"kkt_residual\":")
        .nth(1)
        .and_then(|t| t.split([',', '}']).next())
        .and_then(|v| v.trim().parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no kkt_residual: {text}"));
    assert!(kkt.is_finite() && kkt < 1.0, "kkt_residual {kkt}");
    if text.contains("\"converged\"") {
        assert!(kkt <= 1e-3, "converged with kkt_residual {kkt}");
    }
}

/// Outputs are committed all together or not at all: a command that cannot write one of its
/// files (here a plot whose name is taken by a directory) leaves every previous output intact.
#[test]
fn a_failing_plot_leaves_every_previous_output() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "m.csv", &smooth_map());
    let dwell = write(
        d.path(),
        "d.csv",
        "x_mm,y_mm,dwell_s\n5,5,1\n10,5,2\n15,5,1\n",
    );
    let out = d.path().join("out");
    let args = |plots: bool| {
        let mut a = vec![
            "simulate".to_string(),
            "--map".into(),
            s(&map).into(),
            "--dwell".into(),
            s(&dwell).into(),
            "--gaussian-sigma-mm".into(),
            "2".into(),
            "--gaussian-peak-nm-per-s".into(),
            "10".into(),
            "--out".into(),
            s(&out).into(),
        ];
        if plots {
            a.push("--plots".into());
        }
        a
    };
    let first = Command::new(exe()).args(args(false)).output().unwrap();
    assert_eq!(
        first.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&first.stderr)
    );
    let before = snapshot(&out);
    std::fs::create_dir(out.join("residual.png")).unwrap();
    std::fs::write(
        d.path().join("d.csv"),
        "x_mm,y_mm,dwell_s\n5,5,3\n10,5,2\n15,5,1\n",
    )
    .unwrap();
    let r = Command::new(exe()).args(args(true)).output().unwrap();
    refused(&r, &["residual.png", "directory"]);
    std::fs::remove_dir(out.join("residual.png")).unwrap();
    assert_eq!(snapshot(&out), before, "outputs changed by a failed run");
    let names: Vec<String> = snapshot(&out).into_iter().map(|(n, _)| n).collect();
    assert!(names.iter().all(|n| !n.starts_with('.')), "{names:?}");
}

/// A second run into a directory another live run holds waits for it, then fails naming it; a
/// lock and temporary files left by killed runs are cleared by the next run; concurrent runs
/// into one directory leave one run's complete, consistent set.
#[cfg(target_os = "linux")]
#[test]
fn output_directories_are_locked_and_crash_leftovers_cleared() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "m.csv", &smooth_map());
    let out = d.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let o = out.to_str().unwrap();
    let mut holder = Command::new("sleep").arg("60").spawn().unwrap();
    std::fs::write(out.join(".preston.lock"), format!("{}\n", holder.id())).unwrap();
    let r = capped_env(
        &solve_args(s(&map), &["--raster-pitch-mm", "1"], o),
        &[("PRESTON_LOCK_WAIT_S", "0.3")],
    );
    refused(&r, &[&format!("process {}", holder.id()), "writing into"]);
    assert!(!out.join("dwell.csv").exists());
    holder.kill().unwrap();
    holder.wait().unwrap();
    // The holder is gone: its lock and a partial file of a killed run are cleared.
    let dead = 4_194_305u32; // above Linux's largest pid
    let stale = out.join(format!(".dwell.csv.preston-{dead}-AbCdEf.tmp"));
    std::fs::write(&stale, "x_mm,y_mm,ds_mm,dw").unwrap();
    let r = preston(&solve_args(s(&map), &["--raster-pitch-mm", "1"], o));
    assert_eq!(
        r.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&r.stderr)
    );
    assert!(!stale.exists() && !out.join(".preston.lock").exists());

    // Concurrent runs with different answers: dwell.csv and report.json always from one run.
    for round in 0..3 {
        let kids: Vec<_> = ["1", "2"]
            .iter()
            .map(|pitch| {
                Command::new(exe())
                    .args(solve_args(s(&map), &["--raster-pitch-mm", pitch], o))
                    .stderr(std::process::Stdio::null())
                    .stdout(std::process::Stdio::null())
                    .spawn()
                    .unwrap()
            })
            .collect();
        for mut k in kids {
            assert!(k.wait().unwrap().success(), "round {round}");
        }
        let rows = std::fs::read_to_string(out.join("dwell.csv"))
            .unwrap()
            .lines()
            .count()
            - 1;
        let rep: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap())
                .unwrap();
        let n = rep.to_string();
        assert!(
            rep["n"].as_u64() == Some(rows as u64),
            "round {round}: dwell.csv has {rows} rows, report {n}"
        );
        let leftovers: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().starts_with('.'))
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");
    }
}

/// Point sets that leave rigid motions undetermined are refused with exit 2 naming them: too
/// few points, points on one line, and coplanar points on a plane design (in-plane motions
/// free); holding those motions with --lock makes the registration well posed.
#[test]
fn registration_refuses_undetermined_motions() {
    let d = tempfile::tempdir().unwrap();
    let plane = write(d.path(), "plane.json", r#"{"type":"plane"}"#);
    let out = d.path().join("reg");
    let o = out.to_str().unwrap();
    let mut grid = String::from("x_mm,y_mm,z_mm\n");
    for i in 0..6 {
        for j in 0..6 {
            grid.push_str(&format!(
                "{i},{j},{}\n",
                0.001 * (i as f64) - 0.0005 * j as f64
            ));
        }
    }
    let pts = write(d.path(), "p.csv", &grid);
    let err = refused(
        &capped(&[
            "register",
            "--surface",
            s(&plane),
            "--points",
            s(&pts),
            "--out",
            o,
        ]),
        &["do not determine", "--lock"],
    );
    for m in ["tx", "ty", "rz"] {
        assert!(err.contains(m), "{m} not named: {err}");
    }
    assert!(!out.exists());
    let r = preston(&[
        "register",
        "--surface",
        s(&plane),
        "--points",
        s(&pts),
        "--lock",
        "rz,tx,ty",
        "--out",
        o,
    ]);
    assert_eq!(
        r.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&r.stderr)
    );
    let mut line = String::from("x_mm,y_mm,z_mm\n");
    for k in 0..10 {
        line.push_str(&format!("{k},{k},{}\n", 0.0001 * k as f64));
    }
    let line = write(d.path(), "line.csv", &line);
    let sphere = write(
        d.path(),
        "s.json",
        r#"{"type":"conic","curvature_per_mm":0.01}"#,
    );
    refused(
        &capped(&[
            "register",
            "--surface",
            s(&sphere),
            "--points",
            s(&line),
            "--out",
            o,
        ]),
        &["one line", "undetermined motions"],
    );
    let two = write(d.path(), "two.csv", "x_mm,y_mm,z_mm\n0,0,0\n1,0,0\n");
    refused(
        &capped(&[
            "register",
            "--surface",
            s(&sphere),
            "--points",
            s(&two),
            "--out",
            o,
        ]),
        &["at least"],
    );
}

/// Negative numbers given as option values reach the option's validation on every subcommand
/// (a sample of each subcommand; the unit test in main.rs checks every option of the tree).
#[test]
fn negative_option_values_reach_the_validator() {
    for args in [
        &["iterate", "--rho", "-1", "--out", "x"][..],
        &["solve", "--v-max", "-1", "--out", "x"],
        &[
            "tif",
            "gaussian",
            "--sigma-mm",
            "-1",
            "--peak-nm-per-s",
            "1",
            "--pitch-mm",
            "0.1",
            "--out",
            "x",
        ],
        &[
            "path",
            "spiral",
            "--radius-mm",
            "-1",
            "--pitch-mm",
            "1",
            "--out",
            "x",
        ],
        &[
            "simulate",
            "--map",
            "m.csv",
            "--samples-per-point",
            "-1",
            "--out",
            "x",
        ],
        &[
            "map", "fit", "--map", "m.csv", "--basis", "legendre", "--terms", "-3",
        ],
    ] {
        let o = capped(args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(!err.contains("unexpected argument"), "{args:?}: {err}");
    }
}
