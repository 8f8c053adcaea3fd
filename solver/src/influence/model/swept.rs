//! The motion-true (swept) influence model: column `j` of `R` is the removal of the tool swept
//! along dwell point `j`'s stretch of path at constant feed, as the program runs it.
//!
//! Dwell point `j` owns the stretch from boundary `a_j` (the midpoint of the segment before it)
//! through the point `p_j` to boundary `b_j` (the midpoint of the segment after it); the first
//! and last points own a stretch extended straight beyond the path end by half a segment
//! ([`crate::machine::nc`]). The program crosses it in two blocks, `a_j -> p_j` and
//! `p_j -> b_j`, at one feed `ds_j / t_j`, so the removal per second of dwell is
//!
//! ```text
//! R[i, j] = (1 / ds_j) * integral over the stretch of TIF(x_i - p(s)) ds
//! ```
//!
//! (the point model, `R[i, j] = TIF(x_i - p_j)`, is its limit `ds_j -> 0`). The integral is taken
//! by the midpoint rule of the executed run ([`crate::machine::gcode::motion`]): each of the two
//! blocks cut into `ceil(L / h)` equal pieces, a sample at each piece's midpoint weighted by its
//! share of the stretch's length, so the plan's column is the program's removal run at its
//! programmed feed, sample for sample. With `h` 1/64 of the TIF's support radius the rule is
//! within 0.1% of the peak rate of the exact integral for a Gaussian (`h^2 / 24 |TIF''|`; tested
//! against the closed form in `erf`).
//!
//! A footprint cut where its rate is not zero (a truncated Gaussian,
//! [`InfluenceFunction::cut_disc_mm`]) jumps to zero on its cut circle, where the midpoint rule is
//! first-order: a map point whose cut disc just grazes a stretch gets either nothing or a whole
//! piece's share from the sliver inside, and a plan with little time weight leans on those
//! entries. Each sample is therefore its piece ([`Stretches::pieces_of`]) and integrated by the
//! rule of every sampled motion, [`piece_rate`]: for such a footprint the pieces the circle
//! crosses are integrated exactly over their part inside it; the others, and every piece of a
//! footprint that falls continuously to zero, keep the midpoint rule. The executed program's
//! contact motion is integrated by the same rule, piece for piece.
//!
//! The assembled operator takes each column's own stretch ([`assemble_swept`]); the lattice
//! operators (FFT, phase stencils, spreading) one shift-invariant kernel, the TIF averaged along
//! the stretch most dwell points share ([`Stretches::dominant`]; on a raster, the interior
//! stretch along its lines), [`SweptTif`].

use super::piece::piece_rate;
use crate::error::{Error, Result};
use crate::influence::operator::matrix::InfluenceMatrix;
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::tif::InfluenceFunction;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::OnceLock;

/// How the plan models the tool's action at a dwell point.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum InfluenceModel {
    /// The TIF averaged along the dwell point's stretch of path at constant feed.
    ///
    /// What the program does (module documentation). The default.
    #[default]
    Swept,
    /// The whole TIF at the dwell point.
    ///
    /// The literature's model, kept for comparison.
    Point,
}

/// Most quadrature pieces of one block of a stretch (a guard against a stretch far longer than
/// the TIF, whose samples would otherwise grow without bound before any budget is checked).
const MAX_PIECES_PER_BLOCK: usize = 256;

/// The rate at offset `(dx_mm, dy_mm)` from the dwell point of `tif` swept along a stretch whose
/// midpoint samples are `samples` (`(dx_mm, dy_mm, weight)`) and their pieces' halves `halves`
/// (from each sample to its piece's end): the sum of the pieces' rates by [`piece_rate`], or of
/// the rates at the samples when `halves` is empty ([`swept_sum`]).
pub fn swept_rate<T: InfluenceFunction + ?Sized>(
    tif: &T,
    samples: &[[f64; 3]],
    halves: &[[f64; 2]],
    dx_mm: f64,
    dy_mm: f64,
) -> f64 {
    swept_sum(samples, halves, dx_mm, dy_mm, |half, u, w| {
        piece_rate(tif, half, u, w)
    })
}

