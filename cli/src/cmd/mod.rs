pub mod asphere;
pub mod fit;
pub mod nc;
pub mod path;
pub mod register;
pub mod solve;
pub mod surface;
pub mod tif;
