//! NumPy `.npy` height grids (the `npyz` crate): a 2-D array of heights, C or Fortran order, of
//! any float or integer dtype; the lateral pitch comes from `--pitch-mm`, the height unit from
//! `--units` (z; default nm).

use super::grid::Grid;
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

/// Writes a C-order little-endian `f8` `.npy` file of shape `(ny, nx)` (NPY format 1.0). For
/// synthetic test data.
pub fn write_npy(path: &Path, nx: usize, ny: usize, values: &[f64]) -> Result<()> {
    let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({ny}, {nx}), }}");
    let mut header = dict.into_bytes();
    while (10 + header.len() + 1) % 64 != 0 {
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
}
