//! The set-up stage: one job, resolved and validated once, made into a [`Problem`] and solved
//! into an [`Outcome`].
//!
//! ```text
//! SetupInputs (what the io layer read) --Setup::resolve--> Setup (validated: path, bounds,
//! limits, weights, settings, warm start) --Setup::problem--> Built { Problem, edge points }
//! --Setup::solve--> Outcome { solution, removal R t, feeds, feed schedule, statuses }
//! ```
//!
//! Every consumer (the `solve` pipeline, the loop's runs, the benchmarks, the Python package;
//! `simulate` up to the problem, then [`Setup::removal_of`] for the given dwell times or
//! [`Setup::run_program`] for a given program) goes through these three steps, so the decisions
//! they hold are written once: how the dwell points are made (a given path or a serpentine
//! raster), how the dwell area beyond the map is modelled ([`crate::edge`]), how `R` is held
//! (assembled, in the tangent frame of a design surface, or the matrix-free FFT operator,
//! [`OperatorPlan`]) and whether the acceleration limit is imposed by sequential convex
//! programming ([`crate::dwell::accel`]). The removal `R t` and
//! the feed schedule are computed once, in [`Setup::solve`], and handed on in the [`Outcome`].

mod choices;
mod off_lattice;
pub mod pays;
pub mod plausible;
mod problem;
mod resolve;
pub mod robust;
pub mod sensitivity;
mod solve;
pub mod tools;

pub use choices::{Checked, Choices};

use crate::dwell::accel::{self, AccelLimits, AccelMethod, AccelReport};
use crate::dwell::precond::DwellLattice;
use crate::dwell::{
    self, DwellBounds, FeedLimits, OperatorChoice, Problem, Settings, Solution, SolverChoice,
    Status,
};
use crate::dwell::{policy, SolverKind};
use crate::edge::{self, EdgeSettings};
use crate::error::{Error, Result};
use crate::influence::model::surface::{assemble_on_surface, assemble_on_surface_swept, TifFrame};
use crate::influence::operator::fft::FftOperator;
use crate::influence::{assemble_swept, InfluenceMatrix, InfluenceModel, Stretches, SweptTif};
use crate::machine::feeds::FeedSchedule;
use crate::machine::gcode::motion::Kinematics;
use crate::machine::gcode::program::Program;
use crate::machine::gcode::{write_and_check, ProgramCheck};
use crate::machine::nc::{NcProgram, NcSettings};
use crate::machine::{Flat, PartGeometry};
use crate::map::{HeightMap, HeightStats};
use crate::observer::Observer;
use crate::path::raster::{self, RasterAxis};
use crate::path::DwellPath;
use crate::simulate::program::{run_on_map, ProgramRun};
use crate::surface::Surface;
use crate::tif::{HertzParams, InfluenceFunction, Tif};

/// Where the dwell points come from: exactly one of a given path or a generated raster.
#[derive(Debug, Clone, PartialEq)]
pub enum DwellPoints {
    /// Dwell points read from a file, in path order.
    Given(DwellPath),
    /// A serpentine raster of this pitch over the map's bounding box extended by the TIF's
    /// nominal radius ([`raster::serpentine`]).
    Raster {
        /// Line spacing and point spacing, mm.
        pitch_mm: f64,
        /// Direction of the lines.
        along: RasterAxis,
    },
}

impl DwellPoints {
    /// The dwell points of a G-code program as it runs: the contact points of its marked
    /// stretches (`DWELL` comments, as `preston nc` writes them), in program order; in a program
    /// without markers, the tool-centre `(x, y)` halfway through each feed move and at each
    /// pause ([`Program::contact_blocks`]). The set-up then reports the executed run
    /// ([`Setup::run_program`]) on them. A program with neither has nothing to run, an error.
    pub fn of_program(program: &Program) -> Result<Self> {
        if program.stretches.is_empty() {
            let (x, y): (Vec<f64>, Vec<f64>) = program
                .contact_blocks()
                .map(|k| {
                    let p = program.blocks[k].point_at(0.5);
                    (p[0], p[1])
                })
                .unzip();
            if x.is_empty() {
                return Err(Error::invalid(
                    "program",
                    "no feed moves (G1, G2, G3) and no pauses (G4): nothing touches the part",
                ));
            }
            return Ok(DwellPoints::Given(DwellPath::new(x, y)?));
        }
        let (x, y) = program.stretches.iter().map(|s| (s.x_mm, s.y_mm)).unzip();
        Ok(DwellPoints::Given(DwellPath::new(x, y)?))
    }
}

/// Largest arc length of a removal sample along a motion (an executed program, a dwell point's
/// stretch under the swept model), mm, by default: 1/64 of the TIF's support radius, and for a
/// grid TIF at most a quarter of its finer pitch ([`GRID_SAMPLES_PER_PITCH`]), not below
/// 1/512 of the support radius.
///
/// Why the grid's pitch: the samples along a line are a comb of step `h` at a fixed phase to
/// the map's lattice, and the midpoint rule's error is the kernel's spectrum at the comb's
/// harmonics `n / h`. A bilinear grid TIF repeats the spectrum of its samples about every
/// multiple of `1 / dx`, damped only by `sinc^2(f dx)`: at `h` near `dx` (the sample job's
/// 0.08 mm pieces on a 0.088 mm grid) a harmonic falls next to the first image of the TIF's
/// whole volume, and the executed removal is off by a smooth field of about 1e-5 of the
/// removal, which the correction passes then fit (0.023 nm RMS reported against 0.041 nm
/// integrated finely). At `h <= dx / 4` the damping is below `1 / (4 pi)^2` at every harmonic.
/// The executed residual's own resolution, the change against half this step, is reported with
/// it ([`IntegrationResolution`]).
pub fn default_sample_step_mm(tif: &Tif) -> f64 {
    let support = tif.support_radius_mm();
    let smooth = support / 64.0;
    match tif {
        Tif::Grid(g) => {
            let (px, py) = g.pitch_mm();
            let pitch = px.min(py);
            if pitch.is_finite() && pitch > 0.0 {
                smooth.min((pitch / GRID_SAMPLES_PER_PITCH).max(support / 512.0))
            } else {
                smooth
            }
        }
        Tif::Gaussian(_) => smooth,
    }
}

/// Removal samples per pitch of a grid TIF along a motion, at least ([`default_sample_step_mm`]).
pub const GRID_SAMPLES_PER_PITCH: f64 = 4.0;

/// The resolution of an executed residual: how much it moves when the removal is integrated
/// along the same motion with half the sample step (the midpoint rule's pieces halved).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct IntegrationResolution {
    /// The sample step of the reported figures, mm (largest arc length of a removal sample).
    pub sample_step_mm: f64,
    /// Removal samples of the reported figures.
    pub samples: usize,
    /// RMS of the change of the executed residual (piston removed) against the integration at
    /// half the step, nm: a bound on how far the reported RMS moves.
    pub rms_change_nm: f64,
    /// PV of that change, nm: a bound on how far the reported PV moves.
    pub pv_change_nm: f64,
}

impl IntegrationResolution {
    /// The resolution of the residual of `removal_nm` (sampled with `samples` samples at
    /// `sample_step_mm`) against `finer_removal_nm`, the same motion at half the step.
    pub fn of(
        removal_nm: &[f64],
        finer_removal_nm: &[f64],
        sample_step_mm: f64,
        samples: usize,
    ) -> Self {
        let stats = HeightStats::of(&centred_residual_nm(removal_nm, finer_removal_nm));
        IntegrationResolution {
            sample_step_mm,
            samples,
            rms_change_nm: stats.rms_nm,
            pv_change_nm: stats.pv_nm,
        }
    }

