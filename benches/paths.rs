//! Tool-path generation and curvature-dependent influence assembly.
//!
//! `cargo bench --bench paths` (criterion). Targets: paths of 1e6 points in under
//! 1 s; per-dwell-point curvature TIFs assembled at least at half the speed of the
//! shift-invariant case.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use preston::solver::influence::model::curvature::assemble_curvature_dependent;
use preston::solver::influence::InfluenceMatrix;
use preston::solver::influence::{assemble_on_surface, TifFrame};
use preston::solver::map::BoundingBox;
use preston::solver::observer::Silent;
use preston::solver::path::intersection::{intersection, lines_to_path, raster_lines};
use preston::solver::path::raster::RasterAxis;
use preston::solver::path::spiral::archimedes;
use preston::solver::path::{arcs::lines_with_arcs, project};
use preston::solver::surface::{Conic, Surface};
use preston::solver::tif::{HertzParams, HertzTif};

fn paths(c: &mut Criterion) {
    let mut group = c.benchmark_group("paths_1e6");
    group.sample_size(10);
    // 1001 x 1001 = 1.002e6 points.
    let region = BoundingBox {
        x_min_mm: 0.0,
        x_max_mm: 1000.0,
        y_min_mm: 0.0,
        y_max_mm: 1000.0,
    };
    group.throughput(Throughput::Elements(1_002_001));
    group.bench_function("raster", |b| {
        b.iter(|| {
            let lines = raster_lines(&region, 1.0, RasterAxis::X, 0.0).unwrap();
            lines_to_path(&lines, 1.0).unwrap()
        })
    });
    group.bench_function("intersection_k3", |b| {
        b.iter(|| intersection(&region, 1.0, 3).unwrap())
    });
    group.bench_function("raster_arcs", |b| {
        b.iter(|| {
            let lines = raster_lines(&region, 1.0, RasterAxis::X, 0.0).unwrap();
            lines_with_arcs(&lines, 1.0, 0.5, 1e-3).unwrap()
        })
    });
    // pi R^2 / (P step) = 1e6 at P = step = 1 mm: R = 564.19 mm.
    let r = (1e6 / std::f64::consts::PI).sqrt();
    group.bench_function("spiral", |b| {
        b.iter(|| archimedes([0.0, 0.0], r, 1.0, 1.0).unwrap())
    });
    let sphere = Surface::Conic(Conic {
        curvature_per_mm: -1.0 / 2000.0,
        conic: 0.0,
    });
    let spiral = archimedes([0.0, 0.0], r, 1.0, 1.0).unwrap();
    group.bench_function("spiral_projected_on_sphere", |b| {
        b.iter(|| project(&spiral, Some(&sphere)).unwrap())
    });
    group.finish();
}

fn curvature_assembly(c: &mut Criterion) {
    let mut group = c.benchmark_group("curvature_assembly");
    group.sample_size(10);
    // 100 x 100 mm map at 0.5 mm (40,401 points), dwell raster at 1 mm (10,201 points) on a
    // convex ellipsoid whose curvature varies over the part.
    let n = 201;
    let (mut mx, mut my) = (Vec::new(), Vec::new());
    for iy in 0..n {
        for ix in 0..n {
            mx.push(ix as f64 * 0.5 - 50.0);
            my.push(iy as f64 * 0.5 - 50.0);
        }
    }
    let region = BoundingBox::of_points(&mx, &my).unwrap();
    let path = intersection(&region, 1.0, 0).unwrap();
    let (dx, dy) = (path.x_mm().to_vec(), path.y_mm().to_vec());
    let surface = Surface::Conic(Conic {
        curvature_per_mm: -1.0 / 150.0,
        conic: -0.5,
    });
    let params = HertzParams {
        preston_k_mm2_per_n: 1e-6,
        ..HertzParams::default()
    };
    let centre = HertzTif::with_curvatures(&params, -1.0 / 150.0, -1.0 / 150.0).unwrap();
    let nnz = assemble_curvature_dependent(
        &surface,
        &mx,
        &my,
        &dx,
        &dy,
        &params,
        TifFrame::MachineX,
        &Silent,
    )
    .unwrap()
    .nnz();
    group.throughput(Throughput::Elements(nnz as u64));
    group.bench_function("shift_invariant_plan", |b| {
        b.iter(|| InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &centre, &Silent).unwrap())
    });
    group.bench_function("shift_invariant_on_surface", |b| {
        b.iter(|| {
            assemble_on_surface(
                &surface,
                &mx,
                &my,
                &dx,
                &dy,
                &centre,
                TifFrame::MachineX,
                &Silent,
            )
            .unwrap()
        })
    });
    group.bench_function("curvature_dependent_on_surface", |b| {
        b.iter(|| {
            assemble_curvature_dependent(
                &surface,
                &mx,
                &my,
                &dx,
                &dy,
                &params,
                TifFrame::MachineX,
                &Silent,
            )
            .unwrap()
        })
    });
    group.finish();
}

criterion_group!(benches, paths, curvature_assembly);
criterion_main!(benches);
