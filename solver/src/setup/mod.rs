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

mod off_lattice;
pub mod plausible;
pub mod robust;
pub mod sensitivity;
pub mod tools;

use crate::dwell::accel::{self, AccelLimits, AccelMethod, AccelReport};
use crate::dwell::precond::DwellLattice;
use crate::dwell::{
    self, DwellBounds, FeedLimits, OperatorChoice, Problem, Settings, Solution, SolverChoice,
    Status,
};
use crate::dwell::{policy, SolverKind};
use crate::edge::{self, EdgeSettings};
use crate::error::{Error, Result};
use crate::influence::curvature::assemble_curvature_dependent;
use crate::influence::fft::FftOperator;
use crate::influence::surface::{assemble_on_surface, TifFrame};
use crate::influence::{assemble_swept, InfluenceMatrix, InfluenceModel, Stretches, SweptTif};
use crate::machine::feeds::FeedSchedule;
use crate::machine::gcode::motion::Kinematics;
use crate::machine::gcode::program::Program;
use crate::machine::gcode::{run_on_map, write_and_check, ProgramRun};
use crate::machine::nc::{NcProgram, NcSettings};
use crate::machine::{Flat, PartGeometry};
use crate::map::{HeightMap, HeightStats};
use crate::observer::Observer;
use crate::path::raster::{self, RasterAxis};
use crate::path::DwellPath;
use crate::surface::Surface;
use crate::tif::{HertzParams, InfluenceFunction, Tif};

/// Values held per dwell point through a solve (path, lengths, dwell, feeds, solver work
/// vectors), not counting the influence matrix: the memory budget's lower bound.
const DWELL_POINT_VALUES: f64 = 16.0;

/// The FFT operator is used only when the map's bounding box holds at most this many lattice cells
/// per map point (a round aperture fills 79% of its square, i.e. 1.27 cells per point).
const MAX_LATTICE_CELLS_PER_MAP_POINT: f64 = 4.0;

/// `auto` takes the FFT operator only where its padded lattice (map and dwell points, the TIF's
/// reach around them) holds at most this many cells per map or dwell point: a few dwell points
/// far from the others would otherwise make a mostly empty lattice of hundreds of MB (a padded
/// raster over a strip holds about 3).
const MAX_FFT_CELLS_PER_POINT: f64 = 16.0;

/// Why a warm start and an acceleration limit are refused together.
const WARM_START_WITH_ACCEL: &str = "cannot be combined with an acceleration limit: the \
    sequential convex programme starts from its own feed-limited optimum (drop the warm start or \
    the limit)";

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

/// Largest arc length of a removal sample along an executed program, mm, by default: 1/64 of
/// the TIF's support radius (0.11 mm for the sample job's fluid-jet TIF); halving it moves the
/// sample job's residual RMS by less than 0.05% (README, `preston simulate`).
pub fn default_sample_step_mm(tif: &Tif) -> f64 {
    tif.support_radius_mm() / 64.0
}

/// How the TIF acts on the part: exactly one of the shift-invariant TIF (in the plane, or in each
/// dwell point's tangent plane of the design surface) or a Hertzian TIF per dwell point from the
/// surface's local curvatures ([`crate::influence::curvature`]).
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

/// The job's choices (limits, weights, solver settings, edge and TIF model), before anything
/// is read: [`Choices::check`] validates them once, before the inputs are read.
#[derive(Debug, Clone)]
pub struct Choices {
    /// Feed limits (`None`: none, the dwell bounds are `t >= 0`; a plan evaluated as given).
    pub feed: Option<FeedLimits>,
    /// Acceleration limit along a line, mm/s^2 (`None`: none).
    pub a_max_mm_per_s2: Option<f64>,
    /// Turn angle above which the path splits into lines, degrees (`None`: 60).
    pub corner_angle_deg: Option<f64>,
    /// How the acceleration limit is imposed.
    pub accel_method: AccelMethod,
    /// Weight of the total dwell (nm^2 per s).
    pub rho: f64,
    /// Weight of dwell differences along the path (nm^2/s^2).
    pub lambda: f64,
    /// Solver settings (solver, operator choice, tolerances).
    pub settings: Settings,
    /// Edge handling.
    pub edge: EdgeSettings,
    /// How the TIF acts on the part.
    pub tif_model: TifModel,
    /// Orientation of the TIF's x axis in the tangent plane (with a surface).
    pub tif_frame: TifFrame,
    /// Whether a warm start is given (it cannot be combined with an acceleration limit).
    pub warm_start: bool,
}

/// [`Choices`] validated: only [`Choices::check`] makes one.
#[derive(Debug, Clone)]
pub struct Checked {
    choices: Choices,
    accel: Option<AccelLimits>,
    corner_angle_deg: f64,
}

impl Checked {
    /// The validated choices.
    pub fn choices(&self) -> &Choices {
        &self.choices
    }

    /// The acceleration limit with default SCP settings, validated.
    pub fn accel(&self) -> Option<&AccelLimits> {
        self.accel.as_ref()
    }

    /// The machine's corner angle, degrees.
    pub fn corner_angle_deg(&self) -> f64 {
        self.corner_angle_deg
    }
}

