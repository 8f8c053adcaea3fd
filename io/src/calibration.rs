//! `preston calibrate`: reads a run (the maps before and after it, the program that ran, the
//! spot-test TIF), executes the program as the controller ran it, fits the tool
//! ([`preston_solver::calibrate`]) and writes `calibration.json`, the calibrated `tif.csv` and the
//! figures. `solve --calibration` reads `calibration.json` back ([`read_calibration`]).

use crate::atomic::{commit_all, Staged};
use crate::error::{Error, Result};
use crate::figures::FigureStyle;
use crate::metrology::MapSource;
use crate::plots::stage_map_plot;
use crate::simulation::read_program;
use crate::writers::{stage_columns_csv, stage_json};
use preston_solver::calibrate::{
    calibrate, Calibration, CalibrationSettings, ContactMotion, Correlation, FreeformCorrection,
    HeldFigure, MapShiftTest, MeasuredChange, Nuisance, SpotFootprint, ToolFigures,
};
use preston_solver::machine::gcode::dialect::Dialect;
use preston_solver::machine::gcode::motion::{execute, sample_contact, Kinematics};
use preston_solver::tif::{GridTif, Tif};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Name of the calibrated TIF written beside `calibration.json`.
pub const CALIBRATED_TIF: &str = "tif.csv";
/// Name of the calibration record.
pub const CALIBRATION_JSON: &str = "calibration.json";
/// Removal samples per footprint radius along the executed motion.
const SAMPLES_PER_RADIUS: f64 = 32.0;

/// What one calibration reads.
#[derive(Debug, Clone)]
pub struct CalibrationInputs {
    /// The map measured before the run.
    pub before: MapSource,
    /// The map measured after it.
    pub after: MapSource,
    /// The program that ran.
    pub program: PathBuf,
    /// Its dialect (default: its header's, else ISO).
    pub dialect: Option<Dialect>,
    /// The spot test.
    pub tif: Tif,
    /// The spot test's file, for the record.
    pub tif_file: Option<PathBuf>,
    /// How the controller ran the program.
    pub kinematics: Kinematics,
    /// Largest removal sample along the motion, mm (default: the footprint radius / 32).
    pub sample_step_mm: Option<f64>,
    /// What to fit.
    pub settings: CalibrationSettings,
}

/// A calibration and what it was made from.
#[derive(Debug, Clone)]
pub struct Calibrated {
    /// The fit.
    pub calibration: Calibration,
    /// The record written as `calibration.json`.
    pub record: CalibrationRecord,
}

/// A TIF as a grid ([`preston_solver::calibrate::tool::tif_grid`]).
pub fn tif_grid(tif: &Tif) -> Result<GridTif> {
    preston_solver::calibrate::tool::tif_grid(tif).map_err(Error::Solver)
}

/// The contact motion of `program` executed under `kinematics`, sampled every `step_mm`.
pub fn contact_motion(
    program: &preston_solver::machine::gcode::program::Program,
    kinematics: Kinematics,
    step_mm: f64,
) -> preston_solver::Result<(ContactMotion, f64)> {
    let executed = execute(program, kinematics)?;
    let samples = sample_contact(program, &executed, step_mm)?;
    Ok((
        ContactMotion {
            x_mm: samples.x_mm,
            y_mm: samples.y_mm,
            dwell_s: samples.time_s,
            time_s: samples.at_s,
        },
        executed.total_time_s,
    ))
}

/// Reads the run and calibrates the tool.
pub fn run_calibration(inputs: &CalibrationInputs) -> Result<Calibrated> {
    inputs.settings.validate().map_err(Error::Solver)?;
    let before_file = inputs.before.file.clone().unwrap_or_default();
    let after_file = inputs.after.file.clone().unwrap_or_default();
    let before = inputs.before.read()?.map;
    let after = inputs.after.read()?.map;
    let program = read_program(&inputs.program, inputs.dialect)?;
    let grid = tif_grid(&inputs.tif)?;
    let spot = SpotFootprint::new(grid).map_err(|e| match &inputs.tif_file {
        Some(f) => Error::engine(f, e),
        None => Error::Solver(e),
    })?;
    let step = inputs
        .sample_step_mm
        .unwrap_or(spot.radius_mm() / SAMPLES_PER_RADIUS);
    let (motion, program_time_s) = contact_motion(&program, inputs.kinematics, step)
        .map_err(|e| Error::engine(&inputs.program, e))?;
    let change = MeasuredChange::new(&before, &after).map_err(|e| Error::engine(&after_file, e))?;
    let calibration = calibrate(&change, &motion, &spot, &inputs.settings)
        .map_err(|e| Error::engine(&inputs.program, e))?;
    let record = CalibrationRecord::of(
        &calibration,
        Files {
            before: before_file,
            after: after_file,
            program: inputs.program.clone(),
            source_tif: inputs.tif_file.clone(),
            source_tif_sha256: inputs
                .tif_file
                .as_deref()
                .map(|f| file_sha256(f, "TIF"))
                .transpose()?,
        },
        program_time_s,
    );
    Ok(Calibrated {
        calibration,
        record,
    })
}

