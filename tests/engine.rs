//! Known-answer and reference tests of the dwell engine (engine issue).
#![allow(clippy::needless_range_loop)] // the dense reference is clearer with indices

use preston::solver::dwell::{self, DwellBounds, FeedLimits, Problem, Settings, SolverChoice};
use preston::solver::influence::InfluenceMatrix;
use preston::solver::observer::Silent;
use preston::solver::path::raster::{serpentine, RasterAxis};
use preston::solver::path::DwellPath;
use preston::solver::tif::GaussianTif;

/// Relative objective agreement required against the independent NNLS reference.
const REFERENCE_REL_TOL: f64 = 1e-7;
/// RMS below which an exactly reachable map counts as removed, nm.
const EXACT_RMS_TOL_NM: f64 = 1e-6;

/// splitmix64 in [0, 1).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// A map on a `nx x ny` grid at `pitch` with a smooth random error, a Gaussian TIF and a raster
/// of dwell points at `dwell_pitch` over the map extended by the TIF radius.
fn case(
    nx: usize,
    ny: usize,
    pitch: f64,
    dwell_pitch: f64,
    seed: u64,
) -> (Vec<f64>, Vec<f64>, Vec<f64>, DwellPath, GaussianTif) {
    let mut rng = Rng(seed);
    let modes: Vec<(f64, f64, f64, f64)> = (0..6)
        .map(|_| {
            (
                rng.next() * 0.4,
                rng.next() * 0.4,
                rng.next() * 6.0,
                20.0 + 40.0 * rng.next(),
            )
        })
        .collect();
    let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
    for iy in 0..ny {
        for ix in 0..nx {
            let (px, py) = (ix as f64 * pitch, iy as f64 * pitch);
            x.push(px);
            y.push(py);
            z.push(
                modes
                    .iter()
                    .map(|(kx, ky, ph, a)| a * (kx * px + ky * py + ph).cos())
                    .sum::<f64>()
                    + 100.0,
            );
        }
    }
    let tif = GaussianTif::new(1.5, 8.0, 4.5).unwrap();
    let bbox = preston::solver::map::BoundingBox::of_points(&x, &y)
        .unwrap()
        .expanded(2.0);
    let path = serpentine(&bbox, dwell_pitch, RasterAxis::X).unwrap();
    (x, y, z, path, tif)
}

fn problem(
    x: &[f64],
    y: &[f64],
    z: Vec<f64>,
    path: &DwellPath,
    tif: &GaussianTif,
    limits: FeedLimits,
    rho: f64,
) -> Problem {
    let r = InfluenceMatrix::assemble(x, y, path.x_mm(), path.y_mm(), tif, &Silent).unwrap();
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits).unwrap();
    Problem::new(r, z, bounds, rho, 0.0).unwrap()
}

fn qp() -> Settings {
    Settings {
        solver: SolverChoice::Qp,
        ..Settings::default()
    }
}

const FEEDS: FeedLimits = FeedLimits {
    v_max_mm_per_min: 3000.0,
    v_min_mm_per_min: 0.0,
};

#[test]
fn reachable_map_is_removed_exactly() {
    let (x, y, _, path, tif) = case(25, 15, 0.5, 1.0, 11);
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &FEEDS).unwrap();
    // t* = lower bound + a smooth positive extra; z = R t*.
    let t_star: Vec<f64> = bounds
        .lower_s()
        .iter()
        .enumerate()
        .map(|(j, l)| l + 2.0 + (j as f64 * 0.3).sin())
        .collect();
    let z = r.removal_nm(&t_star).unwrap();
    let p = Problem::new(r, z, bounds, 0.0, 0.0).unwrap();
    let sol = dwell::solve(&p, &qp(), &Silent).unwrap();
    assert!(sol.status.is_converged());
    let eval = p.evaluate(&sol.dwell_s).unwrap();
    let m = p.m() as f64;
    let rms = (2.0 * eval.objective / m).sqrt();
    assert!(rms < EXACT_RMS_TOL_NM, "residual RMS {rms} nm");
}

