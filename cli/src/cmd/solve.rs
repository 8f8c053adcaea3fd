//! `preston solve`: dwell times and feeds for a map, a TIF and a dwell path.

use super::hertz_args::HertzArgs;
use super::map_input::{print_input_notes, MapInputArgs, PitchArg};
use super::nc::{print_program_check, program_check_json};
use super::tif_source::TifArgs;
use crate::output::{print_json, OutputArgs};
use crate::progress::Bars;
use anyhow::Context;
use preston_io::job::{Job, TifSource};
use preston_io::pipeline;
use preston_io::surface::read_surface;
use preston_solver::dwell::accel::AccelMethod;
use preston_solver::dwell::{FirstOrderMethod, OperatorChoice, OperatorKind, SolverChoice};
use preston_solver::edge::EdgeMethod;
use preston_solver::influence::surface::TifFrame;
use preston_solver::influence::InfluenceModel;
use preston_solver::machine::gcode::{write_and_check, ProgramCheck};
use preston_solver::machine::nc::{NcProgram, NcSettings};
use preston_solver::machine::{Flat, PartGeometry};
use preston_solver::path::raster::RasterAxis;
use preston_solver::psd::LineAxis;
use std::path::PathBuf;
use std::process::ExitCode;

use super::EXIT_NOT_CONVERGED;

/// A TIF process model on the command line.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum TifModelArg {
    /// A spherical tool in Hertzian contact (the flags of `preston tif hertz`, --tif-pitch-mm).
    Hertz,
}