impl Choices {
    /// The choices of a plan evaluated as given (`simulate`: a dwell file or a program's
    /// executed stretches): `feed` (if any) only for the bounds the report checks, no
    /// acceleration limit, no weights, no edge rows, the assembled `R` of the shift-invariant
    /// TIF in the plane; nothing is solved.
    pub fn evaluation(feed: Option<FeedLimits>) -> Self {
        Self {
            feed,
            a_max_mm_per_s2: None,
            corner_angle_deg: None,
            accel_method: AccelMethod::default(),
            rho: 0.0,
            lambda: 0.0,
            settings: Settings {
                operator: OperatorChoice::Sparse,
                influence: InfluenceModel::Point,
                ..Settings::default()
            },
            edge: EdgeSettings {
                method: edge::EdgeMethod::None,
                ..EdgeSettings::default()
            },
            tif_model: TifModel::ShiftInvariant,
            tif_frame: TifFrame::default(),
            warm_start: false,
        }
    }

    /// Validates every choice once: solver settings, feed and acceleration limits, weights, the
    /// TIF model and their combinations. A warm start with an acceleration limit is refused: the
    /// sequential convex programme starts from its own feed-limited optimum and would not use it.
    pub fn check(self, observer: &dyn Observer) -> SetupResult<Checked> {
        observer.setup_step(SetupStep::CheckChoices);
        crate::counts::record(crate::counts::Counted::ChoicesChecked);
        self.settings.validate().at(SetupInput::Job)?;
        if let Some(feed) = &self.feed {
            feed.validate().at(SetupInput::Job)?;
        }
        for (name, v) in [("rho", self.rho), ("lambda", self.lambda)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::invalid(name, format!("must be >= 0, got {v}")))
                    .at(SetupInput::Job);
            }
        }
        let corner_angle_deg = self
            .corner_angle_deg
            .unwrap_or(AccelLimits::default().corner_angle_deg);
        let accel = match self.a_max_mm_per_s2 {
            None => None,
            Some(a) => {
                let limits = AccelLimits {
                    a_max_mm_per_s2: a,
                    corner_angle_deg,
                    method: self.accel_method,
                    // The solver's iteration limits bound the limited stage too: the SCP's
                    // QP solves and the squared-speed method's gradient steps.
                    max_iterations: AccelLimits::default()
                        .max_iterations
                        .min(self.settings.max_iterations),
                    max_gradient_steps: self.settings.first_order_max_iterations,
                    ..AccelLimits::default()
                };
                limits.validate().at(SetupInput::Job)?;
                if self.settings.min_time {
                    return Err(Error::invalid(
                        "a_max_mm_per_s2",
                        "cannot be combined with min_time (the SCP minimises the residual \
                         objective)",
                    ))
                    .at(SetupInput::Job);
                }
                Some(limits)
            }
        };
        if accel.is_some() && self.warm_start {
            return Err(Error::invalid("warm_start", WARM_START_WITH_ACCEL)).at(SetupInput::Job);
        }
        if let TifModel::CurvatureDependent(params) = &self.tif_model {
            params.validate().at(SetupInput::Job)?;
        }
        Ok(Checked {
            choices: self,
            accel,
            corner_angle_deg,
        })
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
    /// With the swept influence model in the plane: every dwell point's stretch sampled for the
    /// assembled `R`, and the kernel the lattice operators share ([`crate::influence::swept`]).
    pub swept: Option<(Stretches, SweptTif<Tif>)>,
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
    /// Warnings about the operator choice.
    pub warnings: Vec<String>,
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
}

/// Most correction passes against the executed program.
pub const MAX_CORRECTION_PASSES: usize = 4;

/// Smallest relative fall of the executed RMS for which a correction pass is kept.
pub const PASS_GAIN: f64 = 1e-3;

