//! The influence operator `R` (m x n, nm/s): `R[i, j]` is the removal rate at measurement point `i`
//! while the tool dwells at point `j`, so the removal is `h = R t` for dwell times `t` (s).
//!
//! Everything that builds or applies `R` lives here:
//! - [`matrix`]: the sparse matrix assembled from a shift-invariant TIF on the plane;
//! - [`surface`]: the same on a curved part, the TIF applied in each dwell point's tangent frame;
//! - [`curvature`]: one Hertzian TIF per dwell point from the local principal curvatures;
//! - [`fft`]: the matrix-free operator for map and dwell points on one lattice (FFT convolution);
//! - `complement`: the FFT operator's normal product through the kernel's autocorrelation on the
//!   dwell lattice, less the band of cells within reach that the map does not cover once;
//! - [`spread`]: the matrix-free operator for dwell points off the map lattice (bilinear spreading
//!   onto an oversampled lattice, then FFT convolution);
//! - [`nufft`]: the matrix-free operator for dwell points anywhere with a controlled error
//!   (exponential-of-semicircle spreading onto a fine lattice, deconvolved FFT convolution);
//! - [`stencil`]: the exact matrix-free operator for dwell points off the map lattice at few
//!   distinct positions within a cell (one tabulated stencil per position, scattered and
//!   gathered on the lattice);
//! - [`direct`]: `R t` summed without assembling `R` (one product with many columns: sampled
//!   programs);
//! - [`swept`]: the motion-true model, the TIF averaged along each dwell point's stretch of path;
//! - [`swept_correction`]: the lattice operators' shared swept kernel corrected, column by
//!   column, at the dwell points whose stretch differs (row ends, the path's ends);
//! - [`gram`]: the Gram matrix `R^T R` of the assembled matrix, for the solvers' normal products;
//! - [`stacked`]: several tools' matrices side by side (one solve over all their dwell times);
//! - [`operator`]: the traits: [`InfluenceOperator`] (`R` as a dwell problem holds it, whichever of
//!   the above it is) and [`LinearOperator`] (the products `R t`, `R^T y` every solver goes through).

mod complement;
pub mod curvature;
pub mod direct;
pub mod fft;
pub mod gram;
pub(crate) mod lattice;
pub mod matrix;
pub mod nufft;
pub mod operator;
pub mod piece;
pub mod spread;
pub mod stacked;
pub mod stencil;
pub mod surface;
pub mod swept;
pub mod swept_correction;

pub use curvature::{
    assemble_curvature_dependent, assemble_curvature_dependent_swept, hertz_tifs_on_surface,
};
pub use fft::FftOperator;
pub use gram::{GramMatrix, GramOperator};
pub use matrix::{InfluenceMatrix, NNZ_BYTES};
pub use nufft::NufftOperator;
pub use operator::{InfluenceOperator, LinearOperator, OperatorKind, Products, SparseOperator};
pub use piece::{piece_rate, PieceTif};
pub use spread::SpreadOperator;
pub use stacked::StackedRows;
pub use stencil::StencilOperator;
pub use surface::{
    assemble_on_surface, assemble_on_surface_swept, assemble_on_surface_with, TifFrame,
    SEARCH_RADIUS_FACTOR,
};
pub use swept::{assemble_swept, InfluenceModel, Stretches, SweptTif};
