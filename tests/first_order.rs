//! The first-order dwell solver against the QP, its certificate, and its determinism.

use preston::solver::dwell::certificate::{ConvergenceCriterion, GapBoundReason};
use preston::solver::dwell::precond::DwellLattice;
use preston::solver::dwell::{
    self, DwellBounds, FeedLimits, FirstOrderMethod, OperatorKind, Preconditioner, Problem,
    Settings, SolverChoice, Status, DEFAULT_LBFGS_MEMORY, DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS,
    MAX_LBFGS_MEMORY,
};
use preston::solver::influence::InfluenceMatrix;
use preston::solver::observer::Silent;
use preston::solver::path::raster::{serpentine, RasterAxis};
use preston::solver::path::DwellPath;
use preston::solver::tif::{GaussianTif, GridTif, InfluenceFunction};

/// Relative agreement of the first-order and QP objectives.
const AGREE_REL_TOL: f64 = 1e-6;

/// A smooth random map on an `nx x ny` grid at 0.5 mm, a Gaussian TIF and a 1 mm raster.
fn case(nx: usize, ny: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>, DwellPath, GaussianTif) {
    let mut s = seed;
    let mut next = move || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let modes: Vec<(f64, f64, f64, f64)> = (0..6)
        .map(|_| {
            (
                next() * 0.4,
                next() * 0.4,
                next() * 6.0,
                20.0 + 40.0 * next(),
            )
        })
        .collect();
    let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
    for iy in 0..ny {
        for ix in 0..nx {
            let (px, py) = (ix as f64 * 0.5, iy as f64 * 0.5);
            x.push(px);
            y.push(py);
            z.push(
                modes
                    .iter()
                    .map(|(kx, ky, ph, a)| a * (kx * px + ky * py + ph).cos())
                    .sum::<f64>(),
            );
        }
    }
    let tif = GaussianTif::new(1.5, 8.0, 4.5).unwrap();
    let bbox = preston::solver::map::BoundingBox::of_points(&x, &y)
        .unwrap()
        .expanded(2.0);
    let path = serpentine(&bbox, 1.0, RasterAxis::X).unwrap();
    (x, y, z, path, tif)
}

fn problem(seed: u64, v_min: f64, rho: f64, lambda: f64) -> Problem {
    sized_problem(25, 15, seed, v_min, rho, lambda)
}

fn sized_problem(nx: usize, ny: usize, seed: u64, v_min: f64, rho: f64, lambda: f64) -> Problem {
    let (x, y, z, path, tif) = case(nx, ny, seed);
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let limits = FeedLimits {
        v_max_mm_per_min: 3000.0,
        v_min_mm_per_min: v_min,
    };
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits).unwrap();
    Problem::new(r, z, bounds, rho, lambda).unwrap()
}

/// As [`sized_problem`], telling the problem its dwell points' lattice.
fn lattice_problem(nx: usize, ny: usize, seed: u64, v_min: f64) -> Problem {
    let (_, _, _, path, _) = case(nx, ny, seed);
    let lattice = DwellLattice::detect(path.x_mm(), path.y_mm());
    assert!(lattice.is_some(), "the raster is a lattice");
    sized_problem(nx, ny, seed, v_min, 0.0, 0.0)
        .with_dwell_lattice(lattice)
        .unwrap()
}

fn circulant_newton_cg() -> Settings {
    Settings {
        preconditioner: Preconditioner::Circulant,
        ..first_order(FirstOrderMethod::NewtonCg)
    }
}

#[test]
fn circulant_preconditioned_newton_cg_reaches_the_qp_optimum() {
    for v_min in [0.0, 300.0] {
        let p = lattice_problem(25, 15, 5, v_min);
        let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
        let fo = dwell::solve(&p, &circulant_newton_cg(), &Silent).unwrap();
        assert!(
            fo.status.is_converged(),
            "{:?} after {}",
            fo.status,
            fo.iterations
        );
        assert!(p.bounds().max_violation_s(&fo.dwell_s) == 0.0);
        let (fq, ff) = (
            full_objective(&p, &qp.dwell_s),
            full_objective(&p, &fo.dwell_s),
        );
        let rel = (ff - fq).abs() / fq.abs().max(1e-300);
        assert!(
            rel < AGREE_REL_TOL,
            "v_min {v_min}: {ff} vs QP {fq}: rel {rel:e}"
        );
    }
}

#[test]
fn circulant_preconditioned_newton_cg_is_independent_of_the_thread_count() {
    let p = lattice_problem(150, 120, 17, 300.0);
    assert!(p.m() + p.n() > 20_000);
    let s = Settings {
        first_order_max_iterations: 20,
        ..circulant_newton_cg()
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| dwell::solve(&p, &s, &Silent).unwrap())
    };
    let one = run(1);
    let two = run(2);
    assert!(one
        .dwell_s
        .iter()
        .zip(&two.dwell_s)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    assert_eq!(one.iterations, two.iterations);
}

