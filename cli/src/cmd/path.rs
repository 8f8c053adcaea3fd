//! `preston path`: tool paths (raster, intersection, spiral, chord-height, edge-offset, random)
//! written as `x_mm,y_mm,z_mm,tx,ty,tz,ds_mm`, optionally projected onto a design surface. The
//! file is a valid `preston solve --dwell` input (the reader takes `x_mm,y_mm` and ignores the rest).

use anyhow::{bail, Context};
use preston_io::surface::{read_surface, stage_columns_csv};
use preston_io::table::{read_table, ColumnSpec};
use preston_solver::map::BoundingBox;
use preston_solver::path::arcs::lines_with_arcs;
use preston_solver::path::chord_height::{chord_height_line, ChordHeightSettings};
use preston_solver::path::edge_offset::{edge_offset, EdgeOffsetSettings, SpotProgression};
use preston_solver::path::intersection::{
    clip_to_aperture, intersection_lines, lines_to_path, raster_lines,
};
use preston_solver::path::random::{random_unicursal, RandomPathSettings};
use preston_solver::path::raster::RasterAxis;
use preston_solver::path::spiral::archimedes;
use preston_solver::path::{project, DwellPath, PathSummary, ProjectedPath};
use preston_solver::surface::Surface;
use std::path::{Path, PathBuf};

/// Arguments of `preston path`.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    kind: Kind,
}

#[derive(Debug, clap::Subcommand)]
enum Kind {
    /// Serpentine raster over a rectangle (lines within P/2 of every point).
    Raster(RasterArgs),
    /// Raster of intersection iteration K: x, y, x + P/2, y + P/2, repeating.
    Intersection(IntersectionArgs),
    /// Archimedes spiral from the centre out to a radius.
    Spiral(SpiralArgs),
    /// Equal chord-height points along a line x = X on a surface.
    ChordHeight(ChordArgs),
    /// Lifting-bonnet edge-offset trajectory inside a closed edge.
    EdgeOffset(EdgeArgs),
    /// Pseudo-random unicursal path: every grid node once, one stroke, short straight runs.
    Random(RandomArgs),
}

/// Options every kind shares.
#[derive(Debug, clap::Args)]
struct Common {
    /// Project the path onto this surface JSON (z and 3-D tangents); without it z = 0.
    #[arg(long, value_name = "S.json")]
    surface: Option<PathBuf>,
    /// Output CSV `x_mm,y_mm,z_mm,tx,ty,tz,ds_mm`.
    #[arg(long, value_name = "PATH.csv")]
    out: PathBuf,
}

/// Parses `A,B` into two finite numbers.
pub(crate) fn parse_pair(s: &str) -> Result<(f64, f64), String> {
    let mut it = s.split(',');
    let (Some(a), Some(b), None) = (it.next(), it.next(), it.next()) else {
        return Err(format!("expected two numbers A,B, got `{s}`"));
    };
    let f = |t: &str| {
        t.trim()
            .parse::<f64>()
            .map_err(|e| format!("`{t}`: {e}"))
            .and_then(|v| {
                if v.is_finite() {
                    Ok(v)
                } else {
                    Err(format!("`{t}` is not finite"))
                }
            })
    };
    Ok((f(a)?, f(b)?))
}

/// Region and line options of the raster kinds.
#[derive(Debug, clap::Args)]
struct Region {
    /// x range A,B, mm.
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, value_name = "A,B")]
    x_mm: (f64, f64),
    /// y range C,D, mm.
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, value_name = "C,D")]
    y_mm: (f64, f64),
    /// Line pitch P, mm.
    #[arg(long)]
    pitch_mm: f64,
    /// Point spacing along the lines, mm (default: the pitch).
    #[arg(long)]
    step_mm: Option<f64>,
    /// Extend the region by this margin on every side, mm.
    #[arg(long, default_value_t = 0.0)]
    margin_mm: f64,
    /// Join lines by tangent-continuous circular arcs of this radius (at most P/2), mm.
    #[arg(long)]
    arc_radius_mm: Option<f64>,
    /// Largest distance of an arc's chords from the arc (sagitta), um, whatever the step.
    #[arg(long, default_value_t = 1.0)]
    arc_tolerance_um: f64,
    /// Clear-aperture polygon CSV `x_mm,y_mm`: keep only points inside it or within the margin.
    #[arg(long, value_name = "APERTURE.csv")]
    aperture: Option<PathBuf>,
}

