//! Writers for the engine's outputs. Every file is staged in a temporary file and renamed into
//! place (see [`crate::atomic`]).

use crate::atomic::{stage, Staged};
use crate::error::{Error, Result};
use crate::report::Report;
use preston_solver::map::HeightMap;
use std::path::Path;

/// Stages a CSV file: one header line, then one line per row with every column's value in the
/// shortest form that reads back to the same `f64`. Columns of unequal length are refused (an
/// error naming the file and the column), never truncated or padded.
pub fn stage_columns_csv(path: &Path, headers: &[&str], columns: &[&[f64]]) -> Result<Staged> {
    check_extension(path, "CSV", &["csv", "txt"])?;
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

/// Refuses a file name whose extension is not one of `allowed` (a name without one is
/// accepted): a writer never puts one format under another's extension.
pub fn check_extension(path: &Path, format: &str, allowed: &[&str]) -> Result<()> {
    let Some(ext) = path.extension() else {
        return Ok(());
    };
    let ext = ext.to_string_lossy().to_ascii_lowercase();
    if allowed.contains(&ext.as_str()) {
        return Ok(());
    }
    Err(Error::engine(
        path,
        preston_solver::Error::invalid(
            "output file name",
            format!(
                "this output is written as {format}; give a name ending in .{}",
                allowed.join(" or .")
            ),
        ),
    ))
}

/// Stages a map as a NumPy `.npy` grid: `(ny, nx)` little-endian `f8` heights in nm, C order,
/// rows in increasing y and columns in increasing x; cells of the lattice the map does not
/// cover are NaN. The map's points must lie on one lattice of equal pitch in x and y (a map
/// read from a grid does). Returns the pitch, mm, and the position of cell `(0, 0)`, mm, which
/// the file cannot carry.
pub fn stage_map_npy(path: &Path, map: &HeightMap) -> Result<(Staged, f64, [f64; 2])> {
    let refuse = |why: String| Error::engine(path, preston_solver::Error::invalid(".npy map", why));
    let axis = |v: &[f64]| {
        let mut u: Vec<f64> = v.to_vec();
        u.sort_by(f64::total_cmp);
        u.dedup();
        u
    };
    let (xs, ys) = (axis(map.x_mm()), axis(map.y_mm()));
    let step = |u: &[f64]| match u {
        [a, b, ..] => Some(b - a),
        _ => None,
    };
    let pitch = match (step(&xs), step(&ys)) {
        (Some(a), Some(b)) => a.min(b),
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => 1.0,
    };
    let index = |v: f64, origin: f64| -> Option<usize> {
        let k = (v - origin) / pitch;
        let r = k.round();
        ((k - r).abs() <= 1e-6 && r >= 0.0).then_some(r as usize)
    };
    let (x0, y0) = (xs[0], ys[0]);
    let nx = index(xs[xs.len() - 1], x0).map_or(0, |k| k + 1);
    let ny = index(ys[ys.len() - 1], y0).map_or(0, |k| k + 1);
    if nx == 0 || ny == 0 || (nx as f64) * (ny as f64) > 4.0 * map.len() as f64 + 16.0 {
        return Err(refuse(
            "the points do not lie on one lattice of equal x and y pitch; write .csv".into(),
        ));
    }
    let mut z = vec![f64::NAN; nx * ny];
    for k in 0..map.len() {
        match (index(map.x_mm()[k], x0), index(map.y_mm()[k], y0)) {
            (Some(i), Some(j)) if i < nx && j < ny => z[j * nx + i] = map.z_nm()[k],
            _ => {
                return Err(refuse(format!(
                    "point {k} (x {} y {} mm) is off the {pitch} mm lattice; write .csv",
                    map.x_mm()[k],
                    map.y_mm()[k]
                )))
            }
        }
    }
    let staged = stage(path, |w| {
        let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({ny}, {nx}), }}");
        let mut header = dict.into_bytes();
        while (10 + header.len() + 1) % 64 != 0 {
            header.push(b' ');
        }
        header.push(b'\n');
        w.write_all(b"\x93NUMPY\x01\x00")?;
        w.write_all(&(header.len() as u16).to_le_bytes())?;
        w.write_all(&header)?;
        for v in &z {
            w.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    })?;
    Ok((staged, pitch, [x0, y0]))
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
