//! `preston simulate`: the removal a dwell plan produces (swept, discrete or continuous motion),
//! or the removal a G-code program produces as the machine runs it (`--program`).

use super::machine_args::MachineArgs;
use super::map_input::{print_input_notes, MapInputArgs, PitchArg};
use super::tif_source::TifArgs;
use crate::progress::Bars;
use crate::summary_output::{figure_nm, print_json, resolution_phrase, OutputArgs};
use anyhow::Context;
use preston_io::job::{Job, MapSource};
use preston_io::pipeline::load_tif;
use preston_io::simulation::{
    simulate, simulate_program, write_program_simulation, write_simulation, PlanMotion,
    ProgramOptions,
};
use preston_io::surface::read_surface;
use preston_solver::dwell::FeedLimits;
use preston_solver::machine::gcode::motion::Kinematics;
use preston_solver::setup::TifModel;
use preston_solver::simulate::Motion;
use preston_solver::tif::Tif;
use std::path::Path;
use std::path::PathBuf;

/// Motion model on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum MotionArg {
    /// The tool sweeps each dwell point's stretch of path at its feed, the TIF averaged along
    /// it: the solver's default (swept) influence model, so the plan's own prediction.
    Swept,
    /// The tool dwells at the points: the solver's point influence model (`--influence point`).
    Discrete,
    /// The tool sweeps the path at the scheduled feeds, --samples-per-point midpoint samples per
    /// dwell point.
    Continuous,
}

/// Arguments of `preston simulate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Error map: CSV `x_mm,y_mm,z_nm` or any format of `preston map convert` (default: the
    /// job's [map]).
    #[arg(long, value_name = "FILE", required_unless_present = "job")]
    pub map: Option<PathBuf>,
    /// Job file (TOML): the map, the TIF and the machine ([machine] acceleration and corner
    /// angle, [nc] dialect and tool radius, [surface]) when the flags do not give them.
    #[arg(long, value_name = "JOB.toml")]
    pub job: Option<PathBuf>,
    /// Machine profile file ([machine] and [nc] tables, as in a job): the dialect, the tool
    /// radius and the acceleration limit of the machine that runs --program.
    #[arg(long, value_name = "PROFILE.toml")]
    pub machine: Option<PathBuf>,
    #[command(flatten)]
    pub map_input: MapInputArgs,
    #[command(flatten)]
    pub map_pitch: PitchArg,
    #[command(flatten)]
    pub tif: TifArgs,
    /// Dwell plan CSV `x_mm,y_mm,dwell_s` in path order (the dwell.csv of `preston solve`).
    #[arg(
        long,
        value_name = "dwell.csv",
        required_unless_present = "program",
        conflicts_with = "program"
    )]
    pub dwell: Option<PathBuf>,
    /// G-code program, any G0/G1/G2/G3 program in any dialect and feed mode (G93/G94, G4
    /// pauses): run block by block as written and the removal integrated along the motion. The
    /// DWELL markers `preston nc` writes, where present, add the per-point comparison with the
    /// plan (executed_dwell.csv); without them every feed move and pause is in contact.
    #[arg(long, value_name = "program.nc")]
    pub program: Option<PathBuf>,
    /// The machine's limits and controller (shared with solve and nc): --v-max for a plan,
    /// --a-max-mm-per-s2, --corner-angle-deg and --dialect for --program.
    #[command(flatten)]
    pub machine_args: MachineArgs,
    /// With --program: largest arc length of a removal sample, mm (default: TIF support
    /// radius / 64, for a grid TIF at most a quarter of its pitch: the solve's own).
    #[arg(
        long,
        value_name = "MM",
        requires = "program",
        allow_negative_numbers = true
    )]
    pub sample_step_mm: Option<f64>,
    /// With --program: the part surface JSON, to map tool centres back to contact points.
    #[arg(long, value_name = "S.json", requires = "program")]
    pub surface: Option<PathBuf>,
    /// With --program and a surface: the tool-centre offset along the normal (tool radius), mm
    /// (default: the machine profile's [nc] tool_radius_mm).
    #[arg(long, value_name = "MM", allow_negative_numbers = true)]
    pub tool_radius_mm: Option<f64>,
    /// Motion model; the default, swept, is the solver's default influence model, so a plan
    /// solved with it is simulated as it was planned.
    #[arg(long, value_enum, default_value = "swept")]
    pub motion: MotionArg,
    /// Midpoint-rule samples per dwell point for continuous motion.
    #[arg(long, default_value_t = 8)]
    pub samples_per_point: usize,
    /// Write figures next to the CSVs: error before, removal, residual, the PSDs (1-D along x,
    /// 2-D, azimuthal; with their CSVs) and, for a program, planned against executed dwell.
    #[arg(long)]
    pub plots: bool,
    #[command(flatten)]
    pub figures: super::figure_args::FigureArgs,
    /// Output directory for residual.csv and report.json.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
}

