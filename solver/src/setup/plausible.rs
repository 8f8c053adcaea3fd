//! Whether the inputs' sizes can be what the user meant, checked before the solve.
//!
//! Units go wrong silently: a TIF whose coordinates are in metres (or pixels) under an `x_mm`
//! header, heights in um under `z_nm`, a dwell path that misses the map. Each leaves a problem
//! that solves to a plan nobody wants. What cannot be meant at all is refused
//! ([`no_dwell_point_reaches_the_map`]); what is only implausible is a warning
//! ([`size_warnings`]), given before a solve that may run for minutes.

use crate::map::HeightMap;
use crate::tif::{InfluenceFunction, Tif};

/// Share of the dwell points that reach no map point above which a warning is given.
pub const UNREACHABLE_SHARE_WARNING: f64 = 0.5;

/// Estimated dwell, s, above which the total removal is called implausible for the TIF's rate
/// (about eleven days of polishing).
pub const IMPLAUSIBLE_DWELL_S: f64 = 1e6;

/// Peak-to-valley below which a height map is called implausibly flat, nm (below the noise of
/// interferometric metrology: heights in um under a `z_nm` header read 1000-fold too small).
pub const IMPLAUSIBLE_PV_NM: f64 = 0.5;

/// Grid points per radius over which the TIF's volume rate is summed.
const VOLUME_STEPS: i32 = 40;

/// The message refusing a problem in which no dwell point's tool footprint holds a map point:
/// `R` is zero, and no dwell time changes the part. `None` where some dwell point reaches it.
pub fn no_dwell_point_reaches_the_map(
    empty_columns: usize,
    dwell_points: usize,
    tif: &Tif,
) -> Option<String> {
    (dwell_points > 0 && empty_columns >= dwell_points).then(|| {
        format!(
            "none of the {dwell_points} dwell points has a map point within the TIF's reach \
             ({:.4} mm): R is zero and no dwell time changes the part; check that the dwell path \
             lies over the map and that the TIF's coordinates are in mm",
            tif.support_radius_mm()
        )
    })
}

/// The warning for a large share of dwell points that reach no map point, if the share is
/// above [`UNREACHABLE_SHARE_WARNING`].
pub fn unreachable_share_warning(empty_columns: usize, dwell_points: usize) -> Option<String> {
    let share = empty_columns as f64 / dwell_points.max(1) as f64;
    (share > UNREACHABLE_SHARE_WARNING).then(|| {
        format!(
            "{empty_columns} of {dwell_points} dwell points ({:.0}%) have no map point in the \
             tool's reach: does the dwell path lie over the map?",
            100.0 * share
        )
    })
}

/// The TIF's volume removal rate `V = integral of TIF dA`, nm mm^2 / s (midpoint rule on a
/// square grid of [`VOLUME_STEPS`] cells per support radius).
pub fn volume_rate_nm_mm2_per_s(tif: &Tif) -> f64 {
    let r = tif.support_radius_mm();
    if !(r.is_finite() && r > 0.0) {
        return 0.0;
    }
    let h = r / VOLUME_STEPS as f64;
    let mut sum = 0.0;
    for i in -VOLUME_STEPS..VOLUME_STEPS {
        for j in -VOLUME_STEPS..VOLUME_STEPS {
            sum += tif.rate_nm_per_s((i as f64 + 0.5) * h, (j as f64 + 0.5) * h);
        }
    }
    sum * h * h
}

/// The map's point spacing, mm, against which a TIF's footprint is judged: the smaller of the
/// typical spacing over its bounding box (`sqrt(area / points)`, exact for a full rectangular
/// grid, larger for a round aperture) and the pitch of the lattice its points lie on (the
/// smallest step between distinct coordinates; small for scattered points, so that they are
/// never judged on it). `None` for a map with no area.
pub fn map_spacing_mm(map: &HeightMap) -> Option<f64> {
    let b = map.bounding_box_mm()?;
    let area = ((b.x_max_mm - b.x_min_mm) * (b.y_max_mm - b.y_min_mm)).max(0.0);
    if !(area > 0.0) {
        return None;
    }
    let typical = (area / map.len().max(1) as f64).sqrt();
    let lattice =
        crate::influence::FftOperator::lattice_pitch_mm(map.x_mm(), map.y_mm()).unwrap_or(typical);
    Some(typical.min(lattice))
}

