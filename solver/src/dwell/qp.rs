//! The contract as a sparse conic QP for Clarabel (Goulart & Chen, "Clarabel: An interior-point
//! solver for conic programs with quadratic objectives", 2024).
//!
//! Variables `x = [t (n); c (1); r (m)]`. The residual `r = R t - z - c 1` enters as equality rows,
//! so `R` appears once in `A` and `R^T R` is never formed:
//!
//! ```text
//! minimise   0.5 ||r||^2 + rho 1't + 0.5 lambda ||D t||^2
//! subject to R t - c 1 - r = z            (zero cone, m rows)
//!            -t <= -lb,  t <= ub          (non-negative cone)
//! ```
//!
//! The minimum-time mode solves that with `rho = 0` for `f*`, then minimises `1't` subject to
//! `||(r, sqrt(lambda) D t)|| <= sqrt(2 (1 + tol) f*)` (a second-order cone).

use super::certificate::ConvergenceCriterion;
use super::{
    DwellBounds, Evaluation, MinTimeReport, Problem, Settings, Solution, SolverKind, Status,
};
use crate::error::{Error, Result};
use crate::observer::{IterationInfo, Observer, Stage};
use clarabel::algebra::CscMatrix as ClCsc;
use clarabel::solver::{DefaultSettings, DefaultSolver, IPSolver, SolverStatus, SupportedConeT};
use std::time::Instant;

/// What the QP optimises.
#[derive(Debug, Clone, Copy)]
enum Goal {
    /// The contract objective with the problem's rho and lambda.
    Contract,
    /// Minimum total dwell with the quadratic part capped at `cap` (nm^2).
    MinTime { cap: f64 },
}

/// Solves the problem with Clarabel (two solves in minimum-time mode).
pub fn solve(problem: &Problem, settings: &Settings, observer: &dyn Observer) -> Result<Solution> {
    let start = Instant::now();
    observer.start(Stage::Solve, 0);
    let result = if settings.min_time {
        solve_min_time(problem, settings, observer)
    } else {
        run(problem, settings, Goal::Contract, observer).map(|(s, t, it, _)| (s, t, it, None))
    };
    observer.finish(Stage::Solve);
    let (status, dwell_s, iterations, min_time) = result?;
    finish(problem, status, dwell_s, iterations, start, min_time)
}