fn settings(choice: SolverChoice) -> Settings {
    Settings {
        solver: choice,
        tolerance: 1e-10,
        first_order_tolerance: 1e-11,
        first_order_max_iterations: 200_000,
        ..Settings::default()
    }
}

fn full_objective(p: &Problem, t: &[f64]) -> f64 {
    p.evaluate(t).unwrap().full_objective
}

/// Both iterations of the first-order solver.
const METHODS: [FirstOrderMethod; 3] = [
    FirstOrderMethod::Fista,
    FirstOrderMethod::NewtonCg,
    FirstOrderMethod::Lbfgs,
];

fn first_order(method: FirstOrderMethod) -> Settings {
    Settings {
        first_order_method: method,
        ..settings(SolverChoice::FirstOrder)
    }
}

fn assert_agree(p: &Problem) {
    let qp = dwell::solve(p, &settings(SolverChoice::Qp), &Silent).unwrap();
    for method in METHODS {
        assert_agree_with(p, &qp, method);
    }
}

fn assert_agree_with(p: &Problem, qp: &dwell::Solution, method: FirstOrderMethod) {
    let fo = dwell::solve(p, &first_order(method), &Silent).unwrap();
    assert!(qp.status.is_converged(), "QP {:?}", qp.status);
    assert!(
        fo.status.is_converged(),
        "{method:?}: {:?} after {}",
        fo.status,
        fo.iterations
    );
    assert!(p.bounds().max_violation_s(&fo.dwell_s) == 0.0);
    let (fq, ff) = (
        full_objective(p, &qp.dwell_s),
        full_objective(p, &fo.dwell_s),
    );
    let rel = (ff - fq).abs() / fq.abs().max(1e-300);
    assert!(
        rel < AGREE_REL_TOL,
        "{method:?}: {ff} vs QP {fq}: rel {rel:e}"
    );
}

#[test]
fn first_order_agrees_with_qp_without_v_min() {
    // rho = 0 without v_min is the worst-conditioned case (a uniform extra layer is nearly free):
    // a smaller map keeps the test fast.
    assert_agree(&sized_problem(15, 9, 3, 0.0, 0.0, 0.0));
}

#[test]
fn first_order_agrees_with_qp_with_v_min() {
    assert_agree(&problem(5, 300.0, 0.0, 0.0));
}

#[test]
fn first_order_agrees_with_qp_with_rho_and_lambda() {
    assert_agree(&problem(7, 0.0, 0.5, 2.0));
}

/// The pairs projected L-BFGS keeps change its path, not where it ends: with one pair, the
/// default and twenty it reaches the QP's optimum on the worst-conditioned case (no `v_min`, no
/// `rho`), and each memory takes its own number of iterations (the pairs are used). Out-of-range
/// memories are refused by name; a job's `[solver]` table sets it.
#[test]
fn lbfgs_reaches_the_qp_optimum_with_any_memory() {
    let p = sized_problem(15, 9, 3, 0.0, 0.0, 0.0);
    let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
    let fq = full_objective(&p, &qp.dwell_s);
    let mut iterations = Vec::new();
    for memory in [1, DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS, 20] {
        let s = Settings {
            lbfgs_memory: Some(memory),
            ..first_order(FirstOrderMethod::Lbfgs)
        };
        let fo = dwell::solve(&p, &s, &Silent).unwrap();
        assert!(fo.status.is_converged(), "memory {memory}: {:?}", fo.status);
        let rel = (full_objective(&p, &fo.dwell_s) - fq).abs() / fq;
        assert!(rel < AGREE_REL_TOL, "memory {memory}: rel {rel:e}");
        iterations.push(fo.iterations);
    }
    assert!(
        iterations[0] != iterations[1] && iterations[1] != iterations[2],
        "{iterations:?}"
    );
    for memory in [0, MAX_LBFGS_MEMORY + 1] {
        let s = Settings {
            lbfgs_memory: Some(memory),
            ..Settings::default()
        };
        let e = s.validate().unwrap_err().to_string();
        assert!(e.contains("lbfgs_memory"), "{e}");
    }
    let from_job: Settings = serde_json::from_str(r#"{"lbfgs_memory": 10}"#).unwrap();
    assert_eq!(from_job.lbfgs_memory, Some(10));
    assert_eq!(Settings::default().lbfgs_memory, None);
    assert_eq!(
        from_job.first_order_tolerance,
        Settings::default().first_order_tolerance
    );
}

/// The map, `R` assembled and as the FFT operator, and the dwell bounds of the 25 x 15 case, its
/// 1 mm raster at feeds from `v_min` to 3000 mm/min.
fn sparse_and_fft_case(
    v_min: f64,
) -> (
    InfluenceMatrix,
    preston::solver::influence::operator::fft::FftOperator,
    Vec<f64>,
    DwellBounds,
) {
    let (x, y, z, path, tif) = case(25, 15, 29);
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let limits = FeedLimits {
        v_max_mm_per_min: 3000.0,
        v_min_mm_per_min: v_min,
    };
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits).unwrap();
    let fft = preston::solver::influence::operator::fft::FftOperator::new(
        &x,
        &y,
        path.x_mm(),
        path.y_mm(),
        0.5,
        &tif,
    )
    .unwrap();
    (r, fft, z, bounds)
}

