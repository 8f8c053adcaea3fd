//! Writers for the engine's outputs. Every file is staged in a temporary file and renamed into
//! place (see [`crate::atomic`]).

use crate::atomic::{stage, Staged};
use crate::error::Result;
use crate::report::Report;
use std::path::Path;

/// Formats a float so that it reads back to the same value (shortest round-trip form).
fn num(v: f64) -> String {
    format!("{v}")
}

/// Stages `dwell.csv`: `x_mm,y_mm,ds_mm,dwell_s,feed_mm_per_min`.
pub fn stage_dwell_csv(
    path: &Path,
    x_mm: &[f64],
    y_mm: &[f64],
    ds_mm: &[f64],
    dwell_s: &[f64],
    feed_mm_per_min: &[f64],
) -> Result<Staged> {
    stage(path, |w| {
        writeln!(w, "x_mm,y_mm,ds_mm,dwell_s,feed_mm_per_min")?;
        for k in 0..x_mm.len() {
            let get = |v: &[f64]| v.get(k).copied().unwrap_or(f64::NAN);
            writeln!(
                w,
                "{},{},{},{},{}",
                num(get(x_mm)),
                num(get(y_mm)),
                num(get(ds_mm)),
                num(get(dwell_s)),
                num(get(feed_mm_per_min))
            )?;
        }
        Ok(())
    })
}

/// Stages `residual.csv`: `x_mm,y_mm,z_nm,removal_nm,residual_nm`.
pub fn stage_residual_csv(
    path: &Path,
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    removal_nm: &[f64],
    residual_nm: &[f64],
) -> Result<Staged> {
    stage(path, |w| {
        writeln!(w, "x_mm,y_mm,z_nm,removal_nm,residual_nm")?;
        for k in 0..x_mm.len() {
            let get = |v: &[f64]| v.get(k).copied().unwrap_or(f64::NAN);
            writeln!(
                w,
                "{},{},{},{},{}",
                num(get(x_mm)),
                num(get(y_mm)),
                num(get(z_nm)),
                num(get(removal_nm)),
                num(get(residual_nm))
            )?;
        }
        Ok(())
    })
}

/// Stages a map file `x_mm,y_mm,z_nm`.
pub fn stage_map_csv(path: &Path, x_mm: &[f64], y_mm: &[f64], z_nm: &[f64]) -> Result<Staged> {
    stage(path, |w| {
        writeln!(w, "x_mm,y_mm,z_nm")?;
        for ((x, y), z) in x_mm.iter().zip(y_mm).zip(z_nm) {
            writeln!(w, "{},{},{}", num(*x), num(*y), num(*z))?;
        }
        Ok(())
    })
}

/// Stages a pretty-printed JSON document.
pub fn stage_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<Staged> {
    stage(path, |w| {
        serde_json::to_writer_pretty(&mut *w, value).map_err(std::io::Error::other)?;
        writeln!(w)
    })
}

/// Stages `report.json`.
pub fn stage_report(path: &Path, report: &Report) -> Result<Staged> {
    stage_json(path, report)
}