fn solve_min_time(
    problem: &Problem,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<(Status, Vec<f64>, usize, Option<MinTimeReport>)> {
    let rho0 = problem.with_weights(0.0, problem.lambda())?;
    let (status1, t1, it1, _) = run(&rho0, settings, Goal::Contract, observer)?;
    let eval1 = rho0.evaluate(&t1)?;
    let f1 = quadratic_part(&rho0, &t1, &eval1);
    if !status1.is_converged() {
        return Ok((status1, t1, it1, None));
    }
    // A floor keeps the cone non-degenerate when the map can be matched exactly.
    let scale = 0.5 * problem.z_nm().iter().map(|z| z * z).sum::<f64>();
    let cap = (1.0 + settings.min_time_tolerance) * f1 + 1e-14 * scale.max(1.0);
    let (status2, t2, it2, _) = run(problem, settings, Goal::MinTime { cap }, observer)?;
    let report = MinTimeReport {
        objective_rho0: eval1.objective,
        total_dwell_rho0_s: eval1.total_dwell_s,
        tolerance: settings.min_time_tolerance,
    };
    Ok((status2, t2, it1 + it2, Some(report)))
}

/// `0.5 ||r||^2 + 0.5 lambda ||D t||^2` at the optimal piston.
fn quadratic_part(problem: &Problem, t: &[f64], eval: &Evaluation) -> f64 {
    let smooth: f64 = t.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
    eval.objective + 0.5 * problem.lambda() * smooth
}

/// Projects onto the bounds, puts unreachable dwell points on their lower bound and evaluates.
pub(crate) fn finish(
    problem: &Problem,
    status: Status,
    mut dwell_s: Vec<f64>,
    iterations: usize,
    start: Instant,
    min_time: Option<MinTimeReport>,
) -> Result<Solution> {
    problem.bounds().project(&mut dwell_s);
    let eval = problem.evaluate(&dwell_s)?;
    Ok(Solution {
        status,
        solver: SolverKind::Qp,
        piston_nm: eval.piston_nm,
        objective: eval.objective,
        dwell_s,
        iterations,
        solve_seconds: start.elapsed().as_secs_f64(),
        kkt_residual: None,
        objective_gap_bound: None,
        gap_bound_reason: None,
        converged_by: status
            .is_converged()
            .then_some(ConvergenceCriterion::InteriorPoint),
        min_time,
    })
}

fn status_of(s: SolverStatus) -> Status {
    match s {
        SolverStatus::Solved => Status::Converged,
        SolverStatus::AlmostSolved => Status::AlmostConverged,
        SolverStatus::MaxIterations => Status::MaxIterations,
        SolverStatus::MaxTime => Status::TimeLimit,
        SolverStatus::PrimalInfeasible
        | SolverStatus::AlmostPrimalInfeasible
        | SolverStatus::DualInfeasible
        | SolverStatus::AlmostDualInfeasible => Status::Infeasible,
        _ => Status::NumericalError,
    }
}

/// Builds and solves one QP; returns the status, `t`, iterations.
fn run(
    problem: &Problem,
    settings: &Settings,
    goal: Goal,
    observer: &dyn Observer,
) -> Result<(Status, Vec<f64>, usize, f64)> {
    run_with(problem, problem.bounds(), None, settings, goal, observer)
}

/// Extra linear inequality rows `G t <= h` on the dwell times, stored by dwell column
/// (used by the acceleration-limited sequential convex programme, [`super::accel`]).
#[derive(Debug, Clone, Default)]
pub(crate) struct ExtraRows {
    /// `by_column[j]` lists `(row, G[row, j])`.
    pub by_column: Vec<Vec<(usize, f64)>>,
    /// Right-hand sides `h`, one per row.
    pub rhs: Vec<f64>,
}

/// Solves the contract QP with `bounds` in place of the problem's and extra rows `G t <= h`;
/// returns the status, `t` and the interior-point iterations.
pub(crate) fn solve_with_rows(
    problem: &Problem,
    bounds: &DwellBounds,
    extra: &ExtraRows,
    settings: &Settings,
    observer: &dyn Observer,
) -> Result<(Status, Vec<f64>, usize)> {
    let (status, t, it, _) = run_with(
        problem,
        bounds,
        Some(extra),
        settings,
        Goal::Contract,
        observer,
    )?;
    Ok((status, t, it))
}

/// Units of the QP's variables: the dwell times in `t_s` seconds and the heights (residual,
/// piston, map) in `h_nm` nanometres. The problem is first solved in its own units
/// ([`Scale::NONE`]); one that Clarabel then calls infeasible is solved again in units where
/// the map, the removal at the lower bounds and the dwell that removes the map's largest height
/// are all of order one ([`Scale::of`]): far-apart magnitudes (a single spike a million times
/// the rest, a feed limit that puts every dwell at a million seconds) otherwise leave the
/// interior-point method's equilibration short of a feasible point that exists.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Scale {
    t_s: f64,
    h_nm: f64,
}

impl Scale {
    /// The problem's own units.
    const NONE: Scale = Scale {
        t_s: 1.0,
        h_nm: 1.0,
    };

    /// Units of order one for `problem` under `bounds` (see the type's documentation).
    fn of(problem: &Problem, bounds: &DwellBounds) -> Result<Self> {
        let finite_max = |v: &mut dyn Iterator<Item = f64>| {
            v.filter(|x| x.is_finite())
                .fold(0.0f64, |a, b| a.max(b.abs()))
        };
        let z_max = finite_max(&mut problem.z_nm().iter().copied());
        let rate_max = finite_max(
            &mut problem
                .require_matrix("the QP solver")?
                .csc()
                .values()
                .iter()
                .copied(),
        );
        let lower_max = finite_max(&mut bounds.lower_s().iter().copied());
        let positive = |v: f64| if v.is_finite() && v > 0.0 { v } else { 1.0 };
        let t_s = positive(if rate_max > 0.0 {
            lower_max.max(z_max / rate_max)
        } else {
            lower_max
        });
        let h_nm = positive(z_max.max(rate_max * t_s));
        Ok(Scale { t_s, h_nm })
    }
}

fn run_with(
    problem: &Problem,
    bounds: &DwellBounds,
    extra: Option<&ExtraRows>,
    settings: &Settings,
    goal: Goal,
    observer: &dyn Observer,
) -> Result<(Status, Vec<f64>, usize, f64)> {
    let first = run_scaled(
        problem,
        bounds,
        extra,
        settings,
        goal,
        observer,
        Scale::NONE,
    )?;
    if first.0 != Status::Infeasible {
        return Ok(first);
    }
    let scale = Scale::of(problem, bounds)?;
    if scale == Scale::NONE {
        return Ok(first);
    }
    let second = run_scaled(problem, bounds, extra, settings, goal, observer, scale)?;
    Ok((second.0, second.1, first.2 + second.2, second.3))
}