/// Arguments of `preston solve`. Flags override the job file.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Job file (TOML) holding all inputs; flags below override it.
    #[arg(long, value_name = "JOB.toml")]
    pub job: Option<PathBuf>,
    /// Machine profile file ([machine] and [nc] tables, as in a job): feed and acceleration
    /// limits and the program the plan is checked with; the job's own keys win over it.
    #[arg(long, value_name = "PROFILE.toml")]
    pub machine: Option<PathBuf>,
    /// Error map: CSV `x_mm,y_mm,z_nm` or any format of `preston map convert`.
    #[arg(long, value_name = "FILE")]
    pub map: Option<PathBuf>,
    #[command(flatten)]
    pub map_input: MapInputArgs,
    #[command(flatten)]
    pub map_pitch: PitchArg,
    /// The TIF (overrides the job's `[tif]`).
    #[command(flatten)]
    pub tif: TifArgs,
    /// The TIF from a process model instead of --tif or --gaussian-*: `hertz`, a spherical tool
    /// in Hertzian contact with --force-n, --tool-radius-mm, --spindle-rad-s, --tilt-deg,
    /// --tool-e-gpa, --tool-nu, --part-e-gpa, --part-nu and --preston-k (as `preston tif hertz`),
    /// sampled on a flat part at --tif-pitch-mm.
    #[arg(long, value_enum, conflicts_with_all = ["tif", "gaussian_sigma_mm"])]
    pub tif_model: Option<TifModelArg>,
    #[command(flatten)]
    pub hertz: HertzArgs,
    /// Pitch of the grid on which the Hertz model on a flat part is sampled, mm.
    #[arg(long, value_name = "MM")]
    pub tif_pitch_mm: Option<f64>,
    /// With the Hertz model: one TIF per dwell point, its effective radius from the design
    /// surface's principal curvatures there (needs --surface or the job's [surface]).
    #[arg(long)]
    pub curvature_dependent: bool,
    /// Dwell points CSV `x_mm,y_mm` in path order. Repeated with --tif (the k-th --dwell goes
    /// with the k-th --tif), several tools in one solve: dwell_tool1.csv, dwell_tool2.csv, ...
    #[arg(long, value_name = "D.csv", conflicts_with = "raster_pitch_mm", action = clap::ArgAction::Append)]
    pub dwell: Vec<PathBuf>,
    /// Generate a serpentine raster at this pitch (mm) over the map extended by the TIF radius.
    #[arg(long)]
    pub raster_pitch_mm: Option<f64>,
    /// Direction of the generated raster lines.
    #[arg(long, value_enum)]
    pub raster_along: Option<RasterAxis>,
    /// Fastest feed, mm/min. With several tools: once for all, or once per tool in order.
    #[arg(long = "v-max", value_name = "MM_PER_MIN", action = clap::ArgAction::Append)]
    pub v_max_mm_per_min: Vec<f64>,
    /// Several tools: weight of each tool's machining time in the rho term (once per tool, in
    /// order; default 1).
    #[arg(long, value_name = "W", action = clap::ArgAction::Append)]
    pub time_weight: Vec<f64>,
    /// Slowest feed, mm/min (0 = no limit).
    #[arg(long = "v-min", value_name = "MM_PER_MIN")]
    pub v_min_mm_per_min: Option<f64>,
    /// Acceleration limit along each path line, mm/s^2: |v_{j+1}^2 - v_j^2| <= 2 a s_j with s_j
    /// the distance between consecutive dwell points.
    #[arg(long, value_name = "MM_PER_S2")]
    pub a_max_mm_per_s2: Option<f64>,
    /// How the acceleration limit is imposed: squared-speed (default; projected gradient in
    /// squared speed, any size and operator), scp-qp (sequential QP, the small-case reference) or
    /// squared-speed-then-scp-qp (the first, refined by the second).
    #[arg(long, value_enum)]
    pub accel_method: Option<AccelMethod>,
    /// Turn angle (degrees) above which the path splits into lines for the acceleration limit
    /// and the machining time (default 60).
    #[arg(long, value_name = "DEG")]
    pub corner_angle_deg: Option<f64>,
    /// How the dwell area beyond the map is modelled (default: the job's [edge], else none).
    #[arg(long, value_enum)]
    pub edge: Option<EdgeMethod>,
    /// Width of the edge band beyond the map, mm (default: the TIF's nominal radius).
    #[arg(long, value_name = "MM")]
    pub edge_width_mm: Option<f64>,
    /// Weight of total dwell time in the objective (nm^2 per s).
    #[arg(long)]
    pub rho: Option<f64>,
    /// Weight of dwell-time differences along the path (nm^2/s^2).
    #[arg(long)]
    pub lambda: Option<f64>,
    /// Find the smallest total dwell within --min-time-tolerance of the rho = 0 optimum.
    #[arg(long)]
    pub min_time: bool,
    /// Relative objective tolerance of --min-time (default 0.001).
    #[arg(long)]
    pub min_time_tolerance: Option<f64>,
    /// Relative optimality tolerance of the solver (the QP's and the first-order solver's;
    /// defaults 1e-8 and 1e-6). The first-order solver stops when its gap bound, or its KKT
    /// residual, is below it. The residual is relative to the gradient at zero dwell and, where
    /// the plan removes more than 1 - 1e-5 of the objective (the RMS more than 316-fold), to
    /// what is left: at 1e-6 the generated benchmarks land 0.03-0.07% above the optimum, a
    /// two-tool plan 0.07% (docs/preconditioning.md).
    #[arg(long)]
    pub tolerance: Option<f64>,
    /// Iteration of the first-order solver (default: the job's, else lbfgs).
    #[arg(long, value_enum)]
    pub first_order_method: Option<FirstOrderMethod>,
    /// Correction pairs of the projected L-BFGS, 1 to 100 (default: the job's, else 10, or 5
    /// with the FFT operator). More
    /// pairs take fewer iterations: faster where a product costs far more than a pass over the
    /// dwell times (off-lattice stencil products), slower where the operator is cheap per dwell
    /// point (FFT-served maps); docs/off_lattice.md has the figures.
    #[arg(long, value_name = "PAIRS")]
    pub lbfgs_memory: Option<usize>,
    /// Iteration limit of the solver.
    #[arg(long)]
    pub max_iterations: Option<usize>,
    /// Which solver to run (default: the job's, else auto).
    #[arg(long, value_enum)]
    pub solver: Option<SolverChoice>,
    /// How R is held: assembled, or matrix-free by FFT (default: the job's, else auto).
    #[arg(long, value_enum)]
    pub operator: Option<OperatorChoice>,
    /// How the plan models the tool at a dwell point: swept (the TIF averaged along the point's
    /// stretch of path at constant feed, as the program runs it) or point (the whole TIF at the
    /// point) (default: the job's, else swept).
    #[arg(long, value_enum)]
    pub influence: Option<InfluenceModel>,
    /// Plan for the mean residual over the TIF-uncertainty scenarios (the TIF 3% wider and
    /// narrower, the tool 0.05 mm off in x and y, and the nominal): report.json `robust` gives
    /// both plans per scenario, what it costs nominally and saves in the worst scenario (job:
    /// `[solver] robust = true`). Assembles R for each scenario.
    #[arg(long)]
    pub robust: bool,
    /// Largest estimated relative error of the off-lattice spreading operator against the
    /// assembled R (default: the job's, else 1e-4).
    #[arg(long)]
    pub spread_tolerance: Option<f64>,
    /// Start the first-order solver from the `dwell_s` column of a previous dwell.csv (same dwell
    /// points, in the same order).
    #[arg(long, value_name = "dwell.csv")]
    pub warm_start: Option<PathBuf>,
    /// Exit 0 even when the solver stops before converging (the status is still reported).
    #[arg(long)]
    pub accept_best_iterate: bool,
    /// Also write figures (error_before, removal, residual, dwell, feed, tif, path; PNG or, with
    /// `--plot-format svg`, SVG) and the PSDs of error and residual: along the raster direction
    /// (psd.png, psd.csv), 2-D (psd_2d.png, psd_2d.csv) and azimuthally averaged
    /// (psd_azimuthal.png, psd_azimuthal.csv).
    #[arg(long)]
    pub plots: bool,
    /// Also write report.html: one self-contained page with the inputs and their SHA-256, the
    /// result, the machine summary, the warnings and the figures embedded.
    #[arg(long)]
    pub report: bool,
    #[command(flatten)]
    pub figures: super::figure_args::FigureArgs,
    /// Design surface JSON of a curved part: the TIF acts in each dwell point's tangent plane.
    #[arg(long, value_name = "S.json")]
    pub surface: Option<PathBuf>,
    /// Orientation of the TIF's x axis on a curved part.
    #[arg(long, value_enum, requires = "surface")]
    pub tif_frame: Option<TifFrame>,
    /// Output directory for dwell.csv, residual.csv and report.json.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
}

