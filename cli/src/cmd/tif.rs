//! `preston tif`: tool influence functions from process models (Hertzian sphere, bonnet,
//! Gaussian) or a measured grid, written as the grid CSV `x_mm,y_mm,rate_nm_per_s` that
//! `preston solve --tif` reads; a JSON summary goes to stdout.

use anyhow::{bail, Context};
use preston_io::readers::read_tif;
use preston_io::surface::{read_surface, stage_columns_csv};
use preston_solver::tif::bonnet::{BonnetParams, BonnetTif};
use preston_solver::tif::hertz::{sample_on_grid, HertzTif};
use preston_solver::tif::{GaussianTif, GridTif};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

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

/// What `preston tif` prints (stdout, JSON).
#[derive(Debug, Serialize)]
struct Summary {
    model: &'static str,
    /// Contact (spot, support) radius, mm.
    contact_radius_mm: f64,
    /// Peak contact pressure, MPa (null for Gaussian and measured grids).
    peak_pressure_mpa: Option<f64>,
    /// Largest rate in the written grid, nm/s.
    peak_rate_nm_per_s: f64,
    /// Volumetric removal rate of the model (quadrature), mm^3/min.
    volume_rate_mm3_per_min: f64,
    /// Volumetric rate of the written grid (bilinear, exact trapezoid), mm^3/min.
    grid_volume_rate_mm3_per_min: f64,
    /// Equivalent-circle FWHM of the grid, mm.
    fwhm_mm: f64,
    /// Sliding speed at the centre, mm/s (process models).
    centre_speed_mm_per_s: Option<f64>,
    /// Effective Hertz radius, mm (Hertz only).
    effective_radius_mm: Option<f64>,
    /// Grid shape.
    nx: usize,
    /// Grid shape.
    ny: usize,
    /// Grid pitch, mm.
    pitch_mm: f64,
}

/// Runs `preston tif`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let (grid, out, mut summary) = match args.kind {
        Kind::Spot(a) => return super::tif_spot::run(a),
        Kind::Hertz(a) => {
            let p = a.model.params()?;
            let t = match (a.part_radius_mm, &a.surface, a.at_mm) {
                (Some(r), _, _) => HertzTif::with_part_radius(&p, r)?,
                (None, Some(f), Some((x, y))) => {
                    let s = read_surface(f)?;
                    let (k1, k2) = s
                        .principal_curvatures_per_mm(x, y)
                        .with_context(|| format!("surface curvature at ({x}, {y}) mm"))?;
                    HertzTif::with_curvatures(&p, k1, k2)?
                }
                _ => HertzTif::flat(&p)?,
            };
            let grid = t.to_grid(a.pitch_mm)?;
            let s = Summary {
                model: "hertz",
                contact_radius_mm: t.contact_radius_mm(),
                peak_pressure_mpa: Some(t.peak_pressure_mpa()),
                volume_rate_mm3_per_min: t.volume_rate_mm3_per_s() * 60.0,
                centre_speed_mm_per_s: Some(t.sliding_speed_mm_per_s(0.0, 0.0)),
                effective_radius_mm: Some(t.effective_radius_mm()),
                ..blank()
            };
            (grid, a.out, s)
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
            let t = BonnetTif::new(&p)?;
            let grid = t.to_grid(a.pitch_mm)?;
            // The model volume by a fine grid (the pressure vanishes linearly at the edge, so
            // the trapezoid rule converges as pitch^2).
            let fine = t.to_grid(t.spot_radius_mm() / 400.0)?;
            let s = Summary {
                model: "bonnet",
                contact_radius_mm: t.spot_radius_mm(),
                peak_pressure_mpa: Some(t.peak_pressure_mpa()),
                volume_rate_mm3_per_min: fine.volume_rate_mm3_per_s() * 60.0,
                centre_speed_mm_per_s: Some(t.sliding_speed_mm_per_s(0.0, 0.0)),
                ..blank()
            };
            (grid, a.out, s)
        }
        Kind::Gaussian(a) => {
            let g = GaussianTif::new(
                a.sigma_mm,
                a.peak_nm_per_s,
                a.truncation_mm.unwrap_or(3.0 * a.sigma_mm),
            )?;
            let grid = sample_on_grid(&g, g.truncation_radius_mm, a.pitch_mm)?;
            let s = Summary {
                model: "gaussian",
                contact_radius_mm: g.truncation_radius_mm,
                volume_rate_mm3_per_min: g.volume_rate_mm3_per_s() * 60.0,
                ..blank()
            };
            (grid, a.out, s)
        }
        Kind::Grid(a) => {
            let mut g: GridTif = read_tif(&a.input)?;
            if let Some(p) = a.pitch_mm {
                g = g.resampled(p)?;
            }
            if a.recentre {
                g = g.recentred()?;
            }
            if let Some(p) = a.peak_nm_per_s {
                g = g.scaled_to_peak(p)?;
            }
            if let Some(v) = a.volume_mm3_per_min {
                g = g.scaled_to_volume(v / 60.0)?;
            }
            let s = Summary {
                model: "grid",
                contact_radius_mm: preston_solver::tif::InfluenceFunction::support_radius_mm(&g),
                volume_rate_mm3_per_min: g.volume_rate_mm3_per_s() * 60.0,
                ..blank()
            };
            (g, a.out, s)
        }
    };
    let (nx, ny) = grid.shape();
    summary.nx = nx;
    summary.ny = ny;
    summary.pitch_mm = grid.pitch_mm().0;
    summary.peak_rate_nm_per_s = grid.peak_rate_nm_per_s();
    summary.grid_volume_rate_mm3_per_min = grid.volume_rate_mm3_per_s() * 60.0;
    summary.fwhm_mm = grid.fwhm_mm();
    if summary.peak_rate_nm_per_s.is_nan() || summary.peak_rate_nm_per_s <= 0.0 {
        bail!("the TIF has no positive rate (check K, speed and force)");
    }
    write_grid(&out, &grid)?;
    crate::outln!("{}", serde_json::to_string_pretty(&summary)?);
    crate::errln!("preston tif: {nx} x {ny} grid; wrote {}", out.display());
    Ok(ExitCode::SUCCESS)
}

fn blank() -> Summary {
    Summary {
        model: "",
        contact_radius_mm: 0.0,
        peak_pressure_mpa: None,
        peak_rate_nm_per_s: 0.0,
        volume_rate_mm3_per_min: 0.0,
        grid_volume_rate_mm3_per_min: 0.0,
        fwhm_mm: 0.0,
        centre_speed_mm_per_s: None,
        effective_radius_mm: None,
        nx: 0,
        ny: 0,
        pitch_mm: 0.0,
    }
}

/// Writes the grid as `x_mm,y_mm,rate_nm_per_s`, row-major, atomically.
pub(super) fn write_grid(path: &Path, g: &GridTif) -> anyhow::Result<()> {
    let (nx, ny) = g.shape();
    let (x0, y0) = g.origin_mm();
    let (px, py) = g.pitch_mm();
    let mut x = Vec::with_capacity(nx * ny);
    let mut y = Vec::with_capacity(nx * ny);
    for iy in 0..ny {
        for ix in 0..nx {
            x.push(x0 + ix as f64 * px);
            y.push(y0 + iy as f64 * py);
        }
    }
    stage_columns_csv(
        path,
        &["x_mm", "y_mm", "rate_nm_per_s"],
        &[&x, &y, g.rates_nm_per_s()],
    )?
    .commit()
    .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
