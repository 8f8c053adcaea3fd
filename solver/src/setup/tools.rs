//! Several tools in one solve, through the set-up stage: each tool `k` has its own TIF (`R_k`),
//! dwell path and feed limits, and one optimisation runs over all dwell times at once,
//!
//! `min 0.5 ||sum_k R_k t_k - z - c 1||^2 + rho sum_k w_k sum_j t_kj`,
//! `ds_kj / v_max,k <= t_kj <= ds_kj / v_min,k`,
//!
//! with `w_k` the tool's machining-time weight (`time_weight`, default 1). With `u_k = w_k t_k`
//! this is the single-tool contract ([`crate::dwell`]) for the stacked operator
//! `[R_1 / w_1, R_2 / w_2, ...]` ([`crate::influence::operator::stacked`]) and the bounds scaled by `w_k`,
//! so the QP and the first-order solver run on it unchanged. Large and small tools in one plan:
//! the large tool takes the low spatial frequencies cheaply, the small one what it cannot reach.
//!
//! ```text
//! Choices::check -> ToolChoices::check --ToolsSetup::resolve--> ToolsSetup --problem--> Problem (stacked, scaled)
//! --solve--> ToolsOutcome { solution, each tool's dwell and removal, total removal }
//! ```
//!
//! What one stacked solve cannot hold is refused by [`ToolChoices::check`], naming the choice:
//! the smoothness term `lambda` (it would couple the last dwell of one tool to the first of the
//! next), an acceleration limit, a warm start, a curvature-dependent TIF and a matrix-free
//! operator (the stacked `R` is assembled). The map is used as measured: no edge extension.

use super::sensitivity::Sensitivity;
use super::{At, Checked, SetupInput, SetupResult, SetupStep, TifModel};
use crate::dwell::{self, DwellBounds, FeedLimits, OperatorChoice, Problem, Settings, Solution};
use crate::error::{Error, Result};
use crate::influence::operator::stacked::stack_scaled;
use crate::influence::{assemble_swept, InfluenceMatrix, InfluenceModel, Stretches};
use crate::map::HeightMap;
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::tif::Tif;

/// One tool: its TIF, path, path lengths, feed limits and machining-time weight.
#[derive(Debug, Clone)]
pub struct Tool {
    /// The TIF.
    pub tif: Tif,
    /// The dwell path.
    pub path: DwellPath,
    /// Path length per dwell point, mm ([`DwellPath::ds_mm`]).
    pub ds_mm: Vec<f64>,
    /// Feed limits.
    pub limits: FeedLimits,
    /// Machining-time weight `w_k` (> 0).
    pub time_weight: f64,
}

impl Tool {
    /// Tool number `k` (from 1, for messages): checks the feed limits and that the weight is
    /// positive and finite, and computes the path lengths.
    pub fn new(
        k: usize,
        tif: Tif,
        path: DwellPath,
        limits: FeedLimits,
        time_weight: f64,
    ) -> Result<Self> {
        limits.validate().map_err(|e| match e {
            Error::InvalidInput { what, why } => Error::invalid(what, format!("tool {k}: {why}")),
            e => e,
        })?;
        if !(time_weight.is_finite() && time_weight > 0.0) {
            return Err(Error::invalid(
                "time_weight",
                format!("tool {k}: must be positive, got {time_weight}"),
            ));
        }
        let ds_mm = path.ds_mm();
        Ok(Self {
            tif,
            path,
            ds_mm,
            limits,
            time_weight,
        })
    }
}

/// A multi-tool job resolved and validated once.
#[derive(Debug, Clone)]
pub struct ToolsSetup {
    /// The error map.
    pub map: HeightMap,
    /// The tools, in order.
    pub tools: Vec<Tool>,
    /// Weight of the (weighted) total dwell.
    pub rho: f64,
    /// Solver settings, validated.
    pub settings: Settings,
}

