//! Preston engine: dwell-time computation for deterministic sub-aperture polishing.
//!
//! Data flow: inputs ([`map::HeightMap`], [`tif`], [`path::DwellPath`]) -> influence matrix
//! ([`influence::InfluenceMatrix`]) -> dwell problem ([`dwell::Problem`]) -> solve
//! ([`dwell::solve`]) -> [`dwell::Solution`]. Units: lengths mm, heights nm, time s, rates nm/s,
//! feeds mm/min.
#![warn(missing_docs)]
#![deny(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used, clippy::panic))]
// Input checks are written `!(x > 0.0)` on purpose: the negated form also rejects NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod aperture;
pub mod band;
pub mod budget;
pub mod calibrate;
pub mod counts;
pub mod dwell;
pub mod edge;
pub mod error;
pub mod fit;
pub mod influence;
pub mod iterate;
pub mod kinematics;
mod lstsq;
pub mod machine;
pub mod map;
pub mod modal;
pub mod observer;
pub mod path;
pub mod psd;
pub mod registration;
pub mod rng;
pub mod setup;
pub mod simulate;
pub mod status;
pub mod surface;
pub mod tif;

#[cfg(test)]
mod test_support;

pub use error::{Error, Result};
