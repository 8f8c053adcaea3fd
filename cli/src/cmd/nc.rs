//! `preston nc`: G-code and a point list for CAM from a solved dwell file.

use anyhow::{bail, Context};
use preston_io::atomic::commit_all;
use preston_io::job::Job;
use preston_io::machine::{read_dwell_times, stage_gcode, stage_points_csv};
use preston_io::surface::read_surface;
use preston_solver::machine::nc::{NcProgram, NcSettings, ToolAxis};
use preston_solver::machine::{Flat, PartGeometry};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Arguments of `preston nc`. Flags override the job file.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Solved dwell file (`dwell.csv` of `preston solve`: x_mm,y_mm,...,dwell_s,...).
    #[arg(long, value_name = "dwell.csv")]
    pub dwell: PathBuf,
    /// Part surface JSON (as `preston surface`/`fit` read and write); default: flat z = 0.
    #[arg(long, value_name = "S.json")]
    pub surface: Option<PathBuf>,
    /// Tool radius, mm: tool centre A = P + r n/|n| (default 0, or job [nc] tool_radius_mm).
    #[arg(long, value_name = "MM")]
    pub tool_radius_mm: Option<f64>,
    /// Write a fixed tool-axis angle B, degrees.
    #[arg(
        long,
        value_name = "DEG",
        allow_negative_numbers = true,
        conflicts_with = "tool_axis_normal"
    )]
    pub tool_axis_deg: Option<f64>,
    /// Write B following the surface normal, B = atan2(nx, nz) in degrees.
    #[arg(long)]
    pub tool_axis_normal: bool,
    /// Job file (TOML): [machine] a_max_mm_per_s2 / corner_angle_deg, [nc], [compensation].
    #[arg(long, value_name = "JOB.toml")]
    pub job: Option<PathBuf>,
    /// Machine acceleration, mm/s^2: adds the ramps to the machining time in the header.
    #[arg(long, value_name = "MM_PER_S2")]
    pub a_max_mm_per_s2: Option<f64>,
    /// Turn angle (degrees) above which the machine stops at a corner (default 60).
    #[arg(long, value_name = "DEG")]
    pub corner_angle_deg: Option<f64>,
    /// Point list `x_mm,y_mm,z_mm,nx,ny,nz,dwell_s,feed_mm_per_min` (default: the G-code path
    /// with the extension `.csv`).
    #[arg(long, value_name = "P.csv")]
    pub points_out: Option<PathBuf>,
    /// Output G-code program.
    #[arg(long, value_name = "program.nc")]
    pub out: PathBuf,
}

/// Runs `preston nc`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let job = match &args.job {
        Some(p) => Job::load(p)?,
        None => Job::default(),
    };
    let points_out = args
        .points_out
        .clone()
        .unwrap_or_else(|| args.out.with_extension("csv"));
    if points_out == args.out {
        bail!(
            "the point list and the G-code would both be written to {}; give --points-out",
            args.out.display()
        );
    }
    let tool_axis = if args.tool_axis_normal {
        ToolAxis::Normal
    } else if let Some(b_deg) = args.tool_axis_deg {
        ToolAxis::Fixed { b_deg }
    } else {
        job.nc.tool_axis.unwrap_or_default()
    };
    let settings = NcSettings {
        tool_radius_mm: args.tool_radius_mm.or(job.nc.tool_radius_mm).unwrap_or(0.0),
        tool_axis,
        a_max_mm_per_s2: args.a_max_mm_per_s2.or(job.machine.a_max_mm_per_s2),
        corner_angle_deg: args
            .corner_angle_deg
            .unwrap_or_else(|| job.corner_angle_deg()),
        compensation: job.compensation.clone(),
    };
    settings.validate()?;
    let dwell = read_dwell_times(&args.dwell)?;
    let surface = args.surface.as_deref().map(read_surface).transpose()?;
    let geometry: &dyn PartGeometry = match &surface {
        Some(s) => s,
        None => &Flat,
    };
    let program = NcProgram::plan(&dwell.path, &dwell.dwell_s, geometry, &settings)
        .with_context(|| format!("planning the program for {}", args.dwell.display()))?;
    let mut notes = vec![format!("DWELL FILE {}", file_name(&args.dwell))];
    match &args.surface {
        Some(p) => notes.push(format!("SURFACE FILE {}", file_name(p))),
        None => notes.push("SURFACE FLAT Z = 0".into()),
    }
    if let Some(p) = &args.job {
        notes.push(format!("JOB FILE {}", file_name(p)));
    }
    commit_all(vec![
        stage_gcode(&args.out, &program, &notes)?,
        stage_points_csv(&points_out, &program)?,
    ])?;
    let s = &program.schedule;
    let (f_lo, f_hi) = s.feed_range_mm_per_min();
    eprintln!(
        "preston nc: {} points, total dwell {:.2} s, machining time {:.2} s, feed {:.1} .. {:.1} mm/min, max acceleration {:.3} mm/s^2",
        program.points.len(),
        s.total_dwell_s,
        s.machining_time_s,
        f_lo,
        f_hi,
        s.max_accel_mm_per_s2
    );
    if s.segments_over_limit > 0 {
        eprintln!(
            "  warning: {} moves exceed the acceleration limit by more than 1%",
            s.segments_over_limit
        );
    }
    eprintln!(
        "  wrote {} and {}",
        args.out.display(),
        points_out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// The last component of a path (the header must not depend on where the files lie).
fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| p.display().to_string())
}
