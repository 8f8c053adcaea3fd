//! `preston nc`: G-code and a point list for CAM from a solved dwell file.

use super::machine_args::MachineArgs;
use crate::summary_output::{print_json, OutputArgs};
use anyhow::{bail, Context};
use preston_io::atomic::{commit_all, stage};
use preston_io::job::Job;
use preston_io::machine::{program_check_summary, read_dwell_times, stage_points_csv};
use preston_io::surface::read_surface;
use preston_solver::machine::gcode::{write_and_check, ProgramCheck};
use preston_solver::machine::nc::{NcProgram, NcSettings, ToolAxis};
use preston_solver::machine::profile::{Coolant, MachineProfile};
use preston_solver::machine::{Flat, PartGeometry};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Arguments of `preston nc`. Flags override the job file.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Solved dwell file (`dwell.csv` of `preston solve`: x_mm,y_mm,...,dwell_s,...).
    #[arg(long, value_name = "dwell.csv")]
    pub dwell: PathBuf,
    /// Part surface JSON (as `preston surface`/`fit` read and write); default: the job's
    /// [surface], else flat z = 0.
    #[arg(long, value_name = "S.json")]
    pub surface: Option<PathBuf>,
    /// Tool radius, mm: tool centre A = P + r n/|n| (default 0, or job [nc] tool_radius_mm).
    #[arg(long, value_name = "MM", allow_negative_numbers = true)]
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
    /// Job file (TOML): [machine] a_max_mm_per_s2 / corner_angle_deg / v_max_mm_per_min, [nc]
    /// (the machine profile), [compensation].
    #[arg(long, value_name = "JOB.toml")]
    pub job: Option<PathBuf>,
    /// Machine profile file ([machine] and [nc] tables, as in a job) shared by the jobs of one
    /// machine: dialect, feed mode, work offset, start and end blocks, spindle, coolant, program
    /// number, decimals, tool radius and axis. The job's own keys win over it, the flags over
    /// both.
    #[arg(long, value_name = "PROFILE.toml")]
    pub machine: Option<PathBuf>,
    /// The machine's limits and controller (shared with solve and simulate).
    #[command(flatten)]
    pub machine_args: MachineArgs,
    /// Clearance above the highest tool-centre point, mm: rapid there, above the run-in start,
    /// plunge, and retract at the end (default: the machine profile's, else 5).
    #[arg(long, value_name = "MM", allow_negative_numbers = true)]
    pub clearance_mm: Option<f64>,
    /// Feed of the plunge from the clearance plane, mm/min (default: the machine profile's,
    /// else 300).
    #[arg(long, value_name = "MM_PER_MIN", allow_negative_numbers = true)]
    pub plunge_feed_mm_per_min: Option<f64>,
    /// Shortest block the controller runs, ms (its block rate): a shorter block is an error
    /// (default: the machine profile's, else 2).
    #[arg(long, value_name = "MS", allow_negative_numbers = true)]
    pub min_block_time_ms: Option<f64>,
    /// Spindle speed, rpm: `S.. M3` at the start, `M5` at the end.
    #[arg(long, value_name = "RPM", allow_negative_numbers = true)]
    pub spindle_rpm: Option<f64>,
    /// Coolant or slurry on (`M8`) during the program, off (`M9`) at the end.
    #[arg(long)]
    pub coolant: bool,
    /// Decimals of the coordinates, 3 to 6 (default: the machine profile's, else 4).
    #[arg(long, value_name = "N")]
    pub decimals: Option<usize>,
    /// Write G02/G03 (G17, I J centre offsets) where the tool-centre path is a circular arc.
    #[arg(long)]
    pub arcs: bool,
    /// With --arcs: largest distance of a dwell point from the arc it is written on, um
    /// (default: the machine profile's arc_tolerance_um, else 1).
    #[arg(long, value_name = "UM")]
    pub arc_tolerance_um: Option<f64>,
    /// Point list `x_mm,y_mm,z_mm,nx,ny,nz,dwell_s,feed_mm_per_min` (default: the G-code path
    /// with the extension `.csv`).
    #[arg(long, value_name = "P.csv")]
    pub points_out: Option<PathBuf>,
    /// Output G-code program (its directory is created).
    #[arg(long, value_name = "program.nc")]
    pub out: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// The machine profile with the flags given over it.
fn profile_with_flags(args: &Args, job: &Job) -> MachineProfile {
    let mut p = job.nc.clone();
    if let Some(r) = args.tool_radius_mm {
        p.tool_radius_mm = r;
    }
    if args.tool_axis_normal {
        p.tool_axis = ToolAxis::Normal;
    } else if let Some(b_deg) = args.tool_axis_deg {
        p.tool_axis = ToolAxis::Fixed { b_deg };
    }
    if let Some(c) = args.clearance_mm {
        p.clearance_mm = c;
    }
    if let Some(f) = args.plunge_feed_mm_per_min {
        p.plunge_feed_mm_per_min = f;
    }
    if let Some(t) = args.min_block_time_ms {
        p.min_block_time_ms = t;
    }
    if args.spindle_rpm.is_some() {
        p.spindle_rpm = args.spindle_rpm;
    }
    if args.coolant {
        p.coolant = Coolant::Flood;
    }
    if let Some(d) = args.decimals {
        p.decimals = d;
    }
    if args.arcs {
        p.arc_tolerance_um = Some(args.arc_tolerance_um.or(p.arc_tolerance_um).unwrap_or(1.0));
    }
    p
}

