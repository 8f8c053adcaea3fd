//! The influence operator `R` (m x n, nm/s): `R[i, j]` is the removal rate at measurement point `i`
//! while the tool dwells at point `j`, so the removal is `h = R t` for dwell times `t` (s).
//!
//! Two concepts, two folders:
//! - [`model`]: what a column of `R` is, the physics. The point model (the TIF at the offset
//!   between map and dwell point, [`model::point`]), the motion-true swept model (the TIF averaged
//!   along each dwell point's stretch of path, [`model::swept`]), the same on a curved part in each
//!   dwell point's tangent frame ([`model::surface`]) and with one Hertzian TIF per dwell point
//!   ([`model::curvature`]). `R t` summed without assembling `R`, the removal of a motion, is the
//!   simulation's ([`crate::simulate::direct`]).
//! - [`operator`]: how `R` is held and applied, the numerics. The traits every solver goes
//!   through ([`InfluenceOperator`], [`LinearOperator`]) and their implementations: the assembled
//!   sparse [`InfluenceMatrix`] with its Gram matrix, the matrix-free FFT operator on one lattice,
//!   the off-lattice stencil, spreading and non-uniform FFT operators, several tools' operators
//!   side by side.
//!
//! [`swept_correction`] joins the two: a lattice operator's shared swept kernel corrected, column
//! by column, at the dwell points whose stretch differs (row ends, the path's ends).
//!
//! A model uses the operators' types (it assembles an [`InfluenceMatrix`]); no operator uses a
//! model.

pub mod model;
pub mod operator;
pub mod swept_correction;

pub use model::curvature::{
    assemble_curvature_dependent, assemble_curvature_dependent_swept, hertz_tifs_on_surface,
};
pub use model::piece::{piece_rate, PieceTif};
pub use model::surface::{
    assemble_on_surface, assemble_on_surface_swept, assemble_on_surface_with, TifFrame,
    SEARCH_RADIUS_FACTOR,
};
pub use model::swept::{assemble_swept, InfluenceModel, Stretches, SweptTif};
pub use operator::expansion::{ColumnShape, ExpansionOperator};
pub use operator::fft::FftOperator;
pub use operator::gram::{GramMatrix, GramOperator};
pub use operator::matrix::{InfluenceMatrix, NNZ_BYTES};
pub use operator::nufft::NufftOperator;
pub use operator::sparse::SparseOperator;
pub use operator::spread::SpreadOperator;
pub use operator::stacked::StackedRows;
pub use operator::stencil::StencilOperator;
pub use operator::{InfluenceOperator, LinearOperator, OperatorKind, Products};