/// Lawson-Hanson active-set NNLS: min ||A s - b|| subject to s >= 0 (dense, column-major
/// `a[j][i]`), with normal equations solved by Cholesky. Slow and independent of the engine.
fn nnls(a: &[Vec<f64>], b: &[f64]) -> Vec<f64> {
    let n = a.len();
    let dot = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(p, q)| p * q).sum::<f64>();
    let mut s = vec![0.0; n];
    let mut passive = vec![false; n];
    let residual = |s: &[f64]| -> Vec<f64> {
        let mut r = b.to_vec();
        for (j, col) in a.iter().enumerate() {
            for (ri, aij) in r.iter_mut().zip(col) {
                *ri -= aij * s[j];
            }
        }
        r
    };
    let solve_passive = |passive: &[bool]| -> Vec<f64> {
        let idx: Vec<usize> = (0..n).filter(|&j| passive[j]).collect();
        let k = idx.len();
        let mut g = vec![vec![0.0; k]; k];
        let mut h = vec![0.0; k];
        for (p, &jp) in idx.iter().enumerate() {
            h[p] = dot(&a[jp], b);
            for (q, &jq) in idx.iter().enumerate() {
                g[p][q] = dot(&a[jp], &a[jq]);
            }
        }
        // Cholesky G = L L^T.
        let mut l = vec![vec![0.0; k]; k];
        for i in 0..k {
            for j in 0..=i {
                let mut sum = g[i][j];
                for t in 0..j {
                    sum -= l[i][t] * l[j][t];
                }
                l[i][j] = if i == j {
                    sum.max(1e-300).sqrt()
                } else {
                    sum / l[j][j]
                };
            }
        }
        let mut w = vec![0.0; k];
        for i in 0..k {
            let mut sum = h[i];
            for t in 0..i {
                sum -= l[i][t] * w[t];
            }
            w[i] = sum / l[i][i];
        }
        for i in (0..k).rev() {
            let mut sum = w[i];
            for t in i + 1..k {
                sum -= l[t][i] * w[t];
            }
            w[i] = sum / l[i][i];
        }
        let mut full = vec![0.0; n];
        for (p, &j) in idx.iter().enumerate() {
            full[j] = w[p];
        }
        full
    };
    for _outer in 0..10 * n {
        let r = residual(&s);
        let grad: Vec<f64> = a.iter().map(|col| dot(col, &r)).collect();
        let scale = grad.iter().fold(0.0f64, |m, g| m.max(g.abs())).max(1.0);
        let cand = (0..n)
            .filter(|&j| !passive[j] && grad[j] > 1e-12 * scale)
            .max_by(|&p, &q| grad[p].total_cmp(&grad[q]));
        let Some(j) = cand else { break };
        passive[j] = true;
        loop {
            let z = solve_passive(&passive);
            if (0..n).all(|j| !passive[j] || z[j] > 0.0) {
                s = z;
                break;
            }
            let mut alpha = f64::INFINITY;
            for j in 0..n {
                if passive[j] && z[j] <= 0.0 {
                    alpha = alpha.min(s[j] / (s[j] - z[j]));
                }
            }
            for j in 0..n {
                s[j] += alpha * (z[j] - s[j]);
                if passive[j] && s[j] <= 1e-14 {
                    passive[j] = false;
                    s[j] = 0.0;
                }
            }
        }
    }
    s
}

#[test]
fn qp_matches_dense_nnls_reference() {
    for seed in [1u64, 2, 3] {
        let mut rng = Rng(seed * 7919);
        // Scattered map points, a short random dwell path.
        let m = 120;
        let n = 25;
        let x: Vec<f64> = (0..m).map(|_| 12.0 * rng.next()).collect();
        let y: Vec<f64> = (0..m).map(|_| 8.0 * rng.next()).collect();
        let z: Vec<f64> = (0..m)
            .map(|i| 50.0 * (0.3 * x[i]).sin() + 30.0 * (0.5 * y[i]).cos() + 20.0 * rng.next())
            .collect();
        let dx: Vec<f64> = (0..n).map(|_| -1.0 + 14.0 * rng.next()).collect();
        let dy: Vec<f64> = (0..n).map(|_| -1.0 + 10.0 * rng.next()).collect();
        let path = DwellPath::new(dx, dy).unwrap();
        let tif = GaussianTif::new(1.8, 5.0, 5.4).unwrap();
        let limits = FeedLimits {
            v_max_mm_per_min: 600.0,
            v_min_mm_per_min: 0.0,
        };
        let p = problem(&x, &y, z.clone(), &path, &tif, limits, 0.0);
        let sol = dwell::solve(&p, &qp(), &Silent).unwrap();
        assert!(sol.status.is_converged());

        // Reference: t = lb + s, s >= 0; the free piston is removed by centring (projection
        // P = I - 11^T/m), which is exact for a free constant column.
        let lb = p.bounds().lower_s().to_vec();
        let r_lb = p.removal_nm(&lb).unwrap();
        let centre = |v: &mut Vec<f64>| {
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            v.iter_mut().for_each(|e| *e -= mean);
        };
        let mut cols = Vec::new();
        for j in 0..n {
            let mut e = vec![0.0; n];
            e[j] = 1.0;
            let mut c = p.removal_nm(&e).unwrap();
            centre(&mut c);
            cols.push(c);
        }
        let mut b: Vec<f64> = z.iter().zip(&r_lb).map(|(zi, hi)| zi - hi).collect();
        centre(&mut b);
        let s = nnls(&cols, &b);
        let t_ref: Vec<f64> = lb.iter().zip(&s).map(|(l, si)| l + si).collect();
        let ref_obj = p.evaluate(&t_ref).unwrap().objective;
        let rel = (sol.objective - ref_obj).abs() / ref_obj;
        assert!(
            rel < REFERENCE_REL_TOL,
            "seed {seed}: QP {} vs NNLS {} (rel {rel:e})",
            sol.objective,
            ref_obj
        );
    }
}