impl Args {
    /// The job with every flag applied over the job file.
    fn into_job(self) -> anyhow::Result<(Job, PathBuf, PathBuf, bool)> {
        let mut job = Job::load_with_profile(self.job.as_deref(), self.machine.as_deref())?;
        let job_path = self
            .job
            .clone()
            .unwrap_or_else(|| PathBuf::from("<command line>"));
        if let Some(m) = self.map {
            job.map.file = Some(m);
        }
        self.map_input.apply(&mut job.map);
        if let Some(p) = self.map_pitch.pitch_mm {
            job.map.pitch_mm = Some(p);
        }
        let tools = self.tif.tif.len().max(self.dwell.len());
        if tools > 1 {
            apply_tools(
                &mut job,
                &self.tif.tif,
                &self.dwell,
                &self.v_max_mm_per_min,
                &self.time_weight,
            )?;
        } else if !self.time_weight.is_empty() {
            anyhow::bail!("--time-weight is for several tools (repeated --tif and --dwell)");
        }
        // A TIF on the command line replaces the job's whole [tif] section.
        if let (1, Some(t)) = (tools, self.tif.tif.first()) {
            job.tif = TifSource {
                file: Some(t.clone()),
                ..TifSource::default()
            };
        }
        if let Some(g) = self.tif.gaussian()? {
            job.tif = TifSource {
                gaussian: Some(g),
                ..TifSource::default()
            };
        }
        match self.tif_model {
            Some(TifModelArg::Hertz) => {
                job.tif = TifSource {
                    hertz: Some(self.hertz.params().context("--tif-model hertz")?),
                    pitch_mm: job.tif.pitch_mm,
                    curvature_dependent: job.tif.curvature_dependent,
                    ..TifSource::default()
                };
            }
            None if self.hertz.is_given() => anyhow::bail!(
                "the Hertz tool's flags (--force-n, --tool-e-gpa, ...) go with --tif-model hertz"
            ),
            None => {}
        }
        if let Some(p) = self.tif_pitch_mm {
            job.tif.pitch_mm = Some(p);
        }
        if self.curvature_dependent {
            job.tif.curvature_dependent = true;
        }
        if let (1, Some(d)) = (tools, self.dwell.first()) {
            job.dwell.file = Some(d.clone());
            job.dwell.raster_pitch_mm = None;
        }
        if let Some(p) = self.raster_pitch_mm {
            job.dwell.raster_pitch_mm = Some(p);
            job.dwell.file = None;
        }
        if let Some(a) = self.raster_along {
            job.dwell.raster_along = a;
        }
        if let [v] = self.v_max_mm_per_min.as_slice() {
            job.machine.v_max_mm_per_min = Some(*v);
        } else if self.v_max_mm_per_min.len() > 1 && tools <= 1 {
            anyhow::bail!(
                "--v-max is repeated only with several tools (repeated --tif and --dwell)"
            );
        }
        if let Some(v) = self.v_min_mm_per_min {
            job.machine.v_min_mm_per_min = Some(v);
        }
        if let Some(a) = self.a_max_mm_per_s2 {
            job.machine.a_max_mm_per_s2 = Some(a);
        }
        if let Some(c) = self.corner_angle_deg {
            job.machine.corner_angle_deg = Some(c);
        }
        if let Some(m) = self.accel_method {
            job.machine.accel_method = Some(m);
        }
        if let Some(e) = self.edge {
            job.edge.method = e;
        }
        if let Some(w) = self.edge_width_mm {
            job.edge.width_mm = Some(w);
        }
        if let Some(r) = self.rho {
            job.objective.rho = r;
        }
        if let Some(l) = self.lambda {
            job.objective.lambda = l;
        }
        if self.min_time {
            job.solver.min_time = true;
        }
        if let Some(t) = self.min_time_tolerance {
            job.solver.min_time_tolerance = t;
        }
        if let Some(t) = self.tolerance {
            job.solver.tolerance = t;
            job.solver.first_order_tolerance = t;
        }
        if let Some(pairs) = self.lbfgs_memory {
            job.solver.lbfgs_memory = Some(pairs);
        }
        if let Some(m) = self.first_order_method {
            job.solver.first_order_method = m;
        }
        if let Some(k) = self.max_iterations {
            job.solver.max_iterations = k;
            job.solver.first_order_max_iterations = k;
        }
        if let Some(k) = self.solver {
            job.solver.solver = k;
        }
        if let Some(o) = self.influence {
            job.solver.influence = o;
        }
        if self.robust {
            job.solver.robust = true;
        }
        if let Some(o) = self.operator {
            job.solver.operator = o;
        }
        if let Some(t) = self.spread_tolerance {
            job.solver.spread_tolerance = t;
        }
        if let Some(w) = self.warm_start {
            job.dwell.warm_start = Some(w);
        }
        if let Some(f) = self.surface {
            job.surface.file = Some(f);
        }
        if let Some(f) = self.tif_frame {
            job.surface.tif_frame = f;
        }
        Ok((job, job_path, self.out, self.accept_best_iterate))
    }
}