/// `sum_k w_k piece(h_k, dx - sx_k, dy - sy_k)` over the samples `(sx_k, sy_k, w_k)` of a
/// stretch and their pieces' halves `h_k` (zero, points, when `halves` is empty): the one sum of
/// a swept column, in plan ([`swept_rate`]) and in a curved part's tangent frame
/// ([`super::surface::assemble_on_surface_swept_with`]), so that a plane sums exactly as the
/// flat part. `piece(h, u, w)` is the rate at offset `(u, w)` of the TIF along the piece of half
/// `h` ([`piece_rate`]).
#[inline]
pub fn swept_sum<F: Fn([f64; 2], f64, f64) -> f64>(
    samples: &[[f64; 3]],
    halves: &[[f64; 2]],
    dx_mm: f64,
    dy_mm: f64,
    piece: F,
) -> f64 {
    if halves.is_empty() {
        return samples
            .iter()
            .map(|s| s[2] * piece([0.0, 0.0], dx_mm - s[0], dy_mm - s[1]))
            .sum();
    }
    samples
        .iter()
        .zip(halves)
        .map(|(s, &h)| s[2] * piece(h, dx_mm - s[0], dy_mm - s[1]))
        .sum()
}

/// The quadrature samples of every dwell point's stretch: offsets from the dwell point, mm, and
/// weights (fractions of the dwell, summing to 1 per stretch). Each distinct stretch (the same
/// boundary offsets, bit for bit) is sampled and held once; on a raster nearly every point
/// shares one.
#[derive(Debug, Clone)]
pub struct Stretches {
    /// For each dwell point, the index of its stretch among the distinct ones.
    kind_of: Vec<u32>,
    /// `kind_offsets[k]..kind_offsets[k + 1]` index the samples of distinct stretch `k`.
    kind_offsets: Vec<usize>,
    /// `(dx_mm, dy_mm, weight)` of every sample of the distinct stretches.
    samples: Vec<[f64; 3]>,
    /// Half of every sample's piece, from the sample to the piece's end, mm (zero for a
    /// stretch of length zero), beside `samples`.
    halves: Vec<[f64; 2]>,
    /// Largest distance of a sample from its dwell point, mm.
    reach_mm: f64,
    /// Largest distance of a piece's end from its dwell point, mm.
    extent_mm: f64,
    /// The dominant stretch, found once when first asked for.
    dominant: OnceLock<Dominant>,
}

/// The stretch most dwell points share ([`Stretches::dominant`]).
#[derive(Debug, Clone)]
struct Dominant {
    samples: Vec<[f64; 3]>,
    halves: Vec<[f64; 2]>,
    count: usize,
    /// The dwell points whose stretch differs, ascending.
    outside: Vec<usize>,
}

impl PartialEq for Stretches {
    /// The same samples for every dwell point (whether the dominant one was found yet aside).
    fn eq(&self, other: &Self) -> bool {
        self.len() == other.len()
            && self.reach_mm == other.reach_mm
            && (0..self.len()).all(|j| self.of(j) == other.of(j))
    }
}

/// The boundaries of dwell point `j`'s stretch relative to it, `(a, b)`: half the segment before
/// and after (the path's ends mirrored straight beyond).
fn boundaries(x: &[f64], y: &[f64], j: usize) -> ((f64, f64), (f64, f64)) {
    let half = |k: usize| (0.5 * (x[k] - x[j]), 0.5 * (y[k] - y[j]));
    match (j.checked_sub(1), (j + 1 < x.len()).then_some(j + 1)) {
        (Some(p), Some(q)) => (half(p), half(q)),
        (Some(p), None) => {
            let a = half(p);
            (a, (-a.0, -a.1))
        }
        (None, Some(q)) => {
            let b = half(q);
            ((-b.0, -b.1), b)
        }
        (None, None) => ((0.0, 0.0), (0.0, 0.0)),
    }
}

