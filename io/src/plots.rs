//! Plots (plotters): maps of scattered values with a colour bar in their unit, tool paths,
//! TIFs, PSDs and convergence curves, as PNG or, for a destination ending in `.svg`, as SVG
//! ([`PlotFormat`]; the map rasters are embedded in the SVG as PNG images, the axes, text and
//! curves are vectors). Every plot is rendered in memory, staged as a temporary file next to its
//! destination and renamed into place together with the command's other outputs
//! ([`crate::atomic::commit_all`]).
//!
//! Text uses the DejaVu Sans font shipped in `io/assets` (Bitstream Vera licence, see
//! `io/assets/DejaVuSans-LICENSE.txt`), so plots look the same on every machine.

use crate::atomic::{commit_all, stage, Staged};
use crate::error::{Error, Result};
use plotters::coord::combinators::BindKeyPoints;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use std::path::Path;
use std::sync::Once;

/// Plot width and height, pixels.
pub const PLOT_SIZE_PX: (u32, u32) = (900, 700);

static FONT: Once = Once::new();

fn register_font() {
    FONT.call_once(|| {
        // The bytes are a valid TrueType font; if registration failed anyway, text would be
        // missing from the plots but nothing else would change.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../assets/DejaVuSans.ttf"),
        );
    });
}

fn plot_error<E: std::fmt::Display>(path: &Path, e: E) -> Error {
    Error::io(path, std::io::Error::other(format!("plotting failed: {e}")))
}

/// The file format of a plot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum PlotFormat {
    /// Portable Network Graphics, a raster image.
    #[default]
    Png,
    /// Scalable Vector Graphics: axes, text and curves as vectors, map rasters embedded as PNG.
    Svg,
}

impl PlotFormat {
    /// The file extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            PlotFormat::Png => "png",
            PlotFormat::Svg => "svg",
        }
    }

    /// The file name of the figure `stem` in this format, e.g. `residual.svg`.
    pub fn file_name(self, stem: &str) -> String {
        format!("{stem}.{}", self.extension())
    }

    /// The format a plot written to `path` gets: SVG for a `.svg` extension (any case), else PNG.
    pub fn of_path(path: &Path) -> PlotFormat {
        match path.extension().and_then(|e| e.to_str()) {
            Some(e) if e.eq_ignore_ascii_case("svg") => PlotFormat::Svg,
            _ => PlotFormat::Png,
        }
    }
}

impl std::str::FromStr for PlotFormat {
    type Err = String;

    /// `png` or `svg`.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "png" => Ok(PlotFormat::Png),
            "svg" => Ok(PlotFormat::Svg),
            _ => Err(format!("`{s}`: give `png` or `svg`")),
        }
    }
}

/// The root drawing area of a plot.
type Root<DB> = DrawingArea<DB, plotters::coord::Shift>;

/// Draws on a canvas of `size_px` in memory with `draw` and stages the PNG for `path` (committed
/// together with the other outputs, see [`crate::atomic::stage`]).
fn stage_png_sized<F>(path: &Path, size_px: (u32, u32), draw: F) -> Result<Staged>
where
    F: FnOnce(&Root<BitMapBackend<'_>>) -> Result<()>,
{
    register_font();
    let (w, h) = size_px;
    let mut rgb = vec![0u8; w as usize * h as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size_px).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_error(path, e))?;
        draw(&root)?;
        root.present().map_err(|e| plot_error(path, e))?;
    }
    stage(path, |out: &mut dyn std::io::Write| {
        let mut encoder = png::Encoder::new(out, w, h);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(std::io::Error::other)?;
        writer
            .write_image_data(&rgb)
            .map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)
    })
}

/// Draws on an SVG canvas of `size_px` (user units of one pixel) with `draw` and stages the
/// document for `path`.
fn stage_svg_sized<F>(path: &Path, size_px: (u32, u32), draw: F) -> Result<Staged>
where
    F: FnOnce(&Root<SVGBackend<'_>>) -> Result<()>,
{
    register_font();
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size_px).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_error(path, e))?;
        draw(&root)?;
        root.present().map_err(|e| plot_error(path, e))?;
    }
    // plotters writes embedded images with the media type `png`; browsers and editors want the
    // registered `image/png`.
    let svg = svg.replace("href=\"data:png;base64,", "href=\"data:image/png;base64,");
    stage(path, |out: &mut dyn std::io::Write| {
        out.write_all(svg.as_bytes())
    })
}

/// Stages the plot that `|root| body` draws on a canvas of `size_px` at `path`, in the format of
/// the path ([`PlotFormat::of_path`]): the drawing is written once and instantiated for each
/// backend.
macro_rules! stage_plot {
    ($path:expr, $size_px:expr, |$root:ident| $body:expr) => {{
        let path: &Path = $path;
        match PlotFormat::of_path(path) {
            PlotFormat::Png => stage_png_sized(path, $size_px, |$root| $body),
            PlotFormat::Svg => stage_svg_sized(path, $size_px, |$root| $body),
        }
    }};
}

/// Finite range of `v`, widened when all values are equal; `None` when none is finite.
fn value_range(v: &[f64]) -> Option<(f64, f64)> {
    let (lo, hi) = v
        .iter()
        .filter(|x| x.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    if lo
        .partial_cmp(&hi)
        .is_none_or(|o| o == std::cmp::Ordering::Greater)
    {
        return None;
    }
    if hi - lo > 0.0 {
        Some((lo, hi))
    } else {
        let pad = lo.abs().max(1.0) * 1e-6;
        Some((lo - pad, hi + pad))
    }
}

/// Width of every map plot, pixels; the height follows the data's aspect ratio.
pub const MAP_WIDTH_PX: u32 = 1000;
/// Height above the data for the title, pixels.
const TITLE_PX: u32 = 44;
/// Room left of the data for the y tick labels and axis name, pixels.
const Y_LABELS_PX: u32 = 72;
/// Blank margin at the canvas's left edge, pixels (inside `Y_LABELS_PX`).
const LEFT_PX: u32 = 10;
/// Room below the data for the x tick labels and axis name, pixels.
const X_LABELS_PX: u32 = 48;
/// Margin right of the data, pixels.
const RIGHT_PX: u32 = 36;
/// Length of the tick marks of map axes and colour bars, pixels. plotters sets tick labels twice
/// this far from their axis, so the labels keep clear of the frame and of a colour bar's baseline.
const TICK_PX: i32 = 5;
/// Height of the colour-bar strip below the map (bar, ticks, unit), pixels.
const BAR_AREA_PX: u32 = 76;
/// Tallest data area, pixels (near-square parts).
const MAX_DATA_HEIGHT_PX: u32 = 720;
/// Most elongated data area drawn (long side over short side): a part more elongated than this
/// is drawn at this aspect, its short axis stretched (the title says by how much), so that a
/// strip stays strip-shaped but its short axis is readable.
pub const MAX_DRAWN_ASPECT: f64 = 6.0;
/// Colour of pixels inside the plot frame that no data point covers (outside the aperture).
const NO_DATA: RGBColor = RGBColor(200, 200, 200);
/// Colour of points below the colour range.
pub const UNDER_RANGE: RGBColor = RGBColor(0, 0, 0);
/// Colour of points above the colour range.
pub const OVER_RANGE: RGBColor = RGBColor(255, 0, 255);

/// Where a map plot puts its data: the part's long axis across the width (a part taller than wide
/// is turned a quarter turn clockwise: `y` across, `x` down), equal mm per pixel on both axes up
/// to an aspect of [`MAX_DRAWN_ASPECT`], the short axis stretched beyond it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapLayout {
    /// Canvas size, pixels.
    pub canvas_px: (u32, u32),
    /// Top-left corner of the data area on the canvas, pixels.
    pub data_origin_px: (u32, u32),
    /// Size of the data area, pixels.
    pub data_size_px: (u32, u32),
    /// True when the plot shows `y` across and `x` down.
    pub rotated: bool,
    /// Pixels per mm down over pixels per mm across: 1 at equal scale, more for a stretched strip.
    pub stretch: f64,
}

impl MapLayout {
    /// The layout for a data extent of `width_mm` by `height_mm` (x by y, both positive).
    pub fn for_extent(width_mm: f64, height_mm: f64) -> Self {
        let rotated = height_mm > width_mm;
        let (across, down) = if rotated {
            (height_mm, width_mm)
        } else {
            (width_mm, height_mm)
        };
        let drawn_down = down.max(across / MAX_DRAWN_ASPECT);
        let max_w = MAP_WIDTH_PX - Y_LABELS_PX - RIGHT_PX;
        let mut w = max_w as f64;
        let mut h = w * drawn_down / across;
        if h > MAX_DATA_HEIGHT_PX as f64 {
            h = MAX_DATA_HEIGHT_PX as f64;
            w = h * across / drawn_down;
        }
        let (w, h) = (w.round().max(1.0) as u32, h.round().max(1.0) as u32);
        MapLayout {
            canvas_px: (MAP_WIDTH_PX, TITLE_PX + h + X_LABELS_PX + BAR_AREA_PX),
            data_origin_px: (Y_LABELS_PX, TITLE_PX),
            data_size_px: (w, h),
            rotated,
            stretch: drawn_down / down,
        }
    }

    /// A note for the title when the short axis is stretched, e.g. ` (y stretched 2.4x)`.
    fn stretch_note(&self) -> String {
        if self.stretch > 1.0 + 1e-9 {
            format!(
                " ({} stretched {:.1}x)",
                if self.rotated { "x" } else { "y" },
                self.stretch
            )
        } else {
            String::new()
        }
    }
}

/// Points farther from the median than this many median absolute deviations are outliers, clipped
/// by the robust colour range ([`ColorLimits::Robust`]). Five MADs are 3.4 standard deviations of
/// normally distributed values and 3.5 amplitudes of a sinusoid: a smooth map has none.
pub const OUTLIER_MADS: f64 = 5.0;

