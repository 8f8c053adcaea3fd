pub mod asphere;
pub mod bench;
pub mod calibrate;
pub mod figure_args;
pub mod fit;
pub mod hertz_args;
pub mod iterate;
pub mod machine_args;
pub mod map;
pub mod map_input;
pub mod nc;
pub mod path;
pub mod register;
pub mod sample;
pub mod shop;
pub mod shop_tool_args;
pub mod simulate;
pub mod solve;
pub mod surface;
pub mod tif;
pub mod tif_source;
pub mod tif_spot;

/// Exit code of every command whose iterative step (dwell solve, SCP, registration, fit, the
/// loop's inner steps) did not converge: the outputs are written and their status says so.
pub const EXIT_NOT_CONVERGED: u8 = 3;
