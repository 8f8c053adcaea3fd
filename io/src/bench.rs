//! `preston bench`: a suite of generated dwell problems (and the sample job) solved end to end,
//! with sizes, accuracy, timings and peak memory.
//!
//! Generated problems: a square map at 0.5 mm pitch holding a smooth random error (a sum of
//! eight cosine modes, wavelengths 8 mm to the map size, amplitudes 20 to 60 nm), a Gaussian TIF
//! (sigma 2 mm, peak 10 nm/s, truncated at 3 sigma), a serpentine raster at 1 mm pitch over the map
//! extended by the TIF radius, `v_max` 2000 mm/min, `rho = lambda = 0`. The map side is chosen so
//! the raster has about the requested number of dwell points.

use crate::error::Result;
use crate::job::Job;
use crate::pipeline;
use preston_solver::dwell::precond::DwellLattice;
use preston_solver::dwell::{policy, SolverKind};
use preston_solver::dwell::{
    DwellBounds, FeedLimits, OperatorChoice, OperatorKind, Problem, Settings, SolverChoice,
};
use preston_solver::edge::{EdgeMethod, EdgeSettings};
use preston_solver::influence::model::surface::TifFrame;
use preston_solver::influence::operator::fft::FftOperator;
use preston_solver::influence::InfluenceMatrix;
use preston_solver::map::{BoundingBox, HeightMap, HeightStats};
use preston_solver::observer::Silent;
use preston_solver::path::raster::{serpentine, RasterAxis};
use preston_solver::setup::{Choices, DwellPoints, Setup, SetupData, SetupError, TifModel};
use preston_solver::tif::{GaussianTif, Tif};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// Map pitch of the generated problems, mm.
pub const MAP_PITCH_MM: f64 = 0.5;
/// Dwell pitch of the generated problems, mm.
pub const DWELL_PITCH_MM: f64 = 1.0;
/// Gaussian TIF sigma, mm.
pub const TIF_SIGMA_MM: f64 = 2.0;
/// Gaussian TIF peak removal rate, nm/s.
pub const TIF_PEAK_NM_PER_S: f64 = 10.0;
/// Fastest feed, mm/min.
pub const V_MAX_MM_PER_MIN: f64 = 2000.0;

/// One row of the benchmark table.
#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    /// Problem name (`random-2e4`, `sample-job`).
    pub problem: String,
    /// Solver that ran (`qp`, `first-order`).
    pub solver: String,
    /// Map points.
    pub m: usize,
    /// Dwell points.
    pub n: usize,
    /// Non-zeros of `R`.
    pub nnz: usize,
    /// RMS of the map before, nm.
    pub rms_before_nm: f64,
    /// RMS of the residual after, nm.
    pub rms_after_nm: f64,
    /// Contract objective `0.5 ||R t - z - c||^2`, nm^2.
    pub objective: f64,
    /// Total dwell, s.
    pub total_dwell_s: f64,
    /// Problem generation and assembly, s.
    pub build_seconds: f64,
    /// Solve, s.
    pub solve_seconds: f64,
    /// Solver iterations.
    pub iterations: usize,
    /// How the solve ended (serialised as in `report.json`).
    pub status: crate::report::ReportStatus,
    /// Peak resident memory of the process so far (VmHWM), MiB; `None` where unavailable.
    pub peak_memory_mib: Option<f64>,
}

/// Peak resident set size of this process, MiB, from `VmHWM` in `/proc/self/status` (Linux).
pub fn peak_memory_mib() -> Option<f64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The inputs of a generated problem: map points and heights, dwell path, TIF and bounds.
pub struct GeneratedInputs {
    /// Map x, mm.
    pub x_mm: Vec<f64>,
    /// Map y, mm.
    pub y_mm: Vec<f64>,
    /// Height error, nm.
    pub z_nm: Vec<f64>,
    /// Dwell path.
    pub path: preston_solver::path::DwellPath,
    /// The Gaussian TIF.
    pub tif: GaussianTif,
    /// Dwell bounds from `v_max`.
    pub bounds: DwellBounds,
}

/// A generated problem with about `n_target` dwell points (see the module documentation).
pub fn generated_problem(n_target: usize, seed: u64) -> Result<Problem> {
    generated_problem_with(n_target, seed, OperatorChoice::Sparse)
}

/// As [`generated_problem`], matrix-free for `OperatorChoice::Fft` (assembled otherwise).
pub fn generated_problem_with(
    n_target: usize,
    seed: u64,
    operator: OperatorChoice,
) -> Result<Problem> {
    let g = generated_inputs(n_target, seed)?;
    if operator == OperatorChoice::Fft {
        let op = FftOperator::new(
            &g.x_mm,
            &g.y_mm,
            g.path.x_mm(),
            g.path.y_mm(),
            MAP_PITCH_MM,
            &g.tif,
        )?;
        let lattice = DwellLattice::detect(g.path.x_mm(), g.path.y_mm());
        return Ok(Problem::new(op, g.z_nm, g.bounds, 0.0, 0.0)?.with_dwell_lattice(lattice)?);
    }
    let r = InfluenceMatrix::assemble(
        &g.x_mm,
        &g.y_mm,
        g.path.x_mm(),
        g.path.y_mm(),
        &g.tif,
        &Silent,
    )?;
    let lattice = DwellLattice::detect(g.path.x_mm(), g.path.y_mm());
    Ok(Problem::new(r, g.z_nm, g.bounds, 0.0, 0.0)?.with_dwell_lattice(lattice)?)
}

