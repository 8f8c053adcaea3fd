//! Streaming CSV reader for numeric tables whose columns are found by header name.
//!
//! Accepts a UTF-8 byte-order mark and Windows line endings; rejects missing columns (suggesting
//! a same-named column with another unit), non-numeric cells and infinities, naming file, line and
//! column. Memory grows with the requested columns only (8 bytes per value and row).

use crate::error::{Error, Result};
use crate::limits::{column_range, LimitedReader};
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

/// How a column treats empty and NaN cells.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Missing {
    /// Empty or NaN cells are errors.
    Reject,
    /// Empty or NaN cells drop the whole row (counted in [`Table::skipped_rows`]).
    SkipRow,
}

/// A column to read.
#[derive(Debug, Clone, Copy)]
pub struct ColumnSpec {
    /// Header name, with its unit (`x_mm`).
    pub name: &'static str,
    /// Whether the column must be present.
    pub required: bool,
    /// Treatment of empty and NaN cells.
    pub missing: Missing,
}

impl ColumnSpec {
    /// A required column whose cells must all be numbers.
    pub const fn required(name: &'static str) -> Self {
        Self {
            name,
            required: true,
            missing: Missing::Reject,
        }
    }

    /// A required column whose empty/NaN cells drop their row.
    pub const fn required_skip(name: &'static str) -> Self {
        Self {
            name,
            required: true,
            missing: Missing::SkipRow,
        }
    }

    /// An optional column.
    pub const fn optional(name: &'static str) -> Self {
        Self {
            name,
            required: false,
            missing: Missing::Reject,
        }
    }
}

/// The columns read from a CSV file.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    /// The file read.
    pub file: PathBuf,
    /// One vector per requested column, `None` for an absent optional column.
    pub columns: Vec<Option<Vec<f64>>>,
    /// The 1-based line of each kept row.
    pub lines: Vec<u64>,
    /// Rows dropped because a [`Missing::SkipRow`] column was empty or NaN.
    pub skipped_rows: usize,
}

impl Table {
    /// Column `k` (as requested); an empty slice for an absent optional column.
    pub fn column(&self, k: usize) -> &[f64] {
        self.columns
            .get(k)
            .and_then(|c| c.as_deref())
            .unwrap_or(&[])
    }

    /// Takes column `k` out of the table.
    pub fn take(&mut self, k: usize) -> Option<Vec<f64>> {
        self.columns.get_mut(k).and_then(Option::take)
    }

    /// Number of kept rows.
    pub fn len(&self) -> usize {
        self.lines.len()
    }

    /// True when no rows were kept.
    pub fn is_empty(&self) -> bool {
        self.lines.is_empty()
    }
}

/// Reads the requested columns of a CSV file.
pub fn read_table(path: &Path, specs: &[ColumnSpec]) -> Result<Table> {
    let file = crate::limits::open_regular(path)?;
    read_table_from(BufReader::with_capacity(1 << 20, file), path, specs)
}

