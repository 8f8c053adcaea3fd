//! `preston bench`: generated problems and the sample job, solved and timed.

use preston_io::bench::{self, BenchRow};
use preston_solver::dwell::{OperatorChoice, Settings, SolverChoice};
use std::path::PathBuf;

/// Solvers to compare.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum BenchSolvers {
    /// Both solvers (the QP only up to --qp-max-n dwell points).
    Both,
    /// Only the QP.
    Qp,
    /// Only the first-order solver.
    FirstOrder,
    /// Only the first-order solver on the matrix-free FFT operator (nnz shown as 0).
    FirstOrderFft,
    /// The default: `solver = "auto"`, `operator = "auto"` (the cost-model policy).
    Auto,
}

/// Arguments of `preston bench`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Approximate dwell-point counts of the generated problems (comma separated).
    #[arg(long, value_delimiter = ',', default_values_t = [2_000usize, 20_000, 200_000])]
    pub sizes: Vec<usize>,
    /// Add the 1e6-dwell-point problem.
    #[arg(long)]
    pub large: bool,
    /// Which solvers to run.
    #[arg(long, value_enum, default_value = "both")]
    pub solvers: BenchSolvers,
    /// Largest problem (dwell points) given to the QP.
    #[arg(long, default_value_t = 20_000)]
    pub qp_max_n: usize,
    /// Relative tolerance of the first-order solver (KKT residual or gap bound).
    #[arg(long)]
    pub first_order_tolerance: Option<f64>,
    /// Iteration of the first-order solver on the generated problems (default lbfgs).
    #[arg(long, value_enum)]
    pub first_order_method: Option<preston_solver::dwell::FirstOrderMethod>,
    /// Correction pairs of the projected L-BFGS (default 10, or 5 with the FFT operator).
    #[arg(long, value_name = "PAIRS")]
    pub lbfgs_memory: Option<usize>,
    /// How the generated problems model the tool at a dwell point (default swept, as `solve`):
    /// `point` to compare with the literature's model.
    #[arg(long, value_enum)]
    pub influence: Option<preston_solver::influence::InfluenceModel>,
    /// Sample job to include (default data/job.toml when it exists; "none" to skip).
    #[arg(long, value_name = "JOB.toml")]
    pub job: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Runs `preston bench`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let mut sizes = args.sizes.clone();
    if args.large {
        sizes.push(1_000_000);
    }
    let mut settings = Settings::default();
    if let Some(t) = args.first_order_tolerance {
        settings.first_order_tolerance = t;
    }
    if let Some(m) = args.first_order_method {
        settings.first_order_method = m;
    }
    if let Some(pairs) = args.lbfgs_memory {
        settings.lbfgs_memory = Some(pairs);
    }
    if let Some(model) = args.influence {
        settings.influence = model;
    }
    // The named solvers run on the assembled R (FFT: first-order-fft); `auto` leaves the
    // operator to the policy as `preston solve` does.
    settings.operator = if args.solvers == BenchSolvers::Auto {
        OperatorChoice::Auto
    } else {
        OperatorChoice::Sparse
    };
    settings.validate()?;
    let solvers: Vec<SolverChoice> = match args.solvers {
        BenchSolvers::Both => vec![SolverChoice::Qp, SolverChoice::FirstOrder],
        BenchSolvers::Qp => vec![SolverChoice::Qp],
        BenchSolvers::FirstOrder | BenchSolvers::FirstOrderFft => vec![SolverChoice::FirstOrder],
        BenchSolvers::Auto => vec![SolverChoice::Auto],
    };
    let fft = args.solvers == BenchSolvers::FirstOrderFft;
    let mut rows: Vec<BenchRow> = Vec::new();
    let job = match &args.job {
        Some(p) if p.as_os_str() == "none" => None,
        Some(p) => Some(p.clone()),
        None => Some(PathBuf::from("data/job.toml")).filter(|p| p.exists()),
    };
    if let Some(job) = job {
        for &s in &solvers {
            let row = bench::run_job(&job, s)?;
            crate::err!("{}", bench::format_table(std::slice::from_ref(&row)));
            rows.push(row);
        }
    }
    for &n in &sizes {
        for &s in &solvers {
            if s == SolverChoice::Qp && n > args.qp_max_n {
                continue;
            }
            let row = if fft {
                bench::run_generated_fft(n, &settings)?
            } else {
                bench::run_generated(n, s, &settings)?
            };
            crate::err!("{}", bench::format_table(std::slice::from_ref(&row)));
            rows.push(row);
        }
    }
    if args.json {
        crate::outln!("{}", serde_json::to_string_pretty(&rows)?);
    } else {
        crate::out!("{}", bench::format_table(&rows));
    }
    let unconverged = rows.iter().filter(|r| !r.status.is_converged()).count();
    if unconverged > 0 {
        crate::errln!(
            "  warning: {unconverged} of {} solves did not converge",
            rows.len()
        );
        return Ok(super::EXIT_NOT_CONVERGED);
    }
    Ok(crate::EXIT_OK)
}