    /// Decimals of a figure in nm that this resolution supports, 1 to 3: the most whose last
    /// digit's unit is not below the larger of the RMS change and a thousandth of a nm.
    pub fn decimals(&self) -> usize {
        let r = self.rms_change_nm.max(1e-3);
        (1..=3)
            .rev()
            .find(|&d| 10f64.powi(-(d as i32)) >= r)
            .unwrap_or(1)
    }
}

/// How the TIF acts on the part: exactly one of the shift-invariant TIF (in the plane, or in each
/// dwell point's tangent plane of the design surface) or a Hertzian TIF per dwell point from the
/// surface's local curvatures ([`crate::influence::model::curvature`]).
#[derive(Debug, Clone, PartialEq)]
pub enum TifModel {
    /// One TIF for every dwell point.
    ShiftInvariant,
    /// A Hertz contact TIF per dwell point, from the design surface's principal curvatures
    /// there; needs a design surface.
    CurvatureDependent(HertzParams),
}

/// Which input a set-up failure is about, so that the caller can name the file at fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SetupInput {
    /// The job's settings (limits, weights, solver and operator choice).
    Job,
    /// The error map (edge extension, lattice, assembly over the map points).
    Map,
    /// The given dwell points.
    Dwell,
    /// The design surface.
    Surface,
    /// The warm start's dwell times.
    WarmStart,
    /// No single input (a resource budget, a numerical failure).
    None,
}

/// A set-up failure and the input it is about.
#[derive(Debug)]
pub struct SetupError {
    /// The input at fault.
    pub input: SetupInput,
    /// What went wrong.
    pub source: Error,
}

impl std::fmt::Display for SetupError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.source.fmt(f)
    }
}

impl std::error::Error for SetupError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        Some(&self.source)
    }
}

impl From<SetupError> for Error {
    fn from(e: SetupError) -> Self {
        e.source
    }
}

/// The result of a set-up step.
pub type SetupResult<T> = std::result::Result<T, SetupError>;

trait At<T> {
    fn at(self, input: SetupInput) -> SetupResult<T>;
}

impl<T> At<T> for Result<T> {
    fn at(self, input: SetupInput) -> SetupResult<T> {
        self.map_err(|source| SetupError { input, source })
    }
}

/// The data the io layer read (or the caller passed in memory).
#[derive(Debug, Clone)]
pub struct SetupData {
    /// The error map, nm (rows with an empty height already removed).
    pub map: HeightMap,
    /// The TIF.
    pub tif: Tif,
    /// The dwell points.
    pub dwell: DwellPoints,
    /// The design surface of a curved part (`None`: a flat part, plan-view offsets).
    pub surface: Option<Surface>,
    /// Dwell times to start the first-order solver from, one per dwell point.
    pub warm_start_s: Option<Vec<f64>>,
}

pub use crate::observer::SetupStep;

/// A job resolved and validated once: every later step reads it and checks nothing again.
#[derive(Debug, Clone)]
pub struct Setup {
    /// The error map.
    pub map: HeightMap,
    /// The TIF.
    pub tif: Tif,
    /// How the TIF acts on the part.
    pub tif_model: TifModel,
    /// The dwell path (given or generated).
    pub path: DwellPath,
    /// Path length per dwell point, mm.
    pub ds_mm: Vec<f64>,
    /// The design surface, if the part is curved.
    pub surface: Option<Surface>,
    /// TIF orientation on the surface.
    pub tif_frame: TifFrame,
    /// Feed limits (`None`: none).
    pub feed: Option<FeedLimits>,
    /// The dwell bounds the feed limits give (`t >= 0` without limits).
    pub bounds: DwellBounds,
    /// The acceleration limit, validated (`None`: only feed limits).
    pub accel: Option<AccelLimits>,
    /// Corner angle of the machine, degrees.
    pub corner_angle_deg: f64,
    /// Weight of the total dwell.
    pub rho: f64,
    /// Weight of dwell differences.
    pub lambda: f64,
    /// Solver settings, validated.
    pub settings: Settings,
    /// Edge handling.
    pub edge: EdgeSettings,
    /// The warm start, checked against the dwell points.
    pub warm_start_s: Option<Vec<f64>>,
    /// With the swept influence model (in the plane, or on a curved part in each dwell point's
    /// tangent frame, [`crate::influence::model::surface::assemble_on_surface_swept`], with a
    /// curvature-dependent TIF each point's own,
    /// [`crate::influence::model::curvature::assemble_curvature_dependent_swept`]): every dwell
    /// point's stretch sampled for the assembled `R`, and the kernel the lattice operators share
    /// ([`crate::influence::model::swept`]).
    pub swept: Option<(Stretches, SweptTif<Tif>)>,
    /// A generated raster's placement on the map's lattice (`None`: given dwell points).
    pub raster: Option<raster::RasterPlacement>,
    /// The tool's rate drift per hour of program time (a calibration's): the executed program's
    /// removal weights each contact sample by it, so the correction passes plan for it.
    pub rate_drift_per_hour: f64,
    /// How well the tool is known (a spot test's defaults, the job's, or a calibration's): the
    /// robust plan's scenarios are drawn from it ([`robust::scenarios`]).
    pub tool_uncertainty: crate::calibrate::ToolUncertainty,
}

/// How `R` is held for a problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum OperatorPlan {
    /// Assemble the sparse `R`.
    Assembled,
    /// The matrix-free FFT operator on the lattice of this pitch, mm.
    Fft {
        /// Lattice pitch, mm.
        pitch_mm: f64,
    },
}

/// The problem a set-up builds.
#[derive(Debug, Clone)]
pub struct Built {
    /// The validated problem: the map's rows first, then the edge extension's.
    pub problem: Problem,
    /// Edge extension points appended to the map's rows.
    pub edge_points: usize,
    /// Warnings about the operator choice and the inputs' sizes.
    pub warnings: Vec<String>,
    /// Notes: what the set-up chose, for information (the operator `auto` chose, the swept
    /// columns made exact); printed as notes, not warnings.
    pub notes: Vec<String>,
    /// A robust plan's scenario weights ([`robust::SCENARIO_NAMES`] order, summing to their count);
    /// `None` for a nominal plan.
    pub scenario_weights: Option<Vec<f64>>,
}

/// Marks a message of the set-up's list as a note (a choice made, for information) rather than
/// a warning; [`split_notes`] takes the notes out of the list.
pub(crate) const NOTE_MARK: &str = "\u{1}note\u{1}";

/// A note for the set-up's list of messages (see [`NOTE_MARK`]).
pub(crate) fn note(text: String) -> String {
    format!("{NOTE_MARK}{text}")
}

/// The set-up's messages split into warnings and notes (the marked ones, unmarked), each in its
/// order.
pub(crate) fn split_notes(messages: Vec<String>) -> (Vec<String>, Vec<String>) {
    let (notes, warnings): (Vec<String>, Vec<String>) =
        messages.into_iter().partition(|m| m.starts_with(NOTE_MARK));
    let notes = notes
        .into_iter()
        .map(|n| n.trim_start_matches(NOTE_MARK).to_string())
        .collect();
    (warnings, notes)
}

