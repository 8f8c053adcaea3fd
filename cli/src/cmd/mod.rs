pub mod bench;
pub mod fit;
pub mod register;
pub mod solve;
pub mod surface;
