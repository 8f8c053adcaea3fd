//! Gridded height data (an interferometer's camera frame) and its conversion to points.

use super::RawPoints;

/// `f64` arrays of a grid's size held at once while it is read and made points: the values
/// read, the heights, and the points' x and y.
pub(crate) const GRID_ARRAYS: f64 = 4.0;

/// Checks a grid of `ny x nx` pixels, as a file's header or dataset declares it, against the
/// memory budget ([`preston_solver::budget`]) before its values are read: [`GRID_ARRAYS`] `f64`
/// arrays of `ny * nx`. The error names the grid's size and the limit.
pub(crate) fn check_grid_budget(ny: u64, nx: u64) -> preston_solver::Result<()> {
    preston_solver::budget::check_f64s(
        "grid size",
        &format!("a grid of {ny} x {nx} pixels ({GRID_ARRAYS} arrays of f64)"),
        ny as f64 * nx as f64,
        GRID_ARRAYS,
    )
}

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

    /// A 30000 x 30000 dataset, as a few-kilobyte chunked `.datx` can declare, needs
    /// 30000^2 x 4 arrays x 8 bytes = 28.8 GB: over any limit the budget allows (at most
    /// 8 GiB), refused with its size; a camera frame of 1000 x 1000 (32 MB) passes.
    #[test]
    fn a_declared_grid_over_the_memory_budget_is_refused() {
        let e = check_grid_budget(30000, 30000).unwrap_err().to_string();
        assert!(
            e.contains("30000 x 30000") && e.contains("28.800 GB"),
            "{e}"
        );
        assert!(check_grid_budget(1000, 1000).is_ok());
    }
}
