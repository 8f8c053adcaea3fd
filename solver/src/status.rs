//! One status vocabulary for every iterative step: the dwell solvers (QP, first-order), the
//! acceleration limit's sequential convex programme, the registration's Gauss-Newton ICP, the
//! surface fit's Levenberg-Marquardt and the polishing loop. In the manner of argmin's
//! termination reasons: how the iteration stopped, carried typed to the edge (reports, exit
//! codes) and serialised only there. Not converging is a status, never an error.

use serde::{Deserialize, Serialize};

/// How an iterative step ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    /// A stopping test was met at the requested tolerance (which one, where the solver has
    /// several, is told beside the status: [`crate::dwell::certificate::ConvergenceCriterion`]).
    Converged,
    /// Converged to a reduced tolerance.
    AlmostConverged,
    /// Stopped at the iteration limit.
    MaxIterations,
    /// Stopped because no step made progress any more while the stopping test was not met.
    Stalled,
    /// Stopped at the time limit.
    TimeLimit,
    /// The problem has no feasible point.
    Infeasible,
    /// The solver hit a numerical difficulty and stopped.
    NumericalError,
}

impl Status {
    /// True for the statuses whose result can be trusted as the step's answer.
    pub fn is_converged(self) -> bool {
        matches!(self, Status::Converged | Status::AlmostConverged)
    }

    /// The name reports use (`converged`, `max_iterations`, ...): the serde name.
    pub fn name(self) -> &'static str {
        match self {
            Status::Converged => "converged",
            Status::AlmostConverged => "almost_converged",
            Status::MaxIterations => "max_iterations",
            Status::Stalled => "stalled",
            Status::TimeLimit => "time_limit",
            Status::Infeasible => "infeasible",
            Status::NumericalError => "numerical_error",
        }
    }
}

impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_report_name_is_the_serde_name() {
        for s in [
            Status::Converged,
            Status::AlmostConverged,
            Status::MaxIterations,
            Status::Stalled,
            Status::TimeLimit,
            Status::Infeasible,
            Status::NumericalError,
        ] {
            let json = serde_json::to_value(s).unwrap();
            assert_eq!(json.as_str(), Some(s.name()));
            assert_eq!(serde_json::from_value::<Status>(json).unwrap(), s);
        }
        assert!(Status::AlmostConverged.is_converged() && !Status::Stalled.is_converged());
    }
}
