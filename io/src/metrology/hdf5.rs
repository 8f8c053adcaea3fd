//! HDF5-based instrument files, read with the pure-Rust `hdf5-pure` crate (contiguous and
//! chunked datasets, deflate and shuffle filters; no system library).
//!
//! - Zygo Mx `.datx`: heights are the first dataset (in name order) under `/Data/Surface`; its
//!   attributes give `No Data` (values at or above it are dropped when it is large, equal to it
//!   otherwise) and `Unit`: `NanoMeters`, `MicroMeters`, `MilliMeters`, `Meters`, or `Fringes`
//!   (height `= v * Interferometric Scale Factor * Obliquity Factor * Wavelength`, wavelength in
//!   metres). The lateral resolution, metres per pixel, is the attribute
//!   `Data Context.Lateral Resolution:Value` of the last group (in name order) under
//!   `/Attributes`.
//! - 4D Technology `.h5`/`.4D`: heights are `/Measurement/SurfaceInWaves/Data` (waves) times
//!   `WavelengthInNanometers` (an attribute of `/Measurement`, or of `SurfaceInWaves` or `Data`);
//!   NaN is no data. The pixel size is `--pitch-mm`, else an `XYScale` attribute (metres per
//!   pixel) on `SurfaceInWaves` or `Data`.
//!
//! (Public descriptions: prysm's `read_zygo_datx`; 4D users' h5py readers.)

use super::grid::{check_grid_budget, Grid};
use crate::error::{Error, Result};
use hdf5_pure::{AttrValue, File, FileBuilder};
use std::collections::HashMap;
use std::path::Path;

/// Largest grid read (pixels), checked from the dataset's shape before reading it.
const MAX_PIXELS: u64 = 1 << 30;

fn open(path: &Path) -> Result<File> {
    if !path.exists() {
        return Err(Error::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        ));
    }
    drop(crate::limits::open_regular(path)?);
    File::open(path).map_err(|e| Error::binary(path, "HDF5 structure", cause(&e)))
}

/// The crate's message, kept short (its messages name structures, never data bytes).
fn cause(e: &hdf5_pure::Error) -> String {
    let s = e.to_string();
    if s.chars().count() > 300 {
        format!("{}...", s.chars().take(300).collect::<String>())
    } else {
        s
    }
}

/// The first numeric value of an attribute (scalar or array).
fn attr_f64(v: &AttrValue) -> Option<f64> {
    match v {
        AttrValue::F64(x) => Some(*x),
        AttrValue::F32(x) => Some(f64::from(*x)),
        AttrValue::F64Array(a) => a.first().copied(),
        AttrValue::F32Array(a) => a.first().map(|x| f64::from(*x)),
        AttrValue::I32(x) => Some(f64::from(*x)),
        AttrValue::I32Array(a) => a.first().map(|x| f64::from(*x)),
        AttrValue::I64(x) => Some(*x as f64),
        AttrValue::I64Array(a) => a.first().map(|x| *x as f64),
        AttrValue::U32(x) => Some(f64::from(*x)),
        AttrValue::U32Array(a) => a.first().map(|x| f64::from(*x)),
        AttrValue::I16(x) => Some(f64::from(*x)),
        AttrValue::U16(x) => Some(f64::from(*x)),
        AttrValue::U8(x) => Some(f64::from(*x)),
        AttrValue::U64(x) => Some(*x as f64),
        _ => None,
    }
}

/// The first string of an attribute (fixed or variable length, scalar or array).
fn attr_str(v: &AttrValue) -> Option<String> {
    let s = match v {
        AttrValue::String(s)
        | AttrValue::AsciiString(s)
        | AttrValue::VarLenString(s)
        | AttrValue::VarLenAsciiString(s) => s.clone(),
        AttrValue::StringArray(a)
        | AttrValue::AsciiStringArray(a)
        | AttrValue::VarLenStringArray(a)
        | AttrValue::VarLenAsciiStringArray(a)
        | AttrValue::VarLenAsciiCharArray(a) => a.first()?.clone(),
        AttrValue::StringSized { value, .. } | AttrValue::AsciiStringSized { value, .. } => {
            value.clone()
        }
        AttrValue::StringArraySized { values, .. }
        | AttrValue::AsciiStringArraySized { values, .. } => values.first()?.clone(),
        _ => return None,
    };
    Some(s.trim_end_matches('\0').trim().to_string())
}