/// Without a memory set, projected L-BFGS keeps `DEFAULT_LBFGS_MEMORY` pairs with the assembled
/// `R` and `DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS` with the FFT operator (whose products cost about
/// as much per dwell point as the passes more pairs add): the default's dwell times are those of
/// the explicit memory, bit for bit, and differ from the other's.
#[test]
fn the_default_lbfgs_memory_follows_the_operator() {
    use preston::solver::dwell::first_order::minimise;
    use preston::solver::influence::operator::sparse::SparseOperator;
    let (r, fft, z, bounds) = sparse_and_fft_case(0.0);
    let sparse = SparseOperator::new(r.csc());
    let run = |op: &dyn preston::solver::influence::LinearOperator, memory: Option<usize>| {
        let s = Settings {
            lbfgs_memory: memory,
            first_order_tolerance: 1e-7,
            ..first_order(FirstOrderMethod::Lbfgs)
        };
        minimise(op, &z, &bounds, 0.0, 0.0, &s, None, &Silent).unwrap()
    };
    let (cheap, dear) = (
        Some(DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS),
        Some(DEFAULT_LBFGS_MEMORY),
    );
    for (op, name, default, other) in [
        (
            &sparse as &dyn preston::solver::influence::LinearOperator,
            "sparse",
            dear,
            cheap,
        ),
        (&fft, "fft", cheap, dear),
    ] {
        let implicit = run(op, None);
        assert_eq!(implicit.dwell_s, run(op, default).dwell_s, "{name}");
        assert_ne!(implicit.dwell_s, run(op, other).dwell_s, "{name}");
    }
}

/// Largest growth of the default stop's excess over the QP's optimum from a removal depth of
/// 4e4 to one of 4e6 (100 times deeper; the excess grew about as the depth before the KKT
/// normalisation followed what is left).
const EXCESS_GROWTH_WITH_DEPTH: f64 = 10.0;
/// Largest excess the default stop may leave on the shallowest case (0.1%).
const SHALLOW_STOP_EXCESS: f64 = 1e-3;

/// The default stop's excess over the optimum does not grow with the depth of the removal. The
/// maps are `z = R t + eps e`: a removable figure `R t` plus a rough `e` (white, no dwell follows
/// it), `eps` from 1 down to 0.01 nm, so that the depth `f(0) / f*` spans four decades. With the
/// KKT residual relative to the gradient at zero dwell alone, the deepest case stopped 16% above
/// its optimum (0.18% at 4e4).
#[test]
fn the_default_stop_does_not_loosen_with_the_removal_depth() {
    let base = sized_problem(25, 15, 11, 0.0, 0.0, 0.0);
    let figure: Vec<f64> = (0..base.n())
        .map(|j| 1.0 + 2.0 * ((j * 7919) % 17) as f64 / 17.0)
        .collect();
    let removable = base.removal_nm(&figure).unwrap();
    let (mut depths, mut excesses) = (Vec::new(), Vec::new());
    for eps_nm in [1.0, 0.1, 0.01] {
        let z: Vec<f64> = removable
            .iter()
            .enumerate()
            .map(|(i, h)| h + eps_nm * (((i * 7919) % 13) as f64 - 6.0) / 6.0)
            .collect();
        let p = Problem::new(
            base.influence().unwrap().clone(),
            z.clone(),
            base.bounds().clone(),
            0.0,
            0.0,
        )
        .unwrap();
        let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
        let defaults = Settings {
            solver: SolverChoice::FirstOrder,
            ..Settings::default()
        };
        let fo = dwell::solve(&p, &defaults, &Silent).unwrap();
        assert!(fo.status.is_converged(), "eps {eps_nm}: {:?}", fo.status);
        let (fq, ff) = (
            full_objective(&p, &qp.dwell_s),
            full_objective(&p, &fo.dwell_s),
        );
        let mean = z.iter().sum::<f64>() / z.len() as f64;
        let f_zero = 0.5 * z.iter().map(|z| (z - mean).powi(2)).sum::<f64>();
        depths.push(f_zero / fq);
        excesses.push((ff - fq) / fq);
    }
    assert!(depths[1] < 1e5 && depths[2] > 1e6, "{depths:?}");
    assert!(excesses[0] <= SHALLOW_STOP_EXCESS, "{excesses:?}");
    assert!(
        excesses[2] <= EXCESS_GROWTH_WITH_DEPTH * excesses[1],
        "excess {excesses:?} at depths {depths:?}"
    );
}

