//! Dwell-time optimisation: the problem contract, solver settings and solutions.
//!
//! The contract (engine issue): minimise over `t` and a free piston `c`
//! `0.5 ||R t - z - c 1||^2 + rho sum(t) + 0.5 lambda ||D t||^2` subject to
//! `ds_j / v_max <= t_j <= ds_j / v_min`, where `D` differences consecutive dwell times.

pub mod accel;
pub mod bounds;
pub mod certificate;
pub mod first_order;
pub mod policy;
pub mod precond;
pub mod qp;

pub use bounds::{DwellBounds, FeedLimits};

use crate::error::{Error, Result};
use crate::influence::{InfluenceMatrix, InfluenceOperator, LinearOperator};
use crate::map::HeightStats;
use crate::observer::Observer;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, OnceLock};

pub use crate::influence::OperatorKind;

/// A validated dwell problem: the influence operator, the error map, bounds and weights.
#[derive(Debug, Clone)]
pub struct Problem {
    /// `R`, however it is held (shared by the problems derived from this one).
    operator: Arc<dyn InfluenceOperator>,
    z_nm: Vec<f64>,
    bounds: DwellBounds,
    rho: f64,
    lambda: f64,
    dwell_lattice: Option<Arc<precond::DwellLattice>>,
    /// The robust plan's rows: scenario blocks of equal height, block `s` scaled by `a_s`
    /// (`[a_1 R_1; ...]` against `[a_1 z; ...]`); `None` for one unscaled block.
    scenario_scales: Option<Arc<[f64]>>,
    /// The largest eigenvalue of the Jacobi-scaled Hessian `S (R^T P R + lambda D^T D) S` (a
    /// property of `R` and `lambda` alone), estimated by the first solve that needs it and kept
    /// for the next (the acceleration-limited stage after its feed-limited reference).
    scaled_hessian_norm: OnceLock<f64>,
}

/// How `R` is held and applied: `auto` uses a matrix-free operator (FFT on one lattice, phase
/// stencils off it) where it is predicted faster and the inputs allow it (see the set-up's
/// operator plans).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum OperatorChoice {
    /// A matrix-free operator where the cost models predict it faster than the assembled R and the
    /// inputs allow it: FFT on the map lattice, phase stencils or the spreading operator off it.
    ///
    /// The FFT operator when map and dwell points lie on one lattice, the TIF is applied in the
    /// plane, nothing needs the QP and the cost models of [`policy`] predict it faster than the
    /// assembled matrix (and the QP); for dwell points off the map lattice the phase stencils,
    /// then the spreading operator, where they serve and are predicted faster; the assembled
    /// matrix otherwise.
    #[default]
    Auto,
    /// Assemble the sparse influence matrix `R`.
    Sparse,
    /// Never form R: products by FFT convolution (map and dwell points on one lattice, first-order
    /// solver).
    ///
    /// Never form `R`: products by FFT convolution ([`fft::FftOperator`]). Needs map and dwell
    /// points on one regular lattice and the first-order solver.
    Fft,
    /// Never form R: dwell points spread onto an oversampled map lattice, then FFT (map on a
    /// lattice, dwell points anywhere, first-order solver; error within the spread tolerance).
    ///
    /// Never form `R`: dwell points spread onto an oversampled map lattice, then FFT convolution
    /// ([`crate::influence::SpreadOperator`]), with the smallest oversampling whose estimated
    /// error is within `spread_tolerance`. Needs map points on a regular lattice (dwell points
    /// anywhere) and the first-order solver.
    FftSpread,
    /// Never form R: one stencil per distinct dwell position within a map cell, scattered and
    /// gathered on the map lattice (exact; map on a lattice, first-order solver).
    ///
    /// Never form `R`: one stencil tabulated per distinct dwell position within a map cell, scattered
    /// and gathered on the map lattice ([`crate::influence::StencilOperator`]; exact, no
    /// tolerance). Needs map points on a regular lattice and the first-order solver; pays where
    /// the dwell raster's pitch is a rational multiple of the map's (few distinct positions).
    Stencil,
    /// Never form R: dwell points spread by the exponential-of-semicircle kernel onto a fine
    /// lattice, then FFT (map on a lattice, dwell points anywhere, first-order solver; its error
    /// against the exact R measured and reported).
    ///
    /// Never form `R`: dwell points spread by the exponential-of-semicircle kernel onto a fine
    /// lattice, then a deconvolved FFT convolution ([`crate::influence::NufftOperator`]; the
    /// error against the exact `R` measured, within
    /// [`crate::influence::operator::nufft::DEFAULT_NUFFT_TOLERANCE`] for `auto`). Needs map points on a
    /// regular lattice (dwell points anywhere) and the first-order solver.
    Nufft,
    /// Never form R for products: each column the TIF and its second-order expansion in the
    /// stretch's direction, spread from the stretch's centroid (four FFT convolutions), with the
    /// exact entries where the expansion is poor (a cut TIF's edge, odd stretches); error summed
    /// over every entry, within the spread tolerance (map on a lattice, first-order solver).
    ///
    /// Never form `R` for products ([`crate::influence::ExpansionOperator`]): the build assembles
    /// `R` once to choose the exact correction. For spirals and random paths under the swept
    /// model, and TIFs cut at a radius. Needs map points on a regular lattice and the first-order
    /// solver.
    Expansion,
}

impl Problem {
    /// Builds the problem over the influence operator `operator` (the assembled
    /// [`InfluenceMatrix`], or a matrix-free [`crate::influence::FftOperator`] or
    /// [`crate::influence::SpreadOperator`], which only the first-order solver can solve);
    /// `z_nm` has one entry per row of `R`, the bounds one per column, `rho >= 0` (nm^2 per s of
    /// dwell) and `lambda >= 0` (nm^2/s^2) finite.
    pub fn new(
        operator: impl InfluenceOperator + 'static,
        z_nm: Vec<f64>,
        bounds: DwellBounds,
        rho: f64,
        lambda: f64,
    ) -> Result<Self> {
        Self::build(Arc::new(operator), z_nm, bounds, rho, lambda)
    }

