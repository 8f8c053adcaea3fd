//! How the figures are drawn, shared by `preston solve`, `preston simulate` and `preston iterate`:
//! the same flag names and defaults in all three.

use preston_io::figures::FigureStyle;
use preston_io::plots::{ColorLimits, PlotFormat};

/// The colour range of the height maps and the file format of every figure.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct FigureArgs {
    /// Colour range of the error and residual maps: LO,HI in nm, `robust` (default: every point
    /// but the outliers beyond 5 median absolute deviations of the median, which are marked and
    /// counted under the colour bar) or `full`.
    #[arg(long, value_name = "LO,HI", allow_hyphen_values = true)]
    pub color_limits: Option<ColorLimits>,
    /// File format of the figures: `png`, or `svg` (axes, text and curves as vectors, the map
    /// rasters embedded as images); report.html embeds either.
    #[arg(long, value_enum, default_value_t)]
    pub plot_format: PlotFormat,
}

impl FigureArgs {
    /// The library's figure style of these flags.
    pub fn style(&self) -> FigureStyle {
        FigureStyle {
            color_limits: self.color_limits.unwrap_or_default(),
            format: self.plot_format,
        }
    }
}