/// The generated inputs with about `n_target` dwell points (see the module documentation).
pub fn generated_inputs(n_target: usize, seed: u64) -> Result<GeneratedInputs> {
    let tif = GaussianTif::new(TIF_SIGMA_MM, TIF_PEAK_NM_PER_S, 3.0 * TIF_SIGMA_MM)?;
    let radius = 3.0 * TIF_SIGMA_MM;
    let dwell_side = (n_target as f64).sqrt() * DWELL_PITCH_MM;
    let map_side = (dwell_side - 2.0 * radius).max(4.0 * MAP_PITCH_MM);
    let k = (map_side / MAP_PITCH_MM).round() as usize + 1;
    let mut state = seed;
    let mut next = move || {
        // splitmix64 in [0, 1).
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let modes: Vec<(f64, f64, f64, f64)> = (0..8)
        .map(|_| {
            let wavelength = 8.0 + (map_side - 8.0).max(0.0) * next();
            let angle = std::f64::consts::TAU * next();
            let kk = std::f64::consts::TAU / wavelength;
            (
                kk * angle.cos(),
                kk * angle.sin(),
                next() * 6.0,
                20.0 + 40.0 * next(),
            )
        })
        .collect();
    let mut x = Vec::with_capacity(k * k);
    let mut y = Vec::with_capacity(k * k);
    let mut z = Vec::with_capacity(k * k);
    for iy in 0..k {
        for ix in 0..k {
            let (px, py) = (ix as f64 * MAP_PITCH_MM, iy as f64 * MAP_PITCH_MM);
            x.push(px);
            y.push(py);
            z.push(
                modes
                    .iter()
                    .map(|(kx, ky, ph, a)| a * (kx * px + ky * py + ph).cos())
                    .sum(),
            );
        }
    }
    let bbox = BoundingBox::of_points(&x, &y)
        .ok_or_else(|| preston_solver::Error::invalid("bench map", "has no points"))?
        .expanded(radius);
    let path = serpentine(&bbox, DWELL_PITCH_MM, RasterAxis::X)?;
    let limits = FeedLimits {
        v_max_mm_per_min: V_MAX_MM_PER_MIN,
        v_min_mm_per_min: 0.0,
    };
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits)?;
    Ok(GeneratedInputs {
        x_mm: x,
        y_mm: y,
        z_nm: z,
        path,
        tif,
        bounds,
    })
}

/// Builds the generated problem with the matrix-free FFT operator (no `R` is formed) and solves
/// it with the first-order solver (the solver column reads `first-order-fft`; nnz is the count
/// of `R`'s implicit non-zeros).
pub fn run_generated_fft(n_target: usize, settings: &Settings) -> Result<BenchRow> {
    let s = Settings {
        operator: OperatorChoice::Fft,
        ..settings.clone()
    };
    run_generated(n_target, SolverChoice::FirstOrder, &s)
}

/// Builds the generated problem with about `n_target` dwell points (matrix-free when
/// `settings.operator` is `fft`, assembled otherwise) and solves it with `solver`.
pub fn run_generated(
    n_target: usize,
    solver: SolverChoice,
    settings: &Settings,
) -> Result<BenchRow> {
    let start = Instant::now();
    let g = generated_inputs(n_target, 1)?;
    // The generated problem through the set-up stage: no edge model, the operator `auto` gives
    // this problem's size (or the one asked for).
    let choices = Choices {
        feed: Some(FeedLimits {
            v_max_mm_per_min: V_MAX_MM_PER_MIN,
            v_min_mm_per_min: 0.0,
        }),
        a_max_mm_per_s2: None,
        corner_angle_deg: None,
        accel_method: Default::default(),
        rho: 0.0,
        lambda: 0.0,
        settings: Settings {
            solver,
            operator: match settings.operator {
                OperatorChoice::Auto => auto_operator(n_target, solver, settings.min_time),
                o => o,
            },
            ..settings.clone()
        },
        edge: EdgeSettings {
            method: EdgeMethod::None,
            ..EdgeSettings::default()
        },
        tif_model: TifModel::ShiftInvariant,
        tif_frame: TifFrame::default(),
        warm_start: false,
    };
    let setup_error = |e: SetupError| crate::Error::Solver(e.source);
    let checked = choices.check(&Silent).map_err(setup_error)?;
    let data = SetupData {
        map: HeightMap::new(g.x_mm, g.y_mm, g.z_nm)?,
        tif: Tif::Gaussian(g.tif),
        dwell: DwellPoints::Given(g.path),
        surface: None,
        warm_start_s: None,
    };
    let setup = Setup::resolve(checked, data, &Silent).map_err(setup_error)?;
    let problem = setup.problem(&Silent).map_err(setup_error)?.problem;
    let build_seconds = start.elapsed().as_secs_f64();
    let outcome = setup.solve(&problem, &Silent)?;
    let sol = &outcome.solution;
    let residual: Vec<f64> = outcome
        .removal_nm
        .iter()
        .zip(problem.z_nm())
        .map(|(h, z)| z - h)
        .collect();
    let mut solver_name = crate::report::solver_name(sol.solver);
    if problem.operator_kind() == OperatorKind::Fft {
        solver_name.push_str("-fft");
    }
    Ok(BenchRow {
        problem: format!("random-{}", size_label(n_target)),
        solver: solver_name,
        m: problem.m(),
        n: problem.n(),
        nnz: problem.nnz(),
        rms_before_nm: problem.stats_before().rms_nm,
        rms_after_nm: HeightStats::of(&residual).rms_nm,
        objective: sol.objective,
        total_dwell_s: sol.dwell_s.iter().sum(),
        build_seconds,
        solve_seconds: sol.solve_seconds,
        iterations: sol.iterations,
        status: crate::report::ReportStatus::Solved(sol.status),
        peak_memory_mib: peak_memory_mib(),
    })
}