/// The default program executed at the acceleration limit on the map: what the machine would
/// remove against the plan.
#[derive(Debug, Clone)]
pub struct Executed {
    /// The path acceleration, mm/s^2.
    pub a_max_mm_per_s2: f64,
    /// Statistics of the executed residual (piston removed), nm.
    pub after: HeightStats,
    /// The executed run.
    pub run: ProgramRun,
    /// Correction passes kept ([`AccelMethod::CorrectionPasses`]; 0 for the other methods).
    pub correction_passes: usize,
    /// The settings the program was written with.
    pub settings: NcSettings,
    /// The program written, read back and checked.
    pub program: ProgramCheck,
    /// The executed residual's resolution: its change against the removal integrated at half
    /// the sample step, taken once for the plan returned (`None` before that).
    pub resolution: Option<IntegrationResolution>,
}

/// A finished solve: everything downstream needs, computed once.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The solver's answer.
    pub solution: Solution,
    /// Predicted removal `R t` at the measured map points, nm (edge rows dropped).
    pub removal_nm: Vec<f64>,
    /// Predicted residual at the measured map points about its mean, nm:
    /// `(z - R t) - mean(z - R t)` ([`centred_residual_nm`]).
    pub residual_nm: Vec<f64>,
    /// Dwell on the points whose nearest map point is farther than the map's pitch, s
    /// ([`crate::machine::machinability::dwell_outside_map_s`]).
    pub dwell_outside_map_s: f64,
    /// Feed at each dwell point, mm/min (`ds / t * 60`, 0 where either is 0).
    pub feeds_mm_per_min: Vec<f64>,
    /// The feed schedule (machining time, largest acceleration).
    pub schedule: FeedSchedule,
    /// The acceleration-limited solve's account, with its RMS figures on the measured map.
    pub accel: Option<AccelReport>,
    /// With an acceleration limit: the default program (on a curved part following the design
    /// surface) executed at that limit, or why no program can deliver the plan.
    pub executed: Option<std::result::Result<Executed, Error>>,
    /// With an approximate operator: its measured error on the returned dwell (the removal
    /// above is the exact `R`'s).
    pub approximation: Option<OperatorError>,
    /// The residual of the plan's program (as executed, else at its programmed feeds) under each
    /// scenario of TIF uncertainty ([`sensitivity`]); `None` where the plan cannot be written
    /// as a program.
    pub sensitivity: Option<sensitivity::Sensitivity>,
}

/// The measured error of an approximate operator on the dwell a solve returned.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OperatorError {
    /// `||R~ t - R t|| / ||R t||` at the measured map points, `R~` the operator the solve used,
    /// `R` the exact one.
    pub relative_removal_error: f64,
    /// The error the operator was built to (`spread_tolerance`, or the NUFFT operator's design
    /// tolerance).
    pub tolerance: f64,
    /// RMS of the residual the solve saw (with `R~`), nm.
    pub rms_after_operator_nm: f64,
    /// RMS of the residual of the exact `R` on the same dwell, nm (the one reported).
    pub rms_after_exact_nm: f64,
}

/// Relative difference of the residual RMS the approximate operator predicts from the exact
/// `R`'s above which a warning is given: the operator's error, small against the removal, can
/// still dominate the residual that is left.
pub const RESIDUAL_MISMATCH_WARNING: f64 = 0.05;

impl OperatorError {
    /// Whether the measured error exceeds the tolerance the operator was built to, or misstates
    /// the residual RMS by more than [`RESIDUAL_MISMATCH_WARNING`] of the exact one.
    pub fn exceeds_tolerance(&self) -> bool {
        let mismatch = (self.rms_after_operator_nm - self.rms_after_exact_nm).abs();
        self.relative_removal_error > self.tolerance
            || mismatch > RESIDUAL_MISMATCH_WARNING * self.rms_after_exact_nm
    }

    /// The warning to give when [`OperatorError::exceeds_tolerance`].
    pub fn warning(&self) -> String {
        format!(
            "the approximate operator's measured error on the returned dwell is {:.2e} of the \
             removal (tolerance {:.0e}): the residual it predicts, RMS {:.4} nm, is {:.4} nm with \
             the exact R (the figure reported); a smaller spread_tolerance (fft-spread), or \
             operator = \"sparse\", plans with the exact R",
            self.relative_removal_error,
            self.tolerance,
            self.rms_after_operator_nm,
            self.rms_after_exact_nm
        )
    }
}

impl Outcome {
    /// How the solve ended.
    pub fn status(&self) -> Status {
        self.solution.status
    }
}

/// Feed at each dwell point, mm/min: `ds / dwell * 60` (0 where `ds` or the dwell is 0).
pub fn feeds_mm_per_min(ds_mm: &[f64], dwell_s: &[f64]) -> Vec<f64> {
    ds_mm
        .iter()
        .zip(dwell_s)
        .map(|(&d, &t)| {
            if d > 0.0 && t > 0.0 {
                d / t * 60.0
            } else {
                0.0
            }
        })
        .collect()
}

/// Residual about its mean, nm: `(z - h) - mean(z - h)`.
pub fn centred_residual_nm(z_nm: &[f64], removal_nm: &[f64]) -> Vec<f64> {
    let e: Vec<f64> = z_nm.iter().zip(removal_nm).map(|(z, h)| z - h).collect();
    let mean = if e.is_empty() {
        0.0
    } else {
        e.iter().sum::<f64>() / e.len() as f64
    };
    e.into_iter().map(|v| v - mean).collect()
}

#[cfg(test)]
mod tests {
    use super::solve::{solution_is_finite, MAX_CORRECTION_PASSES};
    use super::*;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    fn choices() -> Choices {
        Choices {
            feed: Some(FeedLimits {
                v_max_mm_per_min: 3000.0,
                v_min_mm_per_min: 0.0,
            }),
            a_max_mm_per_s2: None,
            corner_angle_deg: None,
            accel_method: Default::default(),
            rho: 0.0,
            lambda: 0.0,
            settings: Settings::default(),
            edge: EdgeSettings {
                method: crate::edge::EdgeMethod::None,
                ..EdgeSettings::default()
            },
            tif_model: TifModel::ShiftInvariant,
            tif_frame: TifFrame::default(),
            warm_start: false,
        }
    }

    /// A 21 x 21 map at 0.5 mm (10 x 10 mm from the origin) with heights `z(x, y)`, nm: the
    /// fixture of the set-up tests here and in [`super::tools`].
    pub(super) fn grid_map_21(z: impl Fn(f64, f64) -> f64) -> HeightMap {
        let (mut xs, mut ys, mut zs) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..21 {
            for i in 0..21 {
                let (x, y) = (i as f64 * 0.5, j as f64 * 0.5);
                xs.push(x);
                ys.push(y);
                zs.push(z(x, y));
            }
        }
        HeightMap::new(xs, ys, zs).unwrap()
    }

    fn data() -> SetupData {
        SetupData {
            map: grid_map_21(|x, y| 10.0 + (0.3 * x).sin() * (0.2 * y).cos()),
            tif: Tif::Gaussian(GaussianTif::new(1.0, 10.0, 3.0).unwrap()),
            dwell: DwellPoints::Raster {
                pitch_mm: 1.0,
                along: RasterAxis::X,
            },
            surface: None,
            warm_start_s: None,
        }
    }

    #[test]
    fn a_warm_start_with_an_acceleration_limit_is_refused_not_dropped() {
        let c = Choices {
            a_max_mm_per_s2: Some(500.0),
            warm_start: true,
            ..choices()
        };
        let e = c.check(&Silent).unwrap_err();
        assert_eq!(e.input, SetupInput::Job);
        assert!(e.to_string().contains("warm_start"), "{e}");
        // The same refusal when only the data carry the warm start.
        let checked = Choices {
            a_max_mm_per_s2: Some(500.0),
            ..choices()
        }
        .check(&Silent)
        .unwrap();
        let mut d = data();
        d.warm_start_s = Some(vec![0.0; 3]);
        assert!(Setup::resolve(checked, d, &Silent).is_err());
    }

