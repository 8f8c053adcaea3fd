//! Writers for the engine's outputs. Every file is staged in a temporary file and renamed into
//! place (see [`crate::atomic`]).

use crate::atomic::{stage, Staged};
use crate::error::{Error, Result};
use crate::report::Report;
use std::path::Path;

/// Stages a CSV file: one header line, then one line per row with every column's value in the
/// shortest form that reads back to the same `f64`. Columns of unequal length are refused (an
/// error naming the file and the column), never truncated or padded.
pub fn stage_columns_csv(path: &Path, headers: &[&str], columns: &[&[f64]]) -> Result<Staged> {
    let refuse =
        |why: String| Error::engine(path, preston_solver::Error::invalid("CSV columns", why));
    if headers.len() != columns.len() {
        return Err(refuse(format!(
            "{} headers for {} columns",
            headers.len(),
            columns.len()
        )));
    }
    let rows = columns.first().map_or(0, |c| c.len());
    if let Some((h, c)) = headers.iter().zip(columns).find(|(_, c)| c.len() != rows) {
        return Err(refuse(format!(
            "column {h} has {} values where {} has {rows}",
            c.len(),
            headers[0]
        )));
    }
    stage(path, |w| {
        writeln!(w, "{}", headers.join(","))?;
        let mut line = String::new();
        for r in 0..rows {
            line.clear();
            for (k, c) in columns.iter().enumerate() {
                if k > 0 {
                    line.push(',');
                }
                line.push_str(&format!("{}", c[r]));
            }
            writeln!(w, "{line}")?;
        }
        Ok(())
    })
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
    stage_columns_csv(
        path,
        &["x_mm", "y_mm", "ds_mm", "dwell_s", "feed_mm_per_min"],
        &[x_mm, y_mm, ds_mm, dwell_s, feed_mm_per_min],
    )
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
    stage_columns_csv(
        path,
        &["x_mm", "y_mm", "z_nm", "removal_nm", "residual_nm"],
        &[x_mm, y_mm, z_nm, removal_nm, residual_nm],
    )
}

/// Stages a map file `x_mm,y_mm,z_nm`.
pub fn stage_map_csv(path: &Path, x_mm: &[f64], y_mm: &[f64], z_nm: &[f64]) -> Result<Staged> {
    stage_columns_csv(path, &["x_mm", "y_mm", "z_nm"], &[x_mm, y_mm, z_nm])
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unequal_columns_are_refused_and_equal_ones_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.csv");
        let e = stage_columns_csv(&p, &["a_mm", "b_nm"], &[&[1.0, 2.0], &[3.0]])
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("b_nm") && e.contains("c.csv"), "{e}");
        assert!(stage_columns_csv(&p, &["a_mm"], &[&[1.0], &[2.0]]).is_err());
        let x = [0.1, 1.0 / 3.0, -2.5e-12];
        crate::atomic::commit_all(vec![
            stage_columns_csv(&p, &["x_mm", "y_mm"], &[&x, &x]).unwrap()
        ])
        .unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        let back: Vec<f64> = text
            .lines()
            .skip(1)
            .map(|l| l.split(',').next().unwrap().parse().unwrap())
            .collect();
        assert_eq!(back, x);
        assert!(text.starts_with("x_mm,y_mm\n"));
    }
}