/// How a map's colours span its values.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum ColorLimits {
    /// Every point but the outliers: the values (their `log10` on a log scale) farther than
    /// [`OUTLIER_MADS`] median absolute deviations from their median are clipped, drawn in
    /// [`UNDER_RANGE`] and [`OVER_RANGE`] and counted under the colour bar; the range is that of
    /// the others (symmetric about zero on the diverging scale). With no spread (a MAD of zero)
    /// nothing is clipped.
    #[default]
    Robust,
    /// The values' whole range.
    Full,
    /// Given limits, in the map's unit (`lo < hi`).
    Fixed {
        /// Lower limit.
        lo: f64,
        /// Upper limit.
        hi: f64,
    },
}

impl std::str::FromStr for ColorLimits {
    type Err = String;

    /// `robust`, `full`, or `LO,HI` (numbers, `LO < HI`).
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.trim() {
            "robust" => return Ok(ColorLimits::Robust),
            "full" => return Ok(ColorLimits::Full),
            _ => {}
        }
        let bad = || format!("`{s}`: give LO,HI (two numbers, LO < HI), `robust` or `full`");
        let (a, b) = s.split_once(',').ok_or_else(bad)?;
        let lo: f64 = a.trim().parse().map_err(|_| bad())?;
        let hi: f64 = b.trim().parse().map_err(|_| bad())?;
        if !(lo.is_finite() && hi.is_finite() && lo < hi) {
            return Err(bad());
        }
        Ok(ColorLimits::Fixed { lo, hi })
    }
}

/// Median of sorted, non-empty `v`.
fn median_of_sorted(v: &[f64]) -> f64 {
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The smallest and largest of the finite `v` that are not outliers: within [`OUTLIER_MADS`]
/// median absolute deviations of the median (all of them when the MAD is zero); `None` when no
/// value is finite.
pub fn inlier_range(v: &[f64]) -> Option<(f64, f64)> {
    inlier_range_by(v, |x| x)
}

/// [`inlier_range`] with the test made on `f` of the values (`f` increasing, e.g. `log10`); the
/// range is of the values themselves.
fn inlier_range_by(v: &[f64], f: impl Fn(f64) -> f64) -> Option<(f64, f64)> {
    let mut sorted: Vec<(f64, f64)> = v
        .iter()
        .map(|&x| (x, f(x)))
        .filter(|(x, t)| x.is_finite() && t.is_finite())
        .collect();
    if sorted.is_empty() {
        return None;
    }
    sorted.sort_by(|p, q| p.1.total_cmp(&q.1));
    let t: Vec<f64> = sorted.iter().map(|p| p.1).collect();
    let m = median_of_sorted(&t);
    let mut dev: Vec<f64> = t.iter().map(|x| (x - m).abs()).collect();
    dev.sort_by(f64::total_cmp);
    let reach = OUTLIER_MADS * median_of_sorted(&dev);
    let (first, last) = (sorted[0].0, sorted[sorted.len() - 1].0);
    if reach.is_nan() || reach <= 0.0 {
        return Some((first, last));
    }
    let lo = sorted.iter().find(|p| p.1 >= m - reach).map(|p| p.0);
    let hi = sorted.iter().rev().find(|p| p.1 <= m + reach).map(|p| p.0);
    Some((lo.unwrap_or(first), hi.unwrap_or(last)))
}

/// The colour scale a map asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ColourScale {
    /// Linear: the diverging scale centred on zero for signed values, viridis for one-signed.
    #[default]
    Linear,
    /// The diverging scale centred on zero whatever the values (residuals, differences).
    Diverging,
    /// Viridis over `log10` of the values (dwell, feed: ranges of several decades); linear when
    /// a value (or a given limit) is not positive or the values span less than a decade.
    Log,
}

impl ColourScale {
    /// The scale a map in `unit` gets by default: logarithmic for dwell (`s`) and feed
    /// (`mm/min`), linear otherwise.
    pub fn for_unit(unit: &str) -> Self {
        match unit {
            "s" | "mm/min" => ColourScale::Log,
            _ => ColourScale::Linear,
        }
    }
}

/// The colour range a map is drawn with and the points it clips.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColourRange {
    /// Lower end of the colour range, in the map's unit.
    pub lo: f64,
    /// Upper end of the colour range, in the map's unit.
    pub hi: f64,
    /// Finite points below `lo` (drawn in [`UNDER_RANGE`]).
    pub below: usize,
    /// Finite points above `hi` (drawn in [`OVER_RANGE`]).
    pub above: usize,
    scale: Scale,
}

impl ColourRange {
    /// Points drawn outside the colour range.
    pub fn clipped(&self) -> usize {
        self.below + self.above
    }

    /// Whether the colours follow `log10` of the values.
    pub fn is_log(&self) -> bool {
        self.scale == Scale::Log
    }

    /// Whether the colours are the diverging scale (centred on zero unless given limits say
    /// otherwise).
    pub fn is_diverging(&self) -> bool {
        self.scale == Scale::Diverging
    }

    /// Where `v` falls in the colour range, 0 at `lo` to 1 at `hi` (along `log10` on a log
    /// scale); outside 0..1 for clipped values.
    pub fn position(&self, v: f64) -> f64 {
        self.scale.position(v, self.lo, self.hi)
    }
}

/// The colour range of the values `v` under `limits` on the scale `wanted` asks for, and the
/// points outside it ([`ColorLimits`], [`ColourScale`]).
pub fn colour_range(v: &[f64], limits: ColorLimits, wanted: ColourScale) -> ColourRange {
    let (lo, hi) = value_range(v).unwrap_or((0.0, 1.0));
    let positive = |a: f64| a > 0.0;
    let scale = match (wanted, limits) {
        (ColourScale::Diverging, _) => Scale::Diverging,
        (ColourScale::Log, ColorLimits::Fixed { lo, hi }) if positive(lo) && hi >= 10.0 * lo => {
            Scale::Log
        }
        (ColourScale::Log, ColorLimits::Full | ColorLimits::Robust)
            if positive(lo)
                && hi >= 10.0 * lo
                && v.iter().filter(|x| x.is_finite()).all(|&x| positive(x)) =>
        {
            Scale::Log
        }
        (_, ColorLimits::Fixed { lo, hi }) => Scale::for_values(lo, hi),
        _ => Scale::for_values(lo, hi),
    };
    let (a, b) = match limits {
        ColorLimits::Fixed { lo, hi } => (lo, hi),
        ColorLimits::Full => scale.range(lo, hi),
        ColorLimits::Robust => {
            let inliers = if scale == Scale::Log {
                inlier_range_by(v, f64::log10)
            } else {
                inlier_range(v)
            };
            // The inliers' own range, widened like the whole one when it is a single value.
            let (a, b) = inliers
                .and_then(|(a, b)| value_range(&[a, b]))
                .unwrap_or((lo, hi));
            scale.range(a, b)
        }
    };
    let (a, b) = if b > a { (a, b) } else { scale.range(lo, hi) };
    let (below, above) = outside_counts(v, a, b);
    ColourRange {
        lo: a,
        hi: b,
        below,
        above,
        scale,
    }
}

/// Points of `v` below and above `[lo, hi]`.
fn outside_counts(v: &[f64], lo: f64, hi: f64) -> (usize, usize) {
    v.iter().fold((0, 0), |(a, b), &x| {
        (a + usize::from(x < lo), b + usize::from(x > hi))
    })
}

/// Decimals that print every tick of `lo..hi` (at most `n` ticks, as the mesh places them)
/// exactly, the same for all: `0, 20, 40` or `0.0, 0.5, 1.0`, never `0` beside `100.0`.
fn tick_decimals(lo: f64, hi: f64, n: usize) -> usize {
    use plotters::coord::ranged1d::{BoldPoints, Ranged};
    use plotters::coord::types::RangedCoordf64;
    let (a, b) = if lo <= hi { (lo, hi) } else { (hi, lo) };
    let ticks = RangedCoordf64::from(a..b).key_points(BoldPoints(n));
    (0..=6)
        .find(|&d| {
            let f = 10f64.powi(d as i32);
            ticks
                .iter()
                .all(|t| ((t * f) - (t * f).round()).abs() < 1e-6 * (t * f).abs().max(1.0))
        })
        .unwrap_or(6)
}

/// Tick label of `v` with `decimals`; `-0` printed as `0`.
fn tick_label(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

/// Which colour scale a map gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scale {
    /// Viridis from the smallest to the largest value (one-signed quantities).
    Sequential,
    /// Moreland's cool-warm map, symmetric about zero (signed quantities).
    Diverging,
    /// Viridis over `log10` of the values (positive quantities spanning decades).
    Log,
}

/// Moreland's diverging cool-warm map (K. Moreland, "Diverging Color Maps for Scientific
/// Visualization", ISVC 2009), sampled at nine points; grey at zero, never white.
const COOL_WARM: [(f64, (u8, u8, u8)); 9] = [
    (0.0, (59, 76, 192)),
    (0.125, (98, 130, 234)),
    (0.25, (141, 176, 254)),
    (0.375, (184, 208, 249)),
    (0.5, (221, 221, 221)),
    (0.625, (245, 196, 173)),
    (0.75, (244, 154, 123)),
    (0.875, (222, 96, 77)),
    (1.0, (180, 4, 38)),
];

fn cool_warm(u: f64) -> RGBColor {
    let u = if u.is_finite() {
        u.clamp(0.0, 1.0)
    } else {
        0.5
    };
    let k = COOL_WARM
        .windows(2)
        .position(|w| u <= w[1].0)
        .unwrap_or(COOL_WARM.len() - 2);
    let ((a, ca), (b, cb)) = (COOL_WARM[k], COOL_WARM[k + 1]);
    let f = (u - a) / (b - a);
    let mix = |p: u8, q: u8| (p as f64 + f * (q as f64 - p as f64)).round() as u8;
    RGBColor(mix(ca.0, cb.0), mix(ca.1, cb.1), mix(ca.2, cb.2))
}

impl Scale {
    /// Signed data (values of both signs) get the diverging scale.
    fn for_values(lo: f64, hi: f64) -> Self {
        if lo < 0.0 && hi > 0.0 {
            Scale::Diverging
        } else {
            Scale::Sequential
        }
    }

