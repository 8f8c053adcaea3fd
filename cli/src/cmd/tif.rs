//! `preston tif`: tool influence functions from process models (Hertzian sphere, bonnet,
//! Gaussian) or a measured grid, written as the grid CSV `x_mm,y_mm,rate_nm_per_s` that
//! `preston solve --tif` reads; a JSON summary goes to stdout.

use anyhow::Context;
use preston_io::readers::read_tif;
use preston_io::surface::{read_surface, stage_columns_csv};
use preston_solver::tif::{
    BonnetParams, GaussianTif, GridAdjustment, GridTif, HertzPart, ProcessModel, SampledTif,
    TifSummary,
};
use std::path::{Path, PathBuf};

/// Arguments of `preston tif`.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    kind: Kind,
}

#[derive(Debug, clap::Subcommand)]
enum Kind {
    /// Spherical tool in Hertzian contact, spinning about a tilted axis.
    Hertz(HertzArgs),
    /// Bonnet tool pressed by a depth, precessed.
    Bonnet(BonnetArgs),
    /// Truncated Gaussian.
    Gaussian(GaussianArgs),
    /// Measured grid: resample, recentre on the centroid, scale to a peak or volume rate.
    Grid(GridArgs),
    /// Measured removal spot: (before - after) / dwell, background removed, cropped.
    Spot(super::tif_spot::SpotArgs),
}

/// `preston tif hertz`.
#[derive(Debug, clap::Args)]
struct HertzArgs {
    #[command(flatten)]
    model: super::hertz_args::HertzArgs,
    /// Part radius of curvature, mm: positive convex, negative concave; omitted: flat.
    #[arg(long, allow_negative_numbers = true)]
    part_radius_mm: Option<f64>,
    /// Take the part's principal curvatures from this surface JSON at `--at-mm X,Y`.
    #[arg(
        long,
        value_name = "S.json",
        conflicts_with = "part_radius_mm",
        requires = "at_mm"
    )]
    surface: Option<PathBuf>,
    /// Where on `--surface` the tool sits, X,Y mm.
    #[arg(long, value_parser = crate::cmd::path::parse_pair, allow_hyphen_values = true, requires = "surface", value_name = "X,Y")]
    at_mm: Option<(f64, f64)>,
    /// Grid pitch, mm.
    #[arg(long)]
    pitch_mm: f64,
    /// Output TIF CSV `x_mm,y_mm,rate_nm_per_s`.
    #[arg(long, value_name = "TIF.csv")]
    out: PathBuf,
}

/// `preston tif bonnet`.
#[derive(Debug, clap::Args)]
struct BonnetArgs {
    /// Bonnet radius, mm.
    #[arg(long)]
    bonnet_radius_mm: f64,
    /// Pressing depth, mm.
    #[arg(long)]
    depth_mm: f64,
    /// Precession angle, degrees.
    #[arg(long, default_value_t = 20.0)]
    precession_deg: f64,
    /// Precession azimuths averaged (1: one tilted position; 4: the usual four).
    #[arg(long, default_value_t = 1)]
    azimuths: usize,
    /// Spindle speed, rad/s.
    #[arg(long, default_value_t = 104.72)]
    spindle_rad_s: f64,
    /// Normal force, N.
    #[arg(long)]
    force_n: f64,
    /// Preston coefficient K, mm^2/N.
    #[arg(long)]
    preston_k: f64,
    /// Grid pitch, mm.
    #[arg(long)]
    pitch_mm: f64,
    /// Output TIF CSV.
    #[arg(long, value_name = "TIF.csv")]
    out: PathBuf,
}

/// `preston tif gaussian`.
#[derive(Debug, clap::Args)]
struct GaussianArgs {
    /// Standard deviation, mm.
    #[arg(long)]
    sigma_mm: f64,
    /// Peak removal rate, nm/s.
    #[arg(long)]
    peak_nm_per_s: f64,
    /// Truncation radius, mm (default 3 sigma).
    #[arg(long)]
    truncation_mm: Option<f64>,
    /// Grid pitch, mm.
    #[arg(long)]
    pitch_mm: f64,
    /// Output TIF CSV.
    #[arg(long, value_name = "TIF.csv")]
    out: PathBuf,
}

