//! A piece of straight motion at constant feed: the removal rate of a footprint swept uniformly
//! along it, per second, the one integration rule of every swept column and every sampled
//! motion (a plan's stretches, a program's contact motion) on a flat part.
//!
//! A footprint that falls continuously to zero is taken at the piece's midpoint (the midpoint
//! rule, `h^2 / 24 |TIF''|` off the exact average). A footprint cut where its rate is not zero (a
//! truncated Gaussian, [`InfluenceFunction::cut_disc_mm`]) jumps to zero on its cut circle, where
//! the midpoint rule is first-order: a map point whose cut disc just grazes the motion gets
//! either nothing or a whole piece's share from the sliver inside. For such a footprint a piece
//! the circle crosses is cut where the motion enters or leaves the map point's disc and the part
//! inside integrated by 4-point Gauss-Legendre; a piece wholly inside keeps the midpoint rule,
//! one wholly outside adds nothing, and so does one whose line only touches the circle, to the
//! rounding by which the circle is closed ([`piece_rate`]).
//!
//! The rule is written once: flat parts (a plan's columns, the lattice kernels, the sampled and
//! executed motions) call it in plan, curved parts in each dwell point's or sample's tangent
//! frame, with the piece lifted into that frame ([`super::surface`]); on the plane `z = 0` both
//! are the same arithmetic.

use crate::tif::gaussian::ON_CIRCLE_REL;
use crate::tif::InfluenceFunction;

/// Gauss-Legendre nodes and weights on `[-1, 1]`, 4 points: exact for cubics, so within
/// `1e-9` of the peak rate over a crossed piece (at most 1/64 of the support radius) of a Gaussian.
const GAUSS_LEGENDRE_4: [(f64, f64); 4] = [
    (-0.861_136_311_594_052_6, 0.347_854_845_137_453_9),
    (-0.339_981_043_584_856_3, 0.652_145_154_862_546_1),
    (0.339_981_043_584_856_3, 0.652_145_154_862_546_1),
    (0.861_136_311_594_052_6, 0.347_854_845_137_453_9),
];

/// Whether a motion's line at distance `d` from the centre of a cut circle of radius `r_mm` (the
/// support, closed up to rounding by [`ON_CIRCLE_REL`]) only touches the disc, given
/// `disc_over_a = r^2 - d^2` scaled by `a > 0`: `d >= r (1 - 2 ON_CIRCLE_REL)`, within rounding
/// of the circle itself. Such a line crosses the closed disc over a chord of at most
/// `2 r sqrt(8 ON_CIRCLE_REL)` (0.034 mm at a 6 mm cut) that rounding, not the motion, decides:
/// lattices and rasters put whole families of motions exactly tangent to the circle (a
/// generated raster's last row lies `r_trunc` past the map's edge), and counting the chord
/// would give their dwell points columns of a few 1e-4 of the peak rate where the point model
/// has none, which leaves the plan's problem without a useful condition number. The touch is
/// taken as the tangent point: nothing.
#[inline]
fn touches_only(disc: f64, a: f64, r_mm: f64) -> bool {
    let inner = r_mm * (1.0 - 2.0 * ON_CIRCLE_REL);
    !(disc > a * (r_mm * r_mm - inner * inner))
}

/// The rate at offset `(dx_mm, dy_mm)` from a piece's midpoint of `tif` swept uniformly along the
/// piece from `-half_mm` to `+half_mm` about its midpoint, per second of the piece's time (module
/// documentation). A piece of length zero, or a footprint without a cut disc: the rate at the
/// midpoint. The direction of travel does not matter.
#[inline]
pub fn piece_rate<T: InfluenceFunction + ?Sized>(
    tif: &T,
    half_mm: [f64; 2],
    dx_mm: f64,
    dy_mm: f64,
) -> f64 {
    let (ux, uy) = (half_mm[0], half_mm[1]);
    let a = ux * ux + uy * uy;
    let cut = match tif.cut_disc_mm() {
        Some(c) if a > 0.0 => c,
        _ => return tif.rate_nm_per_s(dx_mm, dy_mm),
    };
    // The motion at parameter u in [-1, 1] is at offset -u half from the map point's view:
    // the TIF is evaluated at (dx, dy) - u half, inside the cut when |(dx, dy) - c - u half| <= r.
    let (fx, fy) = (dx_mm - cut.0, dy_mm - cut.1);
    let half_b = -(fx * ux + fy * uy);
    let c = fx * fx + fy * fy - cut.2 * cut.2;
    // `disc / a` is `r^2 - d^2` for the distance `d` of the motion's line from the centre. A
    // line that comes no nearer than the circle less its rounding only touches the disc
    // ([`touches_only`]).
    let disc = half_b * half_b - a * c;
    if touches_only(disc, a, cut.2) {
        return 0.0;
    }
    let root = disc.sqrt();
    let (t1, t2) = ((-half_b - root) / a, (-half_b + root) / a);
    if t2 <= -1.0 || t1 >= 1.0 {
        return 0.0;
    }
    if t1 <= -1.0 && 1.0 <= t2 {
        return tif.rate_nm_per_s(dx_mm, dy_mm);
    }
    let (c0, c1) = (t1.max(-1.0), t2.min(1.0));
    let (mid, half) = (0.5 * (c0 + c1), 0.5 * (c1 - c0));
    let integral: f64 = GAUSS_LEGENDRE_4
        .iter()
        .map(|&(x, w)| {
            let u = mid + half * x;
            w * tif.rate_nm_per_s(dx_mm - u * ux, dy_mm - u * uy)
        })
        .sum();
    // The average over [-1, 1]: the integral over [c0, c1] (half times the weighted sum) over 2.
    0.5 * half * integral
}