    /// The value range the colours span.
    fn range(self, lo: f64, hi: f64) -> (f64, f64) {
        match self {
            Scale::Sequential | Scale::Log => (lo, hi),
            Scale::Diverging => {
                let a = lo.abs().max(hi.abs());
                (-a, a)
            }
        }
    }

    /// Where `v` falls from `lo` (0) to `hi` (1): linearly, or along `log10` on the log scale.
    fn position(self, v: f64, lo: f64, hi: f64) -> f64 {
        match self {
            Scale::Sequential | Scale::Diverging => (v - lo) / (hi - lo),
            Scale::Log => (v.log10() - lo.log10()) / (hi.log10() - lo.log10()),
        }
    }

    fn colour(self, v: f64, lo: f64, hi: f64) -> RGBColor {
        match self {
            Scale::Sequential | Scale::Log => {
                let u = self.position(v, lo, hi);
                let u = if u.is_finite() {
                    u.clamp(0.0, 1.0)
                } else {
                    0.0
                };
                ViridisRGB::get_color_normalized(u, 0.0, 1.0)
            }
            Scale::Diverging => cool_warm(self.position(v, lo, hi)),
        }
    }
}

/// Scattered points binned into square cells for drawing: each cell holds the index of the last
/// point that falls in it. The cell is the lattice pitch on lattice maps (the smallest step
/// between distinct coordinates) unless that would make more than four cells per point, else the
/// mean spacing `sqrt(area / n)`.
struct CellIndex {
    x0: f64,
    y0: f64,
    cell_mm: f64,
    nx: usize,
    ny: usize,
    cells: Vec<u32>,
}

const EMPTY_CELL: u32 = u32::MAX;

impl CellIndex {
    fn new(x: &[f64], y: &[f64], v: &[f64], extent: (f64, f64, f64, f64)) -> Self {
        let (x0, x1, y0, y1) = extent;
        let n = x.len().max(1) as f64;
        let mean_spacing = ((x1 - x0).max(1e-9) * (y1 - y0).max(1e-9) / n).sqrt();
        let lattice = preston_solver::influence::operator::fft::FftOperator::lattice_pitch_mm(x, y);
        let cells_at = |c: f64| ((x1 - x0) / c + 1.0) * ((y1 - y0) / c + 1.0);
        let cell_mm = match lattice {
            Some(p) if p > 0.0 && cells_at(p) <= 4.0 * n => p,
            _ => mean_spacing.max(1e-9),
        };
        let nx = ((x1 - x0) / cell_mm).round() as usize + 1;
        let ny = ((y1 - y0) / cell_mm).round() as usize + 1;
        let mut cells = vec![EMPTY_CELL; nx * ny];
        for i in 0..x.len() {
            if !v[i].is_finite() || !x[i].is_finite() || !y[i].is_finite() {
                continue;
            }
            let ix = (((x[i] - x0) / cell_mm).round() as usize).min(nx - 1);
            let iy = (((y[i] - y0) / cell_mm).round() as usize).min(ny - 1);
            cells[iy * nx + ix] = i as u32;
        }
        CellIndex {
            x0,
            y0,
            cell_mm,
            nx,
            ny,
            cells,
        }
    }

    /// The point drawn at `(x, y)` mm: its own cell, else the nearest filled cell of the eight
    /// around it (so that scattered data leave no holes).
    fn at(&self, x: f64, y: f64) -> Option<usize> {
        let fx = (x - self.x0) / self.cell_mm;
        let fy = (y - self.y0) / self.cell_mm;
        let (cx, cy) = (fx.round(), fy.round());
        let mut best: Option<(f64, usize)> = None;
        for dy in -1..=1_i64 {
            for dx in -1..=1_i64 {
                let (ix, iy) = (cx as i64 + dx, cy as i64 + dy);
                if ix < 0 || iy < 0 || ix >= self.nx as i64 || iy >= self.ny as i64 {
                    continue;
                }
                let k = self.cells[iy as usize * self.nx + ix as usize];
                if k == EMPTY_CELL {
                    continue;
                }
                let d = (ix as f64 - fx).powi(2) + (iy as f64 - fy).powi(2);
                if (dx, dy) != (0, 0) && d > 1.0 {
                    continue;
                }
                if best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, k as usize));
                }
            }
        }
        best.map(|(_, k)| k)
    }
}

/// The title with the map's statistics: PV and RMS about the mean for heights (`nm`), as
/// `report.json` computes them ([`preston_solver::map::HeightStats`]); the value range otherwise.
fn titled(title: &str, unit: &str, v: &[f64]) -> String {
    let finite: Vec<f64> = v.iter().copied().filter(|a| a.is_finite()).collect();
    if unit == "nm" {
        let s = preston_solver::map::HeightStats::of(&finite);
        format!("{title}: PV {:.3} nm, RMS {:.3} nm", s.pv_nm, s.rms_nm)
    } else {
        match value_range(&finite) {
            Some((lo, hi)) => format!("{title}: {} to {} {unit}", sig(lo), sig(hi)),
            None => title.to_string(),
        }
    }
}

/// Four significant digits, without an exponent for everyday magnitudes.
fn sig(v: f64) -> String {
    let a = v.abs();
    if a == 0.0 || (1e-3..1e5).contains(&a) {
        let decimals = (3 - a.log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.3e}")
    }
}

/// Plots scattered values `v` at `(x, y)` (mm) as an image (each pixel takes the value of the
/// point in its cell, see [`MapLayout`]), with PV and RMS (or the range) in the title and a
/// colour bar labelled `unit` below, which says how many points are clipped. Signed data get a
/// diverging scale centred on zero, one-signed data viridis, dwell (`s`) and feed (`mm/min`)
/// viridis over `log10` ([`ColourScale::for_unit`]). Heights (`unit` `nm`) clip their outliers
/// ([`ColorLimits::Robust`]), where edge spikes would set the whole range; other quantities
/// (dwell, feed, TIF), whose extremes matter, keep their whole range.
pub fn plot_map(
    path: &Path,
    title: &str,
    unit: &str,
    x: &[f64],
    y: &[f64],
    v: &[f64],
) -> Result<()> {
    commit_all(vec![stage_map_plot(path, title, unit, x, y, v)?])
}

/// [`plot_map`], staged for a commit together with other outputs.
pub fn stage_map_plot(
    path: &Path,
    title: &str,
    unit: &str,
    x: &[f64],
    y: &[f64],
    v: &[f64],
) -> Result<Staged> {
    let limits = if unit == "nm" {
        ColorLimits::Robust
    } else {
        ColorLimits::Full
    };
    stage_map_plot_with(path, title, unit, x, y, v, limits)
}

/// [`stage_map_plot`] with the colour range chosen by `limits`.
pub fn stage_map_plot_with(
    path: &Path,
    title: &str,
    unit: &str,
    x: &[f64],
    y: &[f64],
    v: &[f64],
    limits: ColorLimits,
) -> Result<Staged> {
    let scale = ColourScale::for_unit(unit);
    stage_map_plot_scaled(path, title, unit, x, y, v, limits, scale)
}

/// [`stage_map_plot_with`] on the colour scale `scale`.
#[allow(clippy::too_many_arguments)]
pub fn stage_map_plot_scaled(
    path: &Path,
    title: &str,
    unit: &str,
    x: &[f64],
    y: &[f64],
    v: &[f64],
    limits: ColorLimits,
    scale: ColourScale,
) -> Result<Staged> {
    let n = x.len().min(y.len()).min(v.len());
    let (x, y, v) = (&x[..n], &y[..n], &v[..n]);
    let (x0, x1) = value_range(x).ok_or_else(|| Error::Empty {
        file: path.to_path_buf(),
        why: "nothing to plot".into(),
    })?;
    let (y0, y1) = value_range(y).unwrap_or((x0, x1));
    let range = colour_range(v, limits, scale);
    let (scale, lo, hi) = (range.scale, range.lo, range.hi);
    let cells = CellIndex::new(x, y, v, (x0, x1, y0, y1));
    let half = 0.5 * cells.cell_mm;
    let (ex0, ex1, ey0, ey1) = (x0 - half, x1 + half, y0 - half, y1 + half);
    let layout = MapLayout::for_extent(ex1 - ex0, ey1 - ey0);
    let heading = titled(title, unit, v) + &layout.stretch_note();
    stage_plot!(path, layout.canvas_px, |root| {
        root.draw(&Text::new(
            heading.as_str(),
            (layout.data_origin_px.0 as i32, 10),
            ("sans-serif", 22).into_font(),
        ))
        .map_err(|e| plot_error(path, e))?;
        let (top, bar) = root.split_vertically(layout.canvas_px.1 - BAR_AREA_PX);
        let (_, body) = top.split_vertically(TITLE_PX);
        let right = layout.canvas_px.0 - Y_LABELS_PX - layout.data_size_px.0;
        let mut cb = ChartBuilder::on(&body);
        cb.margin_right(right)
            .margin_left(LEFT_PX)
            .x_label_area_size(X_LABELS_PX)
            .y_label_area_size(Y_LABELS_PX - LEFT_PX);
        // Across and down in plot terms; a rotated plot shows y across and x downwards.
        let (across, down, across_name, down_name) = if layout.rotated {
            ((ey0, ey1), (ex1, ex0), "y (mm)", "x (mm)")
        } else {
            ((ex0, ex1), (ey0, ey1), "x (mm)", "y (mm)")
        };
        let mut chart = cb
            .build_cartesian_2d(across.0..across.1, down.0..down.1)
            .map_err(|e| plot_error(path, e))?;
        map_mesh(
            &mut chart,
            path,
            layout,
            across,
            down,
            across_name,
            down_name,
        )?;
        let (xr, yr) = chart.plotting_area().get_pixel_range();
        let (w, h) = ((xr.end - xr.start).max(1), (yr.end - yr.start).max(1));
        // The data area as one RGB image: pixels on a PNG, an embedded image in an SVG.
        let mut raster = Vec::with_capacity(w as usize * h as usize * 3);
        for py in 0..h {
            for px in 0..w {
                // Pixel centre in plot units, then in part coordinates.
                let a = across.0 + (across.1 - across.0) * (px as f64 + 0.5) / w as f64;
                let d = down.1 + (down.0 - down.1) * (py as f64 + 0.5) / h as f64;
                let (qx, qy) = if layout.rotated { (d, a) } else { (a, d) };
                let colour = match cells.at(qx, qy) {
                    Some(i) if v[i] < lo => UNDER_RANGE,
                    Some(i) if v[i] > hi => OVER_RANGE,
                    Some(i) => scale.colour(v[i], lo, hi),
                    None => NO_DATA,
                };
                raster.extend_from_slice(&[colour.0, colour.1, colour.2]);
            }
        }
        let image =
            BitMapElement::with_owned_buffer((xr.start, yr.start), (w as u32, h as u32), raster)
                .ok_or_else(|| plot_error(path, "the map raster does not fill its area"))?;
        root.draw(&image).map_err(|e| plot_error(path, e))?;
        colour_bar(path, &bar, unit, &range, layout, n)
    })
}

