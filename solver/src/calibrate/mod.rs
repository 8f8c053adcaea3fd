//! Calibration: the tool that actually ran, learned from the measured removal of a whole run.
//!
//! A shop has the map measured before a run `B`, the map measured after it `A` (each with its own
//! piston and tilt, with noise, perhaps on another grid), the program that ran and the spot test
//! `f`. The measured change is modelled as
//!
//! ```text
//! d_i = B(x_i + s) - A(x_i) = r Σ_k τ_k (1 + δ (t_k - t_mid) / 3600) f_θ(x_i - p_k)
//!                             + a + b x_i + c y_i [+ p (x_i² + y_i²)] + e_i
//! ```
//!
//! with the contact motion `(p_k, τ_k, t_k)` of the program as the controller ran it, the
//! footprint's figures `θ` ([`tool`]: rate, width, centroid offset, ellipticity, skew), the
//! rate's drift `δ` per hour of program time, the nuisance piston and tilt (and power) that each
//! interferometer measurement drops, a shift `s` between the two measurements (it moves the whole
//! map, also where nothing was removed; a tool offset moves only the removal, so the two separate
//! where the map has structure) and the noise `e`. Where the run removed most of the structure,
//! a shift takes up what the tool's model misses instead: the run is fitted with and without `s`,
//! and `s` is kept only where it lowers the fit's RMS by [`MAP_SHIFT_MIN_GAIN`] ([`MapShiftTest`]).
//!
//! The fit is a maximum a posteriori estimate by variable-projection Levenberg-Marquardt
//! ([`fit`]): the linear figures (rate, rate times drift, nuisance) are solved for at every step,
//! the others by damped Gauss-Newton with a forward-difference Jacobian through the lattice
//! convolution of [`forward`]. Every figure but the rate carries the spot test's uncertainty as a
//! Gaussian prior about its spot-test value ([`Prior`]), a pseudo-observation
//! `s (θ_j - θ_j⁰) / σ_j` beside the data, so a figure the run cannot determine stays at the spot
//! test's value instead of wandering along a valley of the fit. The covariance is `s² (JᵀJ)⁻¹`
//! over data and priors, `s²` the residual's variance per point inflated by its own correlation
//! between neighbouring points (Bartlett's factor `Π (1 + ρ₁) / (1 - ρ₁)` over the axes), so a
//! structured misfit is not counted as independent evidence. A figure whose posterior standard
//! deviation is more than [`UNDETERMINED_FRACTION`] of its prior's is reported as not determined
//! by the run (held near its spot-test value), with the figure it is confounded with: for example
//! a drift against the tilt on a raster whose rows run in time across the part.
//!
//! Where the data support it, a free-form correction of the footprint ([`freeform`]) takes up
//! what the parametric figures leave.

pub mod change;
pub mod expect;
mod fit;
pub mod forward;
mod freeform;
pub mod tool;

pub use change::{GriddedMap, MeasuredChange};
pub use expect::{
    expected_reading, map_noise_rms_nm, Expected, FloorCause, ReadingParts, ToolUncertainty,
};
pub use forward::{mid_times_s, ContactMotion, LatticeRemoval};
pub use freeform::FreeformCorrection;
pub use tool::{SpotFootprint, ToolFigures, TransformedTif};

use crate::error::{Error, Result};
use crate::status::Status;
use crate::tif::GridTif;
use serde::{Deserialize, Serialize};

/// What a calibration fits, and how.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationSettings {
    /// Fit the footprint's shape (ellipticity and skew) besides its rate, width and offset.
    pub fit_shape: bool,
    /// Fit the rate's drift over the run's program time.
    pub fit_drift: bool,
    /// Fit a shift between the two measurements (a nuisance).
    pub fit_map_shift: bool,
    /// Fit a nuisance power term `p (x² + y²)` besides piston and tilt.
    pub fit_power: bool,
    /// Offer a free-form correction of the footprint where the data support it.
    pub freeform: bool,
    /// Pitch of the convolution lattice, mm (default: the footprint's second-moment radius over
    /// 10, made a whole fraction of the map's pitch).
    pub lattice_pitch_mm: Option<f64>,
    /// Largest number of Levenberg-Marquardt steps per fit.
    pub max_iterations: usize,
    /// The spot test's uncertainty: the prior of every figure.
    pub prior: Prior,
}

