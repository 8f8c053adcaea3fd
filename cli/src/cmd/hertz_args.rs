//! The parameters of a spherical tool in Hertzian contact, shared by `preston tif hertz` and
//! `preston solve --tif-model hertz`: the same flag names, units and defaults in both.

use preston_solver::tif::HertzParams;

/// A spherical tool pressed on a part and spun about a tilted axis
/// ([`preston_solver::tif::hertz`]). Every flag is optional to clap (so that `preston solve`
/// runs without them); [`HertzArgs::params`] fills the defaults and names the missing ones.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct HertzArgs {
    /// Normal force, N [default: 10].
    #[arg(long, value_name = "N")]
    pub force_n: Option<f64>,
    /// Tool (sphere) radius, mm [default: 16].
    #[arg(long, value_name = "MM")]
    pub tool_radius_mm: Option<f64>,
    /// Spindle speed, rad/s [default: 104.72].
    #[arg(long, value_name = "RAD_S")]
    pub spindle_rad_s: Option<f64>,
    /// Tilt of the spindle axis from the part normal, degrees [default: 15].
    #[arg(long, value_name = "DEG")]
    pub tilt_deg: Option<f64>,
    /// Tool Young's modulus, GPa (no default: needed by the Hertz model).
    #[arg(long, value_name = "GPA")]
    pub tool_e_gpa: Option<f64>,
    /// Tool Poisson ratio (no default: needed by the Hertz model).
    #[arg(long, value_name = "NU")]
    pub tool_nu: Option<f64>,
    /// Part Young's modulus, GPa (no default: needed by the Hertz model).
    #[arg(long, value_name = "GPA")]
    pub part_e_gpa: Option<f64>,
    /// Part Poisson ratio (no default: needed by the Hertz model).
    #[arg(long, value_name = "NU")]
    pub part_nu: Option<f64>,
    /// Preston coefficient K, mm^2/N (rate mm/s = K * p MPa * v mm/s) (no default: needed by the Hertz model).
    #[arg(long, value_name = "K")]
    pub preston_k: Option<f64>,
}

impl HertzArgs {
    /// Whether any of the flags is given.
    pub fn is_given(&self) -> bool {
        [
            self.force_n,
            self.tool_radius_mm,
            self.spindle_rad_s,
            self.tilt_deg,
            self.tool_e_gpa,
            self.tool_nu,
            self.part_e_gpa,
            self.part_nu,
            self.preston_k,
        ]
        .iter()
        .any(Option::is_some)
    }

    /// The model's parameters (validated where they are used): force, tool radius, spindle
    /// speed and tilt default to the published case of [`HertzParams::default`]; the materials
    /// and the Preston coefficient must be given.
    pub fn params(&self) -> anyhow::Result<HertzParams> {
        let missing: Vec<&str> = [
            ("--tool-e-gpa", self.tool_e_gpa),
            ("--tool-nu", self.tool_nu),
            ("--part-e-gpa", self.part_e_gpa),
            ("--part-nu", self.part_nu),
            ("--preston-k", self.preston_k),
        ]
        .iter()
        .filter(|(_, v)| v.is_none())
        .map(|(flag, _)| *flag)
        .collect();
        if !missing.is_empty() {
            anyhow::bail!("the Hertz model needs {}", missing.join(", "));
        }
        let d = HertzParams::default();
        Ok(HertzParams {
            force_n: self.force_n.unwrap_or(d.force_n),
            tool_radius_mm: self.tool_radius_mm.unwrap_or(d.tool_radius_mm),
            spindle_rad_s: self.spindle_rad_s.unwrap_or(d.spindle_rad_s),
            tilt_deg: self.tilt_deg.unwrap_or(d.tilt_deg),
            tool_e_gpa: self.tool_e_gpa.unwrap_or(d.tool_e_gpa),
            tool_nu: self.tool_nu.unwrap_or(d.tool_nu),
            part_e_gpa: self.part_e_gpa.unwrap_or(d.part_e_gpa),
            part_nu: self.part_nu.unwrap_or(d.part_nu),
            preston_k_mm2_per_n: self.preston_k.unwrap_or(d.preston_k_mm2_per_n),
        })
    }
}