/// The refusal of a TIF whose support radius is below half the map's point spacing
/// ([`map_spacing_mm`]): its footprint fits between map points, so each dwell point feels at
/// most the map point it sits on, and whatever a few such points reach, the plan is not the
/// tool's. A measured TIF in metres under an `x_mm` header is the usual cause (a 10 mm TIF
/// reads 10 um across). `None` where the footprint spans the spacing.
pub fn tif_narrower_than_the_map_spacing(map: &HeightMap, tif: &Tif) -> Option<String> {
    let spacing = map_spacing_mm(map)?;
    let r = tif.support_radius_mm();
    (r < 0.5 * spacing).then(|| {
        format!(
            "the TIF is narrower than the map's point spacing: its support radius ({r:.3e} mm) \
             is below half the spacing ({spacing:.4} mm), so its footprint fits between map \
             points and no dwell point can shape the surface; are the TIF's coordinates in mm? \
             A TIF written in metres under an x_mm header reads 1000 times too small (a {:.3} \
             mm footprint if they are m)",
            2.0e3 * r
        )
    })
}

/// Warnings on sizes that are implausible together: the TIF against the map's extent, the map's
/// height range, and the total removal against the TIF's volume rate. (A TIF narrower than the
/// map's spacing is refused: [`tif_narrower_than_the_map_spacing`].)
pub fn size_warnings(map: &HeightMap, tif: &Tif) -> Vec<String> {
    let mut out = Vec::new();
    let Some(b) = map.bounding_box_mm() else {
        return out;
    };
    let m = map.len().max(1) as f64;
    let (w, h) = (b.x_max_mm - b.x_min_mm, b.y_max_mm - b.y_min_mm);
    let area = (w * h).max(0.0);
    let extent = w.max(h);
    if extent > 0.0 && tif.nominal_radius_mm() > extent {
        out.push(format!(
            "the TIF's radius ({:.3} mm) exceeds the map's whole extent ({extent:.3} mm); are the \
             TIF's coordinates in mm (not pixels or um)?",
            tif.nominal_radius_mm()
        ));
    }
    let z = map.z_nm();
    let (lo, hi) = z
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, u), &v| {
            (l.min(v), u.max(v))
        });
    let pv = hi - lo;
    if map.len() > 1 && pv.is_finite() && pv < IMPLAUSIBLE_PV_NM {
        out.push(format!(
            "the map's peak-to-valley is {pv:.3e} nm, below what metrology resolves; are the \
             heights in nm (not um)?"
        ));
    }
    let rate = volume_rate_nm_mm2_per_s(tif);
    if rate > 0.0 && area > 0.0 && pv.is_finite() {
        // Removing down to the lowest point: the material above it over the map's area.
        let volume: f64 = z.iter().map(|&v| v - lo).sum::<f64>() * area / m;
        let dwell = volume / rate;
        if dwell > IMPLAUSIBLE_DWELL_S {
            out.push(format!(
                "removing this map takes about {dwell:.2e} s of dwell at the TIF's volume rate \
                 ({rate:.3e} nm mm^2/s): are the map's heights in nm and the TIF's rates in nm/s?"
            ));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tif::GaussianTif;

    fn gaussian(sigma: f64, peak: f64) -> Tif {
        Tif::Gaussian(GaussianTif::new(sigma, peak, 3.0 * sigma).unwrap())
    }

    fn grid_map(n: usize, pitch: f64, z: impl Fn(f64, f64) -> f64) -> HeightMap {
        let (mut xs, mut ys, mut zs) = (vec![], vec![], vec![]);
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (i as f64 * pitch, j as f64 * pitch);
                xs.push(x);
                ys.push(y);
                zs.push(z(x, y));
            }
        }
        HeightMap::new(xs, ys, zs).unwrap()
    }

    /// The volume rate of a Gaussian truncated at 3 sigma: `2 pi sigma^2 A (1 - e^{-9/2})`.
    #[test]
    fn volume_rate_matches_the_gaussian_closed_form() {
        let (sigma, peak) = (1.5, 20.0);
        let exact = 2.0 * std::f64::consts::PI * sigma * sigma * peak * (1.0 - (-4.5f64).exp());
        let got = volume_rate_nm_mm2_per_s(&gaussian(sigma, peak));
        assert!((got - exact).abs() < 1e-3 * exact, "{got} vs {exact}");
    }

    #[test]
    fn plausible_sizes_give_no_warning() {
        let map = grid_map(41, 0.5, |x, y| 20.0 * (x / 5.0).sin() + 0.5 * y);
        assert!(size_warnings(&map, &gaussian(1.0, 50.0)).is_empty());
    }

    #[test]
    fn each_implausible_size_is_named() {
        let map = grid_map(41, 0.5, |x, y| 20.0 * (x / 5.0).sin() + 0.5 * y);
        // TIF in pixels: wider than the whole map.
        let w = size_warnings(&map, &gaussian(100.0, 50.0));
        assert!(w.iter().any(|s| s.contains("extent")), "{w:?}");
        // Heights in um under z_nm.
        let flat = grid_map(41, 0.5, |x, _| 0.02 * (x / 5.0).sin());
        let w = size_warnings(&flat, &gaussian(1.0, 50.0));
        assert!(w.iter().any(|s| s.contains("peak-to-valley")), "{w:?}");
        // Heights in pm (or a rate in nm/min): a year of dwell.
        let deep = grid_map(41, 0.5, |x, _| 1e7 * (1.0 + (x / 5.0).sin()));
        let w = size_warnings(&deep, &gaussian(1.0, 1.0));
        assert!(w.iter().any(|s| s.contains("of dwell")), "{w:?}");
    }

    /// A 10 mm TIF (sigma 1.5 mm, support 4.5 mm) read as metres is 1000 times smaller: its
    /// 4.5 um support radius against a 0.5 mm pitch is refused, the message suggesting the
    /// unit; the same TIF in mm, and one whose support radius is just over half the pitch,
    /// pass. On a round aperture the pitch, not the coarser box spacing, is the measure.
    #[test]
    fn a_tif_narrower_than_the_map_spacing_is_refused() {
        let map = grid_map(41, 0.5, |x, y| 20.0 * (x / 5.0).sin() + 0.5 * y);
        let why = tif_narrower_than_the_map_spacing(&map, &gaussian(1.5e-3, 50.0))
            .expect("a TIF in metres is refused");
        assert!(why.contains("in mm") && why.contains("metres"), "{why}");
        assert!(tif_narrower_than_the_map_spacing(&map, &gaussian(1.5, 50.0)).is_none());
        // Support radius 3 sigma: 0.26 mm passes, 0.24 mm is refused (half the pitch: 0.25).
        assert!(tif_narrower_than_the_map_spacing(&map, &gaussian(0.26 / 3.0, 50.0)).is_none());
        assert!(tif_narrower_than_the_map_spacing(&map, &gaussian(0.24 / 3.0, 50.0)).is_some());
        let (mut xs, mut ys, mut zs) = (vec![], vec![], vec![]);
        for i in -20..=20 {
            for j in -20..=20 {
                let (x, y) = (i as f64 * 0.5, j as f64 * 0.5);
                if x * x + y * y <= 100.0 {
                    xs.push(x);
                    ys.push(y);
                    zs.push(x);
                }
            }
        }
        let round = HeightMap::new(xs, ys, zs).unwrap();
        let spacing = map_spacing_mm(&round).unwrap();
        assert!((spacing - 0.5).abs() < SPACING_TOL_MM, "{spacing}");
        assert!(tif_narrower_than_the_map_spacing(&round, &gaussian(0.26 / 3.0, 50.0)).is_none());
    }

    /// Agreement of a lattice's spacing with its pitch, mm.
    const SPACING_TOL_MM: f64 = 1e-12;

    #[test]
    fn refusal_only_when_no_dwell_point_reaches() {
        let tif = gaussian(1.0, 1.0);
        assert!(no_dwell_point_reaches_the_map(10, 10, &tif).is_some());
        assert!(no_dwell_point_reaches_the_map(9, 10, &tif).is_none());
        assert!(unreachable_share_warning(6, 10).is_some());
        assert!(unreachable_share_warning(5, 10).is_none());
    }
}