/// The axes of a map plot: clean tick labels (one number format per axis), none at the lower
/// left corner where the two axes' first labels would collide.
fn map_mesh<DB: DrawingBackend>(
    chart: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    path: &Path,
    layout: MapLayout,
    across: (f64, f64),
    down: (f64, f64),
    across_name: &str,
    down_name: &str,
) -> Result<()> {
    let n_across = 8;
    let n_down = if layout.data_size_px.1 < 120 { 3 } else { 6 };
    let dx = tick_decimals(across.0, across.1, n_across);
    let dy = tick_decimals(down.0, down.1, n_down);
    // A down label within this many pixels of the bottom edge is left out.
    let corner_px = 14.0;
    let per_px = (down.1 - down.0).abs() / layout.data_size_px.1.max(1) as f64;
    let bottom = down.0;
    let fx = move |v: &f64| tick_label(*v, dx);
    let fy = move |v: &f64| {
        if (v - bottom).abs() < corner_px * per_px {
            String::new()
        } else {
            tick_label(*v, dy)
        }
    };
    chart
        .configure_mesh()
        .disable_mesh()
        .set_all_tick_mark_size(TICK_PX)
        .x_desc(across_name)
        .y_desc(down_name)
        .x_labels(n_across)
        .y_labels(n_down)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy)
        .label_style(("sans-serif", 14))
        .draw()
        .map_err(|e| plot_error(path, e))
}

/// Label of a logarithmic tick `v` (a digit times a power of ten): its digits, no exponent.
fn log_tick_label(v: f64) -> String {
    let decimals = (-(v.log10() + 1e-9).floor()).clamp(0.0, 12.0) as usize;
    tick_label(v, decimals)
}

/// What the colour bar says about the clipped points.
fn clipped_note(range: &ColourRange, total: usize) -> String {
    let (below, above) = (range.below, range.above);
    match below + above {
        0 => "no point clipped".to_string(),
        n => {
            let inside = 100.0 * (total.saturating_sub(n)) as f64 / total.max(1) as f64;
            format!(
                "{n} point{} clipped ({below} below in black, {above} above in magenta; \
                 {inside:.1}% inside)",
                if n == 1 { "" } else { "s" }
            )
        }
    }
}

fn colour_bar<DB: DrawingBackend>(
    path: &Path,
    area: &DrawingArea<DB, plotters::coord::Shift>,
    unit: &str,
    range: &ColourRange,
    layout: MapLayout,
    total: usize,
) -> Result<()> {
    use plotters::coord::combinators::IntoLogRange;
    let (lo, hi, scale) = (range.lo, range.hi, range.scale);
    let log = scale == Scale::Log;
    // The bar's steps are even along the values, or along their log10 on the log scale.
    let to_axis = |v: f64| if log { v.log10() } else { v };
    let from_axis = |t: f64| if log { 10f64.powf(t) } else { t };
    let (a, b) = (to_axis(lo), to_axis(hi));
    let span = b - a;
    // Room at both ends for the out-of-range swatches.
    let ext = 0.06 * span;
    let decimals = tick_decimals(lo, hi, 6);
    let desc = format!(
        "{unit}{}; colour range {} to {} {unit}; {}",
        if log { ", log scale" } else { "" },
        sig(lo),
        sig(hi),
        clipped_note(range, total)
    );
    let label = |v: &f64| {
        if to_axis(*v) < a - 1e-9 * span || to_axis(*v) > b + 1e-9 * span {
            String::new()
        } else if log {
            log_tick_label(*v)
        } else {
            tick_label(*v, decimals)
        }
    };
    let steps = 300;
    let bar = (0..steps).map(|k| {
        let p = from_axis(a + span * k as f64 / steps as f64);
        let q = from_axis(a + span * (k + 1) as f64 / steps as f64);
        let mid = from_axis(a + span * (k as f64 + 0.5) / steps as f64);
        Rectangle::new([(p, 0.0), (q, 1.0)], scale.colour(mid, lo, hi).filled())
    });
    let mut ends = Vec::new();
    if range.below > 0 {
        ends.push(Polygon::new(
            vec![(lo, 0.0), (lo, 1.0), (from_axis(a - ext), 0.5)],
            UNDER_RANGE.filled(),
        ));
    }
    if range.above > 0 {
        ends.push(Polygon::new(
            vec![(hi, 0.0), (hi, 1.0), (from_axis(b + ext), 0.5)],
            OVER_RANGE.filled(),
        ));
    }
    let bar_w = layout.data_size_px.0.min(600);
    let right = layout.canvas_px.0 - Y_LABELS_PX - bar_w;
    let mut builder = ChartBuilder::on(area);
    builder
        .margin_top(14)
        .margin_right(right)
        .margin_left(LEFT_PX)
        .x_label_area_size(44)
        .y_label_area_size(Y_LABELS_PX - LEFT_PX);
    // One drawing for both axis types (linear values, or values on a log axis).
    macro_rules! draw_bar {
        ($chart:expr) => {{
            let mut chart = $chart.map_err(|e| plot_error(path, e))?;
            chart
                .configure_mesh()
                .disable_mesh()
                .set_all_tick_mark_size(TICK_PX)
                .disable_y_axis()
                .x_labels(6)
                .x_label_formatter(&label)
                .x_desc(desc.as_str())
                .label_style(("sans-serif", 13))
                .draw()
                .map_err(|e| plot_error(path, e))?;
            chart.draw_series(bar).map_err(|e| plot_error(path, e))?;
            chart.draw_series(ends).map_err(|e| plot_error(path, e))?;
        }};
    }
    if log {
        draw_bar!(builder.build_cartesian_2d(
            (from_axis(a - ext)..from_axis(b + ext)).log_scale(),
            0.0..1.0
        ));
    } else {
        draw_bar!(builder.build_cartesian_2d(a - ext..b + ext, 0.0..1.0));
    }
    Ok(())
}

/// Plots values on a regular grid (`v[l * nx + k]` at `(x_axis[k], y_axis[l])`, both axes
/// ascending and evenly spaced) as cells in viridis over their whole finite range, with the axes
/// named `names` and a colour bar labelled `unit`: for example a 2-D PSD over `(fx, fy)`.
pub fn stage_grid_plot(
    path: &Path,
    title: &str,
    unit: &str,
    x_axis: &[f64],
    y_axis: &[f64],
    v: &[f64],
    names: (&str, &str),
) -> Result<Staged> {
    let (nx, ny) = (x_axis.len(), y_axis.len());
    let empty = || Error::Empty {
        file: path.to_path_buf(),
        why: "nothing to plot".into(),
    };
    if nx < 2 || ny < 2 || v.len() != nx * ny {
        return Err(empty());
    }
    let (dx, dy) = (x_axis[1] - x_axis[0], y_axis[1] - y_axis[0]);
    let (ex0, ex1) = (x_axis[0] - 0.5 * dx, x_axis[nx - 1] + 0.5 * dx);
    let (ey0, ey1) = (y_axis[0] - 0.5 * dy, y_axis[ny - 1] + 0.5 * dy);
    let (lo, hi) = value_range(v).ok_or_else(empty)?;
    let layout = MapLayout::for_extent(ex1 - ex0, ey1 - ey0);
    let layout = MapLayout {
        rotated: false,
        ..layout
    };
    let layout = if layout.data_size_px.0 < layout.data_size_px.1 {
        MapLayout::for_extent(ey1 - ey0, ex1 - ex0)
    } else {
        layout
    };
    stage_plot!(path, layout.canvas_px, |root| {
        root.draw(&Text::new(
            title,
            (layout.data_origin_px.0 as i32, 10),
            ("sans-serif", 22).into_font(),
        ))
        .map_err(|e| plot_error(path, e))?;
        let (top, bar) = root.split_vertically(layout.canvas_px.1 - BAR_AREA_PX);
        let (_, body) = top.split_vertically(TITLE_PX);
        let right = layout.canvas_px.0 - Y_LABELS_PX - layout.data_size_px.0;
        let mut chart = ChartBuilder::on(&body)
            .margin_right(right)
            .margin_left(LEFT_PX)
            .x_label_area_size(X_LABELS_PX)
            .y_label_area_size(Y_LABELS_PX - LEFT_PX)
            .build_cartesian_2d(ex0..ex1, ey0..ey1)
            .map_err(|e| plot_error(path, e))?;
        let layout_axes = MapLayout {
            rotated: false,
            ..layout
        };
        map_mesh(
            &mut chart,
            path,
            layout_axes,
            (ex0, ex1),
            (ey0, ey1),
            names.0,
            names.1,
        )?;
        chart
            .draw_series((0..ny).flat_map(|l| {
                (0..nx).map(move |k| {
                    let (cx, cy) = (x_axis[k], y_axis[l]);
                    let val = v[l * nx + k];
                    let colour = if val.is_finite() {
                        Scale::Sequential.colour(val, lo, hi)
                    } else {
                        NO_DATA
                    };
                    Rectangle::new(
                        [
                            (cx - 0.5 * dx, cy - 0.5 * dy),
                            (cx + 0.5 * dx, cy + 0.5 * dy),
                        ],
                        colour.filled(),
                    )
                })
            }))
            .map_err(|e| plot_error(path, e))?;
        let total = v.iter().filter(|a| a.is_finite()).count();
        let range = ColourRange {
            lo,
            hi,
            below: 0,
            above: 0,
            scale: Scale::Sequential,
        };
        colour_bar(path, &bar, unit, &range, layout, total)
    })
}

