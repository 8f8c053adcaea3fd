//! `preston solve`: dwell times and feeds for a map, a TIF and a dwell path.

use super::hertz_args::HertzArgs;
use super::machine_args::MachineArgs;
use super::map_input::{print_input_notes, MapInputArgs, PitchArg};
use super::nc::print_program_check;
use super::tif_source::TifArgs;
use crate::progress::Bars;
use crate::summary_output::{figure_nm, print_json, resolution_phrase, OutputArgs};
use anyhow::Context;
use preston_io::job::{Job, TifSource};
use preston_io::machine::program_check_summary;
use preston_io::overrides::Overrides;
use preston_io::pipeline;
use preston_solver::dwell::accel::AccelMethod;
use preston_solver::dwell::OperatorKind;
use preston_solver::machine::gcode::ProgramCheck;
use preston_solver::path::raster::RasterAxis;
use preston_solver::psd::LineAxis;
use preston_solver::setup::pays::PlanScope;
use std::path::{Path, PathBuf};

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
    /// What a solve may change over the job file: one definition with the Python package's
    /// keywords ([`Overrides`]).
    #[command(flatten)]
    pub overrides: Overrides,
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
    /// Dwell points CSV `x_mm,y_mm` in path order. Repeated with --tif (the k-th --dwell goes
    /// with the k-th --tif), several tools in one solve: dwell_tool1.csv, dwell_tool2.csv, ...
    #[arg(long, value_name = "D.csv", action = clap::ArgAction::Append)]
    pub dwell: Vec<PathBuf>,
    /// The machine's limits and controller (shared with nc and simulate).
    #[command(flatten)]
    pub machine_args: MachineArgs,
    /// Several tools: weight of each tool's machining time in the rho term (once per tool, in
    /// order; default 1).
    #[arg(long, value_name = "W", action = clap::ArgAction::Append)]
    pub time_weight: Vec<f64>,
    /// Exit 0 even when the solver stops before converging (the status is still reported).
    #[arg(long)]
    pub accept_best_iterate: bool,
    /// Also write figures (error_before, removal, residual, dwell, feed, tif, path; PNG or, with
    /// `--plot-format svg`, SVG) and the PSDs of error and residual: along the raster direction
    /// (psd.png, psd.csv), 2-D (psd_2d.png, psd_2d.csv) and azimuthally averaged
    /// (psd_azimuthal.png, psd_azimuthal.csv). With several tools: each tool's dwell and feed
    /// (dwell_tool1, feed_tool1, ...) in place of dwell, feed, tif and path.
    #[arg(long)]
    pub plots: bool,
    /// Also write report.html: one self-contained page with the inputs and their SHA-256, the
    /// result, the machine summary, the warnings and the figures embedded.
    #[arg(long)]
    pub report: bool,
    #[command(flatten)]
    pub figures: super::figure_args::FigureArgs,
    /// Output directory for dwell.csv, residual.csv and report.json.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
}

