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
}
