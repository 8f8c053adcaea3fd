//! Job files (TOML): everything a solve needs in one place. Unknown keys are errors, and file
//! paths are relative to the job file's directory.
//!
//! ```toml
//! [map]
//! file = "mirror_error_118x8mm.csv"      # x_mm,y_mm,z_nm, or .xyz/.npy/.dat/.datx/.h5
//! # format = "zygo-datx"                # optional: overrides the extension
//! # aperture = "circle:50"               # optional: circle:R[@x,y], annulus:R1,R2, rect:W,H, polygon:FILE
//! # remove = ["piston", "tilt", "power"] # optional: form terms removed by least squares
//!
//! [tif]
//! file = "tif_fluid_jet_10mm.csv"        # x_mm,y_mm,rate_nm_per_s; or instead:
//! # gaussian = { sigma_mm = 2.0, peak_rate_nm_per_s = 10.0, truncation_radius_mm = 6.0 }
//! # or a spherical tool in Hertzian contact, sampled on a grid of pitch_mm:
//! # hertz = { force_n = 10.0, tool_radius_mm = 16.0, tool_e_gpa = 0.005, tool_nu = 0.4,
//! #           part_e_gpa = 72.0, part_nu = 0.2, preston_k_mm2_per_n = 1e-7 }
//! # pitch_mm = 0.1
//! # curvature_dependent = true          # one Hertz TIF per dwell point from [surface]'s curvature
//!
//! [dwell]
//! raster_pitch_mm = 1.0                  # or: file = "path.csv" (x_mm,y_mm in path order)
//! raster_along = "x"
//!
//! [machine]
//! v_max_mm_per_min = 3000.0
//! v_min_mm_per_min = 0.0
//! a_max_mm_per_s2 = 500.0                # optional: acceleration limit (SCP)
//! corner_angle_deg = 60.0                # optional: lines split at turns sharper than this
//! # profile = "../machines/mill3.toml"   # optional: a machine profile file ([machine], [nc])
//!
//! [nc]                                   # optional: the machine profile (MachineProfile)
//! dialect = "fanuc"                      # feed_mode, work_offset, start_blocks, spindle_rpm, ...
//!
//! [objective]
//! rho = 0.0
//! lambda = 0.0
//!
//! [solver]
//! solver = "auto"
//! min_time = false
//!
//! [edge]                                 # optional: the dwell area beyond the map
//! method = "gaussian"                    # none, zero-band, gaussian, polynomial, gerchberg-papoulis
//! # width_mm = 5.0                       # band beyond the map (default: TIF nominal radius)
//!
//! [surface]                              # optional: a curved part
//! file = "design.json"                   # surface JSON; the TIF acts in the tangent plane
//! tif_frame = "path_tangent"             # or "machine_x"
//! ```

use crate::error::{Error, Result};
use crate::metrology::ApertureSpec;
pub use crate::metrology::MapSource;
use preston_solver::dwell::accel::{AccelLimits, AccelMethod};
use preston_solver::dwell::{FeedLimits, Settings};
use preston_solver::edge::EdgeSettings;
use preston_solver::influence::model::surface::TifFrame;
use preston_solver::kinematics::{
    check_a_max_mm_per_s2, check_corner_angle_deg, DEFAULT_CORNER_ANGLE_DEG,
};
use preston_solver::machine::compensation::NormalDisplacement;
use preston_solver::machine::profile::MachineProfile;
use preston_solver::path::raster::RasterAxis;
use preston_solver::setup::{Choices, TifModel};
use preston_solver::tif::{GaussianTif, HertzParams};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A solve job as written in a TOML file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Job {
    /// The error map.
    #[serde(default)]
    pub map: MapSource,
    /// The tool influence function.
    #[serde(default)]
    pub tif: TifSource,
    /// The dwell points.
    #[serde(default)]
    pub dwell: DwellSection,
    /// Feed limits (`v_max_mm_per_min` required unless given on the command line).
    #[serde(default)]
    pub machine: MachineSection,
    /// Weights of the objective.
    #[serde(default)]
    pub objective: ObjectiveWeights,
    /// Solver settings.
    #[serde(default)]
    pub solver: Settings,
    /// The machine profile of the NC output (`preston nc`, the solve's program check,
    /// `preston simulate --job`): dialect, feed mode, work offset, start and end blocks,
    /// spindle and coolant, tool radius and axis ([`MachineProfile`]).
    #[serde(default)]
    pub nc: MachineProfile,
    /// Normal-displacement compensation (`preston nc`): material table and load.
    #[serde(default)]
    pub compensation: Option<NormalDisplacement>,
    /// The design surface of a curved part (absent: a flat part).
    #[serde(default)]
    pub surface: SurfaceSource,
    /// Edge handling: how the dwell area beyond the map is modelled
    /// ([`preston_solver::edge`]).
    #[serde(default)]
    pub edge: EdgeSettings,
    /// Several tools in one solve (`[[tool]]`, [`crate::tools`]): each with its own TIF, dwell
    /// file and feed limits; when present, `[tif]` and `[dwell]` are not used.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tool: Vec<ToolSpec>,
}