/// A finished solve: everything downstream needs, computed once.
#[derive(Debug, Clone)]
pub struct Outcome {
    /// The solver's answer.
    pub solution: Solution,
    /// Predicted removal `R t` at the measured map points, nm (edge rows dropped).
    pub removal_nm: Vec<f64>,
    /// Feed at each dwell point, mm/min (`ds / t * 60`, 0 where either is 0).
    pub feeds_mm_per_min: Vec<f64>,
    /// The feed schedule (machining time, largest acceleration).
    pub schedule: FeedSchedule,
    /// The acceleration-limited solve's account, with its RMS figures on the measured map.
    pub accel: Option<AccelReport>,
    /// With an acceleration limit on a flat part: the default program executed at that limit,
    /// or why no program can deliver the plan.
    pub executed: Option<std::result::Result<Executed, Error>>,
    /// With an approximate operator: its measured error on the returned dwell (the removal
    /// above is the exact `R`'s).
    pub approximation: Option<OperatorError>,
    /// With an executed program: its residual under each scenario of TIF uncertainty
    /// ([`sensitivity`]).
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

/// The exact removal and the operator's error on it.
struct Exact {
    exact_removal_nm: Vec<f64>,
    error: OperatorError,
}

/// Whether every figure of a solve is finite and within physical range (a dwell of more than
/// 10^12 s, a piston or removal of more than 10^12 nm is a run-away iteration).
fn solution_is_finite(solution: &Solution, removal_nm: &[f64]) -> bool {
    const RUNAWAY: f64 = 1e12;
    let ok = |v: f64| v.is_finite() && v.abs() < RUNAWAY;
    ok(solution.piston_nm)
        && solution.objective.is_finite()
        && solution.dwell_s.iter().all(|&t| ok(t))
        && removal_nm.iter().all(|&h| ok(h))
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

impl Setup {
    /// Resolves the data under the checked choices: the dwell points (generating the raster),
    /// the dwell bounds and the warm start's length. Given points with feed limits are at least
    /// two (a path of length zero has no feed); without limits (a plan evaluated as given,
    /// [`Setup::removal_of`]) one point is a spot.
    pub fn resolve(
        checked: Checked,
        data: SetupData,
        observer: &dyn Observer,
    ) -> SetupResult<Self> {
        observer.setup_step(SetupStep::Resolve);
        let Checked {
            choices,
            accel,
            corner_angle_deg,
        } = checked;
        let SetupData {
            map,
            tif,
            dwell,
            surface,
            warm_start_s,
        } = data;
        if warm_start_s.is_some() && accel.is_some() {
            return Err(Error::invalid("warm_start", WARM_START_WITH_ACCEL)).at(SetupInput::Job);
        }
        if matches!(choices.tif_model, TifModel::CurvatureDependent(_)) && surface.is_none() {
            return Err(Error::invalid(
                "curvature-dependent TIF",
                "needs a design surface ([surface] file or --surface)",
            ))
            .at(SetupInput::Job);
        }
        if let Some(s) = &surface {
            s.validate().at(SetupInput::Surface)?;
        }
        let path = match dwell {
            DwellPoints::Given(p) => {
                // A plan to solve for needs feeds; one evaluated as given (no limits) may be a
                // single spot.
                if p.len() < 2 && choices.feed.is_some() {
                    return Err(Error::invalid(
                        "dwell points",
                        "one dwell point: a path of length zero has no feed; give at least two \
                         points",
                    ))
                    .at(SetupInput::Dwell);
                }
                p
            }
            DwellPoints::Raster { pitch_mm, along } => {
                let bbox = map
                    .bounding_box_mm()
                    .ok_or_else(|| Error::invalid("map", "no data rows"))
                    .at(SetupInput::Map)?
                    .expanded(tif.nominal_radius_mm());
                if pitch_mm.is_finite() && pitch_mm > 0.0 {
                    let points = ((bbox.x_max_mm - bbox.x_min_mm) / pitch_mm + 1.0)
                        * ((bbox.y_max_mm - bbox.y_min_mm) / pitch_mm + 1.0);
                    crate::budget::check_f64s(
                        "--raster-pitch-mm",
                        &format!(
                            "a raster of pitch {pitch_mm} mm over the map plus the TIF radius \
                             ({points:.3e} dwell points, at least {DWELL_POINT_VALUES} values each)"
                        ),
                        points,
                        DWELL_POINT_VALUES,
                    )
                    .at(SetupInput::None)?;
                }
                raster::serpentine(&bbox, pitch_mm, along).at(SetupInput::Job)?
            }
        };
        let ds_mm = path.ds_mm();
        let bounds = match &choices.feed {
            Some(feed) => DwellBounds::from_feeds(&ds_mm, feed),
            None => DwellBounds::new(vec![0.0; path.len()], None),
        }
        .at(SetupInput::Job)?;
        if let Some(w) = &warm_start_s {
            if w.len() != path.len() {
                return Err(Error::invalid(
                    "warm start",
                    format!(
                        "has {} dwell times but the job has {} dwell points",
                        w.len(),
                        path.len()
                    ),
                ))
                .at(SetupInput::WarmStart);
            }
        }
        // The swept model in the plane: a given plan evaluated (no feed limits) keeps the point
        // model, whose `R t` simulate's discrete motion is.
        let swept = match (choices.settings.influence, &surface, &choices.feed) {
            (InfluenceModel::Swept, None, Some(_)) => {
                let stretches = Stretches::of_path(&path, default_sample_step_mm(&tif))
                    .at(SetupInput::Dwell)?;
                let kernel = SweptTif::new(tif.clone(), stretches.dominant().0);
                Some((stretches, kernel))
            }
            _ => None,
        };
        Ok(Self {
            swept,
            map,
            tif,
            tif_model: choices.tif_model,
            path,
            ds_mm,
            surface,
            tif_frame: choices.tif_frame,
            feed: choices.feed,
            bounds,
            accel,
            corner_angle_deg,
            rho: choices.rho,
            lambda: choices.lambda,
            settings: choices.settings,
            edge: choices.edge,
            warm_start_s,
        })
    }

    /// The problem's rows: the measured map, then the edge extension into the dwell area.
    fn rows(&self) -> SetupResult<(HeightMap, usize)> {
        let map = &self.map;
        let extension = edge::extend(
            &self.edge,
            map.x_mm(),
            map.y_mm(),
            map.z_nm(),
            self.path.x_mm(),
            self.path.y_mm(),
            self.tif.nominal_radius_mm(),
            self.tif.support_radius_mm(),
        )
        .at(SetupInput::Map)?;
        let edge_points = extension.len();
        if extension.is_empty() {
            return Ok((map.clone(), 0));
        }
        let cat = |a: &[f64], b: &[f64]| [a, b].concat();
        let rows = HeightMap::new(
            cat(map.x_mm(), &extension.x_mm),
            cat(map.y_mm(), &extension.y_mm),
            cat(map.z_nm(), &extension.z_nm),
        )
        .at(SetupInput::Map)?;
        Ok((rows, edge_points))
    }

    /// The influence model the plan uses: swept where the set-up built it (a solve in the plane
    /// with a shift-invariant TIF), the point model otherwise.
    pub fn influence_model(&self) -> InfluenceModel {
        if self.swept.is_some() {
            InfluenceModel::Swept
        } else {
            InfluenceModel::Point
        }
    }

    /// The shift-invariant kernel of the lattice operators: the TIF swept along the stretch most
    /// dwell points share (swept model), or the TIF itself (point model).
    pub(crate) fn lattice_kernel(&self) -> &dyn InfluenceFunction {
        match &self.swept {
            Some((_, kernel)) => kernel,
            None => &self.tif,
        }
    }

    /// What keeps the FFT operator from serving this set-up, if anything.
    fn fft_blocker(&self) -> Option<&'static str> {
        if self.surface.is_some() {
            Some("a [surface] file (the TIF acts in each point's tangent frame)")
        } else if self
            .accel
            .as_ref()
            .is_some_and(|a| a.method.needs_assembled_r())
        {
            Some("accel_method = \"scp-qp\" or \"squared-speed-then-scp-qp\" (the sequential QP needs R)")
        } else if self.settings.min_time {
            Some("the minimum-time mode (it runs the QP)")
        } else if self.settings.solver == SolverChoice::Qp {
            Some("solver = \"qp\" (the QP needs R)")
        } else {
            None
        }
    }

    /// How `R` is held for the problem rows `rows` (`operator` of the settings): `fft` with
    /// inputs it cannot serve is an error naming why; `auto` takes the FFT operator when the
    /// cost models of [`policy::choose`] predict it faster than the assembled `R`, the map fills
    /// its lattice and nothing blocks it (a warning says so), the assembled matrix otherwise.
    pub fn operator_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
    ) -> SetupResult<OperatorPlan> {
        let choice = self.settings.operator;
        // The off-lattice operators are planned by `stencil_plan` and `spread_plan` where the
        // lattice one is not.
        if matches!(
            choice,
            OperatorChoice::Sparse
                | OperatorChoice::FftSpread
                | OperatorChoice::Stencil
                | OperatorChoice::Nufft
        ) {
            return Ok(OperatorPlan::Assembled);
        }
        let blocker = self.fft_blocker();
        // The map must fill a fair share of its lattice (a gridded map, perhaps with a round
        // aperture), or the FFT buffers would dwarf the map.
        let pitch = FftOperator::lattice_pitch_mm(rows.x_mm(), rows.y_mm()).filter(|&p| {
            rows.bounding_box_mm().is_some_and(|b| {
                let cells =
                    ((b.x_max_mm - b.x_min_mm) / p + 1.0) * ((b.y_max_mm - b.y_min_mm) / p + 1.0);
                cells <= MAX_LATTICE_CELLS_PER_MAP_POINT * rows.len() as f64
            })
        });
        match (choice, blocker, pitch) {
            (OperatorChoice::Fft, Some(why), _) => Err(Error::invalid(
                "operator",
                format!("operator = \"fft\" cannot be used with {why}"),
            ))
            .at(SetupInput::Job),
            (OperatorChoice::Fft, None, None) => Err(Error::invalid(
                "operator",
                "operator = \"fft\" needs map points on a regular lattice that they fill at \
                 least a quarter of",
            ))
            .at(SetupInput::Job),
            (OperatorChoice::Fft, None, Some(p)) => Ok(OperatorPlan::Fft { pitch_mm: p }),
            (_, Some(_), _) | (_, None, None) => Ok(OperatorPlan::Assembled),
            // Dwell points off the lattice are the off-lattice operators' case.
            (_, None, Some(p))
                if !rows
                    .bounding_box_mm()
                    .is_some_and(|b| self.dwell_on_map_lattice(&b, p)) =>
            {
                Ok(OperatorPlan::Assembled)
            }
            (_, None, Some(p)) => {
                // Map points inside one TIF disc, at most all of them, per dwell point.
                let r = self.tif.support_radius_mm();
                let per_column = (std::f64::consts::PI * r * r / (p * p)).min(rows.len() as f64);
                let estimate = per_column * self.dwell_points_in_reach(rows) as f64;
                let fft_cells = fft_lattice_cells(rows, &self.path, r, p);
                let points = (rows.len() + self.path.len()) as f64;
                if fft_cells > MAX_FFT_CELLS_PER_POINT * points {
                    warnings.push(format!(
                        "operator auto: the FFT lattice spanning the map and dwell points would \
                         hold {fft_cells:.3e} cells for {points:.0} points (dwell points far from \
                         the others?), mostly empty; assembling R (operator = \"fft\" forces it)"
                    ));
                    return Ok(OperatorPlan::Assembled);
                }
                let choice = policy::choose(&policy::PolicyInputs {
                    nnz: estimate,
                    fft_cells: Some(fft_cells),
                    needs_qp: false,
                    solver: match self.settings.solver {
                        SolverChoice::FirstOrder => Some(SolverKind::FirstOrder),
                        SolverChoice::Qp => Some(SolverKind::Qp),
                        SolverChoice::Auto => None,
                    },
                });
                if choice.operator == policy::OperatorKind::Fft {
                    warnings.push(format!(
                        "operator auto: about {estimate:.2e} non-zeros in R; the FFT operator is \
                         predicted faster ({:.2} s against {:.2} s first-order with R, {:.2} s QP), \
                         so products use it (operator = \"sparse\" assembles R)",
                        choice.first_order_fft_s, choice.first_order_sparse_s, choice.qp_s
                    ));
                    Ok(OperatorPlan::Fft { pitch_mm: p })
                } else {
                    Ok(OperatorPlan::Assembled)
                }
            }
        }
    }

