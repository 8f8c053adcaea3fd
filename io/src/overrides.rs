//! Overrides of a job: what a user changes over a job file for one solve, in one definition that
//! both faces read. The command line parses it as the flags of `preston solve` (with the `clap`
//! feature, each field's doc comment its help); the Python package deserialises it from the
//! keywords of `preston.solve` (the same names, `_` for `-`; [`Overrides`] lists the aliases).
//! [`Overrides::apply`] is the only place where an override becomes a job key, so a new option is
//! a field here and a key of the job, and nothing per face.
//!
//! Each override replaces the job's key; a few replace a whole choice: a TIF file, a Gaussian
//! model or a Hertzian tool replaces the job's `[tif]`, and a dwell file or a raster pitch the
//! job's dwell source (given both, [`DwellSource::of`] refuses them as the job file does).

use crate::error::{Error, Result};
use crate::job::{DwellSource, Job, TifSource};
use preston_solver::dwell::accel::AccelMethod;
use preston_solver::dwell::{FirstOrderMethod, OperatorChoice, RobustWeighting, SolverChoice};
use preston_solver::edge::EdgeMethod;
use preston_solver::influence::model::surface::TifFrame;
use preston_solver::influence::InfluenceModel;
use preston_solver::path::raster::RasterAxis;
use preston_solver::tif::{GaussianTif, HertzParams};
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// What a solve changes over its job file. Every field is optional; an absent one leaves the
/// job's key as it is.
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct Overrides {
    /// Error map: CSV `x_mm,y_mm,z_nm` or any format of `preston map convert`.
    #[cfg_attr(feature = "clap", arg(long, value_name = "FILE"))]
    pub map: Option<PathBuf>,
    /// TIF grid file `x_mm,y_mm,rate_nm_per_s` (replaces the job's `[tif]`).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub tif: Option<PathBuf>,
    /// A truncated Gaussian TIF (replaces the job's `[tif]`).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub gaussian: Option<GaussianTif>,
    /// A spherical tool in Hertzian contact (replaces the job's `[tif]`, keeping its `pitch_mm`
    /// and `curvature_dependent`).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub hertz: Option<HertzParams>,
    /// Pitch of the grid on which the Hertz model on a flat part is sampled, mm.
    #[cfg_attr(feature = "clap", arg(long, value_name = "MM"))]
    pub tif_pitch_mm: Option<f64>,
    /// A calibration of the tool (calibration.json of `preston calibrate`): the plan includes the
    /// tool's drift, report.json's expected_rms_nm draws from its uncertainty; its calibrated
    /// TIF (tif.csv beside it) is the TIF unless one is given.
    #[cfg_attr(feature = "clap", arg(long, value_name = "calibration.json"))]
    pub calibration: Option<PathBuf>,
    /// With the Hertz model: one TIF per dwell point, its effective radius from the design
    /// surface's principal curvatures there (needs --surface or the job's [surface]).
    #[cfg_attr(
        feature = "clap",
        arg(long, num_args = 0..=1, default_missing_value = "true", value_name = "BOOL")
    )]
    pub curvature_dependent: Option<bool>,
    /// Dwell points CSV `x_mm,y_mm` in path order (replaces a raster pitch).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub dwell: Option<PathBuf>,
    /// Generate a serpentine raster at this pitch (mm) over the map extended by the TIF radius.
    #[cfg_attr(feature = "clap", arg(long, value_name = "MM"))]
    pub raster_pitch_mm: Option<f64>,
    /// Direction of the generated raster lines.
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub raster_along: Option<RasterAxis>,
    /// Start the first-order solver from the `dwell_s` column of a previous dwell.csv (same dwell
    /// points, in the same order).
    #[cfg_attr(feature = "clap", arg(long, value_name = "dwell.csv"))]
    pub warm_start: Option<PathBuf>,
    /// Fastest feed, mm/min (Python: `v_max`).
    #[cfg_attr(feature = "clap", arg(skip))]
    #[serde(alias = "v_max")]
    pub v_max_mm_per_min: Option<f64>,
    /// Slowest feed, mm/min (0 = no limit).
    #[cfg_attr(feature = "clap", arg(long = "v-min", value_name = "MM_PER_MIN"))]
    #[serde(alias = "v_min")]
    pub v_min_mm_per_min: Option<f64>,
    /// Acceleration limit along each path line, mm/s^2: |v_{j+1}^2 - v_j^2| <= 2 a s_j with s_j
    /// the distance between consecutive dwell points (on the command line, the machine's flags
    /// shared by solve, nc and simulate).
    #[cfg_attr(feature = "clap", arg(skip))]
    #[serde(alias = "a_max")]
    pub a_max_mm_per_s2: Option<f64>,
    /// How the acceleration limit is imposed (default: the job's, else correction-passes):
    /// correction-passes (default; the feed-limited plan re-solved against the program executed
    /// at the limit with look-ahead: the best part as the machine makes it, the controller holds
    /// the limit), squared-speed (the limit in the plan's own feeds: projected gradient in
    /// squared speed, any size and operator), scp-qp (sequential QP, the small-case reference)
    /// or squared-speed-then-scp-qp (the second refining the first).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub accel_method: Option<AccelMethod>,
    /// Turn angle (degrees) above which the path splits into lines for the acceleration limit
    /// and the machining time (default 60; on the command line, the machine's flags).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub corner_angle_deg: Option<f64>,
    /// How the dwell area beyond the map is modelled (default: the job's [edge], else none).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub edge: Option<EdgeMethod>,
    /// Width of the edge band beyond the map, mm (default: the TIF's nominal radius).
    #[cfg_attr(feature = "clap", arg(long, value_name = "MM"))]
    pub edge_width_mm: Option<f64>,
    /// Weight of total dwell time in the objective (nm^2 per s).
    #[cfg_attr(feature = "clap", arg(long))]
    pub rho: Option<f64>,
    /// Weight of dwell-time differences along the path (nm^2/s^2) (Python: `lambda_`).
    #[cfg_attr(feature = "clap", arg(long))]
    #[serde(alias = "lambda_")]
    pub lambda: Option<f64>,
    /// Find the smallest total dwell within --min-time-tolerance of the rho = 0 optimum.
    #[cfg_attr(
        feature = "clap",
        arg(long, num_args = 0..=1, default_missing_value = "true", value_name = "BOOL")
    )]
    pub min_time: Option<bool>,
    /// Relative objective tolerance of --min-time (default 0.001).
    #[cfg_attr(feature = "clap", arg(long))]
    pub min_time_tolerance: Option<f64>,
    /// Relative optimality tolerance of the solver (the QP's and the first-order solver's;
    /// defaults 1e-8 and 1e-6). The first-order solver stops when its gap bound, or its KKT
    /// residual, is below it. The residual is relative to the gradient at zero dwell and, where
    /// the plan removes more than 1 - 1e-5 of the objective (the RMS more than 316-fold), to
    /// what is left. `preston bench` reports how far above the optimum a tolerance lands
    /// (docs/benchmarks.md).
    #[cfg_attr(feature = "clap", arg(long))]
    pub tolerance: Option<f64>,
    /// Iteration of the first-order solver (default: the job's, else lbfgs).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub first_order_method: Option<FirstOrderMethod>,
    /// Correction pairs of the projected L-BFGS, 1 to 100 (default: the job's, else 10, or 5
    /// with the FFT operator). More pairs take fewer iterations: faster where a product costs far
    /// more than a pass over the dwell times (off-lattice stencil products), slower where the
    /// operator is cheap per dwell point (FFT-served maps); docs/off_lattice.md has the figures.
    #[cfg_attr(feature = "clap", arg(long, value_name = "PAIRS"))]
    pub lbfgs_memory: Option<usize>,
    /// Iteration limit of the solver.
    #[cfg_attr(feature = "clap", arg(long))]
    pub max_iterations: Option<usize>,
    /// Which solver to run (default: the job's, else auto).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub solver: Option<SolverChoice>,
    /// How R is held: assembled, or matrix-free by FFT (default: the job's, else auto).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub operator: Option<OperatorChoice>,
    /// How the plan models the tool at a dwell point: swept (the TIF averaged along the point's
    /// stretch of path at constant feed, as the program runs it) or point (the whole TIF at the
    /// point) (default: the job's, else swept).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub influence: Option<InfluenceModel>,
    /// Plan for the mean residual over the TIF-uncertainty scenarios (the TIF 3% wider and
    /// narrower, the tool 0.05 mm off in x and y, and the nominal): report.json `robust` gives
    /// both plans per scenario, what it costs nominally and saves in the worst scenario (job:
    /// `[solver] robust = true`). Each scenario's lattice operator (FFT, stencil, NUFFT or
    /// spreading) where the nominal plan takes one, else each scenario's assembled R.
    #[cfg_attr(
        feature = "clap",
        arg(long, num_args = 0..=1, default_missing_value = "true", value_name = "BOOL")
    )]
    pub robust: Option<bool>,
    /// How a robust plan weighs its scenarios: mean (equal weights, the default) or minimax
    /// (weights moved towards the worst scenario over up to 6 rounds, each a solve: the plan
    /// whose worst scenario is smallest) (job: `[solver] robust_weighting`).
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub robust_weighting: Option<RobustWeighting>,
    /// Largest estimated relative error of the off-lattice spreading operator against the
    /// assembled R (default: the job's, else 1e-4).
    #[cfg_attr(feature = "clap", arg(long))]
    pub spread_tolerance: Option<f64>,
    /// Design surface JSON of a curved part: the TIF acts in each dwell point's tangent plane.
    #[cfg_attr(feature = "clap", arg(long, value_name = "S.json"))]
    pub surface: Option<PathBuf>,
    /// Orientation of the TIF's x axis on a curved part.
    #[cfg_attr(feature = "clap", arg(long, value_enum))]
    pub tif_frame: Option<TifFrame>,
}