/// A finished multi-tool solve.
#[derive(Debug, Clone)]
pub struct ToolsOutcome {
    /// The solver's answer on the stacked problem (scaled dwell `u_k = w_k t_k`; its status).
    pub solution: Solution,
    /// Each tool's dwell times, s (`t_k = u_k / w_k`).
    pub dwell_s: Vec<Vec<f64>>,
    /// Removal of all tools together at the map points, `sum_k R_k t_k`, nm.
    pub removal_nm: Vec<f64>,
    /// Each tool's removal `R_k t_k` at the map points, nm.
    pub tool_removal_nm: Vec<Vec<f64>>,
    /// The plan's residual with every tool's TIF perturbed ([`super::sensitivity`]).
    pub sensitivity: Sensitivity,
}

/// Why `what` cannot be part of a multi-tool solve.
fn refuse(what: &str) -> Error {
    Error::invalid(
        "tool",
        format!("several tools cannot be combined with {what}"),
    )
}

/// The job's choices checked for a multi-tool solve: only [`ToolChoices::check`] makes one.
#[derive(Debug, Clone)]
pub struct ToolChoices {
    rho: f64,
    settings: Settings,
}

impl ToolChoices {
    /// Refuses what one stacked, assembled solve cannot hold (module documentation), before any
    /// input is read; the choices' feed limits are unused (each tool has its own).
    pub fn check(checked: Checked) -> SetupResult<Self> {
        let c = checked.choices();
        let refusal = if c.lambda > 0.0 {
            Some("lambda > 0 (it would couple one tool's path to the next)")
        } else if checked.accel().is_some() {
            Some("an acceleration limit")
        } else if c.warm_start {
            Some("a warm start")
        } else if matches!(c.tif_model, TifModel::CurvatureDependent(_)) {
            Some("a curvature-dependent TIF")
        } else if !matches!(
            c.settings.operator,
            OperatorChoice::Auto | OperatorChoice::Sparse
        ) {
            Some("a matrix-free operator (the stacked R is assembled)")
        } else {
            None
        };
        if let Some(what) = refusal {
            return Err(refuse(what)).at(SetupInput::Job);
        }
        Ok(Self {
            rho: c.rho,
            settings: c.settings.clone(),
        })
    }
}

impl ToolsSetup {
    /// The tools over `map` with the checked choices.
    pub fn resolve(choices: &ToolChoices, map: HeightMap, tools: Vec<Tool>) -> SetupResult<Self> {
        if tools.is_empty() {
            return Err(Error::invalid("tool", "no tools")).at(SetupInput::Job);
        }
        Ok(Self {
            map,
            tools,
            rho: choices.rho,
            settings: choices.settings.clone(),
        })
    }

    /// The stacked problem `[R_1 / w_1, R_2 / w_2, ...]` over the map with bounds `w_k ds / v`,
    /// each `R_k` under the settings' influence model (swept: tool `k`'s TIF averaged along
    /// each stretch of its own path, [`crate::influence::model::swept`]).
    pub fn problem(&self, observer: &dyn Observer) -> SetupResult<Problem> {
        observer.setup_step(SetupStep::BuildProblem);
        let mut blocks = Vec::with_capacity(self.tools.len());
        let (mut lower, mut upper, mut any_upper) = (Vec::new(), Vec::new(), false);
        for tool in &self.tools {
            let (mx, my) = (self.map.x_mm(), self.map.y_mm());
            let r = match self.settings.influence {
                // Each tool's TIF swept along its own path's stretches, as its program runs it.
                InfluenceModel::Swept => {
                    let stretches =
                        Stretches::of_path(&tool.path, super::default_sample_step_mm(&tool.tif))
                            .at(SetupInput::Dwell)?;
                    assemble_swept(mx, my, &tool.path, &stretches, &tool.tif, observer)
                }
                InfluenceModel::Point => InfluenceMatrix::assemble(
                    mx,
                    my,
                    tool.path.x_mm(),
                    tool.path.y_mm(),
                    &tool.tif,
                    observer,
                ),
            }
            .at(SetupInput::Map)?;
            let w = tool.time_weight;
            blocks.push((r, w));
            let b = DwellBounds::from_feeds(&tool.ds_mm, &tool.limits).at(SetupInput::Job)?;
            lower.extend(b.lower_s().iter().map(|l| l * w));
            match b.upper_s() {
                Some(u) => {
                    any_upper = true;
                    upper.extend(u.iter().map(|u| u * w));
                }
                None => upper.extend(std::iter::repeat_n(f64::INFINITY, tool.path.len())),
            }
        }
        let refs: Vec<(&InfluenceMatrix, f64)> = blocks.iter().map(|(r, w)| (r, *w)).collect();
        let stacked = stack_scaled(&refs).at(SetupInput::Job)?;
        let bounds = DwellBounds::new(lower, any_upper.then_some(upper)).at(SetupInput::Job)?;
        Problem::new(stacked, self.map.z_nm().to_vec(), bounds, self.rho, 0.0).at(SetupInput::Map)
    }