/// The operator `operator = "auto"` gives the generated problem with about `n_target` dwell
/// points under `solver` ([`policy::choose`], as the pipeline decides it for a job).
pub fn auto_operator(n_target: usize, solver: SolverChoice, min_time: bool) -> OperatorChoice {
    let radius = 3.0 * TIF_SIGMA_MM;
    let dwell_side = (n_target as f64).sqrt() * DWELL_PITCH_MM;
    let map_side = (dwell_side - 2.0 * radius).max(4.0 * MAP_PITCH_MM);
    let map_points = (map_side / MAP_PITCH_MM + 1.0).powi(2);
    let per_column =
        (std::f64::consts::PI * radius * radius / (MAP_PITCH_MM * MAP_PITCH_MM)).min(map_points);
    let cells = ((dwell_side + 2.0 * radius) / MAP_PITCH_MM + 1.0).powi(2);
    let choice = policy::choose(&policy::PolicyInputs {
        nnz: per_column * n_target as f64,
        fft_cells: Some(cells),
        needs_qp: min_time,
        solver: match solver {
            SolverChoice::Qp => Some(SolverKind::Qp),
            SolverChoice::FirstOrder => Some(SolverKind::FirstOrder),
            SolverChoice::Auto => None,
        },
    });
    match choice.operator {
        policy::OperatorKind::Fft => OperatorChoice::Fft,
        policy::OperatorKind::Sparse => OperatorChoice::Sparse,
    }
}

/// Runs a job file (the sample job) through the whole pipeline with `solver`.
pub fn run_job(job_path: &Path, solver: SolverChoice) -> Result<BenchRow> {
    let mut job = Job::load(job_path)?;
    job.solver.solver = solver;
    let prepared = pipeline::prepare(&job, job_path, &Silent)?;
    let solved = pipeline::solve(prepared, &job, &Silent)?;
    let r = &solved.report;
    Ok(BenchRow {
        problem: "sample-job".into(),
        solver: r.solver.to_string(),
        m: r.m,
        n: r.n,
        nnz: r.nnz,
        rms_before_nm: r.rms_before_nm,
        rms_after_nm: r.rms_after_nm,
        objective: r.objective,
        total_dwell_s: r.total_dwell_s,
        build_seconds: r.build_seconds,
        solve_seconds: r.solve_seconds,
        iterations: r.iterations,
        status: r.status,
        peak_memory_mib: peak_memory_mib(),
    })
}

/// `2000 -> "2e3"`, `20000 -> "2e4"`.
pub fn size_label(n: usize) -> String {
    let e = (n.max(1) as f64).log10().floor() as i32;
    let mant = n as f64 / 10f64.powi(e);
    format!("{}e{e}", (mant * 10.0).round() / 10.0)
}

/// The table as text, one row per line, with a header.
pub fn format_table(rows: &[BenchRow]) -> String {
    let mut s = format!(
        "{:<12} {:<12} {:>8} {:>8} {:>10} {:>9} {:>9} {:>14} {:>11} {:>8} {:>8} {:>6} {:<15} {:>9}\n",
        "problem", "solver", "m", "n", "nnz", "rms0_nm", "rms1_nm", "objective", "dwell_s",
        "build_s", "solve_s", "iters", "status", "peak_MiB"
    );
    for r in rows {
        s.push_str(&format!(
            "{:<12} {:<12} {:>8} {:>8} {:>10} {:>9.3} {:>9.3} {:>14.6e} {:>11.1} {:>8.3} {:>8.3} {:>6} {:<15} {:>9}\n",
            r.problem,
            r.solver,
            r.m,
            r.n,
            r.nnz,
            r.rms_before_nm,
            r.rms_after_nm,
            r.objective,
            r.total_dwell_s,
            r.build_seconds,
            r.solve_seconds,
            r.iterations,
            r.status,
            r.peak_memory_mib
                .map_or_else(|| "-".to_string(), |v| format!("{v:.0}"))
        ));
    }
    s
}