/// Appends the midpoint-rule samples of the stretch `a -> 0 -> b` with pieces of at most
/// `step_mm` to `samples` and their pieces' halves to `halves` (module documentation), and
/// returns the samples' and the pieces' ends' largest distance from the dwell point.
fn sample_stretch(
    (a, b): ((f64, f64), (f64, f64)),
    step_mm: f64,
    samples: &mut Vec<[f64; 3]>,
    halves: &mut Vec<[f64; 2]>,
) -> (f64, f64) {
    let la = a.0.hypot(a.1);
    let lb = b.0.hypot(b.1);
    let ds = la + lb;
    let mut reach = 0.0f64;
    if ds <= 0.0 {
        samples.push([0.0, 0.0, 1.0]);
        halves.push([0.0, 0.0]);
        return (reach, reach);
    }
    // Block a -> p (from the boundary to the point), then p -> b.
    for (from, to, len) in [(a, (0.0, 0.0), la), ((0.0, 0.0), b, lb)] {
        if len <= 0.0 {
            continue;
        }
        // A stretch far longer than the TIF (a connecting move) is cut into at most
        // MAX_PIECES_PER_BLOCK pieces: coarser than the executed run's sampling there.
        let pieces = (len / step_mm)
            .ceil()
            .clamp(1.0, MAX_PIECES_PER_BLOCK as f64);
        let k = pieces as usize;
        let w = len / pieces / ds;
        let half = [
            0.5 * (to.0 - from.0) / pieces,
            0.5 * (to.1 - from.1) / pieces,
        ];
        for i in 0..k {
            let f = (i as f64 + 0.5) / pieces;
            let (sx, sy) = (from.0 + f * (to.0 - from.0), from.1 + f * (to.1 - from.1));
            reach = reach.max(sx.hypot(sy));
            samples.push([sx, sy, w]);
            halves.push(half);
        }
    }
    // The pieces' ends: the stretch's own ends and the dwell point.
    (reach, reach.max(la).max(lb))
}

impl Stretches {
    /// The stretches of `path` sampled with pieces of at most `step_mm` of arc length (module
    /// documentation). A single point has a stretch of length zero: one sample, weight 1.
    pub fn of_path(path: &DwellPath, step_mm: f64) -> Result<Self> {
        if !(step_mm.is_finite() && step_mm > 0.0) {
            return Err(Error::invalid(
                "swept influence step",
                format!("must be positive and finite, got {step_mm} mm"),
            ));
        }
        let (x, y) = (path.x_mm(), path.y_mm());
        let n = x.len();
        let mut kind_of = Vec::with_capacity(n);
        let mut kind_offsets = vec![0];
        let mut samples = Vec::new();
        let mut halves = Vec::new();
        let mut reach = 0.0f64;
        let mut extent = 0.0f64;
        // Distinct stretches by their boundaries' bits: equal bits, equal samples.
        let mut kinds: HashMap<[u64; 4], u32> = HashMap::new();
        for j in 0..n {
            let (a, b) = boundaries(x, y, j);
            let bits = [a.0, a.1, b.0, b.1].map(f64::to_bits);
            let kind = match kinds.get(&bits) {
                Some(&k) => k,
                None => {
                    let k = u32::try_from(kinds.len()).map_err(|_| {
                        Error::invalid("dwell path", "has more distinct stretches than 2^32")
                    })?;
                    let (r, e) = sample_stretch((a, b), step_mm, &mut samples, &mut halves);
                    reach = reach.max(r);
                    extent = extent.max(e);
                    kind_offsets.push(samples.len());
                    kinds.insert(bits, k);
                    k
                }
            };
            kind_of.push(kind);
        }
        Ok(Self {
            kind_of,
            kind_offsets,
            samples,
            halves,
            reach_mm: reach,
            extent_mm: extent,
            dominant: OnceLock::new(),
        })
    }

