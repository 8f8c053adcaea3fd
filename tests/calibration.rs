//! Calibration of the tool from a run's measured removal: the figures of a known true tool are
//! recovered from synthetic before and after maps (the removal summed directly along the contact
//! samples, an independent reference for the fit's lattice convolution), within the tolerances a
//! shop needs and within three standard deviations.

use preston::solver::calibrate::{
    calibrate, CalibrationSettings, ContactMotion, MeasuredChange, SpotFootprint,
};
use preston::solver::map::HeightMap;
use preston::solver::rng::SplitMix64;
use preston::solver::tif::{GaussianTif, GridTif, InfluenceFunction};

/// Rate factor recovered within this (relative).
const RATE_TOL: f64 = 0.005;
/// Width factor recovered within this (relative).
const WIDTH_TOL: f64 = 0.01;
/// Centroid offset recovered within this, mm.
const OFFSET_TOL_MM: f64 = 0.02;
/// The truth lies within this many standard deviations.
const SIGMAS: f64 = 3.0;

const SIGMA_MM: f64 = 1.4;
const PEAK_NM_PER_S: f64 = 12.0;

fn spot() -> SpotFootprint {
    let g = GaussianTif::new(SIGMA_MM, PEAK_NM_PER_S, 4.0 * SIGMA_MM).expect("gaussian");
    let pitch = 0.1;
    let n = (8.0 * SIGMA_MM / pitch).round() as usize + 1;
    let x0 = -(n as f64 - 1.0) / 2.0 * pitch;
    let rates = (0..n * n)
        .map(|k| g.rate_nm_per_s(x0 + (k % n) as f64 * pitch, x0 + (k / n) as f64 * pitch))
        .collect();
    SpotFootprint::new(GridTif::new(x0, x0, pitch, pitch, n, n, rates).expect("grid"))
        .expect("spot")
}

/// A form error, nm: smooth terms the run corrects and fine ripples (periods 3.9-6.3 mm, eight pixels or more) it
/// cannot, as real maps carry.
fn form_nm(x: f64, y: f64) -> f64 {
    60.0 * (0.21 * x).sin() * (0.33 * y + 0.4).cos()
        + 40.0 * (0.13 * x + 0.17 * y).cos()
        + 0.08 * x * x
        + 3.0 * (1.5 * x + 0.6 * y).sin()
        + 2.0 * (1.0 * x - 1.2 * y + 0.7).cos()
        + 1.5 * (1.5 * y + 0.3 * x).sin()
}

/// A serpentine raster along x over the map and a margin, its dwell varying on scales from the
/// part's to a few TIF widths, as a plan's does; samples every 0.1 mm with their program times.
fn motion() -> ContactMotion {
    let mut m = ContactMotion::default();
    let mut t = 0.0;
    let (x0, x1, y0, y1, pitch, step) = (-5.0, 35.0, -5.0, 21.0, 0.5, 0.1);
    let rows = ((y1 - y0) / pitch) as usize + 1;
    let cols = ((x1 - x0) / step) as usize + 1;
    for r in 0..rows {
        let y = y0 + r as f64 * pitch;
        for c in 0..cols {
            let c = if r % 2 == 0 { c } else { cols - 1 - c };
            let x = x0 + c as f64 * step;
            let dwell = 0.02
                * (1.0
                    + 0.5 * (0.25 * x).sin() * (0.31 * y).cos()
                    + 0.3 * (1.1 * x + 0.4 * y).sin()
                    + 0.15 * (0.9 * y - 0.5 * x).cos());
            m.x_mm.push(x);
            m.y_mm.push(y);
            m.dwell_s.push(dwell);
            m.time_s.push(t + dwell / 2.0);
            t += dwell;
        }
    }
    m
}

/// The true tool: a Gaussian `width` times wider, `rate` times the volume, centred at `offset`,
/// drifting by `drift` per hour about the run's middle.
struct Truth {
    rate: f64,
    width: f64,
    offset: (f64, f64),
    drift: f64,
}