    /// Assembles `R` over `rows`: in the plane, in each dwell point's tangent frame on the design
    /// surface, or with a curvature-dependent TIF per dwell point.
    fn assemble(&self, rows: &HeightMap, observer: &dyn Observer) -> SetupResult<InfluenceMatrix> {
        let (mx, my, px, py) = (rows.x_mm(), rows.y_mm(), self.path.x_mm(), self.path.y_mm());
        match (&self.surface, &self.tif_model) {
            (None, TifModel::ShiftInvariant) if self.swept.is_some() => {
                let stretches = self.swept.as_ref().map(|s| &s.0);
                match stretches {
                    Some(st) => assemble_swept(mx, my, &self.path, st, &self.tif, observer)
                        .at(SetupInput::None),
                    None => InfluenceMatrix::assemble(mx, my, px, py, &self.tif, observer)
                        .at(SetupInput::None),
                }
            }
            (None, _) => {
                InfluenceMatrix::assemble(mx, my, px, py, &self.tif, observer).at(SetupInput::None)
            }
            (Some(s), TifModel::ShiftInvariant) => {
                assemble_on_surface(s, mx, my, px, py, &self.tif, self.tif_frame, observer)
                    .at(SetupInput::Surface)
            }
            (Some(s), TifModel::CurvatureDependent(params)) => {
                assemble_curvature_dependent(s, mx, my, px, py, params, self.tif_frame, observer)
                    .at(SetupInput::Surface)
            }
        }
    }

