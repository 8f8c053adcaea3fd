//! `preston map`: inspect and prepare measured maps: convert any readable format to the CSV
//! contract, remove form terms, fit Zernike or Legendre polynomials.

use super::map_input::{print_input_notes, MapInputArgs, PitchArg};
use anyhow::{bail, Context};
use preston_io::atomic::commit_all;
use preston_io::metrology::MapRead;
use preston_io::writers::{stage_map_csv, stage_map_npy};
use preston_solver::map::HeightStats;
use preston_solver::modal::{self, Basis, FormRemoval};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Arguments of `preston map`.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    pub command: MapCommand,
}

/// The `map` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum MapCommand {
    /// Read a map in any supported format and write it as x_mm,y_mm,z_nm.
    Convert(ConvertArgs),
    /// Remove form terms (piston, tilt, power, ...) by least squares; write the residual map.
    Detrend(ConvertArgs),
    /// Fit Zernike or Legendre polynomials by least squares; JSON on stdout.
    Fit(FitArgs),
}

/// Arguments of `preston map convert` and `preston map detrend`.
#[derive(Debug, clap::Args)]
pub struct ConvertArgs {
    /// The map (any supported format).
    #[arg(long, value_name = "FILE")]
    pub map: PathBuf,
    #[command(flatten)]
    pub input: MapInputArgs,
    #[command(flatten)]
    pub pitch: PitchArg,
    /// Output map: CSV x_mm,y_mm,z_nm, or a NumPy grid (heights in nm) for a .npy name.
    #[arg(long, value_name = "map.csv")]
    pub out: PathBuf,
}

/// Arguments of `preston map fit`.
#[derive(Debug, clap::Args)]
pub struct FitArgs {
    /// The map (any supported format).
    #[arg(long, value_name = "FILE")]
    pub map: PathBuf,
    #[command(flatten)]
    pub input: MapInputArgs,
    #[command(flatten)]
    pub pitch: PitchArg,
    /// Polynomial family.
    #[arg(long, value_enum)]
    pub basis: Basis,
    /// Number of terms (1-based indices 1..=N in the basis's ordering).
    #[arg(long)]
    pub terms: usize,
    /// Normalisation radius, mm (default: the smallest origin-centred disk holding the points;
    /// for legendre, the half-width of the smallest origin-centred square).
    #[arg(long, value_name = "MM")]
    pub norm_radius_mm: Option<f64>,
    /// Also write the fit residual as x_mm,y_mm,z_nm.
    #[arg(long, value_name = "residual.csv")]
    pub residual_out: Option<PathBuf>,
}

/// Runs `preston map`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    match args.command {
        MapCommand::Convert(a) => convert(a, false),
        MapCommand::Detrend(a) => convert(a, true),
        MapCommand::Fit(a) => fit(a),
    }
}

fn read(map: &Path, input: &MapInputArgs, pitch: PitchArg) -> anyhow::Result<MapRead> {
    let r = input.source(map.to_path_buf(), pitch.pitch_mm).read()?;
    print_input_notes(&r.input);
    Ok(r)
}

/// Writes the map as CSV `x_mm,y_mm,z_nm`, or as a NumPy grid for a `.npy` name (heights in nm;
/// the pitch and origin, which the file cannot carry, are printed).
fn write_map(out: &Path, r: &MapRead) -> anyhow::Result<()> {
    let m = &r.map;
    let npy = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    if npy {
        let (staged, pitch, origin) = stage_map_npy(out, m)?;
        commit_all(vec![staged]).with_context(|| format!("writing {}", out.display()))?;
        crate::errln!(
            "  {}: heights in nm, pitch {pitch} mm, cell (0, 0) at x {} y {} mm (read it back with --pitch-mm {pitch})",
            out.display(),
            origin[0],
            origin[1]
        );
        return Ok(());
    }
    commit_all(vec![stage_map_csv(out, m.x_mm(), m.y_mm(), m.z_nm())?])
        .with_context(|| format!("writing {}", out.display()))
}

/// The JSON printed by `map convert` and `map detrend`.
#[derive(Serialize)]
struct ConvertSummary<'a> {
    format: String,
    points: usize,
    invalid_points: usize,
    outside_aperture: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pitch_mm: Option<f64>,
    rms_nm: f64,
    pv_nm: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    removed: Option<&'a FormRemoval>,
}

fn convert(a: ConvertArgs, detrend: bool) -> anyhow::Result<u8> {
    if detrend && a.input.remove.as_ref().is_none_or(|r| r.0.is_empty()) {
        bail!("map detrend needs --remove (for example piston,tilt,power)");
    }
    let r = read(&a.map, &a.input, a.pitch)?;
    write_map(&a.out, &r)?;
    let s = HeightStats::of(r.map.z_nm());
    let summary = ConvertSummary {
        format: r.input.format.to_string(),
        points: r.map.len(),
        invalid_points: r.input.invalid_points,
        outside_aperture: r.input.outside_aperture,
        pitch_mm: r.input.pitch_mm,
        rms_nm: s.rms_nm,
        pv_nm: s.pv_nm,
        removed: r.input.removed.as_ref(),
    };
    crate::outln!("{}", serde_json::to_string_pretty(&summary)?);
    crate::errln!(
        "preston map {}: {} points, RMS {:.4} nm, PV {:.4} nm; wrote {}",
        if detrend { "detrend" } else { "convert" },
        r.map.len(),
        s.rms_nm,
        s.pv_nm,
        a.out.display()
    );
    Ok(crate::EXIT_OK)
}

/// The JSON printed by `map fit`.
#[derive(Serialize)]
struct FitSummary {
    basis: Basis,
    terms: usize,
    norm_radius_mm: f64,
    points: usize,
    /// Coefficients of terms 1..=N, nm.
    coefficients_nm: Vec<f64>,
    /// RMS of the fit residual about its mean, nm.
    rms_nm: f64,
    /// PV of the fit residual, nm.
    pv_nm: f64,
}

fn fit(a: FitArgs) -> anyhow::Result<u8> {
    let r = read(&a.map, &a.input, a.pitch)?;
    let m = &r.map;
    let basis: Basis = a.basis;
    let radius = match (a.norm_radius_mm, basis) {
        (Some(v), _) => v,
        (None, Basis::Legendre) => m
            .x_mm()
            .iter()
            .chain(m.y_mm())
            .fold(0.0f64, |acc, v| acc.max(v.abs())),
        (None, _) => modal::enclosing_radius_mm(m.x_mm(), m.y_mm()),
    };
    let f = modal::fit(m.x_mm(), m.y_mm(), m.z_nm(), basis, a.terms, radius)
        .with_context(|| format!("fitting {}", a.map.display()))?;
    let s = HeightStats::of(&f.residual_nm);
    if let Some(out) = &a.residual_out {
        commit_all(vec![stage_map_csv(
            out,
            m.x_mm(),
            m.y_mm(),
            &f.residual_nm,
        )?])
        .with_context(|| format!("writing {}", out.display()))?;
    }
    let summary = FitSummary {
        basis,
        terms: a.terms,
        norm_radius_mm: radius,
        points: m.len(),
        coefficients_nm: f.coefficients_nm,
        rms_nm: s.rms_nm,
        pv_nm: s.pv_nm,
    };
    crate::outln!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(crate::EXIT_OK)
}
