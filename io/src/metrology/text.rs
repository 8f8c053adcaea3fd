//! Text maps: CSV with units in the header, and whitespace- or semicolon-separated XYZ files
//! with or without a header.

use super::{LengthUnit, MapSource, RawPoints, Units};
use crate::error::{Error, Result};
use crate::readers::{check_duplicates, read_map};
use crate::table::{read_table, ColumnSpec};
use std::io::BufReader;
use std::path::Path;

const X_NAMES: [(&str, LengthUnit); 3] = [
    ("x_mm", LengthUnit::Mm),
    ("x_um", LengthUnit::Um),
    ("x_m", LengthUnit::M),
];
const Y_NAMES: [(&str, LengthUnit); 3] = [
    ("y_mm", LengthUnit::Mm),
    ("y_um", LengthUnit::Um),
    ("y_m", LengthUnit::M),
];
const Z_NAMES: [(&str, LengthUnit); 4] = [
    ("z_nm", LengthUnit::Nm),
    ("z_um", LengthUnit::Um),
    ("z_mm", LengthUnit::Mm),
    ("z_m", LengthUnit::M),
];

/// The header line of a CSV file, split and trimmed.
fn csv_header(path: &Path) -> Result<Vec<String>> {
    let f = crate::limits::open_regular(path)?;
    let mut line = String::new();
    crate::limits::read_line_limited(&mut BufReader::new(f), &mut line, path, 1)?;
    Ok(line
        .trim_start_matches('\u{feff}')
        .trim()
        .split(',')
        .map(|s| s.trim().to_string())
        .collect())
}

fn conversion_note(axis: &str, from: LengthUnit, to: LengthUnit, assumed: bool) -> Option<String> {
    if assumed {
        Some(format!("{axis} taken in {} (no unit given)", from.name()))
    } else if from != to {
        Some(format!(
            "{axis} converted from {} to {} (x {})",
            from.name(),
            to.name(),
            from.factor_to(to)
        ))
    } else {
        None
    }
}