/// Reads the requested columns from any reader; `path` names the source in messages.
pub fn read_table_from<R: Read>(reader: R, path: &Path, specs: &[ColumnSpec]) -> Result<Table> {
    let reader = LimitedReader::new(reader, b',');
    let ranges: Vec<Option<(f64, &str)>> = specs.iter().map(|s| column_range(s.name)).collect();
    let mut rdr = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(false)
        .trim(csv::Trim::All)
        // Records end at '\n' only; a Windows '\r' before it is trimmed as whitespace. This keeps
        // the reported line numbers right for CRLF files (csv counts '\r' and '\n' separately).
        .terminator(csv::Terminator::Any(b'\n'))
        .from_reader(reader);
    let headers = rdr.byte_headers().map_err(|e| csv_error(path, &e))?.clone();
    let names = header_names(&headers);
    if names.iter().all(|n| n.is_empty()) {
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: "the file is empty (no header line)".into(),
        });
    }
    let index = column_index(path, specs, &names)?;
    let mut columns: Vec<Option<Vec<f64>>> = index.iter().map(|k| k.map(|_| Vec::new())).collect();
    let mut lines = Vec::new();
    let mut skipped_rows = 0usize;
    let mut record = csv::ByteRecord::new();
    let mut row_values = vec![0.0f64; specs.len()];
    loop {
        match rdr.read_byte_record(&mut record) {
            Ok(true) => {}
            Ok(false) => break,
            Err(e) => return Err(csv_error(path, &e)),
        }
        let line = record.position().map(|p| p.line()).unwrap_or(0);
        if record.len() == 1 && record.get(0).is_some_and(|f| f.is_empty()) {
            continue; // a blank line
        }
        let mut skip = false;
        for (spec_k, ((spec, k), slot)) in specs
            .iter()
            .zip(&index)
            .zip(row_values.iter_mut())
            .enumerate()
        {
            let Some(k) = *k else { continue };
            let cell = record.get(k).unwrap_or(b"");
            let text = std::str::from_utf8(cell).map_err(|_| Error::Cell {
                file: path.to_path_buf(),
                line,
                column: spec.name.to_string(),
                why: "not valid UTF-8".into(),
            })?;
            let parsed = parse_cell(path, line, spec.name, text, ranges[spec_k])?;
            match (parsed, spec.missing) {
                (Some(v), _) => *slot = v,
                (None, Missing::SkipRow) => skip = true,
                (None, Missing::Reject) => {
                    return Err(Error::Cell {
                        file: path.to_path_buf(),
                        line,
                        column: spec.name.to_string(),
                        why: if text.is_empty() {
                            "empty cell".into()
                        } else {
                            format!("`{}` is not a finite number", truncate(text))
                        },
                    })
                }
            }
        }
        if skip {
            skipped_rows += 1;
            continue;
        }
        for (col, &v) in columns.iter_mut().zip(&row_values) {
            if let Some(c) = col {
                c.push(v);
            }
        }
        lines.push(line);
    }
    Ok(Table {
        file: path.to_path_buf(),
        columns,
        lines,
        skipped_rows,
    })
}

/// The header's column names, trimmed, without a byte-order mark on the first.
fn header_names(headers: &csv::ByteRecord) -> Vec<String> {
    headers
        .iter()
        .enumerate()
        .map(|(k, h)| {
            let s = String::from_utf8_lossy(h).to_string();
            let s = if k == 0 {
                s.trim_start_matches('\u{feff}').to_string()
            } else {
                s
            };
            s.trim().to_string()
        })
        .collect()
}

/// The column of each spec among `names` (`None` for an optional one that is absent); an error
/// for a required column missing or any column named twice.
fn column_index(path: &Path, specs: &[ColumnSpec], names: &[String]) -> Result<Vec<Option<usize>>> {
    let mut index: Vec<Option<usize>> = Vec::with_capacity(specs.len());
    for spec in specs {
        let found: Vec<usize> = names
            .iter()
            .enumerate()
            .filter(|(_, n)| n.as_str() == spec.name)
            .map(|(k, _)| k)
            .collect();
        match found.as_slice() {
            [k] => index.push(Some(*k)),
            [] if !spec.required => index.push(None),
            [] => {
                return Err(Error::MissingColumn {
                    file: path.to_path_buf(),
                    column: spec.name.to_string(),
                    found: truncate(&names.join(",")),
                    hint: hint_for(spec.name, names),
                })
            }
            _ => {
                return Err(Error::DuplicateColumn {
                    file: path.to_path_buf(),
                    column: spec.name.to_string(),
                })
            }
        }
    }
    Ok(index)
}

/// The value of one cell: `None` when empty or NaN; an error naming the cell when infinite,
/// not a number, or beyond the column's physical `range` (`(max |value|, what)`).
fn parse_cell(
    path: &Path,
    line: u64,
    column: &str,
    text: &str,
    range: Option<(f64, &str)>,
) -> Result<Option<f64>> {
    let cell_error = |why: String| Error::Cell {
        file: path.to_path_buf(),
        line,
        column: column.to_string(),
        why,
    };
    let parsed = if text.is_empty() {
        None
    } else {
        match text.parse::<f64>() {
            Ok(v) if v.is_nan() => None,
            Ok(v) if v.is_infinite() => {
                return Err(cell_error(format!("`{}` is infinite", truncate(text))))
            }
            Ok(v) => Some(v),
            Err(_) if text.contains(';') && !text.contains(',') => {
                return Err(cell_error(format!(
                    "`{}` is not a number; the values look separated by `;`, Preston's \
                     CSV is comma-separated",
                    truncate(text)
                )))
            }
            Err(_) => return Err(cell_error(format!("`{}` is not a number", truncate(text)))),
        }
    };
    if let (Some(v), Some((max, what))) = (parsed, range) {
        if v.abs() > max {
            return Err(cell_error(format!(
                "{v:e} is beyond the physical range of a {what} (|value| <= {max:e}); \
                 check the units"
            )));
        }
    }
    Ok(parsed)
}

