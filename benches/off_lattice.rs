//! The off-lattice operators on the simulated 210 x 30 mm mirror: map 580 x 81 points at 0.36 mm
//! (46,980), dwell raster 440 x 79 at 0.5 mm (34,760), off the map lattice.
//!
//! `cargo bench --bench off_lattice` prints, for each TIF and oversampling factor `s`, the
//! spreading operator's estimated relative error (sampled columns), the relative error of `R~ t`
//! against the assembled `R t` for a random `t`, and the time of one `R^T R t` by each operator;
//! then the same for the exact phase-stencil operator (18 x 18 phases). With
//! `PRESTON_MIRROR_DIR=dir` it also writes `dir/map.csv` and `dir/dwell.csv` for timing
//! `preston solve` on the same case (docs/off_lattice.md).

use preston::solver::influence::{
    InfluenceMatrix, LinearOperator, SparseOperator, SpreadOperator, StencilOperator,
};
use preston::solver::observer::Silent;
use preston::solver::tif::{GaussianTif, Tif};
use std::io::Write;
use std::path::Path;
use std::time::Instant;

/// The mirror's height error, nm, at `(x, y)` mm: low-order figure plus mid-spatial ripple.
fn mirror_z_nm(x: f64, y: f64) -> f64 {
    use std::f64::consts::PI;
    20.0 * (2.0 * PI * x / 70.0).cos() * (2.0 * PI * y / 40.0).cos()
        + 8.0 * (2.0 * PI * (x + 0.5 * y) / 23.0).sin()
        + 3.0 * (2.0 * PI * x / 9.0 + 1.0).cos() * (2.0 * PI * y / 11.0).sin()
        + 15.0 * (x / 104.0).powi(2)
}

type Points = (Vec<f64>, Vec<f64>);

/// Map (580 x 81 at 0.36 mm) and serpentine dwell raster (440 x 79 at 0.5 mm).
fn mirror() -> (Points, Vec<f64>, Points) {
    let (mut mx, mut my, mut mz) = (vec![], vec![], vec![]);
    for j in 0..81 {
        for i in 0..580 {
            let (x, y) = (-104.22 + 0.36 * i as f64, -14.4 + 0.36 * j as f64);
            mx.push(x);
            my.push(y);
            mz.push(mirror_z_nm(x, y));
        }
    }
    let (mut dx, mut dy) = (vec![], vec![]);
    for j in 0..79 {
        for k in 0..440 {
            let i = if j % 2 == 0 { k } else { 439 - k };
            dx.push(-109.75 + 0.5 * i as f64);
            dy.push(-19.5 + 0.5 * j as f64);
        }
    }
    ((mx, my), mz, (dx, dy))
}

fn write_csvs(dir: &Path, map: &Points, z: &[f64], dwell: &Points) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("map.csv"))?);
    writeln!(f, "x_mm,y_mm,z_nm")?;
    for ((x, y), z) in map.0.iter().zip(&map.1).zip(z) {
        writeln!(f, "{x:.4},{y:.4},{z:.6}")?;
    }
    let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("dwell.csv"))?);
    writeln!(f, "x_mm,y_mm")?;
    for (x, y) in dwell.0.iter().zip(&dwell.1) {
        writeln!(f, "{x:.4},{y:.4}")?;
    }
    Ok(())
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|a| a * a).sum::<f64>().sqrt()
}

/// Seconds per `R^T R t`, best of `reps`.
fn time_normal(op: &dyn LinearOperator, t: &[f64], reps: usize) -> f64 {
    let mut scratch = vec![0.0; op.nrows()];
    let mut out = vec![0.0; op.ncols()];
    (0..reps)
        .map(|_| {
            let s = Instant::now();
            op.apply_normal(t, &mut scratch, &mut out);
            s.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() {
    let (map, z, dwell) = mirror();
    if let Some(dir) = std::env::var_os("PRESTON_MIRROR_DIR") {
        let dir = Path::new(&dir);
        if let Err(e) = write_csvs(dir, &map, &z, &dwell) {
            eprintln!("cannot write {}: {e}", dir.display());
        }
    }
    let jet = preston::io::readers::read_tif(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("data/tif_fluid_jet_10mm.csv"),
    )
    .map(Tif::Grid);
    let mut tifs = vec![
        (
            "Gaussian sigma 1.7 mm, cut at 3 sigma",
            Tif::Gaussian(GaussianTif::new(1.7, 20.0, 5.1).unwrap()),
        ),
        (
            "Gaussian sigma 1.7 mm, cut at 4.5 sigma",
            Tif::Gaussian(GaussianTif::new(1.7, 20.0, 7.65).unwrap()),
        ),
    ];
    if let Ok(j) = jet {
        tifs.push(("fluid jet 10 mm (grid, data/)", j));
    }
    let t: Vec<f64> = (0..dwell.0.len())
        .map(|j| 0.5 + ((j * 7919) % 101) as f64 / 101.0)
        .collect();
    let mut stencils = Vec::new();
    println!("| TIF | s | fine pitch mm | estimated error | ||R~t - Rt|| / ||Rt|| | R^T R t spread ms | R^T R t sparse ms |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for (name, tif) in &tifs {
        let exact =
            InfluenceMatrix::assemble(&map.0, &map.1, &dwell.0, &dwell.1, tif, &Silent).unwrap();
        let sparse = SparseOperator::new(exact.csc());
        let mut rt = vec![0.0; sparse.nrows()];
        sparse.apply(&t, &mut rt);
        let sparse_ms = 1e3 * time_normal(&sparse, &t, 5);
        let stencil = StencilOperator::new(&map.0, &map.1, &dwell.0, &dwell.1, 0.36, tif).unwrap();
        let mut exact_rt = vec![0.0; stencil.nrows()];
        stencil.apply(&t, &mut exact_rt);
        let diff: Vec<f64> = exact_rt.iter().zip(&rt).map(|(a, b)| a - b).collect();
        stencils.push(format!(
            "| {name} | {} | {:.2e} | {:.2} | {sparse_ms:.2} |",
            stencil.phase_class_count(),
            norm(&diff) / norm(&rt),
            1e3 * time_normal(&stencil, &t, 5)
        ));
        for s in 1..=4 {
            let op = SpreadOperator::new(&map.0, &map.1, &dwell.0, &dwell.1, 0.36, s, tif).unwrap();
            let mut approx = vec![0.0; op.nrows()];
            op.apply(&t, &mut approx);
            let diff: Vec<f64> = approx.iter().zip(&rt).map(|(a, b)| a - b).collect();
            println!(
                "| {name} | {s} | {:.3} | {:.2e} | {:.2e} | {:.2} | {:.2} |",
                op.fine_pitch_mm(),
                op.estimated_error(),
                norm(&diff) / norm(&rt),
                1e3 * time_normal(&op, &t, 5),
                sparse_ms
            );
        }
    }
    println!();
    println!("| TIF | phase stencils | ||R t (stencil) - R t|| / ||R t|| | R^T R t stencil ms | R^T R t sparse ms |");
    println!("| --- | --- | --- | --- | --- |");
    for row in &stencils {
        println!("{row}");
    }
}
