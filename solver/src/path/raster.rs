//! Serpentine (boustrophedon) raster paths over a rectangle.

use super::DwellPath;
use crate::error::{Error, Result};
use crate::map::BoundingBox;
use serde::{Deserialize, Serialize};

/// The direction of the raster lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum RasterAxis {
    /// Lines run along x and step in y.
    #[default]
    X,
    /// Lines run along y and step in x.
    Y,
}

/// A serpentine raster at `pitch_mm` (both along and across lines) that covers `region`.
///
/// The grid starts at the region's lower corner and has `floor(width / pitch) + 1` points per
/// side (so it stops within one pitch of the far edges). Line `k` runs forward for even `k` and
/// backward for odd `k`.
pub fn serpentine(region: &BoundingBox, pitch_mm: f64, along: RasterAxis) -> Result<DwellPath> {
    if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
        return Err(Error::invalid(
            "raster pitch_mm",
            format!("must be positive, got {pitch_mm}"),
        ));
    }
    let axis = |lo: f64, hi: f64| -> Result<(f64, usize)> {
        let width = hi - lo;
        if !(width.is_finite() && width >= 0.0) {
            return Err(Error::invalid(
                "raster region",
                format!("bad extent [{lo}, {hi}] mm"),
            ));
        }
        let steps = (width / pitch_mm + 1e-9).floor().max(0.0);
        if steps > 1e7 {
            return Err(Error::invalid(
                "raster pitch_mm",
                format!("{pitch_mm} mm gives more than 1e7 points across {width} mm"),
            ));
        }
        let count = steps as usize + 1;
        Ok((lo, count))
    };
    let (x0, nx) = axis(region.x_min_mm, region.x_max_mm)?;
    let (y0, ny) = axis(region.y_min_mm, region.y_max_mm)?;
    let (n_lines, n_along) = match along {
        RasterAxis::X => (ny, nx),
        RasterAxis::Y => (nx, ny),
    };
    let total = n_lines
        .checked_mul(n_along)
        .filter(|&t| t <= 100_000_000)
        .ok_or_else(|| Error::invalid("raster", "more than 1e8 points"))?;
    let mut xs = Vec::with_capacity(total);
    let mut ys = Vec::with_capacity(total);
    for line in 0..n_lines {
        for k in 0..n_along {
            let a = if line % 2 == 0 { k } else { n_along - 1 - k };
            let (ix, iy) = match along {
                RasterAxis::X => (a, line),
                RasterAxis::Y => (line, a),
            };
            xs.push(x0 + ix as f64 * pitch_mm);
            ys.push(y0 + iy as f64 * pitch_mm);
        }
    }
    DwellPath::new(xs, ys)
}

/// Where a generated raster sits against the map's lattice: its first node and, where the map
/// lies on a regular lattice, that lattice's pitch and the raster's phase on it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RasterPlacement {
    /// Line spacing and point spacing, mm.
    pub pitch_mm: f64,
    /// The raster's lower corner (its first line's first or last node), mm.
    pub origin_mm: [f64; 2],
    /// The pitch of the map's lattice, mm (`None`: the map points are not on one).
    pub map_lattice_pitch_mm: Option<f64>,
    /// The origin's offset from the nearest map lattice node below it, in map cells, each in
    /// `[0, 1)`: zero where the raster was placed on the lattice.
    pub phase_cells: Option<[f64; 2]>,
}

/// `region` with its lower corner moved down onto the lattice of pitch `pitch_mm` through
/// `origin_mm` (the nearest node at or below it, to a millionth of a cell), so that a raster
/// from that corner at a pitch that is a multiple of the lattice's has every node on the lattice
/// (the FFT operator serves it) and at a rational multiple `p / q` takes `q` phases per axis
/// (the phase stencils serve it); the region only grows, so the raster still covers it.
pub fn snapped_to_lattice(region: &BoundingBox, pitch_mm: f64, origin_mm: [f64; 2]) -> BoundingBox {
    let down = |v: f64, o: f64| o + ((v - o) / pitch_mm + 1e-6).floor() * pitch_mm;
    BoundingBox {
        x_min_mm: down(region.x_min_mm, origin_mm[0]),
        y_min_mm: down(region.y_min_mm, origin_mm[1]),
        ..*region
    }
}

