//! The map-input flags shared by every subcommand that reads a map (`--map-format`, `--columns`,
//! `--units`, `--aperture`, `--remove`), flattened into each one's arguments, and `--pitch-mm`
//! ([`PitchArg`], flattened separately: `iterate` has a `--pitch-mm` of its own and takes the
//! map's as `--map-pitch-mm`).

use preston_io::metrology::{
    parse_form_terms, ApertureSpec, Columns, MapFormat, MapInput, MapSource, Units,
};
use preston_solver::modal::FormTerm;
use std::path::PathBuf;

fn parse_columns(s: &str) -> Result<Columns, String> {
    s.parse().map_err(|e: preston_io::Error| e.to_string())
}
fn parse_units(s: &str) -> Result<Units, String> {
    s.parse().map_err(|e: preston_io::Error| e.to_string())
}
fn parse_aperture(s: &str) -> Result<ApertureSpec, String> {
    s.parse().map_err(|e: preston_io::Error| e.to_string())
}
/// A `--remove` list (one value holding several terms).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RemoveList(pub Vec<FormTerm>);

fn parse_remove(s: &str) -> Result<RemoveList, String> {
    parse_form_terms(s)
        .map(RemoveList)
        .map_err(|e| e.to_string())
}

/// How to read the map given by `--map`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct MapInputArgs {
    /// Map format (default: from the extension: .csv, .xyz/.txt/.asc, .npy, .dat, .datx,
    /// .h5/.4D).
    #[arg(long, value_enum)]
    pub map_format: Option<MapFormat>,
    /// Column order of a text map, e.g. x,y,z or z,x,y (`_` skips a column).
    #[arg(long, value_name = "x,y,z", value_parser = parse_columns)]
    pub columns: Option<Columns>,
    /// Units of a text map's x,y,z columns (m, mm, um, nm), e.g. mm,mm,um; default: from the
    /// header, else mm,mm,nm. For .npy the z unit applies.
    #[arg(long, value_name = "UX,UY,UZ", value_parser = parse_units)]
    pub units: Option<Units>,
    /// Clear aperture: circle:R[@x,y] | annulus:R1,R2 | rect:W,H | polygon:FILE (x_mm,y_mm), mm.
    #[arg(long, value_name = "SHAPE", value_parser = parse_aperture)]
    pub aperture: Option<ApertureSpec>,
    /// Form terms removed by least squares: piston,tilt,power,astig,coma,trefoil,spherical.
    #[arg(long, value_name = "LIST", value_parser = parse_remove)]
    pub remove: Option<RemoveList>,
}

impl MapInputArgs {
    /// Applies the flags given over `src` (a job's `[map]`).
    pub fn apply(&self, src: &mut MapSource) {
        if let Some(f) = self.map_format {
            src.format = Some(f);
        }
        if let Some(c) = &self.columns {
            src.columns = Some(c.clone());
        }
        if let Some(u) = self.units {
            src.units = Some(u);
        }
        if let Some(a) = &self.aperture {
            src.aperture = Some(a.clone());
        }
        if let Some(r) = &self.remove {
            src.remove.clone_from(&r.0);
        }
    }

    /// The source for `file` with these flags and the grid pitch.
    pub fn source(&self, file: PathBuf, pitch_mm: Option<f64>) -> MapSource {
        let mut s = MapSource::from_file(file);
        self.apply(&mut s);
        if pitch_mm.is_some() {
            s.pitch_mm = pitch_mm;
        }
        s
    }
}

/// `--pitch-mm`: the pixel pitch of a map grid that does not carry one.
#[derive(Debug, Clone, Copy, Default, clap::Args)]
pub struct PitchArg {
    /// Pixel pitch of a .npy grid (or a 4D file without one), mm.
    #[arg(long, value_name = "MM")]
    pub pitch_mm: Option<f64>,
}

/// Prints how a map was read (unit notes, dropped points, removed terms) on stderr.
pub fn print_input_notes(input: &MapInput) {
    for n in &input.notes {
        crate::note!("  note: {n}");
    }
    if input.invalid_points > 0 {
        crate::note!(
            "  note: {} points dropped (NaN, empty or no-data height)",
            input.invalid_points
        );
    }
    if input.outside_aperture > 0 {
        crate::note!(
            "  note: {} points outside the aperture dropped",
            input.outside_aperture
        );
    }
    if let Some(r) = &input.removed {
        let terms: Vec<String> = r
            .terms
            .iter()
            .map(|t| format!("Z{} {:.4} nm", t.noll, t.coefficient_nm))
            .collect();
        crate::note!(
            "  note: removed (Noll, normalisation radius {:.3} mm): {}",
            r.norm_radius_mm,
            terms.join(", ")
        );
    }
}