/// SHA-256 of a file's bytes, hex; `what` names the file in an error.
pub fn file_sha256(path: &Path, what: &str) -> Result<String> {
    let bytes = crate::limits::read_regular(path, 1 << 30, what)?;
    Ok(crate::digest::sha256_hex(&bytes))
}

/// The files a calibration was made from.
struct Files {
    before: PathBuf,
    after: PathBuf,
    program: PathBuf,
    source_tif: Option<PathBuf>,
    source_tif_sha256: Option<String>,
}

/// `calibration.json`: each figure with its standard deviation (`<key>_sigma`), how well the
/// calibrated tool explains the run, and what could not be determined.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct CalibrationRecord {
    /// How the fit ended (`converged`, `max_iterations`).
    pub status: String,
    /// Ratio of the TIF's volume to the spot test's.
    pub rate_factor: f64,
    /// Its standard deviation.
    pub rate_factor_sigma: f64,
    /// Ratio of the footprint's second-moment radius to the spot test's.
    pub width_factor: f64,
    /// Its standard deviation.
    pub width_factor_sigma: f64,
    /// Centroid offset along x from the programmed point, mm.
    pub offset_x_mm: f64,
    /// Its standard deviation, mm.
    pub offset_x_mm_sigma: f64,
    /// Centroid offset along y, mm.
    pub offset_y_mm: f64,
    /// Its standard deviation, mm.
    pub offset_y_mm_sigma: f64,
    /// Ellipticity along the axes (log stretch).
    pub ellipticity: f64,
    /// Its standard deviation.
    pub ellipticity_sigma: f64,
    /// Ellipticity along the diagonals.
    pub ellipticity_45: f64,
    /// Its standard deviation.
    pub ellipticity_45_sigma: f64,
    /// Skew along x.
    pub skew_x: f64,
    /// Its standard deviation.
    pub skew_x_sigma: f64,
    /// Skew along y.
    pub skew_y: f64,
    /// Its standard deviation.
    pub skew_y_sigma: f64,
    /// Relative change of the removal rate per hour of program time.
    pub drift_per_hour: f64,
    /// Its standard deviation.
    pub drift_per_hour_sigma: f64,
    /// Figures the run could not determine, held at the spot test's values, and why.
    pub held: Vec<HeldFigure>,
    /// RMS of the measured change (nuisance removed), nm.
    pub measured_change_rms_nm: f64,
    /// RMS of the fit's residual, nm.
    pub fit_rms_nm: f64,
    /// Metrology noise of one map, nm RMS (from the residual's neighbour differences).
    pub noise_rms_nm: f64,
    /// Factor the residual's correlation applies to the figures' variances.
    pub variance_inflation: f64,
    /// The calibrated TIF (relative to this file's folder).
    pub tif_file: PathBuf,
    /// SHA-256 of the calibrated TIF file.
    pub tif_sha256: String,
    /// The spot test it was calibrated from.
    pub source_tif_file: Option<PathBuf>,
    /// SHA-256 of the spot test's file: a solve whose TIF is this file plans with the calibrated
    /// TIF in its place.
    pub source_tif_sha256: Option<String>,
    /// The map before the run.
    pub before_file: PathBuf,
    /// The map after it.
    pub after_file: PathBuf,
    /// The program that ran.
    pub program_file: PathBuf,
    /// Executed time of the program, s.
    pub program_time_s: f64,
    /// Contact time, s.
    pub contact_time_s: f64,
    /// Program time at which the drift does not act (the rate of the calibrated TIF), s.
    pub mid_time_s: f64,
    /// Points used.
    pub points: usize,
    /// Points skipped (dropouts, edges).
    pub skipped: usize,
    /// Convolution lattice pitch, mm.
    pub lattice_pitch_mm: f64,
    /// Levenberg-Marquardt steps.
    pub iterations: usize,
    /// Nuisance terms (piston, tilt, power, shift between the measurements).
    pub nuisance: Nuisance,
    /// Correlations of the fitted figures and nuisance terms.
    pub correlation: Correlation,
    /// The free-form correction of the footprint.
    pub freeform: Option<FreeformCorrection>,
    /// Whether a shift between the measurements was kept, with the fit's RMS with and without.
    pub map_shift: Option<MapShiftTest>,
}

