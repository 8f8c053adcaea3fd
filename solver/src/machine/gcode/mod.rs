//! G-code programs: controller dialects and feed modes ([`dialect`]), the writer that turns a
//! plan into a program delivering every dwell ([`write`]), the reader that takes any program
//! Preston writes back ([`program`]) and the motion a controller executes for it ([`motion`]).
//! The removal an executed program leaves on the part is the simulation's
//! ([`crate::simulate::program`]).

pub mod dialect;
pub mod motion;
pub mod program;
pub mod write;

use crate::error::Result;
use crate::machine::nc::NcProgram;
use motion::{check_stretches, execute, Kinematics, StretchCheck};
use program::Program;
use write::{write_program, Written};

/// A written program, read back and executed: what the machine will do with it.
#[derive(Debug, Clone, PartialEq)]
pub struct ProgramCheck {
    /// The text and what the writer changed.
    pub written: Written,
    /// The text read back.
    pub program: Program,
    /// Stretch times at the programmed feeds against the plan.
    pub programmed: StretchCheck,
    /// With the settings' acceleration limit: stretch times of the trapezoidal motion.
    pub accelerated: Option<StretchCheck>,
}

/// Writes `nc` as G-code, reads the text back and executes it (at the programmed feeds, and with
/// the acceleration limit of its settings when one is set).
pub fn write_and_check(nc: &NcProgram, notes: &[String]) -> Result<ProgramCheck> {
    let written = write_program(nc, notes)?;
    let program = Program::parse(&written.text, nc.settings.dialect)?;
    // The program at its programmed feeds and under the acceleration limit: independent runs,
    // side by side.
    let (programmed, accelerated) = rayon::join(
        || -> Result<StretchCheck> {
            Ok(check_stretches(
                &program,
                &execute(&program, Kinematics::ProgrammedFeed)?,
            ))
        },
        || -> Result<Option<StretchCheck>> {
            match nc.settings.a_max_mm_per_s2 {
                Some(a) => {
                    let k = Kinematics::Trapezoidal {
                        a_max_mm_per_s2: a,
                        corner_angle_deg: nc.settings.corner_angle_deg,
                    };
                    Ok(Some(check_stretches(&program, &execute(&program, k)?)))
                }
                None => Ok(None),
            }
        },
    );
    let (programmed, accelerated) = (programmed?, accelerated?);
    Ok(ProgramCheck {
        written,
        program,
        programmed,
        accelerated,
    })
}