/// The design surface on which the TIF is applied in each dwell point's tangent plane.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SurfaceSource {
    /// Surface JSON (as written by `preston fit`); absent: a flat part, plan-view offsets.
    pub file: Option<PathBuf>,
    /// Orientation of the TIF's x axis in the tangent plane.
    pub tif_frame: TifFrame,
}

/// Where the TIF comes from: a grid file, a Gaussian model or a Hertzian spherical tool (exactly
/// one).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TifSource {
    /// CSV file `x_mm,y_mm,rate_nm_per_s` on a regular grid.
    pub file: Option<PathBuf>,
    /// A truncated Gaussian model.
    pub gaussian: Option<GaussianTif>,
    /// A spherical tool in Hertzian contact ([`preston_solver::tif::hertz`]): contact radius
    /// `a = (3 F R_eff / (4 E*))^(1/3)`, Preston rate `K p v`.
    pub hertz: Option<HertzParams>,
    /// Pitch, mm, of the grid on which the `hertz` model on a flat part is sampled (the TIF of a
    /// shift-invariant solve; with `curvature_dependent` it sets the raster margin, the edge band
    /// and the TIF figure).
    pub pitch_mm: Option<f64>,
    /// With `hertz`: one Hertz TIF per dwell point, its effective radius from the `[surface]`'s
    /// principal curvatures there (`1/R' = 1/R_tool - k1`, `1/R'' = 1/R_tool - k2`,
    /// `R_eff = sqrt(R' R'')`); needs a design surface.
    #[serde(default)]
    pub curvature_dependent: bool,
    /// A calibration of the tool (`calibration.json` of `preston calibrate`): the plan includes
    /// its drift and the expected result draws from its uncertainty; its calibrated TIF is the
    /// job's TIF when `file`, `gaussian` and `hertz` are not set.
    pub calibration: Option<PathBuf>,
    /// Relative standard deviation of the TIF's rate before any calibration (default 0.07).
    pub rate_sigma: Option<f64>,
    /// Relative standard deviation of its width before any calibration (default 0.05).
    pub width_sigma: Option<f64>,
    /// Standard deviation of where the tool lands, mm, along each axis (default 0.2).
    pub offset_sigma_mm: Option<f64>,
}

/// The one TIF source a job names ([`TifSource::resolve`]).
#[derive(Debug, Clone, PartialEq)]
pub enum TifInput {
    /// A gridded TIF file.
    File(PathBuf),
    /// A truncated Gaussian model.
    Gaussian(GaussianTif),
    /// A Hertzian spherical tool.
    Hertz {
        /// The contact and process parameters.
        params: HertzParams,
        /// Pitch of the grid the flat-part model is sampled on, mm.
        pitch_mm: f64,
        /// One TIF per dwell point from the design surface's local curvatures.
        curvature_dependent: bool,
    },
}

impl TifSource {
    /// The one source this section names: exactly one of `file`, `gaussian` and `hertz` must be
    /// set; `pitch_mm` goes with (and is required by) `hertz`, as does `curvature_dependent`.
    pub fn resolve(&self, job_path: &Path) -> Result<TifInput> {
        let refuse = |why: &str| {
            Err(Error::Job {
                file: job_path.to_path_buf(),
                why: why.into(),
            })
        };
        if self.hertz.is_none() {
            if self.pitch_mm.is_some() {
                return refuse(
                    "[tif] pitch_mm is the grid of the `hertz` model; set hertz or drop it",
                );
            }
            if self.curvature_dependent {
                return refuse(
                    "[tif] curvature_dependent needs the `hertz` model (or --tif-model hertz)",
                );
            }
        }
        match (&self.file, &self.gaussian, &self.hertz) {
            (Some(f), None, None) => Ok(TifInput::File(f.clone())),
            (None, Some(g), None) => Ok(TifInput::Gaussian(g.clone())),
            (None, None, Some(h)) => match self.pitch_mm {
                Some(pitch_mm) => Ok(TifInput::Hertz {
                    params: h.clone(),
                    pitch_mm,
                    curvature_dependent: self.curvature_dependent,
                }),
                None => refuse(
                    "[tif] hertz needs pitch_mm, the pitch of the grid it is sampled on (or \
                     --tif-pitch-mm)",
                ),
            },
            (None, None, None) => refuse(
                "no TIF: set [tif] file, gaussian or hertz (or --tif / --gaussian-sigma-mm / \
                 --tif-model hertz)",
            ),
            _ => refuse("[tif] names more than one of `file`, `gaussian` and `hertz`; choose one"),
        }
    }

