//! Zygo MetroPro binary `.dat` files.
//!
//! Layout (all header fields big-endian, offsets in bytes): magic number `0x881B036F`/`70`/`71`
//! at 0, header format (u16) at 4, header size (u32) at 6; intensity frame x, y, width, height,
//! buckets (u16) at 48..58; phase frame x, y, width, height (u16) at 64..72; intensity scale
//! factor `S` (f32) at 164, wavelength `lambda` in metres (f32) at 168, obliquity factor `O` (f32)
//! at 176, lateral resolution in metres per pixel (f32) at 184, phase resolution code (u16) at
//! 218 (0: `R` = 4096, 1: 32768, 2: 131072). After the header come the intensity frames
//! (u16, `width * height * buckets`) and the phase frame (i32, row-major, first row on top);
//! phase values `>= 2147483640` mark no data. Height `= phase * S * O * lambda / R`.
//! (Public descriptions: Zygo's MetroPro reference guide; prysm's `read_zygo_dat`.)

use super::grid::Grid;
use crate::error::{Error, Result};
use std::path::Path;

/// Smallest phase value meaning "no data".
pub const DAT_NO_DATA: i32 = 2_147_483_640;
const MAGIC: [u32; 3] = [0x881B_036F, 0x881B_0370, 0x881B_0371];
const MIN_HEADER: usize = 834;

/// The header fields of a MetroPro file that place and scale the phase frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DatHeader {
    /// Phase frame width, pixels.
    pub nx: u16,
    /// Phase frame height, pixels.
    pub ny: u16,
    /// Lateral resolution, m per pixel.
    pub lateral_resolution_m: f32,
    /// Wavelength, m.
    pub wavelength_m: f32,
    /// Interferometric scale factor `S`.
    pub scale_factor: f32,
    /// Obliquity factor `O`.
    pub obliquity: f32,
    /// Phase resolution code (0, 1 or 2).
    pub phase_res: u16,
}

impl DatHeader {
    /// Height of one phase count, nm: `S O lambda / R * 1e9`.
    pub fn quantum_nm(&self) -> Result<f64> {
        let r = match self.phase_res {
            0 => 4096.0,
            1 => 32768.0,
            2 => 131072.0,
            other => {
                return Err(Error::option(
                    "phase resolution",
                    format!("code {other} is not 0, 1 or 2"),
                ))
            }
        };
        Ok(dec(self.scale_factor) * dec(self.obliquity) * dec(self.wavelength_m) / r * 1e9)
    }
}

fn be_u16(b: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([b[at], b[at + 1]])
}
fn be_u32(b: &[u8], at: usize) -> u32 {
    u32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}
fn be_f32(b: &[u8], at: usize) -> f32 {
    f32::from_bits(be_u32(b, at))
}
/// A header `f32` as the decimal it was written from: the shortest decimal that rounds to it,
/// read as `f64` (so `2.5e-4` stays `2.5e-4`, not `2.4999999e-4`).
fn dec(v: f32) -> f64 {
    format!("{v:e}").parse().unwrap_or(f64::from(v))
}

/// Reads the phase frame of a MetroPro `.dat` file as heights in nm.
pub(crate) fn read_dat(path: &Path) -> Result<Grid> {
    let b = crate::limits::read_regular(path, preston_solver::budget::limit_bytes(), "map file")?;
    if b.len() < MIN_HEADER {
        return Err(Error::binary(
            path,
            "byte 0",
            format!(
                "the file is {} bytes, shorter than a MetroPro header ({MIN_HEADER} bytes)",
                b.len()
            ),
        ));
    }
    let magic = be_u32(&b, 0);
    if !MAGIC.contains(&magic) {
        return Err(Error::binary(
            path,
            "byte 0 (magic number)",
            format!("{magic:#010x} is not a MetroPro magic number (0x881b036f..0x881b0371)"),
        ));
    }
    let header_size = be_u32(&b, 6) as usize;
    if header_size < MIN_HEADER || header_size > b.len() {
        return Err(Error::binary(
            path,
            "byte 6 (header size)",
            format!(
                "header size {header_size} is outside {MIN_HEADER}..{} (the file's length)",
                b.len()
            ),
        ));
    }
    let (iw, ih, ib) = (
        be_u16(&b, 52) as usize,
        be_u16(&b, 54) as usize,
        be_u16(&b, 56).max(1) as usize,
    );
    let h = DatHeader {
        nx: be_u16(&b, 68),
        ny: be_u16(&b, 70),
        scale_factor: be_f32(&b, 164),
        wavelength_m: be_f32(&b, 168),
        obliquity: be_f32(&b, 176),
        lateral_resolution_m: be_f32(&b, 184),
        phase_res: be_u16(&b, 218),
    };
    let (nx, ny) = (h.nx as usize, h.ny as usize);
    if nx == 0 || ny == 0 {
        return Err(Error::binary(
            path,
            "byte 68 (phase frame size)",
            "the file holds no phase frame (width or height 0)",
        ));
    }
    let q = h
        .quantum_nm()
        .map_err(|e| Error::binary(path, "byte 218 (phase resolution)", e.to_string()))?;
    if !(q.is_finite() && q > 0.0) {
        return Err(Error::binary(
            path,
            "bytes 164..180 (scale factor, wavelength, obliquity)",
            format!("give a height per phase count of {q} nm, not a positive number"),
        ));
    }
    let pitch_mm = dec(h.lateral_resolution_m) * 1e3;
    if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
        return Err(Error::binary(
            path,
            "byte 184 (lateral resolution)",
            format!(
                "{} m per pixel is not a positive length",
                h.lateral_resolution_m
            ),
        ));
    }
    let start = header_size + iw * ih * ib * 2;
    let need = nx * ny * 4;
    if b.len() < start + need {
        return Err(Error::binary(
            path,
            format!("byte {start} (phase frame)"),
            format!(
                "truncated: the {nx} x {ny} phase frame needs {need} bytes, the file has {} after byte {start}",
                b.len().saturating_sub(start)
            ),
        ));
    }
    let z_nm = b[start..start + need]
        .chunks_exact(4)
        .map(|c| {
            let v = i32::from_be_bytes([c[0], c[1], c[2], c[3]]);
            if v >= DAT_NO_DATA {
                f64::NAN
            } else {
                f64::from(v) * q
            }
        })
        .collect();
    Ok(Grid {
        nx,
        ny,
        pitch_mm,
        z_nm,
        notes: vec![format!(
            "MetroPro phase x {q:.6e} nm per count (S {}, O {}, lambda {} m), pitch {pitch_mm} mm",
            h.scale_factor, h.obliquity, h.wavelength_m
        )],
    })
}