/// One Clarabel solve of the QP in the units `scale`; returns the status, `t` (s), the
/// iterations and the objective (in the problem's units).
#[allow(clippy::too_many_arguments)]
fn run_scaled(
    problem: &Problem,
    bounds: &DwellBounds,
    extra: Option<&ExtraRows>,
    settings: &Settings,
    goal: Goal,
    observer: &dyn Observer,
    scale: Scale,
) -> Result<(Status, Vec<f64>, usize, f64)> {
    let data = build(problem, bounds, goal, extra, scale)?;
    let cl_settings = DefaultSettings::<f64> {
        verbose: settings.verbose,
        max_iter: u32::try_from(settings.max_iterations).unwrap_or(u32::MAX),
        time_limit: settings.time_limit_s,
        tol_gap_abs: settings.tolerance,
        tol_gap_rel: settings.tolerance,
        tol_feas: settings.tolerance.max(1e-10),
        // faer's supernodal LDL^T: the Schur complement on t is close to dense (R^T R couples
        // every dwell point with all others within a TIF diameter), where supernodes pay off.
        direct_solve_method: "faer".to_string(),
        max_threads: 1,
        ..DefaultSettings::default()
    };
    let mut solver =
        DefaultSolver::new(&data.p, &data.q, &data.a, &data.b, &data.cones, cl_settings).map_err(
            |e| Error::Numerical {
                stage: "QP set-up",
                why: e.to_string(),
            },
        )?;
    solver.solve();
    crate::observer::check_cancelled(observer)?;
    let sol = &solver.solution;
    let n = problem.n();
    let t: Vec<f64> = sol.x.iter().take(n).map(|v| v * scale.t_s).collect();
    if t.len() != n {
        return Err(Error::Numerical {
            stage: "QP solve",
            why: "solution vector has the wrong length".into(),
        });
    }
    observer.iteration(&IterationInfo {
        iteration: sol.iterations as usize,
        objective: sol.obj_val,
        kkt_residual: None,
    });
    let objective_scale = match goal {
        Goal::Contract => scale.h_nm * scale.h_nm,
        Goal::MinTime { .. } => scale.t_s,
    };
    Ok((
        status_of(sol.status),
        t,
        sol.iterations as usize,
        sol.obj_val * objective_scale,
    ))
}

struct QpData {
    p: ClCsc<f64>,
    q: Vec<f64>,
    a: ClCsc<f64>,
    b: Vec<f64>,
    cones: Vec<SupportedConeT<f64>>,
}

