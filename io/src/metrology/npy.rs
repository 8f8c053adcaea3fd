//! NumPy `.npy` height grids (the `npyz` crate): a 2-D array of heights, C or Fortran order, of
//! any float or integer dtype; the lateral pitch comes from `--pitch-mm`, the height unit from
//! `--units` (z; default nm).

use super::grid::{check_grid_budget, Grid};
use super::LengthUnit;
use crate::error::{Error, Result};
use npyz::{NpyFile, Order};
use std::path::Path;

/// Largest grid read (pixels), checked from the header before reading the data.
const MAX_PIXELS: u64 = 1 << 30;

/// Reads a 2-D `.npy` grid of heights in `z_unit` with pitch `pitch_mm`.
pub(crate) fn read_npy(path: &Path, pitch_mm: Option<f64>, z_unit: LengthUnit) -> Result<Grid> {
    let pitch = pitch_mm.ok_or_else(|| {
        Error::option(
            "--pitch-mm",
            format!(
                "{}: a .npy grid carries no pixel size; give --pitch-mm",
                path.display()
            ),
        )
    })?;
    if !(pitch.is_finite() && pitch > 0.0) {
        return Err(Error::option(
            "--pitch-mm",
            format!("{pitch} is not a positive length"),
        ));
    }
    let bytes =
        crate::limits::read_regular(path, preston_solver::budget::limit_bytes(), "map file")?;
    check_preamble(path, &bytes)?;
    let npy =
        NpyFile::new(&bytes[..]).map_err(|e| Error::binary(path, "NPY header", e.to_string()))?;
    let (ny, nx) = match npy.shape() {
        [ny, nx] => (*ny, *nx),
        other => {
            return Err(Error::binary(
                path,
                "NPY header (shape)",
                format!("shape {other:?} is not a 2-D grid"),
            ))
        }
    };
    if nx == 0 || ny == 0 || nx.saturating_mul(ny) > MAX_PIXELS {
        return Err(Error::binary(
            path,
            "NPY header (shape)",
            format!("grid of {ny} x {nx} is empty or larger than {MAX_PIXELS} pixels"),
        ));
    }
    let order = npy.order();
    let descr = npy.dtype().descr();
    let dtype = descr.trim_matches('\'');
    check_data_size(path, &bytes, ny, nx, npy.dtype().num_bytes())?;
    let data_err = |e: std::io::Error| Error::binary(path, "NPY data", e.to_string());
    let values: Vec<f64> = match dtype.trim_start_matches(['<', '>', '|', '=']) {
        "f8" => npy.into_vec::<f64>().map_err(data_err)?,
        "f4" => npy
            .into_vec::<f32>()
            .map_err(data_err)?
            .into_iter()
            .map(f64::from)
            .collect(),
        "i4" => npy
            .into_vec::<i32>()
            .map_err(data_err)?
            .into_iter()
            .map(f64::from)
            .collect(),
        "i2" => npy
            .into_vec::<i16>()
            .map_err(data_err)?
            .into_iter()
            .map(f64::from)
            .collect(),
        "u2" => npy
            .into_vec::<u16>()
            .map_err(data_err)?
            .into_iter()
            .map(f64::from)
            .collect(),
        "i8" => npy
            .into_vec::<i64>()
            .map_err(data_err)?
            .into_iter()
            .map(|v| v as f64)
            .collect(),
        other => {
            return Err(Error::binary(
                path,
                "NPY header (descr)",
                format!("dtype `{other}` is not a float or integer type Preston reads"),
            ))
        }
    };
    let (nx, ny) = (nx as usize, ny as usize);
    if values.len() != nx * ny {
        return Err(Error::binary(
            path,
            "NPY data",
            format!("truncated: {} values for a {ny} x {nx} grid", values.len()),
        ));
    }
    let f = z_unit.factor_to(LengthUnit::Nm);
    let z_nm: Vec<f64> = match order {
        Order::C => values.into_iter().map(|v| v * f).collect(),
        Order::Fortran => (0..ny * nx)
            .map(|k| values[(k % nx) * ny + k / nx] * f)
            .collect(),
    };
    Ok(Grid {
        nx,
        ny,
        pitch_mm: pitch,
        z_nm,
        notes: vec![format!(
            "{}: {ny} x {nx} grid, heights in {} (--units z), pitch {pitch} mm (--pitch-mm)",
            path.display(),
            z_unit.name()
        )],
    })
}

/// Bytes of the magic string and version of every `.npy` file (`\x93NUMPY`, major, minor).
const MAGIC_AND_VERSION: usize = 8;

/// The preamble of a `.npy` file: where its header text starts and how long it is, as its
/// length field states (format 1: 2 bytes; formats 2 and 3: 4 bytes, so up to 4 GiB).
fn header_extent(bytes: &[u8]) -> Option<(usize, u64)> {
    if bytes.len() < MAGIC_AND_VERSION || &bytes[..6] != b"\x93NUMPY" {
        return None;
    }
    match bytes[6] {
        1 => {
            let b = bytes.get(8..10)?;
            Some((10, u64::from(u16::from_le_bytes([b[0], b[1]]))))
        }
        2 | 3 => {
            let b = bytes.get(8..12)?;
            Some((12, u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))))
        }
        _ => None,
    }
}

