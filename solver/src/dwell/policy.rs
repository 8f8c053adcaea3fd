//! The `auto` policy: which operator (assembled sparse `R` or the matrix-free FFT operator) and
//! which solver (the interior-point QP or the first-order solver) a problem runs with, from cost
//! models fitted to `preston bench` timings on 2 cores (docs/preconditioning.md, "The `auto`
//! policy", has the commands; refit the constants below from them on another host). A pure
//! function of sizes, so it can be called wherever the decision is made.
//!
//! **Cost models** (seconds):
//! * assembling `R` and its row copy: `nnz / ASSEMBLY_NNZ_PER_S`;
//! * one product pair `R t`, `R^T y` with the sparse `R`: `nnz * SPARSE_PAIR_S_PER_NNZ`;
//! * one `R^T R t` with the FFT operator: `cells * FFT_PAIR_S_PER_CELL`, `cells` the padded
//!   lattice's cell count;
//! * the first-order solve: [`FIRST_ORDER_PRODUCTS`] products;
//! * the QP: `QP_S_PER_NNZ * nnz` (Clarabel's sparse LDL^T of the KKT system dominates).
//!
//! The QP is kept where it is predicted to take under [`QP_CHEAP_S`]: it then returns the
//! certified optimum at little cost.

use super::SolverKind;

/// Seconds per non-zero of `R` for one `R t` and one `R^T y` (sparse, 2 cores; generated 2e4
/// problem: 22 ms per pair at 7.45e6 non-zeros).
pub const SPARSE_PAIR_S_PER_NNZ: f64 = 2.95e-9;
/// Seconds per lattice cell for one `R^T R t` by FFT (2 cores; generated 2e4 problem: 2.6 ms per
/// product on a lattice of about 1e5 cells).
pub const FFT_PAIR_S_PER_CELL: f64 = 2.6e-8;
/// Non-zeros of `R` assembled per second (with its row copy).
pub const ASSEMBLY_NNZ_PER_S: f64 = 4.0e7;
/// Seconds of interior-point QP per non-zero of `R` (sample job 4.5 s at 7.7e5 non-zeros,
/// generated 2e3 2.6 s at 4.8e5, generated 2e4 68 s at 7.45e6).
pub const QP_S_PER_NNZ: f64 = 6.0e-6;
/// Products of a first-order solve, a round figure for the generated problems at the default
/// tolerance (`preston bench --sizes N --solvers first-order --job none` prints the iterations of
/// each size; projected L-BFGS takes up to twice this at 2e4). The crossovers that matter (FFT
/// against sparse, per product) do not depend on it; the QP's superlinear growth in memory
/// (1.5 GB at 2e4) is not in its linear model.
pub const FIRST_ORDER_PRODUCTS: f64 = 1000.0;
/// The QP is chosen where it is predicted to take less than this, s: it returns the certified
/// optimum, where the first-order solver at its default tolerance stops 0.1% to 4% above it on
/// the generated problems.
pub const QP_CHEAP_S: f64 = 1.0;

/// What the policy needs to know about a problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolicyInputs {
    /// Non-zeros of the assembled `R` (counted or estimated).
    pub nnz: f64,
    /// Cells of the FFT operator's padded lattice, when the FFT operator applies to the problem
    /// (map and dwell points on one lattice, planar TIF); `None` otherwise.
    pub fft_cells: Option<f64>,
    /// The QP is required (minimum-time mode, acceleration limits).
    pub needs_qp: bool,
    /// The user fixed the solver (`Some`), or left it to the policy.
    pub solver: Option<SolverKind>,
}

/// How `R` is held, as the policy decides it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OperatorKind {
    /// The assembled sparse matrix.
    Sparse,
    /// The matrix-free FFT operator.
    Fft,
}

