//! Preston I/O: CSV readers and writers (units in every header), job files, reports, and the
//! atomic output that guarantees a file appears whole or not at all.
#![warn(missing_docs)]
#![deny(clippy::unwrap_used, clippy::expect_used, clippy::panic)]
#![cfg_attr(test, allow(clippy::unwrap_used, clippy::expect_used, clippy::panic))]

pub mod atomic;
pub mod bench;
pub mod calibration;
pub mod digest;
pub mod error;
pub mod figures;
pub mod html;
pub mod machine;
pub mod metrology;
pub mod overrides;
pub mod readers;
pub mod report;
pub mod residual;
pub mod sample;
pub mod shop;
pub mod surface;
pub mod table;
pub mod tools;
pub mod writers;

pub use error::{Error, Result};
pub mod job;
pub mod limits;
pub mod pipeline;
pub mod plots;
pub mod simulation;