    /// How the TIF acts on the part: per dwell point from the local curvature when the section
    /// asks for it (`hertz` with `curvature_dependent`), one TIF for every point otherwise.
    pub fn model(&self) -> std::result::Result<TifModel, preston_solver::Error> {
        match (&self.hertz, self.curvature_dependent) {
            (Some(h), true) => Ok(TifModel::CurvatureDependent(h.clone())),
            (None, true) => Err(preston_solver::Error::invalid(
                "[tif] curvature_dependent",
                "needs the `hertz` model (or --tif-model hertz)",
            )),
            (_, false) => Ok(TifModel::ShiftInvariant),
        }
    }
}

/// Why a dwell file and a raster cannot both be given: the one message every face (the job
/// file's `file` and `raster_pitch_mm`, the command line's `--dwell` and `--raster-pitch-mm`,
/// the Python keywords `dwell=`/`dwell_xy=` and `raster_pitch_mm=`, a batch's jobs) gives, from
/// [`DwellSource::of`]. Short enough to survive the quoting of a parser's message.
pub const DWELL_FILE_OR_RASTER: &str =
    "give the dwell points as a file or a raster pitch, not both";

/// Where the dwell points come from: a file or a generated raster, the choice a type (one of
/// the two, or none given yet: the command line, the Python call or its arrays give them).
#[derive(Debug, Clone, PartialEq, Default)]
pub enum DwellSource {
    /// None named by the job (given elsewhere, or missing).
    #[default]
    Unset,
    /// CSV file `x_mm,y_mm` in path order.
    File(PathBuf),
    /// A generated serpentine raster over the map's bounding box extended by the TIF radius.
    Raster {
        /// Pitch, mm.
        pitch_mm: f64,
    },
}

impl DwellSource {
    /// The one rule "a dwell file or a raster, not both": the source a `file` and a
    /// `raster_pitch_mm` name (the job file's keys, or a face's flags and keywords), refused
    /// with [`DWELL_FILE_OR_RASTER`] when both are given.
    pub fn of(
        file: Option<PathBuf>,
        raster_pitch_mm: Option<f64>,
    ) -> std::result::Result<Self, &'static str> {
        match (file, raster_pitch_mm) {
            (Some(f), None) => Ok(Self::File(f)),
            (None, Some(pitch_mm)) => Ok(Self::Raster { pitch_mm }),
            (None, None) => Ok(Self::Unset),
            (Some(_), Some(_)) => Err(DWELL_FILE_OR_RASTER),
        }
    }

    /// The dwell file, if the source is one.
    pub fn file(&self) -> Option<&Path> {
        match self {
            Self::File(f) => Some(f),
            _ => None,
        }
    }

    /// The raster's pitch, mm, if the source is a raster.
    pub fn raster_pitch_mm(&self) -> Option<f64> {
        match self {
            Self::Raster { pitch_mm } => Some(*pitch_mm),
            _ => None,
        }
    }
}

/// The `[dwell]` section: the source of the dwell points ([`DwellSource`], written as `file` or
/// `raster_pitch_mm`), the raster's direction and a warm start.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(try_from = "DwellToml", into = "DwellToml")]
pub struct DwellSection {
    /// Where the dwell points come from.
    pub source: DwellSource,
    /// Direction of the generated raster's lines (and of the PSD's lines).
    pub raster_along: RasterAxis,
    /// A previous `dwell.csv` (with a `dwell_s` column, same points in the same order) to start
    /// the first-order solver from.
    pub warm_start: Option<PathBuf>,
}