impl Default for CalibrationRecord {
    fn default() -> Self {
        Self {
            status: "converged".into(),
            rate_factor: 1.0,
            rate_factor_sigma: 0.0,
            width_factor: 1.0,
            width_factor_sigma: 0.0,
            offset_x_mm: 0.0,
            offset_x_mm_sigma: 0.0,
            offset_y_mm: 0.0,
            offset_y_mm_sigma: 0.0,
            ellipticity: 0.0,
            ellipticity_sigma: 0.0,
            ellipticity_45: 0.0,
            ellipticity_45_sigma: 0.0,
            skew_x: 0.0,
            skew_x_sigma: 0.0,
            skew_y: 0.0,
            skew_y_sigma: 0.0,
            drift_per_hour: 0.0,
            drift_per_hour_sigma: 0.0,
            held: Vec::new(),
            measured_change_rms_nm: 0.0,
            fit_rms_nm: 0.0,
            noise_rms_nm: 0.0,
            variance_inflation: 1.0,
            tif_file: PathBuf::from(CALIBRATED_TIF),
            tif_sha256: String::new(),
            source_tif_file: None,
            source_tif_sha256: None,
            before_file: PathBuf::new(),
            after_file: PathBuf::new(),
            program_file: PathBuf::new(),
            program_time_s: 0.0,
            contact_time_s: 0.0,
            mid_time_s: 0.0,
            points: 0,
            skipped: 0,
            lattice_pitch_mm: 0.0,
            iterations: 0,
            nuisance: Nuisance::default(),
            correlation: Correlation::default(),
            freeform: None,
            map_shift: None,
        }
    }
}

impl CalibrationRecord {
    fn of(c: &Calibration, files: Files, program_time_s: f64) -> Self {
        let (f, s): (ToolFigures, ToolFigures) = (c.figures, c.sigma);
        Self {
            status: c.status.name().to_string(),
            rate_factor: f.rate_factor,
            rate_factor_sigma: s.rate_factor,
            width_factor: f.width_factor,
            width_factor_sigma: s.width_factor,
            offset_x_mm: f.offset_x_mm,
            offset_x_mm_sigma: s.offset_x_mm,
            offset_y_mm: f.offset_y_mm,
            offset_y_mm_sigma: s.offset_y_mm,
            ellipticity: f.ellipticity,
            ellipticity_sigma: s.ellipticity,
            ellipticity_45: f.ellipticity_45,
            ellipticity_45_sigma: s.ellipticity_45,
            skew_x: f.skew_x,
            skew_x_sigma: s.skew_x,
            skew_y: f.skew_y,
            skew_y_sigma: s.skew_y,
            drift_per_hour: f.drift_per_hour,
            drift_per_hour_sigma: s.drift_per_hour,
            held: c.held.clone(),
            measured_change_rms_nm: c.measured_change_rms_nm,
            fit_rms_nm: c.fit_rms_nm,
            noise_rms_nm: c.noise_rms_nm,
            variance_inflation: c.variance_inflation,
            tif_file: PathBuf::from(CALIBRATED_TIF),
            tif_sha256: String::new(),
            source_tif_file: files.source_tif,
            source_tif_sha256: files.source_tif_sha256,
            before_file: files.before,
            after_file: files.after,
            program_file: files.program,
            program_time_s,
            contact_time_s: c.contact_time_s,
            mid_time_s: c.mid_time_s,
            points: c.points,
            skipped: c.skipped,
            lattice_pitch_mm: c.lattice_pitch_mm,
            iterations: c.iterations,
            nuisance: c.nuisance,
            correlation: c.correlation.clone(),
            freeform: c.freeform.clone(),
            map_shift: c.map_shift,
        }
    }
}

/// The calibrated TIF as CSV text `x_mm,y_mm,rate_nm_per_s`.
fn tif_csv(tif: &GridTif) -> String {
    let (x, y, r) = tif.columns();
    let mut text = String::with_capacity(x.len() * 36);
    text.push_str("x_mm,y_mm,rate_nm_per_s\n");
    for k in 0..x.len() {
        text.push_str(&format!("{:.6},{:.6},{:.9}\n", x[k], y[k], r[k]));
    }
    text
}

