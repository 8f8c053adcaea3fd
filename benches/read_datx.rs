//! Reading a 2000 x 2000 Zygo `.datx` (chunked, deflate-compressed f64 surface with 5% no-data
//! pixels) through `MapSource`: time and the process's peak resident memory against the size
//! of the values read.
//!
//! `cargo bench --bench read_datx` (side: `PRESTON_DATX_SIDE`, default 2000). Not a criterion
//! bench: one timed read after one warm-up read; the peak resident memory of the read (`VmHWM`
//! from /proc, reset before it; Linux) above the resident set before it.

use preston::io::metrology::{write_zygo_datx, DatxUnit, MapSource};
use std::time::Instant;

/// Peak (`VmHWM`) or current (`VmRSS`) resident set size of this process, bytes (Linux
/// `/proc/self/status`), 0 if unknown.
fn rss_bytes(key: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(key))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

fn main() {
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let side: usize = std::env::var("PRESTON_DATX_SIDE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(2000);
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("big.datx");
    {
        let z: Vec<f64> = (0..side * side)
            .map(|k| {
                let (i, j) = ((k / side) as f64, (k % side) as f64);
                if (k * 7919) % 20 == 3 {
                    f64::NAN
                } else {
                    40.0 * (0.011 * j).sin() * (0.007 * i).cos() + 0.01 * ((k % 97) as f64)
                }
            })
            .collect();
        write_zygo_datx(&path, side, side, 0.05, &z, DatxUnit::NanoMeters).expect("write");
    }
    let file_bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let src = MapSource::from_file(&path);
    let mut seconds = Vec::new();
    let mut points = 0;
    let (mut before, mut after) = (0, 0);
    for _ in 0..2 {
        // Reset the peak to the current resident set (Linux: `5` to clear_refs), so the peak
        // seen after the read is the read's.
        let _ = std::fs::write("/proc/self/clear_refs", "5");
        before = rss_bytes("VmRSS:");
        let start = Instant::now();
        let m = src.read().expect("read");
        seconds.push(start.elapsed().as_secs_f64());
        after = rss_bytes("VmHWM:");
        points = m.map.len();
    }
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    let z_bytes = (side * side * 8) as u64;
    let map_bytes = (points * 3 * 8) as u64;
    println!(
        "read_datx: {side} x {side} pixels, {points} valid, file {:.1} MiB; read {:.3} s (warm-up {:.3} s)",
        mib(file_bytes),
        seconds[1],
        seconds[0]
    );
    println!(
        "  resident {:.1} MiB before the read, peak {:.1} MiB during it (+{:.1} MiB): {:.2}x the stored heights ({:.1} MiB f64), {:.2}x the map read (x, y, z: {:.1} MiB)",
        mib(before),
        mib(after),
        mib(after.saturating_sub(before)),
        after.saturating_sub(before) as f64 / z_bytes as f64,
        mib(z_bytes),
        after.saturating_sub(before) as f64 / map_bytes as f64,
        mib(map_bytes)
    );
}