/// `[dwell]` as written in the job file.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct DwellToml {
    /// CSV file `x_mm,y_mm` in path order.
    #[serde(default)]
    file: Option<PathBuf>,
    /// Pitch of a generated serpentine raster, mm.
    #[serde(default)]
    raster_pitch_mm: Option<f64>,
    /// Direction of the generated raster's lines.
    #[serde(default)]
    raster_along: RasterAxis,
    /// A previous `dwell.csv` to start from.
    #[serde(default)]
    warm_start: Option<PathBuf>,
}

impl TryFrom<DwellToml> for DwellSection {
    type Error = &'static str;
    fn try_from(t: DwellToml) -> std::result::Result<Self, Self::Error> {
        Ok(Self {
            source: DwellSource::of(t.file, t.raster_pitch_mm)?,
            raster_along: t.raster_along,
            warm_start: t.warm_start,
        })
    }
}

impl From<DwellSection> for DwellToml {
    fn from(d: DwellSection) -> Self {
        Self {
            raster_pitch_mm: d.source.raster_pitch_mm(),
            file: match d.source {
                DwellSource::File(f) => Some(f),
                _ => None,
            },
            raster_along: d.raster_along,
            warm_start: d.warm_start,
        }
    }
}

/// Machine limits as written in a job (each may be overridden on the command line).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineSection {
    /// Fastest feed, mm/min.
    pub v_max_mm_per_min: Option<f64>,
    /// Slowest feed, mm/min (0 = none).
    pub v_min_mm_per_min: Option<f64>,
    /// Acceleration limit along a line, mm/s^2: `|v_{j+1}^2 - v_j^2| <= 2 a_max s_j`, imposed by
    /// sequential convex programming ([`preston_solver::dwell::accel`]); none when absent.
    #[serde(default)]
    pub a_max_mm_per_s2: Option<f64>,
    /// Turn angle, degrees, above which the path splits into lines (connecting moves carry no
    /// acceleration constraint, the machine stops there); default 60.
    #[serde(default)]
    pub corner_angle_deg: Option<f64>,
    /// How the acceleration limit is imposed: `"correction-passes"` (default; the feed-limited
    /// plan re-solved against the program executed at the limit, the best part as made),
    /// `"squared-speed"` (the limit in the plan's own feeds: projected gradient in squared
    /// speed, any size and operator), `"scp-qp"` (the sequential QP reference) or
    /// `"squared-speed-then-scp-qp"` (the first, refined by the second).
    #[serde(default)]
    pub accel_method: Option<AccelMethod>,
    /// A machine profile file (`[machine]` and `[nc]` tables as in a job, relative to the job
    /// file): its keys apply where the job does not give them ([`Job::load_with_profile`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<PathBuf>,
}

/// A machine profile file: the `[machine]` and `[nc]` tables of a job, shared by the jobs that
/// run on one machine.
#[derive(Debug, Clone, PartialEq, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ProfileFile {
    #[serde(default)]
    machine: MachineSection,
    #[serde(default)]
    nc: MachineProfile,
}

/// Weights of the objective terms.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ObjectiveWeights {
    /// Weight of the total dwell time (nm^2 per s), >= 0.
    pub rho: f64,
    /// Weight of the squared differences of consecutive dwell times (nm^2/s^2), >= 0.
    pub lambda: f64,
}

/// Checks the `[machine]` limits a profile file gives that the job's own `[machine]` table
/// (`job_machine`) does not replace ([`check_machine_limits`]).
fn check_profile_machine(
    own: &MachineSection,
    job_machine: &toml::Table,
) -> std::result::Result<(), preston_solver::Error> {
    let from_profile = |key: &str, v: Option<f64>| v.filter(|_| !job_machine.contains_key(key));
    check_machine_limits(&MachineSection {
        v_max_mm_per_min: from_profile("v_max_mm_per_min", own.v_max_mm_per_min),
        v_min_mm_per_min: from_profile("v_min_mm_per_min", own.v_min_mm_per_min),
        a_max_mm_per_s2: from_profile("a_max_mm_per_s2", own.a_max_mm_per_s2),
        corner_angle_deg: from_profile("corner_angle_deg", own.corner_angle_deg),
        ..MachineSection::default()
    })
}