    /// [`Problem::new`] over an operator already boxed (one chosen at run time).
    pub fn from_boxed(
        operator: Box<dyn InfluenceOperator>,
        z_nm: Vec<f64>,
        bounds: DwellBounds,
        rho: f64,
        lambda: f64,
    ) -> Result<Self> {
        Self::build(Arc::from(operator), z_nm, bounds, rho, lambda)
    }

    fn build(
        operator: Arc<dyn InfluenceOperator>,
        z_nm: Vec<f64>,
        bounds: DwellBounds,
        rho: f64,
        lambda: f64,
    ) -> Result<Self> {
        let (m, n) = operator.shape();
        if z_nm.len() != m {
            return Err(Error::LengthMismatch {
                what: "z_nm",
                got: z_nm.len(),
                expected: m,
            });
        }
        if z_nm.is_empty() {
            return Err(Error::invalid("map", "has no points"));
        }
        if bounds.len() != n {
            return Err(Error::LengthMismatch {
                what: "dwell bounds",
                got: bounds.len(),
                expected: n,
            });
        }
        if let Some((i, z)) = z_nm.iter().enumerate().find(|(_, z)| !z.is_finite()) {
            return Err(Error::NonFinite {
                what: "map",
                index: i,
                detail: format!("z_nm={z}"),
            });
        }
        for (name, v) in [("rho", rho), ("lambda", lambda)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::invalid(name, format!("must be >= 0, got {v}")));
            }
        }
        Ok(Self {
            operator,
            z_nm,
            bounds,
            rho,
            lambda,
            dwell_lattice: None,
            scenario_scales: None,
            scaled_hessian_norm: OnceLock::new(),
        })
    }

    /// The same problem knowing that its dwell points lie on `lattice` (one cell per dwell
    /// point, in order; see [`precond::DwellLattice::detect`]): the first-order solver then
    /// preconditions with the circulant model of `R^T R`. A lattice of another length is an error.
    pub fn with_dwell_lattice(mut self, lattice: Option<precond::DwellLattice>) -> Result<Self> {
        if let Some(l) = &lattice {
            if l.len() != self.n() {
                return Err(Error::LengthMismatch {
                    what: "dwell lattice",
                    got: l.len(),
                    expected: self.n(),
                });
            }
        }
        self.dwell_lattice = lattice.map(Arc::new);
        Ok(self)
    }

    /// The same problem knowing that its rows are scenario blocks of equal height, block `s`
    /// scaled by `scales[s]` (the robust plan's `[a_1 R_1; ...]` against `[a_1 z; ...]`). Scales
    /// that are not positive and finite, or whose count does not divide the rows, are an error.
    pub fn with_scenario_scales(mut self, scales: Vec<f64>) -> Result<Self> {
        if scales.is_empty() || !self.m().is_multiple_of(scales.len()) {
            return Err(Error::LengthMismatch {
                what: "scenario blocks",
                got: scales.len(),
                expected: self.m(),
            });
        }
        if let Some(a) = scales.iter().find(|a| !(a.is_finite() && **a > 0.0)) {
            return Err(Error::invalid(
                "scenario scale",
                format!("must be positive and finite, got {a}"),
            ));
        }
        self.scenario_scales = Some(Arc::from(scales));
        Ok(self)
    }

    /// The scale of each block of rows (`[1.0]` unless [`Problem::with_scenario_scales`] says
    /// otherwise): the rows are `scenario_scales().len()` blocks of equal height.
    pub fn scenario_scales(&self) -> &[f64] {
        self.scenario_scales.as_deref().unwrap_or(&[1.0])
    }

    /// The dwell points' lattice, when they lie on one and the caller said so.
    pub fn dwell_lattice(&self) -> Option<&precond::DwellLattice> {
        self.dwell_lattice.as_deref()
    }

    /// The influence operator `R`, however it is held.
    pub fn operator(&self) -> &dyn InfluenceOperator {
        self.operator.as_ref()
    }

    /// The assembled influence matrix `R` (m x n); `None` for a matrix-free problem.
    pub fn influence(&self) -> Option<&InfluenceMatrix> {
        self.operator.downcast_ref::<InfluenceMatrix>()
    }

    /// The assembled `R`, or an error naming `who` for a matrix-free problem (the QP needs `R`).
    pub fn require_matrix(&self, who: &'static str) -> Result<&InfluenceMatrix> {
        self.influence().ok_or_else(|| {
            Error::invalid(
                who,
                "needs the assembled influence matrix, but this problem uses the matrix-free FFT \
                 operator: use the first-order solver or operator = \"sparse\"",
            )
        })
    }

    /// How `R` is held: assembled, matrix-free on one lattice, or spread onto the map lattice.
    pub fn operator_kind(&self) -> OperatorKind {
        self.operator.kind()
    }

    /// Whether `R` is matrix-free (no assembled matrix): only the first-order solver runs.
    pub fn is_matrix_free(&self) -> bool {
        self.operator.downcast_ref::<InfluenceMatrix>().is_none()
    }

    /// Non-zero entries of `R` (stored, or implicit in a matrix-free operator).
    pub fn nnz(&self) -> usize {
        self.operator.nnz()
    }

    /// Dwell points whose column of `R` is empty (no measurement point in the tool's reach).
    pub fn empty_columns(&self) -> Vec<usize> {
        self.operator.empty_columns()
    }

    /// Removal `h = R t`, nm, at the measurement points for dwell times `t` (s).
    pub fn removal_nm(&self, dwell_s: &[f64]) -> Result<Vec<f64>> {
        self.operator.removal_nm(dwell_s)
    }

    /// The height error to remove, nm.
    pub fn z_nm(&self) -> &[f64] {
        &self.z_nm
    }

    /// The dwell-time bounds.
    pub fn bounds(&self) -> &DwellBounds {
        &self.bounds
    }

    /// Weight of the total dwell time, `rho`.
    pub fn rho(&self) -> f64 {
        self.rho
    }

    /// Weight of the smoothness term, `lambda`.
    pub fn lambda(&self) -> f64 {
        self.lambda
    }

    /// Where the first-order solvers keep the largest eigenvalue of the Jacobi-scaled Hessian
    /// once estimated (see the field's documentation).
    pub(crate) fn scaled_hessian_norm(&self) -> &OnceLock<f64> {
        &self.scaled_hessian_norm
    }

    /// Number of measurement points `m`.
    pub fn m(&self) -> usize {
        self.operator.shape().0
    }

    /// Number of dwell points `n`.
    pub fn n(&self) -> usize {
        self.operator.shape().1
    }

    /// The same problem (operator, bounds, weights) with another target `z_nm` (one per row).
    pub fn with_target_nm(&self, z_nm: Vec<f64>) -> Result<Self> {
        let mut p = Self::build(
            Arc::clone(&self.operator),
            z_nm,
            self.bounds.clone(),
            self.rho,
            self.lambda,
        )?;
        p.dwell_lattice.clone_from(&self.dwell_lattice);
        p.scenario_scales.clone_from(&self.scenario_scales);
        // The scaled Hessian `S (R^T P R + lambda D^T D) S` does not depend on the target: a
        // norm estimated for this problem serves the new one.
        if let Some(&norm) = self.scaled_hessian_norm.get() {
            let _ = p.scaled_hessian_norm.set(norm);
        }
        Ok(p)
    }

    /// The same problem with other weights (used by the minimum-time mode).
    pub fn with_weights(&self, rho: f64, lambda: f64) -> Result<Self> {
        let mut p = Self::build(
            Arc::clone(&self.operator),
            self.z_nm.clone(),
            self.bounds.clone(),
            rho,
            lambda,
        )?;
        p.dwell_lattice.clone_from(&self.dwell_lattice);
        p.scenario_scales.clone_from(&self.scenario_scales);
        Ok(p)
    }

    /// The problem without the listed columns (sorted, unique), and the kept column indices.
    /// The removed dwell points' lower-bound removal is not included (callers put them at the
    /// lower bound only when their columns are empty).
    /// Needs the assembled matrix.
    pub fn without_columns(&self, removed: &[usize]) -> Result<(Self, Vec<usize>)> {
        let csc = self.require_matrix("column selection")?.csc();
        let n = csc.ncols();
        let mut keep = vec![true; n];
        for &j in removed {
            if let Some(k) = keep.get_mut(j) {
                *k = false;
            }
        }
        let kept: Vec<usize> = (0..n).filter(|&j| keep[j]).collect();
        let (off, rows, vals) = csc.csc_data();
        let mut new_off = Vec::with_capacity(kept.len() + 1);
        new_off.push(0);
        let mut new_rows = Vec::new();
        let mut new_vals = Vec::new();
        for &j in &kept {
            let (a, b) = (off[j], off[j + 1]);
            new_rows.extend_from_slice(&rows[a..b]);
            new_vals.extend_from_slice(&vals[a..b]);
            new_off.push(new_rows.len());
        }
        let sub = nalgebra_sparse::CscMatrix::try_from_csc_data(
            csc.nrows(),
            kept.len(),
            new_off,
            new_rows,
            new_vals,
        )
        .map_err(|e| Error::Numerical {
            stage: "column selection",
            why: e.to_string(),
        })?;
        let lower: Vec<f64> = kept.iter().map(|&j| self.bounds.lower_s()[j]).collect();
        let upper = self
            .bounds
            .upper_s()
            .map(|u| kept.iter().map(|&j| u[j]).collect());
        let problem = Self::new(
            InfluenceMatrix::from_csc(sub),
            self.z_nm.clone(),
            DwellBounds::new(lower, upper)?,
            self.rho,
            self.lambda,
        )?
        .with_dwell_lattice(self.dwell_lattice().and_then(|l| l.subset(&kept)))?;
        Ok((problem, kept))
    }

    /// Evaluates a dwell vector: removal, optimal piston and the contract's objective terms.
    pub fn evaluate(&self, dwell_s: &[f64]) -> Result<Evaluation> {
        let removal_nm = self.removal_nm(dwell_s)?;
        let m = removal_nm.len() as f64;
        // Optimal piston: c = mean(R t - z).
        let piston_nm = removal_nm
            .iter()
            .zip(&self.z_nm)
            .map(|(h, z)| h - z)
            .sum::<f64>()
            / m;
        let residual_sq: f64 = removal_nm
            .iter()
            .zip(&self.z_nm)
            .map(|(h, z)| {
                let r = h - z - piston_nm;
                r * r
            })
            .sum();
        let smooth_sq: f64 = dwell_s.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
        let total_dwell_s: f64 = dwell_s.iter().sum();
        Ok(Evaluation {
            objective: 0.5 * residual_sq,
            full_objective: 0.5 * residual_sq
                + self.rho * total_dwell_s
                + 0.5 * self.lambda * smooth_sq,
            piston_nm,
            total_dwell_s,
            removal_nm,
        })
    }

    /// Statistics of the error map before polishing.
    pub fn stats_before(&self) -> HeightStats {
        HeightStats::of(&self.z_nm)
    }
}