/// Reads a CSV map. `x_mm,y_mm,z_nm` is read as is; `x_um`/`x_m`, `y_um`/`y_m` and
/// `z_um`/`z_mm`/`z_m` are converted (with a note); with `--columns` or `--units` the file is read
/// as delimited text; any other header is an error naming the missing column.
pub(crate) fn read_csv(path: &Path, src: &MapSource) -> Result<RawPoints> {
    if src.columns.is_some() {
        return read_delimited(path, src, Some(b','));
    }
    let names = csv_header(path)?;
    let pick = |cands: &[(&'static str, LengthUnit)]| {
        cands
            .iter()
            .copied()
            .find(|(n, _)| names.iter().any(|h| h == n))
    };
    let (Some(x), Some(y), Some(z)) = (pick(&X_NAMES), pick(&Y_NAMES), pick(&Z_NAMES)) else {
        if src.units.is_some() {
            return read_delimited(path, src, Some(b','));
        }
        // The map reader's error: the missing column and a same-named column in another unit.
        read_map(path)?;
        return Err(Error::Empty {
            file: path.to_path_buf(),
            why: "no x_mm, y_mm and z_nm columns (or the same in um or m)".into(),
        });
    };
    if (x.0, y.0, z.0) == ("x_mm", "y_mm", "z_nm") {
        let m = read_map(path)?;
        let invalid = m.skipped_rows;
        let (xs, ys, zs) = (
            m.map.x_mm().to_vec(),
            m.map.y_mm().to_vec(),
            m.map.z_nm().to_vec(),
        );
        return Ok(RawPoints {
            x_mm: xs,
            y_mm: ys,
            z_nm: zs,
            invalid,
            pitch_mm: None,
            notes: Vec::new(),
        });
    }
    let mut t = read_table(
        path,
        &[
            ColumnSpec::required(x.0),
            ColumnSpec::required(y.0),
            ColumnSpec::required_skip(z.0),
        ],
    )?;
    let (fx, fy, fz) = (
        x.1.factor_to(LengthUnit::Mm),
        y.1.factor_to(LengthUnit::Mm),
        z.1.factor_to(LengthUnit::Nm),
    );
    let mut xs = t.take(0).unwrap_or_default();
    let mut ys = t.take(1).unwrap_or_default();
    let mut zs = t.take(2).unwrap_or_default();
    xs.iter_mut().for_each(|v| *v *= fx);
    ys.iter_mut().for_each(|v| *v *= fy);
    zs.iter_mut().for_each(|v| *v *= fz);
    super::check_ranges(path, &xs, &ys, &zs, Some(&t.lines))?;
    check_duplicates(path, &xs, &ys, &t.lines)?;
    let notes = [
        conversion_note(x.0, x.1, LengthUnit::Mm, false),
        conversion_note(y.0, y.1, LengthUnit::Mm, false),
        conversion_note(z.0, z.1, LengthUnit::Nm, false),
    ]
    .into_iter()
    .flatten()
    .map(|n| format!("{}: {n}", path.display()))
    .collect();
    Ok(RawPoints {
        x_mm: xs,
        y_mm: ys,
        z_nm: zs,
        invalid: t.skipped_rows,
        pitch_mm: None,
        notes,
    })
}

/// Reads a whitespace- or semicolon-separated XYZ map.
pub(crate) fn read_xyz(path: &Path, src: &MapSource) -> Result<RawPoints> {
    read_delimited(path, src, None)
}

fn split_line(line: &str, delim: Option<u8>) -> Vec<&str> {
    match delim {
        Some(d) => line.split(d as char).map(str::trim).collect(),
        None if line.contains(';') => line.split(';').map(str::trim).collect(),
        None if line.contains(',') => line.split(',').map(str::trim).collect(),
        None => line.split_whitespace().collect(),
    }
}

/// The role and unit a header name gives (`x_um` -> x in um; `Z` -> z, no unit); `Err` with the
/// suffix when a coordinate column carries a unit Preston does not know (`z_pm`).
fn header_role(name: &str) -> Option<(char, std::result::Result<Option<LengthUnit>, String>)> {
    let lower = name.to_ascii_lowercase();
    let (stem, unit) = match lower.split_once(['_', '(', '[', ' ']) {
        Some((s, u)) => {
            let u = u.trim_matches([')', ']', ' ']);
            (
                s.to_string(),
                u.parse::<LengthUnit>().map(Some).map_err(|_| u.to_string()),
            )
        }
        None => (lower.clone(), Ok(None)),
    };
    match stem.as_str() {
        "x" => Some(('x', unit)),
        "y" => Some(('y', unit)),
        "z" | "height" | "h" => Some(('z', unit)),
        _ => None,
    }
}

fn parse_cell(path: &Path, line: u64, column: &str, text: Option<&&str>) -> Result<Option<f64>> {
    let text = text.copied().unwrap_or("");
    if text.is_empty() {
        return Ok(None);
    }
    match text.parse::<f64>() {
        Ok(v) if v.is_nan() => Ok(None),
        Ok(v) if v.is_infinite() => Err(Error::Cell {
            file: path.to_path_buf(),
            line,
            column: column.into(),
            why: format!("`{text}` is infinite"),
        }),
        Ok(v) => Ok(Some(v)),
        Err(_) => Err(Error::Cell {
            file: path.to_path_buf(),
            line,
            column: column.into(),
            why: format!(
                "`{}` is not a number",
                text.chars().take(40).collect::<String>()
            ),
        }),
    }
}

/// Delimited text: `delim` (comma for CSV) or, for `None`, semicolons when the line has one,
/// else commas when it has one, else whitespace. Lines starting with `#`, `%` or `//` are comments. A first line that is
/// not all numbers is a header naming `x`, `y`, `z` (optionally with a unit suffix such as
/// `z_um`); `--columns` gives the order instead, `--units` the units (default mm, mm, nm).
fn read_delimited(path: &Path, src: &MapSource, delim: Option<u8>) -> Result<RawPoints> {
    let f = crate::limits::open_regular(path)?;
    let reader = BufReader::with_capacity(1 << 20, f);
    let max_fields = crate::limits::max_fields() as usize;
    let mut pos: Option<(usize, usize, usize)> = src.columns.as_ref().map(|c| c.positions());
    let mut header_units: [Option<LengthUnit>; 3] = [None; 3];
    let mut seen_first = false;
    let (mut xs, mut ys, mut zs, mut lines) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut invalid = 0usize;
    let mut buf = String::new();
    let mut reader = reader;
    let mut line_no = 0u64;
    loop {
        let n = crate::limits::read_line_limited(&mut reader, &mut buf, path, line_no + 1)?;
        if n == 0 {
            break;
        }
        line_no += 1;
        let line = buf.trim_start_matches('\u{feff}').trim();
        if line.is_empty()
            || line.starts_with('#')
            || line.starts_with('%')
            || line.starts_with("//")
        {
            continue;
        }
        let toks = split_line(line, delim);
        if toks.len() > max_fields {
            return Err(Error::Csv {
                file: path.to_path_buf(),
                line: line_no,
                why: format!(
                    "more than {max_fields} fields (the limit; raise it with --max-fields)"
                ),
            });
        }
        if !seen_first {
            seen_first = true;
            let numeric = toks
                .iter()
                .all(|t| t.parse::<f64>().is_ok() || t.is_empty());
            if !numeric {
                let header = header_columns(path, line_no, line, &toks, src, pos)?;
                (pos, header_units) = (header.pos, header.units);
                continue;
            }
        }
        let (x, y, z) = data_row(path, line_no, &toks, pos.unwrap_or((0, 1, 2)))?;
        match z {
            Some(z) => {
                xs.push(x);
                ys.push(y);
                zs.push(z);
                lines.push(line_no);
            }
            None => invalid += 1,
        }
    }
    let (units, notes) = units_and_notes(path, src, header_units);
    let (fx, fy, fz) = (
        units.x.factor_to(LengthUnit::Mm),
        units.y.factor_to(LengthUnit::Mm),
        units.z.factor_to(LengthUnit::Nm),
    );
    xs.iter_mut().for_each(|v| *v *= fx);
    ys.iter_mut().for_each(|v| *v *= fy);
    zs.iter_mut().for_each(|v| *v *= fz);
    super::check_ranges(path, &xs, &ys, &zs, Some(&lines))?;
    check_duplicates(path, &xs, &ys, &lines)?;
    Ok(RawPoints {
        x_mm: xs,
        y_mm: ys,
        z_nm: zs,
        invalid,
        pitch_mm: None,
        notes,
    })
}

/// What a header line says: the x, y and z columns, and the unit of each named with one.
struct HeaderColumns {
    pos: Option<(usize, usize, usize)>,
    units: [Option<LengthUnit>; 3],
}

/// The x, y and z columns and units a header line names (`toks`, the line `line_no`): the
/// columns given (`pos`) or found by name, the units found by name. An error for a unit it
/// cannot read (unless columns or units are given) or a header without x, y and z.
fn header_columns(
    path: &Path,
    line_no: u64,
    line: &str,
    toks: &[&str],
    src: &MapSource,
    pos: Option<(usize, usize, usize)>,
) -> Result<HeaderColumns> {
    let mut header_units: [Option<LengthUnit>; 3] = [None; 3];
    let mut found: [Option<usize>; 3] = [None; 3];
    for (k, t) in toks.iter().enumerate() {
        if let Some((role, unit)) = header_role(t) {
            let slot = match role {
                'x' => 0,
                'y' => 1,
                _ => 2,
            };
            let unit = match unit {
                Ok(u) => u,
                Err(_) if pos.is_some() || src.units.is_some() => None,
                Err(u) => {
                    return Err(Error::Csv {
                        file: path.to_path_buf(),
                        line: line_no,
                        why: format!(
                            "column `{t}`: unit `{u}` is not m, mm, um or nm; \
                             convert it or give --units"
                        ),
                    })
                }
            };
            if found[slot].is_none() {
                found[slot] = Some(k);
                header_units[slot] = unit;
            }
        }
    }
    if pos.is_some() {
        return Ok(HeaderColumns {
            pos,
            units: header_units,
        });
    }
    match found {
        [Some(a), Some(b), Some(c)] => Ok(HeaderColumns {
            pos: Some((a, b, c)),
            units: header_units,
        }),
        _ => Err(Error::Csv {
            file: path.to_path_buf(),
            line: line_no,
            why: format!(
                "the header `{}` does not name x, y and z columns; give \
                 --columns (for example x,y,z) and --units",
                line.chars().take(80).collect::<String>()
            ),
        }),
    }
}

/// The x, y and z of a data line (`toks`) from the columns `(px, py, pz)`; z `None` when empty
/// or NaN. An error for too few fields or an empty or NaN coordinate.
fn data_row(
    path: &Path,
    line_no: u64,
    toks: &[&str],
    (px, py, pz): (usize, usize, usize),
) -> Result<(f64, f64, Option<f64>)> {
    let need = px.max(py).max(pz) + 1;
    if toks.len() < need && !(toks.len() == need - 1 && pz == need - 1) {
        return Err(Error::Csv {
            file: path.to_path_buf(),
            line: line_no,
            why: format!("has {} fields, the columns need {need}", toks.len()),
        });
    }
    let x = parse_cell(path, line_no, "x", toks.get(px))?;
    let y = parse_cell(path, line_no, "y", toks.get(py))?;
    let z = parse_cell(path, line_no, "z", toks.get(pz))?;
    let (Some(x), Some(y)) = (x, y) else {
        return Err(Error::Cell {
            file: path.to_path_buf(),
            line: line_no,
            column: "x/y".into(),
            why: "empty or NaN coordinate".into(),
        });
    };
    Ok((x, y, z))
}

/// The units of the columns (given, else from the header, else mm, mm, nm) and the notes on
/// what was converted or assumed.
fn units_and_notes(
    path: &Path,
    src: &MapSource,
    header_units: [Option<LengthUnit>; 3],
) -> (Units, Vec<String>) {
    let units = match src.units {
        Some(u) => u,
        None => Units {
            x: header_units[0].unwrap_or(LengthUnit::Mm),
            y: header_units[1].unwrap_or(LengthUnit::Mm),
            z: header_units[2].unwrap_or(LengthUnit::Nm),
        },
    };
    let assumed = src.units.is_none();
    let mut notes = Vec::new();
    for (axis, from, to, was_assumed) in [
        (
            "x",
            units.x,
            LengthUnit::Mm,
            assumed && header_units[0].is_none(),
        ),
        (
            "y",
            units.y,
            LengthUnit::Mm,
            assumed && header_units[1].is_none(),
        ),
        (
            "z",
            units.z,
            LengthUnit::Nm,
            assumed && header_units[2].is_none(),
        ),
    ] {
        if let Some(n) = conversion_note(axis, from, to, was_assumed) {
            notes.push(format!("{}: {n}", path.display()));
        }
    }
    (units, notes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn file(name: &str, text: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join(name);
        std::fs::File::create(&p)
            .unwrap()
            .write_all(text.as_bytes())
            .unwrap();
        (dir, p)
    }

    #[test]
    fn csv_in_other_units_is_converted_with_a_note() {
        let (_d, p) = file("m.csv", "x_um,y_mm,z_um\n1000,0,0.5\n2000,1,nan\n0,1,-1\n");
        let r = read_csv(&p, &MapSource::default()).unwrap();
        assert_eq!(r.x_mm, vec![1.0, 0.0]);
        assert_eq!(r.z_nm, vec![500.0, -1000.0]);
        assert_eq!(r.invalid, 1);
        assert!(r
            .notes
            .iter()
            .any(|n| n.contains("x_um converted from um to mm")));
        assert!(r.notes.iter().any(|n| n.contains("z_um")));
    }

    #[test]
    fn xyz_whitespace_semicolon_header_or_not() {
        let (_d, p) = file("a.xyz", "# comment\n0 0 1.5\n1\t0  nan\n0 1 -2\n");
        let r = read_xyz(&p, &MapSource::default()).unwrap();
        assert_eq!((r.x_mm.len(), r.invalid), (2, 1));
        assert!(r.notes.iter().any(|n| n.contains("no unit given")));
        let (_d, p) = file("b.txt", "X[mm];Y[mm];Z[um]\n0;0;1\n1;0;2\n");
        let r = read_xyz(&p, &MapSource::default()).unwrap();
        assert_eq!(r.z_nm, vec![1000.0, 2000.0]);
        let (_d, p) = file("d.txt", "x_mm,y_mm,z_nm\n0,0,1\n1,0,2\n");
        let r = read_xyz(&p, &MapSource::default()).unwrap();
        assert_eq!(
            (r.x_mm.clone(), r.z_nm.clone()),
            (vec![0.0, 1.0], vec![1.0, 2.0])
        );
        assert!(r.notes.is_empty(), "{:?}", r.notes);
        let (_d, p) = file("c.txt", "5 0 0\n6 1 0\n");
        let src = MapSource {
            columns: Some("z,x,y".parse().unwrap()),
            units: Some("m,m,um".parse().unwrap()),
            ..MapSource::default()
        };
        let r = read_xyz(&p, &src).unwrap();
        assert_eq!(r.x_mm, vec![0.0, 1000.0]);
        assert_eq!(r.z_nm, vec![5000.0, 6000.0]);
    }

    #[test]
    fn xyz_errors_name_line_and_column() {
        let (_d, p) = file("a.xyz", "0 0 1\n1 zz 2\n");
        let e = read_xyz(&p, &MapSource::default()).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("`y`"), "{e}");
        let (_d, p) = file("a.xyz", "a b c\n0 0 1\n");
        let e = read_xyz(&p, &MapSource::default()).unwrap_err().to_string();
        assert!(e.contains("--columns"), "{e}");
        let (_d, p) = file("a.txt", "x_mm y_mm z_pm\n0 0 1\n");
        let e = read_xyz(&p, &MapSource::default()).unwrap_err().to_string();
        assert!(e.contains("z_pm") && e.contains("`pm`"), "{e}");
        let (_d, p) = file("a.csv", "x_mm,y_mm,z_pm\n0,0,1\n");
        let e = read_csv(&p, &MapSource::default()).unwrap_err().to_string();
        assert!(
            e.contains("missing column `z_nm`") && e.contains("z_pm"),
            "{e}"
        );
        let (_d, p) = file("a.xyz", "0 0 1\n0 0 2\n");
        let e = read_xyz(&p, &MapSource::default()).unwrap_err().to_string();
        assert!(e.contains("line 2 repeats"), "{e}");
    }
}