/// The phase, in cells of pitch `pitch_mm` through `origin_mm`, of the point `at_mm`: each
/// coordinate's offset from the nearest node at or below it, in `[0, 1)` (a millionth of a cell
/// counts as on the node).
pub fn lattice_phase_cells(at_mm: [f64; 2], pitch_mm: f64, origin_mm: [f64; 2]) -> [f64; 2] {
    let phase = |v: f64, o: f64| {
        let u = (v - o) / pitch_mm;
        let f = u - (u + 1e-6).floor();
        if f.abs() <= 1e-6 {
            0.0
        } else {
            f
        }
    };
    [phase(at_mm[0], origin_mm[0]), phase(at_mm[1], origin_mm[1])]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn serpentine_covers_and_alternates() {
        let region = BoundingBox {
            x_min_mm: 0.0,
            x_max_mm: 2.5,
            y_min_mm: -1.0,
            y_max_mm: 1.0,
        };
        let p = serpentine(&region, 1.0, RasterAxis::X).unwrap();
        // 3 points across 2.5 mm (0, 1, 2), 3 lines.
        assert_eq!(p.len(), 9);
        assert_eq!(&p.x_mm()[..3], &[0.0, 1.0, 2.0]);
        assert_eq!(&p.x_mm()[3..6], &[2.0, 1.0, 0.0]);
        assert_eq!(p.y_mm()[0], -1.0);
        assert_eq!(p.y_mm()[8], 1.0);
        // Every step is one pitch long.
        let ds = p.ds_mm();
        assert!(ds.iter().all(|&d| (d - 1.0).abs() < 1e-12));
        let py = serpentine(&region, 1.0, RasterAxis::Y).unwrap();
        assert_eq!(py.len(), 9);
        assert_eq!(py.x_mm()[0], py.x_mm()[2]);
    }

    /// A raster from the snapped corner: at twice the lattice pitch every node is a lattice
    /// node (phase zero), at 1.5 times it the nodes take two phases per axis (0 and 0.5 of a
    /// cell), and it still covers the region (its first nodes at or below the region's corner,
    /// its last within one pitch of the far edges).
    #[test]
    fn a_snapped_raster_sits_on_the_lattice_phases() {
        const ON: f64 = 1e-9;
        let (h, origin) = (0.32, [0.0, 0.0]);
        let region = BoundingBox {
            x_min_mm: -5.019373,
            x_max_mm: 123.0,
            y_min_mm: -5.019373,
            y_max_mm: 13.0,
        };
        let snapped = snapped_to_lattice(&region, h, origin);
        assert!((snapped.x_min_mm + 16.0 * h).abs() <= ON, "{snapped:?}");
        assert!((snapped.y_min_mm + 16.0 * h).abs() <= ON);
        assert_eq!(
            (snapped.x_max_mm, snapped.y_max_mm),
            (region.x_max_mm, region.y_max_mm)
        );
        // A corner already on a node stays there (to a millionth of a cell).
        let on_node = snapped_to_lattice(&snapped, h, origin);
        assert!((on_node.x_min_mm - snapped.x_min_mm).abs() <= ON);
        let phases = |pitch: f64| {
            let p = serpentine(&snapped, pitch, RasterAxis::X).unwrap();
            let mut seen: Vec<[i64; 2]> = p
                .x_mm()
                .iter()
                .zip(p.y_mm())
                .map(|(&x, &y)| {
                    let f = lattice_phase_cells([x, y], h, origin);
                    [(f[0] * 1e6).round() as i64, (f[1] * 1e6).round() as i64]
                })
                .collect();
            seen.sort_unstable();
            seen.dedup();
            let (xs, ys) = (p.x_mm(), p.y_mm());
            let x_last = xs.iter().copied().fold(f64::MIN, f64::max);
            let y_last = ys.iter().copied().fold(f64::MIN, f64::max);
            assert!(x_last > region.x_max_mm - pitch && y_last > region.y_max_mm - pitch);
            seen
        };
        assert_eq!(phases(2.0 * h), vec![[0, 0]]);
        assert_eq!(
            phases(1.5 * h),
            vec![[0, 0], [0, 500_000], [500_000, 0], [500_000, 500_000]]
        );
        // The unsnapped corner's phase, and a lattice through another origin.
        let f = lattice_phase_cells([region.x_min_mm, region.y_min_mm], h, origin);
        assert!((f[0] - (16.0 - 5.019373 / h)).abs() <= ON, "{f:?}");
        assert_eq!(lattice_phase_cells([1.1, 0.9], 0.2, [0.1, 0.1]), [0.0, 0.0]);
    }
}