/// `inner` swept uniformly along a piece `-half_mm..half_mm` about the origin ([`piece_rate`]):
/// the kernel of the samples of a motion that share a piece.
#[derive(Debug, Clone)]
pub struct PieceTif<T: InfluenceFunction> {
    inner: T,
    half_mm: [f64; 2],
}

impl<T: InfluenceFunction> PieceTif<T> {
    /// `inner` along the piece of half `half_mm`.
    pub fn new(inner: T, half_mm: [f64; 2]) -> Self {
        Self { inner, half_mm }
    }
}

/// How far from its midpoint a piece of half `half_mm` of `tif` reaches beyond the footprint's
/// own support radius, mm: the half's length for a footprint with a cut disc (integrated up to
/// the piece's ends), none otherwise (taken at the midpoint).
pub fn piece_reach_mm<T: InfluenceFunction + ?Sized>(tif: &T, half_mm: [f64; 2]) -> f64 {
    if tif.cut_disc_mm().is_some() {
        half_mm[0].hypot(half_mm[1])
    } else {
        0.0
    }
}

impl<T: InfluenceFunction> InfluenceFunction for PieceTif<T> {
    #[inline]
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        piece_rate(&self.inner, self.half_mm, dx_mm, dy_mm)
    }

    fn support_radius_mm(&self) -> f64 {
        self.inner.support_radius_mm() + piece_reach_mm(&self.inner, self.half_mm)
    }

    fn nominal_radius_mm(&self) -> f64 {
        self.inner.nominal_radius_mm()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tif::GaussianTif;

    /// A fine midpoint sum against the rule: the first-order error of `FINE` pieces at the cut.
    const FINE: usize = 200_000;
    const FINE_REL_TOL: f64 = 1e-5;

    /// The rule against a fine midpoint sum of the same piece, for pieces wholly inside (where
    /// the rule is the midpoint rule, second order), crossed once, crossed twice, and outside.
    #[test]
    fn a_crossed_piece_is_its_average_inside_the_cut() {
        let tif = GaussianTif::new(0.4, 10.0, 1.0).unwrap();
        let half = [0.05, 0.02];
        for (dx, dy) in [
            (0.99, 0.0),
            (1.04, 0.0),
            (0.0, 1.02),
            (0.5, 0.5),
            (0.3, 0.985),
            (2.0, 0.0),
        ] {
            let fine: f64 = (0..FINE)
                .map(|k| {
                    let u = -1.0 + (2 * k + 1) as f64 / FINE as f64;
                    tif.rate_nm_per_s(dx - u * half[0], dy - u * half[1])
                })
                .sum::<f64>()
                / FINE as f64;
            let got = piece_rate(&tif, half, dx, dy);
            let mid = tif.rate_nm_per_s(dx, dy);
            // Inside: the midpoint itself; crossed: the average to the fine sum's accuracy.
            let inside = (dx - half[0]).hypot(dy - half[1]) < 1.0
                && (dx + half[0]).hypot(dy + half[1]) < 1.0;
            if inside {
                assert_eq!(got, mid);
            } else {
                assert!(
                    (got - fine).abs() <= FINE_REL_TOL * tif.peak_rate_nm_per_s,
                    "({dx}, {dy}): {got} against {fine}"
                );
            }
            // The reversed piece is the same piece.
            assert_eq!(got, piece_rate(&tif, [-half[0], -half[1]], dx, dy));
        }
    }

    /// A motion along a line tangent to the cut circle (a raster row `r_trunc` from a map
    /// point) removes nothing there, as the point model does; a line one part in 1e3 inside the
    /// circle crosses it over the chord `2 sqrt(r^2 - d^2)`, and its pieces' rates average to
    /// the integral over the chord spread over the motion (a fine sum's accuracy).
    #[test]
    fn a_tangent_motion_removes_nothing_and_a_near_one_its_chord() {
        let r = 1.0;
        let tif = GaussianTif::new(0.4, 10.0, r).unwrap();
        let half = [0.05, 0.0];
        // Pieces tiling x in [-0.3, 0.3] at y = d from the map point.
        let pieces: Vec<f64> = (0..6).map(|k| -0.25 + 0.1 * k as f64).collect();
        for &x in &pieces {
            assert_eq!(piece_rate(&tif, half, x, r), 0.0, "tangent piece at {x}");
            assert_eq!(piece_rate(&tif, half, x, -r), 0.0, "tangent piece at {x}");
        }
        let d = r * (1.0 - 1e-3);
        // The chord inside the (closed) cut circle, integrated by a fine midpoint sum.
        let half_chord = (tif.support_radius_mm().powi(2) - d * d).sqrt();
        let on_chord: f64 = (0..FINE)
            .map(|k| {
                let x = -half_chord + 2.0 * half_chord * (k as f64 + 0.5) / FINE as f64;
                tif.rate_nm_per_s(x, d)
            })
            .sum::<f64>()
            * (2.0 * half_chord / FINE as f64);
        // The mean over the pieces (each a sixth of the motion's 0.6 mm) against the chord's
        // integral over the motion's length.
        let mean: f64 = pieces
            .iter()
            .map(|&x| piece_rate(&tif, half, x, d))
            .sum::<f64>()
            / pieces.len() as f64;
        let want = on_chord / 0.6;
        assert!(want > 0.0);
        assert!(
            (mean - want).abs() <= FINE_REL_TOL * tif.peak_rate_nm_per_s,
            "{mean} against {want}"
        );
    }
}