/// What a dwell vector achieves on a problem.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// `0.5 ||R t - z - c||^2` at the optimal piston `c` (nm^2).
    pub objective: f64,
    /// The whole contract objective, with the `rho` and `lambda` terms.
    pub full_objective: f64,
    /// Optimal piston `c = mean(R t - z)`, nm: the uniform extra layer removed.
    pub piston_nm: f64,
    /// Sum of dwell times, s.
    pub total_dwell_s: f64,
    /// Predicted removal `R t` at the measurement points, nm.
    pub removal_nm: Vec<f64>,
}

/// Which solver to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum SolverChoice {
    /// Sparse interior-point QP (Clarabel).
    Qp,
    /// First-order solver (projected L-BFGS, FISTA or projected Newton-CG; products with R only)
    /// with a KKT/gap certificate.
    ///
    /// The iterations of [`first_order`].
    FirstOrder,
    /// The first-order solver above about 1.6e5 non-zeros of R (a predicted 1 s of QP), the QP
    /// below and in minimum-time mode (cost models, docs/preconditioning.md).
    ///
    /// Choose by the cost models of [`policy`] (see [`SolverChoice::resolve`]); always the QP in
    /// minimum-time mode.
    #[default]
    Auto,
}

impl SolverChoice {
    /// The solver this choice runs on `problem` (resolves `auto` by the cost models of
    /// [`policy`]: the first-order solver on a matrix-free problem, the QP in minimum-time mode,
    /// otherwise the one predicted faster, the QP where it is predicted under
    /// [`policy::QP_CHEAP_S`]).
    pub fn resolve(self, problem: &Problem, min_time: bool) -> SolverKind {
        match self {
            SolverChoice::Qp => SolverKind::Qp,
            SolverChoice::FirstOrder => SolverKind::FirstOrder,
            SolverChoice::Auto if min_time => SolverKind::Qp,
            SolverChoice::Auto if problem.is_matrix_free() => SolverKind::FirstOrder,
            SolverChoice::Auto => {
                policy::choose(&policy::PolicyInputs {
                    nnz: problem.nnz() as f64,
                    fft_cells: None,
                    needs_qp: false,
                    solver: None,
                })
                .solver
            }
        }
    }
}

