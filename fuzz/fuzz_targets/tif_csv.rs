//! Arbitrary bytes as a gridded TIF file (`preston_io::readers::read_tif`, which reads a path: the
//! bytes are written to a per-process file under the temp directory). Errors are fine; a panic is
//! a bug. An accepted TIF must have at least 2 x 2 nodes, positive finite pitches, one finite
//! non-negative rate per node and a support radius that is not NaN.
#![no_main]

use libfuzzer_sys::fuzz_target;
use preston_io::readers::read_tif;
use preston_solver::tif::InfluenceFunction;
use std::io::Write;
use std::path::PathBuf;
use std::sync::OnceLock;

fn scratch() -> &'static PathBuf {
    static PATH: OnceLock<PathBuf> = OnceLock::new();
    PATH.get_or_init(|| {
        std::env::temp_dir().join(format!("preston-fuzz-tif-{}.csv", std::process::id()))
    })
}

/// Overwrites the file from offset 0 and then cuts it to length. `std::fs::write` truncates to zero
/// first, and on ext4 closing a file truncated to zero forces its blocks to disk (`auto_da_alloc`),
/// which made every execution wait for the disk (about 200 instead of 3,000 executions/s).
fn write_in_place(path: &PathBuf, data: &[u8]) -> std::io::Result<()> {
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)?;
    f.write_all(data)?;
    f.set_len(data.len() as u64)
}

fuzz_target!(|data: &[u8]| {
    let path = scratch();
    write_in_place(path, data).expect("write the scratch TIF file");
    let Ok(tif) = read_tif(path) else {
        return;
    };
    let (nx, ny) = tif.shape();
    assert!(nx >= 2 && ny >= 2, "grid {nx} x {ny}");
    let (px, py) = tif.pitch_mm();
    assert!(
        px.is_finite() && px > 0.0 && py.is_finite() && py > 0.0,
        "pitches {px} x {py}"
    );
    let rates = tif.rates_nm_per_s();
    assert_eq!(rates.len(), nx * ny);
    assert!(
        rates.iter().all(|r| r.is_finite() && *r >= 0.0),
        "rates {rates:?}"
    );
    let r = tif.support_radius_mm();
    assert!(r >= 0.0, "support radius {r}");
    // Bilinear interpolation reproduces the samples at the grid nodes (to rounding of the node
    // coordinates: the error is at most a few ulps of the peak rate).
    let (x0, y0) = tif.origin_mm();
    let peak = tif.peak_rate_nm_per_s();
    for (k, &rate) in rates.iter().enumerate().take(256) {
        let (x, y) = (x0 + (k % nx) as f64 * px, y0 + (k / nx) as f64 * py);
        let got = tif.rate_nm_per_s(x, y);
        assert!(
            (got - rate).abs() <= 1e-9 * peak,
            "node {k} at ({x}, {y}) mm: rate {got}, sample {rate} (grid {nx} x {ny}, pitch {px} x {py}, origin ({x0}, {y0}))"
        );
    }
});