/// Plots a tool path (mm) as a polyline with its start marked, at equal mm per pixel on both
/// axes (the layout of [`plot_map`], without the colour bar).
pub fn plot_path(path: &Path, title: &str, x: &[f64], y: &[f64]) -> Result<()> {
    commit_all(vec![stage_path_plot(path, title, x, y)?])
}

/// [`plot_path`], staged for a commit together with other outputs.
pub fn stage_path_plot(path: &Path, title: &str, x: &[f64], y: &[f64]) -> Result<Staged> {
    let n = x.len().min(y.len());
    let (x0, x1) = value_range(&x[..n]).ok_or_else(|| Error::Empty {
        file: path.to_path_buf(),
        why: "nothing to plot".into(),
    })?;
    let (y0, y1) = value_range(&y[..n]).unwrap_or((x0, x1));
    let pad = 0.02 * (x1 - x0).max(y1 - y0);
    let (ex0, ex1, ey0, ey1) = (x0 - pad, x1 + pad, y0 - pad, y1 + pad);
    let layout = MapLayout::for_extent(ex1 - ex0, ey1 - ey0);
    let canvas = (layout.canvas_px.0, layout.canvas_px.1 - BAR_AREA_PX);
    let heading = format!("{title}: {n} points{}", layout.stretch_note());
    stage_plot!(path, canvas, |root| {
        root.draw(&Text::new(
            heading.as_str(),
            (layout.data_origin_px.0 as i32, 10),
            ("sans-serif", 22).into_font(),
        ))
        .map_err(|e| plot_error(path, e))?;
        let (_, body) = root.split_vertically(TITLE_PX);
        let right = layout.canvas_px.0 - Y_LABELS_PX - layout.data_size_px.0;
        let (across, down, across_name, down_name) = if layout.rotated {
            ((ey0, ey1), (ex1, ex0), "y (mm)", "x (mm)")
        } else {
            ((ex0, ex1), (ey0, ey1), "x (mm)", "y (mm)")
        };
        let mut chart = ChartBuilder::on(&body)
            .margin_right(right)
            .margin_left(LEFT_PX)
            .x_label_area_size(X_LABELS_PX)
            .y_label_area_size(Y_LABELS_PX - LEFT_PX)
            .build_cartesian_2d(across.0..across.1, down.0..down.1)
            .map_err(|e| plot_error(path, e))?;
        map_mesh(
            &mut chart,
            path,
            layout,
            across,
            down,
            across_name,
            down_name,
        )?;
        let at = |i: usize| {
            if layout.rotated {
                (y[i], x[i])
            } else {
                (x[i], y[i])
            }
        };
        chart
            .draw_series(LineSeries::new((0..n).map(at), BLUE))
            .map_err(|e| plot_error(path, e))?;
        if n > 0 {
            chart
                .draw_series(std::iter::once(Circle::new(at(0), 5, RED.filled())))
                .map_err(|e| plot_error(path, e))?;
        }
        Ok(())
    })
}

/// One PSD curve: label and PSD values (nm^2 mm) at the plot's frequencies.
pub type PsdCurve<'a> = (&'a str, &'a [f64]);

/// Plots 1-D PSDs (nm^2 mm) against spatial frequency (1/mm) on log-log axes, with a dashed line
/// at `marker_per_mm` (for example the raster pitch's frequency) when given. The zero frequency
/// is left out.
pub fn stage_psd_plot(
    path: &Path,
    title: &str,
    frequency_per_mm: &[f64],
    curves: &[PsdCurve<'_>],
    marker_per_mm: Option<(f64, &str)>,
) -> Result<Staged> {
    stage_spectrum_plot(
        path,
        title,
        "PSD (nm^2 mm)",
        frequency_per_mm,
        curves,
        marker_per_mm,
    )
}

/// [`stage_psd_plot`] with the value axis named `y_desc` (for example the azimuthal average of a
/// 2-D PSD, nm^2 mm^2).
pub fn stage_spectrum_plot(
    path: &Path,
    title: &str,
    y_desc: &str,
    frequency_per_mm: &[f64],
    curves: &[PsdCurve<'_>],
    marker_per_mm: Option<(f64, &str)>,
) -> Result<Staged> {
    let keep: Vec<usize> = (0..frequency_per_mm.len())
        .filter(|&k| frequency_per_mm[k] > 0.0 && frequency_per_mm[k].is_finite())
        .collect();
    let freqs: Vec<f64> = keep.iter().map(|&k| frequency_per_mm[k]).collect();
    let (f0, f1) = value_range(&freqs).ok_or_else(|| Error::Empty {
        file: path.to_path_buf(),
        why: "no positive frequency to plot".into(),
    })?;
    let values: Vec<f64> = curves
        .iter()
        .flat_map(|(_, c)| keep.iter().filter_map(|&k| c.get(k).copied()))
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    let (lo, hi) = value_range(&values).unwrap_or((1e-6, 1.0));
    let ticks = log_ticks(f0, f1);
    stage_plot!(path, PLOT_SIZE_PX, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 22))
            .margin(16)
            .x_label_area_size(48)
            .y_label_area_size(80)
            .build_cartesian_2d(
                (f0..f1).log_scale().with_key_points(ticks.clone()),
                (lo * 0.5..hi * 2.0).log_scale(),
            )
            .map_err(|e| plot_error(path, e))?;
        chart
            .configure_mesh()
            .light_line_style(TRANSPARENT)
            .x_desc("spatial frequency (1/mm)")
            .y_desc(y_desc)
            .x_labels(ticks.len())
            .x_label_formatter(&|v| log_tick_label(*v))
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        let palette = [BLUE, RED, GREEN, MAGENTA, BLACK];
        for (i, (label, c)) in curves.iter().enumerate() {
            let colour = palette[i % palette.len()];
            let pts: Vec<(f64, f64)> = keep
                .iter()
                .filter_map(|&k| Some((frequency_per_mm[k], *c.get(k)?)))
                .filter(|p| p.1 > 0.0 && p.1.is_finite())
                .collect();
            chart
                .draw_series(LineSeries::new(pts, colour.stroke_width(2)))
                .map_err(|e| plot_error(path, e))?
                .label(*label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
        }
        let off_axis = marker_per_mm.and_then(|m| marker_off_axis(m, f0, f1));
        if let Some(note) = off_axis {
            // Said in the legend, where the line would be named.
            chart
                .draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())
                .map_err(|e| plot_error(path, e))?
                .label(note)
                .legend(|(x, y)| EmptyElement::at((x, y)));
        }
        if let Some((f, label)) = marker_per_mm.filter(|m| m.0 >= f0 && m.0 <= f1) {
            let grey = RGBColor(40, 40, 40);
            chart
                .draw_series(DashedLineSeries::new(
                    vec![(f, lo * 0.5), (f, hi * 2.0)],
                    6,
                    4,
                    grey.stroke_width(2),
                ))
                .map_err(|e| plot_error(path, e))?
                .label(label)
                .legend(move |(x, y)| {
                    EmptyElement::at((x, y))
                        + PathElement::new(vec![(0, 0), (6, 0)], grey.stroke_width(2))
                        + PathElement::new(vec![(10, 0), (16, 0)], grey.stroke_width(2))
                });
        }
        draw_legend(&mut chart, path)
    })
}

/// Ticks of a logarithmic axis over `[lo, hi]` (both positive): the powers of ten inside it, or
/// where fewer than three are, 1, 2 and 5 times them, or else every digit times them; an axis
/// narrower than any of these gets its two ends.
pub fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    if !(lo > 0.0 && hi > lo && hi.is_finite()) {
        return vec![];
    }
    let (e0, e1) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    let mut last = Vec::new();
    for mantissas in [
        &[1.0][..],
        &[1.0, 2.0, 5.0],
        &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0],
    ] {
        let ticks: Vec<f64> = (e0..=e1)
            .flat_map(|e| mantissas.iter().map(move |m| m * 10f64.powi(e)))
            // Relative slack for the rounding of 10^e.
            .filter(|t| *t >= lo * (1.0 - 1e-12) && *t <= hi * (1.0 + 1e-12))
            .collect();
        if ticks.len() >= 3 {
            return ticks;
        }
        last = ticks;
    }
    if last.len() >= 2 {
        last
    } else {
        vec![lo, hi]
    }
}

/// The legend's note for a marker `(frequency_per_mm, name)` that lies off a frequency axis of
/// `[f0, f1]` (none when it is on it), e.g. `raster pitch: 3.125 /mm, beyond this axis (to 1.562 /mm)`.
pub fn marker_off_axis(marker: (f64, &str), f0: f64, f1: f64) -> Option<String> {
    let (f, name) = marker;
    if f >= f0 && f <= f1 {
        None
    } else {
        let (side, end) = if f > f1 {
            ("beyond", "to")
        } else {
            ("below", "from")
        };
        Some(format!(
            "{name}: {} /mm, {side} this axis ({end} {} /mm)",
            sig(f),
            sig(if f > f1 { f1 } else { f0 })
        ))
    }
}