/// Reads a 2-D float dataset as `(ny, nx, values)`, checking its size before reading.
fn read_2d(path: &Path, f: &File, ds_path: &str) -> Result<(usize, usize, Vec<f64>)> {
    let at = format!("dataset /{ds_path}");
    let ds = f
        .dataset(ds_path)
        .map_err(|e| Error::binary(path, &at, cause(&e)))?;
    let shape = ds
        .shape()
        .map_err(|e| Error::binary(path, &at, cause(&e)))?;
    let (ny, nx) = match shape.as_slice() {
        [ny, nx] => (*ny, *nx),
        [1, ny, nx] => (*ny, *nx),
        other => {
            return Err(Error::binary(
                path,
                &at,
                format!("has shape {other:?}, not a 2-D grid"),
            ))
        }
    };
    if nx == 0 || ny == 0 || nx.saturating_mul(ny) > MAX_PIXELS {
        return Err(Error::binary(
            path,
            &at,
            format!("grid of {ny} x {nx} pixels is empty or larger than {MAX_PIXELS}"),
        ));
    }
    check_grid_budget(ny, nx).map_err(|e| Error::binary(path, &at, e.to_string()))?;
    let v = ds
        .read_f64()
        .map_err(|e| Error::binary(path, &at, cause(&e)))?;
    if v.len() as u64 != nx * ny {
        return Err(Error::binary(
            path,
            &at,
            format!("holds {} values for a {ny} x {nx} grid", v.len()),
        ));
    }
    Ok((ny as usize, nx as usize, v))
}

fn attrs_of_dataset(path: &Path, f: &File, ds_path: &str) -> Result<HashMap<String, AttrValue>> {
    let at = format!("dataset /{ds_path}");
    f.dataset(ds_path)
        .and_then(|d| d.attrs())
        .map_err(|e| Error::binary(path, at, cause(&e)))
}

fn attrs_of_group(path: &Path, f: &File, g: &str) -> Result<HashMap<String, AttrValue>> {
    f.group(g)
        .and_then(|g| g.attrs())
        .map_err(|e| Error::binary(path, format!("group /{g}"), cause(&e)))
}