/// A problem whose optimum is known exactly: `z = R t*` with `t*` strictly inside a bounded box
/// (`v_min` > 0), `rho = lambda = 0`, so `min f = 0`.
fn exactly_removable() -> Problem {
    let base = problem(9, 300.0, 0.0, 0.0);
    let t_star: Vec<f64> = (0..base.n())
        .map(|j| {
            let (l, u) = (base.bounds().lower_s()[j], base.bounds().upper(j));
            l + (u - l) * (0.3 + 0.4 * ((j as f64) * 0.37).sin().abs())
        })
        .collect();
    let z = base.removal_nm(&t_star).unwrap();
    Problem::new(
        base.influence().unwrap().clone(),
        z,
        base.bounds().clone(),
        0.0,
        0.0,
    )
    .unwrap()
}

/// On a problem whose optimum is known exactly (`z = R t*` with `t*` strictly inside a bounded
/// box, so `min f = 0`), the reported bound is at least the true gap `f(t_k) - 0` after any number
/// of iterations, and it shrinks as the iteration converges.
#[test]
fn gap_bound_is_honest_on_a_known_optimum() {
    let p = exactly_removable();
    for method in METHODS {
        gap_bound_is_honest_with(&p, method);
    }
}

fn gap_bound_is_honest_with(p: &Problem, method: FirstOrderMethod) {
    let mut last = f64::INFINITY;
    for iters in [10, 100, 1000] {
        let s = Settings {
            first_order_max_iterations: iters,
            first_order_tolerance: 1e-15,
            ..first_order(method)
        };
        let sol = dwell::solve(p, &s, &Silent).unwrap();
        let true_gap = full_objective(p, &sol.dwell_s);
        let bound = sol.objective_gap_bound.unwrap();
        assert!(
            bound >= true_gap,
            "{method:?}, {iters} iterations: bound {bound} < true gap {true_gap}"
        );
        if sol.iterations >= iters {
            assert!(
                bound < last,
                "{method:?}: the bound did not shrink: {bound} after {last}"
            );
        }
        last = bound;
    }
}

/// Newton-CG on a known optimum (`z = R t*`, `t*` strictly inside the box, `min f = 0`): the
/// removal reproduces the map to far below a nanometre, as the engine asks of the QP.
#[test]
fn newton_cg_recovers_an_exactly_removable_map() {
    let p = exactly_removable();
    let s = Settings {
        first_order_tolerance: 1e-13,
        ..first_order(FirstOrderMethod::NewtonCg)
    };
    let sol = dwell::solve(&p, &s, &Silent).unwrap();
    assert!(sol.status.is_converged(), "{:?}", sol.status);
    let residual_rms = (2.0 * full_objective(&p, &sol.dwell_s) / p.m() as f64).sqrt();
    assert!(
        residual_rms < EXACT_RMS_NM,
        "residual RMS {residual_rms} nm"
    );
}

/// Residual RMS of an exactly removable map (the engine's QP criterion), nm.
const EXACT_RMS_NM: f64 = 1e-6;

/// With `rho > 0` the level-set bound makes the dual finite without `v_min`; the reference optimum
/// is the QP at tight tolerance (an upper bound on the true optimum, so the check is necessary).
#[test]
fn gap_bound_covers_the_qp_optimum_with_rho() {
    let p = problem(13, 0.0, 1.0, 0.0);
    let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
    let f_star = full_objective(&p, &qp.dwell_s);
    for (method, iters) in METHODS.iter().flat_map(|&m| [(m, 20), (m, 200)]) {
        let s = Settings {
            first_order_max_iterations: iters,
            first_order_tolerance: 1e-15,
            ..first_order(method)
        };
        let sol = dwell::solve(&p, &s, &Silent).unwrap();
        let gap = full_objective(&p, &sol.dwell_s) - f_star;
        let bound = sol.objective_gap_bound.unwrap();
        assert!(
            bound >= gap,
            "{method:?}, {iters} iterations: bound {bound} < gap {gap}"
        );
        assert!(sol.kkt_residual.unwrap() >= 0.0);
    }
}

