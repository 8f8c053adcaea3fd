//! Measured maps in: every map format Preston reads, the options that tell it how to read them,
//! and the clear aperture and form-term removal applied to every map read.
//!
//! All readers give the same [`HeightMap`] (x, y in mm, heights in nm); invalid pixels (NaN or
//! the instrument's "no data" value) are dropped and counted. Gridded files (Zygo `.dat`/`.datx`,
//! 4D `.h5`/`.4D`, `.npy`) are placed with pixel `(row i, column j)` at
//! `x = (j - (nx - 1) / 2) p`, `y = ((ny - 1) / 2 - i) p` for pitch `p`: the grid is centred on
//! the origin and its first stored row is at the top (largest y), as the camera sees it.

mod grid;
mod hdf5;
mod npy;
mod text;
mod zygo;

pub use grid::Grid;
pub use hdf5::{write_4d_h5, write_zygo_datx, DatxUnit, DATX_NO_DATA};
pub use npy::write_npy;
pub use zygo::{write_zygo_dat, DatHeader, DAT_NO_DATA};

use crate::error::{Error, Result};
use crate::table::read_table;
use preston_solver::aperture::Aperture;
use preston_solver::map::HeightMap;
use preston_solver::modal::{remove_form, FormRemoval, FormTerm};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The file formats of a map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum MapFormat {
    /// Comma-separated with a header naming units (`x_mm,y_mm,z_nm`; also `x_um`, `x_m`, `z_um`,
    /// `z_m`, `z_mm`, converted).
    Csv,
    /// Whitespace- or semicolon-separated columns, with or without a header.
    Xyz,
    /// A 2-D NumPy array of heights (`--pitch-mm` gives the lateral pitch).
    Npy,
    /// Zygo MetroPro binary `.dat`.
    ZygoDat,
    /// Zygo Mx HDF5 `.datx`.
    ZygoDatx,
    /// 4D Technology HDF5 `.h5` / `.4D`.
    FourD,
}

impl MapFormat {
    /// The format a file's extension implies (`.csv`, `.xyz`/`.txt`/`.asc`, `.npy`, `.dat`,
    /// `.datx`, `.h5`/`.hdf5`/`.4d`), `None` for any other (read as CSV).
    pub fn from_extension(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        Some(match ext.as_str() {
            "csv" => MapFormat::Csv,
            "xyz" | "txt" | "asc" => MapFormat::Xyz,
            "npy" => MapFormat::Npy,
            "dat" => MapFormat::ZygoDat,
            "datx" => MapFormat::ZygoDatx,
            "h5" | "hdf5" | "4d" => MapFormat::FourD,
            _ => return None,
        })
    }

    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            MapFormat::Csv => "csv",
            MapFormat::Xyz => "xyz",
            MapFormat::Npy => "npy",
            MapFormat::ZygoDat => "zygo-dat",
            MapFormat::ZygoDatx => "zygo-datx",
            MapFormat::FourD => "four-d",
        }
    }
}

impl fmt::Display for MapFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A length unit of a map column.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LengthUnit {
    /// Metres.
    M,
    /// Millimetres.
    Mm,
    /// Micrometres.
    Um,
    /// Nanometres.
    Nm,
}

impl LengthUnit {
    /// Metres per unit.
    pub fn metres(self) -> f64 {
        match self {
            LengthUnit::M => 1.0,
            LengthUnit::Mm => 1e-3,
            LengthUnit::Um => 1e-6,
            LengthUnit::Nm => 1e-9,
        }
    }

    /// Decimal exponent of the unit in metres.
    fn exponent(self) -> i32 {
        match self {
            LengthUnit::M => 0,
            LengthUnit::Mm => -3,
            LengthUnit::Um => -6,
            LengthUnit::Nm => -9,
        }
    }

    /// Factor from this unit to `to`, `10^(e_from - e_to)` (exact for whole powers of ten).
    pub fn factor_to(self, to: LengthUnit) -> f64 {
        10f64.powi(self.exponent() - to.exponent())
    }

    /// The unit's suffix (`mm`).
    pub fn name(self) -> &'static str {
        match self {
            LengthUnit::M => "m",
            LengthUnit::Mm => "mm",
            LengthUnit::Um => "um",
            LengthUnit::Nm => "nm",
        }
    }
}

impl FromStr for LengthUnit {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s.trim().to_ascii_lowercase().as_str() {
            "m" => LengthUnit::M,
            "mm" => LengthUnit::Mm,
            "um" | "µm" | "micron" => LengthUnit::Um,
            "nm" => LengthUnit::Nm,
            other => {
                return Err(Error::option(
                    "--units",
                    format!("`{other}` is not a length unit (m, mm, um, nm)"),
                ))
            }
        })
    }
}