/// How much the rate's change over a run is known before it: one standard deviation, relative,
/// from the run's first contact to its last. The spot test's uncertainty of the drift (the
/// calibration's prior), and the scatter of the next run's drift about a calibrated one (a
/// calibration measures the drift of the run that was, not of the next).
pub const DRIFT_SIGMA_PER_RUN: f64 = 0.05;

/// A shift between the two measurements is kept only where it lowers the fit's RMS by at least
/// this fraction ([`MapShiftTest`]).
pub const MAP_SHIFT_MIN_GAIN: f64 = 0.05;

/// Posterior standard deviation, as a fraction of the prior's, above which a figure counts as
/// not determined by the run.
pub const UNDETERMINED_FRACTION: f64 = 0.7;

/// How well the spot test knows the tool before a run: one standard deviation of each figure
/// about its spot-test value. The same figures a plan's expected result draws from before any
/// calibration.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Prior {
    /// Relative standard deviation of the rate (not a prior of the fit: the rate is always
    /// determined; the expected result of an uncalibrated plan draws from it).
    pub rate_sigma: f64,
    /// Relative standard deviation of the width.
    pub width_sigma: f64,
    /// Standard deviation of the centroid offset along each axis, mm.
    pub offset_sigma_mm: f64,
    /// Standard deviation of the ellipticity and of the skew.
    pub shape_sigma: f64,
    /// Standard deviation of the rate's change over one run (relative, from the run's first
    /// contact to its last).
    pub drift_sigma_per_run: f64,
    /// Standard deviation of the shift between two measurements, mm (default: half a pixel of
    /// the map before the run).
    pub map_shift_sigma_mm: Option<f64>,
}

impl Default for Prior {
    fn default() -> Self {
        Self {
            rate_sigma: 0.05,
            width_sigma: 0.05,
            offset_sigma_mm: 0.2,
            shape_sigma: 0.1,
            drift_sigma_per_run: DRIFT_SIGMA_PER_RUN,
            map_shift_sigma_mm: None,
        }
    }
}

impl Prior {
    /// Checks that every standard deviation is positive and finite.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("rate_sigma", self.rate_sigma),
            ("width_sigma", self.width_sigma),
            ("offset_sigma_mm", self.offset_sigma_mm),
            ("shape_sigma", self.shape_sigma),
            ("drift_sigma_per_run", self.drift_sigma_per_run),
            ("map_shift_sigma_mm", self.map_shift_sigma_mm.unwrap_or(1.0)),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::invalid(
                    format!("prior {name}"),
                    format!("must be positive and finite, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

impl Default for CalibrationSettings {
    fn default() -> Self {
        Self {
            fit_shape: true,
            fit_drift: true,
            fit_map_shift: true,
            fit_power: false,
            freeform: true,
            lattice_pitch_mm: None,
            max_iterations: 60,
            prior: Prior::default(),
        }
    }
}

impl CalibrationSettings {
    /// Checks the settings.
    pub fn validate(&self) -> Result<()> {
        if let Some(p) = self.lattice_pitch_mm {
            if !(p.is_finite() && p > 0.0) {
                return Err(Error::invalid(
                    "calibration lattice_pitch_mm",
                    format!("must be positive, got {p}"),
                ));
            }
        }
        if self.max_iterations == 0 {
            return Err(Error::invalid(
                "calibration max_iterations",
                "must be at least 1",
            ));
        }
        self.prior.validate()
    }
}

/// A figure the run could not determine: it stays near its spot-test value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldFigure {
    /// The figure's name ([`ToolFigures::NAMES`], or `map_shift_x_mm`, `map_shift_y_mm`).
    pub name: String,
    /// Why: how little the run narrowed it and the figure it is confounded with.
    pub reason: String,
}

/// Whether the data support a shift between the two measurements: the calibration fitted with and
/// without one. Where the run removed most of the map's structure, a shift of the after map and
/// an offset or a change of shape of the tool change the data nearly alike, and a shift fitted
/// there takes up what the tool's model misses (placing the tool wrongly for the next run); a
/// shift is therefore kept only where it lowers the fit's RMS by at least [`MAP_SHIFT_MIN_GAIN`],
/// as a part put back visibly off does. Otherwise the maps are taken to be in one frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MapShiftTest {
    /// Whether the fit with the shift is the calibration.
    pub kept: bool,
    /// RMS of the fit's residual with the shift, nm (`None`: that fit failed).
    pub fit_rms_with_nm: Option<f64>,
    /// RMS of the fit's residual without it, nm (`None`: that fit failed).
    pub fit_rms_without_nm: Option<f64>,
}

/// The nuisance terms of the measured change: what each interferometer measurement drops.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Nuisance {
    /// Piston, nm.
    pub piston_nm: f64,
    /// Tilt along x, nm/mm.
    pub tilt_x_nm_per_mm: f64,
    /// Tilt along y, nm/mm.
    pub tilt_y_nm_per_mm: f64,
    /// Power, nm/mm² (zero unless fitted).
    pub power_nm_per_mm2: f64,
    /// Shift between the two measurements along x, mm.
    pub map_shift_x_mm: f64,
    /// Shift along y, mm.
    pub map_shift_y_mm: f64,
}