    #[test]
    fn the_raster_and_bounds_are_resolved_once_and_the_warm_start_length_checked() {
        let checked = choices().check(&Silent).unwrap();
        let setup = Setup::resolve(checked.clone(), data(), &Silent).unwrap();
        assert_eq!(setup.ds_mm.len(), setup.path.len());
        assert_eq!(setup.bounds.len(), setup.path.len());
        let mut d = data();
        d.warm_start_s = Some(vec![0.0; setup.path.len() + 1]);
        let e = Setup::resolve(checked, d, &Silent).unwrap_err();
        assert_eq!(e.input, SetupInput::WarmStart);
    }

    #[test]
    fn the_operator_plan_follows_the_choice_and_what_blocks_the_fft() {
        let fft = |settings: Settings| {
            let checked = Choices {
                settings,
                ..choices()
            }
            .check(&Silent)
            .unwrap();
            let setup = Setup::resolve(checked, data(), &Silent).unwrap();
            let mut w = Vec::new();
            setup.operator_plan(&setup.map.clone(), &mut w)
        };
        let with = |operator, solver| Settings {
            operator,
            solver,
            ..Settings::default()
        };
        // A small problem: auto assembles R.
        assert_eq!(
            fft(with(OperatorChoice::Auto, SolverChoice::Auto)).unwrap(),
            OperatorPlan::Assembled
        );
        match fft(with(OperatorChoice::Fft, SolverChoice::FirstOrder)).unwrap() {
            OperatorPlan::Fft { pitch_mm } => assert!((pitch_mm - 0.5).abs() < 1e-12),
            p => panic!("{p:?}"),
        }
        let e = fft(with(OperatorChoice::Fft, SolverChoice::Qp)).unwrap_err();
        assert!(e.to_string().contains("qp"), "{e}");
    }

    /// `auto` takes the FFT operator for a large raster on a lattice map, and not once two dwell
    /// points far out make its lattice mostly empty (a warning says why); the same far points
    /// with `operator = "fft"` are planned as asked.
    #[test]
    fn auto_does_not_take_a_mostly_empty_fft_lattice() {
        let (mut xs, mut ys, mut zs) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..201 {
            for i in 0..201 {
                let (x, y) = (i as f64 * 0.5, j as f64 * 0.5);
                xs.push(x);
                ys.push(y);
                zs.push(10.0 + (0.1 * x).sin() * (0.07 * y).cos());
            }
        }
        let map = HeightMap::new(xs, ys, zs).unwrap();
        let (mut px, mut py) = (Vec::new(), Vec::new());
        for j in 0..101 {
            for k in 0..101 {
                let i = if j % 2 == 0 { k } else { 100 - k };
                px.push(i as f64);
                py.push(j as f64);
            }
        }
        let plan = |px: &[f64], py: &[f64], operator| {
            let checked = Choices {
                settings: Settings {
                    operator,
                    solver: SolverChoice::FirstOrder,
                    ..Settings::default()
                },
                ..choices()
            }
            .check(&Silent)
            .unwrap();
            let d = SetupData {
                map: map.clone(),
                tif: Tif::Gaussian(GaussianTif::new(3.0, 10.0, 10.0).unwrap()),
                dwell: DwellPoints::Given(DwellPath::new(px.to_vec(), py.to_vec()).unwrap()),
                surface: None,
                warm_start_s: None,
            };
            let setup = Setup::resolve(checked, d, &Silent).unwrap();
            let mut w = Vec::new();
            let p = setup.operator_plan(&setup.map.clone(), &mut w).unwrap();
            (p, w, setup.dwell_points_in_reach(&setup.map))
        };
        let (near, _, reach) = plan(&px, &py, OperatorChoice::Auto);
        assert!(matches!(near, OperatorPlan::Fft { .. }), "{near:?}");
        assert_eq!(reach, px.len());
        px.extend([3000.0, -2000.0, 110.0]);
        py.extend([3000.0, 2500.0, 50.0]);
        let (far, w, reach) = plan(&px, &py, OperatorChoice::Auto);
        assert_eq!(far, OperatorPlan::Assembled);
        assert!(w.iter().any(|m| m.contains("mostly empty")), "{w:?}");
        // The cost models count only the dwell points that reach the map (the point 10 mm past
        // its edge is within the 10 mm truncation radius).
        assert_eq!(reach, px.len() - 2);
        let (forced, _, _) = plan(&px, &py, OperatorChoice::Fft);
        assert!(matches!(forced, OperatorPlan::Fft { .. }), "{forced:?}");
    }

    #[test]
    fn a_plan_without_feed_limits_is_evaluated_as_given() {
        let checked = Choices {
            feed: None,
            ..choices()
        }
        .check(&Silent)
        .unwrap();
        let path = DwellPath::new(vec![2.0, 6.5], vec![3.0, 4.5]).unwrap();
        let d = SetupData {
            dwell: DwellPoints::Given(path.clone()),
            ..data()
        };
        let setup = Setup::resolve(checked.clone(), d, &Silent).unwrap();
        // No limits: every bound is t >= 0.
        assert!(setup.bounds.lower_s().iter().all(|&l| l == 0.0));
        let built = setup.problem(&Silent).unwrap();
        let dwell_s = [1.5, 0.25];
        let removal = setup.removal_of(&built.problem, &dwell_s, &Silent).unwrap();
        // R t by hand: the TIF at each map point's offset from each dwell point.
        let m = &setup.map;
        assert_eq!(removal.len(), m.len());
        for ((&h, &x), &y) in removal.iter().zip(m.x_mm()).zip(m.y_mm()) {
            let want: f64 = (0..2)
                .map(|j| {
                    dwell_s[j]
                        * setup
                            .tif
                            .rate_nm_per_s(x - path.x_mm()[j], y - path.y_mm()[j])
                })
                .sum();
            assert!((h - want).abs() <= 1e-12 * want.abs().max(1.0));
        }
        // One point: a spot without limits, refused with them.
        let spot = DwellPath::new(vec![2.0], vec![3.0]).unwrap();
        let d = SetupData {
            dwell: DwellPoints::Given(spot.clone()),
            ..data()
        };
        assert!(Setup::resolve(checked, d, &Silent).is_ok());
        let d = SetupData {
            dwell: DwellPoints::Given(spot),
            ..data()
        };
        let limited = choices().check(&Silent).unwrap();
        assert_eq!(
            Setup::resolve(limited, d, &Silent).unwrap_err().input,
            SetupInput::Dwell
        );
    }

    #[test]
    fn the_outcome_carries_the_removal_and_feeds_of_its_solution() {
        let setup = Setup::resolve(choices().check(&Silent).unwrap(), data(), &Silent).unwrap();
        let built = setup.problem(&Silent).unwrap();
        let o = setup.solve(&built.problem, &Silent).unwrap();
        assert_eq!(
            o.removal_nm,
            built.problem.removal_nm(&o.solution.dwell_s).unwrap()
        );
        assert_eq!(
            o.feeds_mm_per_min,
            feeds_mm_per_min(&setup.ds_mm, &o.solution.dwell_s)
        );
        assert!(o.solution.status.is_converged());
    }