fn truncate(s: &str) -> String {
    crate::limits::quote(s)
}

fn csv_error(path: &Path, e: &csv::Error) -> Error {
    let line = e.position().map(|p| p.line()).unwrap_or(0);
    let why = match e.kind() {
        csv::ErrorKind::UnequalLengths {
            expected_len, len, ..
        } => format!("has {len} fields where the header has {expected_len}"),
        csv::ErrorKind::Io(err) => {
            if let Some(limit) = err
                .get_ref()
                .and_then(|e| e.downcast_ref::<crate::limits::LimitExceeded>())
            {
                return Error::Csv {
                    file: path.to_path_buf(),
                    line: limit.line,
                    why: limit.why.clone(),
                };
            }
            return Error::io(path, std::io::Error::new(err.kind(), err.to_string()));
        }
        _ => e.to_string(),
    };
    Error::Csv {
        file: path.to_path_buf(),
        line,
        why,
    }
}

/// Suggests a present column with the same quantity and another unit (`x_um` for `x_mm`).
fn hint_for(wanted: &str, names: &[String]) -> String {
    if let [only] = names {
        if only.split_whitespace().count() > 1 {
            return "; the header is separated by spaces or tabs, not commas: a height map in \
                    whitespace-separated columns is read with `--map-format xyz` (`format = \
                    \"xyz\"` under [map]); Preston's other tables are comma-separated"
                .to_string();
        }
        for (d, name) in [(';', "semicolons"), ('|', "bars")] {
            if only.contains(d) {
                return format!(
                    "; the header is separated by {name}, not commas: Preston's CSV is \
                     comma-separated (write the file with `,` between fields)"
                );
            }
        }
    }
    let stem = wanted.split('_').next().unwrap_or(wanted);
    let unit = wanted.strip_prefix(stem).unwrap_or("");
    let close: Vec<&String> = names
        .iter()
        .filter(|n| n.split('_').next() == Some(stem) || n.eq_ignore_ascii_case(wanted))
        .collect();
    match close.first() {
        Some(n) => format!(
            "; found `{n}`: Preston reads `{wanted}` (unit `{}`), convert the column and rename it",
            unit.trim_start_matches('_')
        ),
        None => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPECS: [ColumnSpec; 3] = [
        ColumnSpec::required("x_mm"),
        ColumnSpec::required("y_mm"),
        ColumnSpec::required_skip("z_nm"),
    ];

    fn read(text: &str) -> Result<Table> {
        read_table_from(text.as_bytes(), Path::new("t.csv"), &SPECS)
    }

    #[test]
    fn columns_by_name_any_order_bom_crlf() {
        let t = read("\u{feff}z_nm,extra,y_mm,x_mm\r\n1,a,2,3\r\n4,b,5,6\r\n").unwrap();
        assert_eq!(t.column(0), &[3.0, 6.0]);
        assert_eq!(t.column(2), &[1.0, 4.0]);
        assert_eq!(t.lines, vec![2, 3]);
    }

    #[test]
    fn skipped_rows_counted() {
        let t = read("x_mm,y_mm,z_nm\n0,0,1\n1,0,\n2,0,NaN\n3,0,4\n").unwrap();
        assert_eq!(t.len(), 2);
        assert_eq!(t.skipped_rows, 2);
    }

    #[test]
    fn errors_name_line_and_column() {
        let e = read("x_mm,y_mm,z_nm\n0,0,1\n0,abc,1\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t.csv") && e.contains("line 3") && e.contains("y_mm"),
            "{e}"
        );
        let e = read("x_mm,y_mm,z_nm\n0,0,inf\n").unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("infinite"), "{e}");
        let e = read("x_um,y_mm,z_nm\n0,0,1\n").unwrap_err().to_string();
        assert!(
            e.contains("missing column `x_mm`") && e.contains("x_um"),
            "{e}"
        );
        let e = read("").unwrap_err().to_string();
        assert!(e.contains("empty"), "{e}");
        let e = read("x_mm,y_mm,z_nm\n0,0\n").unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
    }
}
