//! Helpers shared by the CLI integration tests: running the binary, file fixtures, reading the
//! CSV, JSON and PNG outputs. Each test crate uses a part of them.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The keys of `report.json` `sensitivity` (the interface the outside checks keep).
pub const SENSITIVITY_KEYS: [&str; 5] = [
    "tif_wider_3pct",
    "tif_narrower_3pct",
    "rate_plus_3pct",
    "offset_x_0p05mm",
    "offset_y_0p05mm",
];

/// The `preston` binary under test.
pub fn exe() -> &'static str {
    env!("CARGO_BIN_EXE_preston")
}

/// A command running the binary, to add arguments to.
pub fn preston_cmd() -> Command {
    Command::new(exe())
}

/// Runs the binary with `args`.
pub fn preston(args: &[&str]) -> Output {
    preston_cmd().args(args).output().unwrap()
}

/// Asserts a successful exit; returns stderr.
pub fn ok(out: &Output) -> String {
    assert!(
        out.status.success(),
        "exit {:?}\nstderr: {}",
        out.status.code(),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stderr).to_string()
}

/// Runs `cmd`, asserting a successful exit.
pub fn run_ok(cmd: &mut Command) -> Output {
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "{:?} failed: {}",
        cmd,
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// A path as a command-line argument.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A file of the sample data set (`data/`).
pub fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../data")
        .join(name)
}

/// [`data`] as a command-line argument.
pub fn data_arg(name: &str) -> String {
    data(name).to_string_lossy().to_string()
}

/// Writes `text` to `dir/name`.
pub fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// [`write`], the path as a command-line argument.
pub fn write_arg(dir: &Path, name: &str, text: &str) -> String {
    write(dir, name, text).to_string_lossy().to_string()
}

/// A JSON file.
pub fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// `dir/report.json`.
pub fn report(dir: &Path) -> serde_json::Value {
    read_json(&dir.join("report.json"))
}

/// The JSON a command printed on stdout.
pub fn stdout_json(out: &Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A CSV of numbers: (header line, rows).
pub fn csv_rows(p: &Path) -> (String, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(p).unwrap();
    let mut lines = text.lines();
    let header = lines.next().unwrap().to_string();
    let rows = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    (header, rows)
}

/// A CSV of numbers: (column names, rows).
pub fn read_csv(p: &Path) -> (Vec<String>, Vec<Vec<f64>>) {
    let (header, rows) = csv_rows(p);
    (header.split(',').map(str::to_string).collect(), rows)
}

/// The named columns of a CSV of numbers, in the order asked.
pub fn csv_columns(p: &Path, names: &[&str]) -> Vec<Vec<f64>> {
    let (header, rows) = read_csv(p);
    names
        .iter()
        .map(|n| {
            let k = header
                .iter()
                .position(|h| h == n)
                .unwrap_or_else(|| panic!("{} has no column {n}: {header:?}", p.display()));
            rows.iter().map(|r| r[k]).collect()
        })
        .collect()
}

/// Runs `preston solve ARGS --out DIR/result` and asserts exit 2, every needle in stderr and
/// nothing written.
pub fn expect_failure(args: &[&str], needles: &[&str]) {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("result");
    let o = preston_cmd()
        .arg("solve")
        .args(args)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{args:?}: {stderr}");
    for n in needles {
        assert!(stderr.contains(n), "stderr lacks `{n}`: {stderr}");
    }
    assert!(
        !out.exists() || std::fs::read_dir(&out).unwrap().next().is_none(),
        "output written despite the error"
    );
}

/// Width and height of a PNG, from its header.
pub fn png_size(path: &Path) -> (u32, u32) {
    let b = std::fs::read(path).unwrap();
    assert_eq!(
        &b[..8],
        b"\x89PNG\r\n\x1a\n",
        "{} is not a PNG",
        path.display()
    );
    let be = |k: usize| u32::from_be_bytes([b[k], b[k + 1], b[k + 2], b[k + 3]]);
    (be(16), be(20))
}

/// Every file of `dir` with its bytes, sorted by name.
pub fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| {
            (
                e.file_name().to_string_lossy().to_string(),
                std::fs::read(e.path()).unwrap_or_default(),
            )
        })
        .collect();
    v.sort();
    v
}

/// Asserts a successful exit; returns the JSON printed on stdout (null when there is none).
pub fn ok_json(out: &Output) -> serde_json::Value {
    ok(out);
    serde_json::from_slice(&out.stdout).unwrap_or(serde_json::Value::Null)
}
