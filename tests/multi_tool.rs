//! Several tools in one solve: a large and a small Gaussian tool on one map, solved jointly
//! (the stacked matrix `[R_1, R_2]`) against each tool alone and the sequential plan (large tool
//! first, then the small one on what it left).

use preston::solver::dwell::{self, DwellBounds, Problem, Settings, SolverChoice};
use preston::solver::influence::operator::stacked::stack_scaled;
use preston::solver::influence::InfluenceMatrix;
use preston::solver::observer::Silent;
use preston::solver::tif::GaussianTif;

/// Relative slack for comparing optima reached by the interior-point QP.
const QP_SLACK: f64 = 1e-6;
/// The first-order solve must reach the stacked QP's optimum within this (0.1%).
const FIRST_ORDER_GAP: f64 = 1e-3;

type Grid = (Vec<f64>, Vec<f64>);

fn grid(x0: f64, y0: f64, pitch: f64, nx: usize, ny: usize) -> Grid {
    (0..nx * ny)
        .map(|k| (x0 + pitch * (k % nx) as f64, y0 + pitch * (k / nx) as f64))
        .unzip()
}

/// A 21 x 21 mm map at 1 mm: a broad bump plus a 5 mm ripple.
fn map() -> (Grid, Vec<f64>) {
    let g = grid(0.0, 0.0, 1.0, 21, 21);
    let z =
        g.0.iter()
            .zip(&g.1)
            .map(|(&x, &y)| {
                let (u, v) = (x - 10.0, y - 10.0);
                30.0 * (-(u * u + v * v) / 80.0).exp()
                    + 4.0
                        * (std::f64::consts::TAU * x / 5.0).sin()
                        * (std::f64::consts::TAU * y / 7.0).cos()
            })
            .collect();
    (g, z)
}

fn assemble(map: &Grid, dwell: &Grid, tif: &GaussianTif) -> InfluenceMatrix {
    InfluenceMatrix::assemble(&map.0, &map.1, &dwell.0, &dwell.1, tif, &Silent).unwrap()
}

fn solve(r: InfluenceMatrix, z: &[f64], solver: SolverChoice) -> (f64, Vec<f64>) {
    let n = r.ncols();
    let problem = Problem::new(
        r,
        z.to_vec(),
        DwellBounds::new(vec![0.0; n], None).unwrap(),
        0.0,
        0.0,
    )
    .unwrap();
    // The default tolerance: the joint plan removes nearly all of the map, the case the KKT
    // normalisation's depth term is for.
    let settings = Settings {
        solver,
        ..Settings::default()
    };
    let sol = dwell::solve(&problem, &settings, &Silent).unwrap();
    let e = problem.evaluate(&sol.dwell_s).unwrap();
    (e.objective, sol.dwell_s)
}

/// `0.5 ||h - z - c||^2` at the optimal piston.
fn objective(h: &[f64], z: &[f64]) -> f64 {
    let c = h.iter().zip(z).map(|(h, z)| h - z).sum::<f64>() / z.len() as f64;
    0.5 * h
        .iter()
        .zip(z)
        .map(|(h, z)| (h - z - c).powi(2))
        .sum::<f64>()
}

#[test]
fn joint_solve_beats_each_tool_and_the_sequential_plan_and_matches_the_stacked_qp() {
    let (m, z) = map();
    let large = GaussianTif::new(3.0, 2.0, 9.0).unwrap();
    let small = GaussianTif::new(0.7, 1.0, 2.1).unwrap();
    let d_large = grid(-4.0, -4.0, 2.0, 15, 15);
    let d_small = grid(0.0, 0.0, 1.0, 21, 21);
    let r1 = assemble(&m, &d_large, &large);
    let r2 = assemble(&m, &d_small, &small);
    let stacked = stack_scaled(&[(&r1, 1.0), (&r2, 1.0)]).unwrap();

    let (joint_qp, _) = solve(stacked.clone(), &z, SolverChoice::Qp);
    let (joint_fo, t_fo) = solve(stacked, &z, SolverChoice::FirstOrder);
    let (large_only, t1) = solve(r1.clone(), &z, SolverChoice::Qp);
    let (small_only, _) = solve(r2.clone(), &z, SolverChoice::Qp);
    // Sequential: the large tool's optimum, then the small tool on the map it left.
    let h1 = r1.removal_nm(&t1).unwrap();
    let left: Vec<f64> = z.iter().zip(&h1).map(|(z, h)| z - h).collect();
    let (_, t2) = solve(r2.clone(), &left, SolverChoice::Qp);
    let h2 = r2.removal_nm(&t2).unwrap();
    let h_seq: Vec<f64> = h1.iter().zip(&h2).map(|(a, b)| a + b).collect();
    let sequential = objective(&h_seq, &z);

    let slack = QP_SLACK * objective(&vec![0.0; z.len()], &z);
    assert!(
        joint_qp <= large_only + slack,
        "{joint_qp} vs large {large_only}"
    );
    assert!(
        joint_qp <= small_only + slack,
        "{joint_qp} vs small {small_only}"
    );
    assert!(
        joint_qp <= sequential + slack,
        "{joint_qp} vs sequential {sequential}"
    );
    // The two tools together do strictly better than either here (the large tool cannot follow
    // the ripple, the small one's reach is too short for the bump at this dwell budget).
    assert!(joint_qp < large_only.min(small_only));
    assert!(
        joint_fo <= joint_qp * (1.0 + FIRST_ORDER_GAP) + slack,
        "first-order {joint_fo} vs QP {joint_qp}"
    );
    // The first-order dwell, split back into the tools, reproduces its removal.
    let (a, b) = t_fo.split_at(r1.ncols());
    let h: Vec<f64> = r1
        .removal_nm(a)
        .unwrap()
        .iter()
        .zip(r2.removal_nm(b).unwrap())
        .map(|(x, y)| x + y)
        .collect();
    assert!((objective(&h, &z) - joint_fo).abs() <= 1e-9 * joint_fo.max(1e-12));
}

#[test]
fn a_heavier_time_weight_shifts_dwell_off_that_tool() {
    let (m, z) = map();
    let large = GaussianTif::new(3.0, 2.0, 9.0).unwrap();
    let small = GaussianTif::new(0.7, 1.0, 2.1).unwrap();
    let r1 = assemble(&m, &grid(-4.0, -4.0, 2.0, 15, 15), &large);
    let r2 = assemble(&m, &grid(0.0, 0.0, 1.0, 21, 21), &small);
    let n1 = r1.ncols();
    let small_share = |w2: f64| {
        let stacked = stack_scaled(&[(&r1, 1.0), (&r2, w2)]).unwrap();
        let n = stacked.ncols();
        let problem = Problem::new(
            stacked,
            z.clone(),
            DwellBounds::new(vec![0.0; n], None).unwrap(),
            5.0,
            0.0,
        )
        .unwrap();
        let settings = Settings {
            solver: SolverChoice::Qp,
            ..Settings::default()
        };
        let u = dwell::solve(&problem, &settings, &Silent).unwrap().dwell_s;
        // Dwell times of the small tool, s: u / w2.
        u[n1..].iter().sum::<f64>() / w2
    };
    let (even, heavy) = (small_share(1.0), small_share(10.0));
    assert!(
        heavy < 0.9 * even,
        "small tool dwell {heavy} s at w = 10 vs {even} s at w = 1"
    );
}