/// Several tools from the command line: the k-th --tif with the k-th --dwell (and the k-th
/// --v-max and --time-weight when those are repeated; one --v-max applies to every tool).
fn apply_tools(
    job: &mut Job,
    tifs: &[PathBuf],
    dwells: &[PathBuf],
    v_max: &[f64],
    weights: &[f64],
) -> anyhow::Result<()> {
    let k = tifs.len();
    if dwells.len() != k {
        anyhow::bail!(
            "several tools: {k} --tif but {} --dwell; give one --dwell after each --tif",
            dwells.len()
        );
    }
    if v_max.len() > 1 && v_max.len() != k {
        anyhow::bail!(
            "several tools: {} --v-max for {k} tools; give one for all or one per tool",
            v_max.len()
        );
    }
    if !weights.is_empty() && weights.len() != k {
        anyhow::bail!(
            "several tools: {} --time-weight for {k} tools; give one per tool",
            weights.len()
        );
    }
    if let [v] = v_max {
        job.machine.v_max_mm_per_min = Some(*v);
    }
    job.tool = tifs
        .iter()
        .zip(dwells)
        .enumerate()
        .map(|(i, (t, d))| preston_io::job::ToolSpec {
            tif: TifSource {
                file: Some(t.clone()),
                ..TifSource::default()
            },
            dwell: d.clone(),
            v_max_mm_per_min: (v_max.len() > 1).then(|| v_max[i]),
            v_min_mm_per_min: None,
            time_weight: weights.get(i).copied(),
        })
        .collect();
    Ok(())
}