    /// Number of stretches (dwell points).
    pub fn len(&self) -> usize {
        self.kind_of.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The samples `(dx_mm, dy_mm, weight)` of stretch `j`.
    pub fn of(&self, j: usize) -> &[[f64; 3]] {
        self.of_kind(self.kind_of[j] as usize)
    }

    /// The samples of distinct stretch `k`.
    fn of_kind(&self, k: usize) -> &[[f64; 3]] {
        &self.samples[self.kind_offsets[k]..self.kind_offsets[k + 1]]
    }

    /// Half of the piece of every sample of stretch `j` ([`Stretches::of`]), from the sample to
    /// the piece's end, mm: the motion the sample stands for ([`piece_rate`]).
    pub fn pieces_of(&self, j: usize) -> &[[f64; 2]] {
        self.halves_of_kind(self.kind_of[j] as usize)
    }

    /// The pieces' halves of distinct stretch `k`.
    fn halves_of_kind(&self, k: usize) -> &[[f64; 2]] {
        &self.halves[self.kind_offsets[k]..self.kind_offsets[k + 1]]
    }

    /// The rate at offset `(dx_mm, dy_mm)` from dwell point `j` of `tif` swept along its
    /// stretch, per second of its dwell ([`swept_rate`]): column `j` of the swept `R`.
    pub fn rate_nm_per_s<T: InfluenceFunction + ?Sized>(
        &self,
        j: usize,
        tif: &T,
        dx_mm: f64,
        dy_mm: f64,
    ) -> f64 {
        let k = self.kind_of[j] as usize;
        swept_rate(tif, self.of_kind(k), self.halves_of_kind(k), dx_mm, dy_mm)
    }

    /// `tif` swept along the dominant stretch ([`Stretches::dominant`]): the lattice operators'
    /// shared kernel, integrated as the columns are ([`swept_rate`]).
    pub fn dominant_kernel<T: InfluenceFunction>(&self, tif: T) -> SweptTif<T> {
        let d = self.dominant_stretch();
        SweptTif::with_pieces(tif, d.samples.clone(), d.halves.clone())
    }

    /// Largest distance of a sample from its dwell point, mm.
    pub fn reach_mm(&self) -> f64 {
        self.reach_mm
    }

    /// Largest distance from a dwell point at which its swept column of `tif` can be non-zero,
    /// mm: the support radius and the samples' reach, or, for a footprint with a cut disc
    /// (integrated up to the pieces' ends, [`piece_rate`]), the pieces' ends' reach.
    pub fn reach_of<T: InfluenceFunction + ?Sized>(&self, tif: &T) -> f64 {
        let along = if tif.cut_disc_mm().is_some() {
            self.extent_mm.max(self.reach_mm)
        } else {
            self.reach_mm
        };
        tif.support_radius_mm() + along
    }

    /// The stretch most dwell points share (the same samples up to order, to 1e-9 mm), and how
    /// many share it: the shift-invariant kernel of the lattice operators. On a serpentine raster
    /// it is the interior stretch along the lines; the row ends (an L-shaped stretch, a TIF
    /// radius off the map) and the path's ends differ.
    pub fn dominant(&self) -> (Vec<[f64; 3]>, usize) {
        let d = self.dominant_stretch();
        (d.samples.clone(), d.count)
    }

    /// The dwell points whose stretch is not the dominant one ([`Stretches::dominant`]),
    /// ascending: the columns the lattice operators' shared kernel does not reproduce.
    pub fn outside_dominant(&self) -> Vec<usize> {
        self.dominant_stretch().outside.clone()
    }

    /// A stretch's samples up to order, to 1e-9 mm and 1e-12 of weight.
    fn key(s: &[[f64; 3]]) -> Vec<[i64; 3]> {
        let mut k: Vec<[i64; 3]> = s
            .iter()
            .map(|p| {
                [
                    (p[0] * 1e9).round() as i64,
                    (p[1] * 1e9).round() as i64,
                    (p[2] * 1e12).round() as i64,
                ]
            })
            .collect();
        k.sort_unstable();
        k
    }

    /// The dominant stretch, found on the first call: the dwell points counted by distinct
    /// stretch, those counts merged over the stretches with one key (in the order the stretches
    /// first occur), then the points whose key differs.
    fn dominant_stretch(&self) -> &Dominant {
        self.dominant.get_or_init(|| {
            let kinds = self.kind_offsets.len() - 1;
            // Points and the first point of each distinct stretch.
            let mut per_kind = vec![(0usize, usize::MAX); kinds];
            for (j, &k) in self.kind_of.iter().enumerate() {
                let e = &mut per_kind[k as usize];
                e.0 += 1;
                e.1 = e.1.min(j);
            }
            let keys: Vec<Vec<[i64; 3]>> = (0..kinds).map(|k| Self::key(self.of_kind(k))).collect();
            let mut by_key: HashMap<&[[i64; 3]], (usize, usize)> = HashMap::new();
            for (key, &(count, first)) in keys.iter().zip(&per_kind) {
                let e = by_key.entry(key.as_slice()).or_insert((0, first));
                e.0 += count;
                e.1 = e.1.min(first);
            }
            // Most shared; ties to the earliest stretch, so the choice does not depend on
            // hashing.
            let best = by_key
                .values()
                .max_by(|a, b| a.0.cmp(&b.0).then(b.1.cmp(&a.1)))
                .copied();
            match best {
                Some((count, j)) => {
                    let dominant = &keys[self.kind_of[j] as usize];
                    let inside: Vec<bool> = keys.iter().map(|k| k == dominant).collect();
                    let outside = (0..self.len())
                        .filter(|&i| !inside[self.kind_of[i] as usize])
                        .collect();
                    Dominant {
                        samples: self.of(j).to_vec(),
                        halves: self.pieces_of(j).to_vec(),
                        count,
                        outside,
                    }
                }
                None => Dominant {
                    samples: vec![[0.0, 0.0, 1.0]],
                    halves: vec![[0.0, 0.0]],
                    count: 0,
                    outside: Vec::new(),
                },
            }
        })
    }
}

/// A TIF averaged along one stretch: `rate(dx, dy) = sum_k w_k TIF(dx - sx_k, dy - sy_k)`, the
/// swept kernel shared by the lattice operators (module documentation).
#[derive(Debug, Clone)]
pub struct SweptTif<T: InfluenceFunction> {
    inner: T,
    samples: Vec<[f64; 3]>,
    /// The samples' pieces' halves where known ([`Stretches::dominant_kernel`]): a footprint
    /// with a cut disc is then integrated exactly where the circle crosses a piece
    /// ([`piece_rate`]); none, the samples are points.
    halves: Vec<[f64; 2]>,
    reach_mm: f64,
    /// Largest distance of the pieces' ends from the dwell point (the samples' reach without
    /// pieces), mm.
    extent_mm: f64,
}

impl<T: InfluenceFunction> SweptTif<T> {
    /// `inner` averaged over `samples` (`(dx_mm, dy_mm, weight)`).
    pub fn new(inner: T, samples: Vec<[f64; 3]>) -> Self {
        let reach_mm = samples.iter().map(|s| s[0].hypot(s[1])).fold(0.0, f64::max);
        Self {
            inner,
            samples,
            halves: Vec::new(),
            reach_mm,
            extent_mm: reach_mm,
        }
    }

