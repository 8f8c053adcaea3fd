//! A measured-style grid TIF cut hard where its rate is not zero (a Gaussian zeroed beyond
//! 3 sigma, on a grid as fine as the map) planned through the FFT operator: dwell points whose
//! tool reaches the map only through rounding (rates of 1e-13 nm/s from the grid's bilinear
//! weights at the cut) must not decide the solver's scaling or its convergence test. The plan
//! through the FFT operator agrees with the plan through the assembled `R`.

use preston::io::job::Job;
use preston::io::pipeline;
use preston::solver::observer::Silent;
use std::fmt::Write as _;
use std::path::Path;

/// The FFT plan's residual RMS against the assembled plan's: both minimise the same objective to
/// the same first-order tolerance, so they agree to a few percent of the residual.
const PLAN_AGREEMENT_REL: f64 = 0.05;

/// Writes the map (smooth waves on a 12 x 6 mm part at 0.1 mm) and the TIF (a Gaussian sigma
/// 2 mm, 15 nm/s, on a 0.1 mm grid, zeroed beyond 6 mm) into `dir`, and a job for them.
fn write_job(dir: &Path, operator: &str) -> std::path::PathBuf {
    let mut map = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..=60 {
        for ix in 0..=120 {
            let (x, y) = (0.1 * f64::from(ix), 0.1 * f64::from(iy));
            let z =
                40.0 * (0.5 * x).sin() + 25.0 * (0.8 * y + 0.3).cos() + 10.0 * (0.9 * x * y).sin();
            writeln!(map, "{x:.4},{y:.4},{z:.6}").unwrap();
        }
    }
    std::fs::write(dir.join("map.csv"), map).unwrap();
    let mut tif = String::from("x_mm,y_mm,rate_nm_per_s\n");
    for iy in -61i32..=61 {
        for ix in -61i32..=61 {
            let (x, y) = (0.1 * f64::from(ix), 0.1 * f64::from(iy));
            let r2 = x * x + y * y;
            let v = if r2 <= 36.0 + 1e-9 {
                15.0 * (-r2 / 8.0).exp()
            } else {
                0.0
            };
            writeln!(tif, "{x:.4},{y:.4},{v:.9}").unwrap();
        }
    }
    std::fs::write(dir.join("tif.csv"), tif).unwrap();
    let job = format!(
        "[map]\nfile = \"map.csv\"\n[tif]\nfile = \"tif.csv\"\n[dwell]\nraster_pitch_mm = 1.0\n\
         [machine]\nv_max_mm_per_min = 3000.0\nv_min_mm_per_min = 1.0\n\
         [solver]\ninfluence = \"point\"\noperator = \"{operator}\"\n"
    );
    let path = dir.join(format!("job_{operator}.toml"));
    std::fs::write(&path, job).unwrap();
    path
}

/// `(rms before, rms after, iterations)` of the job's plan.
fn plan(path: &Path) -> (f64, f64, usize) {
    let job = Job::load(path).unwrap();
    let prepared = pipeline::prepare(&job, path, &Silent).unwrap();
    let solved = pipeline::solve(prepared, &job, &Silent).unwrap();
    let r = &solved.report;
    (
        r.rms_before_nm,
        r.rms_after_nm,
        solved.outcome.solution.iterations,
    )
}

#[test]
fn a_hard_cut_grid_tif_plans_through_the_fft_operator_as_through_r() {
    let dir = tempfile::tempdir().unwrap();
    let (before, fft_after, fft_iterations) = plan(&write_job(dir.path(), "fft"));
    let (_, sparse_after, _) = plan(&write_job(dir.path(), "sparse"));
    eprintln!(
        "RMS {before} nm: fft {fft_after} nm in {fft_iterations} iterations, sparse {sparse_after} nm"
    );
    assert!(
        sparse_after < 0.5 * before,
        "the assembled plan corrects the map: {before} -> {sparse_after} nm"
    );
    assert!(
        (fft_after - sparse_after).abs() <= PLAN_AGREEMENT_REL * sparse_after,
        "fft plan {fft_after} nm against the assembled plan's {sparse_after} nm \
         ({fft_iterations} iterations)"
    );
}