    /// Feeds against hand values: 1 mm in 0.1 s is 10 mm/s, 600 mm/min; 2 mm in 0.5 s is
    /// 240 mm/min; no feed where the spacing or the dwell is zero.
    #[test]
    fn feeds_are_spacing_over_dwell_in_mm_per_min() {
        let f = feeds_mm_per_min(&[1.0, 2.0, 0.0, 1.5, 0.3], &[0.1, 0.5, 1.0, 0.0, 0.006]);
        let expected = [600.0, 240.0, 0.0, 0.0, 3000.0];
        for (got, want) in f.iter().zip(expected) {
            assert!((got - want).abs() <= 1e-12 * want.max(1.0), "{f:?}");
        }
    }
    /// The swept plan's removal `R t` against the program `preston nc` writes for `t`, run at its
    /// programmed feeds (`simulate --program` without an acceleration limit): the same removal
    /// up to the program's 4-decimal coordinates, relative to the largest removal.
    const SWEPT_VS_PROGRAM_TOL: f64 = 1e-4;

    /// Runs the default program for `dwell_s` under `kinematics` on the set-up's map.
    fn program_removal(setup: &Setup, dwell_s: &[f64], kinematics: Kinematics) -> Vec<f64> {
        let nc = NcProgram::plan(&setup.path, dwell_s, &Flat, &NcSettings::default()).unwrap();
        let check = write_and_check(&nc, &[]).unwrap();
        setup
            .run_program(&check.program, kinematics, None, None, &Silent)
            .unwrap()
            .removal_nm
    }

    #[test]
    fn the_swept_plan_is_the_program_at_its_feeds_and_the_point_plan_is_not() {
        // Dwell varying along the raster so that the feeds differ from point to point.
        let dwell = |n: usize| -> Vec<f64> {
            (0..n)
                .map(|j| 0.05 + 0.04 * (0.7 * j as f64).sin().abs())
                .collect()
        };
        let mut errors = Vec::new();
        for model in [InfluenceModel::Swept, InfluenceModel::Point] {
            let mut c = choices();
            c.settings.influence = model;
            c.settings.operator = OperatorChoice::Sparse;
            let setup = Setup::resolve(c.check(&Silent).unwrap(), data(), &Silent).unwrap();
            assert_eq!(setup.influence_model(), model);
            let built = setup.problem(&Silent).unwrap();
            let t = dwell(setup.path.len());
            let plan = setup.removal_of(&built.problem, &t, &Silent).unwrap();
            let run = program_removal(&setup, &t, Kinematics::ProgrammedFeed);
            let peak = run.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
            let err = plan
                .iter()
                .zip(&run)
                .fold(0.0f64, |a, (p, r)| a.max((p - r).abs()))
                / peak;
            errors.push(err);
        }
        assert!(errors[0] < SWEPT_VS_PROGRAM_TOL, "swept: {}", errors[0]);
        // The point model misses the sweep by far more (a 1 mm stretch of a sigma 1 mm TIF).
        assert!(
            errors[1] > 10.0 * SWEPT_VS_PROGRAM_TOL,
            "point: {}",
            errors[1]
        );
    }

    #[test]
    fn the_lattice_operator_is_the_assembled_swept_matrix_row_ends_included() {
        // Map and raster on one 0.5 mm lattice: the FFT operator with the swept kernel, its row
        // ends' and path ends' columns corrected (`swept_correction`), gives the assembled swept
        // R's removal for dwell on every point.
        let mut d = data();
        d.dwell = DwellPoints::Raster {
            pitch_mm: 0.5,
            along: RasterAxis::X,
        };
        let mut c = choices();
        c.settings.influence = InfluenceModel::Swept;
        c.settings.operator = OperatorChoice::Sparse;
        let assembled = Setup::resolve(c.check(&Silent).unwrap(), d.clone(), &Silent).unwrap();
        let mut c = choices();
        c.settings.influence = InfluenceModel::Swept;
        c.settings.operator = OperatorChoice::Fft;
        let lattice = Setup::resolve(c.check(&Silent).unwrap(), d, &Silent).unwrap();
        let pa = assembled.problem(&Silent).unwrap().problem;
        let pl = lattice.problem(&Silent).unwrap().problem;
        assert_eq!(pl.operator_kind(), crate::influence::OperatorKind::Fft);
        let (x, y) = (assembled.path.x_mm(), assembled.path.y_mm());
        let t: Vec<f64> = x
            .iter()
            .zip(y)
            .map(|(&px, &py)| 1.0 + 0.1 * (px + 2.0 * py).sin())
            .collect();
        let ha = pa.removal_nm(&t).unwrap();
        let hl = pl.removal_nm(&t).unwrap();
        let peak = ha.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
        for (a, l) in ha.iter().zip(&hl) {
            assert!((a - l).abs() <= 1e-9 * peak, "{a} vs {l}");
        }
    }

    /// Without an executed program the sensitivity is the plan's own motion under each
    /// scenario: on the FFT operator each scenario's operator product, on the assembled `R` the
    /// stretch samples summed directly; the same figures for the same dwell, and each scenario
    /// leaves more than the nominal residual.
    #[test]
    fn the_plan_sensitivity_on_the_lattice_is_the_direct_sum_of_its_motion() {
        /// The lattice products against the direct sum (row ends exact, the rest the same
        /// kernel on the lattice).
        const LATTICE_REL_TOL: f64 = 1e-9;
        let mut d = data();
        d.dwell = DwellPoints::Raster {
            pitch_mm: 0.5,
            along: RasterAxis::X,
        };
        let setup = |operator| {
            let mut c = choices();
            c.settings.influence = InfluenceModel::Swept;
            c.settings.operator = operator;
            Setup::resolve(c.check(&Silent).unwrap(), d.clone(), &Silent).unwrap()
        };
        let (direct, lattice) = (setup(OperatorChoice::Sparse), setup(OperatorChoice::Fft));
        let pd = direct.problem(&Silent).unwrap().problem;
        let pl = lattice.problem(&Silent).unwrap().problem;
        assert_eq!(pl.operator_kind(), crate::influence::OperatorKind::Fft);
        let t: Vec<f64> = direct
            .path
            .x_mm()
            .iter()
            .zip(direct.path.y_mm())
            .map(|(&px, &py)| 0.3 + 0.1 * (px + 2.0 * py).sin())
            .collect();
        let h = pd.removal_nm(&t).unwrap();
        let h = &h[..direct.map.len()];
        let a = direct.plan_sensitivity(&pd, &t, h, &Silent).unwrap();
        let b = lattice.plan_sensitivity(&pl, &t, h, &Silent).unwrap();
        let nominal = HeightStats::of(&centred_residual_nm(direct.map.z_nm(), h)).rms_nm;
        for (x, y) in [
            (a.tif_wider_3pct, b.tif_wider_3pct),
            (a.tif_narrower_3pct, b.tif_narrower_3pct),
            (a.rate_plus_3pct, b.rate_plus_3pct),
            (a.offset_x_0p05mm, b.offset_x_0p05mm),
            (a.offset_y_0p05mm, b.offset_y_0p05mm),
        ] {
            assert!(
                (x.rms_nm - y.rms_nm).abs() <= LATTICE_REL_TOL * x.rms_nm,
                "{x:?} against {y:?}"
            );
            assert!((x.pv_nm - y.pv_nm).abs() <= LATTICE_REL_TOL * x.pv_nm);
            assert!(x.rms_nm != nominal);
        }
    }

