//! When a solve uses the off-lattice spreading operator ([`SpreadOperator`]): map points on a
//! regular lattice, dwell points off it, a plane TIF and the first-order solver, and then only
//! when `operator = "fft-spread"` asks for it, or `auto` finds it both accurate enough (estimated
//! relative operator error within `spread_tolerance`) and cheaper per product than the assembled
//! `R` by the cost model below.
//!
//! Cost model (per `R^T R t`, the first-order solver's product): the sparse operator makes two
//! passes over the non-zeros, `2 nnz` multiply-adds at about [`SPARSE_NS_PER_NNZ`]; the spreading
//! operator transforms the padded fine lattice of `F` cells forth and back, about
//! `F log2 F` times [`SPREAD_NS_PER_CELL_LOG`]. Assembling `R` costs a TIF evaluation per
//! non-zero on top, which the comparison leaves out (in the spreading operator's favour).

use super::{At, Setup, SetupInput, SetupResult};
use crate::dwell::{policy, OperatorChoice, SolverChoice, SolverKind};
use crate::error::Error;
use crate::influence::fft::FftOperator;
use crate::influence::spread::MAX_OVERSAMPLING;
use crate::influence::SpreadOperator;
use crate::map::HeightMap;
use crate::tif::InfluenceFunction;

/// Sparse `R^T R t`: nanoseconds per stored non-zero (two passes, 2 cores).
pub const SPARSE_NS_PER_NNZ: f64 = 1.0;
/// Spreading operator `R^T R t`: nanoseconds per `F log2 F` of the fine lattice (2 cores).
pub const SPREAD_NS_PER_CELL_LOG: f64 = 0.5;
/// The map must fill at least this share of its lattice's bounding box.
const MIN_LATTICE_FILL: f64 = 0.25;

impl Setup {
    /// The spreading operator over the problem rows `rows` when it applies (see the module
    /// documentation); `None` to assemble `R`. With `operator = "fft-spread"` inputs it cannot
    /// serve are an error naming why. Notes on the choice go to `warnings`.
    pub(super) fn spread_plan(
        &self,
        rows: &HeightMap,
        warnings: &mut Vec<String>,
    ) -> SetupResult<Option<SpreadOperator>> {
        let forced = self.settings.operator == OperatorChoice::FftSpread;
        if !forced && self.settings.operator != OperatorChoice::Auto {
            return Ok(None);
        }
        let refuse = |why: String| -> SetupResult<Option<SpreadOperator>> {
            if forced {
                Err(Error::invalid(
                    "operator",
                    format!("operator = \"fft-spread\" cannot be used: {why}"),
                ))
                .at(SetupInput::Job)
            } else {
                Ok(None)
            }
        };
        if let Some(why) = self.fft_blocker() {
            return refuse(format!("with {why}"));
        }
        let Some(pitch) = FftOperator::lattice_pitch_mm(rows.x_mm(), rows.y_mm()) else {
            return refuse("the map points are not on a regular lattice".into());
        };
        let Some(bbox) = rows.bounding_box_mm() else {
            return refuse("the map is empty".into());
        };
        let cells = ((bbox.x_max_mm - bbox.x_min_mm) / pitch + 1.0)
            * ((bbox.y_max_mm - bbox.y_min_mm) / pitch + 1.0);
        if (rows.len() as f64) < MIN_LATTICE_FILL * cells {
            return refuse(format!(
                "the map fills less than {MIN_LATTICE_FILL} of its {pitch} mm lattice"
            ));
        }
        let (mx, my, dx, dy) = (rows.x_mm(), rows.y_mm(), self.path.x_mm(), self.path.y_mm());
        // Map points inside one TIF disc, at most all of them, per dwell point.
        let r = self.tif.support_radius_mm();
        let per_column = (std::f64::consts::PI * r * r / (pitch * pitch)).min(rows.len() as f64);
        let nnz = per_column * self.path.len() as f64;
        let sparse_ns = 2.0 * SPARSE_NS_PER_NNZ * nnz;
        let spread_ns = |s: usize| {
            let fine = pitch / s as f64;
            let pad = 2.0 * r / fine;
            let lattice = ((bbox.x_max_mm - bbox.x_min_mm) / fine + pad)
                * ((bbox.y_max_mm - bbox.y_min_mm) / fine + pad);
            SPREAD_NS_PER_CELL_LOG * lattice * lattice.max(2.0).log2()
        };
        if !forced {
            // Only where the first-order solver would run anyway: below the policy's crossover
            // the QP on the assembled `R` is the faster, certified route.
            let first_order = match self.settings.solver {
                SolverChoice::FirstOrder => true,
                SolverChoice::Qp => false,
                SolverChoice::Auto => {
                    policy::choose(&policy::PolicyInputs {
                        nnz,
                        fft_cells: None,
                        needs_qp: false,
                        solver: None,
                    })
                    .solver
                        == SolverKind::FirstOrder
                }
            };
            if !first_order {
                return Ok(None);
            }
            // Dwell points on the map lattice are the FFT operator's (exact) case.
            let on = |v: f64, o: f64| ((v - o) / pitch - ((v - o) / pitch).round()).abs() <= 1e-6;
            let all_on = dx
                .iter()
                .zip(dy)
                .all(|(&x, &y)| on(x, bbox.x_min_mm) && on(y, bbox.y_min_mm));
            if all_on || spread_ns(1) >= sparse_ns {
                return Ok(None);
            }
        }
        let tolerance = self.settings.spread_tolerance;
        let chosen =
            match SpreadOperator::oversampling_for(mx, my, dx, dy, pitch, &self.tif, tolerance) {
                Ok(c) => c,
                Err(e) => return refuse(e.to_string()),
            };
        let Some((s, error)) = chosen else {
            return refuse(format!(
                "no oversampling up to {MAX_OVERSAMPLING} brings the estimated operator error \
                 within spread_tolerance = {tolerance}"
            ));
        };
        if !forced {
            if spread_ns(s) >= sparse_ns {
                return Ok(None);
            }
            warnings.push(format!(
                "operator auto: dwell points off the map lattice; products spread them onto a \
                 {:.4} mm lattice (oversampling {s}, estimated operator error {error:.1e} <= \
                 {tolerance:.0e}) and use the FFT, about {:.0}x cheaper per product than R's \
                 {nnz:.2e} non-zeros (operator = \"sparse\" assembles R)",
                pitch / s as f64,
                sparse_ns / spread_ns(s)
            ));
        }
        match SpreadOperator::new(mx, my, dx, dy, pitch, s, &self.tif) {
            Ok(op) => Ok(Some(op)),
            Err(e) if forced => Err(e).at(SetupInput::Map),
            Err(e) => {
                warnings.push(format!(
                    "operator auto: the spreading operator does not apply ({e}); assembling R"
                ));
                Ok(None)
            }
        }
    }
}
