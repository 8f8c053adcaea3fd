//! Readers for the engine's inputs: height maps, TIF grids and dwell-point files.

use crate::error::{Error, Result};
use crate::table::{read_table, ColumnSpec};
use preston_solver::map::HeightMap;
use preston_solver::path::DwellPath;
use preston_solver::tif::GridTif;
use std::path::Path;

/// A map as read from `x_mm,y_mm,z_nm`, with the count of rows skipped for an empty or NaN height.
#[derive(Debug, Clone, PartialEq)]
pub struct MapFile {
    /// The kept points.
    pub map: HeightMap,
    /// Rows whose `z_nm` was empty or NaN.
    pub skipped_rows: usize,
}

/// Reads a height map (`x_mm,y_mm,z_nm`). Rows with an empty or NaN `z_nm` are skipped and
/// counted; repeated points and an empty result are errors.
pub fn read_map(path: &Path) -> Result<MapFile> {
    let mut t = read_table(
        path,
        &[
            ColumnSpec::required("x_mm"),
            ColumnSpec::required("y_mm"),
            ColumnSpec::required_skip("z_nm"),
        ],
    )?;
    if t.is_empty() {
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: if t.skipped_rows > 0 {
                format!("all {} rows have an empty or NaN z_nm", t.skipped_rows)
            } else {
                "no data rows".into()
            },
        });
    }
    let (x, y, z) = (
        t.take(0).unwrap_or_default(),
        t.take(1).unwrap_or_default(),
        t.take(2).unwrap_or_default(),
    );
    check_duplicates(path, &x, &y, &t.lines)?;
    let map = HeightMap::new(x, y, z).map_err(|e| Error::engine(path, e))?;
    Ok(MapFile {
        map,
        skipped_rows: t.skipped_rows,
    })
}

/// Reads a gridded TIF (`x_mm,y_mm,rate_nm_per_s`, rows in any order).
pub fn read_tif(path: &Path) -> Result<GridTif> {
    let t = read_table(
        path,
        &[
            ColumnSpec::required("x_mm"),
            ColumnSpec::required("y_mm"),
            ColumnSpec::required("rate_nm_per_s"),
        ],
    )?;
    if t.is_empty() {
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: "no data rows".into(),
        });
    }
    check_duplicates(path, t.column(0), t.column(1), &t.lines)?;
    GridTif::from_samples(t.column(0), t.column(1), t.column(2)).map_err(|e| Error::engine(path, e))
}

/// Dwell points read from a file, with dwell times when the file has them (a previous solution,
/// usable as a warm start or for simulation).
#[derive(Debug, Clone, PartialEq)]
pub struct DwellFile {
    /// The points in path order.
    pub path: DwellPath,
    /// `dwell_s` column, when present.
    pub dwell_s: Option<Vec<f64>>,
}

/// Reads dwell points (`x_mm,y_mm`, optional `dwell_s`) in path order.
pub fn read_dwell(path: &Path) -> Result<DwellFile> {
    read_dwell_columns(path, ColumnSpec::optional("dwell_s"))
}

/// The one dwell-file reader: `x_mm,y_mm` and the `dwell_s` column as `dwell` asks (optional,
/// or required for a solved dwell file); no repeated consecutive point, no negative dwell.
pub(crate) fn read_dwell_columns(path: &Path, dwell: ColumnSpec) -> Result<DwellFile> {
    let mut t = read_table(
        path,
        &[
            ColumnSpec::required("x_mm"),
            ColumnSpec::required("y_mm"),
            dwell,
        ],
    )?;
    if t.is_empty() {
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: "no dwell points".into(),
        });
    }
    let dwell_s = t.take(2);
    if let Some(d) = &dwell_s {
        if let Some((k, v)) = d.iter().enumerate().find(|(_, v)| **v < 0.0) {
            return Err(Error::Cell {
                file: path.to_path_buf(),
                line: t.lines.get(k).copied().unwrap_or(0),
                column: "dwell_s".into(),
                why: format!("negative dwell time {v}"),
            });
        }
    }
    let (x, y) = (t.take(0).unwrap_or_default(), t.take(1).unwrap_or_default());
    // A point equal to the one before it makes a segment of length zero: its feed would be 0.
    if let Some(k) = (1..x.len()).find(|&k| x[k] == x[k - 1] && y[k] == y[k - 1]) {
        return Err(Error::Csv {
            file: path.to_path_buf(),
            line: t.lines.get(k).copied().unwrap_or(0),
            why: format!(
                "repeats the point ({}, {}) mm of line {}: a segment of length zero has no feed; \
                 remove the repeat",
                x[k],
                y[k],
                t.lines.get(k - 1).copied().unwrap_or(0)
            ),
        });
    }
    let dp = DwellPath::new(x, y).map_err(|e| Error::engine(path, e))?;
    Ok(DwellFile { path: dp, dwell_s })
}

/// Rejects two rows with bit-identical coordinates (+0.0 and -0.0 alike), naming both lines (the
/// earliest repeat in file order). Sorts 32-bit row indices by coordinates: 4 bytes per row, so
/// large maps stream through with little memory on top of their values.
pub(crate) fn check_duplicates(path: &Path, x: &[f64], y: &[f64], lines: &[u64]) -> Result<()> {
    let n = u32::try_from(x.len()).map_err(|_| Error::Empty {
        file: path.to_path_buf(),
        why: format!(
            "{} rows: more than a map can hold (at most {})",
            x.len(),
            u32::MAX
        ),
    })?;
    let key = |k: u32| {
        let k = k as usize;
        ((x[k] + 0.0).to_bits(), (y[k] + 0.0).to_bits())
    };
    let mut order: Vec<u32> = (0..n).collect();
    order.sort_unstable_by(|&a, &b| key(a).cmp(&key(b)).then(a.cmp(&b)));
    // Among equal neighbours (first, repeat), the repeat that comes first in the file.
    let repeat = order
        .windows(2)
        .filter(|w| key(w[0]) == key(w[1]))
        .map(|w| (w[1] as usize, w[0] as usize))
        .min();
    match repeat {
        Some((k, first)) => Err(Error::DuplicatePoint {
            file: path.to_path_buf(),
            line: lines.get(k).copied().unwrap_or(0),
            first_line: lines.get(first).copied().unwrap_or(0),
            x_mm: x[k],
            y_mm: y[k],
        }),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn file(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(text.as_bytes()).unwrap();
        f
    }

    #[test]
    fn map_duplicates_and_empty() {
        let f = file("x_mm,y_mm,z_nm\n0,0,1\n1,0,2\n0,0,3\n");
        let e = read_map(f.path()).unwrap_err().to_string();
        assert!(e.contains("line 4") && e.contains("line 2"), "{e}");
        let f = file("x_mm,y_mm,z_nm\n");
        assert!(matches!(read_map(f.path()), Err(Error::Empty { .. })));
        let f = file("x_mm,y_mm,z_nm\n0,0,1\n1,0,nan\n");
        let m = read_map(f.path()).unwrap();
        assert_eq!((m.map.len(), m.skipped_rows), (1, 1));
    }

    #[test]
    fn tif_not_on_grid() {
        let f = file("x_mm,y_mm,rate_nm_per_s\n0,0,1\n1,0,1\n3,0,1\n0,1,1\n1,1,1\n3,1,1\n");
        let e = read_tif(f.path()).unwrap_err().to_string();
        assert!(e.contains("regular grid"), "{e}");
    }
}