    /// With a curvature-dependent TIF the set-up's `R` is the library's curvature-dependent
    /// assembly bit for bit, under the swept model and the point model.
    #[test]
    fn the_curvature_dependent_r_is_the_librarys_assembly() {
        let sphere = crate::surface::Surface::Conic(crate::surface::Conic {
            curvature_per_mm: -1.0 / 30.0,
            conic: -0.6,
        });
        let params = HertzParams {
            preston_k_mm2_per_n: 1e-6,
            ..HertzParams::default()
        };
        for model in [InfluenceModel::Swept, InfluenceModel::Point] {
            let mut c = choices();
            c.settings.influence = model;
            c.tif_model = TifModel::CurvatureDependent(params.clone());
            let mut d = data();
            d.surface = Some(sphere.clone());
            let setup = Setup::resolve(c.check(&Silent).unwrap(), d, &Silent).unwrap();
            let got = setup.assemble(&setup.map, &Silent).unwrap();
            let (mx, my) = (setup.map.x_mm(), setup.map.y_mm());
            let frame = setup.tif_frame;
            let want = match &setup.swept {
                Some((stretches, _)) => {
                    crate::influence::model::curvature::assemble_curvature_dependent_swept(
                        &sphere,
                        mx,
                        my,
                        &setup.path,
                        stretches,
                        &params,
                        frame,
                        &Silent,
                    )
                }
                None => crate::influence::model::curvature::assemble_curvature_dependent(
                    &sphere,
                    mx,
                    my,
                    setup.path.x_mm(),
                    setup.path.y_mm(),
                    &params,
                    frame,
                    &Silent,
                ),
            }
            .unwrap();
            assert_eq!(setup.swept.is_some(), model == InfluenceModel::Swept);
            assert!(want.nnz() > 0);
            assert_eq!(got, want, "{model:?}");
        }
    }

    /// Each robust scenario's assembled `R` is the scenario's closed form: the Gaussian's sigma
    /// and cut times the width factor and its peak over its square, the tool moved by the
    /// offset; in the plane the plan distance, on a sphere of radius 30 mm the distance in the
    /// tangent plane of the moved dwell point, `|P - S'|^2 - ((P - S') . n')^2`.
    #[test]
    fn each_robust_scenario_matrix_is_its_closed_form() {
        /// Two evaluations of one closed form.
        const CLOSED_FORM_TOL: f64 = 1e-12;
        let path = DwellPath::new(vec![2.0, 4.5, 7.0], vec![3.0, 5.0, 4.5]).unwrap();
        let (sigma, peak, cut) = (1.0, 10.0, 3.0);
        let sphere = crate::surface::Surface::Conic(crate::surface::Conic {
            curvature_per_mm: 1.0 / 30.0,
            conic: 0.0,
        });
        for surface in [None, Some(sphere)] {
            let mut c = choices();
            c.settings.influence = InfluenceModel::Point;
            let mut d = data();
            d.dwell = DwellPoints::Given(path.clone());
            d.surface = surface.clone();
            let setup = Setup::resolve(c.check(&Silent).unwrap(), d, &Silent).unwrap();
            let t = [1.0, 0.5, 2.0];
            let (mx, my) = (setup.map.x_mm(), setup.map.y_mm());
            let mut nonzero = 0;
            for s in &robust::scenarios(&Default::default()) {
                let p = crate::tif::Perturbation {
                    width_factor: s.width_factor,
                    rate_factor: 1.0,
                    offset_mm: s.offset_mm,
                };
                let h = setup
                    .assemble_scenario(&setup.map, &p, &Silent)
                    .unwrap()
                    .removal_nm(&t)
                    .unwrap();
                let w = s.width_factor;
                for i in 0..mx.len() {
                    let mut want = 0.0;
                    let mut on_the_cut = false;
                    for (j, tj) in t.iter().enumerate() {
                        let (sx, sy) = (
                            path.x_mm()[j] + s.offset_mm.0,
                            path.y_mm()[j] + s.offset_mm.1,
                        );
                        let (dx, dy) = (mx[i] - sx, my[i] - sy);
                        let rho2 = match &surface {
                            None => dx * dx + dy * dy,
                            Some(f) => {
                                let dz =
                                    f.sag_mm(mx[i], my[i]).unwrap() - f.sag_mm(sx, sy).unwrap();
                                let n = f.normal(sx, sy).unwrap();
                                let a = dx * n[0] + dy * n[1] + dz * n[2];
                                dx * dx + dy * dy + dz * dz - a * a
                            }
                        };
                        let r = rho2.sqrt() / w;
                        on_the_cut |= (r - cut).abs() < 1e-9;
                        if r <= cut {
                            want += tj * peak / (w * w) * (-r * r / (2.0 * sigma * sigma)).exp();
                        }
                    }
                    if !on_the_cut {
                        assert!(
                            (h[i] - want).abs() <= CLOSED_FORM_TOL * want.abs().max(1.0),
                            "{:?} {} point {i}: {} against {want}",
                            surface.is_some(),
                            s.name,
                            h[i]
                        );
                        nonzero += usize::from(want > 0.0);
                    }
                }
            }
            assert!(nonzero > 300, "{nonzero}");
        }
    }

    #[test]
    fn the_robust_lattice_stack_is_the_stacked_assembled_scenario_matrices() {
        // Map and raster on one 0.5 mm lattice, the swept model: the robust plan's scenario
        // blocks, each the FFT operator with the scenario's swept kernel and its exact row-end
        // columns, give the stacked assembled scenario matrices' products, transposes, normal
        // products and centred column norms; both plans are the same.
        robust_stack_against_assembled(0.5, data().tif, OperatorChoice::Fft, 1e-9);
    }

    #[test]
    fn the_robust_off_lattice_stacks_are_the_stacked_assembled_scenario_matrices() {
        // A 0.55 mm raster over the 0.5 mm map (off its lattice) and a Gaussian (sigma 1.5 mm)
        // cut at 6 sigma, whose band the NUFFT operator keeps: its scenario blocks agree with
        // the assembled scenario matrices to the operator's design tolerance. A 0.75 mm raster puts every
        // dwell point on the half-cell lattice, where the spreading operator is exact.
        let wide = Tif::Gaussian(GaussianTif::new(1.5, 10.0, 9.0).unwrap());
        robust_stack_against_assembled(0.55, wide, OperatorChoice::Nufft, 2e-5);
        robust_stack_against_assembled(0.75, data().tif, OperatorChoice::FftSpread, 1e-9);
    }