/// The solver that produced a solution.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SolverKind {
    /// Clarabel interior-point QP.
    Qp,
    /// Accelerated projected gradient with restart ([`first_order`]).
    FirstOrder,
}

pub use crate::status::Status;

/// Correction pairs the projected L-BFGS keeps by default ([`Settings::lbfgs_memory`]).
pub const DEFAULT_LBFGS_MEMORY: usize = 10;
/// Correction pairs it keeps by default where the products are cheap per dwell point (FFT
/// operators, [`crate::influence::LinearOperator::products_cheap_per_dwell_point`]).
pub const DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS: usize = 5;
/// Most correction pairs [`Settings::lbfgs_memory`] accepts.
pub const MAX_LBFGS_MEMORY: usize = 100;

/// Solver settings. Every field has a default; job files may set any of them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Settings {
    /// Which solver to run.
    pub solver: SolverChoice,
    /// Minimum-time mode: find the smallest total dwell whose objective is within
    /// `min_time_tolerance` (relative) of the `rho = 0` optimum.
    pub min_time: bool,
    /// Relative objective tolerance of the minimum-time mode (0.001 = 0.1%).
    pub min_time_tolerance: f64,
    /// Relative optimality tolerance.
    pub tolerance: f64,
    /// Iteration limit.
    pub max_iterations: usize,
    /// Wall-clock limit of one solve, s.
    pub time_limit_s: f64,
    /// Print the solver's iteration log (Clarabel prints it on stdout).
    pub verbose: bool,
    /// First-order solver: stop when the relative gap bound or the relative KKT residual is
    /// below this. The KKT residual is relative to the scaled gradient at zero dwell and, past a
    /// removal depth `f0 / f` of 1e5, to `sqrt(1e5 f / f0)` of it, so that the excess over the
    /// optimum it allows does not keep growing with the depth (`docs/preconditioning.md`).
    pub first_order_tolerance: f64,
    /// First-order solver: iteration limit (gradient or Hessian products).
    pub first_order_max_iterations: usize,
    /// First-order solver: the iteration ([`FirstOrderMethod`]).
    pub first_order_method: FirstOrderMethod,
    /// Projected L-BFGS: correction pairs kept (1 to [`MAX_LBFGS_MEMORY`]). Each pair costs two
    /// passes over the dwell vector an iteration and two vectors of memory. More pairs take fewer
    /// iterations, which pays where a product costs far more than those passes (assembled `R`,
    /// phase stencils) and not where it costs little more (FFT operators). `None` (the default):
    /// [`DEFAULT_LBFGS_MEMORY`], or [`DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS`] with an FFT
    /// operator; measured in `docs/off_lattice.md`.
    pub lbfgs_memory: Option<usize>,
    /// How `R` is held: assembled, or the matrix-free FFT operator ([`OperatorChoice`]). Read
    /// where the problem is built; the solvers follow the problem they are given.
    pub operator: OperatorChoice,
    /// First-order solver: the preconditioner of Newton-CG's conjugate gradients
    /// ([`Preconditioner`]).
    pub preconditioner: Preconditioner,
    /// Largest estimated relative operator error `||R~ - R||_F / ||R||_F` allowed for the
    /// off-lattice spreading operator ([`crate::influence::operator::spread`]) when `operator = "auto"`
    /// considers it (dwell points off the map lattice).
    pub spread_tolerance: f64,
    /// How the plan models the tool at a dwell point: swept along its stretch of path at
    /// constant feed, as the program runs it (the default), or the whole TIF at the point
    /// ([`crate::influence::InfluenceModel`]). Read where the problem is built.
    pub influence: crate::influence::InfluenceModel,
    /// Plan for the mean residual over the TIF-uncertainty scenarios (the TIF 3% wider and
    /// narrower, the tool 0.05 mm off in x and y, and the nominal) instead of the nominal alone
    /// ([`crate::setup::robust`]); needs the assembled `R`. Read where the problem is built.
    pub robust: bool,
    /// How a robust plan weighs its scenarios: their mean (the default) or, by reweighting
    /// rounds, the worst of them ([`RobustWeighting`]). Read where the problem is built.
    pub robust_weighting: RobustWeighting,
}

