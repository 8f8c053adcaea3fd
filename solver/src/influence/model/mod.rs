//! The influence models: what a column of `R` is. Each takes a TIF (nm/s), the map points and the
//! dwell points (mm) and gives the removal rate at each map point while the tool serves each dwell
//! point:
//! - [`point`]: the TIF at the offset between map and dwell point, `R[i, j] = f(x_i - x_j)`,
//!   assembled as a sparse matrix;
//! - [`swept`]: the motion-true model, the TIF averaged along the dwell point's stretch of path as
//!   the program runs it, `R[i, j] = (1/ds) * integral of f(x_i - p(s)) ds`;
//! - [`surface`]: either model on a curved part, the TIF applied in each dwell point's tangent
//!   frame;
//! - [`curvature`]: one Hertzian TIF per dwell point from the local principal curvatures;
//! - [`piece`]: the one rule every swept column and sampled motion integrates a straight piece of
//!   motion by (its midpoint, and exactly where a truncated TIF's cut circle crosses it).
//!
//! `R t` summed without assembling `R` (one product with many columns: a sampled motion) is the
//! simulation's ([`crate::simulate::direct`]); the traversal of the pairs within a radius it
//! shares with the curved part's direct sum is [`point`]'s.

pub mod curvature;
pub mod piece;
pub mod point;
pub mod surface;
pub mod swept;
