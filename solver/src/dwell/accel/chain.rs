//! Exact weighted projection onto a chain polyhedron, in linear time per line.
//!
//! Given targets `y`, weights `w > 0`, boxes `[l_j, h_j]` and caps `c_j >= 0` on the linked
//! segments of a chain, this solves
//!
//! ```text
//! min_z  sum_j w_j / 2 (z_j - y_j)^2   s.t.  l_j <= z_j <= h_j,   |z_{j+1} - z_j| <= c_j  (linked j)
//! ```
//!
//! by dynamic programming on the value function (the method of Johnson, "A dynamic programming
//! algorithm for the fused lasso and L0-segmentation", J. Comput. Graph. Stat. 22, 2013, with the
//! fused-lasso penalty replaced by a hard bound on the difference). `F_0(z) = w_0/2 (z - y_0)^2`
//! on `[l_0, h_0]`; along a linked segment `F_{j+1}(z) = w_{j+1}/2 (z - y_{j+1})^2 +
//! min_{|s - z| <= c_j} F_j(s)` on `[l_{j+1}, h_{j+1}]`. Each `F_j` is convex and piecewise
//! quadratic, so its derivative is piecewise linear and non-decreasing; the window minimum cuts
//! the derivative at the minimiser `m_j`, shifts the part left of it by `-c_j` and the part right
//! of it by `+c_j`, and puts a zero piece between. Kept as two deques (left and right of `m_j`)
//! with a lazy shift and a lazy added linear term each, a step costs `O(1)` plus the pieces the
//! minimiser moves over. The backward pass is `z_last = m_last`,
//! `z_j = clamp(m_j, z_{j+1} - c_j, z_{j+1} + c_j)`, exact because each `F_j` is convex.
//!
//! **Precision.** A piece's slope is the sum of the weights merged into it and its value is
//! evaluated as `A z + B`, so a weight far below a neighbouring one is resolved to about
//! `1e-16 A / w` of the distances; keep the weights of one chain within about 1e10 of each other
//! (the squared-speed method fixes points whose weight is above that, see [`super::speed`]).
//!
//! An unlinked segment starts a new chain. If rounding leaves a box disjoint from the reach of
//! the previous point (the exact set is then empty or a single point), the chain is cut there and
//! the cut is counted, so the caller can see it.

use std::collections::VecDeque;

/// A side's lazy slope may exceed the next weight by this factor before it is written into the
/// pieces (a relative rounding of about 1e-16 * 1e6 on that weight at worst).
const FLUSH_RATIO: f64 = 1e6;

/// One piece of the derivative: on `[x + shift, next start + shift)` its value is
/// `a (z - shift) + b + alpha z + beta` with the side's `shift`, `alpha`, `beta`.
#[derive(Debug, Clone, Copy)]
struct Piece {
    x: f64,
    a: f64,
    b: f64,
}

/// One side of the minimiser: pieces in increasing order, with the lazy transform.
#[derive(Debug, Default)]
struct Side {
    pieces: VecDeque<Piece>,
    shift: f64,
    alpha: f64,
    beta: f64,
}

impl Side {
    fn reset(&mut self) {
        self.pieces.clear();
        self.shift = 0.0;
        self.alpha = 0.0;
        self.beta = 0.0;
    }

    /// Actual start of a piece.
    fn start(&self, p: &Piece) -> f64 {
        p.x + self.shift
    }

    /// The piece's value at actual `z`.
    fn value(&self, p: &Piece, z: f64) -> f64 {
        let (_, a, b) = self.to_actual(p);
        // At an infinite end a flat piece keeps its value (0 * inf would be NaN).
        if a == 0.0 {
            b
        } else {
            a * z + b
        }
    }

    /// The piece as `A z + B` in actual coordinates, and its actual start.
    fn to_actual(&self, p: &Piece) -> (f64, f64, f64) {
        let a = p.a + self.alpha;
        let b = p.b - p.a * self.shift + self.beta;
        (self.start(p), a, b)
    }

    /// A piece `A z + B` starting at actual `x`, in this side's stored coordinates.
    fn stored(&self, x: f64, a: f64, b: f64) -> Piece {
        let pa = a - self.alpha;
        Piece {
            x: x - self.shift,
            a: pa,
            b: b - self.beta + pa * self.shift,
        }
    }

    /// `f(z) -> f(z - d)`: every piece moves right by `d`.
    fn move_by(&mut self, d: f64) {
        self.shift += d;
        self.beta -= self.alpha * d;
    }