/// Refuses a header whose stated length runs past the end of the file, or would not fit in the
/// memory budget, before the reader allocates a buffer of that length. A preamble the reader
/// will not recognise (no magic, unknown version, cut short) is left to it to name.
fn check_preamble(path: &Path, bytes: &[u8]) -> Result<()> {
    let Some((start, len)) = header_extent(bytes) else {
        return Ok(());
    };
    let file_len = bytes.len() as u64;
    if (start as u64).saturating_add(len) > file_len {
        return Err(Error::binary(
            path,
            "NPY header (length)",
            format!(
                "states a header of {len} bytes, but the file holds {file_len} bytes in all \
                 (truncated or not a .npy file)"
            ),
        ));
    }
    preston_solver::budget::check(
        "header length",
        &format!("a header of {len} bytes"),
        len as f64,
    )
    .map_err(|e| Error::binary(path, "NPY header (length)", e.to_string()))
}

/// Refuses a shape whose data the file cannot hold, or whose values (read, then converted to
/// heights and points: four `f64` arrays of `ny * nx`) do not fit in the memory budget, before
/// the reader allocates them.
fn check_data_size(
    path: &Path,
    bytes: &[u8],
    ny: u64,
    nx: u64,
    item_bytes: Option<usize>,
) -> Result<()> {
    // A dtype without a fixed size is refused by the dtype check that follows.
    let Some(item_bytes) = item_bytes else {
        return Ok(());
    };
    let pixels = ny.saturating_mul(nx);
    let data_bytes = pixels.saturating_mul(item_bytes as u64);
    let held = header_extent(bytes)
        .map(|(start, len)| (bytes.len() as u64).saturating_sub(start as u64 + len))
        .unwrap_or(0);
    if data_bytes > held {
        return Err(Error::binary(
            path,
            "NPY data",
            format!(
                "truncated: the header's shape ({ny}, {nx}) of {item_bytes}-byte values needs \
                 {data_bytes} bytes of data, the file holds {held}"
            ),
        ));
    }
    check_grid_budget(ny, nx).map_err(|e| Error::binary(path, "NPY header (shape)", e.to_string()))
}

/// Writes a C-order little-endian `f8` `.npy` file of shape `(ny, nx)` (NPY format 1.0). For
/// synthetic test data.
pub fn write_npy(path: &Path, nx: usize, ny: usize, values: &[f64]) -> Result<()> {
    let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({ny}, {nx}), }}");
    let mut header = dict.into_bytes();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(b' ');
    }
    header.push(b'\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(&header);
    for v in values {
        b.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, b).map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_a_grid_and_rejects_bad_headers() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("g.npy");
        let v: Vec<f64> = (0..6).map(|k| k as f64 - 1.0).collect();
        write_npy(&p, 3, 2, &v).unwrap();
        let g = read_npy(&p, Some(0.5), LengthUnit::Um).unwrap();
        assert_eq!((g.nx, g.ny), (3, 2));
        assert_eq!(g.z_nm, vec![-1000.0, 0.0, 1000.0, 2000.0, 3000.0, 4000.0]);
        assert!(read_npy(&p, None, LengthUnit::Nm)
            .unwrap_err()
            .to_string()
            .contains("--pitch-mm"));
        let b = std::fs::read(&p).unwrap();
        std::fs::write(&p, &b[..b.len() - 4]).unwrap();
        let e = read_npy(&p, Some(1.0), LengthUnit::Nm)
            .unwrap_err()
            .to_string();
        assert!(e.contains("g.npy") && e.contains("NPY data"), "{e}");
        std::fs::write(&p, b"\x93NUMPY\x01\x00garbage").unwrap();
        let e = read_npy(&p, Some(1.0), LengthUnit::Nm)
            .unwrap_err()
            .to_string();
        assert!(e.contains("NPY header"), "{e}");
    }

    /// A format-2 preamble whose 4-byte length field states a 4 GiB header, in a 20-byte file:
    /// refused from the preamble, naming the file and the stated length, before a buffer of that
    /// length is allocated.
    #[test]
    fn a_header_length_past_the_end_of_the_file_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("huge_header.npy");
        let mut b = b"\x93NUMPY\x02\x00".to_vec();
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        b.extend_from_slice(b"{'descr'");
        assert_eq!(b.len(), 20);
        std::fs::write(&p, &b).unwrap();
        let e = read_npy(&p, Some(1.0), LengthUnit::Nm)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("huge_header.npy")
                && e.contains(&u32::MAX.to_string())
                && e.contains("20 bytes"),
            "{e}"
        );
        assert_eq!(header_extent(&b), Some((12, u64::from(u32::MAX))));
        // A format-1 preamble's length is two bytes.
        let v1 = b"\x93NUMPY\x01\x00\x76\x00";
        assert_eq!(header_extent(v1), Some((10, 0x76)));
    }

    /// A well-formed header declaring a 30000 x 30000 grid with no data behind it: refused as
    /// truncated (7.2 GB of values stated, none held) before the values are read.
    #[test]
    fn a_shape_the_file_cannot_hold_is_refused_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("big_shape.npy");
        write_npy(&p, 3, 2, &[0.0; 6]).unwrap();
        let b = std::fs::read(&p).unwrap();
        let text = String::from_utf8_lossy(&b[10..]).into_owned();
        let head = text
            .split('\n')
            .next()
            .unwrap()
            .replace("(2, 3)", "(30000, 30000)");
        let mut header = head.into_bytes();
        while !(10 + header.len() + 1).is_multiple_of(64) {
            header.push(b' ');
        }
        header.push(b'\n');
        let mut c = b"\x93NUMPY\x01\x00".to_vec();
        c.extend_from_slice(&(header.len() as u16).to_le_bytes());
        c.extend_from_slice(&header);
        std::fs::write(&p, &c).unwrap();
        let e = read_npy(&p, Some(1.0), LengthUnit::Nm)
            .unwrap_err()
            .to_string();
        let stated = 30000u64 * 30000 * 8;
        assert!(
            e.contains("big_shape.npy") && e.contains(&stated.to_string()),
            "{e}"
        );
    }
}