impl Args {
    /// The job with every flag applied over the job file: the map's reading flags and the
    /// several-tools syntax here, the rest through [`Overrides::apply`].
    fn into_job(self) -> anyhow::Result<(Job, PathBuf, PathBuf, bool)> {
        let mut job = Job::load_with_profile(self.job.as_deref(), self.machine.as_deref())?;
        let job_path = self
            .job
            .clone()
            .unwrap_or_else(|| PathBuf::from(preston_io::overrides::COMMAND_LINE));
        self.map_input.apply(&mut job.map);
        if let Some(p) = self.map_pitch.pitch_mm {
            job.map.pitch_mm = Some(p);
        }
        self.machine_args.apply(&mut job)?;
        let mut overrides = self.overrides;
        let tools = self.tif.tif.len().max(self.dwell.len());
        if tools > 1 {
            // Each tool's points are its file: a raster pitch is refused by the one rule.
            preston_io::job::DwellSource::of(
                self.dwell.first().cloned(),
                overrides.raster_pitch_mm,
            )
            .map_err(anyhow::Error::msg)?;
            apply_tools(
                &mut job,
                &self.tif.tif,
                &self.dwell,
                &self.machine_args.v_max_mm_per_min,
                &self.time_weight,
            )?;
        } else {
            if !self.time_weight.is_empty() {
                anyhow::bail!("--time-weight is for several tools (repeated --tif and --dwell)");
            }
            self.machine_args.v_max_mm_per_min()?;
            overrides.tif = self.tif.tif.first().cloned();
            overrides.dwell = self.dwell.first().cloned();
        }
        overrides.gaussian = self.tif.gaussian()?;
        overrides.hertz = match self.tif_model {
            Some(TifModelArg::Hertz) => Some(self.hertz.params().context("--tif-model hertz")?),
            None if self.hertz.is_given() => anyhow::bail!(
                "the Hertz tool's flags (--force-n, --tool-e-gpa, ...) go with --tif-model hertz"
            ),
            None => None,
        };
        overrides.apply(&mut job, Path::new(preston_io::overrides::COMMAND_LINE))?;
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

/// The figures' line direction: the raster's.
fn axis_of(along: RasterAxis) -> LineAxis {
    match along {
        RasterAxis::X => LineAxis::X,
        RasterAxis::Y => LineAxis::Y,
    }
}

/// Runs `preston solve` with several tools (`[[tool]]` or repeated --tif/--dwell), writing
/// what `options` asks for.
fn run_tools(
    job: &Job,
    job_path: &std::path::Path,
    out: &std::path::Path,
    options: &pipeline::OutputOptions,
    accept_best: bool,
    output: OutputArgs,
) -> anyhow::Result<u8> {
    let bars = Bars::new();
    let solved = preston_io::tools::solve_tools(job, job_path, &bars)?;
    let notes = preston_io::tools::write_tool_outputs(&solved, out, options)
        .with_context(|| format!("writing outputs to {}", out.display()))?;
    for note in notes {
        crate::note!("  note: {note}");
    }
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
    finish(
        solved.solution.status.is_converged(),
        accept_best,
        output,
        out,
        r,
        None,
    )
}

/// The end of a solve: the warning of a solve that did not converge, `--json`'s summary and the
/// exit code (0, or 3 when the solver stopped before converging and `--accept-best-iterate` was
/// not given).
fn finish(
    converged: bool,
    accept_best: bool,
    output: OutputArgs,
    out: &std::path::Path,
    report: &preston_io::report::Report,
    check: Option<&ProgramCheck>,
) -> anyhow::Result<u8> {
    if !converged {
        crate::errln!(
            "  warning: the solver did not converge (status {}); outputs hold the best iterate",
            report.status
        );
    }
    let code = if converged || accept_best {
        0
    } else {
        EXIT_NOT_CONVERGED
    };
    if output.json {
        let mut summary = serde_json::json!({
            "command": "solve",
            "exit_code": code,
            "converged": converged,
            "out": out,
            "report": report,
        });
        if let Some(c) = check {
            summary["program_check"] = program_check_summary(c);
        }
        print_json(&summary)?;
    }
    Ok(code)
}

/// Runs `preston solve`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let plots = args.plots;
    let output = args.output;
    output.apply();
    let html = args.report;
    let style = args.figures.style();
    let (job, job_path, out, accept_best) = args.into_job()?;
    let options = pipeline::OutputOptions {
        figures: Some((
            axis_of(job.dwell.raster_along),
            job.dwell.source.raster_pitch_mm(),
        )),
        plots,
        html: html.then(|| {
            preston_io::html::Provenance::of_job(
                &job,
                &job_path,
                Some(preston_io::html::Provenance::command_line()),
            )
        }),
        style,
        // The outputs of a run are the run's: an earlier solve's files this one does not write
        // go with the commit (never the run's own inputs).
        replace_earlier: Some(job.input_files()),
    };
    if preston_io::tools::is_multi_tool(&job) {
        return run_tools(&job, &job_path, &out, &options, accept_best, output);
    }
    let bars = Bars::new();
    let prepared = pipeline::prepare(&job, &job_path, &bars)?;
    // The inputs' warnings come before a solve that may run for minutes.
    for w in &prepared.warnings {
        crate::errln!("  warning: {w}");
    }
    for n in &prepared.notes {
        crate::note!("  note: {n}");
    }
    let early_warnings = prepared.warnings.len();
    let solved = pipeline::solve(prepared, &job, &bars)?;
    let notes = pipeline::write_solve_outputs(&solved, &out, &options)
        .with_context(|| format!("writing outputs to {}", out.display()))?;
    for note in notes {
        crate::note!("  note: {note}");
    }
    print_summary(&solved, early_warnings, &out);
    let r = &solved.report;
    let check = print_check(&solved);
    finish(
        solved.solution().status.is_converged(),
        accept_best,
        output,
        &out,
        r,
        check,
    )
}

/// Prints what a solve did: sizes and operator, the warnings after `early_warnings` (those of
/// the inputs were printed before the solve), the residual, dwell, feeds, machining time, the
/// acceleration limit's account and the solver's certificate.
fn print_summary(solved: &pipeline::Solved, early_warnings: usize, out: &std::path::Path) {
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
            OperatorKind::Expansion => {
                "matrix-free, direction expansion spread onto the map lattice + FFT, exact correction"
            }
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
    if r.unreachable_dwell_points > 0 && r.raster.is_some() {
        // Preston's own raster covers the map widened by the TIF's radius: its points at the
        // margin's corners reach past the footprint's non-zero part. Nothing is wrong with the
        // inputs.
        crate::note!(
            "  note: {} points of the raster's margin (the map widened by the TIF's radius) reach no map point with the TIF's non-zero part; they pass at the fastest feed (listed in report.json)",
            r.unreachable_dwell_points
        );
    } else if r.unreachable_dwell_points > 0 {
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
    let integration = r.executed.as_ref().and_then(|e| e.integration);
    let fig = |v: f64| figure_nm(v, integration.as_ref());
    crate::note!(
        "  RMS {:.3} -> {} nm, PV {:.3} -> {} nm{}, piston {:.3} nm",
        r.rms_before_nm,
        fig(r.rms_after_nm),
        r.pv_before_nm,
        fig(r.pv_after_nm),
        match &r.model {
            Some(m) => format!(
                " as the program executes (model {:.3} nm RMS, {:.3} nm PV)",
                m.rms_nm, m.pv_nm
            ),
            None => String::new(),
        },
        r.piston_nm
    );
    if let Some(i) = &integration {
        crate::note!("  the executed {}", resolution_phrase(i));
    }
    if let (Some(e), Some([lo, hi])) = (&r.expected, r.expected_rms_range_nm) {
        let u = &e.uncertainty;
        crate::note!(
            "  expected reading after the run: {:.3} nm RMS (90%: {:.3} .. {:.3} nm), PV {:.3} nm, with the tool known to {:.1}% in rate, {:.1}% in width, {:.3}/{:.3} mm in place and {:.3} nm of metrology noise",
            e.expected_rms_nm,
            lo,
            hi,
            e.expected_pv_nm,
            100.0 * u.rate_sigma,
            100.0 * u.width_sigma,
            u.offset_x_sigma_mm,
            u.offset_y_sigma_mm,
            u.noise_rms_nm
        );
        let p = &e.parts;
        crate::note!(
            "  of which: {} nm the plan leaves with the nominal tool, {:.3} nm the tool's uncertainty, {:.3} nm the metrology's noise, {:.3} nm the map's noise the plan imprints (in quadrature)",
            fig(p.residual_nm),
            p.tool_nm,
            p.noise_nm,
            p.noise_imprint_nm
        );
        if let (Some(scope), Some(whole_rms_nm), Some(whole_dwell_s)) =
            (r.plan_scope, r.map_plan_expected_rms_nm, r.map_plan_dwell_s)
        {
            let instead = format!(
                "the job's plan of the whole map was expected to read {whole_rms_nm:.3} nm with {whole_dwell_s:.0} s of dwell, this one {:.3} nm with {:.0} s",
                e.expected_rms_nm, r.total_dwell_s
            );
            match scope {
                PlanScope::Band {
                    min_gain,
                    cutoff_per_mm,
                    left_out_rms_nm,
                    ..
                } => crate::note!(
                    "  planned for the correctable band only (up to {:.3} /mm, where the tool's transfer is {:.0}% of its rate; {:.3} nm RMS left out): {instead}",
                    cutoff_per_mm,
                    100.0 * min_gain,
                    left_out_rms_nm,
                ),
                PlanScope::Map => crate::note!(
                    "  planned with the time weight rho = {:.4} nm^2/s (the job's {:.4}), which stops chasing what the run cannot pay for: {instead}",
                    r.plan_rho_nm2_per_s.unwrap_or(f64::NAN),
                    solved.prepared.setup.rho,
                ),
            }
        }
        if r.run_pays == Some(false) {
            crate::errln!(
                "  warning: no run is expected to improve the part by more than its risk: {:.3} nm expected (up to {:.3} nm) against {:.3} nm measured; the floor is set by {}; calibrate the tool or stop",
                e.expected_rms_nm,
                hi,
                e.measured_rms_nm,
                p.cause().describe()
            );
        }
    }
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
    crate::note!("{}", machining_line(r, correction_passes));
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
        "  solver {}{} ({}, status {}{}), build {:.3} s, solve {:.3} s; wrote {}",
        r.solver,
        if certificate.is_empty() {
            String::new()
        } else {
            format!(" [{}]", certificate.join(", "))
        },
        iterations_phrase(r),
        r.status,
        r.converged_by
            .map(|c| format!(" by {c}"))
            .unwrap_or_default(),
        r.build_seconds,
        r.solve_seconds,
        out.display()
    );
}

/// The machining time and the largest acceleration between the programmed feeds. Under
/// correction passes the plan's feeds step faster than the limit: the figure is the programmed
/// feeds' (a step between neighbouring stretches over the time between them), which the
/// controller's look-ahead holds to the limit by ramping; the executed figures include the
/// ramps. Said so, so that a correct plan does not read as one that breaks the limit.
fn machining_line(r: &preston_io::report::Report, correction_passes: bool) -> String {
    match r.a_max_mm_per_s2 {
        Some(a) if correction_passes && r.max_accel_mm_per_s2 > a => format!(
            "  machining time {:.2} s; the programmed feeds step at up to {:.3} mm/s^2 between \
             neighbouring stretches, which the controller's look-ahead holds to the {a} mm/s^2 \
             limit by ramping (the plan was corrected for the executed motion: its figures below \
             include the ramps)",
            r.machining_time_s, r.max_accel_mm_per_s2
        ),
        _ => format!(
            "  machining time {:.2} s, max acceleration {:.3} mm/s^2",
            r.machining_time_s, r.max_accel_mm_per_s2
        ),
    }
}

/// Which solve the reported iterations are of: the plan's own solve, or (under correction
/// passes against the executed program) the last kept pass's warm-started re-solve, so that a
/// handful of iterations after a progress bar that counted thousands is not a contradiction.
fn iterations_phrase(r: &preston_io::report::Report) -> String {
    match r.executed.as_ref().map_or(0, |e| e.correction_passes) {
        0 => format!("{} iterations", r.iterations),
        passes => format!(
            "{} iterations in correction pass {passes}, the last kept, warm-started from the plan \
             before it; the first solve's iterations are not these",
            r.iterations
        ),
    }
}

/// Prints what the machine would do with the program of the plan (the pipeline's check on the
/// job's machine profile); a plan no program can deliver is a warning here (`preston nc`
/// refuses it).
fn print_check(solved: &pipeline::Solved) -> Option<&ProgramCheck> {
    match &solved.program_check {
        Ok(c) => {
            print_program_check(c);
            Some(c)
        }
        Err(e) => {
            crate::errln!("  warning: no G-code program can deliver this plan as it is: {e}");
            None
        }
    }
}