    /// Builds the problem: the edge extension, the operator (assembled or FFT) and the
    /// validated [`Problem`].
    pub fn problem(&self, observer: &dyn Observer) -> SetupResult<Built> {
        observer.setup_step(SetupStep::BuildProblem);
        let (rows, edge_points) = self.rows()?;
        let mut warnings = plausible::size_warnings(&self.map, &self.tif);
        if self.settings.influence == InfluenceModel::Swept
            && self.swept.is_none()
            && self.feed.is_some()
        {
            warnings.push(
                "influence swept: not built on a curved part (tangent frame) or with a                  curvature-dependent TIF; the plan uses the point model"
                    .to_string(),
            );
        }
        if self.settings.robust {
            let problem = self.robust_problem(&rows, &mut warnings, observer)?;
            return self.built(problem, edge_points, warnings);
        }
        let fft = match self.operator_plan(&rows, &mut warnings)? {
            OperatorPlan::Assembled => None,
            OperatorPlan::Fft { pitch_mm } => match FftOperator::new(
                rows.x_mm(),
                rows.y_mm(),
                self.path.x_mm(),
                self.path.y_mm(),
                pitch_mm,
                self.lattice_kernel(),
            ) {
                Ok(op) => Some(op),
                Err(e) if self.settings.operator == OperatorChoice::Fft => {
                    return Err(e).at(SetupInput::Map);
                }
                Err(e) => {
                    warnings.push(format!(
                        "operator auto: the FFT operator does not apply ({e}); assembling R"
                    ));
                    None
                }
            },
        };
        let z_nm = rows.z_nm().to_vec();
        let (bounds, rho, lambda) = (self.bounds.clone(), self.rho, self.lambda);
        let problem = if let Some(op) = fft {
            Problem::new(op, z_nm, bounds, rho, lambda)
        } else if let Some(op) = self.stencil_plan(&rows, &mut warnings)? {
            Problem::new(op, z_nm, bounds, rho, lambda)
        } else if let Some(op) = self.nufft_plan(&rows, &mut warnings)? {
            Problem::new(op, z_nm, bounds, rho, lambda)
        } else if let Some(op) = self.spread_plan(&rows, &mut warnings)? {
            Problem::new(op, z_nm, bounds, rho, lambda)
        } else {
            Problem::new(self.assemble(&rows, observer)?, z_nm, bounds, rho, lambda)
        }
        .and_then(|p| {
            p.with_dwell_lattice(DwellLattice::detect(self.path.x_mm(), self.path.y_mm()))
        })
        .at(SetupInput::Job)?;
        self.built(problem, edge_points, warnings)
    }

    /// `problem` with its checks: refused when no dwell point reaches the map, warned when a
    /// large share reaches nothing.
    fn built(
        &self,
        problem: Problem,
        edge_points: usize,
        mut warnings: Vec<String>,
    ) -> SetupResult<Built> {
        let empty = problem.empty_columns().len();
        if let Some(why) = plausible::no_dwell_point_reaches_the_map(empty, problem.n(), &self.tif)
        {
            return Err(Error::invalid("dwell path", why)).at(SetupInput::None);
        }
        warnings.extend(plausible::unreachable_share_warning(empty, problem.n()));
        Ok(Built {
            problem,
            edge_points,
            warnings,
        })
    }