/// How the command line is named as the source of overrides ([`Overrides::apply`]): its
/// messages name the flag at fault (`--raster-pitch-mm`); any other source the keyword
/// (`raster_pitch_mm=`).
pub const COMMAND_LINE: &str = "<command line>";

/// The override `field` as its source spells it: the flag on the command line, the keyword
/// elsewhere (the Python call).
fn option_name(source: &Path, field: &str) -> String {
    if source == Path::new(COMMAND_LINE) {
        let flag = match field {
            "v_max_mm_per_min" => "v-max".to_string(),
            "v_min_mm_per_min" => "v-min".to_string(),
            _ => field.replace('_', "-"),
        };
        format!("--{flag}")
    } else {
        format!("{field}=")
    }
}

impl Overrides {
    /// The values given that cannot be meant, refused naming the flag (or keyword) rather than
    /// the job they would replace keys of: a raster pitch, the feed and acceleration limits
    /// and the corner angle, each by the rule the set-up stage applies to it.
    fn check_values(&self, source: &Path) -> Result<()> {
        let refuse = |field: &str, why: String| {
            Err(Error::Option {
                option: option_name(source, field),
                why,
            })
        };
        if let Some(p) = self.raster_pitch_mm {
            if !(p.is_finite() && p > 0.0) {
                return refuse(
                    "raster_pitch_mm",
                    format!("the raster pitch must be positive, got {p} mm"),
                );
            }
        }
        let one = |field: &str, machine: crate::job::MachineSection| {
            crate::job::check_machine_limits(&machine).or_else(|e| refuse(field, e.to_string()))
        };
        use crate::job::MachineSection as M;
        one(
            "v_max_mm_per_min",
            M {
                v_max_mm_per_min: self.v_max_mm_per_min,
                ..M::default()
            },
        )?;
        one(
            "v_min_mm_per_min",
            M {
                v_min_mm_per_min: self.v_min_mm_per_min,
                ..M::default()
            },
        )?;
        one(
            "a_max_mm_per_s2",
            M {
                a_max_mm_per_s2: self.a_max_mm_per_s2,
                ..M::default()
            },
        )?;
        one(
            "corner_angle_deg",
            M {
                corner_angle_deg: self.corner_angle_deg,
                ..M::default()
            },
        )
    }