    /// Writes the lazy transform into the pieces and clears it. Needed before a weight far
    /// below the accumulated slope is added: `alpha` would otherwise absorb it (weights of the
    /// squared-speed metric span many decades).
    fn flush(&mut self) {
        let (shift, alpha, beta) = (self.shift, self.alpha, self.beta);
        for p in self.pieces.iter_mut() {
            let a = p.a + alpha;
            let b = p.b - p.a * shift + beta;
            *p = Piece {
                x: p.x + shift,
                a,
                b,
            };
        }
        self.shift = 0.0;
        self.alpha = 0.0;
        self.beta = 0.0;
    }

    /// Flushes when `w` would be lost against the accumulated slope or offset.
    fn prepare_for(&mut self, w: f64) {
        if self.alpha.abs() > FLUSH_RATIO * w {
            self.flush();
        }
    }

    /// Adds `w (z - y)`.
    fn add_linear(&mut self, w: f64, y: f64) {
        self.alpha += w;
        self.beta -= w * y;
    }
}

/// Scratch for one chain (reused across calls: no allocation once grown).
#[derive(Debug, Default)]
pub struct ChainScratch {
    left: Side,
    right: Side,
    minimiser: Vec<f64>,
    cut: Vec<bool>,
}

/// The chain's data for [`project_chain`].
#[derive(Debug, Clone, Copy)]
pub struct Chain<'a> {
    /// Targets `y_j`.
    pub target: &'a [f64],
    /// Weights `w_j > 0`.
    pub weight: &'a [f64],
    /// Lower bounds `l_j` (may be `-inf`).
    pub lower: &'a [f64],
    /// Upper bounds `h_j` (may be `+inf`).
    pub upper: &'a [f64],
    /// Caps `c_j >= 0` of the segments `j -> j + 1` (`n - 1` entries).
    pub cap: &'a [f64],
    /// Whether segment `j -> j + 1` carries the cap (`n - 1` entries).
    pub linked: &'a [bool],
}

impl ChainScratch {
    /// The linked segments `j -> j + 1` the last [`project_chain`] cut (rounding, or boxes that
    /// leave no overlap), by their first point `j`.
    pub fn cut_segments(&self) -> impl Iterator<Item = usize> + '_ {
        self.cut
            .iter()
            .enumerate()
            .filter_map(|(j, &c)| c.then_some(j))
    }

    /// The actual end of the left side (the minimiser split), or `fallback` when the right side
    /// is empty.
    fn split(&self, fallback: f64) -> f64 {
        match self.right.pieces.front() {
            Some(p) => self.right.start(p),
            None => fallback,
        }
    }

    /// Actual end of the right side's first piece.
    fn right_front_end(&self, hi: f64) -> f64 {
        match self.right.pieces.get(1) {
            Some(q) => self.right.start(q),
            None => hi,
        }
    }

    fn move_left_to_right(&mut self) {
        if let Some(p) = self.left.pieces.pop_back() {
            let (x, a, b) = self.left.to_actual(&p);
            let q = self.right.stored(x, a, b);
            self.right.pieces.push_front(q);
        }
    }

    fn move_right_to_left(&mut self) {
        if let Some(p) = self.right.pieces.pop_front() {
            let (x, a, b) = self.right.to_actual(&p);
            let q = self.left.stored(x, a, b);
            self.left.pieces.push_back(q);
        }
    }

    /// Drops pieces entirely outside `[lo, hi]` (never the last one).
    fn prune(&mut self, lo: f64, hi: f64) {
        while !self.left.pieces.is_empty() {
            let end = match self.left.pieces.get(1) {
                Some(p) => self.left.start(p),
                None => self.split(hi),
            };
            if end > lo || self.left.pieces.len() + self.right.pieces.len() <= 1 {
                break;
            }
            self.left.pieces.pop_front();
        }
        while let Some(p) = self.right.pieces.back() {
            if self.right.start(p) >= hi && self.left.pieces.len() + self.right.pieces.len() > 1 {
                self.right.pieces.pop_back();
            } else {
                break;
            }
        }
    }

    /// The minimiser of the current function on `[lo, hi]`; leaves the left side ending and the
    /// right side starting there.
    fn minimise(&mut self, lo: f64, hi: f64) -> f64 {
        // Move right while the zero lies right of the right side's first piece (or that piece is
        // below the domain).
        while let Some(p) = self.right.pieces.front().copied() {
            let end = self.right_front_end(hi);
            if end < hi && (end <= lo || self.right.value(&p, end) < 0.0) {
                self.move_right_to_left();
            } else {
                break;
            }
        }
        // Move left while the zero lies left of the left side's last piece (or that piece is
        // above the domain).
        while let Some(p) = self.left.pieces.back().copied() {
            let start = self.left.start(&p);
            if start > lo && (start >= hi || self.left.value(&p, start) > 0.0) {
                self.move_left_to_right();
            } else {
                break;
            }
        }
        // Pieces starting beyond `hi` are dead: the domain then ends inside the left side's last
        // piece.
        let s = self.split(hi);
        let s_in = s.min(hi);
        // A left side ending at or below `lo` is dead too.
        if let Some(p) = self.left.pieces.back().copied().filter(|_| s > lo) {
            if self.left.value(&p, s_in) > 0.0 {
                // The zero is inside the left side's last piece: split it there.
                let (start, a, b) = self.left.to_actual(&p);
                let root = if a > 0.0 { -b / a } else { start };
                let m = root.min(s_in).max(start.max(lo)).min(hi);
                let q = self.right.stored(m, a, b);
                self.right.pieces.push_front(q);
                return m;
            }
        }
        if s <= hi {
            if let Some(p) = self.right.pieces.front().copied() {
                if self.right.value(&p, s) < 0.0 {
                    // The zero is inside the right side's first piece: split it there.
                    let end = self.right_front_end(hi);
                    let (_, a, b) = self.right.to_actual(&p);
                    let root = if a > 0.0 { -b / a } else { end };
                    let m = root.min(end.min(hi)).max(s.max(lo));
                    self.move_right_to_left();
                    let q = self.right.stored(m, a, b);
                    self.right.pieces.push_front(q);
                    return m;
                }
            }
        }
        // The derivative jumps across zero at the split, or the minimiser is at a bound.
        let m = s.max(lo).min(hi);
        if let Some(p) = self.right.pieces.front_mut() {
            if p.x + self.right.shift < m {
                p.x = m - self.right.shift;
            }
        }
        m
    }
}

