//! A G-code program run on a map: the controller's executed motion ([`execute`]), its contact
//! motion sampled in pieces ([`motion::sample_contact`]), the tool centres mapped back to contact
//! points on the part, and the removal of that contact motion integrated at the map points. With
//! a drift of the removal rate over the run, each sample's time is weighted by the rate at its
//! program time.

use super::SampledProgram;
use crate::error::Result;
use crate::machine::gcode::motion::{self, check_stretches, execute, Kinematics, StretchCheck};
use crate::machine::gcode::program::Program;
use crate::machine::PartGeometry;

/// A program run on a map: its executed motion, the stretch check and the removal it leaves.
#[derive(Debug, Clone, PartialEq)]
pub struct ProgramRun {
    /// Executed motion.
    pub executed: motion::Executed,
    /// Executed stretch times against the plan.
    pub check: StretchCheck,
    /// Removal at the map points, nm.
    pub removal_nm: Vec<f64>,
    /// Removal samples used.
    pub samples: usize,
    /// The contact motion as removal samples (position and time of every piece), to integrate
    /// another TIF along the same motion (the sensitivity of the executed part).
    pub contact: SampledProgram,
    /// Program time at the middle of every contact sample, s.
    pub contact_at_s: Vec<f64>,
}

/// Executes `program` under `kinematics`, samples the contact motion with pieces of at most
/// `step_mm` ([`motion::sample_contact`]), maps tool centres back to contact points on `part`
/// (a surface and the tool-centre offset along its normal; none: X, Y are the contact points),
/// each piece the chord between the contact points of its ends,
/// and integrates the removal of the contact motion with `removal` (the TIF summed along the
/// samples at the map points: [`super::direct::removal_of_samples`] on a flat part). With a
/// drift of the removal rate, each sample's time is weighted by
/// `1 + drift_per_hour (t - t_mid) / 3600` about the contact-time-weighted mean program time
/// `t_mid` (the tool's rate at `t_mid` is the TIF's).
pub fn run_on_map(
    program: &Program,
    kinematics: Kinematics,
    step_mm: f64,
    part: Option<(&dyn PartGeometry, f64)>,
    drift_per_hour: f64,
    removal: &dyn Fn(&SampledProgram) -> Result<Vec<f64>>,
) -> Result<ProgramRun> {
    let executed = execute(program, kinematics)?;
    let check = check_stretches(program, &executed);
    let mut samples = motion::sample_contact(program, &executed, step_mm)?;
    if let Some((geometry, offset_mm)) = part {
        // A piece's end is the next piece's start along a block: its contact point is found once.
        let mut last_end: Option<([f64; 3], (f64, f64))> = None;
        for k in 0..samples.time_s.len() {
            let tool = [samples.x_mm[k], samples.y_mm[k], samples.z_mm[k]];
            (samples.x_mm[k], samples.y_mm[k]) = motion::contact_xy(geometry, offset_mm, tool)?;
            let [start, end] = samples.ends_mm[k];
            let from = match last_end {
                Some((at, c)) if at == start => c,
                _ => motion::contact_xy(geometry, offset_mm, start)?,
            };
            let to = motion::contact_xy(geometry, offset_mm, end)?;
            last_end = Some((end, to));
            samples.half_mm[k] = [0.5 * (to.0 - from.0), 0.5 * (to.1 - from.1)];
        }
    }
    let mut dwell_s = samples.time_s;
    if drift_per_hour != 0.0 {
        let total: f64 = dwell_s.iter().sum();
        let mid = if total > 0.0 {
            dwell_s
                .iter()
                .zip(&samples.at_s)
                .map(|(d, t)| d * t)
                .sum::<f64>()
                / total
        } else {
            0.0
        };
        for (d, t) in dwell_s.iter_mut().zip(&samples.at_s) {
            *d *= (1.0 + drift_per_hour * (t - mid) / 3600.0).max(0.0);
        }
    }
    let sampled = SampledProgram {
        x_mm: samples.x_mm,
        y_mm: samples.y_mm,
        dwell_s,
        half_mm: samples.half_mm,
    };
    let removal_nm = removal(&sampled)?;
    Ok(ProgramRun {
        executed,
        check,
        removal_nm,
        samples: sampled.dwell_s.len(),
        contact: sampled,
        contact_at_s: samples.at_s,
    })
}