    /// Applies every override given over `job`; `source` names where they come from in
    /// messages (the command line, [`COMMAND_LINE`], or the Python call). Refuses two
    /// overrides that exclude each other (two TIFs, a dwell file and a raster pitch) and a
    /// value that cannot be meant, naming the flag or keyword (a raster pitch, a machine
    /// limit).
    pub fn apply(self, job: &mut Job, source: &Path) -> Result<()> {
        self.check_values(source)?;
        let refuse = |why: &str| {
            Err(Error::Job {
                file: source.to_path_buf(),
                why: why.into(),
            })
        };
        let tifs = [
            self.tif.is_some(),
            self.gaussian.is_some(),
            self.hertz.is_some(),
        ];
        if tifs.iter().filter(|&&t| t).count() > 1 {
            return refuse("give one TIF: a file (tif), a Gaussian model or a Hertzian tool");
        }
        // A dwell source given replaces the job's.
        match DwellSource::of(self.dwell.clone(), self.raster_pitch_mm) {
            Ok(DwellSource::Unset) => {}
            Ok(given) => job.dwell.source = given,
            Err(why) => return refuse(why),
        }
        self.apply_tif(job);
        if let Some(m) = self.map {
            job.map.file = Some(m);
        }
        set(&mut job.dwell.raster_along, self.raster_along);
        if self.warm_start.is_some() {
            job.dwell.warm_start = self.warm_start;
        }
        let machine = &mut job.machine;
        set_some(&mut machine.v_max_mm_per_min, self.v_max_mm_per_min);
        set_some(&mut machine.v_min_mm_per_min, self.v_min_mm_per_min);
        set_some(&mut machine.a_max_mm_per_s2, self.a_max_mm_per_s2);
        set_some(&mut machine.corner_angle_deg, self.corner_angle_deg);
        set_some(&mut machine.accel_method, self.accel_method);
        set(&mut job.edge.method, self.edge);
        set_some(&mut job.edge.width_mm, self.edge_width_mm);
        set(&mut job.objective.rho, self.rho);
        set(&mut job.objective.lambda, self.lambda);
        let solver = &mut job.solver;
        set(&mut solver.min_time, self.min_time);
        set(&mut solver.min_time_tolerance, self.min_time_tolerance);
        // One tolerance and one iteration limit for whichever solver runs.
        set(&mut solver.tolerance, self.tolerance);
        set(&mut solver.first_order_tolerance, self.tolerance);
        set(&mut solver.max_iterations, self.max_iterations);
        set(&mut solver.first_order_max_iterations, self.max_iterations);
        set_some(&mut solver.lbfgs_memory, self.lbfgs_memory);
        set(&mut solver.first_order_method, self.first_order_method);
        set(&mut solver.solver, self.solver);
        set(&mut solver.operator, self.operator);
        set(&mut solver.influence, self.influence);
        set(&mut solver.robust, self.robust);
        set(&mut solver.robust_weighting, self.robust_weighting);
        set(&mut solver.spread_tolerance, self.spread_tolerance);
        set_some(&mut job.surface.file, self.surface);
        set(&mut job.surface.tif_frame, self.tif_frame);
        Ok(())
    }