/// How a robust plan ([`Settings::robust`]) weighs its scenarios' squared residuals.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum RobustWeighting {
    /// Equal weights: the mean squared residual over the scenarios (the sample-average
    /// counterpart).
    #[default]
    Mean,
    /// Weights moved towards the worst scenario over a few rounds, each a solve: the plan whose
    /// worst scenario is smallest.
    Minimax,
}

/// The preconditioner of the projected Newton-CG's conjugate gradients.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Preconditioner {
    /// Jacobi scaling alone (the diagonal of the Hessian): the default.
    #[default]
    Jacobi,
    /// The circulant model of `R^T R` diagonalised by the FFT ([`precond`]) where the dwell
    /// points lie on a lattice (Jacobi scaling otherwise). Measured slower than FISTA on the
    /// generated problems (docs/preconditioning.md): the projection onto the bounds spoils the
    /// long-range steps it produces.
    Circulant,
}

/// The iteration of the first-order solver ([`first_order`]). All use only products with `R`
/// and `R^T`, on the same Jacobi-scaled variables, with the same stopping certificate.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum FirstOrderMethod {
    /// Accelerated projected gradient (FISTA) with adaptive restart.
    ///
    /// Accelerated projected gradient (FISTA) with adaptive restart: the cheapest iteration,
    /// but its KKT residual falls well before its objective does (0.7% above the optimum at
    /// 1e-6 on the generated 2e4 problem, docs/preconditioning.md).
    Fista,
    /// Projected Newton-CG.
    ///
    /// Projected Newton-CG: conjugate gradients on the free variables, projected line search.
    /// Far more accurate per product where `R` has more rows than columns and `rho = 0` (the
    /// sample job: 5e-5 relative above the optimum where FISTA is at 2e-4, in the same time),
    /// but slow to drive its KKT residual down when there are many more dwell points than map
    /// points or the problem is very ill-conditioned (README, "Benchmarks").
    NewtonCg,
    /// Projected L-BFGS with an exact line search along the projected step (the default).
    ///
    /// Projected L-BFGS: quasi-Newton directions on the free variables (the two-loop recursion
    /// on the pairs restricted to them), projected gradient steps on the binding ones, and an
    /// exact line search along the projected step; one Hessian product per iteration. The
    /// default: fewest products to a given objective on every problem measured
    /// (docs/preconditioning.md).
    #[default]
    Lbfgs,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            solver: SolverChoice::Auto,
            min_time: false,
            min_time_tolerance: 1e-3,
            tolerance: 1e-8,
            max_iterations: 200,
            time_limit_s: f64::INFINITY,
            verbose: false,
            first_order_tolerance: 1e-6,
            first_order_max_iterations: 20_000,
            first_order_method: FirstOrderMethod::default(),
            lbfgs_memory: None,
            operator: OperatorChoice::default(),
            preconditioner: Preconditioner::default(),
            spread_tolerance: crate::influence::operator::spread::DEFAULT_SPREAD_TOLERANCE,
            influence: crate::influence::InfluenceModel::default(),
            robust: false,
            robust_weighting: RobustWeighting::Mean,
        }
    }
}

impl Settings {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        crate::counts::record(crate::counts::Counted::SettingsValidated);
        if !(self.min_time_tolerance.is_finite() && self.min_time_tolerance > 0.0) {
            return Err(Error::invalid(
                "min_time_tolerance",
                format!("must be positive, got {}", self.min_time_tolerance),
            ));
        }
        if !(self.tolerance.is_finite() && self.tolerance > 0.0 && self.tolerance < 1.0) {
            return Err(Error::invalid(
                "tolerance",
                format!("must be in (0, 1), got {}", self.tolerance),
            ));
        }
        if !(self.first_order_tolerance.is_finite()
            && self.first_order_tolerance > 0.0
            && self.first_order_tolerance < 1.0)
        {
            return Err(Error::invalid(
                "first_order_tolerance",
                format!("must be in (0, 1), got {}", self.first_order_tolerance),
            ));
        }
        if self.first_order_max_iterations == 0 {
            return Err(Error::invalid(
                "first_order_max_iterations",
                "must be at least 1",
            ));
        }
        if !(self.spread_tolerance.is_finite()
            && self.spread_tolerance > 0.0
            && self.spread_tolerance < 1.0)
        {
            return Err(Error::invalid(
                "spread_tolerance",
                format!("must be in (0, 1), got {}", self.spread_tolerance),
            ));
        }
        if self.max_iterations == 0 {
            return Err(Error::invalid("max_iterations", "must be at least 1"));
        }
        if let Some(pairs) = self.lbfgs_memory {
            if !(1..=MAX_LBFGS_MEMORY).contains(&pairs) {
                return Err(Error::invalid(
                    "lbfgs_memory",
                    format!("must be 1 to {MAX_LBFGS_MEMORY} correction pairs, got {pairs}"),
                ));
            }
        }
        if self.time_limit_s.is_nan() || self.time_limit_s <= 0.0 {
            return Err(Error::invalid(
                "time_limit_s",
                format!("must be positive, got {}", self.time_limit_s),
            ));
        }
        if self.robust_weighting == RobustWeighting::Minimax && !self.robust {
            return Err(Error::invalid(
                "robust_weighting",
                "\"minimax\" weighs the scenarios of a robust plan: set robust = true (--robust)",
            ));
        }
        Ok(())
    }
}