/// Checks each machine limit `machine` gives (the feed limits, the acceleration limit and the
/// corner angle) by the rule the set-up stage applies to it, so that a bad value is refused
/// where it was given (a profile file, a flag) rather than blamed on the job later. The
/// feed limits are checked against each other where both are given.
pub fn check_machine_limits(
    machine: &MachineSection,
) -> std::result::Result<(), preston_solver::Error> {
    let (v_max, v_min) = (machine.v_max_mm_per_min, machine.v_min_mm_per_min);
    if let Some(v) = v_max {
        FeedLimits {
            v_max_mm_per_min: v,
            v_min_mm_per_min: 0.0,
        }
        .validate()?;
    }
    if let Some(v) = v_min {
        FeedLimits {
            v_max_mm_per_min: v_max.unwrap_or(f64::MAX),
            v_min_mm_per_min: v,
        }
        .validate()?;
    }
    if let Some(a) = machine.a_max_mm_per_s2 {
        check_a_max_mm_per_s2(a)?;
    }
    if let Some(c) = machine.corner_angle_deg {
        check_corner_angle_deg(c)?;
    }
    Ok(())
}

impl Job {
    /// Reads a job file; relative paths in it are resolved against its directory, and the
    /// machine profile it names (`[machine] profile`) is applied ([`Job::load_with_profile`]).
    pub fn load(path: &Path) -> Result<Self> {
        Self::load_with_profile(Some(path), None)
    }

    /// The job in `job` (none: an empty job) on the machine of the profile file `profile`
    /// (none: the one the job names in `[machine] profile`, if any). A profile file holds
    /// `[machine]` and `[nc]` tables as a job does; the job's own keys in those tables win over
    /// the profile's, key by key, and the command line's flags over both. The merged `[nc]` is
    /// validated here, naming the file at fault.
    pub fn load_with_profile(job: Option<&Path>, profile: Option<&Path>) -> Result<Self> {
        let (mut parsed, text) = match job {
            Some(path) => {
                let text = crate::limits::read_document(path, "job file")?;
                let mut parsed = Self::parse(&text, path)?;
                parsed.resolve_paths(path.parent().unwrap_or_else(|| Path::new(".")));
                (parsed, text)
            }
            None => (Self::default(), String::new()),
        };
        let named = parsed.machine.profile.clone().map(|p| match job {
            Some(j) if p.is_relative() => j.parent().unwrap_or_else(|| Path::new(".")).join(p),
            _ => p,
        });
        let Some(profile) = profile.map(Path::to_path_buf).or(named) else {
            if let Some(path) = job {
                parsed.nc.validate().map_err(|e| Error::engine(path, e))?;
            }
            return Ok(parsed);
        };
        let job_table: toml::Table = text.parse().unwrap_or_default();
        let ptext = crate::limits::read_document(&profile, "machine profile")?;
        let job_error = |why: String| Error::Job {
            file: profile.clone(),
            why: crate::limits::quote_message(why.trim_end()),
        };
        // Typed first, for messages with the line at fault.
        let own: ProfileFile = toml::from_str(&ptext).map_err(|e| job_error(e.to_string()))?;
        // The profile's own machine limits, where the job does not replace them, are checked
        // here, so a bad one is blamed on the profile and its key.
        let job_machine = match job_table.get("machine") {
            Some(toml::Value::Table(t)) => t.clone(),
            _ => toml::Table::new(),
        };
        check_profile_machine(&own.machine, &job_machine)
            .map_err(|e| job_error(format!("[machine] {e}")))?;
        let mut merged: toml::Table = ptext
            .parse()
            .map_err(|e: toml::de::Error| job_error(e.to_string()))?;
        for section in ["machine", "nc"] {
            if let Some(toml::Value::Table(own)) = job_table.get(section) {
                let base = merged
                    .entry(section)
                    .or_insert_with(|| toml::Value::Table(toml::Table::new()));
                if let toml::Value::Table(base) = base {
                    for (k, v) in own {
                        if k != "profile" {
                            base.insert(k.clone(), v.clone());
                        }
                    }
                }
            }
        }
        let file: ProfileFile = toml::Value::Table(merged)
            .try_into()
            .map_err(|e: toml::de::Error| job_error(e.to_string()))?;
        if file.machine.profile.is_some() {
            return Err(job_error(
                "a machine profile may not name another profile ([machine] profile)".into(),
            ));
        }
        parsed.machine = MachineSection {
            profile: Some(profile.clone()),
            ..file.machine
        };
        parsed.nc = file.nc;
        // The merged `[nc]` is the profile's alone where the job has no `[nc]` table.
        let nc_from = match job {
            Some(j) if job_table.contains_key("nc") => j,
            _ => &profile,
        };
        parsed.nc.validate().map_err(|e| Error::Job {
            file: nc_from.to_path_buf(),
            why: format!("[nc] {e}"),
        })?;
        Ok(parsed)
    }