/// The map, TIF and machine of the flags, with a job's (and a machine profile's) where the
/// flags give none.
struct Inputs {
    map: MapSource,
    tif: Tif,
    tif_model: TifModel,
    job: Job,
}

impl Inputs {
    fn of(args: &Args) -> anyhow::Result<Self> {
        let mut job = if args.job.is_some() || args.machine.is_some() {
            Job::load_with_profile(args.job.as_deref(), args.machine.as_deref())?
        } else {
            Job::default()
        };
        let m = &args.machine_args;
        if args.program.is_none() && (m.a_max_mm_per_s2.is_some() || m.dialect.is_some()) {
            anyhow::bail!(
                "--a-max-mm-per-s2 and --dialect are the controller's that runs --program"
            );
        }
        if m.feed_mode.is_some() || m.work_offset.is_some() {
            anyhow::bail!(
                "--feed-mode and --work-offset are written by preston nc; simulate --program \
                 reads them from the program"
            );
        }
        m.v_max_mm_per_min()?;
        m.apply(&mut job)?;
        // The job's TIF (and with it its model: a Hertz TIF per point from the curvature) unless
        // the flags give one.
        let (tif, tif_model) = match (&args.job, args.tif.given()) {
            (Some(path), false) => (load_tif(&job, path)?, job.tif.model()?),
            _ => (args.tif.load()?, TifModel::ShiftInvariant),
        };
        let map = match &args.map {
            Some(file) => args.map_input.source(file.clone(), args.map_pitch.pitch_mm),
            None => {
                let mut m = job.map.clone();
                args.map_input.apply(&mut m);
                if args.map_pitch.pitch_mm.is_some() {
                    m.pitch_mm = args.map_pitch.pitch_mm;
                }
                m
            }
        };
        Ok(Self {
            map,
            tif,
            tif_model,
            job,
        })
    }
}

/// Runs `preston simulate`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    args.output.apply();
    let inputs = Inputs::of(&args)?;
    if let Some(program) = &args.program {
        return run_program(&args, &inputs, program);
    }
    let tif = inputs.tif;
    let Some(dwell) = &args.dwell else {
        anyhow::bail!("give --dwell (a plan) or --program (a G-code program)");
    };
    let motion = match args.motion {
        MotionArg::Swept => PlanMotion::Swept,
        MotionArg::Discrete => PlanMotion::Sampled(Motion::Discrete),
        MotionArg::Continuous => PlanMotion::Sampled(Motion::Continuous {
            samples_per_point: args.samples_per_point,
        }),
    };
    // The flag's feed limit only: a plan's bound violations are reported where one is asked.
    let limits = args.machine_args.v_max_mm_per_min()?.map(|v| FeedLimits {
        v_max_mm_per_min: v,
        v_min_mm_per_min: 0.0,
    });
    let bars = Bars::new();
    let sim = simulate(&inputs.map, &tif, dwell, motion, limits.as_ref(), &bars)?;
    write_simulation(&sim, &args.out, args.plots.then(|| args.figures.style()))
        .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let r = &sim.report;
    if let Some(input) = &r.map_input {
        print_input_notes(input);
    }
    crate::note!(
        "preston simulate ({}): {} map points, {} dwell points; RMS {:.3} -> {:.3} nm, PV {:.3} -> {:.3} nm, total dwell {:.2} s; wrote {}",
        r.solver,
        r.m,
        r.n,
        r.rms_before_nm,
        r.rms_after_nm,
        r.pv_before_nm,
        r.pv_after_nm,
        r.total_dwell_s,
        args.out.display()
    );
    if args.output.json {
        print_json(&serde_json::json!({
            "command": "simulate",
            "out": args.out,
            "report": r,
        }))?;
    }
    Ok(crate::EXIT_OK)
}