/// The minimum-time stage's account of the `rho = 0` optimum it started from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MinTimeReport {
    /// Objective of the `rho = 0` optimum.
    pub objective_rho0: f64,
    /// Total dwell of the `rho = 0` optimum, s.
    pub total_dwell_rho0_s: f64,
    /// Relative tolerance allowed on the objective.
    pub tolerance: f64,
}

/// A solver's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct Solution {
    /// How the solve ended.
    pub status: Status,
    /// Which solver ran.
    pub solver: SolverKind,
    /// Dwell times, s, one per dwell point, inside the bounds.
    pub dwell_s: Vec<f64>,
    /// Optimal piston `c`, nm.
    pub piston_nm: f64,
    /// `0.5 ||R t - z - c||^2` at the optimal piston, nm^2.
    pub objective: f64,
    /// Iterations taken (summed over stages).
    pub iterations: usize,
    /// Wall-clock solve time, s.
    pub solve_seconds: f64,
    /// Projected-gradient (KKT) residual of the returned point, when computed.
    pub kkt_residual: Option<f64>,
    /// Proven upper bound on `full objective - optimum` (nm^2), when one exists.
    pub objective_gap_bound: Option<f64>,
    /// Why `objective_gap_bound` is absent.
    pub gap_bound_reason: Option<certificate::GapBoundReason>,
    /// Which test a converged solve met.
    pub converged_by: Option<certificate::ConvergenceCriterion>,
    /// The `rho = 0` stage of a minimum-time solve.
    pub min_time: Option<MinTimeReport>,
}

/// Solves the problem with the solver the settings choose.
///
/// Dwell points that no measurement point can feel (empty columns of `R`) do not change the
/// residual; without the smoothness term (`lambda = 0`) they are taken out of the solve and put on
/// their lower bound, which keeps them from making the problem degenerate. A matrix-free problem
/// keeps them in the (first-order) iteration, where their zero gradient leaves them unchanged, and
/// puts them on their lower bound afterwards.
pub fn solve(problem: &Problem, settings: &Settings, observer: &dyn Observer) -> Result<Solution> {
    solve_from(problem, settings, observer, None)
}

/// As [`solve`], starting the first-order solver from `warm_start_s` (one dwell time per dwell
/// point, s; projected onto the bounds). The QP ignores the start.
pub fn solve_from(
    problem: &Problem,
    settings: &Settings,
    observer: &dyn Observer,
    warm_start_s: Option<&[f64]>,
) -> Result<Solution> {
    settings.validate()?;
    solve_validated(problem, settings, observer, warm_start_s)
}

/// As [`solve_from`], with `settings` already validated (by [`crate::setup::Choices::check`]).
pub(crate) fn solve_validated(
    problem: &Problem,
    settings: &Settings,
    observer: &dyn Observer,
    warm_start_s: Option<&[f64]>,
) -> Result<Solution> {
    if let Some(w) = warm_start_s {
        if w.len() != problem.n() {
            return Err(Error::LengthMismatch {
                what: "warm start dwell_s",
                got: w.len(),
                expected: problem.n(),
            });
        }
    }
    let empty = problem.empty_columns();
    if problem.lambda() > 0.0 || empty.is_empty() {
        return dispatch(problem, settings, observer, warm_start_s);
    }
    if problem.is_matrix_free() {
        // Empty columns have zero gradient, so the first-order iteration leaves them where it
        // started; put them on their lower bound as the assembled route does.
        let mut sol = dispatch(problem, settings, observer, warm_start_s)?;
        for &j in &empty {
            if let (Some(t), Some(&l)) = (sol.dwell_s.get_mut(j), problem.bounds().lower_s().get(j))
            {
                *t = l;
            }
        }
        return Ok(sol);
    }
    let (reduced, kept) = problem.without_columns(&empty)?;
    let reduced_start: Option<Vec<f64>> =
        warm_start_s.map(|w| kept.iter().map(|&j| w[j]).collect());
    let mut sol = dispatch(&reduced, settings, observer, reduced_start.as_deref())?;
    let mut dwell_s = problem.bounds().lower_s().to_vec();
    for (&j, &t) in kept.iter().zip(&sol.dwell_s) {
        if let Some(slot) = dwell_s.get_mut(j) {
            *slot = t;
        }
    }
    sol.dwell_s = dwell_s;
    Ok(sol)
}

fn dispatch(
    problem: &Problem,
    settings: &Settings,
    observer: &dyn Observer,
    start: Option<&[f64]>,
) -> Result<Solution> {
    match settings.solver.resolve(problem, settings.min_time) {
        SolverKind::Qp => {
            let mut sol = qp::solve(problem, settings, observer)?;
            if sol.objective_gap_bound.is_none() && sol.min_time.is_none() {
                let gap = certificate::certify(problem, &sol.dwell_s)?;
                sol.objective_gap_bound = gap.value();
                sol.gap_bound_reason = gap.reason();
            }
            Ok(sol)
        }
        SolverKind::FirstOrder => first_order::solve_validated(problem, settings, observer, start),
    }
}

/// Below this first-order tolerance the normal products stay with `R`: `G t` and `R^T (R t)`
/// differ by rounding relative to `||G|| ||t||`, which near a KKT residual of 1e-11 (and large
/// dwell, `rho = 0` without `v_min`) is the residual itself, and Newton-CG then stalls.
const GRAM_MIN_TOLERANCE: f64 = 1e-9;

