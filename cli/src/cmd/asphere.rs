//! `preston asphere`: NC program for a rotationally symmetric asphere polished on a rotating
//! workpiece (constant removal volume, closed-loop feed compensation, edge correction).

use anyhow::{bail, Context};
use preston_io::machine::{read_profile_error, stage_asphere_nc};
use preston_solver::machine::asphere::{
    program, AsphereJob, AsphereProfile, EdgeCorrection, FeedCompensation, SpeedLaw,
};
use std::path::PathBuf;

/// Arguments of `preston asphere`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Clear aperture phi, mm.
    #[arg(long, value_name = "MM")]
    pub aperture_mm: f64,
    /// Workpiece speed at the centre, rpm.
    #[arg(long, value_name = "RPM")]
    pub n_max_rpm: f64,
    /// Workpiece speed at the edge (x = phi/2), rpm.
    #[arg(long, value_name = "RPM", required_unless_present = "match_x_mm")]
    pub n_min_rpm: Option<f64>,
    /// Instead of --n-min-rpm: choose n_min so that the speed is --match-rpm at this radius, mm.
    #[arg(
        long,
        value_name = "MM",
        requires = "match_rpm",
        conflicts_with = "n_min_rpm"
    )]
    pub match_x_mm: Option<f64>,
    /// The speed at --match-x-mm, rpm.
    #[arg(long, value_name = "RPM", requires = "match_x_mm")]
    pub match_rpm: Option<f64>,
    /// Radial feed per revolution dx, mm.
    #[arg(long, value_name = "MM")]
    pub dx_mm: f64,
    /// Radial step between program lines, mm (default dx).
    #[arg(long, value_name = "MM", conflicts_with = "x_mm")]
    pub step_mm: Option<f64>,
    /// Explicit radii of the program lines, mm, comma-separated.
    #[arg(long, value_name = "X1,X2,...", value_delimiter = ',')]
    pub x_mm: Option<Vec<f64>>,
    /// Measured profile error `x_mm,error_nm` for closed-loop feed compensation.
    #[arg(long, value_name = "E.csv")]
    pub profile_error: Option<PathBuf>,
    /// Feed factor a of k(x) = a + b [1 - (dz - dz_min)/(dz_max - dz_min)] (default 0.5).
    #[arg(long, allow_negative_numbers = true)]
    pub feed_comp_a: Option<f64>,
    /// Feed factor b of k(x) (default 1).
    #[arg(long, allow_negative_numbers = true)]
    pub feed_comp_b: Option<f64>,
    /// Edge correction start x1, mm: dZ = c + (d - c)(x - x1)/(x2 - x1) on [x1, x2].
    #[arg(long, value_name = "MM", requires_all = ["edge_x2_mm", "edge_c_mm", "edge_d_mm"])]
    pub edge_x1_mm: Option<f64>,
    /// Edge correction end x2, mm.
    #[arg(long, value_name = "MM", requires = "edge_x1_mm")]
    pub edge_x2_mm: Option<f64>,
    /// Edge correction dZ at x1, mm.
    #[arg(
        long,
        value_name = "MM",
        allow_negative_numbers = true,
        requires = "edge_x1_mm"
    )]
    pub edge_c_mm: Option<f64>,
    /// Edge correction dZ at x2, mm.
    #[arg(
        long,
        value_name = "MM",
        allow_negative_numbers = true,
        requires = "edge_x1_mm"
    )]
    pub edge_d_mm: Option<f64>,
    /// Vertex radius of curvature of the sag profile Z0, mm (default: flat).
    #[arg(long, value_name = "MM", allow_negative_numbers = true)]
    pub radius_mm: Option<f64>,
    /// Conic constant of the sag profile.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub conic: f64,
    /// Even aspheric coefficients A4,A6,... of the sag profile (mm^(1-2i)), comma-separated.
    #[arg(
        long,
        value_name = "A4,A6,...",
        value_delimiter = ',',
        allow_negative_numbers = true
    )]
    pub coefficients: Option<Vec<f64>>,
    /// Output NC program (`N<k> X<x> Z<z> B<b> S<rpm> F<feed>` lines).
    #[arg(long, value_name = "program.nc")]
    pub out: PathBuf,
}

/// Runs `preston asphere`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let n_min_rpm = match (args.n_min_rpm, args.match_x_mm, args.match_rpm) {
        (Some(n), _, _) => n,
        (None, Some(x), Some(s)) => {
            SpeedLaw::n_min_for_speed(args.aperture_mm, args.n_max_rpm, x, s)
                .context("choosing n_min from --match-x-mm and --match-rpm")?
        }
        _ => bail!("give --n-min-rpm, or --match-x-mm with --match-rpm"),
    };
    let defaults = FeedCompensation::default();
    let edge = match (
        args.edge_x1_mm,
        args.edge_x2_mm,
        args.edge_c_mm,
        args.edge_d_mm,
    ) {
        (Some(x1_mm), Some(x2_mm), Some(c_mm), Some(d_mm)) => Some(EdgeCorrection {
            x1_mm,
            x2_mm,
            c_mm,
            d_mm,
        }),
        (None, None, None, None) => None,
        _ => bail!(
            "the edge correction needs all of --edge-x1-mm --edge-x2-mm --edge-c-mm --edge-d-mm"
        ),
    };
    let job = AsphereJob {
        law: SpeedLaw {
            aperture_mm: args.aperture_mm,
            n_max_rpm: args.n_max_rpm,
            n_min_rpm,
            dx_mm: args.dx_mm,
        },
        step_mm: args.step_mm,
        x_mm: args.x_mm.clone(),
        profile: AsphereProfile {
            radius_mm: args.radius_mm,
            conic: args.conic,
            coefficients: args.coefficients.clone().unwrap_or_default(),
        },
        feed_compensation: FeedCompensation {
            a: args.feed_comp_a.unwrap_or(defaults.a),
            b: args.feed_comp_b.unwrap_or(defaults.b),
        },
        edge,
    };
    job.validate()?;
    let error = args
        .profile_error
        .as_deref()
        .map(read_profile_error)
        .transpose()?;
    let lines = program(&job, error.as_ref())?;
    stage_asphere_nc(&args.out, &job, &lines)?.commit()?;
    let (f_lo, f_hi) = lines.iter().fold((f64::INFINITY, 0.0f64), |(a, b), l| {
        (a.min(l.f_mm_per_min), b.max(l.f_mm_per_min))
    });
    crate::errln!(
        "preston asphere: {} lines, n_min {:.3} rpm, feed {:.3} .. {:.3} mm/min{}; wrote {}",
        lines.len(),
        n_min_rpm,
        f_lo,
        f_hi,
        if error.is_some() {
            " (closed-loop compensated)"
        } else {
            ""
        },
        args.out.display()
    );
    Ok(crate::EXIT_OK)
}
