//! `preston surface`: evaluate a surface (sag, normal, principal curvatures) on a grid or at
//! given points.

use anyhow::{bail, Context};
use preston_io::surface::{read_surface, stage_columns_csv};
use preston_io::table::{read_table, ColumnSpec};
use std::path::PathBuf;

/// Arguments of `preston surface`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Surface JSON.
    #[arg(long, value_name = "S.json")]
    pub surface: PathBuf,
    /// Evaluate at the points of this CSV (`x_mm,y_mm`) instead of a grid.
    #[arg(long, value_name = "XY.csv", conflicts_with_all = ["x_min_mm", "x_max_mm", "y_min_mm", "y_max_mm", "step_mm"])]
    pub points: Option<PathBuf>,
    /// Grid: smallest x, mm.
    #[arg(long, allow_negative_numbers = true)]
    pub x_min_mm: Option<f64>,
    /// Grid: largest x, mm.
    #[arg(long, allow_negative_numbers = true)]
    pub x_max_mm: Option<f64>,
    /// Grid: smallest y, mm.
    #[arg(long, allow_negative_numbers = true)]
    pub y_min_mm: Option<f64>,
    /// Grid: largest y, mm.
    #[arg(long, allow_negative_numbers = true)]
    pub y_max_mm: Option<f64>,
    /// Grid pitch, mm.
    #[arg(long)]
    pub step_mm: Option<f64>,
    /// Output CSV `x_mm,y_mm,z_mm,nx,ny,nz,k1_per_mm,k2_per_mm`.
    #[arg(long, value_name = "OUT.csv")]
    pub out: PathBuf,
}

/// Largest grid accepted (points).
const MAX_GRID_POINTS: f64 = 1e8;

/// Runs `preston surface`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let surface = read_surface(&args.surface)?;
    let (x, y) = match &args.points {
        Some(p) => {
            let mut t = read_table(
                p,
                &[ColumnSpec::required("x_mm"), ColumnSpec::required("y_mm")],
            )?;
            (t.take(0).unwrap_or_default(), t.take(1).unwrap_or_default())
        }
        None => {
            let (Some(x0), Some(x1), Some(y0), Some(y1), Some(h)) = (
                args.x_min_mm,
                args.x_max_mm,
                args.y_min_mm,
                args.y_max_mm,
                args.step_mm,
            ) else {
                bail!("give --points, or all of --x-min-mm --x-max-mm --y-min-mm --y-max-mm --step-mm");
            };
            if !(h.is_finite() && h > 0.0) {
                bail!("--step-mm must be positive, got {h}");
            }
            if !(x1 >= x0
                && y1 >= y0
                && x0.is_finite()
                && x1.is_finite()
                && y0.is_finite()
                && y1.is_finite())
            {
                bail!("the grid needs finite limits with min <= max");
            }
            let nx = ((x1 - x0) / h + 1e-9).floor() + 1.0;
            let ny = ((y1 - y0) / h + 1e-9).floor() + 1.0;
            if nx * ny > MAX_GRID_POINTS {
                bail!(
                    "the grid would have {:.3e} points (limit {MAX_GRID_POINTS:e})",
                    nx * ny
                );
            }
            let mut x = Vec::new();
            let mut y = Vec::new();
            for j in 0..ny as usize {
                for i in 0..nx as usize {
                    x.push(x0 + i as f64 * h);
                    y.push(y0 + j as f64 * h);
                }
            }
            (x, y)
        }
    };
    let n = x.len();
    let mut cols: Vec<Vec<f64>> = (0..6).map(|_| Vec::with_capacity(n)).collect();
    for (&xi, &yi) in x.iter().zip(&y) {
        let d = surface
            .derivs(xi, yi)
            .with_context(|| format!("evaluating the surface at ({xi}, {yi}) mm"))?;
        let nrm = d.normal();
        let (k1, k2) = d.principal_curvatures();
        for (c, v) in cols.iter_mut().zip([d.z, nrm[0], nrm[1], nrm[2], k1, k2]) {
            c.push(v);
        }
    }
    stage_columns_csv(
        &args.out,
        &[
            "x_mm",
            "y_mm",
            "z_mm",
            "nx",
            "ny",
            "nz",
            "k1_per_mm",
            "k2_per_mm",
        ],
        &[
            &x, &y, &cols[0], &cols[1], &cols[2], &cols[3], &cols[4], &cols[5],
        ],
    )?
    .commit()?;
    crate::errln!("preston surface: {n} points; wrote {}", args.out.display());
    Ok(crate::EXIT_OK)
}