    /// The influence model every tool's `R_k` is built with.
    pub fn influence_model(&self) -> InfluenceModel {
        self.settings.influence
    }

    /// Solves `problem` (built by [`ToolsSetup::problem`]) and splits the answer by tool: each
    /// tool's dwell times and removal (through the stacked problem with every other block zero,
    /// so no tool's `R` is assembled twice) and the total removal.
    pub fn solve(&self, problem: &Problem, observer: &dyn Observer) -> Result<ToolsOutcome> {
        observer.setup_step(SetupStep::Solve);
        let solution = dwell::solve_validated(problem, &self.settings, observer, None)?;
        observer.setup_step(SetupStep::Removal);
        let removal_nm = problem.removal_nm(&solution.dwell_s)?;
        let mut dwell_s = Vec::with_capacity(self.tools.len());
        let mut tool_removal_nm = Vec::with_capacity(self.tools.len());
        let mut start = 0;
        for tool in &self.tools {
            let end = start + tool.path.len();
            let block = solution
                .dwell_s
                .get(start..end)
                .ok_or(Error::LengthMismatch {
                    what: "stacked dwell",
                    got: solution.dwell_s.len(),
                    expected: end,
                })?;
            dwell_s.push(block.iter().map(|u| u / tool.time_weight).collect());
            let mut u_k = vec![0.0; solution.dwell_s.len()];
            u_k[start..end].copy_from_slice(block);
            tool_removal_nm.push(problem.removal_nm(&u_k)?);
            start = end;
        }
        let sensitivity = self.sensitivity(&dwell_s, &removal_nm, observer)?;
        Ok(ToolsOutcome {
            solution,
            dwell_s,
            removal_nm,
            tool_removal_nm,
            sensitivity,
        })
    }