    /// The robust plan over the fixture map with a `pitch_mm` raster and `tif`, the swept model,
    /// through `operator` against the stacked assembled scenario matrices: `R t`, `R^T y`,
    /// `R^T R t` and the centred column norms within `tol` of their peaks, and the two plans'
    /// robust objectives (through the assembled matrices) equal.
    fn robust_stack_against_assembled(pitch_mm: f64, tif: Tif, operator: OperatorChoice, tol: f64) {
        let mut d = data();
        d.tif = tif;
        d.dwell = DwellPoints::Raster {
            pitch_mm,
            along: RasterAxis::X,
        };
        let resolve = |operator| {
            let mut c = choices();
            c.settings.influence = InfluenceModel::Swept;
            c.settings.operator = operator;
            c.settings.robust = true;
            // A time weight keeps the plan off exact interpolation, and a tight stop makes the
            // two plans' difference the operators' own.
            c.rho = 0.1;
            c.settings.first_order_tolerance = 1e-10;
            Setup::resolve(c.check(&Silent).unwrap(), d.clone(), &Silent).unwrap()
        };
        let assembled = resolve(OperatorChoice::Sparse);
        let lattice = resolve(operator);
        let pa = assembled.problem(&Silent).unwrap().problem;
        let built = lattice.problem(&Silent).unwrap();
        let pl = built.problem;
        let kind = match operator {
            OperatorChoice::Fft => crate::influence::OperatorKind::Fft,
            OperatorChoice::Nufft => crate::influence::OperatorKind::Nufft,
            _ => crate::influence::OperatorKind::FftSpread,
        };
        assert_eq!(pa.operator_kind(), crate::influence::OperatorKind::Sparse);
        assert_eq!(pl.operator_kind(), kind);
        assert!(
            built.warnings.iter().any(|w| w.contains("(matrix-free)")),
            "{:?}",
            built.warnings
        );
        assert_eq!((pa.m(), pa.n()), (pl.m(), pl.n()));
        assert_eq!(pa.m(), robust::SCENARIO_COUNT * lattice.map.len());
        let close = |a: &[f64], b: &[f64], what: &str| {
            let peak = a.iter().fold(0.0f64, |p, v| p.max(v.abs()));
            for (k, (u, v)) in a.iter().zip(b).enumerate() {
                assert!((u - v).abs() <= tol * peak, "{what} {k}: {u} vs {v}");
            }
        };
        let (x, y) = (lattice.path.x_mm(), lattice.path.y_mm());
        let t: Vec<f64> = x
            .iter()
            .zip(y)
            .map(|(&px, &py)| 1.0 + 0.1 * (px + 2.0 * py).sin())
            .collect();
        close(
            &pa.removal_nm(&t).unwrap(),
            &pl.removal_nm(&t).unwrap(),
            "R t",
        );
        let (oa, ol) = (pa.operator().products(None), pl.operator().products(None));
        let yv: Vec<f64> = (0..pa.m()).map(|i| (0.37 * i as f64).cos()).collect();
        let (mut ta, mut tl) = (vec![0.0; pa.n()], vec![0.0; pa.n()]);
        oa.apply_transpose(&yv, &mut ta);
        ol.apply_transpose(&yv, &mut tl);
        close(&ta, &tl, "R^T y");
        let mut scratch = vec![0.0; pa.m()];
        oa.apply_normal(&t, &mut scratch, &mut ta);
        ol.apply_normal(&t, &mut scratch, &mut tl);
        close(&ta, &tl, "R^T R t");
        close(
            &oa.centred_column_norms_sq(),
            &ol.centred_column_norms_sq(),
            "centred norms",
        );
        let sa = assembled.solve(&pa, &Silent).unwrap();
        let sl = lattice.solve(&pl, &Silent).unwrap();
        // Both plans' dwell in the robust objective through the assembled scenario matrices,
        // `0.5 ||P (R t - z)||^2 + rho s sum t` (one piston over every block): equal to the
        // solver's tolerance, the plan through the lattice blocks no worse.
        let z = lattice.map.z_nm();
        let rho = 0.1 * robust::SCENARIO_COUNT as f64;
        let objective = |t: &[f64]| {
            let h = pa.removal_nm(t).unwrap();
            let r: Vec<f64> = h
                .iter()
                .enumerate()
                .map(|(i, v)| v - z[i % z.len()])
                .collect();
            let piston = r.iter().sum::<f64>() / r.len() as f64;
            0.5 * r.iter().map(|v| (v - piston).powi(2)).sum::<f64>() + rho * t.iter().sum::<f64>()
        };
        let (fa, fl) = (
            objective(&sa.solution.dwell_s),
            objective(&sl.solution.dwell_s),
        );
        assert!(fl <= fa * (1.0 + 1e-5), "{fa} vs {fl}");
        // An approximate operator's plan reports the exact residual of its dwell.
        if let Some(a) = &sl.approximation {
            let rl = HeightStats::of(&sl.residual_nm).rms_nm;
            assert!(
                (a.rms_after_exact_nm - rl).abs() <= 1e-12 * rl.max(1.0),
                "{a:?}"
            );
            assert!(a.relative_removal_error <= 1e-6, "{a:?}");
        }
    }

    /// A solve that ran away (a piston of 1e155 nm, a non-finite dwell or removal) is no answer:
    /// the guard that turns it into `numerical_error` rejects each, and accepts a real solve.
    #[test]
    fn a_runaway_or_non_finite_solution_fails_the_guard() {
        let setup = Setup::resolve(choices().check(&Silent).unwrap(), data(), &Silent).unwrap();
        let problem = setup.problem(&Silent).unwrap().problem;
        let o = setup.solve(&problem, &Silent).unwrap();
        assert!(solution_is_finite(&o.solution, &o.removal_nm));
        let mut s = o.solution.clone();
        s.piston_nm = 1.2e155;
        assert!(!solution_is_finite(&s, &o.removal_nm));
        let mut s = o.solution.clone();
        s.dwell_s[0] = f64::NAN;
        assert!(!solution_is_finite(&s, &o.removal_nm));
        let mut s = o.solution.clone();
        s.objective = f64::INFINITY;
        assert!(!solution_is_finite(&s, &o.removal_nm));
        let mut h = o.removal_nm.clone();
        h[0] = f64::INFINITY;
        assert!(!solution_is_finite(&o.solution, &h));
    }

    /// Under the swept model the exact removal an approximate operator is checked against is
    /// the assembled swept `R`'s, not the point model's.
    #[test]
    fn the_exact_removal_of_an_approximate_operator_follows_the_swept_contract() {
        let mut d = data();
        d.dwell = DwellPoints::Raster {
            pitch_mm: 0.7,
            along: RasterAxis::X,
        };
        let mut c = choices();
        c.settings.influence = InfluenceModel::Swept;
        c.settings.operator = OperatorChoice::Sparse;
        let assembled = Setup::resolve(c.check(&Silent).unwrap(), d.clone(), &Silent).unwrap();
        let mut c = choices();
        c.settings.influence = InfluenceModel::Swept;
        c.settings.operator = OperatorChoice::FftSpread;
        c.settings.spread_tolerance = 1e-2;
        let spread = Setup::resolve(c.check(&Silent).unwrap(), d, &Silent).unwrap();
        let pa = assembled.problem(&Silent).unwrap().problem;
        let ps = spread.problem(&Silent).unwrap().problem;
        assert_eq!(
            ps.operator_kind(),
            crate::influence::OperatorKind::FftSpread
        );
        let t: Vec<f64> = (0..pa.n()).map(|j| 1.0 + 0.3 * (j as f64).sin()).collect();
        let mut ha = pa.removal_nm(&t).unwrap();
        ha.truncate(assembled.map.len());
        let exact = spread.exact_removal(&ps, &t, &Silent).unwrap().unwrap();
        let peak = ha.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
        for (a, e) in ha.iter().zip(&exact.exact_removal_nm) {
            assert!((a - e).abs() <= 1e-9 * peak, "{a} vs {e}");
        }
    }

    /// Relative margin by which the default plan's executed residual may exceed the best
    /// method's on the same part.
    const DEFAULT_TO_BEST: f64 = 0.05;