    /// Makes every relative file path of the job (map, TIF, dwell, warm start, surface, polygon
    /// aperture) relative to `base` instead (the job file's directory).
    pub fn resolve_paths(&mut self, base: &Path) {
        for p in [
            &mut self.map.file,
            &mut self.tif.file,
            &mut self.tif.calibration,
            &mut self.dwell.warm_start,
            &mut self.surface.file,
        ]
        .into_iter()
        .flatten()
        .chain(match &mut self.dwell.source {
            DwellSource::File(f) => Some(f),
            _ => None,
        }) {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
        for t in &mut self.tool {
            for p in [Some(&mut t.dwell), t.tif.file.as_mut()]
                .into_iter()
                .flatten()
            {
                if p.is_relative() {
                    *p = base.join(&*p);
                }
            }
        }
        if let Some(ApertureSpec::PolygonFile(p)) = &mut self.map.aperture {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
    }

    /// Every file the job reads (map, TIF, dwell, warm start, surface, polygon aperture and
    /// each tool's TIF and dwell), as its paths stand (after [`Job::resolve_paths`], relative to
    /// the working directory).
    pub fn input_files(&self) -> Vec<PathBuf> {
        let mut files: Vec<PathBuf> = [
            &self.map.file,
            &self.tif.file,
            &self.dwell.warm_start,
            &self.surface.file,
        ]
        .into_iter()
        .flatten()
        .cloned()
        .chain(self.dwell.source.file().map(Path::to_path_buf))
        .collect();
        for t in &self.tool {
            files.push(t.dwell.clone());
            files.extend(t.tif.file.iter().cloned());
        }
        if let Some(ApertureSpec::PolygonFile(p)) = &self.map.aperture {
            files.push(p.clone());
        }
        files
    }

    /// Parses job text; `path` names it in messages.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        preston_solver::counts::record(preston_solver::counts::Counted::JobParsed);
        toml::from_str(text).map_err(|e| Error::Job {
            file: path.to_path_buf(),
            why: crate::limits::quote_message(e.to_string().trim_end()),
        })
    }

    /// The feed limits, once command-line overrides are applied.
    pub fn feed_limits(&self) -> std::result::Result<FeedLimits, preston_solver::Error> {
        let v_max = self.machine.v_max_mm_per_min.ok_or_else(|| {
            preston_solver::Error::invalid(
                "v_max_mm_per_min",
                "is required (job [machine] or --v-max)",
            )
        })?;
        let limits = FeedLimits {
            v_max_mm_per_min: v_max,
            v_min_mm_per_min: self.machine.v_min_mm_per_min.unwrap_or(0.0),
        };
        limits.validate()?;
        Ok(limits)
    }

    /// The job's choices for the set-up stage ([`Choices::check`] validates them); the feed
    /// limit `v_max_mm_per_min` must be given.
    pub fn choices(&self) -> std::result::Result<Choices, preston_solver::Error> {
        let v_max = self.machine.v_max_mm_per_min.ok_or_else(|| {
            preston_solver::Error::invalid(
                "v_max_mm_per_min",
                "is required (job [machine] or --v-max)",
            )
        })?;
        self.choices_with_feed(Some(FeedLimits {
            v_max_mm_per_min: v_max,
            v_min_mm_per_min: self.machine.v_min_mm_per_min.unwrap_or(0.0),
        }))
    }

    /// As [`Job::choices`] with the feed limits given (`None` for several tools, each of which
    /// has its own).
    pub fn choices_with_feed(
        &self,
        feed: Option<FeedLimits>,
    ) -> std::result::Result<Choices, preston_solver::Error> {
        let tif_model = self.tif.model()?;
        if matches!(tif_model, TifModel::CurvatureDependent(_)) && self.surface.file.is_none() {
            return Err(preston_solver::Error::invalid(
                "[tif] curvature_dependent",
                "needs a design surface ([surface] file or --surface): the TIF of each dwell \
                 point follows the surface's curvature there",
            ));
        }
        Ok(Choices {
            feed,
            a_max_mm_per_s2: self.machine.a_max_mm_per_s2,
            corner_angle_deg: self.machine.corner_angle_deg,
            accel_method: self.machine.accel_method.unwrap_or_default(),
            rho: self.objective.rho,
            lambda: self.objective.lambda,
            settings: self.solver.clone(),
            edge: self.edge.clone(),
            tif_model,
            tif_frame: self.surface.tif_frame,
            warm_start: self.dwell.warm_start.is_some(),
        })
    }

    /// The settings of the program written for a plan of this job: the `[nc]` machine profile
    /// with the job's feed and acceleration limits, corner angle and compensation (what
    /// `preston nc --job` writes without flags).
    pub fn nc_settings(&self) -> preston_solver::machine::nc::NcSettings {
        preston_solver::machine::nc::NcSettings {
            a_max_mm_per_s2: self.machine.a_max_mm_per_s2,
            corner_angle_deg: self.corner_angle_deg(),
            compensation: self.compensation.clone(),
            v_max_mm_per_min: self.machine.v_max_mm_per_min,
            ..self.nc.nc_settings()
        }
    }

    /// Corner angle of the machine, degrees (`[machine] corner_angle_deg`, default 60).
    pub fn corner_angle_deg(&self) -> f64 {
        self.machine
            .corner_angle_deg
            .unwrap_or(DEFAULT_CORNER_ANGLE_DEG)
    }

    /// The acceleration limit with default SCP settings, when `[machine] a_max_mm_per_s2` is set;
    /// validated.
    pub fn accel_limits(&self) -> std::result::Result<Option<AccelLimits>, preston_solver::Error> {
        let Some(a) = self.machine.a_max_mm_per_s2 else {
            return Ok(None);
        };
        let limits = AccelLimits {
            a_max_mm_per_s2: a,
            corner_angle_deg: self.corner_angle_deg(),
            method: self.machine.accel_method.unwrap_or_default(),
            ..AccelLimits::default()
        };
        limits.validate()?;
        if self.solver.min_time {
            return Err(preston_solver::Error::invalid(
                "a_max_mm_per_s2",
                "cannot be combined with min_time (the SCP minimises the residual objective)",
            ));
        }
        Ok(Some(limits))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A job that names no acceleration method plans by correction passes against the program
    /// executed at the limit, as the command line and Python do.
    #[test]
    fn a_job_without_an_acceleration_method_plans_by_correction_passes() {
        let job = Job::parse(
            "[machine]\nv_max_mm_per_min = 3000\na_max_mm_per_s2 = 1000\n",
            Path::new("j.toml"),
        )
        .unwrap();
        assert_eq!(
            job.choices().unwrap().accel_method,
            AccelMethod::CorrectionPasses
        );
        assert_eq!(
            job.accel_limits().unwrap().map(|l| l.method),
            Some(AccelMethod::CorrectionPasses)
        );
    }

    #[test]
    fn unknown_keys_are_named() {
        let e = Job::parse(
            "[machine]\nv_max_mm_per_min = 1\nvmin = 2\n",
            Path::new("j.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("j.toml") && e.contains("vmin"), "{e}");
        let e = Job::parse("[solver]\nsolver = \"fastest\"\n", Path::new("j.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("fastest"), "{e}");
    }

    #[test]
    fn full_job_parses() {
        let j = Job::parse(
            "[map]\nfile='m.csv'\n[tif]\ngaussian={sigma_mm=2.0,peak_rate_nm_per_s=10.0,truncation_radius_mm=6.0}\n\
             [dwell]\nraster_pitch_mm=1.0\nraster_along='y'\n[machine]\nv_max_mm_per_min=3000\n\
             [objective]\nrho=0.5\n[solver]\nmin_time=true\n",
            Path::new("j.toml"),
        )
        .unwrap();
        assert_eq!(j.dwell.raster_along, RasterAxis::Y);
        assert_eq!(j.objective.rho, 0.5);
        assert!(j.solver.min_time);
        assert_eq!(j.feed_limits().unwrap().v_max_mm_per_min, 3000.0);
        assert_eq!(j.accel_limits().unwrap(), None);
    }

    #[test]
    fn hertz_tif_sections_resolve_to_one_model_or_are_refused() {
        let job = |tif: &str| {
            Job::parse(
                &format!(
                    "[machine]\nv_max_mm_per_min=3000\n[surface]\nfile='s.json'\n[tif]\n{tif}"
                ),
                Path::new("j.toml"),
            )
            .unwrap()
        };
        let j = job("hertz={force_n=20.0}\npitch_mm=0.1\ncurvature_dependent=true\n");
        let params = HertzParams {
            force_n: 20.0,
            ..HertzParams::default()
        };
        assert_eq!(
            j.tif.resolve(Path::new("j.toml")).unwrap(),
            TifInput::Hertz {
                params: params.clone(),
                pitch_mm: 0.1,
                curvature_dependent: true
            }
        );
        assert_eq!(
            j.choices().unwrap().tif_model,
            TifModel::CurvatureDependent(params)
        );
        let flat = job("hertz={}\npitch_mm=0.1\n");
        assert_eq!(flat.choices().unwrap().tif_model, TifModel::ShiftInvariant);
        // Without a surface, without the model, without the grid, with two models.
        let mut no_surface = j.clone();
        no_surface.surface.file = None;
        let e = no_surface.choices().unwrap_err().to_string();
        assert!(e.contains("design surface"), "{e}");
        for (tif, needle) in [
            (
                "file='t.csv'\ncurvature_dependent=true\n",
                "curvature_dependent",
            ),
            ("hertz={}\n", "pitch_mm"),
            ("file='t.csv'\npitch_mm=0.1\n", "pitch_mm"),
            ("file='t.csv'\nhertz={}\npitch_mm=0.1\n", "more than one"),
        ] {
            let e = job(tif)
                .tif
                .resolve(Path::new("j.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{tif}: {e}");
        }
    }

    #[test]
    fn map_options_parse_and_polygon_paths_resolve() {
        let dir = tempfile::tempdir().unwrap();
        let job = dir.path().join("j.toml");
        std::fs::write(
            &job,
            "[map]\nfile='m.datx'\nformat='zygo-datx'\nunits='mm,mm,um'\ncolumns='z,x,y'\n\
             pitch_mm=0.1\naperture='polygon:outline.csv'\nremove=['piston','tilt','power']\n",
        )
        .unwrap();
        let j = Job::load(&job).unwrap();
        assert_eq!(j.map.format, Some(crate::metrology::MapFormat::ZygoDatx));
        assert_eq!(j.map.remove.len(), 3);
        assert_eq!(j.map.pitch_mm, Some(0.1));
        assert_eq!(
            j.map.aperture,
            Some(ApertureSpec::PolygonFile(dir.path().join("outline.csv")))
        );
        let e = Job::parse("[map]\naperture='circle:-1'\n", Path::new("j.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("radius"), "{e}");
        let e = Job::parse("[map]\nremove=['focus']\n", Path::new("j.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("focus"), "{e}");
    }

    #[test]
    fn machine_tables_parse() {
        let j = Job::parse(
            "[machine]\nv_max_mm_per_min=3000\na_max_mm_per_s2=250\ncorner_angle_deg=45\n\
             [nc]\ntool_radius_mm=5\ntool_axis={type='fixed',b_deg=10}\n\
             [compensation]\ngrain_radius_mm=0.01\ngrain_sigma_mm=0.002\nforce_n=20\n\
             curvature_radius_mm=100\n[compensation.part]\ne_gpa=70\nnu=0.34\nhardness_gpa=0.06\n",
            Path::new("j.toml"),
        )
        .unwrap();
        let a = j.accel_limits().unwrap().unwrap();
        assert_eq!((a.a_max_mm_per_s2, a.corner_angle_deg), (250.0, 45.0));
        assert_eq!(j.nc.tool_radius_mm, 5.0);
        let c = j.compensation.unwrap();
        assert_eq!((c.force_n, c.part.e_gpa), (20.0, 70.0));
        assert_eq!(c.grain, NormalDisplacement::default().grain);
        let bad = Job::parse("[machine]\na_max_mm_per_s2=-1\n", Path::new("j.toml")).unwrap();
        assert!(bad.accel_limits().is_err());
        let e = Job::parse("[compensation]\nforce=1\n", Path::new("j.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("force"), "{e}");
    }
}

/// One tool of a multi-tool job (`[[tool]]` in the job file).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolSpec {
    /// The tool's TIF: `file` or `gaussian`, as in `[tif]`.
    #[serde(default)]
    pub tif: TifSource,
    /// The tool's dwell points, CSV `x_mm,y_mm` in path order.
    pub dwell: PathBuf,
    /// Fastest feed of this tool, mm/min (default: `[machine] v_max_mm_per_min`).
    #[serde(default)]
    pub v_max_mm_per_min: Option<f64>,
    /// Slowest feed of this tool, mm/min (default: `[machine] v_min_mm_per_min`, else 0).
    #[serde(default)]
    pub v_min_mm_per_min: Option<f64>,
    /// Weight of this tool's machining time in the `rho` term (default 1; > 0).
    #[serde(default)]
    pub time_weight: Option<f64>,
}