/// With `rho = 0` and no `v_min` no dual bound is finite away from an exact optimum: the solve
/// reports no bound and says why, rather than the objective itself; when it still converges, it
/// names the KKT residual as the test met.
#[test]
fn no_gap_bound_without_time_weight_or_upper_bound() {
    let p = sized_problem(15, 9, 3, 0.0, 0.0, 0.0);
    assert!(p.bounds().upper_s().is_none());
    for method in METHODS {
        for iters in [5, 50] {
            let s = Settings {
                first_order_max_iterations: iters,
                first_order_tolerance: 1e-15,
                ..first_order(method)
            };
            let sol = dwell::solve(&p, &s, &Silent).unwrap();
            assert_eq!(
                sol.objective_gap_bound, None,
                "{method:?}, {iters} iterations"
            );
            assert_eq!(
                sol.gap_bound_reason,
                Some(GapBoundReason::UnboundedDwellWithoutTimeWeight)
            );
            assert_eq!(sol.converged_by, None, "not converged, so no criterion");
        }
        let sol = dwell::solve(&p, &first_order(method), &Silent).unwrap();
        if sol.status.is_converged() && sol.objective_gap_bound.is_none() {
            assert_eq!(sol.converged_by, Some(ConvergenceCriterion::KktResidual));
        }
    }
}

/// A converged first-order solve names the test it met, and that test holds on the report's
/// own figures.
#[test]
fn converged_by_names_a_test_that_holds() {
    let p = problem(7, 0.0, 0.5, 2.0);
    for method in METHODS {
        let s = first_order(method);
        let sol = dwell::solve(&p, &s, &Silent).unwrap();
        assert!(sol.status.is_converged(), "{method:?}");
        let f = full_objective(&p, &sol.dwell_s);
        match sol.converged_by {
            Some(ConvergenceCriterion::ObjectiveGap) => {
                let gap = sol.objective_gap_bound.unwrap();
                assert!(gap / f <= s.first_order_tolerance, "{gap} / {f}");
            }
            Some(ConvergenceCriterion::KktResidual) => {
                let tol = match sol.status {
                    Status::AlmostConverged => s.first_order_tolerance.sqrt(),
                    _ => s.first_order_tolerance,
                };
                assert!(sol.kkt_residual.unwrap() <= tol);
            }
            other => panic!("{method:?}: converged by {other:?}"),
        }
    }
}

/// The QP's answer carries the same dual certificate, recomputed from `R` at its point: finite
/// with `rho > 0` or `v_min`, at least the true gap to a tighter first-order optimum, and tiny
/// relative to the objective; the interior-point tolerances are named as the test met.
#[test]
fn qp_solutions_carry_a_valid_gap_bound() {
    for p in [problem(13, 0.0, 1.0, 0.0), problem(5, 300.0, 0.0, 0.0)] {
        let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
        assert_eq!(qp.converged_by, Some(ConvergenceCriterion::InteriorPoint));
        let bound = qp.objective_gap_bound.unwrap();
        let f_qp = full_objective(&p, &qp.dwell_s);
        assert!(
            bound >= 0.0 && bound / f_qp < QP_GAP_REL,
            "{bound} vs {f_qp}"
        );
        let tight = Settings {
            first_order_tolerance: 1e-12,
            first_order_max_iterations: 200_000,
            ..first_order(FirstOrderMethod::NewtonCg)
        };
        let fo = dwell::solve(&p, &tight, &Silent).unwrap();
        let f_fo = full_objective(&p, &fo.dwell_s);
        assert!(
            bound >= f_qp - f_fo,
            "bound {bound} below the gap to a better point {}",
            f_qp - f_fo
        );
    }
}

/// How close to optimal Clarabel's default tolerances put the QP, relative (gap bound / objective).
const QP_GAP_REL: f64 = 1e-5;

#[test]
fn first_order_is_independent_of_the_thread_count() {
    // Large enough (m + n above the single-thread threshold) that the iteration runs on the
    // whole pool.
    let p = sized_problem(150, 120, 17, 300.0, 0.1, 1.0);
    assert!(p.m() + p.n() > 20_000);
    for method in METHODS {
        independent_of_the_thread_count_with(&p, method);
    }
}

fn independent_of_the_thread_count_with(p: &Problem, method: FirstOrderMethod) {
    let s = Settings {
        first_order_max_iterations: 20,
        ..first_order(method)
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| dwell::solve(p, &s, &Silent).unwrap())
    };
    let one = run(1);
    for threads in [2, 3] {
        let other = run(threads);
        let same = one
            .dwell_s
            .iter()
            .zip(&other.dwell_s)
            .all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(
            same,
            "{method:?}: {threads} threads changed the dwell times"
        );
        assert_eq!(one.iterations, other.iterations);
    }
}

#[test]
fn warm_start_from_the_optimum_stops_early() {
    let p = problem(19, 300.0, 0.0, 0.0);
    for method in METHODS {
        let s = first_order(method);
        let cold = dwell::solve(&p, &s, &Silent).unwrap();
        let warm = dwell::solve_from(&p, &s, &Silent, Some(&cold.dwell_s)).unwrap();
        assert!(warm.status.is_converged(), "{method:?}: {:?}", warm.status);
        assert!(
            warm.iterations < cold.iterations / 2,
            "{method:?}: {} vs {}",
            warm.iterations,
            cold.iterations
        );
    }
}