    /// The default acceleration method is the one that makes the best part as executed: with
    /// nothing chosen (feed and acceleration limits only), the program executed at the limit
    /// with look-ahead leaves a residual within [`DEFAULT_TO_BEST`] of the best method's, each
    /// plan executed independently of its solve.
    #[test]
    fn the_default_acceleration_method_makes_the_best_part_as_executed() {
        assert_eq!(AccelMethod::default(), AccelMethod::CorrectionPasses);
        assert_eq!(AccelLimits::default().method, AccelMethod::default());
        const A_MAX: f64 = 5.0;
        let mut d = data();
        d.dwell = DwellPoints::Raster {
            pitch_mm: 0.5,
            along: RasterAxis::X,
        };
        d.map = grid_map_21(|x, y| 40.0 + 20.0 * (0.9 * x).sin() * (0.6 * y).cos());
        let executed_rms_nm = |method: Option<AccelMethod>| {
            let mut c = choices();
            c.a_max_mm_per_s2 = Some(A_MAX);
            if let Some(m) = method {
                c.accel_method = m;
            }
            c.feed = Some(FeedLimits {
                v_max_mm_per_min: 3000.0,
                v_min_mm_per_min: 1.0,
            });
            let checked = c.check(&Silent).unwrap();
            assert_eq!(
                checked.accel().map(|l| l.method),
                Some(method.unwrap_or_default())
            );
            let setup = Setup::resolve(checked, d.clone(), &Silent).unwrap();
            let built = setup.problem(&Silent).unwrap();
            let o = setup.solve(&built.problem, &Silent).unwrap();
            setup
                .executed_at_limit(&o.solution.dwell_s, A_MAX, &Silent)
                .unwrap()
                .after
                .rms_nm
        };
        let default_nm = executed_rms_nm(None);
        let best_nm = [AccelMethod::SquaredSpeed, AccelMethod::CorrectionPasses]
            .into_iter()
            .map(|m| executed_rms_nm(Some(m)))
            .fold(f64::INFINITY, f64::min);
        assert!(
            default_nm <= best_nm * (1.0 + DEFAULT_TO_BEST),
            "the default executes to {default_nm} nm RMS, the best method to {best_nm} nm"
        );
    }

    #[test]
    fn correction_passes_never_worsen_the_executed_residual_and_report_it() {
        // A fine raster at a low acceleration limit: the ramps matter.
        const A_MAX: f64 = 5.0;
        let mut d = data();
        d.dwell = DwellPoints::Raster {
            pitch_mm: 0.5,
            along: RasterAxis::X,
        };
        d.map = grid_map_21(|x, y| 40.0 + 20.0 * (0.9 * x).sin() * (0.6 * y).cos());
        let run = |method: AccelMethod| {
            let mut c = choices();
            c.settings.influence = InfluenceModel::Swept;
            c.a_max_mm_per_s2 = Some(A_MAX);
            c.accel_method = method;
            c.feed = Some(FeedLimits {
                v_max_mm_per_min: 3000.0,
                v_min_mm_per_min: 1.0,
            });
            let setup = Setup::resolve(c.check(&Silent).unwrap(), d.clone(), &Silent).unwrap();
            let built = setup.problem(&Silent).unwrap();
            let o = setup.solve(&built.problem, &Silent).unwrap();
            let e = o.executed.unwrap().unwrap();
            // The reported executed residual is the program's, re-run independently here.
            let again = setup
                .executed_at_limit(&o.solution.dwell_s, A_MAX, &Silent)
                .unwrap();
            assert_eq!(e.after.rms_nm, again.after.rms_nm);
            (e.after.rms_nm, e.correction_passes)
        };
        // The feed-limited optimum (no limit in the plan), executed at the limit.
        let mut c = choices();
        c.settings.influence = InfluenceModel::Swept;
        c.feed = Some(FeedLimits {
            v_max_mm_per_min: 3000.0,
            v_min_mm_per_min: 1.0,
        });
        let setup = Setup::resolve(c.check(&Silent).unwrap(), d.clone(), &Silent).unwrap();
        let built = setup.problem(&Silent).unwrap();
        let o = setup.solve(&built.problem, &Silent).unwrap();
        let plain = setup
            .executed_at_limit(&o.solution.dwell_s, A_MAX, &Silent)
            .unwrap()
            .after
            .rms_nm;
        // A pass is kept only where it lowers the executed residual: never worse than the
        // feed-limited plan executed (on the sample part job two passes are kept,
        // `cli/tests/sample_part_cli.rs`).
        let (passes_rms, passes) = run(AccelMethod::CorrectionPasses);
        assert!(passes <= MAX_CORRECTION_PASSES);
        assert!(
            passes_rms <= plain,
            "passes {passes_rms} vs feed-limited {plain}"
        );
    }

    /// A measured (bilinear, noisy) grid TIF swept along a raster on a map's lattice at a few
    /// times the grid's pitch, each stretch its own time: the midpoint rule at the default step
    /// integrates the removal to [`DEFAULT_STEP_REL_TOL`] of the removal's own variation against a
    /// fine reference (101 pieces per stretch), where pieces near the grid's pitch do not.
    #[test]
    fn the_default_step_integrates_a_measured_grid_tif_to_the_figures_precision() {
        /// The default step's removal error (RMS, piston removed) over the removal's RMS
        /// variation, with 6% noise on the TIF's samples: a tenth of a percent (pieces at the
        /// grid's pitch leave more than ten times that).
        const DEFAULT_STEP_REL_TOL: f64 = 1e-3;
        let (pitch, n) = (0.088, 115usize);
        let c = (n / 2) as f64;
        let rates: Vec<f64> = (0..n)
            .flat_map(|j| {
                (0..n).map(move |i| {
                    let (x, y) = ((i as f64 - c) * pitch, (j as f64 - c) * pitch);
                    let r2 = x * x + y * y;
                    // A few percent of measurement noise on the samples.
                    let noise = ((i * 7919 + j * 104_729) % 1000) as f64 / 1000.0 - 0.5;
                    if r2 <= 4.8 * 4.8 {
                        20.0 * (-r2 / (2.0 * 1.2 * 1.2)).exp() * (1.0 + 0.06 * noise)
                    } else {
                        0.0
                    }
                })
            })
            .collect();
        let tif = Tif::Grid(
            crate::tif::GridTif::new(-c * pitch, -c * pitch, pitch, pitch, n, n, rates).unwrap(),
        );
        let lattice = 0.32;
        let (mut mx, mut my) = (Vec::new(), Vec::new());
        for j in 0..6 {
            for i in 0..30 {
                mx.push(i as f64 * lattice);
                my.push(j as f64 * lattice);
            }
        }
        // The removal of the raster with each stretch cut into `pieces` equal pieces, a sample
        // at each piece's midpoint carrying its share of the stretch's time.
        let removal = |pieces: usize| -> Vec<f64> {
            let (mut x, mut y, mut t) = (Vec::new(), Vec::new(), Vec::new());
            for r in -16..=21 {
                for s in -16..=45 {
                    let time = 1.0 + 0.5 * (0.37 * s as f64 + 0.91 * r as f64).sin();
                    for k in 0..pieces {
                        let f = (k as f64 + 0.5) / pieces as f64 - 0.5;
                        x.push((s as f64 + f) * lattice);
                        y.push(r as f64 * lattice);
                        t.push(time / pieces as f64);
                    }
                }
            }
            crate::simulate::direct::removals_nm(
                &mx,
                &my,
                &x,
                &y,
                &t,
                std::slice::from_ref(&tif),
                &Silent,
            )
            .unwrap()
            .remove(0)
        };
        let reference = removal(101);
        let variation = HeightStats::of(&centred_residual_nm(&reference, &vec![0.0; mx.len()]));
        let error = |pieces: usize| {
            HeightStats::of(&centred_residual_nm(&removal(pieces), &reference)).rms_nm
                / variation.rms_nm
        };
        let pieces = (lattice / default_sample_step_mm(&tif)).ceil() as usize;
        let at_default = error(pieces);
        let at_pitch = error((lattice / pitch).ceil() as usize);
        assert!(
            at_default <= DEFAULT_STEP_REL_TOL,
            "{pieces} pieces per stretch: relative error {at_default:e}"
        );
        assert!(
            at_pitch > DEFAULT_STEP_REL_TOL,
            "pieces at the grid's pitch already integrate it: {at_pitch:e}"
        );
    }
}
