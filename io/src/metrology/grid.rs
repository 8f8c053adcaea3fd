//! Gridded height data (an interferometer's camera frame) and its conversion to points.

use super::RawPoints;

/// Heights on a square-pixel grid, row-major, first row at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    /// Columns.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// Pixel pitch, mm.
    pub pitch_mm: f64,
    /// Heights, nm, `ny * nx` row-major; NaN where the instrument has no data.
    pub z_nm: Vec<f64>,
    /// Notes on units and assumptions.
    pub notes: Vec<String>,
}

impl Grid {
    /// The valid pixels as points: pixel `(i, j)` at `x = (j - (nx - 1) / 2) p`,
    /// `y = ((ny - 1) / 2 - i) p`; NaN pixels dropped and counted.
    pub(crate) fn into_points(self) -> RawPoints {
        let valid = self.z_nm.iter().filter(|z| z.is_finite()).count();
        let mut x_mm = Vec::with_capacity(valid);
        let mut y_mm = Vec::with_capacity(valid);
        let mut z_nm = Vec::with_capacity(valid);
        let (cx, cy) = (0.5 * (self.nx as f64 - 1.0), 0.5 * (self.ny as f64 - 1.0));
        for (i, row) in self.z_nm.chunks_exact(self.nx.max(1)).enumerate() {
            let y = (cy - i as f64) * self.pitch_mm;
            for (j, &z) in row.iter().enumerate() {
                if z.is_finite() {
                    x_mm.push((j as f64 - cx) * self.pitch_mm);
                    y_mm.push(y);
                    z_nm.push(z);
                }
            }
        }
        RawPoints {
            x_mm,
            y_mm,
            z_nm,
            invalid: self.z_nm.len() - valid,
            pitch_mm: Some(self.pitch_mm),
            notes: self.notes,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_are_centred_with_row_zero_on_top() {
        let g = Grid {
            nx: 3,
            ny: 2,
            pitch_mm: 0.5,
            z_nm: vec![1.0, f64::NAN, 3.0, 4.0, 5.0, 6.0],
            notes: vec![],
        };
        let p = g.into_points();
        assert_eq!(p.invalid, 1);
        assert_eq!(p.x_mm, vec![-0.5, 0.5, -0.5, 0.0, 0.5]);
        assert_eq!(p.y_mm, vec![0.25, 0.25, -0.25, -0.25, -0.25]);
        assert_eq!(p.z_nm, vec![1.0, 3.0, 4.0, 5.0, 6.0]);
    }
}
