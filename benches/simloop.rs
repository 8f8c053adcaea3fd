//! One iteration of the polishing loop at the published freeform case's sizes: a
//! 51 x 51 measured grid and a 127 x 113 dwell path, plots included. Target: under 5 s on 2 cores.
//!
//! `cargo bench --bench simloop` (one timed run per solver choice; not a criterion bench: a
//! run takes seconds, and the figure wanted is the wall-clock time of the whole iteration).

use preston::io::simulation::write_loop;
use preston::solver::dwell::{FirstOrderMethod, Settings, SolverChoice};
use preston::solver::iterate::{
    run_virtual, Disturbances, FormErrorModel, LoopSettings, VirtualPart, LOOP_SOLVE_TOLERANCE,
};
use preston::solver::map::BoundingBox;
use preston::solver::observer::Silent;
use preston::solver::tif::{GaussianTif, Tif};
use std::time::Instant;

fn main() {
    if !std::env::args().any(|a| a == "--bench") {
        return;
    }
    let surface = preston::io::surface::read_surface(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/design_freeform.json"),
    )
    .expect("surface");
    let part = VirtualPart {
        surface,
        form_error: FormErrorModel::default(),
        rotation_arcsec: [20.0, -15.0, 30.0],
        translation_um: [5.0, -8.0, 3.0],
        measurement_noise_nm: 0.5,
    };
    let tif = Tif::Gaussian(GaussianTif::new(2.0, 10.0, 6.0).expect("tif"));
    // The loop's default is `auto` (the first-order solver, L-BFGS, at this size) at tolerance
    // LOOP_SOLVE_TOLERANCE; the other rows show looser and tighter solves, FISTA, Newton-CG and
    // the QP.
    for (choice, method, tolerance) in [
        (
            SolverChoice::Auto,
            FirstOrderMethod::default(),
            LOOP_SOLVE_TOLERANCE,
        ),
        (SolverChoice::FirstOrder, FirstOrderMethod::Lbfgs, 1e-5),
        (SolverChoice::FirstOrder, FirstOrderMethod::Fista, 1e-4),
        (SolverChoice::FirstOrder, FirstOrderMethod::Fista, 1e-3),
        (SolverChoice::FirstOrder, FirstOrderMethod::Fista, 1e-5),
        (SolverChoice::FirstOrder, FirstOrderMethod::NewtonCg, 1e-4),
        (SolverChoice::Qp, FirstOrderMethod::Fista, 1e-4),
    ] {
        // Aperture 51 x 44 mm, path margin 6 mm, pitch 0.5 mm: 127 x 113 dwell points.
        let settings = LoopSettings {
            aperture: BoundingBox {
                x_min_mm: -25.5,
                x_max_mm: 25.5,
                y_min_mm: -22.0,
                y_max_mm: 22.0,
            },
            grid: [51, 51],
            path_pitch_mm: 0.5,
            max_iterations: 1,
            disturbances: Disturbances {
                tif_rate_error: 0.03,
                positioning_noise_mm: 0.02,
                ..Disturbances::default()
            },
            solver: Settings {
                solver: choice,
                tolerance,
                first_order_tolerance: tolerance,
                first_order_method: method,
                ..Settings::default()
            },
            ..LoopSettings::default()
        };
        let dir = tempfile::tempdir().expect("temp dir");
        let start = Instant::now();
        let outcome = run_virtual(&part, &tif, &settings, &Silent).expect("loop");
        let loop_s = start.elapsed().as_secs_f64();
        let plots_start = Instant::now();
        write_loop(&outcome, dir.path(), true, Default::default()).expect("outputs");
        let plots_s = plots_start.elapsed().as_secs_f64();
        let run = outcome.last_run.as_ref().expect("one run");
        // The contract's objective at the optimal piston: 0.5 ||r||^2 + rho sum(t).
        let objective = 0.5 * run.measured.len() as f64 * run.predicted_rms_nm().powi(2)
            + settings.rho * run.dwell_s.iter().sum::<f64>();
        println!(
            "simloop/{choice:?}/{method:?}/tol {tolerance:e}: {} map points, {} dwell points; RMS {:.2} -> {:.2} nm (predicted {:.2} nm, dwell {:.0} s, objective {:.1} nm^2); loop {:.2} s + outputs and plots {:.2} s = {:.2} s",
            run.measured.len(),
            run.path.len(),
            outcome.records[0].rms_nm,
            outcome.records[1].rms_nm,
            run.predicted_rms_nm(),
            run.dwell_s.iter().sum::<f64>(),
            objective,
            loop_s,
            plots_s,
            loop_s + plots_s
        );
    }
}