impl Region {
    fn bbox(&self) -> anyhow::Result<BoundingBox> {
        let (a, b) = self.x_mm;
        let (c, d) = self.y_mm;
        if !(self.margin_mm.is_finite() && self.margin_mm >= 0.0) {
            bail!("--margin-mm must be non-negative, got {}", self.margin_mm);
        }
        let bbox = BoundingBox {
            x_min_mm: a.min(b),
            x_max_mm: a.max(b),
            y_min_mm: c.min(d),
            y_max_mm: c.max(d),
        }
        .expanded(self.margin_mm);
        let step = self.step_mm.unwrap_or(self.pitch_mm);
        if self.pitch_mm > 0.0 && step > 0.0 {
            // Lines across the region times points along them, x and y of each (and the lines'
            // own end points): checked before any line is generated.
            let (w, h) = (bbox.x_max_mm - bbox.x_min_mm, bbox.y_max_mm - bbox.y_min_mm);
            let along =
                |across: f64, length: f64| (across / self.pitch_mm + 1.0) * (length / step + 1.0);
            let points = along(h, w).max(along(w, h));
            preston_solver::budget::check_f64s(
                "--pitch-mm",
                &format!(
                    "a path of pitch {} mm and step {step} mm over the region (up to {points:.3e} \
                     points)",
                    self.pitch_mm
                ),
                points,
                4.0,
            )?;
        }
        Ok(bbox)
    }
}

#[derive(Debug, clap::Args)]
struct RasterArgs {
    #[command(flatten)]
    region: Region,
    /// Line direction.
    #[arg(long, value_enum, default_value = "x")]
    along: RasterAxis,
    #[command(flatten)]
    common: Common,
}

#[derive(Debug, clap::Args)]
struct IntersectionArgs {
    #[command(flatten)]
    region: Region,
    /// Iteration K (0-based).
    #[arg(long)]
    iteration: usize,
    #[command(flatten)]
    common: Common,
}

#[derive(Debug, clap::Args)]
struct SpiralArgs {
    /// Outer radius, mm.
    #[arg(long)]
    radius_mm: f64,
    /// Pitch between turns, mm.
    #[arg(long)]
    pitch_mm: f64,
    /// Point spacing along the spiral, mm (default: the pitch).
    #[arg(long)]
    step_mm: Option<f64>,
    /// Centre X,Y, mm.
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, default_value = "0,0", value_name = "X,Y")]
    centre_mm: (f64, f64),
    #[command(flatten)]
    common: Common,
}

#[derive(Debug, clap::Args)]
struct ChordArgs {
    /// The line's x, mm.
    #[arg(long, allow_negative_numbers = true)]
    line_x_mm: f64,
    /// From y = A to y = B, mm.
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, value_name = "A,B")]
    y_mm: (f64, f64),
    /// Tool radius r, mm.
    #[arg(long)]
    tool_radius_mm: f64,
    /// Chord-height window E1,E2, um.
    #[arg(long, value_parser = parse_pair, value_name = "E1,E2")]
    eps_um: (f64, f64),
    /// Step growth h_i, mm.
    #[arg(long, default_value_t = 0.10)]
    grow_mm: f64,
    /// Step shrink h_d, mm.
    #[arg(long, default_value_t = 0.02)]
    shrink_mm: f64,
    /// Surface JSON the line lies on (required); the output is projected onto it.
    #[arg(long, value_name = "S.json")]
    surface: PathBuf,
    /// Output CSV.
    #[arg(long, value_name = "PATH.csv")]
    out: PathBuf,
}