/// Removal of the true tool at the points, summed directly over the samples.
fn removal(truth: &Truth, motion: &ContactMotion, x: &[f64], y: &[f64]) -> Vec<f64> {
    let sigma = SIGMA_MM * truth.width;
    let tif = GaussianTif::new(
        sigma,
        PEAK_NM_PER_S * truth.rate / truth.width.powi(2),
        4.5 * sigma,
    )
    .expect("true tif");
    let mid = motion.mid_time_s();
    x.iter()
        .zip(y)
        .map(|(&px, &py)| {
            (0..motion.x_mm.len())
                .map(|k| {
                    motion.dwell_s[k]
                        * (1.0 + truth.drift * (motion.time_s[k] - mid) / 3600.0)
                        * tif.rate_nm_per_s(
                            px - motion.x_mm[k] - truth.offset.0,
                            py - motion.y_mm[k] - truth.offset.1,
                        )
                })
                .sum()
        })
        .collect()
}

/// The map grid, 30 x 16 mm at 0.5 mm.
fn grid(shift: (f64, f64)) -> (Vec<f64>, Vec<f64>) {
    (0..61 * 33)
        .map(|k| {
            (
                (k % 61) as f64 * 0.5 + shift.0,
                (k / 61) as f64 * 0.5 + shift.1,
            )
        })
        .unzip()
}

/// Before and after maps with their own piston, tilt and noise; the after map measured in a
/// frame shifted by `frame_shift` (the part moved between the measurements).
fn maps(
    truth: &Truth,
    motion: &ContactMotion,
    frame_shift: (f64, f64),
    noise_nm: f64,
) -> (HeightMap, HeightMap) {
    let mut rng = SplitMix64::new(7);
    let (bx, by) = grid((0.0, 0.0));
    let before: Vec<f64> = bx
        .iter()
        .zip(&by)
        .map(|(&x, &y)| form_nm(x, y) + 3.0 + 0.2 * x - 0.1 * y + noise_nm * rng.normal())
        .collect();
    // After: the same part seen at points whose part coordinates are x + frame_shift.
    let (ax, ay) = grid((0.0, 0.0));
    let (px, py): (Vec<f64>, Vec<f64>) = ax
        .iter()
        .zip(&ay)
        .map(|(x, y)| (x + frame_shift.0, y + frame_shift.1))
        .unzip();
    let h = removal(truth, motion, &px, &py);
    let after: Vec<f64> = px
        .iter()
        .zip(&py)
        .zip(&h)
        .map(|((&x, &y), h)| form_nm(x, y) - h - 7.0 - 0.3 * x + 0.25 * y + noise_nm * rng.normal())
        .collect();
    (
        HeightMap::new(bx, by, before).expect("before"),
        HeightMap::new(ax, ay, after).expect("after"),
    )
}

fn check(name: &str, value: f64, sigma: f64, truth: f64, tol: f64) {
    assert!(
        (value - truth).abs() <= tol,
        "{name}: {value} against the true {truth} (tolerance {tol})"
    );
    assert!(
        (value - truth).abs() <= SIGMAS * sigma,
        "{name}: {value} +- {sigma} leaves the true {truth} beyond {SIGMAS} sigma"
    );
}

/// The rate and width against the truth, within the shop's tolerances and 3 sigma.
fn check_rate_and_width(c: &preston::solver::calibrate::Calibration, truth: &Truth) {
    let (f, s) = (c.figures, c.sigma);
    check(
        "rate_factor",
        f.rate_factor,
        s.rate_factor,
        truth.rate,
        RATE_TOL * truth.rate,
    );
    check(
        "width_factor",
        f.width_factor,
        s.width_factor,
        truth.width,
        WIDTH_TOL,
    );
}

/// The centroid offset against the truth, within the shop's tolerance and 3 sigma.
fn check_offset(c: &preston::solver::calibrate::Calibration, truth: &Truth) {
    let (f, s) = (c.figures, c.sigma);
    check(
        "offset_x_mm",
        f.offset_x_mm,
        s.offset_x_mm,
        truth.offset.0,
        OFFSET_TOL_MM,
    );
    check(
        "offset_y_mm",
        f.offset_y_mm,
        s.offset_y_mm,
        truth.offset.1,
        OFFSET_TOL_MM,
    );
}