    /// The sensitivity of the plan (each tool's `dwell_s`, total removal `removal_nm`): every
    /// tool's TIF perturbed alike ([`super::sensitivity::MOTION_SCENARIOS`]) along its own
    /// motion at its programmed feeds (its stretch samples under the swept model), summed over
    /// the tools.
    fn sensitivity(
        &self,
        dwell_s: &[Vec<f64>],
        removal_nm: &[f64],
        observer: &dyn Observer,
    ) -> Result<Sensitivity> {
        let (mx, my) = (self.map.x_mm(), self.map.y_mm());
        let scenarios = &super::sensitivity::MOTION_SCENARIOS;
        let mut motion = vec![vec![0.0; mx.len()]; scenarios.len()];
        for (tool, t) in self.tools.iter().zip(dwell_s) {
            let stretches = match self.settings.influence {
                InfluenceModel::Swept => Some(Stretches::of_path(
                    &tool.path,
                    super::default_sample_step_mm(&tool.tif),
                )?),
                InfluenceModel::Point => None,
            };
            let samples = crate::simulate::plan::path_motion(&tool.path, stretches.as_ref(), t);
            let h = crate::simulate::direct::removals_in_plan(
                mx, my, &samples, &tool.tif, scenarios, observer,
            )?;
            for (sum, h) in motion.iter_mut().zip(h) {
                sum.iter_mut().zip(h).for_each(|(s, v)| *s += v);
            }
        }
        Sensitivity::of_removals(self.map.z_nm(), removal_nm, &motion)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::setup::Choices;
    use crate::tif::GaussianTif;

    /// Relative agreement of removals computed two ways (rounding only).
    const REMOVAL_TOL: f64 = 1e-12;

    /// The shared defaults (no limits, no weights, the assembled `R`).
    fn choices() -> Choices {
        Choices::evaluation(None)
    }

    fn two_tools() -> (HeightMap, Vec<Tool>) {
        let map = crate::setup::tests::grid_map_21(|x, y| {
            20.0 + 10.0 * (x / 3.0).sin() * (y / 4.0).cos()
        });
        let line = |n: usize, pitch: f64, y0: f64| {
            let xs: Vec<f64> = (0..n).map(|i| 1.0 + i as f64 * pitch).collect();
            DwellPath::new(xs, vec![y0; n]).unwrap()
        };
        let limits = FeedLimits {
            v_max_mm_per_min: 3000.0,
            v_min_mm_per_min: 0.0,
        };
        let big = Tif::Gaussian(GaussianTif::new(2.0, 5.0, 6.0).unwrap());
        let small = Tif::Gaussian(GaussianTif::new(0.7, 10.0, 2.1).unwrap());
        let tools = vec![
            Tool::new(1, big, line(9, 1.0, 5.0), limits, 1.0).unwrap(),
            Tool::new(2, small, line(17, 0.5, 4.0), limits, 3.0).unwrap(),
        ];
        (map, tools)
    }

    /// The sensitivity of several tools sums their motions: one tool split into two identical
    /// tools sharing its dwell has the same figures (each scenario's removal the sum of the
    /// tools' own).
    #[test]
    fn the_tools_sensitivity_sums_their_motions() {
        /// The same sums in another order.
        const SUM_REL_TOL: f64 = 1e-12;
        let (map, tools) = two_tools();
        let mut c = choices();
        c.settings.influence = InfluenceModel::Swept;
        let checked = ToolChoices::check(c.check(&Silent).unwrap()).unwrap();
        let one = ToolsSetup::resolve(&checked, map.clone(), vec![tools[0].clone()]).unwrap();
        let twice =
            ToolsSetup::resolve(&checked, map, vec![tools[0].clone(), tools[0].clone()]).unwrap();
        let t: Vec<f64> = (0..tools[0].path.len())
            .map(|j| 1.0 + 0.3 * j as f64)
            .collect();
        let half: Vec<f64> = t.iter().map(|v| v / 2.0).collect();
        let removal = vec![15.0; one.map.len()];
        let a = one.sensitivity(&[t], &removal, &Silent).unwrap();
        let b = twice
            .sensitivity(&[half.clone(), half], &removal, &Silent)
            .unwrap();
        for (x, y) in [
            (a.tif_wider_3pct, b.tif_wider_3pct),
            (a.tif_narrower_3pct, b.tif_narrower_3pct),
            (a.offset_x_0p05mm, b.offset_x_0p05mm),
            (a.offset_y_0p05mm, b.offset_y_0p05mm),
        ] {
            assert!(x.rms_nm > 0.0);
            assert!(
                (x.rms_nm - y.rms_nm).abs() <= SUM_REL_TOL * x.rms_nm,
                "{x:?} {y:?}"
            );
            assert!(
                (x.pv_nm - y.pv_nm).abs() <= SUM_REL_TOL * x.pv_nm,
                "{x:?} {y:?}"
            );
        }
    }

    /// Agreement of a tool's swept removal with its program swept by the simulator's midpoint
    /// rule (`SWEPT_SAMPLES` samples per stretch), relative to the largest removal: two
    /// quadratures of one integral, within the swept model's contract of 0.1% (3.5e-4 here).
    const SWEPT_TOL: f64 = 1e-3;
    const SWEPT_SAMPLES: usize = 256;

    #[test]
    fn each_tools_removal_is_its_own_assembled_r_times_its_dwell_and_they_sum() {
        for model in [InfluenceModel::Point, InfluenceModel::Swept] {
            tools_removal_under(model);
        }
    }

    /// Under `model`, each tool's removal is its dwell times its own `R_k` (point model: an
    /// independent assembly; swept model: the simulator sweeping the tool's TIF along its own
    /// path at constant feed per stretch), and the tools' removals sum to the total.
    fn tools_removal_under(model: InfluenceModel) {
        let (map, tools) = two_tools();
        let mut c = choices();
        c.settings.influence = model;
        let checked = ToolChoices::check(c.check(&Silent).unwrap()).unwrap();
        let setup = ToolsSetup::resolve(&checked, map, tools).unwrap();
        let problem = setup.problem(&Silent).unwrap();
        let out = setup.solve(&problem, &Silent).unwrap();
        let m = setup.map.len();
        let mut sum = vec![0.0; m];
        for (k, tool) in setup.tools.iter().enumerate() {
            let (h, tol) = match model {
                InfluenceModel::Point => {
                    let r = InfluenceMatrix::assemble(
                        setup.map.x_mm(),
                        setup.map.y_mm(),
                        tool.path.x_mm(),
                        tool.path.y_mm(),
                        &tool.tif,
                        &Silent,
                    )
                    .unwrap();
                    (r.removal_nm(&out.dwell_s[k]).unwrap(), REMOVAL_TOL)
                }
                InfluenceModel::Swept => (
                    crate::simulate::removal_nm(
                        setup.map.x_mm(),
                        setup.map.y_mm(),
                        &tool.path,
                        &out.dwell_s[k],
                        &tool.tif,
                        crate::simulate::Motion::Continuous {
                            samples_per_point: SWEPT_SAMPLES,
                        },
                        &Silent,
                    )
                    .unwrap(),
                    SWEPT_TOL,
                ),
            };
            let scale = h.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(1e-300);
            for (a, b) in h.iter().zip(&out.tool_removal_nm[k]) {
                assert!(
                    (a - b).abs() <= tol * scale,
                    "{model:?} tool {k}: {a} vs {b}"
                );
            }
            for (s, v) in sum.iter_mut().zip(&h) {
                *s += v;
            }
            // Dwell in seconds within the tool's own bounds.
            let b = DwellBounds::from_feeds(&tool.ds_mm, &tool.limits).unwrap();
            assert!(b.max_violation_s(&out.dwell_s[k]) <= 1e-12);
        }
        let scale = sum.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let tol = match model {
            InfluenceModel::Point => REMOVAL_TOL,
            InfluenceModel::Swept => SWEPT_TOL,
        };
        for (a, b) in sum.iter().zip(&out.removal_nm) {
            assert!((a - b).abs() <= tol * scale, "{model:?}: {a} vs {b}");
        }
    }

    #[test]
    fn what_one_stacked_solve_cannot_hold_is_refused() {
        let (_, tools) = two_tools();
        let cases: Vec<(Choices, &str)> = vec![
            (
                Choices {
                    lambda: 1.0,
                    ..choices()
                },
                "lambda",
            ),
            (
                Choices {
                    a_max_mm_per_s2: Some(100.0),
                    ..choices()
                },
                "acceleration",
            ),
            (
                Choices {
                    warm_start: true,
                    ..choices()
                },
                "warm start",
            ),
            (
                Choices {
                    settings: Settings {
                        operator: OperatorChoice::Fft,
                        ..Settings::default()
                    },
                    ..choices()
                },
                "matrix-free",
            ),
        ];
        for (c, what) in cases {
            let e = ToolChoices::check(c.check(&Silent).unwrap()).unwrap_err();
            assert_eq!(e.input, SetupInput::Job);
            assert!(e.to_string().contains(what), "{e} does not name {what}");
        }
        let bad_weight = Tool::new(
            2,
            tools[0].tif.clone(),
            tools[0].path.clone(),
            tools[0].limits,
            0.0,
        )
        .unwrap_err();
        assert!(bad_weight.to_string().contains("tool 2"), "{bad_weight}");
    }
}