#[test]
fn bounds_hold_with_v_min() {
    let (x, y, z, path, tif) = case(21, 13, 0.5, 1.0, 5);
    let limits = FeedLimits {
        v_max_mm_per_min: 3000.0,
        v_min_mm_per_min: 20.0,
    };
    let p = problem(&x, &y, z, &path, &tif, limits, 0.0);
    let sol = dwell::solve(&p, &qp(), &Silent).unwrap();
    assert!(sol.status.is_converged());
    let ds = path.ds_mm();
    for (j, &t) in sol.dwell_s.iter().enumerate() {
        let lo = ds[j] / (3000.0 / 60.0);
        let hi = ds[j] / (20.0 / 60.0);
        assert!(t >= lo && t <= hi, "point {j}: {t} not in [{lo}, {hi}]");
    }
    // The upper bound binds somewhere on this map (100 nm mean height, 8 nm/s peak).
    let at_upper = sol
        .dwell_s
        .iter()
        .zip(&ds)
        .filter(|(t, d)| (**t - *d / (20.0 / 60.0)).abs() < 1e-6)
        .count();
    assert!(at_upper > 0, "v_min never binds: the test does not test it");
}

#[test]
fn rho_lowers_total_dwell_and_piston_absorbs_constants() {
    let (x, y, z, path, tif) = case(21, 13, 0.5, 1.0, 9);
    let p0 = problem(&x, &y, z.clone(), &path, &tif, FEEDS, 0.0);
    let s0 = dwell::solve(&p0, &qp(), &Silent).unwrap();
    let p1 = problem(&x, &y, z.clone(), &path, &tif, FEEDS, 10.0);
    let s1 = dwell::solve(&p1, &qp(), &Silent).unwrap();
    let total = |t: &[f64]| t.iter().sum::<f64>();
    assert!(
        total(&s1.dwell_s) < total(&s0.dwell_s),
        "rho > 0 should lower the total dwell: {} vs {}",
        total(&s1.dwell_s),
        total(&s0.dwell_s)
    );
    assert!(s1.objective >= s0.objective * (1.0 - 1e-9));

    // Adding 37 nm to z changes only the piston (by -37 nm): same objective.
    let shifted: Vec<f64> = z.iter().map(|v| v + 37.0).collect();
    let p2 = problem(&x, &y, shifted, &path, &tif, FEEDS, 10.0);
    let s2 = dwell::solve(&p2, &qp(), &Silent).unwrap();
    let rel = (s2.objective - s1.objective).abs() / s1.objective;
    assert!(rel < 1e-6, "objective changed by {rel:e}");
    assert!(((s1.piston_nm - s2.piston_nm) - 37.0).abs() < 1e-3 * 37.0);
    let dt_total = (total(&s2.dwell_s) - total(&s1.dwell_s)).abs() / total(&s1.dwell_s);
    assert!(dt_total < 1e-4, "dwell changed by {dt_total:e}");
}

#[test]
fn min_time_cuts_dwell_within_tolerance() {
    let (x, y, z, path, tif) = case(21, 13, 0.5, 1.0, 21);
    let p = problem(&x, &y, z, &path, &tif, FEEDS, 0.0);
    let settings = Settings {
        min_time: true,
        min_time_tolerance: 1e-3,
        ..qp()
    };
    let sol = dwell::solve(&p, &settings, &Silent).unwrap();
    assert!(sol.status.is_converged());
    let mt = sol.min_time.unwrap();
    let total: f64 = sol.dwell_s.iter().sum();
    assert!(total <= mt.total_dwell_rho0_s * (1.0 + 1e-9));
    // Within the tolerance of the rho = 0 optimum (plus the solver's own accuracy).
    assert!(sol.objective <= mt.objective_rho0 * (1.0 + 1e-3 + 1e-6));
    // And no looser than necessary: a 0.1% budget is used, the dwell is strictly lower.
    assert!(total < mt.total_dwell_rho0_s);
}