#[derive(Debug, clap::Args)]
struct EdgeArgs {
    /// Circular edge of this radius about the origin, mm.
    #[arg(long, conflicts_with = "edge", required_unless_present = "edge")]
    edge_radius_mm: Option<f64>,
    /// Closed edge polygon CSV `x_mm,y_mm` (first point not repeated).
    #[arg(long, value_name = "EDGE.csv")]
    edge: Option<PathBuf>,
    /// Bonnet radius, mm.
    #[arg(long)]
    bonnet_radius_mm: f64,
    /// Spot radius of the innermost line, mm.
    #[arg(long)]
    spot_max_mm: f64,
    /// Smallest spot radius, mm.
    #[arg(long)]
    spot_min_mm: f64,
    /// Geometric progression ratio q of the spot radii.
    #[arg(
        long,
        conflicts_with = "decrement_mm",
        required_unless_present = "decrement_mm"
    )]
    ratio: Option<f64>,
    /// Arithmetic progression decrement of the spot radii, mm.
    #[arg(long)]
    decrement_mm: Option<f64>,
    /// Residual height between lines, um.
    #[arg(long)]
    residual_um: f64,
    /// How far the smallest spot may reach beyond the edge, mm (0: tangent to it from inside).
    #[arg(long, default_value_t = 0.0)]
    overhang_mm: f64,
    /// Bezier fit tolerance, mm.
    #[arg(long, default_value_t = 0.01)]
    bezier_tol_mm: f64,
    /// Point spacing along the offset curves, mm.
    #[arg(long, default_value_t = 0.5)]
    step_mm: f64,
    #[command(flatten)]
    common: Common,
}

#[derive(Debug, clap::Args)]
struct RandomArgs {
    /// x range A,B, mm.
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, value_name = "A,B")]
    x_mm: (f64, f64),
    /// y range C,D, mm.
    #[arg(long, value_parser = parse_pair, allow_hyphen_values = true, value_name = "C,D")]
    y_mm: (f64, f64),
    /// Grid pitch P (the step length), mm.
    #[arg(long)]
    pitch_mm: f64,
    /// Seed of the random spanning tree.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Longest straight run, steps (at least 3).
    #[arg(long, default_value_t = 20)]
    max_run: usize,
    /// Node jitter, fraction of the pitch in [0, 1] (0: nodes on the lattice).
    #[arg(long, default_value_t = 0.0)]
    jitter: f64,
    #[command(flatten)]
    common: Common,
}

fn write(path: &DwellPath, surface: Option<&Surface>, out: &Path) -> anyhow::Result<ProjectedPath> {
    let p = project(path, surface).context("projecting the path onto the surface")?;
    stage_columns_csv(out, &ProjectedPath::HEADER, &p.columns())?
        .commit()
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(p)
}

fn read_polygon(f: &Path) -> anyhow::Result<Vec<[f64; 2]>> {
    let mut t = read_table(
        f,
        &[ColumnSpec::required("x_mm"), ColumnSpec::required("y_mm")],
    )?;
    let (x, y) = (t.take(0).unwrap_or_default(), t.take(1).unwrap_or_default());
    Ok(x.into_iter().zip(y).map(|(x, y)| [x, y]).collect())
}

fn load_surface(p: &Option<PathBuf>) -> anyhow::Result<Option<Surface>> {
    Ok(match p {
        Some(p) => Some(read_surface(p)?),
        None => None,
    })
}

fn raster_path(
    region: &Region,
    lines: &[preston_solver::path::intersection::Line],
) -> anyhow::Result<DwellPath> {
    let step = region.step_mm.unwrap_or(region.pitch_mm);
    let path = match region.arc_radius_mm {
        Some(r) => lines_with_arcs(lines, step, r, region.arc_tolerance_um * 1e-3)?,
        None => lines_to_path(lines, step)?,
    };
    Ok(match &region.aperture {
        Some(f) => {
            let poly = read_polygon(f)?;
            clip_to_aperture(&path, &poly, region.margin_mm)?
        }
        None => path,
    })
}