/// The correlation matrix of the fitted figures and nuisance terms.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Correlation {
    /// Names of the rows and columns.
    pub names: Vec<String>,
    /// Row-major correlations.
    pub matrix: Vec<Vec<f64>>,
}

/// A calibration: the tool that ran, with its uncertainty and how well it explains the run.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// How the fit ended.
    pub status: Status,
    /// Levenberg-Marquardt steps taken (over every refit).
    pub iterations: usize,
    /// The figures (held figures at their spot-test values).
    pub figures: ToolFigures,
    /// Their standard deviations (zero for held figures).
    pub sigma: ToolFigures,
    /// Figures the run could not determine.
    pub held: Vec<HeldFigure>,
    /// Correlations of the fitted figures and nuisance terms.
    pub correlation: Correlation,
    /// Nuisance terms.
    pub nuisance: Nuisance,
    /// RMS of the measured change, nuisance removed, nm.
    pub measured_change_rms_nm: f64,
    /// RMS of the fit's residual, nm.
    pub fit_rms_nm: f64,
    /// Metrology noise of one map estimated from the residual's neighbour differences, nm RMS.
    pub noise_rms_nm: f64,
    /// Factor by which the residual's correlation inflates the figures' variances.
    pub variance_inflation: f64,
    /// Points of the after map used.
    pub points: usize,
    /// Points skipped (dropouts, edges).
    pub skipped: usize,
    /// Pitch of the convolution lattice, mm.
    pub lattice_pitch_mm: f64,
    /// Contact time of the run, s.
    pub contact_time_s: f64,
    /// Program time at which the drift has no effect (the contact-time-weighted mean), s.
    pub mid_time_s: f64,
    /// The free-form correction of the footprint, when offered.
    pub freeform: Option<FreeformCorrection>,
    /// The test of a shift between the measurements, when the settings fit one.
    pub map_shift: Option<MapShiftTest>,
    /// The calibrated footprint at the run's mean rate: the figures applied to the spot test,
    /// plus the free-form correction where applied.
    pub tif: GridTif,
    /// x of the points, mm.
    pub x_mm: Vec<f64>,
    /// y of the points, mm.
    pub y_mm: Vec<f64>,
    /// Measured removal at the points, nuisance removed, nm.
    pub measured_removal_nm: Vec<f64>,
    /// Removal the calibrated tool gives at the points, nm.
    pub simulated_removal_nm: Vec<f64>,
}

/// Calibrates the tool from one run: `change` the measured change, `motion` the contact motion
/// of the program as the controller ran it, `spot` the spot test (see the module
/// documentation).
pub fn calibrate(
    change: &MeasuredChange,
    motion: &ContactMotion,
    spot: &SpotFootprint,
    settings: &CalibrationSettings,
) -> Result<Calibration> {
    settings.validate()?;
    motion.validate()?;
    if !settings.fit_map_shift {
        return fit::run(change, motion, spot, settings);
    }
    let fixed = CalibrationSettings {
        fit_map_shift: false,
        ..settings.clone()
    };
    // The two fits are independent: each gives the same figures on any thread count.
    let (without, with) = rayon::join(
        || fit::run(change, motion, spot, &fixed),
        || fit::run(change, motion, spot, settings),
    );
    let rms = |fit: &Result<Calibration>| fit.as_ref().ok().map(|c| c.fit_rms_nm);
    let (rms_with, rms_without) = (rms(&with), rms(&without));
    let kept = match (rms_with, rms_without) {
        (Some(w), Some(wo)) => w <= (1.0 - MAP_SHIFT_MIN_GAIN) * wo,
        // A shift large enough that the change without it does not look like the removal.
        (Some(_), None) => true,
        _ => false,
    };
    let mut c = if kept { with? } else { without? };
    let test = MapShiftTest {
        kept,
        fit_rms_with_nm: rms_with,
        fit_rms_without_nm: rms_without,
    };
    c.map_shift = Some(test);
    Ok(c)
}