/// Reads the surface of a Zygo `.datx` file.
pub(crate) fn read_datx(path: &Path) -> Result<Grid> {
    let f = open(path)?;
    let surface = f
        .group("Data/Surface")
        .map_err(|e| Error::binary(path, "group /Data/Surface", cause(&e)))?;
    let mut names = surface
        .datasets()
        .map_err(|e| Error::binary(path, "group /Data/Surface", cause(&e)))?;
    names.sort();
    let name = names.first().ok_or_else(|| {
        Error::binary(
            path,
            "group /Data/Surface",
            "holds no dataset (no surface data)",
        )
    })?;
    let ds_path = format!("Data/Surface/{name}");
    let at = format!("dataset /{ds_path}");
    let attrs = attrs_of_dataset(path, &f, &ds_path)?;
    let number = |key: &str| -> Result<f64> {
        attrs
            .get(key)
            .and_then(attr_f64)
            .filter(|v| v.is_finite())
            .ok_or_else(|| {
                Error::binary(
                    path,
                    &at,
                    format!("attribute `{key}` is missing or not a number"),
                )
            })
    };
    let unit = attrs
        .get("Unit")
        .and_then(attr_str)
        .ok_or_else(|| Error::binary(path, &at, "attribute `Unit` is missing or not a string"))?;
    let (factor, note) = match unit.as_str() {
        "NanoMeters" => (1.0, "heights in NanoMeters".to_string()),
        "MicroMeters" => (1e3, "heights in MicroMeters converted to nm".to_string()),
        "MilliMeters" => (1e6, "heights in MilliMeters converted to nm".to_string()),
        "Meters" => (1e9, "heights in Meters converted to nm".to_string()),
        "Fringes" => {
            let w = number("Wavelength")?;
            let s = number("Interferometric Scale Factor")?;
            let o = number("Obliquity Factor")?;
            (
                w * s * o * 1e9,
                format!(
                    "heights in Fringes x scale factor {s} x obliquity {o} x wavelength {w} m, \
                     converted to nm"
                ),
            )
        }
        other => {
            return Err(Error::binary(
                path,
                &at,
                format!(
                    "unit `{other}` is not NanoMeters, MicroMeters, MilliMeters, Meters or Fringes"
                ),
            ))
        }
    };
    if !(factor.is_finite() && factor > 0.0) {
        return Err(Error::binary(
            path,
            &at,
            format!("the unit conversion gives {factor} nm per unit"),
        ));
    }
    let no_data = attrs.get("No Data").and_then(attr_f64);
    // Lateral resolution: the last group under /Attributes.
    let attr_root = f
        .group("Attributes")
        .map_err(|e| Error::binary(path, "group /Attributes", cause(&e)))?;
    let mut groups = attr_root
        .groups()
        .map_err(|e| Error::binary(path, "group /Attributes", cause(&e)))?;
    groups.sort();
    let last = groups
        .last()
        .ok_or_else(|| Error::binary(path, "group /Attributes", "holds no attribute group"))?;
    let g_path = format!("Attributes/{last}");
    let res_key = "Data Context.Lateral Resolution:Value";
    let res_m = attrs_of_group(path, &f, &g_path)?
        .get(res_key)
        .and_then(attr_f64)
        .ok_or_else(|| {
            Error::binary(
                path,
                format!("group /{g_path}"),
                format!("attribute `{res_key}` is missing or not a number"),
            )
        })?;
    let pitch_mm = res_m * 1e3;
    if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
        return Err(Error::binary(
            path,
            format!("group /{g_path}"),
            format!("lateral resolution {res_m} m is not a positive length"),
        ));
    }
    let (ny, nx, mut z) = read_2d(path, &f, &ds_path)?;
    let is_no_data = |v: f64| match no_data {
        Some(nd) if nd.abs() >= 1e30 => v.abs() >= nd.abs(),
        Some(nd) => v == nd,
        None => false,
    };
    for v in &mut z {
        *v = if v.is_finite() && !is_no_data(*v) {
            *v * factor
        } else {
            f64::NAN
        };
    }
    Ok(Grid {
        nx,
        ny,
        pitch_mm,
        z_nm: z,
        notes: vec![format!("{}: {note}, pitch {pitch_mm} mm", path.display())],
    })
}

/// Reads the surface of a 4D Technology `.h5`/`.4D` file; `pitch_mm` overrides the file's.
pub(crate) fn read_4d(path: &Path, pitch_mm: Option<f64>) -> Result<Grid> {
    let f = open(path)?;
    let ds_path = "Measurement/SurfaceInWaves/Data";
    let sets = [
        attrs_of_group(path, &f, "Measurement")?,
        attrs_of_group(path, &f, "Measurement/SurfaceInWaves")?,
        attrs_of_dataset(path, &f, ds_path)?,
    ];
    let find = |key: &str| sets.iter().find_map(|a| a.get(key).and_then(attr_f64));
    let wl_nm = find("WavelengthInNanometers")
        .filter(|w| w.is_finite() && *w > 0.0)
        .ok_or_else(|| {
            Error::binary(
                path,
                "group /Measurement",
                "attribute `WavelengthInNanometers` is missing or not a positive number",
            )
        })?;
    let mut notes = vec![format!("{}: heights in waves x {wl_nm} nm", path.display())];
    let pitch = match pitch_mm {
        Some(p) => {
            notes.push(format!("pitch {p} mm from --pitch-mm"));
            p
        }
        None => {
            let m = find("XYScale").ok_or_else(|| {
                Error::option(
                    "--pitch-mm",
                    format!(
                        "{}: the 4D file carries no pixel size (XYScale); give --pitch-mm",
                        path.display()
                    ),
                )
            })?;
            notes.push(format!("pitch {} mm from XYScale", m * 1e3));
            m * 1e3
        }
    };
    if !(pitch.is_finite() && pitch > 0.0) {
        return Err(Error::option(
            "--pitch-mm",
            format!("pixel size {pitch} mm is not a positive length"),
        ));
    }
    let (ny, nx, mut z) = read_2d(path, &f, ds_path)?;
    for v in &mut z {
        *v = if v.is_finite() { *v * wl_nm } else { f64::NAN };
    }
    Ok(Grid {
        nx,
        ny,
        pitch_mm: pitch,
        z_nm: z,
        notes,
    })
}

