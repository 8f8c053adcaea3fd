//! Simulation: the removal a motion of the tool leaves on the part.
//!
//! A motion is a list of samples `p_k` (mm, in plan), each carrying the time `tau_k` (s) the tool
//! spends there, and each, where the motion is swept, standing for a straight piece of motion
//! that the tool crosses at constant feed ([`SampledProgram`]). Its removal at map point `x_i` is
//! `h_i = sum_k f(x_i - p_k) tau_k` (Preston's law integrated over the run), each piece's term
//! integrated along it ([`crate::influence::model::piece::piece_rate`]). A motion's samples are
//! used once, so the sum is taken directly, without assembling the influence matrix `R`; for the
//! dwell points themselves it is the solver's `h = R t`.
//!
//! Two models of how the tool moves through a dwell plan:
//! - discrete: the tool stands still at each dwell point `j` for `t_j` (the solver's point
//!   model), the samples are the dwell points;
//! - swept: the tool sweeps each dwell point's stretch of path at constant feed, the samples
//!   cut the stretch into pieces (midpoint samples of each arc for `preston simulate`, the swept
//!   influence model's stretch pieces for the set-up), or they are the executed contact motion of
//!   a G-code program.
//!
//! Where each piece lives:
//! - [`plan`]: a dwell plan's motion as samples under either model ([`Motion`],
//!   [`sample_program`], [`plan::path_motion`]), and its removal in plan ([`removal_nm`]);
//! - [`program`]: a G-code program executed and run on a map ([`program::run_on_map`],
//!   [`program::ProgramRun`]);
//!   the controller's executor itself is the machine's ([`crate::machine::gcode::motion`]);
//! - [`contact`]: the removal of a contact motion on the set-up's part, flat or curved, under the
//!   sensitivity's perturbations of the TIF ([`contact::contact_removals`]);
//! - [`motion_lattice`]: on a flat part whose map is a lattice, the samples that share an offset
//!   from it as lattice products;
//! - [`direct`]: the removal summed directly over the pairs within the TIF's reach, in plan; on a
//!   curved part each sample's tangent frame is the influence model's
//!   ([`crate::influence::model::surface::removals_on_surface_with`]).
//!
//! Writing the outputs of a simulation is the io crate's (its `simulation` module): it only
//! writes.

pub mod contact;
pub mod direct;
pub mod motion_lattice;
pub mod plan;
pub mod program;

pub use plan::{removal_nm, sample_program, Motion};

/// Positions (mm) and dwell (s) of the samples that model the motion, in path order.
#[derive(Debug, Clone, PartialEq)]
pub struct SampledProgram {
    /// x of every sample, mm.
    pub x_mm: Vec<f64>,
    /// y of every sample, mm.
    pub y_mm: Vec<f64>,
    /// Dwell carried by every sample, s.
    pub dwell_s: Vec<f64>,
    /// Half of every sample's piece of motion, from the sample to the piece's end, mm, the tool
    /// at constant feed along it ([`crate::influence::model::piece::piece_rate`]); empty: the
    /// samples are points.
    pub half_mm: Vec<[f64; 2]>,
}