/// Runs `preston path`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let (summary, out) = match args.kind {
        Kind::Raster(a) => {
            let surface = load_surface(&a.common.surface)?;
            let lines = raster_lines(&a.region.bbox()?, a.region.pitch_mm, a.along, 0.0)?;
            let path = raster_path(&a.region, &lines)?;
            let p = write(&path, surface.as_ref(), &a.common.out)?;
            (PathSummary::raster(&p, lines.len()), a.common.out)
        }
        Kind::Intersection(a) => {
            let surface = load_surface(&a.common.surface)?;
            let lines = intersection_lines(&a.region.bbox()?, a.region.pitch_mm, a.iteration)?;
            let path = raster_path(&a.region, &lines)?;
            let p = write(&path, surface.as_ref(), &a.common.out)?;
            let s = PathSummary::intersection(&p, a.iteration, a.region.pitch_mm, lines.len());
            (s, a.common.out)
        }
        Kind::Spiral(a) => {
            let surface = load_surface(&a.common.surface)?;
            let path = archimedes(
                [a.centre_mm.0, a.centre_mm.1],
                a.radius_mm,
                a.pitch_mm,
                a.step_mm.unwrap_or(a.pitch_mm),
            )?;
            let p = write(&path, surface.as_ref(), &a.common.out)?;
            let s = PathSummary::spiral(&p, a.radius_mm, a.pitch_mm);
            (s, a.common.out)
        }
        Kind::ChordHeight(a) => {
            let surface = read_surface(&a.surface)?;
            let set = ChordHeightSettings {
                tool_radius_mm: a.tool_radius_mm,
                eps_min_mm: a.eps_um.0 * 1e-3,
                eps_max_mm: a.eps_um.1 * 1e-3,
                grow_mm: a.grow_mm,
                shrink_mm: a.shrink_mm,
                ..ChordHeightSettings::default()
            };
            let c = chord_height_line(&surface, a.line_x_mm, a.y_mm.0, a.y_mm.1, &set)?;
            let p = write(&c.path, Some(&surface), &a.out)?;
            (PathSummary::chord_height(&p, &c), a.out)
        }
        Kind::EdgeOffset(a) => {
            let surface = load_surface(&a.common.surface)?;
            let edge: Vec<[f64; 2]> = match (&a.edge, a.edge_radius_mm) {
                (Some(f), _) => read_polygon(f)?,
                (None, Some(r)) => {
                    if !(r.is_finite() && r > 0.0) {
                        bail!("--edge-radius-mm must be positive, got {r}");
                    }
                    (0..720)
                        .map(|i| {
                            let t = (i as f64 * 0.5).to_radians();
                            [r * t.cos(), r * t.sin()]
                        })
                        .collect()
                }
                (None, None) => bail!("give --edge or --edge-radius-mm"),
            };
            let progression = match (a.ratio, a.decrement_mm) {
                (Some(q), _) => SpotProgression::Geometric { ratio: q },
                (None, Some(d)) => SpotProgression::Arithmetic { decrement_mm: d },
                (None, None) => bail!("give --ratio or --decrement-mm"),
            };
            let set = EdgeOffsetSettings {
                bonnet_radius_mm: a.bonnet_radius_mm,
                spot_max_mm: a.spot_max_mm,
                spot_min_mm: a.spot_min_mm,
                progression,
                residual_height_mm: a.residual_um * 1e-3,
                overhang_mm: a.overhang_mm,
                bezier_tolerance_mm: a.bezier_tol_mm,
                step_mm: a.step_mm,
            };
            let t = edge_offset(&edge, &set)?;
            let p = write(&t.path, surface.as_ref(), &a.common.out)?;
            (PathSummary::edge_offset(p.len(), &t), a.common.out)
        }
        Kind::Random(a) => {
            let surface = load_surface(&a.common.surface)?;
            let (x0, x1) = a.x_mm;
            let (y0, y1) = a.y_mm;
            let region = BoundingBox {
                x_min_mm: x0.min(x1),
                x_max_mm: x0.max(x1),
                y_min_mm: y0.min(y1),
                y_max_mm: y0.max(y1),
            };
            let set = RandomPathSettings {
                pitch_mm: a.pitch_mm,
                seed: a.seed,
                max_run: a.max_run,
                jitter: a.jitter,
            };
            let r = random_unicursal(&region, &set)?;
            let p = write(&r.path, surface.as_ref(), &a.common.out)?;
            (PathSummary::random(&r, &set, Some(&p)), a.common.out)
        }
    };
    // As a JSON value, its keys in the order `preston path` has always printed (sorted).
    let summary = serde_json::to_value(&summary)?;
    crate::outln!("{}", serde_json::to_string_pretty(&summary)?);
    crate::errln!("preston path: wrote {}", out.display());
    Ok(crate::EXIT_OK)
}