/// SHA-256 of a TIF grid as `tif.csv` holds it.
pub fn tif_digest(tif: &GridTif) -> String {
    crate::digest::sha256_hex(tif_csv(tif).as_bytes())
}

/// Writes `calibration.json`, `tif.csv` and, with `figures`, the measured and simulated removal,
/// their difference and the calibrated TIF, all or none.
pub fn write_calibration(
    calibrated: &mut Calibrated,
    out_dir: &Path,
    figures: Option<&FigureStyle>,
) -> Result<()> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    let c = &calibrated.calibration;
    let text = tif_csv(&c.tif);
    calibrated.record.tif_sha256 = crate::digest::sha256_hex(text.as_bytes());
    let mut staged: Vec<Staged> = vec![
        crate::atomic::stage(&out_dir.join(CALIBRATED_TIF), |w| {
            w.write_all(text.as_bytes())
        })?,
        stage_json(&out_dir.join(CALIBRATION_JSON), &calibrated.record)?,
    ];
    let difference: Vec<f64> = c
        .measured_removal_nm
        .iter()
        .zip(&c.simulated_removal_nm)
        .map(|(m, s)| m - s)
        .collect();
    staged.push(stage_columns_csv(
        &out_dir.join("removal.csv"),
        &[
            "x_mm",
            "y_mm",
            "measured_removal_nm",
            "simulated_removal_nm",
            "difference_nm",
        ],
        &[
            &c.x_mm,
            &c.y_mm,
            &c.measured_removal_nm,
            &c.simulated_removal_nm,
            &difference,
        ],
    )?);
    if let Some(style) = figures {
        for (stem, title, z) in [
            (
                "removal_measured",
                "Measured removal (piston and tilt removed)",
                &c.measured_removal_nm,
            ),
            (
                "removal_simulated",
                "Removal of the calibrated tool",
                &c.simulated_removal_nm,
            ),
            (
                "removal_difference",
                "Measured less simulated removal",
                &difference,
            ),
        ] {
            staged.push(stage_map_plot(
                &style.path(out_dir, stem),
                title,
                "nm",
                &c.x_mm,
                &c.y_mm,
                z,
            )?);
        }
        let (tx, ty, tr) = c.tif.columns();
        staged.push(stage_map_plot(
            &style.path(out_dir, "tif_calibrated"),
            "Calibrated tool influence function",
            "nm/s",
            &tx,
            &ty,
            tr,
        )?);
    }
    commit_all(staged)
}

/// Reads `calibration.json`; its `tif_file` resolved against the file's folder.
pub fn read_calibration(path: &Path) -> Result<CalibrationRecord> {
    let bytes = crate::limits::read_regular(path, 64 << 20, "calibration")?;
    let text = std::str::from_utf8(&bytes).map_err(|_| {
        Error::engine(
            path,
            preston_solver::Error::invalid("calibration", "not UTF-8 text"),
        )
    })?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut record: CalibrationRecord = serde_json::from_str(text).map_err(|e| {
        Error::engine(
            path,
            preston_solver::Error::invalid("calibration", format!("not a calibration.json: {e}")),
        )
    })?;
    let figures = [
        ("rate_factor", record.rate_factor),
        ("width_factor", record.width_factor),
    ];
    for (name, v) in figures {
        if !(v.is_finite() && v > 0.0) {
            return Err(Error::engine(
                path,
                preston_solver::Error::invalid(name, format!("must be positive, got {v}")),
            ));
        }
    }
    for (name, v) in [
        ("rate_factor_sigma", record.rate_factor_sigma),
        ("width_factor_sigma", record.width_factor_sigma),
        ("offset_x_mm_sigma", record.offset_x_mm_sigma),
        ("offset_y_mm_sigma", record.offset_y_mm_sigma),
        ("drift_per_hour_sigma", record.drift_per_hour_sigma),
        ("noise_rms_nm", record.noise_rms_nm),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(Error::engine(
                path,
                preston_solver::Error::invalid(name, format!("must be finite and >= 0, got {v}")),
            ));
        }
    }
    if record.tif_file.is_relative() {
        if let Some(dir) = path.parent() {
            record.tif_file = dir.join(&record.tif_file);
        }
    }
    Ok(record)
}