/// The height unit of a synthetic `.datx` file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DatxUnit {
    /// Heights stored in nm.
    NanoMeters,
    /// Heights stored in fringes: `nm = v * scale * obliquity * wavelength_m * 1e9`.
    Fringes {
        /// Wavelength, m.
        wavelength_m: f64,
        /// Interferometric scale factor.
        scale: f64,
        /// Obliquity factor.
        obliquity: f64,
    },
}

/// No-data value written by [`write_zygo_datx`] (Zygo's `No Data` for float surfaces).
pub const DATX_NO_DATA: f64 = f64::MAX;

/// Writes a Zygo-style `.datx` file: `z_nm` (row-major `ny x nx`, first row on top, NaN for no
/// data) in `unit`, a chunked deflate dataset `/Data/Surface/0` and the lateral resolution under
/// `/Attributes/{...}`. For synthetic test data and benchmarks.
pub fn write_zygo_datx(
    path: &Path,
    nx: usize,
    ny: usize,
    pitch_mm: f64,
    z_nm: &[f64],
    unit: DatxUnit,
) -> Result<()> {
    let (per_unit, unit_name) = match unit {
        DatxUnit::NanoMeters => (1.0, "NanoMeters"),
        DatxUnit::Fringes {
            wavelength_m,
            scale,
            obliquity,
        } => (wavelength_m * scale * obliquity * 1e9, "Fringes"),
    };
    let data: Vec<f64> = z_nm
        .iter()
        .map(|&z| {
            if z.is_nan() {
                DATX_NO_DATA
            } else {
                z / per_unit
            }
        })
        .collect();
    let mut b = FileBuilder::new();
    let mut data_g = b.create_group("Data");
    let mut surf = data_g.create_group("Surface");
    {
        let ds = surf
            .create_dataset("0")
            .with_f64_data(&data)
            .with_shape(&[ny as u64, nx as u64])
            .with_chunks(&[(ny as u64).clamp(1, 256), (nx as u64).clamp(1, 256)])
            .with_deflate(4);
        ds.set_attr("No Data", AttrValue::F64Array(vec![DATX_NO_DATA]));
        ds.set_attr("Unit", AttrValue::StringArray(vec![unit_name.into()]));
        if let DatxUnit::Fringes {
            wavelength_m,
            scale,
            obliquity,
        } = unit
        {
            ds.set_attr("Wavelength", AttrValue::F64Array(vec![wavelength_m]));
            ds.set_attr(
                "Interferometric Scale Factor",
                AttrValue::F64Array(vec![scale]),
            );
            ds.set_attr("Obliquity Factor", AttrValue::F64Array(vec![obliquity]));
        }
    }
    data_g.add_group(surf.finish());
    b.add_group(data_g.finish());
    let mut attrs = b.create_group("Attributes");
    let mut early = attrs.create_group("{0A000000}");
    early.set_attr(
        "Data Context.Lateral Resolution:Value",
        AttrValue::F64Array(vec![0.0]),
    );
    attrs.add_group(early.finish());
    let mut last = attrs.create_group("{FFFFFFFF}");
    last.set_attr(
        "Data Context.Lateral Resolution:Value",
        AttrValue::F64Array(vec![pitch_mm * 1e-3]),
    );
    last.set_attr(
        "Data Context.Lateral Resolution:Unit",
        AttrValue::StringArray(vec!["Meters".into()]),
    );
    attrs.add_group(last.finish());
    b.add_group(attrs.finish());
    b.write(path)
        .map_err(|e| Error::binary(path, "HDF5 writer", cause(&e)))
}