/// As [`with_operator`], for an iterative solver that takes at least `products` normal products
/// `R^T R t` to the first-order `tolerance`: the assembled `R` comes with its Gram matrix when
/// forming it pays ([`crate::influence::GramMatrix::worthwhile`]) and the tolerance is at least
/// `GRAM_MIN_TOLERANCE`.
pub(crate) fn with_solver_operator<T>(
    problem: &Problem,
    products: usize,
    tolerance: f64,
    f: impl FnOnce(&dyn LinearOperator) -> Result<T>,
) -> Result<T> {
    let normal_products = (tolerance >= GRAM_MIN_TOLERANCE).then_some(products);
    f(&*problem.operator().products(normal_products))
}

/// Runs `f` with `problem`'s operator ready for products through `R`
/// ([`InfluenceOperator::products`]).
pub(crate) fn with_operator<T>(
    problem: &Problem,
    f: impl FnOnce(&dyn LinearOperator) -> Result<T>,
) -> Result<T> {
    f(&*problem.operator().products(None))
}

/// `(D^T D t)_j` for the first-difference matrix `D` along the path.
pub(crate) fn dtd(t: &[f64], j: usize) -> f64 {
    let mut dd = 0.0;
    if j > 0 {
        dd += t[j] - t[j - 1];
    }
    if j + 1 < t.len() {
        dd -= t[j + 1] - t[j];
    }
    dd
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::{FftOperator, SpreadOperator};
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    /// Largest entry difference of `R t` between the FFT operator and the assembled `R`,
    /// relative to the largest removal: the same sums in another order, rounding only.
    const FFT_VS_ASSEMBLED_RTOL: f64 = 1e-9;
    /// Relative 2-norm difference of `R t` between the spreading operator and the assembled `R`,
    /// in units of the operator's estimated error `||R~ - R||_F / ||R||_F`: a removal of
    /// positive dwell times is a positive mix of columns, whose error the estimate tracks.
    const SPREAD_VS_ASSEMBLED_IN_ESTIMATES: f64 = 2.0;
    /// `R t` by the column sweep against the products' row sums: rounding only.
    const SWEEP_VS_ROWS_RTOL: f64 = 1e-13;
    /// First-order objective at a KKT residual of 1e-8 against the QP's optimum, relative.
    const ROUTE_VS_QP_RTOL: f64 = 1e-7;

    /// A 41 x 31 map on a 0.4 mm lattice, a Gaussian TIF (sigma 1.2 mm, truncated at 4.5 sigma)
    /// and positive dwell times for `n` points.
    fn map() -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (mut x, mut y, mut z) = (vec![], vec![], vec![]);
        for j in 0..31 {
            for i in 0..41 {
                let (px, py) = (-3.0 + 0.4 * i as f64, 1.0 + 0.4 * j as f64);
                x.push(px);
                y.push(py);
                z.push(20.0 + (0.3 * px).sin() * (0.2 * py).cos());
            }
        }
        (x, y, z)
    }

    fn tif() -> GaussianTif {
        GaussianTif::new(1.2, 10.0, 5.4).unwrap()
    }

    /// Dwell points on the map lattice (every second node, some beyond the map): the FFT
    /// operator's case.
    fn lattice_raster() -> (Vec<f64>, Vec<f64>) {
        let (mut dx, mut dy) = (vec![], vec![]);
        for j in 0..18 {
            for i in 0..24 {
                dx.push(-4.6 + 0.8 * i as f64);
                dy.push(-0.6 + 0.8 * j as f64);
            }
        }
        (dx, dy)
    }

    fn dwell(n: usize) -> Vec<f64> {
        (0..n)
            .map(|j| 0.5 + ((j * 7919) % 13) as f64 * 0.1)
            .collect()
    }

    fn problem(op: impl InfluenceOperator + 'static, z: &[f64]) -> Problem {
        let n = op.shape().1;
        let bounds = DwellBounds::new(vec![0.0; n], None).unwrap();
        Problem::new(op, z.to_vec(), bounds, 0.0, 0.0).unwrap()
    }

    fn max_abs(v: &[f64]) -> f64 {
        v.iter().fold(0.0_f64, |a, x| a.max(x.abs()))
    }

    /// Says "cancel" from its `after`-th solver iteration report on, and counts the reports.
    struct CancelAfter {
        after: usize,
        reports: std::sync::atomic::AtomicUsize,
    }

    impl crate::observer::Observer for CancelAfter {
        fn iteration(&self, _: &crate::observer::IterationInfo) {
            self.reports
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        fn cancelled(&self) -> bool {
            self.reports.load(std::sync::atomic::Ordering::Relaxed) >= self.after
        }
    }

    /// A solve whose observer asks for a stop ends with `Error::Cancelled` at its next progress
    /// report, long before the run would have ended, with every first-order method; the
    /// assembly and the direct removal sums of a cancelled observer return no result either.
    #[test]
    fn a_cancelled_solve_stops_at_its_next_report_with_no_result() {
        let (mx, my, z) = map();
        let tif = tif();
        let (dx, dy) = lattice_raster();
        for method in [
            FirstOrderMethod::Fista,
            FirstOrderMethod::NewtonCg,
            FirstOrderMethod::Lbfgs,
        ] {
            let settings = Settings {
                solver: SolverChoice::FirstOrder,
                first_order_method: method,
                // Not met within the iteration limit: the whole run reports many times.
                first_order_tolerance: 1e-12,
                first_order_max_iterations: 2_000,
                ..Settings::default()
            };
            let op = FftOperator::new(&mx, &my, &dx, &dy, 0.4, &tif).unwrap();
            let fft = problem(op, &z);
            let whole = CancelAfter {
                after: usize::MAX,
                reports: Default::default(),
            };
            solve(&fft, &settings, &whole).unwrap();
            let uncancelled = whole.reports.into_inner();
            assert!(uncancelled > 6, "{method:?}: {uncancelled} reports");
            let cut = CancelAfter {
                after: 3,
                reports: Default::default(),
            };
            let e = solve(&fft, &settings, &cut).unwrap_err();
            assert_eq!(e, Error::Cancelled, "{method:?}");
            let reports = cut.reports.into_inner();
            assert!(
                reports <= 4,
                "{method:?}: {reports} reports after the cancel at 3"
            );
        }
        let at_once = CancelAfter {
            after: 0,
            reports: Default::default(),
        };
        assert_eq!(
            InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &at_once).unwrap_err(),
            Error::Cancelled
        );
        let t = dwell(dx.len());
        assert_eq!(
            crate::simulate::direct::removal_nm(&mx, &my, &dx, &dy, &t, &tif, &at_once)
                .unwrap_err(),
            Error::Cancelled
        );
    }

    /// The first-order solver through the FFT operator's two routes for `R^T R t` (the lattice,
    /// and the autocorrelation less the band around the map) reaches the QP's optimum on the
    /// assembled `R`, a raster on a sub-lattice reaching past the map.
    #[test]
    fn both_normal_routes_solve_to_the_optimum() {
        let (mx, my, mut z) = map();
        // A rough part no dwell removes, so that the optimum is not nearly zero.
        for (i, z) in z.iter_mut().enumerate() {
            *z += ((i * 7919) % 13) as f64 * 0.1;
        }
        let tif = tif();
        let (dx, dy) = lattice_raster();
        let settings = |solver| Settings {
            solver,
            first_order_tolerance: 1e-8,
            first_order_max_iterations: 200_000,
            ..Settings::default()
        };
        let assembled = problem(
            InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap(),
            &z,
        );
        let qp = solve(&assembled, &settings(SolverChoice::Qp), &Silent).unwrap();
        for complement in [false, true] {
            let op = FftOperator::with_route((&mx, &my), (&dx, &dy), 0.4, &tif, complement);
            let fft = problem(op.unwrap(), &z);
            let sol = solve(&fft, &settings(SolverChoice::FirstOrder), &Silent).unwrap();
            assert_eq!(sol.status, Status::Converged, "complement {complement}");
            let excess = (sol.objective - qp.objective) / qp.objective;
            assert!(
                excess.abs() <= ROUTE_VS_QP_RTOL,
                "complement {complement}: {} against the QP's {} ({excess:e})",
                sol.objective,
                qp.objective
            );
        }
    }

    #[test]
    fn each_operator_kind_gives_the_assembled_removal() {
        let (mx, my, z) = map();
        let tif = tif();
        let (dx, dy) = lattice_raster();
        let assembled = problem(
            InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap(),
            &z,
        );
        let fft = problem(FftOperator::new(&mx, &my, &dx, &dy, 0.4, &tif).unwrap(), &z);
        assert_eq!(assembled.operator_kind(), OperatorKind::Sparse);
        assert_eq!(fft.operator_kind(), OperatorKind::Fft);
        assert!(assembled.influence().is_some() && !assembled.is_matrix_free());
        assert!(fft.influence().is_none() && fft.is_matrix_free());
        assert_eq!((fft.m(), fft.n()), (assembled.m(), assembled.n()));
        assert_eq!(fft.nnz(), assembled.nnz());
        assert_eq!(fft.empty_columns(), assembled.empty_columns());
        let t = dwell(assembled.n());
        let (ha, hf) = (
            assembled.removal_nm(&t).unwrap(),
            fft.removal_nm(&t).unwrap(),
        );
        let scale = max_abs(&ha);
        assert!(scale > 0.0);
        for (a, f) in ha.iter().zip(&hf) {
            assert!((a - f).abs() <= FFT_VS_ASSEMBLED_RTOL * scale, "{a} vs {f}");
        }
        // The assembled removal (column sweep) is the products' `R t` (row sums) to rounding.
        let rows = with_operator(&assembled, |op| {
            let mut h = vec![0.0; op.nrows()];
            op.apply(&t, &mut h);
            Ok(h)
        })
        .unwrap();
        for (a, r) in ha.iter().zip(&rows) {
            assert!((a - r).abs() <= SWEEP_VS_ROWS_RTOL * scale, "{a} vs {r}");
        }

        // Dwell points off the lattice: the spreading operator against the assembled `R`.
        let (mut dx, mut dy) = (vec![], vec![]);
        for j in 0..20 {
            for i in 0..28 {
                dx.push(-3.3 + 0.55 * i as f64 + 0.013 * j as f64);
                dy.push(0.7 + 0.55 * j as f64);
            }
        }
        let assembled = problem(
            InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap(),
            &z,
        );
        let op = SpreadOperator::new(&mx, &my, &dx, &dy, 0.4, 2, &tif).unwrap();
        let estimate = op.estimated_error();
        let spread = problem(op, &z);
        assert_eq!(spread.operator_kind(), OperatorKind::FftSpread);
        assert!(spread.influence().is_none() && spread.is_matrix_free());
        assert_eq!((spread.m(), spread.n()), (assembled.m(), assembled.n()));
        let t = dwell(assembled.n());
        let (ha, hs) = (
            assembled.removal_nm(&t).unwrap(),
            spread.removal_nm(&t).unwrap(),
        );
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let diff: Vec<f64> = ha.iter().zip(&hs).map(|(a, s)| a - s).collect();
        let rel = norm(&diff) / norm(&ha);
        assert!(estimate > 0.0 && estimate < 0.05, "estimate {estimate}");
        assert!(
            rel <= SPREAD_VS_ASSEMBLED_IN_ESTIMATES * estimate,
            "relative removal error {rel} against the estimate {estimate}"
        );
        // A wrong length is an error for every kind.
        for p in [&assembled, &fft, &spread] {
            assert!(p.removal_nm(&t[..1]).is_err());
        }
    }
}