/// Projects one chain (see the module documentation) into `out` (the chain's length); returns
/// the number of linked segments cut because rounding left no overlap.
pub fn project_chain(chain: &Chain<'_>, scratch: &mut ChainScratch, out: &mut [f64]) -> usize {
    let n = chain.target.len();
    if n == 0 {
        return 0;
    }
    scratch.minimiser.clear();
    scratch.minimiser.resize(n, 0.0);
    scratch.cut.clear();
    scratch.cut.resize(n, false);
    let mut cuts = 0;
    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
    for j in 0..n {
        let mut fresh = true;
        if j > 0 && chain.linked[j - 1] {
            let c = chain.cap[j - 1];
            let (nlo, nhi) = ((lo - c).max(chain.lower[j]), (hi + c).min(chain.upper[j]));
            if nlo > nhi {
                cuts += 1;
                scratch.cut[j - 1] = true;
            } else {
                fresh = false;
                let w = chain.weight[j];
                scratch.left.prepare_for(w);
                scratch.right.prepare_for(w);
                let m = scratch.minimiser[j - 1];
                scratch.left.move_by(-c);
                scratch.right.move_by(c);
                let zero = scratch.right.stored(m - c, 0.0, 0.0);
                scratch.right.pieces.push_front(zero);
                lo = nlo;
                hi = nhi;
            }
        }
        if fresh {
            scratch.left.reset();
            scratch.right.reset();
            scratch.right.pieces.push_back(Piece {
                x: f64::NEG_INFINITY,
                a: 0.0,
                b: 0.0,
            });
            lo = chain.lower[j];
            hi = chain.upper[j];
        }
        let (w, y) = (chain.weight[j], chain.target[j]);
        scratch.left.add_linear(w, y);
        scratch.right.add_linear(w, y);
        scratch.prune(lo, hi);
        let m = scratch.minimise(lo, hi);
        // At a bound the side beyond it is dead; dropping it keeps rounding in the shifted
        // coordinates from reviving it at the next step.
        if m <= lo {
            scratch.left.pieces.clear();
        }
        if m >= hi {
            scratch.right.pieces.clear();
        }
        scratch.minimiser[j] = m;
    }
    let mins = &scratch.minimiser;
    out[n - 1] = mins[n - 1];
    for j in (0..n - 1).rev() {
        out[j] = if chain.linked[j] && !scratch.cut[j] {
            let c = chain.cap[j];
            mins[j].max(out[j + 1] - c).min(out[j + 1] + c)
        } else {
            mins[j]
        };
    }
    cuts
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64 as Rng;

    /// Agreement with the interior-point reference in the metric, relative to the distance
    /// (asked for 1e-12; with weights over six decades it lands within about 1e-6).
    const REFERENCE_TOL: f64 = 1e-5;
    /// Relative objective margin over the interior-point reference.
    const OBJECTIVE_TOL: f64 = 1e-8;

    fn project(y: &[f64], w: &[f64], l: &[f64], h: &[f64], c: &[f64], linked: &[bool]) -> Vec<f64> {
        let mut out = vec![0.0; y.len()];
        let mut scratch = ChainScratch::default();
        let chain = Chain {
            target: y,
            weight: w,
            lower: l,
            upper: h,
            cap: c,
            linked,
        };
        let cuts = project_chain(&chain, &mut scratch, &mut out);
        assert_eq!(cuts, 0);
        out
    }

    /// The same projection as a Clarabel QP (an interior-point solver, independent of the DP).
    fn reference(
        y: &[f64],
        w: &[f64],
        l: &[f64],
        h: &[f64],
        c: &[f64],
        linked: &[bool],
    ) -> Vec<f64> {
        use clarabel::algebra::CscMatrix as ClCsc;
        use clarabel::solver::{DefaultSettings, DefaultSolver, IPSolver, SupportedConeT};
        let n = y.len();
        // Rows of A z <= b, as (column, value) lists per row.
        let mut rows: Vec<(Vec<(usize, f64)>, f64)> = Vec::new();
        for j in 0..n {
            if l[j].is_finite() {
                rows.push((vec![(j, -1.0)], -l[j]));
            }
            if h[j].is_finite() {
                rows.push((vec![(j, 1.0)], h[j]));
            }
        }
        for j in 0..n - 1 {
            if linked[j] {
                rows.push((vec![(j, -1.0), (j + 1, 1.0)], c[j]));
                rows.push((vec![(j, 1.0), (j + 1, -1.0)], c[j]));
            }
        }
        let m = rows.len();
        let (mut colptr, mut rowval, mut nzval) = (vec![0], Vec::new(), Vec::new());
        for j in 0..n {
            for (r, (entries, _)) in rows.iter().enumerate() {
                for &(col, v) in entries {
                    if col == j {
                        rowval.push(r);
                        nzval.push(v);
                    }
                }
            }
            colptr.push(rowval.len());
        }
        let a = ClCsc::new(m, n, colptr, rowval, nzval);
        let p = ClCsc::new(n, n, (0..=n).collect(), (0..n).collect(), w.to_vec());
        let q: Vec<f64> = (0..n).map(|j| -w[j] * y[j]).collect();
        let b: Vec<f64> = rows.iter().map(|(_, b)| *b).collect();
        let cones = [SupportedConeT::NonnegativeConeT(m)];
        let settings = DefaultSettings::<f64> {
            verbose: false,
            tol_gap_abs: 1e-12,
            tol_gap_rel: 1e-12,
            tol_feas: 1e-12,
            ..DefaultSettings::default()
        };
        let mut solver = DefaultSolver::new(&p, &q, &a, &b, &cones, settings).unwrap();
        solver.solve();
        solver.solution.x.clone()
    }

    #[test]
    fn two_points_closed_form() {
        // Equal weights: the pair meets in the middle of the gap.
        let z = project(
            &[0.0, 10.0],
            &[1.0, 1.0],
            &[-1e9; 2],
            &[1e9; 2],
            &[2.0],
            &[true],
        );
        assert!(
            (z[0] - 4.0).abs() < 1e-12 && (z[1] - 6.0).abs() < 1e-12,
            "{z:?}"
        );
        // Weights 1 and 3: z1 = z0 + 2, z0 + 3 (z0 + 2 - 10) = 0, z0 = 6.
        let z = project(
            &[0.0, 10.0],
            &[1.0, 3.0],
            &[-1e9; 2],
            &[1e9; 2],
            &[2.0],
            &[true],
        );
        assert!(
            (z[0] - 6.0).abs() < 1e-12 && (z[1] - 8.0).abs() < 1e-12,
            "{z:?}"
        );
        // Unlinked: the targets, clamped to their boxes.
        let z = project(
            &[0.0, 10.0],
            &[1.0, 3.0],
            &[1.0, 0.0],
            &[5.0, 7.0],
            &[2.0],
            &[false],
        );
        assert_eq!(z, vec![1.0, 7.0]);
    }

    #[test]
    fn matches_an_interior_point_reference_on_random_chains() {
        let mut rng = Rng::new(7);
        for case in 0..3000 {
            let n = 2 + case % 11;
            let y: Vec<f64> = (0..n).map(|_| 20.0 * rng.uniform() - 10.0).collect();
            // Weights over six decades, as the squared-speed metric has.
            let w: Vec<f64> = (0..n)
                .map(|_| 10f64.powf(6.0 * rng.uniform() - 3.0))
                .collect();
            let l: Vec<f64> = (0..n)
                .map(|_| {
                    if rng.uniform() < 0.3 {
                        f64::NEG_INFINITY
                    } else {
                        -8.0 * rng.uniform()
                    }
                })
                .collect();
            let h: Vec<f64> = (0..n)
                .map(|_| {
                    if rng.uniform() < 0.3 {
                        f64::INFINITY
                    } else {
                        8.0 * rng.uniform()
                    }
                })
                .collect();
            let c: Vec<f64> = (0..n - 1).map(|_| 3.0 * rng.uniform()).collect();
            let linked: Vec<bool> = (0..n - 1).map(|_| rng.uniform() < 0.85).collect();
            let z = project(&y, &w, &l, &h, &c, &linked);
            let r = reference(&y, &w, &l, &h, &c, &linked);
            let obj = |z: &[f64]| {
                (0..n)
                    .map(|j| 0.5 * w[j] * (z[j] - y[j]).powi(2))
                    .sum::<f64>()
            };
            for j in 0..n {
                assert!(
                    z[j] >= l[j] - 1e-12 && z[j] <= h[j] + 1e-12,
                    "case {case}: box {j}"
                );
                if j + 1 < n && linked[j] {
                    assert!(
                        (z[j + 1] - z[j]).abs() <= c[j] + 1e-9,
                        "case {case}: cap {j}"
                    );
                }
                // Positions weighted by the metric: a point of tiny weight is determined only
                // loosely by the interior-point solver.
                let scale = 1.0 + obj(&r).sqrt();
                assert!(
                    w[j].sqrt() * (z[j] - r[j]).abs() <= REFERENCE_TOL * scale,
                    "case {case}: z {z:?} reference {r:?}"
                );
            }
            // The interior-point solution is feasible only to its tolerance: the exact
            // projection's objective is no worse than it beyond that.
            assert!(
                obj(&z) <= obj(&r) * (1.0 + OBJECTIVE_TOL) + OBJECTIVE_TOL,
                "case {case}"
            );
        }
    }

    #[test]
    fn long_chain_is_feasible_and_optimal_against_perturbations() {
        // A 2,000-point chain with a spike: the result is feasible, and no feasible
        // perturbation along single coordinates lowers the objective (a necessary condition).
        let n = 2000;
        let mut rng = Rng::new(3);
        let y: Vec<f64> = (0..n)
            .map(|j| {
                if j == 700 {
                    500.0
                } else {
                    10.0 * rng.uniform()
                }
            })
            .collect();
        let w: Vec<f64> = (0..n).map(|_| 0.5 + rng.uniform()).collect();
        let (l, h) = (vec![0.0; n], vec![400.0; n]);
        let c = vec![1.0; n - 1];
        let linked = vec![true; n - 1];
        let z = project(&y, &w, &l, &h, &c, &linked);
        let obj = |z: &[f64]| {
            (0..n)
                .map(|j| 0.5 * w[j] * (z[j] - y[j]).powi(2))
                .sum::<f64>()
        };
        let feasible = |z: &[f64]| {
            (0..n).all(|j| z[j] >= l[j] - 1e-9 && z[j] <= h[j] + 1e-9)
                && (0..n - 1).all(|j| (z[j + 1] - z[j]).abs() <= c[j] + 1e-9)
        };
        assert!(feasible(&z));
        let f0 = obj(&z);
        for j in (0..n).step_by(37) {
            for d in [-1e-3, 1e-3] {
                let mut p = z.clone();
                p[j] += d;
                if feasible(&p) {
                    assert!(obj(&p) >= f0 - 1e-12, "point {j}");
                }
            }
        }
        // The spike stands above every other target, and the chain falls from it at the cap.
        assert!(z[700] > 10.0 && z[700] < 400.0, "{}", z[700]);
        assert!((z[700] - z[701] - 1.0).abs() < 1e-9 && (z[700] - z[699] - 1.0).abs() < 1e-9);
    }
}