/// Writes a 4D-style `.h5` file: `z_nm / wavelength_nm` waves (NaN for no data) as a chunked
/// deflate dataset `/Measurement/SurfaceInWaves/Data`, `WavelengthInNanometers` on
/// `/Measurement` and `XYScale` (m per pixel) on `SurfaceInWaves` when `pitch_mm` is given.
pub fn write_4d_h5(
    path: &Path,
    nx: usize,
    ny: usize,
    pitch_mm: Option<f64>,
    z_nm: &[f64],
    wavelength_nm: f64,
) -> Result<()> {
    let waves: Vec<f64> = z_nm.iter().map(|z| z / wavelength_nm).collect();
    let mut b = FileBuilder::new();
    let mut meas = b.create_group("Measurement");
    meas.set_attr("WavelengthInNanometers", AttrValue::F64(wavelength_nm));
    let mut siw = meas.create_group("SurfaceInWaves");
    if let Some(p) = pitch_mm {
        siw.set_attr("XYScale", AttrValue::F64(p * 1e-3));
    }
    siw.create_dataset("Data")
        .with_f64_data(&waves)
        .with_shape(&[ny as u64, nx as u64])
        .with_chunks(&[(ny as u64).clamp(1, 128), (nx as u64).clamp(1, 128)])
        .with_shuffle()
        .with_deflate(6);
    meas.add_group(siw.finish());
    b.add_group(meas.finish());
    b.write(path)
        .map_err(|e| Error::binary(path, "HDF5 writer", cause(&e)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn surface(nx: usize, ny: usize) -> Vec<f64> {
        (0..nx * ny)
            .map(|k| {
                if k % 17 == 3 {
                    f64::NAN
                } else {
                    ((k as f64) * 0.37).sin() * 40.0
                }
            })
            .collect()
    }

    #[test]
    fn datx_round_trips_in_nanometres_and_fringes() {
        let dir = tempfile::tempdir().unwrap();
        let (nx, ny) = (300, 260); // more than one chunk each way
        let z = surface(nx, ny);
        for unit in [
            DatxUnit::NanoMeters,
            DatxUnit::Fringes {
                wavelength_m: 632.8e-9,
                scale: 0.5,
                obliquity: 1.0,
            },
        ] {
            let p = dir.path().join("s.datx");
            write_zygo_datx(&p, nx, ny, 0.125, &z, unit).unwrap();
            let g = read_datx(&p).unwrap();
            assert_eq!((g.nx, g.ny), (nx, ny));
            assert!((g.pitch_mm - 0.125).abs() < 1e-12);
            for (a, b) in g.z_nm.iter().zip(&z) {
                assert!(
                    (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-12 * b.abs().max(1.0),
                    "{a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn four_d_reads_waves_times_wavelength() {
        let dir = tempfile::tempdir().unwrap();
        let z = surface(40, 30);
        let p = dir.path().join("m.h5");
        write_4d_h5(&p, 40, 30, Some(0.2), &z, 632.8).unwrap();
        let g = read_4d(&p, None).unwrap();
        assert!((g.pitch_mm - 0.2).abs() < 1e-12);
        for (a, b) in g.z_nm.iter().zip(&z) {
            assert!((a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-12 * b.abs().max(1.0));
        }
        write_4d_h5(&p, 40, 30, None, &z, 632.8).unwrap();
        let e = read_4d(&p, None).unwrap_err().to_string();
        assert!(e.contains("--pitch-mm"), "{e}");
        assert!((read_4d(&p, Some(0.5)).unwrap().pitch_mm - 0.5).abs() < 1e-15);
    }

    #[test]
    fn broken_files_name_the_object_and_cause() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.datx");
        write_zygo_datx(&p, 64, 64, 0.1, &surface(64, 64), DatxUnit::NanoMeters).unwrap();
        let b = std::fs::read(&p).unwrap();
        std::fs::write(&p, &b[..b.len() / 2]).unwrap();
        let e = read_datx(&p).unwrap_err().to_string();
        assert!(e.contains("s.datx"), "{e}");
        std::fs::write(&p, b"not an hdf5 file at all, just text").unwrap();
        let e = read_datx(&p).unwrap_err().to_string();
        assert!(e.contains("s.datx") && e.contains("HDF5"), "{e}");
        // A 4D file is not a datx: the missing group is named.
        let q = dir.path().join("m.h5");
        write_4d_h5(&q, 8, 8, Some(0.1), &surface(8, 8), 632.8).unwrap();
        let e = read_datx(&q).unwrap_err().to_string();
        assert!(e.contains("/Data/Surface"), "{e}");
    }
}