#[test]
fn auto_picks_by_size_and_min_time_stays_on_qp() {
    let p = problem(3, 0.0, 0.0, 0.0);
    assert_eq!(SolverChoice::Auto.resolve(&p, false), dwell::SolverKind::Qp);
    assert_eq!(
        SolverChoice::FirstOrder.resolve(&p, false),
        dwell::SolverKind::FirstOrder
    );
    let s = Settings {
        min_time: true,
        ..settings(SolverChoice::FirstOrder)
    };
    assert!(dwell::solve(&p, &s, &Silent).is_err());
}

/// Agreement of the FFT operator with the sparse matrix (1e-9 relative).
const FFT_REL_TOL: f64 = 1e-9;
/// Adjoint identity `<R x, y> = <x, R^T y>` to rounding.
const ADJOINT_REL_TOL: f64 = 1e-12;

#[test]
fn fft_operator_matches_sparse_and_is_adjoint() {
    use preston::solver::influence::operator::fft::FftOperator;
    use preston::solver::influence::operator::{sparse::SparseOperator, LinearOperator};
    let (x, y, _, path, tif) = case(40, 30, 23);
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let sparse = SparseOperator::new(r.csc());
    let fft = FftOperator::new(&x, &y, path.x_mm(), path.y_mm(), 0.5, &tif).unwrap();
    let (m, n) = (x.len(), path.len());
    assert_eq!((fft.nrows(), fft.ncols()), (m, n));
    let t: Vec<f64> = (0..n).map(|j| 1.0 + ((j * 37) % 11) as f64 * 0.3).collect();
    let w: Vec<f64> = (0..m)
        .map(|i| (((i * 13) % 7) as f64 - 3.0) * 0.7)
        .collect();
    let (mut a, mut b) = (vec![0.0; m], vec![0.0; m]);
    sparse.apply(&t, &mut a);
    fft.apply(&t, &mut b);
    let scale = a.iter().fold(0.0_f64, |s, v| s.max(v.abs()));
    let err = a
        .iter()
        .zip(&b)
        .fold(0.0_f64, |s, (p, q)| s.max((p - q).abs()));
    assert!(
        err <= FFT_REL_TOL * scale,
        "R t differs by {err} (scale {scale})"
    );
    let (mut at, mut bt) = (vec![0.0; n], vec![0.0; n]);
    sparse.apply_transpose(&w, &mut at);
    fft.apply_transpose(&w, &mut bt);
    let scale_t = at.iter().fold(0.0_f64, |s, v| s.max(v.abs()));
    let err_t = at
        .iter()
        .zip(&bt)
        .fold(0.0_f64, |s, (p, q)| s.max((p - q).abs()));
    assert!(err_t <= FFT_REL_TOL * scale_t, "R^T y differs by {err_t}");
    for (op, name) in [(&sparse as &dyn LinearOperator, "sparse"), (&fft, "fft")] {
        let (mut rx, mut rty) = (vec![0.0; m], vec![0.0; n]);
        op.apply(&t, &mut rx);
        op.apply_transpose(&w, &mut rty);
        let lhs: f64 = rx.iter().zip(&w).map(|(p, q)| p * q).sum();
        let rhs: f64 = t.iter().zip(&rty).map(|(p, q)| p * q).sum();
        let mag: f64 = rx.iter().zip(&w).map(|(p, q)| (p * q).abs()).sum();
        assert!(
            (lhs - rhs).abs() <= ADJOINT_REL_TOL * mag,
            "{name}: {lhs} vs {rhs}"
        );
    }
    let (cs, cf) = (
        sparse.centred_column_norms_sq(),
        fft.centred_column_norms_sq(),
    );
    for (p, q) in cs.iter().zip(&cf) {
        assert!((p - q).abs() <= FFT_REL_TOL * p.abs().max(1.0));
    }
}

#[test]
fn first_order_with_the_fft_operator_matches_the_sparse_one() {
    use preston::solver::dwell::first_order::minimise;
    use preston::solver::influence::operator::sparse::SparseOperator;
    let (r, fft, z, bounds) = sparse_and_fft_case(300.0);
    let sparse = SparseOperator::new(r.csc());
    for method in METHODS {
        let s = first_order(method);
        let a = minimise(&sparse, &z, &bounds, 0.0, 0.0, &s, None, &Silent).unwrap();
        let b = minimise(&fft, &z, &bounds, 0.0, 0.0, &s, None, &Silent).unwrap();
        let rel = (a.full_objective - b.full_objective).abs() / a.full_objective;
        assert!(
            rel < AGREE_REL_TOL,
            "{method:?}: sparse {} vs fft {}",
            a.full_objective,
            b.full_objective
        );
    }
}