/// Units of the x, y and z columns of a text map (`--units mm,mm,um`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Units {
    /// Unit of x.
    pub x: LengthUnit,
    /// Unit of y.
    pub y: LengthUnit,
    /// Unit of z.
    pub z: LengthUnit,
}

impl Default for Units {
    fn default() -> Self {
        Self {
            x: LengthUnit::Mm,
            y: LengthUnit::Mm,
            z: LengthUnit::Nm,
        }
    }
}

impl FromStr for Units {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        let parts: Vec<&str> = s.split(',').collect();
        if parts.len() != 3 {
            return Err(Error::option(
                "--units",
                format!("`{s}` must give three units x,y,z (for example mm,mm,um)"),
            ));
        }
        Ok(Self {
            x: parts[0].parse()?,
            y: parts[1].parse()?,
            z: parts[2].parse()?,
        })
    }
}

impl TryFrom<String> for Units {
    type Error = Error;
    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<Units> for String {
    fn from(u: Units) -> String {
        format!("{},{},{}", u.x.name(), u.y.name(), u.z.name())
    }
}

/// What a column of a text map holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColumnRole {
    /// x coordinate.
    X,
    /// y coordinate.
    Y,
    /// Height.
    Z,
    /// Ignored.
    Skip,
}

/// The order of the columns of a text map (`--columns x,y,z`; `_` skips a column).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Columns(pub Vec<ColumnRole>);

impl Columns {
    /// 0-based positions of x, y and z.
    pub fn positions(&self) -> (usize, usize, usize) {
        let find = |r| self.0.iter().position(|c| *c == r).unwrap_or(0);
        (
            find(ColumnRole::X),
            find(ColumnRole::Y),
            find(ColumnRole::Z),
        )
    }
}

impl FromStr for Columns {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        let roles = s
            .split(',')
            .map(|c| match c.trim().to_ascii_lowercase().as_str() {
                "x" => Ok(ColumnRole::X),
                "y" => Ok(ColumnRole::Y),
                "z" => Ok(ColumnRole::Z),
                "_" | "-" | "skip" => Ok(ColumnRole::Skip),
                other => Err(Error::option(
                    "--columns",
                    format!("`{other}` is not x, y, z or _ (skip)"),
                )),
            })
            .collect::<Result<Vec<_>>>()?;
        for r in [ColumnRole::X, ColumnRole::Y, ColumnRole::Z] {
            if roles.iter().filter(|c| **c == r).count() != 1 {
                return Err(Error::option(
                    "--columns",
                    format!("`{s}` must name each of x, y and z exactly once"),
                ));
            }
        }
        Ok(Self(roles))
    }
}

impl TryFrom<String> for Columns {
    type Error = Error;
    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<Columns> for String {
    fn from(c: Columns) -> String {
        c.0.iter()
            .map(|r| match r {
                ColumnRole::X => "x",
                ColumnRole::Y => "y",
                ColumnRole::Z => "z",
                ColumnRole::Skip => "_",
            })
            .collect::<Vec<_>>()
            .join(",")
    }
}

/// A clear aperture as given on the command line or in a job: a shape, or a polygon file
/// (`x_mm,y_mm`, vertices in order) read when the map is read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum ApertureSpec {
    /// A shape given by its dimensions.
    Shape(Aperture),
    /// A polygon whose vertices are in a CSV file `x_mm,y_mm`.
    PolygonFile(PathBuf),
}

impl ApertureSpec {
    /// The aperture (reading the polygon file if there is one), validated.
    pub fn resolve(&self) -> Result<Aperture> {
        let a = match self {
            ApertureSpec::Shape(a) => a.clone(),
            ApertureSpec::PolygonFile(f) => {
                let mut t = read_table(
                    f,
                    &[
                        crate::table::ColumnSpec::required("x_mm"),
                        crate::table::ColumnSpec::required("y_mm"),
                    ],
                )?;
                let (x, y) = (t.take(0).unwrap_or_default(), t.take(1).unwrap_or_default());
                Aperture::Polygon {
                    vertices_mm: x.into_iter().zip(y).collect(),
                }
            }
        };
        a.validate().map_err(|e| match self {
            ApertureSpec::PolygonFile(f) => Error::engine(f, e),
            ApertureSpec::Shape(_) => Error::option("--aperture", e.to_string()),
        })?;
        Ok(a)
    }
}