/// Writes a MetroPro `.dat` file (format 1 header, no intensity frame) holding `phase` counts
/// (row-major, first row on top; `DAT_NO_DATA` for no data). For synthetic test data and
/// benchmarks.
pub fn write_zygo_dat(path: &Path, h: &DatHeader, phase: &[i32]) -> Result<()> {
    let mut b = vec![0u8; MIN_HEADER];
    b[0..4].copy_from_slice(&MAGIC[0].to_be_bytes());
    b[4..6].copy_from_slice(&1u16.to_be_bytes());
    b[6..10].copy_from_slice(&(MIN_HEADER as u32).to_be_bytes());
    b[68..70].copy_from_slice(&h.nx.to_be_bytes());
    b[70..72].copy_from_slice(&h.ny.to_be_bytes());
    b[72..76].copy_from_slice(&(u32::from(h.nx) * u32::from(h.ny) * 4).to_be_bytes());
    b[164..168].copy_from_slice(&h.scale_factor.to_be_bytes());
    b[168..172].copy_from_slice(&h.wavelength_m.to_be_bytes());
    b[176..180].copy_from_slice(&h.obliquity.to_be_bytes());
    b[184..188].copy_from_slice(&h.lateral_resolution_m.to_be_bytes());
    b[218..220].copy_from_slice(&h.phase_res.to_be_bytes());
    for v in phase {
        b.extend_from_slice(&v.to_be_bytes());
    }
    std::fs::write(path, b).map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> DatHeader {
        DatHeader {
            nx: 4,
            ny: 3,
            lateral_resolution_m: 2.5e-4,
            wavelength_m: 632.8e-9,
            scale_factor: 0.5,
            obliquity: 1.0,
            phase_res: 1,
        }
    }

    #[test]
    fn reads_what_it_writes_with_the_published_scaling() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.dat");
        let phase: Vec<i32> = (0..12)
            .map(|k| if k == 5 { DAT_NO_DATA } else { k * 1000 - 4000 })
            .collect();
        write_zygo_dat(&p, &header(), &phase).unwrap();
        let g = read_dat(&p).unwrap();
        assert_eq!((g.nx, g.ny), (4, 3));
        assert!((g.pitch_mm - 0.25).abs() < 1e-9);
        // One count = 0.5 * 632.8e-9 / 32768 m.
        let q = 0.5 * 632.8e-9 / 32768.0 * 1e9;
        assert!((g.z_nm[1] - (-3000.0 * q)).abs() < 1e-9);
        assert!(g.z_nm[5].is_nan());
    }

    #[test]
    fn truncated_and_foreign_files_name_offset_and_cause() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.dat");
        write_zygo_dat(&p, &header(), &[0; 12]).unwrap();
        let mut b = std::fs::read(&p).unwrap();
        b.truncate(b.len() - 7);
        std::fs::write(&p, &b).unwrap();
        let e = read_dat(&p).unwrap_err().to_string();
        assert!(
            e.contains("a.dat") && e.contains("byte 834") && e.contains("truncated"),
            "{e}"
        );
        std::fs::write(&p, b"x_mm,y_mm,z_nm\n0,0,1\n").unwrap();
        let e = read_dat(&p).unwrap_err().to_string();
        assert!(e.contains("byte 0") && e.contains("shorter"), "{e}");
        let mut b = vec![0xABu8; 900];
        b[0..4].copy_from_slice(b"\x00\x01\x02\x03");
        std::fs::write(&p, &b).unwrap();
        let e = read_dat(&p).unwrap_err().to_string();
        assert!(e.contains("magic") && !e.contains("0xab"), "{e}");
    }
}