    /// The TIF overrides: a file or a Gaussian model replaces the whole `[tif]`; a Hertzian tool
    /// keeps its sampling pitch and curvature dependence; then those two are set if given.
    fn apply_tif(&self, job: &mut Job) {
        // What the job knows of the tool's uncertainty stays with a replaced source.
        let known = TifSource {
            calibration: job.tif.calibration.clone(),
            rate_sigma: job.tif.rate_sigma,
            width_sigma: job.tif.width_sigma,
            offset_sigma_mm: job.tif.offset_sigma_mm,
            ..TifSource::default()
        };
        if let Some(f) = &self.tif {
            job.tif = TifSource {
                file: Some(f.clone()),
                ..TifSource::default()
            };
        }
        if let Some(g) = &self.gaussian {
            job.tif = TifSource {
                gaussian: Some(g.clone()),
                ..TifSource::default()
            };
        }
        if let Some(h) = &self.hertz {
            job.tif = TifSource {
                hertz: Some(h.clone()),
                pitch_mm: job.tif.pitch_mm,
                curvature_dependent: job.tif.curvature_dependent,
                ..TifSource::default()
            };
        }
        set_some(&mut job.tif.pitch_mm, self.tif_pitch_mm);
        set(&mut job.tif.curvature_dependent, self.curvature_dependent);
        job.tif.calibration = self.calibration.clone().or(known.calibration);
        job.tif.rate_sigma = known.rate_sigma;
        job.tif.width_sigma = known.width_sigma;
        job.tif.offset_sigma_mm = known.offset_sigma_mm;
    }
}

