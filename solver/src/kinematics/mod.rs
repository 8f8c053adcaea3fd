//! Kinematics: how the machine moves along a dwell path, in one place for the optimiser
//! ([`crate::dwell::accel`]), the feed schedule and NC writer ([`crate::machine::feeds`],
//! [`crate::machine::nc`]) and the program executor ([`crate::machine::gcode::motion`]).
//!
//! [`lines`] cuts a path into lines at its corners and gives each segment's length, turn angle
//! and acceleration between dwell points; here are the limits every face checks, written once:
//! an acceleration limit is positive and finite ([`check_a_max_mm_per_s2`]), a corner angle in
//! `[0, 180]` degrees ([`check_corner_angle_deg`]), and the corner angle is
//! [`DEFAULT_CORNER_ANGLE_DEG`] where none is given. [`Kinematics`] names the controller's
//! motion model (programmed feed or acceleration-limited look-ahead) that the simulator, the
//! calibration and the planner's executed check share.

pub mod lines;

use crate::error::{Error, Result};

/// The turn angle, degrees, above which a path splits into lines (the machine stops there)
/// where none is given.
pub const DEFAULT_CORNER_ANGLE_DEG: f64 = 60.0;

/// Checks an acceleration limit, mm/s^2: positive and finite.
pub fn check_a_max_mm_per_s2(a_max_mm_per_s2: f64) -> Result<()> {
    if a_max_mm_per_s2.is_finite() && a_max_mm_per_s2 > 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(
            "a_max_mm_per_s2",
            format!("must be positive and finite, got {a_max_mm_per_s2}"),
        ))
    }
}

/// Checks a corner angle, degrees: in `[0, 180]`.
pub fn check_corner_angle_deg(corner_angle_deg: f64) -> Result<()> {
    if (0.0..=180.0).contains(&corner_angle_deg) {
        Ok(())
    } else {
        Err(Error::invalid(
            "corner_angle_deg",
            format!("must be in [0, 180], got {corner_angle_deg}"),
        ))
    }
}

/// How the controller moves through the blocks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kinematics {
    /// Constant programmed feed in every block.
    ProgrammedFeed,
    /// Acceleration-limited look-ahead ([`crate::machine::gcode::motion`]).
    Trapezoidal {
        /// Path acceleration limit, mm/s^2.
        a_max_mm_per_s2: f64,
        /// Turn angle above which the tool stops at a junction, degrees.
        corner_angle_deg: f64,
    },
}

impl Kinematics {
    /// The controller of an optional path acceleration limit `a_max_mm_per_s2` (mm/s^2):
    /// [`Kinematics::Trapezoidal`] with the corner angle `corner_angle_deg` (degrees) when there
    /// is one, [`Kinematics::ProgrammedFeed`] when there is none; validated, so that a face
    /// refuses a bad limit before it reads a map or a program.
    pub fn of_limit(a_max_mm_per_s2: Option<f64>, corner_angle_deg: f64) -> Result<Self> {
        let k = match a_max_mm_per_s2 {
            Some(a_max_mm_per_s2) => Kinematics::Trapezoidal {
                a_max_mm_per_s2,
                corner_angle_deg,
            },
            None => Kinematics::ProgrammedFeed,
        };
        k.validate()?;
        Ok(k)
    }

    /// Checks the acceleration limit: positive and finite.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Kinematics::Trapezoidal {
                a_max_mm_per_s2, ..
            } => check_a_max_mm_per_s2(a_max_mm_per_s2),
            Kinematics::ProgrammedFeed => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_limits_refuse_what_no_machine_has_and_keep_the_edges() {
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(check_a_max_mm_per_s2(bad).is_err(), "{bad}");
        }
        assert!(check_a_max_mm_per_s2(f64::MIN_POSITIVE).is_ok());
        for bad in [-1e-12, 180.0 + 1e-12, f64::NAN] {
            assert!(check_corner_angle_deg(bad).is_err(), "{bad}");
        }
        for good in [0.0, DEFAULT_CORNER_ANGLE_DEG, 180.0] {
            assert!(check_corner_angle_deg(good).is_ok(), "{good}");
        }
    }
}