fn parse_numbers(s: &str, n: usize, form: &str) -> Result<Vec<f64>> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| Error::option("--aperture", format!("`{s}`: expected {form}")))?;
    if v.len() != n || v.iter().any(|x| !x.is_finite()) {
        return Err(Error::option(
            "--aperture",
            format!("`{s}`: expected {form}"),
        ));
    }
    Ok(v)
}

impl FromStr for ApertureSpec {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        let (kind, rest) = s.split_once(':').ok_or_else(|| {
            Error::option(
                "--aperture",
                format!("`{s}` is not circle:R[@x,y], annulus:R1,R2, rect:W,H or polygon:FILE"),
            )
        })?;
        let spec = match kind.trim() {
            "circle" => {
                let (r, c) = match rest.split_once('@') {
                    Some((r, c)) => (r, Some(c)),
                    None => (rest, None),
                };
                let r = parse_numbers(r, 1, "circle:R[@x,y] in mm")?[0];
                let c = match c {
                    Some(c) => parse_numbers(c, 2, "circle:R@x,y in mm")?,
                    None => vec![0.0, 0.0],
                };
                ApertureSpec::Shape(Aperture::Circle {
                    radius_mm: r,
                    centre_x_mm: c[0],
                    centre_y_mm: c[1],
                })
            }
            "annulus" => {
                let v = parse_numbers(rest, 2, "annulus:R1,R2 in mm")?;
                ApertureSpec::Shape(Aperture::Annulus {
                    inner_radius_mm: v[0],
                    outer_radius_mm: v[1],
                })
            }
            "rect" => {
                let v = parse_numbers(rest, 2, "rect:W,H in mm")?;
                ApertureSpec::Shape(Aperture::Rect {
                    width_mm: v[0],
                    height_mm: v[1],
                })
            }
            "polygon" => {
                if rest.trim().is_empty() {
                    return Err(Error::option("--aperture", "polygon: needs a file"));
                }
                ApertureSpec::PolygonFile(PathBuf::from(rest.trim()))
            }
            other => {
                return Err(Error::option(
                    "--aperture",
                    format!("`{other}` is not circle, annulus, rect or polygon"),
                ))
            }
        };
        if let ApertureSpec::Shape(a) = &spec {
            a.validate()
                .map_err(|e| Error::option("--aperture", e.to_string()))?;
        }
        Ok(spec)
    }
}

impl TryFrom<String> for ApertureSpec {
    type Error = Error;
    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<ApertureSpec> for String {
    fn from(a: ApertureSpec) -> String {
        match a {
            ApertureSpec::PolygonFile(f) => format!("polygon:{}", f.display()),
            ApertureSpec::Shape(Aperture::Circle {
                radius_mm,
                centre_x_mm,
                centre_y_mm,
            }) => format!("circle:{radius_mm}@{centre_x_mm},{centre_y_mm}"),
            ApertureSpec::Shape(Aperture::Annulus {
                inner_radius_mm,
                outer_radius_mm,
            }) => format!("annulus:{inner_radius_mm},{outer_radius_mm}"),
            ApertureSpec::Shape(Aperture::Rect {
                width_mm,
                height_mm,
            }) => format!("rect:{width_mm},{height_mm}"),
            ApertureSpec::Shape(Aperture::Polygon { vertices_mm }) => format!(
                "polygon of {} vertices (write them to a file for polygon:FILE)",
                vertices_mm.len()
            ),
        }
    }
}

/// Parses a comma-separated list of form terms (`piston,tilt,power`).
pub fn parse_form_terms(s: &str) -> Result<Vec<FormTerm>> {
    s.split(',')
        .filter(|t| !t.trim().is_empty())
        .map(|t| {
            t.parse::<FormTerm>()
                .map_err(|e| Error::option("--remove", e.to_string()))
        })
        .collect()
}

/// How to read a map: the file and every option that applies to it.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapSource {
    /// The map file (any format of [`MapFormat`]).
    pub file: Option<PathBuf>,
    /// The format, overriding the file's extension.
    #[serde(default)]
    pub format: Option<MapFormat>,
    /// Column order of a text map (`x,y,z`; `_` skips a column).
    #[serde(default)]
    pub columns: Option<Columns>,
    /// Units of a text map's x, y and z columns (default: from the header, else mm,mm,nm).
    #[serde(default)]
    pub units: Option<Units>,
    /// Lateral pitch of a `.npy` grid (or of a 4D file without one), mm.
    #[serde(default)]
    pub pitch_mm: Option<f64>,
    /// Clear aperture: points outside it are dropped (and every statistic is over the rest).
    #[serde(default)]
    pub aperture: Option<ApertureSpec>,
    /// Form terms removed by least squares after the aperture is applied.
    #[serde(default)]
    pub remove: Vec<FormTerm>,
}

