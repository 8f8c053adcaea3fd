//! The flags of a shop's true tool against its spot test, shared by `shop` and `iterate`.

use preston_solver::iterate::shop::ShopTool;

/// The true tool against the spot test ([`ShopTool`]).
#[derive(Debug, Clone, clap::Args)]
pub struct ShopToolArgs {
    /// The true tool's rate against the spot test's.
    #[arg(long, default_value_t = 1.0)]
    pub tool_rate_factor: f64,
    /// The true tool's width against the spot test's (volume kept).
    #[arg(long, default_value_t = 1.0)]
    pub tool_width_factor: f64,
    /// Where the tool lands off the programmed point, mm: X,Y.
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.0], allow_hyphen_values = true)]
    pub tool_offset_mm: Vec<f64>,
    /// The true tool's ellipticity (log stretch along x).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub tool_ellipticity: f64,
    /// A linear skew across the footprint: relative rate change per second-moment radius.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub tool_skew: f64,
    /// Direction of the skew, degrees from x.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub tool_skew_angle_deg: f64,
    /// The rate's relative change from the run's first contact to its last.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub tool_drift_per_run: f64,
}

impl ShopToolArgs {
    /// The tool the flags describe.
    pub fn tool(&self) -> anyhow::Result<ShopTool> {
        let [ox, oy] = self.tool_offset_mm[..] else {
            anyhow::bail!("--tool-offset-mm: give X,Y");
        };
        let tool = ShopTool {
            rate_factor: self.tool_rate_factor,
            width_factor: self.tool_width_factor,
            offset_x_mm: ox,
            offset_y_mm: oy,
            ellipticity: self.tool_ellipticity,
            skew: self.tool_skew,
            skew_angle_deg: self.tool_skew_angle_deg,
            drift_per_run: self.tool_drift_per_run,
        };
        tool.validate()?;
        Ok(tool)
    }
}
