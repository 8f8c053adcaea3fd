//! Observers: how long-running engine work reports progress without the engine knowing about
//! terminals (the CLI draws progress bars from these calls).

/// A stage of the pipeline that reports progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Assembling the influence matrix (units: dwell points).
    Assembly,
    /// Iterating a dwell solver (units: iterations).
    Solve,
    /// Iterations of a higher-level loop (units: loop iterations).
    Loop,
}

/// A step of the set-up stage, reported to [`Observer::setup_step`] once each per job.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SetupStep {
    /// The job's choices are validated ([`crate::setup::Choices::check`]).
    CheckChoices,
    /// The inputs are resolved: dwell points, bounds ([`crate::setup::Setup::resolve`]).
    Resolve,
    /// The problem is built ([`crate::setup::Setup::problem`]).
    BuildProblem,
    /// The solver runs ([`crate::setup::Setup::solve`]).
    Solve,
    /// The removal `R t` of the solution is computed.
    Removal,
    /// The feed schedule of the solution is computed.
    FeedSchedule,
}

/// One solver iteration as seen by an observer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IterationInfo {
    /// Iteration number, starting at 1.
    pub iteration: usize,
    /// Current objective value (the contract's objective, nm^2 units).
    pub objective: f64,
    /// Current projected-gradient (KKT) residual, when the solver computes one.
    pub kkt_residual: Option<f64>,
}

/// Receives progress reports. Every method has an empty default, so observers implement only
/// what they show. Called from worker threads, hence `Sync`.
pub trait Observer: Sync {
    /// A stage starts with `total` units of work.
    fn start(&self, _stage: Stage, _total: u64) {}
    /// `units` more units of the current stage are done.
    fn advance(&self, _stage: Stage, _units: u64) {}
    /// The stage is over.
    fn finish(&self, _stage: Stage) {}
    /// A solver finished an iteration.
    fn iteration(&self, _info: &IterationInfo) {}
    /// A step of the set-up stage ([`crate::setup`]) runs.
    fn setup_step(&self, _step: SetupStep) {}
    /// Whether the caller wants the work stopped (an interrupt). The long loops ask at their
    /// progress reports and between stages, and then end with [`crate::Error::Cancelled`]
    /// instead of a result. Called often: it must be cheap.
    fn cancelled(&self) -> bool {
        false
    }
}

/// [`crate::Error::Cancelled`] once `observer` asks for the work to stop.
pub fn check_cancelled(observer: &dyn Observer) -> crate::Result<()> {
    if observer.cancelled() {
        Err(crate::Error::Cancelled)
    } else {
        Ok(())
    }
}

/// An observer that ignores everything.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Observer for Silent {}