/// A map as read, with what reading it did.
#[derive(Debug, Clone, PartialEq)]
pub struct MapRead {
    /// The kept points (inside the aperture, form terms removed).
    pub map: HeightMap,
    /// What was read and how, for reports.
    pub input: MapInput,
}

/// How a map was read: for `report.json` (`map_input`) and stderr.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapInput {
    /// The format read.
    pub format: MapFormat,
    /// Points (rows or pixels) dropped for an empty, NaN or no-data height.
    pub invalid_points: usize,
    /// Points dropped outside the aperture.
    pub outside_aperture: usize,
    /// Lateral pitch of a gridded file, mm.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub pitch_mm: Option<f64>,
    /// Unit conversions and assumptions made while reading (also printed on stderr).
    #[serde(default)]
    pub notes: Vec<String>,
    /// Form terms removed, with their coefficients.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub removed: Option<FormRemoval>,
}

/// Raw points of a reader, before the aperture and form removal.
#[derive(Debug)]
pub(crate) struct RawPoints {
    pub x_mm: Vec<f64>,
    pub y_mm: Vec<f64>,
    pub z_nm: Vec<f64>,
    pub invalid: usize,
    pub pitch_mm: Option<f64>,
    pub notes: Vec<String>,
}

impl MapSource {
    /// A source for `file` with default options.
    pub fn from_file(file: impl Into<PathBuf>) -> Self {
        Self {
            file: Some(file.into()),
            ..Self::default()
        }
    }

    /// The format to read: `format`, else the file's extension, else CSV (the map contract).
    pub fn resolved_format(&self, file: &Path) -> MapFormat {
        self.format
            .or_else(|| MapFormat::from_extension(file))
            .unwrap_or(MapFormat::Csv)
    }

    /// Reads the map: the format's reader, then the aperture, then the form removal.
    pub fn read(&self) -> Result<MapRead> {
        let file = self
            .file
            .as_deref()
            .ok_or_else(|| Error::option("--map", "no map file given"))?;
        let format = self.resolved_format(file);
        let raw = match format {
            MapFormat::Csv => text::read_csv(file, self)?,
            MapFormat::Xyz => text::read_xyz(file, self)?,
            MapFormat::Npy => npy::read_npy(
                file,
                self.pitch_mm,
                self.units.map_or(LengthUnit::Nm, |u| u.z),
            )?
            .into_points(),
            MapFormat::ZygoDat => zygo::read_dat(file)?.into_points(),
            MapFormat::ZygoDatx => hdf5::read_datx(file)?.into_points(),
            MapFormat::FourD => hdf5::read_4d(file, self.pitch_mm)?.into_points(),
        };
        self.finish(file, format, raw)
    }

    fn finish(&self, file: &Path, format: MapFormat, raw: RawPoints) -> Result<MapRead> {
        let RawPoints {
            mut x_mm,
            mut y_mm,
            mut z_nm,
            invalid,
            pitch_mm,
            notes,
        } = raw;
        check_ranges(file, &x_mm, &y_mm, &z_nm, None)?;
        let mut outside = 0;
        if let Some(spec) = &self.aperture {
            let a = spec.resolve()?;
            let mut k = 0;
            for i in 0..x_mm.len() {
                if a.contains(x_mm[i], y_mm[i]) {
                    x_mm[k] = x_mm[i];
                    y_mm[k] = y_mm[i];
                    z_nm[k] = z_nm[i];
                    k += 1;
                }
            }
            outside = x_mm.len() - k;
            x_mm.truncate(k);
            y_mm.truncate(k);
            z_nm.truncate(k);
        }
        if x_mm.is_empty() {
            return Err(Error::Empty {
                file: file.to_path_buf(),
                why: format!(
                    "no valid points ({invalid} invalid{})",
                    if outside > 0 {
                        format!(", {outside} outside the aperture")
                    } else {
                        String::new()
                    }
                ),
            });
        }
        let removed = if self.remove.is_empty() {
            None
        } else {
            let (res, removal) = remove_form(&x_mm, &y_mm, &z_nm, &self.remove, None)
                .map_err(|e| Error::engine(file, e))?;
            z_nm = res;
            Some(removal)
        };
        let map = HeightMap::new(x_mm, y_mm, z_nm).map_err(|e| Error::engine(file, e))?;
        Ok(MapRead {
            map,
            input: MapInput {
                format,
                invalid_points: invalid,
                outside_aperture: outside,
                pitch_mm,
                notes,
                removed,
            },
        })
    }
}