/// Runs `preston solve` with several tools (`[[tool]]` or repeated --tif/--dwell).
fn run_tools(
    job: &Job,
    job_path: &std::path::Path,
    out: &std::path::Path,
    accept_best: bool,
    output: OutputArgs,
) -> anyhow::Result<ExitCode> {
    let bars = Bars::new();
    let solved = preston_io::tools::solve_tools(job, job_path, &bars)?;
    preston_io::tools::write_tool_outputs(&solved, out)
        .with_context(|| format!("writing outputs to {}", out.display()))?;
    let r = &solved.report;
    crate::note!(
        "preston solve: {} map points, {} tools, {} dwell points in all, {} non-zeros (assembled, stacked)",
        r.m,
        r.tools.len(),
        r.n,
        r.nnz
    );
    for w in &r.warnings {
        crate::errln!("  warning: {w}");
    }
    for t in &r.tools {
        crate::note!(
            "  tool {}: {} points, dwell {:.2} s, removal RMS {:.3} nm PV {:.3} nm, feed {:.1} .. {:.1} mm/min",
            t.tool, t.n, t.total_dwell_s, t.removal_rms_nm, t.removal_pv_nm, t.min_feed_mm_per_min, t.max_feed_mm_per_min
        );
    }
    crate::note!(
        "  RMS {:.3} -> {:.3} nm, PV {:.3} -> {:.3} nm; solver {} ({} iterations, status {}), solve {:.3} s; wrote {}",
        r.rms_before_nm, r.rms_after_nm, r.pv_before_nm, r.pv_after_nm, r.solver, r.iterations, r.status, r.solve_seconds,
        out.display()
    );
    let converged = solved.solution.status.is_converged();
    if !converged {
        crate::errln!(
            "  warning: the solver did not converge (status {}); outputs hold the best iterate",
            r.status
        );
    }
    let code = if converged || accept_best {
        0
    } else {
        EXIT_NOT_CONVERGED
    };
    if output.json {
        print_json(&serde_json::json!({
            "command": "solve",
            "exit_code": code,
            "converged": converged,
            "out": out,
            "report": r,
        }))?;
    }
    Ok(ExitCode::from(code))
}