/// The policy's decision, with the predicted times.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolicyChoice {
    /// Operator.
    pub operator: OperatorKind,
    /// Solver.
    pub solver: SolverKind,
    /// Predicted solve time of the QP (with assembly), s.
    pub qp_s: f64,
    /// Predicted first-order time with the sparse `R` (with assembly), s.
    pub first_order_sparse_s: f64,
    /// Predicted first-order time with the FFT operator, s (infinite where it does not apply).
    pub first_order_fft_s: f64,
}

/// Chooses operator and solver (module documentation).
pub fn choose(inputs: &PolicyInputs) -> PolicyChoice {
    let assembly = inputs.nnz / ASSEMBLY_NNZ_PER_S;
    let products = FIRST_ORDER_PRODUCTS;
    let qp_s = assembly + QP_S_PER_NNZ * inputs.nnz;
    let first_order_sparse_s = assembly + products * SPARSE_PAIR_S_PER_NNZ * inputs.nnz;
    let first_order_fft_s = inputs
        .fft_cells
        .map_or(f64::INFINITY, |c| products * FFT_PAIR_S_PER_CELL * c);
    let first_order = |fft_s: f64, sparse_s: f64| {
        if fft_s < sparse_s {
            OperatorKind::Fft
        } else {
            OperatorKind::Sparse
        }
    };
    let (operator, solver) = match (inputs.needs_qp, inputs.solver) {
        (true, _) | (false, Some(SolverKind::Qp)) => (OperatorKind::Sparse, SolverKind::Qp),
        (false, Some(SolverKind::FirstOrder)) => (
            first_order(first_order_fft_s, first_order_sparse_s),
            SolverKind::FirstOrder,
        ),
        (false, None) => {
            let fo = first_order_fft_s.min(first_order_sparse_s);
            if qp_s < QP_CHEAP_S || qp_s <= fo {
                (OperatorKind::Sparse, SolverKind::Qp)
            } else {
                (
                    first_order(first_order_fft_s, first_order_sparse_s),
                    SolverKind::FirstOrder,
                )
            }
        }
    };
    PolicyChoice {
        operator,
        solver,
        qp_s,
        first_order_sparse_s,
        first_order_fft_s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inputs(nnz: f64, fft_cells: Option<f64>) -> PolicyInputs {
        PolicyInputs {
            nnz,
            fft_cells,
            needs_qp: false,
            solver: None,
        }
    }

    #[test]
    fn small_problems_take_the_qp_and_convolution_problems_the_fft_path() {
        // A few hundred dwell points: the QP is cheap and exact.
        let small = choose(&inputs(2.0e4, Some(4.0e3)));
        assert_eq!(small.solver, SolverKind::Qp);
        // The generated 2e4 problem (9e6 non-zeros, 1.2e5 lattice cells): FFT, first-order.
        let big = choose(&inputs(9.0e6, Some(1.2e5)));
        assert_eq!(
            (big.operator, big.solver),
            (OperatorKind::Fft, SolverKind::FirstOrder)
        );
        // Off the lattice: the sparse operator.
        let off = choose(&inputs(9.0e6, None));
        assert_eq!(
            (off.operator, off.solver),
            (OperatorKind::Sparse, SolverKind::FirstOrder)
        );
        // Constraints that need the QP win over every cost.
        let q = choose(&PolicyInputs {
            needs_qp: true,
            ..inputs(9.0e6, Some(1.2e5))
        });
        assert_eq!(
            (q.operator, q.solver),
            (OperatorKind::Sparse, SolverKind::Qp)
        );
    }

    #[test]
    fn the_fft_operator_wins_where_each_dwell_point_touches_many_lattice_cells() {
        // Crossover: FFT pair per cell against sparse pair per non-zero.
        let ratio = FFT_PAIR_S_PER_CELL / SPARSE_PAIR_S_PER_NNZ;
        let cells = 1.0e6;
        let below = choose(&inputs(0.5 * ratio * cells, Some(cells)));
        let above = choose(&inputs(2.0 * ratio * cells, Some(cells)));
        assert_eq!(below.operator, OperatorKind::Sparse);
        assert_eq!(above.operator, OperatorKind::Fft);
    }
}