    /// The robust plan's problem over `rows` ([`robust`]): the scenarios' assembled matrices
    /// stacked against the target repeated, `rho` and `lambda` times the scenario count (the
    /// mean over the scenarios). Refused on a curved part or with a curvature-dependent TIF, and
    /// with an operator other than the assembled `R`.
    fn robust_problem(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
        observer: &dyn Observer,
    ) -> SetupResult<Problem> {
        if self.surface.is_some() || !matches!(self.tif_model, TifModel::ShiftInvariant) {
            return Err(Error::invalid(
                "robust",
                "not built on a curved part or with a curvature-dependent TIF",
            ))
            .at(SetupInput::Job);
        }
        if !matches!(
            self.settings.operator,
            OperatorChoice::Auto | OperatorChoice::Sparse
        ) {
            return Err(Error::invalid(
                "robust",
                "the robust plan stacks the scenarios' assembled matrices: use operator = \
                 \"auto\" or \"sparse\"",
            ))
            .at(SetupInput::Job);
        }
        let scenarios = robust::SCENARIOS.len();
        let stacked = robust::stacked_matrix(
            rows.x_mm(),
            rows.y_mm(),
            &self.path,
            self.swept.as_ref().map(|s| &s.0),
            &self.tif,
            observer,
        )
        .at(SetupInput::None)?;
        warnings.push(format!(
            "robust: the plan minimises the mean residual over {scenarios} scenarios (nominal, \
             TIF 3% wider and narrower, tool 0.05 mm off in x and y), {:.2e} non-zeros in the \
             stacked R",
            stacked.nnz() as f64
        ));
        let z_nm = rows.z_nm().repeat(scenarios);
        let s = scenarios as f64;
        Problem::new(
            stacked,
            z_nm,
            self.bounds.clone(),
            self.rho * s,
            self.lambda * s,
        )
        .and_then(|p| {
            p.with_dwell_lattice(DwellLattice::detect(self.path.x_mm(), self.path.y_mm()))
        })
        .at(SetupInput::Job)
    }

    /// Solves `problem` (built by [`Setup::problem`]): the acceleration-limited SCP when the
    /// set-up has a limit, the dwell solver the settings choose otherwise (from the warm start
    /// if there is one). Computes the removal `R t` and the feed schedule once.
    pub fn solve(&self, problem: &Problem, observer: &dyn Observer) -> Result<Outcome> {
        observer.setup_step(SetupStep::Solve);
        let m = self.map.len();
        let edge_rows = problem.m() > m;
        let (solution, removal_all, accel) = match &self.accel {
            Some(limits) => {
                let a =
                    accel::solve_validated(problem, &self.path, limits, &self.settings, observer)?;
                let mut report = a.report;
                observer.setup_step(SetupStep::Removal);
                let removal = problem.removal_nm(&a.solution.dwell_s)?;
                if edge_rows {
                    // The SCP's RMS figures are over every row; give them on the measured map.
                    let on_map = |h: &[f64]| {
                        HeightStats::of(&centred_residual_nm(self.map.z_nm(), &h[..m])).rms_nm
                    };
                    report.rms_after_nm = on_map(&removal);
                    report.rms_after_reference_nm =
                        on_map(&problem.removal_nm(&a.reference.dwell_s)?);
                }
                (a.solution, removal, Some(report))
            }
            None => {
                let s = dwell::solve_validated(
                    problem,
                    &self.settings,
                    observer,
                    self.warm_start_s.as_deref(),
                )?;
                observer.setup_step(SetupStep::Removal);
                let removal = problem.removal_nm(&s.dwell_s)?;
                (s, removal, None)
            }
        };
        let (solution, removal_all, executed) = match (&self.accel, &self.surface) {
            (Some(l), None) => {
                let first = self.executed_at_limit(&solution.dwell_s, l.a_max_mm_per_s2, observer);
                if l.method == AccelMethod::CorrectionPasses {
                    self.correction_passes(problem, l, solution, removal_all, first, observer)?
                } else {
                    (solution, removal_all, Some(first))
                }
            }
            _ => (solution, removal_all, None),
        };
        let mut removal_nm = removal_all;
        removal_nm.truncate(m);
        let mut solution = solution;
        // A solve that ran away (a non-finite or astronomically large figure) is no answer.
        if !solution_is_finite(&solution, &removal_nm) {
            solution.status = Status::NumericalError;
        }
        let approximation = self.exact_removal(problem, &solution.dwell_s, observer)?;
        if let Some(a) = &approximation {
            // The report gives the exact residual of the dwell returned, and where the problem
            // has no rows beyond the map, its piston and objective.
            removal_nm.clone_from(&a.exact_removal_nm);
            if problem.m() == m && m > 0 {
                let d: Vec<f64> = removal_nm
                    .iter()
                    .zip(self.map.z_nm())
                    .map(|(h, z)| h - z)
                    .collect();
                let piston = d.iter().sum::<f64>() / m as f64;
                solution.piston_nm = piston;
                solution.objective = 0.5 * d.iter().map(|v| (v - piston).powi(2)).sum::<f64>();
            }
        }
        let approximation = approximation.map(|a| a.error);
        observer.setup_step(SetupStep::FeedSchedule);
        let feeds = feeds_mm_per_min(&self.ds_mm, &solution.dwell_s);
        let schedule = FeedSchedule::new(
            &self.path,
            &solution.dwell_s,
            self.accel.as_ref().map(|l| l.a_max_mm_per_s2),
            self.corner_angle_deg,
        )?;
        let sensitivity = match &executed {
            Some(Ok(e)) => Some(sensitivity::of_executed(
                self.map.x_mm(),
                self.map.y_mm(),
                self.map.z_nm(),
                &e.run.contact,
                &e.run.removal_nm,
                &self.tif,
                observer,
            )?),
            _ => None,
        };
        Ok(Outcome {
            solution,
            removal_nm,
            feeds_mm_per_min: feeds,
            schedule,
            accel,
            executed,
            approximation,
            sensitivity,
        })
    }