/// Plots curves of `(x, y)` points on linear axes named `x_desc` and `y_desc`: for example the
/// planned and the executed dwell per point of a program.
pub fn stage_series_plot(
    path: &Path,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    curves: &[Curve<'_>],
) -> Result<Staged> {
    let xs: Vec<f64> = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.0))
        .collect();
    let ys: Vec<f64> = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.1))
        .collect();
    let (x0, x1) = value_range(&xs).ok_or_else(|| Error::Empty {
        file: path.to_path_buf(),
        why: "nothing to plot".into(),
    })?;
    let (y0, y1) = value_range(&ys).unwrap_or((0.0, 1.0));
    let (y0, y1) = (y0.min(0.0), y1 + 0.05 * (y1 - y0.min(0.0)));
    stage_plot!(path, (1200, 600), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 22))
            .margin(16)
            .x_label_area_size(48)
            .y_label_area_size(80)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| plot_error(path, e))?;
        let (dx, dy) = (tick_decimals(x0, x1, 10), tick_decimals(y0, y1, 8));
        chart
            .configure_mesh()
            .light_line_style(TRANSPARENT)
            .x_desc(x_desc)
            .y_desc(y_desc)
            .x_labels(10)
            .y_labels(8)
            .x_label_formatter(&|v| tick_label(*v, dx))
            .y_label_formatter(&|v| tick_label(*v, dy))
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        let palette = [BLUE, RED, GREEN, MAGENTA, BLACK];
        for (k, (label, pts)) in curves.iter().enumerate() {
            let colour = palette[k % palette.len()];
            chart
                .draw_series(LineSeries::new(pts.iter().copied(), colour.stroke_width(1)))
                .map_err(|e| plot_error(path, e))?
                .label(*label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
        }
        draw_legend(&mut chart, path)
    })
}

/// One curve of a convergence plot: label and `(iteration, value)` points.
pub type Curve<'a> = (&'a str, Vec<(f64, f64)>);

/// Plots curves against the iteration with a logarithmic value axis (`unit` labels it).
pub fn plot_convergence(path: &Path, title: &str, unit: &str, curves: &[Curve<'_>]) -> Result<()> {
    commit_all(vec![stage_convergence_plot(path, title, unit, curves)?])
}

/// [`plot_convergence`], staged for a commit together with other outputs.
pub fn stage_convergence_plot(
    path: &Path,
    title: &str,
    unit: &str,
    curves: &[Curve<'_>],
) -> Result<Staged> {
    let all: Vec<f64> = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.1))
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    let (lo, hi) = value_range(&all).unwrap_or((1e-3, 1.0));
    let it_max = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.0))
        .fold(1.0, f64::max)
        .ceil();
    // Whole iterations only: at most ten ticks, on integers.
    let ticks = (it_max as usize + 1).min(10);
    stage_plot!(path, PLOT_SIZE_PX, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 24))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..it_max, (lo * 0.8..hi * 1.25).log_scale())
            .map_err(|e| plot_error(path, e))?;
        chart
            .configure_mesh()
            .x_desc("iteration")
            .x_labels(ticks)
            .x_label_formatter(&|v| {
                if (v - v.round()).abs() < 1e-9 {
                    format!("{}", v.round() as i64)
                } else {
                    String::new()
                }
            })
            .y_desc(unit)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        let palette = [BLUE, RED, GREEN, MAGENTA, BLACK];
        for (k, (label, pts)) in curves.iter().enumerate() {
            let colour = palette[k % palette.len()];
            let pts: Vec<(f64, f64)> = pts.iter().copied().filter(|p| p.1 > 0.0).collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
                .map_err(|e| plot_error(path, e))?
                .label(*label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
            chart
                .draw_series(pts.into_iter().map(|p| Circle::new(p, 4, colour.filled())))
                .map_err(|e| plot_error(path, e))?;
        }
        draw_legend(&mut chart, path)
    })
}