/// Assembles `P` (upper triangle), `q`, `A`, `b` and the cones, column by column, in the
/// units `scale`: `t = t_s tau`, `(c, r, z) = h_nm (gamma, rho, zeta)`, the objective over
/// `h_nm^2` (the contract) or `t_s` (minimum time). [`Scale::NONE`] gives the problem as
/// stated, every coefficient exactly as in its own units.
fn build(
    problem: &Problem,
    bounds: &DwellBounds,
    goal: Goal,
    extra: Option<&ExtraRows>,
    scale: Scale,
) -> Result<QpData> {
    let Scale { t_s, h_nm } = scale;
    let (m, n) = (problem.m(), problem.n());
    let nv = n + 1 + m;
    // The smoothing weight on `tau`: `lambda t_s^2 / h_nm^2`.
    let lambda = problem.lambda() * (t_s / h_nm) * (t_s / h_nm);
    if bounds.len() != n {
        return Err(Error::LengthMismatch {
            what: "dwell bounds",
            got: bounds.len(),
            expected: n,
        });
    }
    let upper = bounds.upper_s();
    let nu = if upper.is_some() { n } else { 0 };
    // Extra rows sit in the non-negative cone right after the bound rows.
    let ne = extra.map_or(0, |e| e.rhs.len());
    let extra_start = m + n + nu;
    let csc = problem.require_matrix("the QP solver")?.csc();
    let (r_off, r_rows, r_vals) = csc.csc_data();

    // ---- P and q
    let mut p_colptr = Vec::with_capacity(nv + 1);
    let mut p_rows = Vec::new();
    let mut p_vals = Vec::new();
    p_colptr.push(0);
    let quad_in_objective = matches!(goal, Goal::Contract);
    for j in 0..n {
        if quad_in_objective && lambda > 0.0 && n > 1 {
            if j > 0 {
                p_rows.push(j - 1);
                p_vals.push(-lambda);
            }
            let degree = if j == 0 || j == n - 1 { 1.0 } else { 2.0 };
            p_rows.push(j);
            p_vals.push(lambda * degree);
        }
        p_colptr.push(p_rows.len());
    }
    p_colptr.push(p_rows.len()); // c
    for i in 0..m {
        if quad_in_objective {
            p_rows.push(n + 1 + i);
            p_vals.push(1.0);
        }
        p_colptr.push(p_rows.len());
    }
    let mut q = vec![0.0; nv];
    let t_weight = match goal {
        Goal::Contract => problem.rho() * t_s / (h_nm * h_nm),
        Goal::MinTime { .. } => 1.0,
    };
    for qj in q.iter_mut().take(n) {
        *qj = t_weight;
    }

    // ---- A, b and cones
    let soc_start = m + n + nu + ne;
    let soc_d_rows = if lambda > 0.0 && n > 1 { n - 1 } else { 0 };
    let (soc_len, cap) = match goal {
        Goal::Contract => (0, 0.0),
        Goal::MinTime { cap } => (1 + m + soc_d_rows, cap),
    };
    let n_rows = soc_start + soc_len;
    let sqrt_l = lambda.sqrt();
    let mut a_colptr = Vec::with_capacity(nv + 1);
    let mut a_rows = Vec::with_capacity(csc.nnz() + 3 * n + 2 * m + m);
    let mut a_vals = Vec::with_capacity(a_rows.capacity());
    a_colptr.push(0);
    // `R t` in heights of `h_nm`: `R (t_s / h_nm)` on `tau`.
    let r_scale = t_s / h_nm;
    for j in 0..n {
        let (s, e) = (r_off[j], r_off[j + 1]);
        a_rows.extend_from_slice(&r_rows[s..e]);
        a_vals.extend(r_vals[s..e].iter().map(|v| v * r_scale));
        a_rows.push(m + j);
        a_vals.push(-1.0);
        if nu > 0 {
            a_rows.push(m + n + j);
            a_vals.push(1.0);
        }
        if let Some(col) = extra.and_then(|e| e.by_column.get(j)) {
            let mut entries: Vec<(usize, f64)> = col
                .iter()
                .filter(|(r, _)| *r < ne)
                .map(|&(r, v)| (extra_start + r, v))
                .collect();
            entries.sort_by_key(|e| e.0);
            for (r, v) in entries {
                a_rows.push(r);
                a_vals.push(v * t_s);
            }
        }
        if soc_len > 0 && soc_d_rows > 0 {
            // Row k of D t is t_{k+1} - t_k: t_j appears as t_{k+1} in row j-1 and as t_k in row j.
            if j > 0 {
                a_rows.push(soc_start + 1 + m + (j - 1));
                a_vals.push(-sqrt_l);
            }
            if j < n - 1 {
                a_rows.push(soc_start + 1 + m + j);
                a_vals.push(sqrt_l);
            }
        }
        a_colptr.push(a_rows.len());
    }
    for i in 0..m {
        a_rows.push(i);
        a_vals.push(-1.0);
    }
    a_colptr.push(a_rows.len()); // c
    for i in 0..m {
        a_rows.push(i);
        a_vals.push(-1.0);
        if soc_len > 0 {
            a_rows.push(soc_start + 1 + i);
            a_vals.push(-1.0);
        }
        a_colptr.push(a_rows.len());
    }

    let mut b = Vec::with_capacity(n_rows);
    b.extend(problem.z_nm().iter().map(|z| z / h_nm));
    b.extend(bounds.lower_s().iter().map(|l| -(l / t_s)));
    if let Some(u) = upper {
        b.extend(u.iter().map(|u| u / t_s));
    }
    if let Some(e) = extra {
        b.extend_from_slice(&e.rhs);
    }
    if soc_len > 0 {
        b.push((2.0 * cap).sqrt() / h_nm);
        b.extend(std::iter::repeat_n(0.0, soc_len - 1));
    }
    let mut cones = vec![
        SupportedConeT::ZeroConeT(m),
        SupportedConeT::NonnegativeConeT(n + nu + ne),
    ];
    if soc_len > 0 {
        cones.push(SupportedConeT::SecondOrderConeT(soc_len));
    }
    Ok(QpData {
        p: ClCsc::new(nv, nv, p_colptr, p_rows, p_vals),
        q,
        a: ClCsc::new(n_rows, nv, a_colptr, a_rows, a_vals),
        b,
        cones,
    })
}
