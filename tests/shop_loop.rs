//! The measure-calibrate-plan-polish loop on a virtual shop whose tool is not the spot test: a
//! rate, width and offset off it, a linear skew the calibration's model does not contain, a drift
//! within each run and a rate that wanders from run to run. The loop that calibrates each run
//! recovers the true footprint's figures and reaches the measurement floor sooner than the loop
//! that learns the rate alone.

use preston::solver::calibrate::SpotFootprint;
use preston::solver::influence::model::surface::TifFrame;
use preston::solver::iterate::{
    run_virtual, Disturbances, FormErrorModel, LoopOutcome, LoopSettings, ShopTool, VirtualPart,
};
use preston::solver::map::BoundingBox;
use preston::solver::observer::Silent;
use preston::solver::surface::{Plane, Surface};
use preston::solver::tif::{GaussianTif, Tif};

/// Interferometer noise, nm RMS.
const NOISE_NM: f64 = 0.3;
/// Rate factor recovered within this (relative); the rate also wanders by the walk's step.
const RATE_TOL: f64 = 0.02;
/// Width factor recovered within this (relative).
const WIDTH_TOL: f64 = 0.02;
/// Centroid recovered within this, mm.
const OFFSET_TOL_MM: f64 = 0.03;

fn tif() -> Tif {
    Tif::Gaussian(GaussianTif::new(2.0, 10.0, 6.0).expect("gaussian"))
}

fn tool() -> ShopTool {
    ShopTool {
        rate_factor: 1.06,
        width_factor: 1.05,
        offset_x_mm: 0.2,
        offset_y_mm: -0.12,
        skew: 0.1,
        skew_angle_deg: 30.0,
        drift_per_run: 0.03,
        ..ShopTool::default()
    }
}

fn part() -> VirtualPart {
    VirtualPart {
        surface: Surface::Plane(Plane {}),
        form_error: FormErrorModel {
            rms_nm: 60.0,
            max_cycles: 2.0,
            ..FormErrorModel::default()
        },
        rotation_arcsec: [0.0; 3],
        translation_um: [0.0; 3],
        measurement_noise_nm: NOISE_NM,
    }
}

fn settings(calibrate: bool) -> LoopSettings {
    LoopSettings {
        aperture: BoundingBox {
            x_min_mm: -15.0,
            x_max_mm: 15.0,
            y_min_mm: -15.0,
            y_max_mm: 15.0,
        },
        grid: [31, 31],
        max_iterations: 2,
        disturbances: Disturbances {
            tool: tool(),
            rate_walk_per_run: 0.01,
            ..Disturbances::default()
        },
        calibrate,
        tif_frame: TifFrame::MachineX,
        min_gain_nm: 0.0,
        ..LoopSettings::default()
    }
}

fn run(calibrate: bool) -> LoopOutcome {
    run_virtual(&part(), &tif(), &settings(calibrate), &Silent).expect("loop")
}

#[test]
fn the_calibrating_loop_learns_the_tool_and_beats_the_rate_alone() {
    let calibrated = run(true);
    assert!(
        calibrated.not_converged.is_empty(),
        "{:?}",
        calibrated.not_converged
    );
    let rms: Vec<f64> = calibrated.records.iter().map(|r| r.rms_nm).collect();
    assert_eq!(rms.len(), 3, "{rms:?}");

    // Run 2 was planned with the calibration of run 1: the true footprint's figures (its moments
    // against the spot test's, the skew's shift of the centroid included).
    let spot = SpotFootprint::of_tif(&tif()).expect("spot");
    let truth = tool().figures(&spot);
    let r = &calibrated.records[1];
    let rate = r.rate_factor_estimate.expect("rate");
    let width = r.width_factor_estimate.expect("width");
    let (ox, oy) = (
        r.offset_x_mm_estimate.expect("offset x"),
        r.offset_y_mm_estimate.expect("offset y"),
    );
    assert!(
        (rate / truth.rate_factor - 1.0).abs() < RATE_TOL,
        "rate {rate} against {truth:?}"
    );
    assert!(
        (width / truth.width_factor - 1.0).abs() < WIDTH_TOL,
        "width {width} against {truth:?}"
    );
    assert!(
        (ox - truth.offset_x_mm).abs() < OFFSET_TOL_MM
            && (oy - truth.offset_y_mm).abs() < OFFSET_TOL_MM,
        "offset ({ox}, {oy}) against {truth:?}"
    );
    assert!(r.drift_per_hour_estimate.is_some());

    // The loop that learns the rate alone plans run 2 with the spot test's footprint at the
    // learned rate: the offset and width it does not know leave more on the part.
    let rate_only = run(false);
    let plain: Vec<f64> = rate_only.records.iter().map(|r| r.rms_nm).collect();
    assert_eq!(rms[0], plain[0]);
    assert!(
        rms[2] < plain[2],
        "after run 2: calibrated {rms:?} against rate-only {plain:?}"
    );
    // Calibrated, run 2 lands within twice the measurement's noise floor, and its prediction
    // (the plan's residual, the uncorrectable band, the rate's spread) is within 30% of what is
    // measured.
    assert!(rms[2] < 2.0 * NOISE_NM, "{rms:?}");
    let predicted = r.predicted_rms_nm.expect("prediction");
    eprintln!(
        "calibrated {rms:?}, rate-only {plain:?}; run 1's calibration: rate {rate}, width \
         {width}, centroid ({ox}, {oy}) mm against {truth:?}; run 2 predicted {predicted} nm"
    );
    assert!(
        (predicted / rms[2] - 1.0).abs() < 0.3,
        "predicted {predicted} nm, measured {} nm",
        rms[2]
    );
}

/// A calibrating loop refuses a curved part and a path-tangent frame: the calibration states the
/// footprint in the machine's x, y.
#[test]
fn the_calibrating_loop_states_its_limits() {
    let mut s = settings(true);
    s.tif_frame = TifFrame::PathTangent;
    let e = run_virtual(&part(), &tif(), &s, &Silent).unwrap_err();
    assert!(e.to_string().contains("machine"), "{e}");
}