/// `preston simulate --program`: the program as the machine runs it.
fn run_program(args: &Args, inputs: &Inputs, program: &Path) -> anyhow::Result<u8> {
    let job = &inputs.job;
    let kinematics = Kinematics::of_limit(job.machine.a_max_mm_per_s2, job.corner_angle_deg())?;
    let surface_file = args.surface.clone().or_else(|| job.surface.file.clone());
    let surface = surface_file.as_deref().map(read_surface).transpose()?;
    let part = surface
        .as_ref()
        .map(|s| (s, args.tool_radius_mm.unwrap_or(job.nc.tool_radius_mm)));
    let bars = Bars::new();
    // The flag's or the profile's dialect; none given: the one the program's header names.
    let given = args.job.is_some() || args.machine.is_some() || args.machine_args.dialect.is_some();
    let options = ProgramOptions {
        dialect: given.then_some(job.nc.dialect),
        kinematics,
        sample_step_mm: args.sample_step_mm,
        part,
        tif_frame: job.surface.tif_frame,
        tif_model: inputs.tif_model.clone(),
    };
    let sim = simulate_program(&inputs.map, &inputs.tif, program, options, &bars)?;
    if let Some(input) = &sim.sim.report.map_input {
        print_input_notes(input);
    }
    write_program_simulation(&sim, &args.out, args.plots.then(|| args.figures.style()))
        .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    let r = &sim.sim.report;
    let c = &sim.check;
    let fig = |v: f64| figure_nm(v, r.integration.as_ref());
    crate::note!(
        "preston simulate ({}): {} map points, {} marked stretches, {} removal samples; RMS {:.3} -> {} nm, PV {:.3} -> {} nm",
        r.solver, r.m, c.stretches, sim.samples, r.rms_before_nm, fig(r.rms_after_nm), r.pv_before_nm, fig(r.pv_after_nm)
    );
    if let Some(i) = &r.integration {
        crate::note!("  the {}", resolution_phrase(i));
    }
    if c.stretches > 0 {
        crate::note!(
            "  executed {:.2} s in the stretches for {:.2} s planned ({:.2} s with the plunge and pauses); worst stretch {:.3}% off (point {}), {} of {} more than 5% off; wrote {}",
            c.executed_total_s,
            c.planned_total_s,
            sim.executed_time_s,
            100.0 * c.max_relative_error,
            c.worst_point,
            c.over_5_percent,
            c.stretches,
            args.out.display()
        );
    } else {
        crate::note!(
            "  no DWELL markers: every feed move and pause in contact, {} of them, {:.2} s executed; wrote {}",
            r.n,
            sim.executed_time_s,
            args.out.display()
        );
    }
    if args.output.json {
        print_json(&serde_json::json!({
            "command": "simulate",
            "out": args.out,
            "program": program,
            "removal_samples": sim.samples,
            "executed_time_s": sim.executed_time_s,
            "stretch_check": (c.stretches > 0).then_some(c),
            "report": r,
        }))?;
    }
    Ok(crate::EXIT_OK)
}