    /// With an approximate operator (the spreading operator): the removal of `dwell_s` by the
    /// exact `R` (summed directly, [`crate::influence::direct`]) at the measured map points and
    /// the operator's measured error on it. `None` for the exact operators.
    fn exact_removal(
        &self,
        problem: &Problem,
        dwell_s: &[f64],
        observer: &dyn Observer,
    ) -> Result<Option<Exact>> {
        use crate::influence::operator::OperatorKind;
        let tolerance = match problem.operator_kind() {
            OperatorKind::FftSpread => self.settings.spread_tolerance,
            OperatorKind::Nufft => crate::influence::nufft::DEFAULT_NUFFT_TOLERANCE,
            _ => return Ok(None),
        };
        if self.surface.is_some() {
            return Ok(None);
        }
        let m = self.map.len();
        let mut approx = problem.removal_nm(dwell_s)?;
        approx.truncate(m);
        // The exact removal of the plan's own model: with the swept model every dwell point's
        // stretch samples carry its dwell in proportion to their weights.
        let exact = match &self.swept {
            Some((stretches, _)) => {
                let (mut x, mut y, mut t) = (Vec::new(), Vec::new(), Vec::new());
                for (j, &tj) in dwell_s.iter().enumerate() {
                    for &[dx, dy, w] in stretches.of(j) {
                        x.push(self.path.x_mm()[j] + dx);
                        y.push(self.path.y_mm()[j] + dy);
                        t.push(tj * w);
                    }
                }
                crate::influence::direct::removal_nm(
                    self.map.x_mm(),
                    self.map.y_mm(),
                    &x,
                    &y,
                    &t,
                    &self.tif,
                    observer,
                )?
            }
            None => crate::influence::direct::removal_nm(
                self.map.x_mm(),
                self.map.y_mm(),
                self.path.x_mm(),
                self.path.y_mm(),
                dwell_s,
                &self.tif,
                observer,
            )?,
        };
        let norm = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x * x).sum::<f64>().sqrt();
        let diff = norm(&mut approx.iter().zip(&exact).map(|(a, e)| a - e));
        let size = norm(&mut exact.iter().copied());
        let rms = |h: &[f64]| HeightStats::of(&centred_residual_nm(self.map.z_nm(), h)).rms_nm;
        let error = OperatorError {
            relative_removal_error: if size > 0.0 { diff / size } else { 0.0 },
            tolerance,
            rms_after_operator_nm: rms(&approx),
            rms_after_exact_nm: rms(&exact),
        };
        Ok(Some(Exact {
            exact_removal_nm: exact,
            error,
        }))
    }

    /// Correction passes against the executed program ([`AccelMethod::CorrectionPasses`]):
    /// from `solution` (removal `removal_all` over every row, executed run `first`), each pass
    /// re-solves the feed-limited problem for the target less the executed removal's departure
    /// from the plan's on the measured map, `z_i - (h_exec_i - (R t)_i)`, warm-started from the
    /// last dwell times, and executes the result; a pass is kept while the executed RMS falls by
    /// more than [`PASS_GAIN`], at most [`MAX_CORRECTION_PASSES`] passes.
    #[allow(clippy::type_complexity)]
    fn correction_passes(
        &self,
        problem: &Problem,
        limits: &AccelLimits,
        solution: Solution,
        removal_all: Vec<f64>,
        first: Result<Executed>,
        observer: &dyn Observer,
    ) -> Result<(Solution, Vec<f64>, Option<Result<Executed>>)> {
        let mut current = match first {
            Ok(e) => e,
            Err(e) => return Ok((solution, removal_all, Some(Err(e)))),
        };
        let (mut solution, mut removal_all) = (solution, removal_all);
        let m = self.map.len();
        for _ in 0..MAX_CORRECTION_PASSES {
            // The executed departure from the plan, on the measured rows of every scenario's
            // block (one block unless the plan is robust).
            let blocks = if self.settings.robust {
                robust::SCENARIOS.len()
            } else {
                1
            };
            let block = problem.m() / blocks;
            let mut target = problem.z_nm().to_vec();
            for b in 0..blocks {
                for i in 0..m {
                    target[b * block + i] -= current.run.removal_nm[i] - removal_all[i];
                }
            }
            let pass = problem.with_target_nm(target)?;
            let s =
                dwell::solve_validated(&pass, &self.settings, observer, Some(&solution.dwell_s))?;
            // A pass whose plan cannot be written as a program is not kept.
            let Ok(e) = self.executed_at_limit(&s.dwell_s, limits.a_max_mm_per_s2, observer) else {
                break;
            };
            if e.after.rms_nm >= current.after.rms_nm * (1.0 - PASS_GAIN) {
                break;
            }
            removal_all = problem.removal_nm(&s.dwell_s)?;
            solution = s;
            current = Executed {
                correction_passes: current.correction_passes + 1,
                ..e
            };
        }
        Ok((solution, removal_all, Some(Ok(current))))
    }

    /// The removal `R t` of given dwell times `dwell_s` at the measured map points, nm (edge
    /// rows dropped), with `problem` built by [`Setup::problem`]: a plan evaluated, no solve.
    pub fn removal_of(
        &self,
        problem: &Problem,
        dwell_s: &[f64],
        observer: &dyn Observer,
    ) -> Result<Vec<f64>> {
        observer.setup_step(SetupStep::Removal);
        let mut removal = problem.removal_nm(dwell_s)?;
        removal.truncate(self.map.len());
        Ok(removal)
    }

    /// Runs `program` as the machine would (block by block under `kinematics`) and integrates
    /// the TIF along the contact motion at the measured map points, in pieces of at most
    /// `step_mm` of arc length (default [`default_sample_step_mm`]); `part`: the part geometry
    /// and the tool-centre offset along its normal, to map tool centres back to contact points
    /// (none: the program's X, Y are the contact points). The executed removal of a given
    /// program, as [`Setup::removal_of`] is of given dwell times; the set-up's dwell points are
    /// the program's marked points ([`DwellPoints::of_program`]) for the report.
    pub fn run_program(
        &self,
        program: &Program,
        kinematics: Kinematics,
        step_mm: Option<f64>,
        part: Option<(&dyn PartGeometry, f64)>,
        observer: &dyn Observer,
    ) -> Result<ProgramRun> {
        observer.setup_step(SetupStep::Removal);
        self.run_on_map(program, kinematics, step_mm, part, observer)
    }

    /// [`Setup::run_program`] without the step report (also the solve's executed program).
    fn run_on_map(
        &self,
        program: &Program,
        kinematics: Kinematics,
        step_mm: Option<f64>,
        part: Option<(&dyn PartGeometry, f64)>,
        observer: &dyn Observer,
    ) -> Result<ProgramRun> {
        let m = &self.map;
        run_on_map(
            program,
            kinematics,
            step_mm.unwrap_or_else(|| default_sample_step_mm(&self.tif)),
            part,
            m.x_mm(),
            m.y_mm(),
            &self.tif,
            observer,
        )
    }

    /// The default program for `dwell_s` (ISO, G94, flat part, the feed limit) executed at
    /// `a_max` with look-ahead, and the removal integrated along the executed motion
    /// ([`crate::machine::gcode::motion`]), on the measured map.
    fn executed_at_limit(
        &self,
        dwell_s: &[f64],
        a_max_mm_per_s2: f64,
        observer: &dyn Observer,
    ) -> Result<Executed> {
        let settings = NcSettings {
            a_max_mm_per_s2: Some(a_max_mm_per_s2),
            corner_angle_deg: self.corner_angle_deg,
            v_max_mm_per_min: self.feed.map(|f| f.v_max_mm_per_min),
            ..NcSettings::default()
        };
        let nc = NcProgram::plan(&self.path, dwell_s, &Flat, &settings)?;
        let check = write_and_check(&nc, &[])?;
        let kinematics = Kinematics::Trapezoidal {
            a_max_mm_per_s2,
            corner_angle_deg: settings.corner_angle_deg,
        };
        let run = self.run_on_map(&check.program, kinematics, None, None, observer)?;
        let after = HeightStats::of(&centred_residual_nm(self.map.z_nm(), &run.removal_nm));
        Ok(Executed {
            a_max_mm_per_s2,
            after,
            run,
            correction_passes: 0,
        })
    }
}