/// Refuses coordinates and heights (after conversion to mm and nm) beyond the physical ranges of
/// [`crate::limits`], naming the line (`lines`, for text files) or the point (1-based, in file
/// order, for grids).
pub(crate) fn check_ranges(
    file: &Path,
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    lines: Option<&[u64]>,
) -> Result<()> {
    use crate::limits::{MAX_ABS_COORDINATE_MM, MAX_ABS_HEIGHT_NM};
    let bad = (0..x_mm.len()).find(|&k| {
        !(x_mm[k].abs() <= MAX_ABS_COORDINATE_MM
            && y_mm[k].abs() <= MAX_ABS_COORDINATE_MM
            && z_nm.get(k).is_none_or(|z| z.abs() <= MAX_ABS_HEIGHT_NM))
    });
    let Some(k) = bad else { return Ok(()) };
    let why = format!(
        "the point ({}, {}) mm, height {} nm is beyond the physical range (|x|, |y| <= \
         {MAX_ABS_COORDINATE_MM:e} mm, |z| <= {MAX_ABS_HEIGHT_NM:e} nm, finite); check the units",
        x_mm[k],
        y_mm[k],
        z_nm.get(k).copied().unwrap_or(0.0)
    );
    match lines.and_then(|l| l.get(k)) {
        Some(&line) => Err(Error::Csv {
            file: file.to_path_buf(),
            line,
            why,
        }),
        None => Err(Error::binary(file, format!("point {}", k + 1), why)),
    }
}

/// Reads a map with default options (format from the extension).
pub fn read_map_file(path: &Path) -> Result<MapRead> {
    MapSource::from_file(path).read()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn apertures_from_text_and_files_drop_points_outside() {
        let dir = tempfile::tempdir().unwrap();
        let map = dir.path().join("m.csv");
        let mut t = String::from("x_mm,y_mm,z_nm\n");
        for i in -5..=5 {
            for j in -5..=5 {
                t.push_str(&format!("{i},{j},{}\n", i * j));
            }
        }
        std::fs::write(&map, t).unwrap();
        let poly = dir.path().join("tri.csv");
        std::fs::write(&poly, "x_mm,y_mm\n0,0\n4,0\n0,4\n").unwrap();
        let count = |aperture: &str| {
            let src = MapSource {
                file: Some(map.clone()),
                aperture: Some(
                    aperture
                        .replace("FILE", poly.to_str().unwrap())
                        .parse()
                        .unwrap(),
                ),
                ..MapSource::default()
            };
            let r = src.read().unwrap();
            assert_eq!(r.map.len() + r.input.outside_aperture, 121);
            r.map.len()
        };
        // Lattice points in each shape, counted by hand.
        assert_eq!(count("circle:1"), 5);
        assert_eq!(count("annulus:1.2,2"), 8);
        assert_eq!(count("rect:4,2"), 15);
        assert_eq!(count("polygon:FILE"), 15);
        let src = MapSource {
            file: Some(map.clone()),
            aperture: Some("polygon:/nonexistent/p.csv".parse().unwrap()),
            ..MapSource::default()
        };
        assert!(src.read().unwrap_err().to_string().contains("p.csv"));
    }

    #[test]
    fn option_strings_parse_and_print() {
        let a: ApertureSpec = "circle:50@1.5,-2".parse().unwrap();
        assert_eq!(
            a,
            ApertureSpec::Shape(Aperture::Circle {
                radius_mm: 50.0,
                centre_x_mm: 1.5,
                centre_y_mm: -2.0
            })
        );
        assert_eq!(String::from(a.clone()).parse::<ApertureSpec>().unwrap(), a);
        assert!("annulus:5,2".parse::<ApertureSpec>().is_err());
        assert!("rect:3".parse::<ApertureSpec>().is_err());
        assert!("hexagon:3".parse::<ApertureSpec>().is_err());
        let u: Units = "mm,mm,um".parse().unwrap();
        assert_eq!(u.z, LengthUnit::Um);
        assert!((LengthUnit::Um.factor_to(LengthUnit::Nm) - 1e3).abs() < 1e-12);
        assert!("mm,mm".parse::<Units>().is_err());
        let c: Columns = "z,_,x,y".parse().unwrap();
        assert_eq!(c.positions(), (2, 3, 0));
        assert!("x,x,z".parse::<Columns>().is_err());
        assert_eq!(
            parse_form_terms("piston, tilt,power").unwrap(),
            vec![FormTerm::Piston, FormTerm::Tilt, FormTerm::Power]
        );
        assert_eq!(
            MapFormat::from_extension(Path::new("a.DATX")),
            Some(MapFormat::ZygoDatx)
        );
    }
}