#[test]
fn matrix_free_problem_solves_like_the_assembled_one() {
    use preston::solver::influence::operator::fft::FftOperator;
    let (x, y, z, _, tif) = case(31, 21, 41);
    // A raster reaching the TIF radius past the map: its corner points touch no map point.
    let bbox = preston::solver::map::BoundingBox::of_points(&x, &y)
        .unwrap()
        .expanded(4.5);
    let path = serpentine(&bbox, 1.0, RasterAxis::X).unwrap();
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let limits = FeedLimits {
        v_max_mm_per_min: 3000.0,
        v_min_mm_per_min: 300.0,
    };
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits).unwrap();
    let assembled = Problem::new(r, z.clone(), bounds.clone(), 0.0, 0.0).unwrap();
    let pitch = FftOperator::lattice_pitch_mm(&x, &y).unwrap();
    assert!((pitch - 0.5).abs() < 1e-12, "detected pitch {pitch}");
    let fft = FftOperator::new(&x, &y, path.x_mm(), path.y_mm(), pitch, &tif).unwrap();
    let free = Problem::new(fft, z, bounds, 0.0, 0.0).unwrap();
    assert!(free.influence().is_none() && free.operator_kind() == OperatorKind::Fft);
    // The implicit R has exactly the assembled one's non-zeros and empty columns.
    assert_eq!(free.nnz(), assembled.nnz());
    assert_eq!(free.empty_columns(), assembled.empty_columns());
    assert!(!assembled.empty_columns().is_empty());
    // Same removal for the same dwell times.
    let t: Vec<f64> = (0..free.n()).map(|j| 0.1 + (j % 5) as f64 * 0.2).collect();
    let (ha, hf) = (
        assembled.removal_nm(&t).unwrap(),
        free.removal_nm(&t).unwrap(),
    );
    let scale = ha.iter().fold(0.0_f64, |s, v| s.max(v.abs()));
    for (a, f) in ha.iter().zip(&hf) {
        assert!((a - f).abs() <= FFT_REL_TOL * scale);
    }
    // `auto` runs the first-order solver on a matrix-free problem; the objectives agree, and the
    // unreachable dwell points sit on their lower bound in both.
    for method in METHODS {
        let s = Settings {
            first_order_method: method,
            ..settings(SolverChoice::Auto)
        };
        let a = dwell::solve(&assembled, &first_order(method), &Silent).unwrap();
        let f = dwell::solve(&free, &s, &Silent).unwrap();
        assert_eq!(f.solver, dwell::SolverKind::FirstOrder);
        let rel = (a.objective - f.objective).abs() / a.objective;
        assert!(
            rel < AGREE_REL_TOL,
            "{method:?}: {} vs {}",
            a.objective,
            f.objective
        );
        for &j in &assembled.empty_columns() {
            assert_eq!(f.dwell_s[j], free.bounds().lower_s()[j]);
            assert_eq!(a.dwell_s[j], assembled.bounds().lower_s()[j]);
        }
    }
    // The QP needs the assembled matrix: a clear error, not a panic.
    let err = dwell::solve(&free, &settings(SolverChoice::Qp), &Silent).unwrap_err();
    assert!(err.to_string().contains("matrix-free"), "{err}");
}

/// Relative agreement of two first-order runs whose products differ by rounding only (the Gram
/// matrix `R^T R` against `R` then `R^T`), both at the tolerance `GRAM_TOL`.
const GRAM_AGREE_REL: f64 = 1e-6;
/// The tolerance of those runs.
const GRAM_TOL: f64 = 1e-9;

#[test]
fn products_through_the_gram_matrix_reach_the_same_optimum_with_an_honest_certificate() {
    use preston::solver::dwell::first_order::minimise;
    use preston::solver::influence::{GramMatrix, GramOperator, SparseOperator};
    // With rho, lambda and an upper bound: the gap bound is finite and must cover the QP's
    // optimum.
    let p = problem(23, 300.0, 0.1, 1.0);
    let r = p.influence().expect("assembled");
    let sparse = SparseOperator::new(r.csc());
    // A map twice as fine as the raster: forming G pays for the power iteration alone, so
    // the default solve takes it.
    assert!(GramMatrix::worthwhile(&sparse, 60));
    let gram = GramOperator::new(SparseOperator::new(r.csc()));
    assert!(gram.gram().nnz() < 2 * r.csc().nnz());
    let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
    let optimum = full_objective(&p, &qp.dwell_s);
    for method in METHODS {
        let s = Settings {
            first_order_tolerance: GRAM_TOL,
            ..first_order(method)
        };
        let run = |op: &dyn preston::solver::influence::LinearOperator| {
            minimise(op, p.z_nm(), p.bounds(), 0.1, 1.0, &s, None, &Silent).unwrap()
        };
        let (a, b) = (run(&sparse), run(&gram));
        assert!(
            a.status.is_converged() && b.status.is_converged(),
            "{method:?}"
        );
        let (fa, fb) = (
            full_objective(&p, &a.dwell_s),
            full_objective(&p, &b.dwell_s),
        );
        assert!(
            (fa - fb).abs() <= GRAM_AGREE_REL * fa,
            "{method:?}: {fa} through R, {fb} through G"
        );
        // The reported objective and gap bound are those of the final point, through R.
        assert!((b.full_objective - fb).abs() <= 1e-9 * fb, "{method:?}");
        let gap = b.objective_gap_bound.value().expect("a finite bound");
        assert!(
            fb - optimum <= gap * (1.0 + 1e-9),
            "{method:?}: {fb} - {optimum} above the bound {gap}"
        );
    }
}