/// Runs `preston nc`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    args.output.apply();
    let mut job = Job::load_with_profile(args.job.as_deref(), args.machine.as_deref())?;
    args.machine_args.v_max_mm_per_min()?;
    args.machine_args.apply(&mut job)?;
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
    let profile = profile_with_flags(&args, &job);
    profile.validate()?;
    let settings = NcSettings {
        a_max_mm_per_s2: job.machine.a_max_mm_per_s2,
        corner_angle_deg: job.corner_angle_deg(),
        compensation: job.compensation.clone(),
        v_max_mm_per_min: job.machine.v_max_mm_per_min,
        ..profile.nc_settings()
    };
    settings.validate()?;
    let dwell = read_dwell_times(&args.dwell)?;
    // The flag's surface, else the job's [surface]: the program follows the part it polishes.
    let surface_file = args.surface.clone().or_else(|| job.surface.file.clone());
    let surface = surface_file.as_deref().map(read_surface).transpose()?;
    let geometry: &dyn PartGeometry = match &surface {
        Some(s) => s,
        None => &Flat,
    };
    let program = NcProgram::plan(&dwell.path, &dwell.dwell_s, geometry, &settings)
        .with_context(|| format!("planning the program for {}", args.dwell.display()))?;
    let mut notes = vec![format!("INPUT DWELL FILE {}", file_name(&args.dwell))];
    match &surface_file {
        Some(p) => notes.push(format!("SURFACE FILE {}", file_name(p))),
        None => notes.push("SURFACE FLAT Z = 0".into()),
    }
    if let Some(p) = &args.job {
        notes.push(format!("JOB FILE {}", file_name(p)));
    }
    if let Some(p) = &job.machine.profile {
        notes.push(format!("MACHINE PROFILE {}", file_name(p)));
    }
    let check = write_and_check(&program, &notes)
        .with_context(|| format!("writing the program for {}", args.dwell.display()))?;
    for dir in [args.out.parent(), points_out.parent()]
        .into_iter()
        .flatten()
    {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("creating the directory {}", dir.display()))?;
        }
    }
    let text = check.written.text.as_bytes();
    commit_all(vec![
        stage(&args.out, |w: &mut dyn Write| w.write_all(text))?,
        stage_points_csv(&points_out, &program)?,
    ])?;
    let s = &program.schedule;
    crate::note!(
        "preston nc: {} points, {} feed blocks ({} dialect, {}), total dwell {:.2} s, max acceleration {:.3} mm/s^2 (solver model)",
        program.points.len(),
        check.written.feed_blocks,
        settings.dialect.name(),
        settings.feed_mode.name(),
        s.total_dwell_s,
        s.max_accel_mm_per_s2
    );
    print_program_check(&check);
    crate::note!(
        "  wrote {} and {}",
        args.out.display(),
        points_out.display()
    );
    if args.output.json {
        print_json(&serde_json::json!({
            "command": "nc",
            "program": args.out,
            "points_out": points_out,
            "points": program.points.len(),
            "dialect": settings.dialect,
            "feed_mode": settings.feed_mode,
            "total_dwell_s": s.total_dwell_s,
            "program_check": program_check_summary(&check),
        }))?;
    }
    Ok(crate::EXIT_OK)
}

/// Prints what the program as written does with the plan (`preston nc` and `preston solve`).
pub fn print_program_check(check: &ProgramCheck) {
    let w = &check.written;
    let p = &check.programmed;
    crate::note!(
        "  program as written: machining time {:.2} s ({:.2} s in the dwell stretches for {:.2} s planned, plunge {:.2} s); worst stretch {:.3}% off (point {}), {} of {} more than 5% off",
        w.stretch_time_s + w.plunge_time_s,
        p.executed_total_s,
        p.planned_total_s,
        w.plunge_time_s,
        100.0 * p.max_relative_error,
        p.worst_point,
        p.over_5_percent,
        p.stretches
    );
    if w.merged_stretches > 0 {
        crate::note!(
            "  {} stretches written as one block through their point (a half would have been shorter than the block time)",
            w.merged_stretches
        );
    }
    if w.slowed_stretches > 0 {
        crate::errln!(
            "  warning: {} stretches need more than v_max on the tool-centre path and are programmed at v_max (up to {:.2}% longer than planned)",
            w.slowed_stretches,
            100.0 * (w.max_slowdown - 1.0)
        );
    }
    if let Some(a) = &check.accelerated {
        crate::note!(
            "  executed with the acceleration limit (the controller's look-ahead ramps between the programmed feeds, moving time between neighbouring stretches; the removal of that motion is what counts): {:.2} s in the stretches; worst stretch {:.2}% off its planned time (point {}), {} of {} more than 5% off",
            a.executed_total_s,
            100.0 * a.max_relative_error,
            a.worst_point,
            a.over_5_percent,
            a.stretches
        );
    }
}

/// The last component of a path (the header must not depend on where the files lie).
fn file_name(p: &Path) -> String {
    p.file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| p.display().to_string())
}