/// `*key = value` where the override is given.
fn set<T>(key: &mut T, value: Option<T>) {
    if let Some(v) = value {
        *key = v;
    }
}

/// `*key = Some(value)` where the override is given.
fn set_some<T>(key: &mut Option<T>, value: Option<T>) {
    if value.is_some() {
        *key = value;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn source() -> &'static Path {
        Path::new("<test>")
    }

    #[test]
    fn an_absent_override_leaves_the_job_and_a_given_one_replaces_its_key() {
        let mut job = Job::default();
        job.machine.v_max_mm_per_min = Some(3000.0);
        job.objective.rho = 2.0;
        job.solver.robust = true;
        let before = job.clone();
        Overrides::default().apply(&mut job, source()).unwrap();
        assert_eq!(job, before);
        let o = Overrides {
            v_min_mm_per_min: Some(1.0),
            robust: Some(false),
            tolerance: Some(1e-7),
            max_iterations: Some(50),
            ..Overrides::default()
        };
        o.apply(&mut job, source()).unwrap();
        assert_eq!(job.machine.v_max_mm_per_min, Some(3000.0));
        assert_eq!(job.machine.v_min_mm_per_min, Some(1.0));
        assert_eq!(job.objective.rho, 2.0);
        assert!(!job.solver.robust);
        assert_eq!(job.solver.tolerance, 1e-7);
        assert_eq!(job.solver.first_order_tolerance, 1e-7);
        assert_eq!(job.solver.max_iterations, 50);
        assert_eq!(job.solver.first_order_max_iterations, 50);
    }

    #[test]
    fn a_tif_or_dwell_choice_replaces_the_other_and_two_at_once_are_refused() {
        let mut job = Job::default();
        job.tif.pitch_mm = Some(0.1);
        job.dwell.source = DwellSource::Raster { pitch_mm: 1.0 };
        let o = Overrides {
            tif: Some("t.csv".into()),
            dwell: Some("d.csv".into()),
            ..Overrides::default()
        };
        o.apply(&mut job, source()).unwrap();
        assert_eq!(job.tif.file.as_deref(), Some(Path::new("t.csv")));
        assert_eq!(job.tif.pitch_mm, None);
        assert_eq!(job.dwell.source, DwellSource::File("d.csv".into()));
        let two = Overrides {
            tif: Some("t.csv".into()),
            gaussian: Some(GaussianTif::new(1.0, 10.0, 3.0).unwrap()),
            ..Overrides::default()
        };
        assert!(two.apply(&mut job, source()).is_err());
        let both = Overrides {
            dwell: Some("d.csv".into()),
            raster_pitch_mm: Some(0.5),
            ..Overrides::default()
        };
        let e = both.apply(&mut job, source()).unwrap_err().to_string();
        assert!(e.contains(crate::job::DWELL_FILE_OR_RASTER), "{e}");
    }

    #[test]
    fn python_keyword_names_and_unknown_ones() {
        let o: Overrides =
            serde_json::from_str(r#"{"v_max": 3000, "lambda_": 0.5, "edge": "none"}"#).unwrap();
        assert_eq!(o.v_max_mm_per_min, Some(3000.0));
        assert_eq!(o.lambda, Some(0.5));
        assert_eq!(o.edge, Some(EdgeMethod::None));
        let e = serde_json::from_str::<Overrides>(r#"{"vmax": 3000}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("vmax"), "{e}");
    }
}