/// Runs `preston solve`.
pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let plots = args.plots;
    let output = args.output;
    output.apply();
    let html = args.report;
    let style = args.figures.style();
    let (job, job_path, out, accept_best) = args.into_job()?;
    if preston_io::tools::is_multi_tool(&job) {
        return run_tools(&job, &job_path, &out, accept_best, output);
    }
    let bars = Bars::new();
    let prepared = pipeline::prepare(&job, &job_path, &bars)?;
    // The inputs' warnings come before a solve that may run for minutes.
    for w in &prepared.warnings {
        crate::errln!("  warning: {w}");
    }
    let early_warnings = prepared.warnings.len();
    let solved = pipeline::solve(prepared, &job, &bars)?;
    let axis = match job.dwell.raster_along {
        RasterAxis::X => LineAxis::X,
        RasterAxis::Y => LineAxis::Y,
    };
    let options = pipeline::OutputOptions {
        figures: Some((axis, job.dwell.raster_pitch_mm)),
        plots,
        html: html.then(|| {
            preston_io::html::Provenance::of_job(
                &job,
                &job_path,
                Some(preston_io::html::Provenance::command_line()),
            )
        }),
        style,
    };
    let notes = pipeline::write_solve_outputs(&solved, &out, &options)
        .with_context(|| format!("writing outputs to {}", out.display()))?;
    for note in notes {
        crate::note!("  note: {note}");
    }
    let r = &solved.report;
    print_input_notes(&solved.prepared.map_input);
    crate::note!(
        "preston solve: {} map points{}, {} dwell points, {} non-zeros ({}){}",
        r.m,
        if r.edge_points > 0 {
            format!(" + {} edge points", r.edge_points)
        } else {
            String::new()
        },
        r.n,
        r.nnz,
        match r.operator {
            OperatorKind::Fft => "matrix-free FFT operator",
            OperatorKind::FftSpread => "matrix-free, spread onto the map lattice + FFT",
            OperatorKind::Stencil => "matrix-free, phase stencils on the map lattice",
            OperatorKind::Nufft => "matrix-free, ES spreading onto a fine lattice + FFT (NUFFT)",
            OperatorKind::Sparse => "assembled",
        },
        if r.skipped_rows > 0 {
            format!(", {} map rows skipped (empty or NaN z_nm)", r.skipped_rows)
        } else {
            String::new()
        }
    );
    for w in r.warnings.iter().skip(early_warnings) {
        crate::errln!("  warning: {w}");
    }
    if r.unreachable_dwell_points > 0 {
        let shown: Vec<String> = r
            .unreachable_dwell_indices
            .iter()
            .take(10)
            .map(|k| k.to_string())
            .collect();
        crate::errln!(
            "  warning: {} dwell points have no map point in the tool's reach; their dwell is at its lower bound (indices {}{}; all listed in report.json)",
            r.unreachable_dwell_points,
            shown.join(", "),
            if r.unreachable_dwell_points > 10 { ", ..." } else { "" }
        );
    }
    crate::note!(
        "  RMS {:.3} -> {:.3} nm, PV {:.3} -> {:.3} nm{}, piston {:.3} nm",
        r.rms_before_nm,
        r.rms_after_nm,
        r.pv_before_nm,
        r.pv_after_nm,
        match &r.model {
            Some(m) => format!(
                " as the program executes (model {:.3} nm RMS, {:.3} nm PV)",
                m.rms_nm, m.pv_nm
            ),
            None => String::new(),
        },
        r.piston_nm
    );
    crate::note!(
        "  total dwell {:.2} s, feed {:.1} .. {:.1} mm/min",
        r.total_dwell_s,
        r.min_feed_mm_per_min,
        r.max_feed_mm_per_min
    );
    if let Some(mt) = &r.min_time {
        crate::note!(
            "  minimum time: {:.2} s instead of {:.2} s at rho = 0 (objective {:.6e} vs {:.6e}, tolerance {})",
            r.total_dwell_s, mt.total_dwell_rho0_s, r.objective, mt.objective_rho0, mt.tolerance
        );
    }
    let correction_passes =
        r.accel.as_ref().map(|x| x.method) == Some(AccelMethod::CorrectionPasses);
    crate::note!(
        "  machining time {:.2} s, max acceleration {:.3} mm/s^2{}",
        r.machining_time_s,
        r.max_accel_mm_per_s2,
        match r.a_max_mm_per_s2 {
            Some(a) if correction_passes && r.max_accel_mm_per_s2 > a => format!(
                " between the programmed feeds (the controller's look-ahead holds {a} mm/s^2; the executed figures include its ramps)"
            ),
            _ => String::new(),
        }
    );
    if let (Some(a), Some(it), Some(rms0)) = (
        r.a_max_mm_per_s2,
        r.accel_iterations,
        r.rms_feed_limited_only_nm,
    ) {
        crate::note!(
            "  acceleration limit {a} mm/s^2: {it} {}, model RMS {:.3} nm vs {rms0:.3} nm feed-limited only",
            match r.accel.as_ref().map(|x| x.method) {
                Some(AccelMethod::ScpQp) => "SCP iterations",
                Some(AccelMethod::SquaredSpeedThenScpQp) => "gradient steps and SCP iterations",
                Some(AccelMethod::CorrectionPasses) => "gradient steps (none: correction passes)",
                _ => "gradient steps in squared speed",
            },
            r.accel.as_ref().map_or(r.rms_after_nm, |x| x.rms_after_nm)
        );
    }
    let mut certificate = Vec::new();
    if let Some(k) = r.kkt_residual {
        certificate.push(format!("KKT residual {k:.2e}"));
    }
    match (r.objective_gap_bound, &r.gap_bound_reason) {
        (Some(g), _) => certificate.push(format!("objective gap <= {g:.3e} nm^2")),
        (None, Some(why)) => certificate.push(format!("no gap bound: {why}")),
        (None, None) => {}
    }
    crate::note!(
        "  solver {}{} ({} iterations, status {}{}), build {:.3} s, solve {:.3} s; wrote {}",
        r.solver,
        if certificate.is_empty() {
            String::new()
        } else {
            format!(" [{}]", certificate.join(", "))
        },
        r.iterations,
        r.status,
        r.converged_by
            .map(|c| format!(" by {c}"))
            .unwrap_or_default(),
        r.build_seconds,
        r.solve_seconds,
        out.display()
    );
    let check = program_check(&solved, &job);
    let converged = solved.solution().status.is_converged();
    if !converged {
        crate::errln!(
            "  warning: the solver did not converge (status {}); outputs hold the best iterate",
            r.status
        );
    }
    let code = if converged || accept_best {
        0
    } else {
        EXIT_NOT_CONVERGED
    };
    if output.json {
        print_json(&serde_json::json!({
            "command": "solve",
            "exit_code": code,
            "converged": converged,
            "out": out,
            "report": r,
            "program_check": check.as_ref().map(program_check_json),
        }))?;
    }
    Ok(ExitCode::from(code))
}

