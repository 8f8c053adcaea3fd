//! Streaming a very large map through the reader: a 10^7-row `x_mm,y_mm,z_nm` file is
//! read with peak memory under twice the size of its values (3 x 8 bytes per row).
//!
//! `cargo bench --bench stream_map` (rows: `PRESTON_STREAM_ROWS`, default 10^7). Not a criterion
//! bench: one timed read, with the process's peak resident memory (`VmHWM` from /proc, Linux)
//! before and after.

use preston::io::readers::read_map;
use std::io::{BufWriter, Write};
use std::time::Instant;

/// Peak resident set size of this process, bytes (Linux `/proc/self/status`), 0 if unknown.
fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

fn main() {
    // `cargo bench` passes `--bench`; a plain `cargo test --benches` run passes nothing and
    // should not spend minutes here.
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let rows: usize = std::env::var("PRESTON_STREAM_ROWS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10_000_000);
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("big_map.csv");
    let side = (rows as f64).sqrt().ceil() as usize;
    {
        let f = std::fs::File::create(&path).expect("create");
        let mut w = BufWriter::with_capacity(1 << 20, f);
        writeln!(w, "x_mm,y_mm,z_nm").expect("write");
        for k in 0..rows {
            let (ix, iy) = (k % side, k / side);
            let (x, y) = (ix as f64 * 0.1, iy as f64 * 0.1);
            let z = 40.0 * (0.05 * x).sin() * (0.03 * y).cos();
            writeln!(w, "{x:.1},{y:.1},{z:.4}").expect("write");
        }
        w.flush().expect("flush");
    }
    let file_bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let before = peak_rss_bytes();
    let start = Instant::now();
    let map = read_map(&path).expect("read");
    let seconds = start.elapsed().as_secs_f64();
    let after = peak_rss_bytes();
    let data_bytes = (map.map.len() * 3 * 8) as u64;
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    println!(
        "stream_map: {} rows, file {:.1} MiB",
        map.map.len(),
        mib(file_bytes)
    );
    println!(
        "  read {:.2} s ({:.2e} rows/s); values {:.1} MiB; peak RSS {:.1} MiB before, {:.1} MiB after",
        seconds,
        map.map.len() as f64 / seconds,
        mib(data_bytes),
        mib(before),
        mib(after)
    );
    println!(
        "  peak RSS / value size = {:.2} (target < 2)",
        after as f64 / data_bytes as f64
    );
}
