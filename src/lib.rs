//! Preston: dwell-time computation for deterministic sub-aperture polishing.
//!
//! This facade re-exports the workspace crates so integration tests and benchmarks can say
//! `preston::solver` and `preston::io`.
pub use preston_io as io;
pub use preston_solver as solver;