#[test]
fn the_true_tool_is_recovered_from_one_run() {
    let motion = motion();
    let truth = Truth {
        rate: 1.07,
        width: 1.04,
        offset: (0.15, -0.12),
        drift: 0.0,
    };
    let (before, after) = maps(&truth, &motion, (0.0, 0.0), 0.3);
    let change = MeasuredChange::new(&before, &after).expect("change");
    let settings = CalibrationSettings {
        fit_drift: false,
        ..CalibrationSettings::default()
    };
    let c = calibrate(&change, &motion, &spot(), &settings).expect("calibration");
    assert!(c.status.is_converged(), "{:?}", c.status);
    // No shift between the maps: none is kept.
    let test = c.map_shift.expect("a shift tried");
    assert!(!test.kept, "{test:?}");
    let f = c.figures;
    check_rate_and_width(&c, &truth);
    check_offset(&c, &truth);
    // The residual is the noise of the two maps: sqrt(2) x 0.3 nm, and the noise estimate one map's.
    assert!(c.fit_rms_nm < 0.6, "fit RMS {} nm", c.fit_rms_nm);
    assert!(
        (c.noise_rms_nm - 0.3).abs() < 0.06,
        "noise {} nm",
        c.noise_rms_nm
    );
    // The calibrated grid carries the figures: its volume ratio is the rate factor.
    let v0 = spot().grid().volume_rate_mm3_per_s();
    let v1 = c.tif.volume_rate_mm3_per_s();
    assert!(
        (v1 / v0 / f.rate_factor - 1.0).abs() < 0.01,
        "volume ratio {}",
        v1 / v0
    );
}

#[test]
fn a_shift_between_the_measurements_is_not_a_tool_offset() {
    let motion = motion();
    let truth = Truth {
        rate: 0.95,
        width: 0.97,
        offset: (-0.1, 0.08),
        drift: 0.0,
    };
    let frame = (0.12, -0.07);
    let (before, after) = maps(&truth, &motion, frame, 0.3);
    let change = MeasuredChange::new(&before, &after).expect("change");
    let c =
        calibrate(&change, &motion, &spot(), &CalibrationSettings::default()).expect("calibration");
    check_rate_and_width(&c, &truth);
    // The shift is kept: it lowers the fit's RMS far more than the 5% that keeps one.
    let test = c.map_shift.expect("a shift tried");
    assert!(test.kept, "{test:?}");
    // The after map's points are part points x + frame: the before map is read at x + frame.
    assert!(
        (c.nuisance.map_shift_x_mm - frame.0).abs() < 0.02,
        "{:?}",
        c.nuisance
    );
    assert!(
        (c.nuisance.map_shift_y_mm - frame.1).abs() < 0.02,
        "{:?}",
        c.nuisance
    );
    check_offset(&c, &truth);
}

#[test]
fn the_drift_over_the_run_is_learned_or_said_to_be_undetermined() {
    let motion = motion();
    let truth = Truth {
        rate: 1.03,
        width: 1.02,
        offset: (0.05, 0.1),
        drift: 0.04 * 3600.0 / motion.span_s(),
    };
    let (before, after) = maps(&truth, &motion, (0.0, 0.0), 0.3);
    let change = MeasuredChange::new(&before, &after).expect("change");
    let c =
        calibrate(&change, &motion, &spot(), &CalibrationSettings::default()).expect("calibration");
    let (f, s) = (c.figures, c.sigma);
    check_rate_and_width(&c, &truth);
    if let Some(h) = c.held.iter().find(|h| h.name == "drift_per_hour") {
        assert!(h.reason.contains("confounded"), "{}", h.reason);
    }
    assert!(
        (f.drift_per_hour - truth.drift).abs() <= SIGMAS * s.drift_per_hour,
        "drift {} +- {} against {}",
        f.drift_per_hour,
        s.drift_per_hour,
        truth.drift
    );
}