/// Plans the program for the solution on the job's machine profile (`[nc]`: dialect, feed mode,
/// tool radius and axis; its surface, feed and acceleration limits), reads it back and prints
/// what the machine would do with it; a plan no program can deliver is a warning here
/// (`preston nc` refuses it).
fn program_check(solved: &pipeline::Solved, job: &Job) -> Option<ProgramCheck> {
    let settings = NcSettings {
        a_max_mm_per_s2: job.machine.a_max_mm_per_s2,
        corner_angle_deg: job.corner_angle_deg(),
        compensation: job.compensation.clone(),
        v_max_mm_per_min: job.machine.v_max_mm_per_min,
        ..job.nc.nc_settings()
    };
    let surface = match &job.surface.file {
        Some(f) => match read_surface(f) {
            Ok(s) => Some(s),
            Err(e) => {
                crate::errln!("  warning: no program check: {e}");
                return None;
            }
        },
        None => None,
    };
    let geometry: &dyn PartGeometry = match &surface {
        Some(s) => s,
        None => &Flat,
    };
    let p = solved.prepared.path();
    let checked = NcProgram::plan(p, &solved.solution().dwell_s, geometry, &settings)
        .and_then(|nc| write_and_check(&nc, &[]));
    match checked {
        Ok(c) => {
            print_program_check(&c);
            Some(c)
        }
        Err(e) => {
            crate::errln!("  warning: no G-code program can deliver this plan as it is: {e}");
            None
        }
    }
}