/// Cells of the FFT operator's lattice (pitch `pitch` mm) for `map` and `path`, padded by the
/// TIF's support radius `radius` mm on every side: the cost model's size.
fn fft_lattice_cells(map: &HeightMap, path: &DwellPath, radius: f64, pitch: f64) -> f64 {
    let span = |v: &mut dyn Iterator<Item = &f64>| {
        let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
        ((hi - lo).max(0.0) + 2.0 * radius) / pitch + 1.0
    };
    span(&mut map.x_mm().iter().chain(path.x_mm()))
        * span(&mut map.y_mm().iter().chain(path.y_mm()))
}

#[cfg(test)]
mod tests {
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
    fn the_lattice_kernel_is_the_assembled_swept_column_inside_the_raster() {
        // Map and raster on one 0.5 mm lattice: the FFT operator with the swept kernel gives the
        // assembled swept R's removal wherever only interior stretches reach (the row ends and
        // the path's ends, whose stretches differ, carry no dwell here).
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
        let (x0, x1) = (
            x.iter().cloned().fold(f64::INFINITY, f64::min),
            x.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
        );
        let t: Vec<f64> = x
            .iter()
            .zip(y)
            .map(|(&px, &py)| {
                if px > x0 + 0.25 && px < x1 - 0.25 {
                    1.0 + 0.1 * (px + 2.0 * py).sin()
                } else {
                    0.0
                }
            })
            .collect();
        let ha = pa.removal_nm(&t).unwrap();
        let hl = pl.removal_nm(&t).unwrap();
        let peak = ha.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
        for (a, l) in ha.iter().zip(&hl) {
            assert!((a - l).abs() <= 1e-9 * peak, "{a} vs {l}");
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
}