/// `preston tif grid`.
#[derive(Debug, clap::Args)]
struct GridArgs {
    /// Measured TIF CSV `x_mm,y_mm,rate_nm_per_s`.
    #[arg(long = "in", value_name = "IN.csv")]
    input: PathBuf,
    /// Resample (bilinear) onto this pitch, mm.
    #[arg(long)]
    pitch_mm: Option<f64>,
    /// Move the origin to the rate-weighted centroid.
    #[arg(long)]
    recentre: bool,
    /// Scale to this peak rate, nm/s.
    #[arg(long, conflicts_with = "volume_mm3_per_min")]
    peak_nm_per_s: Option<f64>,
    /// Scale to this volumetric rate, mm^3/min.
    #[arg(long)]
    volume_mm3_per_min: Option<f64>,
    /// Output TIF CSV.
    #[arg(long, value_name = "TIF.csv")]
    out: PathBuf,
}

/// Runs `preston tif`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let (SampledTif { grid, summary }, out) = match args.kind {
        Kind::Spot(a) => return super::tif_spot::run(a),
        Kind::Hertz(a) => {
            let p = a.model.params()?;
            let part = match (a.part_radius_mm, &a.surface, a.at_mm) {
                (Some(radius_mm), _, _) => HertzPart::Sphere { radius_mm },
                (None, Some(f), Some((x, y))) => {
                    let s = read_surface(f)?;
                    let (k1_per_mm, k2_per_mm) = s
                        .principal_curvatures_per_mm(x, y)
                        .with_context(|| format!("surface curvature at ({x}, {y}) mm"))?;
                    HertzPart::Curvatures {
                        k1_per_mm,
                        k2_per_mm,
                    }
                }
                _ => HertzPart::Flat,
            };
            (ProcessModel::hertz(&p, part)?.sample(a.pitch_mm)?, a.out)
        }
        Kind::Bonnet(a) => {
            let p = BonnetParams {
                bonnet_radius_mm: a.bonnet_radius_mm,
                depth_mm: a.depth_mm,
                precession_deg: a.precession_deg,
                precession_azimuths: a.azimuths,
                spindle_rad_s: a.spindle_rad_s,
                force_n: a.force_n,
                preston_k_mm2_per_n: a.preston_k,
            };
            (ProcessModel::bonnet(&p)?.sample(a.pitch_mm)?, a.out)
        }
        Kind::Gaussian(a) => {
            let g = GaussianTif::truncated(a.sigma_mm, a.peak_nm_per_s, a.truncation_mm)?;
            (ProcessModel::gaussian(g)?.sample(a.pitch_mm)?, a.out)
        }
        Kind::Grid(a) => {
            let adjust = GridAdjustment {
                pitch_mm: a.pitch_mm,
                recentre: a.recentre,
                peak_nm_per_s: a.peak_nm_per_s,
                volume_mm3_per_min: a.volume_mm3_per_min,
            };
            let grid = adjust.apply(read_tif(&a.input)?)?;
            let summary = TifSummary::of_measured(&grid);
            (SampledTif { grid, summary }, a.out)
        }
    };
    write_grid(&out, &grid)?;
    crate::outln!("{}", serde_json::to_string_pretty(&summary)?);
    crate::errln!(
        "preston tif: {} x {} grid; wrote {}",
        summary.nx,
        summary.ny,
        out.display()
    );
    Ok(crate::EXIT_OK)
}

/// Writes the grid as `x_mm,y_mm,rate_nm_per_s`, row-major, atomically.
pub(super) fn write_grid(path: &Path, g: &GridTif) -> anyhow::Result<()> {
    let (x, y, rate) = g.columns();
    stage_columns_csv(path, &["x_mm", "y_mm", "rate_nm_per_s"], &[&x, &y, rate])?
        .commit()
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