    /// `inner` swept along the pieces of `samples` (`(dx_mm, dy_mm, weight)`), `halves` from
    /// each sample to its piece's end ([`swept_rate`]).
    pub fn with_pieces(inner: T, samples: Vec<[f64; 3]>, halves: Vec<[f64; 2]>) -> Self {
        let mut t = Self::new(inner, samples);
        t.extent_mm = t
            .samples
            .iter()
            .zip(&halves)
            .map(|(s, h)| s[0].hypot(s[1]) + h[0].hypot(h[1]))
            .fold(t.reach_mm, f64::max);
        t.halves = halves;
        t
    }

    /// The TIF swept along.
    pub fn inner(&self) -> &T {
        &self.inner
    }
}

impl<T: InfluenceFunction> InfluenceFunction for SweptTif<T> {
    #[inline]
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        swept_rate(&self.inner, &self.samples, &self.halves, dx_mm, dy_mm)
    }

    fn support_radius_mm(&self) -> f64 {
        let along = if self.inner.cut_disc_mm().is_some() {
            self.extent_mm
        } else {
            self.reach_mm
        };
        self.inner.support_radius_mm() + along
    }

    fn nominal_radius_mm(&self) -> f64 {
        self.inner.nominal_radius_mm()
    }
}

/// Assembles the swept `R`: `R[i, j] = sum_k w_jk TIF(x_i - X_j - sx_jk, y_i - Y_j - sy_jk)`
/// over stretch `j`'s samples ([`Stretches::of_path`]), the pieces a cut circle crosses
/// integrated exactly ([`Stretches::rate_nm_per_s`]).
pub fn assemble_swept<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    path: &DwellPath,
    stretches: &Stretches,
    tif: &T,
    observer: &dyn Observer,
) -> Result<InfluenceMatrix> {
    if stretches.len() != path.len() {
        return Err(Error::LengthMismatch {
            what: "stretches",
            got: stretches.len(),
            expected: path.len(),
        });
    }
    InfluenceMatrix::assemble_with(
        map_x_mm,
        map_y_mm,
        path.x_mm(),
        path.y_mm(),
        stretches.reach_of(tif),
        |j, _i, dx, dy| stretches.rate_nm_per_s(j, tif, dx, dy),
        observer,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    /// Accuracy of the midpoint rule at 1/64 of the support radius against the closed form,
    /// relative to the peak rate: the model error the plan may carry, 0.1% (the rule's error is
    /// `h^2 / 24 |TIF''|`; measured 1.2e-4 here).
    const QUADRATURE_TOL: f64 = 1e-3;

    /// `erf` by Abramowitz and Stegun 7.1.26 is too coarse; the series and continued fraction
    /// below are within 1e-15 over the range used.
    fn erf(x: f64) -> f64 {
        if x < 0.0 {
            return -erf(-x);
        }
        if x < 3.0 {
            // Maclaurin series: erf x = 2/sqrt(pi) sum (-1)^n x^(2n+1) / (n! (2n+1)).
            let mut term = x;
            let mut sum = x;
            for n in 1..200 {
                term *= -x * x / n as f64;
                let add = term / (2 * n + 1) as f64;
                sum += add;
                if add.abs() < 1e-18 {
                    break;
                }
            }
            2.0 / std::f64::consts::PI.sqrt() * sum
        } else {
            // erfc x = exp(-x^2)/(x sqrt(pi)) * (1 - 1/(2x^2) + 3/(4x^4) - ...), asymptotic.
            let mut term = 1.0;
            let mut sum = 1.0;
            for n in 1..30 {
                term *= -((2 * n - 1) as f64) / (2.0 * x * x);
                sum += term;
            }
            1.0 - (-x * x).exp() / (x * std::f64::consts::PI.sqrt()) * sum
        }
    }

    #[test]
    fn a_straight_stretch_of_a_gaussian_matches_the_erf_closed_form() {
        // Gaussian A exp(-r^2 / 2 s^2) swept along x over [-L/2, L/2] (a point of a line with
        // segments L): (1/L) int = A exp(-y^2/2s^2) sqrt(pi/2) s / L
        //                      * (erf((x + L/2) / (s sqrt 2)) - erf((x - L/2) / (s sqrt 2))).
        let (sigma, peak, trunc) = (1.5, 4.0, 12.0);
        let tif = GaussianTif::new(sigma, peak, trunc).unwrap();
        let seg = 2.0;
        let path = DwellPath::new(vec![-seg, 0.0, seg], vec![0.0; 3]).unwrap();
        let step = tif.support_radius_mm() / 64.0;
        let st = Stretches::of_path(&path, step).unwrap();
        let w: f64 = st.of(1).iter().map(|s| s[2]).sum();
        assert!((w - 1.0).abs() < 1e-12, "weights sum to {w}");
        let mx: Vec<f64> = (-20..=20).map(|i| 0.25 * i as f64).collect();
        let my: Vec<f64> = mx.iter().map(|x| 0.3 * x).collect();
        let r = assemble_swept(&mx, &my, &path, &st, &tif, &Silent).unwrap();
        let col = r.removal_nm(&[0.0, 1.0, 0.0]).unwrap();
        let s2 = sigma * std::f64::consts::SQRT_2;
        for (i, (&x, &y)) in mx.iter().zip(&my).enumerate() {
            let exact = peak
                * (-y * y / (2.0 * sigma * sigma)).exp()
                * (std::f64::consts::PI / 2.0).sqrt()
                * sigma
                / seg
                * (erf((x + seg / 2.0) / s2) - erf((x - seg / 2.0) / s2));
            let got = col[i];
            assert!(
                (got - exact).abs() <= QUADRATURE_TOL * peak,
                "x {x} y {y}: swept {got} vs closed form {exact}"
            );
        }
        // The point model differs by far more than the tolerance at the centre (the sweep
        // lowers the peak): the test can tell the two apart.
        let point_peak = tif.rate_nm_per_s(0.0, 0.0);
        let i0 = 20;
        assert!((point_peak - col[i0]).abs() > 10.0 * QUADRATURE_TOL * peak);
    }

    #[test]
    fn stretches_follow_the_program_boundaries() {
        // Serpentine corner: (0,0) -> (1,0) -> (1,1). Point 1 owns (0.5,0)->(1,0)->(1,0.5).
        let path = DwellPath::new(vec![0.0, 1.0, 1.0], vec![0.0, 0.0, 1.0]).unwrap();
        let st = Stretches::of_path(&path, 0.1).unwrap();
        let s1 = st.of(1);
        assert_eq!(s1.len(), 10);
        let (mut lx, mut ly) = (0.0, 0.0);
        for s in s1 {
            assert!((s[2] - 0.1).abs() < 1e-12);
            lx += s[2] * s[0];
            ly += s[2] * s[1];
        }
        // Centroid of the L: half along -x (mean -0.25), half along +y (mean 0.25).
        assert!((lx + 0.125).abs() < 1e-12 && (ly - 0.125).abs() < 1e-12);
        // The ends are mirrored: point 0 owns (-0.5,0)..(0.5,0).
        let s0 = st.of(0);
        let c: f64 = s0.iter().map(|s| s[2] * s[0]).sum();
        assert!(c.abs() < 1e-12);
        // The farthest sample: the midpoint of the last 0.1 mm piece of a 0.5 mm half-stretch.
        assert!((st.reach_mm() - 0.45).abs() < 1e-12, "{}", st.reach_mm());
    }

    /// A serpentine raster along x over `[0, width] x [0, height]` mm at `pitch_mm`.
    fn raster(width_mm: f64, height_mm: f64, pitch_mm: f64) -> DwellPath {
        let bbox = crate::map::BoundingBox {
            x_min_mm: 0.0,
            x_max_mm: width_mm,
            y_min_mm: 0.0,
            y_max_mm: height_mm,
        };
        crate::path::raster::serpentine(&bbox, pitch_mm, crate::path::raster::RasterAxis::X)
            .unwrap()
    }

    /// Every point of a raster whose coordinates carry rounding (0.1 mm steps) gets its own
    /// stretch from the stored distinct ones: weights summing to 1, the centroid of its two
    /// blocks `(la a / 2 + lb b / 2) / (la + lb)` and samples within half a piece of both
    /// boundaries; the dominant stretch merges the rounding's variants and leaves out exactly the
    /// row ends.
    #[test]
    fn each_point_gets_its_own_stretch_from_the_distinct_ones() {
        const TOL_MM: f64 = 1e-12;
        let path = raster(2.0, 0.3, 0.1);
        let (x, y) = (path.x_mm(), path.y_mm());
        let n = x.len();
        assert_eq!(n, 84);
        let step = 0.013;
        let st = Stretches::of_path(&path, step).unwrap();
        assert_eq!(st.len(), n);
        assert!(
            st.kind_offsets.len() - 1 < n / 2,
            "{} distinct",
            st.kind_offsets.len() - 1
        );
        for j in 0..n {
            let toward = |k: usize| (0.5 * (x[k] - x[j]), 0.5 * (y[k] - y[j]));
            let b = if j + 1 < n {
                toward(j + 1)
            } else {
                (-toward(j - 1).0, -toward(j - 1).1)
            };
            let a = if j > 0 { toward(j - 1) } else { (-b.0, -b.1) };
            let (la, lb) = (a.0.hypot(a.1), b.0.hypot(b.1));
            let s = st.of(j);
            let w: f64 = s.iter().map(|p| p[2]).sum();
            assert!((w - 1.0).abs() <= TOL_MM, "point {j}: weights {w}");
            let cx: f64 = s.iter().map(|p| p[2] * p[0]).sum();
            let cy: f64 = s.iter().map(|p| p[2] * p[1]).sum();
            let (ex, ey) = (
                (la * a.0 + lb * b.0) / (2.0 * (la + lb)),
                (la * a.1 + lb * b.1) / (2.0 * (la + lb)),
            );
            assert!(
                (cx - ex).abs() <= TOL_MM && (cy - ey).abs() <= TOL_MM,
                "point {j}"
            );
            for end in [a, b] {
                let nearest = s
                    .iter()
                    .map(|p| (p[0] - end.0).hypot(p[1] - end.1))
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    nearest <= 0.5 * step + TOL_MM,
                    "point {j}: {nearest} mm from {end:?}"
                );
            }
        }
        // 4 lines of 21 points: each line's two ends are L-shaped but for the path's own ends,
        // which are mirrored straight along their line.
        let (_, count) = st.dominant();
        assert_eq!(count, n - 6);
        let outside = st.outside_dominant();
        assert_eq!(outside, vec![20, 21, 41, 42, 62, 63]);
    }

    #[test]
    fn the_dominant_stretch_is_the_raster_interior() {
        let path = raster(5.0, 2.0, 1.0);
        let st = Stretches::of_path(&path, 0.1).unwrap();
        let (samples, count) = st.dominant();
        // 3 lines of 6 points: 4 interior points each, and the path's two ends, whose stretch is
        // mirrored straight along their line.
        assert_eq!(count, 14);
        assert!(samples.iter().all(|s| s[1] == 0.0));
        let spread: f64 = samples.iter().map(|s| s[2] * s[0].abs()).sum();
        assert!((spread - 0.25).abs() < 1e-12);
    }
}
