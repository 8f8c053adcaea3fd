//! The job's choices checked once: limits, weights, solver settings, edge model and TIF model
//! ([`Choices::check`] -> [`Checked`]).

use super::*;

/// Why a warm start and an acceleration limit are refused together.
pub(super) const WARM_START_WITH_ACCEL: &str =
    "cannot be combined with an acceleration limit: the \
    sequential convex programme starts from its own feed-limited optimum (drop the warm start or \
    the limit)";

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
    pub(super) choices: Choices,
    pub(super) accel: Option<AccelLimits>,
    pub(super) corner_angle_deg: f64,
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
