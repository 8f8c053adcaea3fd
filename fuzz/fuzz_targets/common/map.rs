//! Shared body of the map-reader targets: arbitrary bytes written to a per-process scratch file
//! with the format's extension, read by `MapSource::read` with the format forced. Errors are
//! fine; a panic is a bug. An accepted map must be non-empty, with finite coordinates and heights
//! inside the physical ranges of `preston_io::limits`, and no repeated point.

use preston_io::limits::{MAX_ABS_COORDINATE_MM, MAX_ABS_HEIGHT_NM};
use preston_io::metrology::{MapFormat, MapSource};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Overwrites the file in place (see `tif_csv.rs`: truncating to zero forces a disk flush).
fn write_in_place(path: &Path, data: &[u8]) -> std::io::Result<()> {
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(false)
        .open(path)?;
    f.write_all(data)?;
    f.set_len(data.len() as u64)
}

/// Reads `data` as a map file of `format` (scratch file `preston-fuzz-<ext>-<pid>.<ext>`) and
/// checks what an accepted map guarantees.
pub fn check(data: &[u8], format: MapFormat, ext: &str, path: &'static std::sync::OnceLock<PathBuf>) {
    let path = path.get_or_init(|| {
        std::env::temp_dir().join(format!("preston-fuzz-{ext}-{}.{ext}", std::process::id()))
    });
    write_in_place(path, data).expect("write the scratch map file");
    let src = MapSource {
        file: Some(path.clone()),
        format: Some(format),
        pitch_mm: Some(0.5),
        ..MapSource::default()
    };
    let Ok(read) = src.read() else {
        return;
    };
    let m = &read.map;
    assert!(!m.is_empty());
    let (x, y, z) = (m.x_mm(), m.y_mm(), m.z_nm());
    assert!(x.len() == y.len() && y.len() == z.len());
    for k in 0..x.len() {
        assert!(
            x[k].abs() <= MAX_ABS_COORDINATE_MM
                && y[k].abs() <= MAX_ABS_COORDINATE_MM
                && z[k].abs() <= MAX_ABS_HEIGHT_NM,
            "point {k}: ({}, {}, {})",
            x[k],
            y[k],
            z[k]
        );
    }
    let mut keys: Vec<(u64, u64)> = x
        .iter()
        .zip(y)
        .map(|(a, b)| ((a + 0.0).to_bits(), (b + 0.0).to_bits()))
        .collect();
    keys.sort_unstable();
    assert!(keys.windows(2).all(|w| w[0] != w[1]), "repeated point");
}
