//! The residual a solve's headline states, and the model's beside it.
//!
//! With an acceleration limit a solve executes its program at that limit, and `report.json`
//! `rms_after_nm` (the report's cards, Python's `report`) is the residual of the program as the
//! controller runs it. Every residual a user gets (`residual.csv`, the residual figure, the
//! PSDs, Python's `residual_nm`) is then that one; the model's residual at the programmed feeds
//! is written beside it under its own name (`residual_model.csv`, `residual_model.png`). Without
//! an executed run the two are one and only the first is written.

use preston_solver::setup::{centred_residual_nm, Outcome};

/// The removal and residual of a solve as its headline states them.
#[derive(Debug, Clone)]
pub struct Delivered<'a> {
    /// Removal at the measured map points, nm: the executed program's where one was executed,
    /// else the model's `R t` at the programmed feeds.
    pub removal_nm: &'a [f64],
    /// The residual `z - removal` about its mean, nm (its RMS is `rms_after_nm`).
    pub residual_nm: Vec<f64>,
    /// Whether the removal is the executed program's.
    pub executed: bool,
}

impl<'a> Delivered<'a> {
    /// The headline's removal and residual of `outcome` on the map heights `z_nm`.
    pub fn of(z_nm: &[f64], outcome: &'a Outcome) -> Self {
        match executed_removal_nm(outcome) {
            Some(removal_nm) => Self {
                removal_nm,
                residual_nm: centred_residual_nm(z_nm, removal_nm),
                executed: true,
            },
            None => Self {
                removal_nm: &outcome.removal_nm,
                residual_nm: outcome.residual_nm.clone(),
                executed: false,
            },
        }
    }
}

/// The executed program's removal at the measured map points, nm, where the solve executed
/// its program (an acceleration limit and a plan that can be written as a program).
pub fn executed_removal_nm(outcome: &Outcome) -> Option<&[f64]> {
    match &outcome.executed {
        Some(Ok(e)) => Some(&e.run.removal_nm),
        _ => None,
    }
}