/// Projected L-BFGS against FISTA at equal products on an ill-conditioned problem (1.5 mm TIF
/// on a 1 mm raster, 45 x 29 map): the quasi-Newton directions reach the QP optimum to within
/// 0.1% in fewer products than FISTA needs for it.
#[test]
fn lbfgs_reaches_the_qp_optimum_in_fewer_products_than_fista() {
    let p = sized_problem(45, 29, 11, 0.0, 0.0, 0.0);
    let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
    let f_qp = full_objective(&p, &qp.dwell_s);
    let products_to = |method: FirstOrderMethod| {
        [50, 100, 200, 400, 800, 1600, 3200, 6400]
            .into_iter()
            .find(|&iters| {
                let s = Settings {
                    first_order_max_iterations: iters,
                    first_order_tolerance: 1e-15,
                    ..first_order(method)
                };
                let sol = dwell::solve(&p, &s, &Silent).unwrap();
                let f = full_objective(&p, &sol.dwell_s);
                f <= f_qp * (1.0 + 1e-3)
            })
    };
    let lbfgs = products_to(FirstOrderMethod::Lbfgs).expect("L-BFGS reaches 0.1%");
    let fista = products_to(FirstOrderMethod::Fista).unwrap_or(usize::MAX);
    assert!(lbfgs < fista, "L-BFGS {lbfgs} products, FISTA {fista}");
}

/// Dwell points whose tool barely reaches the map (a measured-style grid TIF whose bilinear
/// interpolant ramps to zero at its edge, and a raster reaching past the map by its whole
/// support) have almost empty columns and Jacobi scales orders of magnitude above the rest. With
/// a time weight they must not inflate the KKT test's norm: at the default tolerance the solver
/// reaches the QP's optimum (within [`EMPTY_COLUMNS_REL_TOL`]) instead of stopping where it
/// started.
#[test]
fn almost_empty_columns_do_not_stop_the_first_order_solver_early() {
    let (x, y, z, _, gaussian) = case(15, 9, 11);
    let (pitch, half) = (0.25, 26usize);
    let n = 2 * half + 1;
    let x0 = -(half as f64) * pitch;
    let rates = (0..n * n)
        .map(|k| {
            let (i, j) = (k % n, k / n);
            if i == 0 || j == 0 || i == n - 1 || j == n - 1 {
                0.0
            } else {
                gaussian.rate_nm_per_s(x0 + i as f64 * pitch, x0 + j as f64 * pitch)
            }
        })
        .collect();
    let tif = GridTif::new(x0, x0, pitch, pitch, n, n, rates).unwrap();
    let bbox = preston::solver::map::BoundingBox::of_points(&x, &y)
        .unwrap()
        .expanded(6.4);
    let path = serpentine(&bbox, 0.7, RasterAxis::X).unwrap();
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let limits = FeedLimits {
        v_max_mm_per_min: 3000.0,
        v_min_mm_per_min: 0.0,
    };
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits).unwrap();
    let p = Problem::new(r, z, bounds, 0.01, 0.0).unwrap();
    let qp = dwell::solve(&p, &settings(SolverChoice::Qp), &Silent).unwrap();
    assert!(qp.status.is_converged(), "QP {:?}", qp.status);
    let fq = full_objective(&p, &qp.dwell_s);
    let start = full_objective(&p, p.bounds().lower_s());
    for method in [FirstOrderMethod::Lbfgs, FirstOrderMethod::NewtonCg] {
        let s = Settings {
            solver: SolverChoice::FirstOrder,
            first_order_method: method,
            ..Settings::default()
        };
        let fo = dwell::solve(&p, &s, &Silent).unwrap();
        let ff = full_objective(&p, &fo.dwell_s);
        assert!(
            (ff - fq).abs() <= EMPTY_COLUMNS_REL_TOL * (start - fq),
            "{method:?}: {ff} against the QP's {fq} (start {start}), {:?} after {}",
            fo.status,
            fo.iterations
        );
    }
}

/// Share of the objective's fall from the start to the optimum that a default-tolerance solve
/// may leave.
const EMPTY_COLUMNS_REL_TOL: f64 = 1e-3;