/// The series legend, boxed, at the upper right of `chart`.
fn draw_legend<'a, DB, CT>(chart: &mut ChartContext<'a, DB, CT>, path: &Path) -> Result<()>
where
    DB: DrawingBackend + 'a,
    CT: CoordTranslate,
{
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .draw()
        .map_err(|e| plot_error(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Decodes a PNG: (width, height, RGB(A) bytes, bytes per pixel).
    fn decode(path: &Path) -> (u32, u32, Vec<u8>, usize) {
        let decoder = png::Decoder::new(std::fs::File::open(path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf, info.color_type.samples())
    }

    fn grid() -> (Vec<f64>, Vec<f64>) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for j in 0..30 {
            for i in 0..30 {
                x.push(i as f64);
                y.push(j as f64);
            }
        }
        (x, y)
    }

    #[test]
    fn map_plots_are_png_of_the_size_and_follow_the_data() {
        let dir = tempfile::tempdir().unwrap();
        let (x, y) = grid();
        let v: Vec<f64> = x.iter().zip(&y).map(|(a, b)| a + b).collect();
        let a = dir.path().join("a.png");
        plot_map(&a, "error before", "nm", &x, &y, &v).unwrap();
        let (w, h, pa, bpp) = decode(&a);
        assert_eq!((w, h), MapLayout::for_extent(30.0, 30.0).canvas_px);
        // Change the data in the lower-left quarter only: pixels change, and only some of them.
        let mut v2 = v.clone();
        for (k, val) in v2.iter_mut().enumerate() {
            if x[k] < 10.0 && y[k] < 10.0 {
                *val = 18.0 - *val; // mirrored within the quarter: the colour range stays
            }
        }
        let b = dir.path().join("b.png");
        plot_map(&b, "error before", "nm", &x, &y, &v2).unwrap();
        let (_, _, pb, _) = decode(&b);
        let changed = pa
            .chunks(bpp)
            .zip(pb.chunks(bpp))
            .filter(|(p, q)| p != q)
            .count();
        let total = (w * h) as usize;
        assert!(
            changed > total / 100 && changed < total / 3,
            "{changed} of {total}"
        );
        // The same data give the same pixels.
        let c = dir.path().join("c.png");
        plot_map(&c, "error before", "nm", &x, &y, &v).unwrap();
        assert_eq!(decode(&c).2, pa);
        // Several colours are used (a colour scale, not a flat fill).
        let mut colours: Vec<&[u8]> = pa.chunks(bpp).collect();
        colours.sort();
        colours.dedup();
        assert!(colours.len() > 50, "{} colours", colours.len());
    }

    /// The trimmed contents of an SVG's `<text>` elements, in document order.
    fn svg_texts(svg: &str) -> Vec<&str> {
        svg.split("<text")
            .skip(1)
            .map(|t| {
                let body = &t[t.find('>').unwrap() + 1..];
                body[..body.find("</text>").unwrap()].trim()
            })
            .collect()
    }

    /// Decodes standard base64 (with `=` padding), as the SVG backend writes embedded images.
    fn base64_decode(text: &str) -> Vec<u8> {
        let value = |c: u8| -> u32 {
            match c {
                b'A'..=b'Z' => (c - b'A') as u32,
                b'a'..=b'z' => (c - b'a') as u32 + 26,
                b'0'..=b'9' => (c - b'0') as u32 + 52,
                b'+' => 62,
                b'/' => 63,
                _ => panic!("not base64: {c}"),
            }
        };
        let bytes: Vec<u8> = text.bytes().filter(|c| *c != b'=').collect();
        let mut out = Vec::new();
        for chunk in bytes.chunks(4) {
            let mut acc = 0u32;
            for (k, c) in chunk.iter().enumerate() {
                acc |= value(*c) << (18 - 6 * k);
            }
            let n = chunk.len() * 6 / 8;
            out.extend_from_slice(&acc.to_be_bytes()[1..1 + n]);
        }
        out
    }

    /// The SVG of a map holds the same data-area pixels as its PNG (embedded as one image at the
    /// data area's place and size), the title as text, and the axes as vectors; the format
    /// follows the file's extension.
    #[test]
    fn svg_map_plots_embed_the_png_data_area_and_draw_text_as_text() {
        let dir = tempfile::tempdir().unwrap();
        let (x, y) = grid();
        let v: Vec<f64> = x.iter().zip(&y).map(|(a, b)| (a * 0.3).sin() + b).collect();
        let png_path = dir.path().join("m.png");
        let svg_path = dir.path().join("m.svg");
        plot_map(&png_path, "error before", "nm", &x, &y, &v).unwrap();
        plot_map(&svg_path, "error before", "nm", &x, &y, &v).unwrap();
        assert_eq!(PlotFormat::of_path(&svg_path), PlotFormat::Svg);
        assert_eq!(PlotFormat::of_path(Path::new("A.SVG")), PlotFormat::Svg);
        assert_eq!(PlotFormat::of_path(&png_path), PlotFormat::Png);
        let svg = std::fs::read_to_string(&svg_path).unwrap();
        let layout = MapLayout::for_extent(30.0, 30.0);
        assert!(svg.starts_with("<svg"), "{}", &svg[..svg.len().min(80)]);
        assert!(svg.trim_end().ends_with("</svg>"));
        assert!(svg.contains(&format!(
            "width=\"{}\" height=\"{}\"",
            layout.canvas_px.0, layout.canvas_px.1
        )));
        let text = svg_texts(&svg);
        assert!(
            text[0].starts_with("error before: PV"),
            "the title is text: {text:?}"
        );
        assert!(
            text.contains(&"x (mm)") && text.contains(&"y (mm)"),
            "{text:?}"
        );
        // One embedded image: the data area.
        assert_eq!(svg.matches("<image").count(), 1);
        let at = svg.find("<image").unwrap();
        let tag = &svg[at..at + svg[at..].find("/>").unwrap()];
        let attr = |name: &str| -> String {
            let k = tag.find(&format!(" {name}=\"")).unwrap() + name.len() + 3;
            tag[k..k + tag[k..].find('"').unwrap()].to_string()
        };
        let (ix, iy): (u32, u32) = (attr("x").parse().unwrap(), attr("y").parse().unwrap());
        let (iw, ih): (u32, u32) = (
            attr("width").parse().unwrap(),
            attr("height").parse().unwrap(),
        );
        let href = attr("href");
        let b64 = href.strip_prefix("data:image/png;base64,").unwrap();
        let embedded = dir.path().join("embedded.png");
        std::fs::write(&embedded, base64_decode(b64)).unwrap();
        let (ew, eh, epx, ebpp) = decode(&embedded);
        assert_eq!((ew, eh), (iw, ih));
        let (pw, _, ppx, pbpp) = decode(&png_path);
        let mut differ = 0;
        for r in 0..eh {
            for c in 0..ew {
                let e = &epx[((r * ew + c) as usize) * ebpp..][..3];
                let p = &ppx[(((iy + r) * pw + ix + c) as usize) * pbpp..][..3];
                differ += usize::from(e != p);
            }
        }
        assert_eq!(differ, 0, "the SVG's data area is the PNG's");
        assert!(ew * eh > 1000, "{ew} x {eh}");
        // Vectors, not one element per pixel: the file is a fraction of the raw pixels.
        assert!(svg.len() < (layout.canvas_px.0 * layout.canvas_px.1) as usize);
    }

    /// Line plots in SVG draw their curves as vector paths with the legend as text.
    #[test]
    fn svg_line_plots_draw_curves_as_paths() {
        let dir = tempfile::tempdir().unwrap();
        let c = dir.path().join("conv.svg");
        plot_convergence(
            &c,
            "convergence",
            "nm",
            &[
                ("RMS", vec![(0.0, 50.0), (1.0, 2.0), (2.0, 0.5)]),
                ("PV", vec![(0.0, 300.0), (1.0, 20.0), (2.0, 4.0)]),
            ],
        )
        .unwrap();
        let svg = std::fs::read_to_string(&c).unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert!(svg.matches("<polyline").count() >= 2, "two curves");
        let text = svg_texts(&svg);
        assert!(text.contains(&"RMS") && text.contains(&"PV"), "{text:?}");
        assert!(!svg.contains("<image"));
        assert!("SVG".parse::<PlotFormat>() == Ok(PlotFormat::Svg));
        assert!("jpeg".parse::<PlotFormat>().is_err());
    }

    #[test]
    fn path_and_convergence_plots_are_written_whole() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("path.png");
        plot_path(&p, "path", &[0.0, 1.0, 1.0, 0.0], &[0.0, 0.0, 1.0, 1.0]).unwrap();
        assert_eq!(decode(&p).0, MAP_WIDTH_PX);
        let c = dir.path().join("conv.png");
        plot_convergence(
            &c,
            "convergence",
            "nm",
            &[
                ("RMS", vec![(0.0, 50.0), (1.0, 2.0), (2.0, 0.5)]),
                ("PV", vec![(0.0, 300.0), (1.0, 20.0), (2.0, 4.0)]),
            ],
        )
        .unwrap();
        assert_eq!(decode(&c).1, PLOT_SIZE_PX.1);
        // Nothing but the two plots in the directory (no temporary left).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
        // Nothing to plot is an error, and writes nothing.
        let e = dir.path().join("empty.png");
        assert!(plot_map(&e, "t", "nm", &[], &[], &[]).is_err());
        assert!(!e.exists());
    }

    /// The sample mirror's lattice: 372 x 26 points at 0.32 mm (118.72 x 8 mm).
    fn strip() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut x, mut y, mut v) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..26 {
            for i in 0..372 {
                let (a, b) = (i as f64 * 0.32, j as f64 * 0.32);
                x.push(a);
                y.push(b);
                v.push(30.0 * (a / 9.0).sin() + 4.0 * (b / 2.0).cos());
            }
        }
        (x, y, v)
    }

    /// Relative tolerance on the data area's aspect against the part's.
    const ASPECT_REL_TOL: f64 = 0.05;

    fn rgb(p: &[u8]) -> (u8, u8, u8) {
        (p[0], p[1], p[2])
    }

    /// The data area of the strip is strip-shaped at the largest drawn aspect (the long axis
    /// across the width), every pixel in it is data (no white grid lines, no gaps), and a part taller than
    /// wide gets the same layout turned a quarter turn.
    #[test]
    fn map_plots_keep_the_aspect_and_fill_the_data_area() {
        let dir = tempfile::tempdir().unwrap();
        let (x, y, v) = strip();
        let f = dir.path().join("strip.png");
        plot_map(&f, "residual", "nm", &x, &y, &v).unwrap();
        let (w, h, px, bpp) = decode(&f);
        let layout = MapLayout::for_extent(118.72 + 0.32, 8.0 + 0.32);
        assert_eq!((w, h), layout.canvas_px);
        let (dw, dh) = layout.data_size_px;
        let aspect = dw as f64 / dh as f64;
        // The strip (14:1) is drawn at the largest aspect, its y axis stretched to match.
        assert!(
            (aspect / MAX_DRAWN_ASPECT - 1.0).abs() < ASPECT_REL_TOL,
            "aspect {aspect}"
        );
        assert!(
            (layout.stretch * MAX_DRAWN_ASPECT / (119.04 / 8.32) - 1.0).abs() < 1e-9,
            "stretch {}",
            layout.stretch
        );
        assert!(dh >= 140, "data area {dh} px tall");
        // A square part is drawn at equal scale.
        assert_eq!(MapLayout::for_extent(30.0, 30.0).stretch, 1.0);
        let (ox, oy) = layout.data_origin_px;
        for r in oy..oy + dh {
            for c in ox..ox + dw {
                let k = (r * w + c) as usize * bpp;
                let p = rgb(&px[k..k + bpp]);
                assert_ne!(p, (255, 255, 255), "white pixel at ({c}, {r})");
                assert_ne!(p, (NO_DATA.0, NO_DATA.1, NO_DATA.2), "gap at ({c}, {r})");
            }
        }
        // Just outside the data area: the white canvas (the area found is the one drawn).
        let k = ((oy + dh / 2) * w + ox + dw + 3) as usize * bpp;
        assert_eq!(rgb(&px[k..k + bpp]), (255, 255, 255));
        let tall = MapLayout::for_extent(8.32, 119.04);
        assert!(tall.rotated && !layout.rotated);
        assert_eq!(tall.data_size_px, layout.data_size_px);
    }

    /// Edge spikes do not set the colour range: the robust range clips exactly the spikes, they
    /// are drawn in the out-of-range colours, and the whole range or given limits are there on
    /// request.
    #[test]
    fn robust_colour_limits_ignore_spikes_and_mark_them() {
        let (x, y, mut v) = strip();
        let n = v.len();
        let (smooth_lo, smooth_hi) = value_range(&v).unwrap();
        let mut spikes = 0;
        for k in (0..n).step_by(125) {
            v[k] = if k % 250 == 0 { 150.0 } else { -150.0 };
            spikes += 1;
        }
        let r = colour_range(&v, ColorLimits::Robust, ColourScale::Linear);
        assert!(r.is_diverging());
        assert_eq!(r.lo, -r.hi);
        assert!(r.hi <= smooth_lo.abs().max(smooth_hi), "{}", r.hi);
        assert!(r.below > 0 && r.above > 0);
        assert_eq!(r.clipped(), spikes);
        let full = colour_range(&v, ColorLimits::Full, ColourScale::Linear);
        assert_eq!((full.hi, full.clipped()), (150.0, 0));
        let fixed: ColorLimits = "-50,50".parse().unwrap();
        assert_eq!(
            fixed,
            ColorLimits::Fixed {
                lo: -50.0,
                hi: 50.0
            }
        );
        let r = colour_range(&v, fixed, ColourScale::Linear);
        assert_eq!((r.lo, r.hi), (-50.0, 50.0));
        assert_eq!(r.clipped(), spikes);
        for bad in ["50,-50", "a,1", "5", "1,inf"] {
            assert!(bad.parse::<ColorLimits>().is_err(), "{bad}");
        }
        // The spikes show in their colours on the image, and only a few pixels have them.
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("spikes.png");
        plot_map(&f, "residual", "nm", &x, &y, &v).unwrap();
        let (_, _, px, bpp) = decode(&f);
        let count = |c: RGBColor| px.chunks(bpp).filter(|p| rgb(p) == (c.0, c.1, c.2)).count();
        let (under, over) = (count(UNDER_RANGE), count(OVER_RANGE));
        assert!(over > 0 && under > 0, "{under} {over}");
        assert!(over + under < px.len() / bpp / 20);
    }

    /// Tick labels of one axis share one number format, and `-0` prints as `0`.
    #[test]
    fn tick_labels_share_one_format() {
        assert_eq!(tick_decimals(-0.16, 118.88, 8), 0);
        assert_eq!(tick_decimals(-0.16, 8.16, 3), 0);
        assert_eq!(tick_decimals(0.0, 1.0, 6), 1);
        assert_eq!(tick_decimals(-56.0, 56.0, 6), 0);
        assert_eq!(tick_label(-0.0, 1), "0.0");
        assert_eq!(tick_label(2.5, 1), "2.5");
        assert_eq!(tick_label(100.0, 0), "100");
    }

    /// The title carries the PV and RMS that `report.json` computes from the same values.
    #[test]
    fn titles_carry_pv_and_rms_of_the_values() {
        let (_, _, v) = strip();
        let s = preston_solver::map::HeightStats::of(&v);
        let t = titled("Residual", "nm", &v);
        assert_eq!(
            t,
            format!("Residual: PV {:.3} nm, RMS {:.3} nm", s.pv_nm, s.rms_nm)
        );
        assert_eq!(
            titled("Dwell", "s", &[0.5, 2.0, 1234.6]),
            "Dwell: 0.5000 to 1235 s"
        );
    }

    /// Signed data: the scale is symmetric about zero, zero is the neutral grey (not white) and
    /// equal magnitudes of opposite sign get the two ends; one-signed data keep viridis.
    #[test]
    fn signed_maps_get_a_diverging_scale_centred_on_zero() {
        let scale = Scale::for_values(-3.0, 10.0);
        assert_eq!(scale, Scale::Diverging);
        assert_eq!(scale.range(-3.0, 10.0), (-10.0, 10.0));
        assert_eq!(scale.colour(0.0, -10.0, 10.0), RGBColor(221, 221, 221));
        assert_eq!(scale.colour(-10.0, -10.0, 10.0), RGBColor(59, 76, 192));
        assert_eq!(scale.colour(10.0, -10.0, 10.0), RGBColor(180, 4, 38));
        // Monotone in lightness towards the centre from both ends (green channel).
        let g = |v: f64| scale.colour(v, -10.0, 10.0).1;
        assert!(g(-10.0) < g(-5.0) && g(-5.0) < g(0.0) && g(0.0) > g(5.0) && g(5.0) > g(10.0));
        assert_eq!(Scale::for_values(0.0, 10.0), Scale::Sequential);
        assert_eq!(Scale::Sequential.range(2.0, 10.0), (2.0, 10.0));
    }

    /// The sample job's error map (`data/mirror_error_118x8mm.csv`) as `(x, y, z)`.
    fn sample_map() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/mirror_error_118x8mm.csv");
        let text = std::fs::read_to_string(path).unwrap();
        let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
        for line in text.lines().skip(1) {
            let f: Vec<f64> = line.split(',').map(|a| a.trim().parse().unwrap()).collect();
            x.push(f[0]);
            y.push(f[1]);
            z.push(f[2]);
        }
        (x, y, z)
    }

    /// Data-area pixels of a map plot drawn in the under- and over-range colours.
    fn clipped_pixels(f: &Path, x: &[f64], y: &[f64]) -> (usize, usize) {
        let (w, _, px, bpp) = decode(f);
        let (x0, x1) = value_range(x).unwrap();
        let (y0, y1) = value_range(y).unwrap();
        let cell =
            preston_solver::influence::operator::fft::FftOperator::lattice_pitch_mm(x, y).unwrap();
        let layout = MapLayout::for_extent(x1 - x0 + cell, y1 - y0 + cell);
        let ((ox, oy), (dw, dh)) = (layout.data_origin_px, layout.data_size_px);
        let (mut under, mut over) = (0, 0);
        for r in oy..oy + dh {
            for c in ox..ox + dw {
                let k = (r * w + c) as usize * bpp;
                let p = rgb(&px[k..k + bpp]);
                under += usize::from(p == (UNDER_RANGE.0, UNDER_RANGE.1, UNDER_RANGE.2));
                over += usize::from(p == (OVER_RANGE.0, OVER_RANGE.1, OVER_RANGE.2));
            }
        }
        (under, over)
    }

    /// The sample's error map is smooth: the default colour range clips none of its points (and
    /// none is drawn clipped); one 1e6 nm spike added to it is the one point clipped.
    #[test]
    fn the_sample_map_clips_nothing_and_a_spike_is_the_one_point_clipped() {
        let (x, y, mut z) = sample_map();
        assert_eq!(z.len(), 9672);
        let r = colour_range(&z, ColorLimits::Robust, ColourScale::Linear);
        assert_eq!(r.clipped(), 0);
        let (lo, hi) = value_range(&z).unwrap();
        assert_eq!((r.lo, r.hi), (lo, hi));
        assert_eq!(clipped_note(&r, z.len()), "no point clipped");
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("error.png");
        plot_map(&f, "Surface error before", "nm", &x, &y, &z).unwrap();
        assert_eq!(clipped_pixels(&f, &x, &y), (0, 0));

        let spike = 4321;
        z[spike] += 1e6;
        let r = colour_range(&z, ColorLimits::Robust, ColourScale::Linear);
        assert_eq!((r.below, r.above), (0, 1));
        assert_eq!((r.lo, r.hi), (lo, hi));
        assert!(clipped_note(&r, z.len()).starts_with("1 point clipped (0 below"));
        plot_map(&f, "Surface error before", "nm", &x, &y, &z).unwrap();
        let (under, over) = clipped_pixels(&f, &x, &y);
        assert_eq!(under, 0);
        assert!(over > 0, "the spike is not drawn");
        // The same spike negative, on the diverging scale: clipped below.
        z[spike] -= 2e6;
        let r = colour_range(&z, ColorLimits::Robust, ColourScale::Diverging);
        assert_eq!((r.below, r.above), (1, 0));
        assert_eq!(r.hi, -r.lo);
    }

    /// The MAD test against its definition on a small set: median 3, absolute deviations
    /// 0, 0, 0, 1, 1, 1, 1, 5, 5, 5.5, 5.5 (MAD 1), so 5 MADs admit -2 ..= 8; with no spread
    /// nothing is an outlier.
    #[test]
    fn inliers_are_within_five_mads_of_the_median() {
        let v = [
            2.0,
            2.0,
            3.0,
            3.0,
            3.0,
            4.0,
            4.0,
            -2.0,
            8.0,
            -2.5,
            8.5,
            f64::NAN,
        ];
        assert_eq!(inlier_range(&v), Some((-2.0, 8.0)));
        assert_eq!(inlier_range(&[2.0, 2.0, 2.0, 50.0]), Some((2.0, 50.0)));
        assert_eq!(inlier_range(&[f64::NAN]), None);
    }

    /// Dwell and feed maps get the log scale: equal ratios are equal steps of colour, the
    /// geometric mean of the ends is the middle of viridis, the bar's ticks are 1, 2 and 5 times
    /// powers of ten; a value that is not positive falls back to the linear scale.
    #[test]
    fn feed_and_dwell_maps_are_on_a_log_colour_scale() {
        assert_eq!(ColourScale::for_unit("mm/min"), ColourScale::Log);
        assert_eq!(ColourScale::for_unit("s"), ColourScale::Log);
        assert_eq!(ColourScale::for_unit("nm"), ColourScale::Linear);
        let feeds: Vec<f64> = (0..=100)
            .map(|k| 1.4 * (3000.0f64 / 1.4).powf(k as f64 / 100.0))
            .collect();
        let r = colour_range(&feeds, ColorLimits::Full, ColourScale::for_unit("mm/min"));
        assert!(r.is_log() && r.clipped() == 0);
        const POS_TOL: f64 = 1e-12;
        assert!((r.lo - 1.4).abs() < 1e-12 && (r.hi - 3000.0).abs() < 1e-9);
        assert!(r.position(1.4).abs() < POS_TOL);
        assert!((r.position(3000.0) - 1.0).abs() < POS_TOL);
        assert!((r.position((1.4f64 * 3000.0).sqrt()) - 0.5).abs() < POS_TOL);
        let step = |a: f64| r.position(10.0 * a) - r.position(a);
        assert!((step(2.0) - step(200.0)).abs() < POS_TOL);
        assert!((step(2.0) - 1.0 / (3000.0f64 / 1.4).log10()).abs() < POS_TOL);
        // A linear scale would put 100 mm/min at 0.033 of the way; the log scale at 0.56.
        assert!(
            (r.position(100.0) - (100.0f64 / 1.4).log10() / (3000.0f64 / 1.4).log10()).abs()
                < POS_TOL
        );
        assert_eq!(
            r.scale.colour((1.4f64 * 3000.0).sqrt(), r.lo, r.hi),
            ViridisRGB::get_color_normalized(0.5, 0.0, 1.0)
        );
        assert_eq!(log_tick_label(0.2), "0.2");
        assert_eq!(log_tick_label(10.0), "10");
        assert_eq!(log_tick_label(2000.0), "2000");
        let mut signed = feeds.clone();
        signed[0] = 0.0;
        assert!(!colour_range(&signed, ColorLimits::Full, ColourScale::Log).is_log());
        // Less than a decade: linear.
        assert!(!colour_range(&[2.0, 9.0], ColorLimits::Full, ColourScale::Log).is_log());
        // Drawn: the bar and map render on the log scale.
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("feed.png");
        let x: Vec<f64> = (0..=100).map(|k| k as f64).collect();
        let y = vec![0.0; x.len()];
        plot_map(&f, "Feed", "mm/min", &x, &y, &feeds).unwrap();
        assert!(f.exists());
    }

    /// Residuals and differences are drawn on the diverging scale centred on zero even when
    /// every value has one sign.
    #[test]
    fn residual_maps_are_diverging_about_zero() {
        let r = colour_range(&[1.0, 2.0, 5.0], ColorLimits::Full, ColourScale::Diverging);
        assert!(r.is_diverging());
        assert_eq!((r.lo, r.hi), (-5.0, 5.0));
        assert_eq!(r.position(0.0), 0.5);
        assert!(
            !colour_range(&[1.0, 2.0, 5.0], ColorLimits::Full, ColourScale::Linear).is_diverging()
        );
    }

    /// A log axis gets at least three ticks where its range holds them, each inside the range,
    /// ascending, each a digit times a power of ten; the sparsest such set is taken.
    #[test]
    fn log_axes_get_three_or_more_round_ticks() {
        for (lo, hi) in [
            (0.0085, 1.56),
            (0.3, 1.5),
            (0.02, 0.9),
            (1e-4, 10.0),
            (2.1, 5.9),
        ] {
            let t = log_ticks(lo, hi);
            assert!(t.len() >= 3, "{lo}..{hi}: {t:?}");
            assert!(t.windows(2).all(|w| w[0] < w[1]), "{t:?}");
            assert!(t.iter().all(|v| *v >= lo && *v <= hi), "{t:?}");
            for v in &t {
                let m = v / 10f64.powf(v.log10().floor());
                assert!(
                    (m - m.round()).abs() < 1e-9,
                    "{v} is not a digit times 10^k"
                );
            }
        }
        // Three decades: the powers of ten alone.
        assert_eq!(log_ticks(0.0085, 1.56).len(), 3);
        // Less than a tick step: the ends.
        assert_eq!(log_ticks(2.1, 2.15), vec![2.1, 2.15]);
        assert!(log_ticks(0.0, 1.0).is_empty());
    }

    /// A marker on the frequency axis is drawn and named as given; one off it is named in the
    /// legend with where it lies, so no caption claims a line that is not there.
    #[test]
    fn a_marker_off_the_axis_says_so() {
        assert_eq!(marker_off_axis((0.5, "raster pitch"), 0.01, 1.5625), None);
        let note = marker_off_axis((3.125, "raster pitch"), 0.01, 1.5625).unwrap();
        assert!(
            note.contains("3.125 /mm") && note.contains("beyond"),
            "{note}"
        );
        let note = marker_off_axis((0.001, "raster pitch"), 0.01, 1.5625).unwrap();
        assert!(note.contains("below"), "{note}");
    }
}
