//! Geometry benchmarks: XY-polynomial fitting and ICP registration, grouped by size.
//!
//! `cargo bench --bench geometry`. Targets: fit of 1e6 points at order 10 (65 terms) under 2 s;
//! registration of 1e5 points under 1 s.

#[path = "../tests/support/geometry_cases.rs"]
mod cases;

use cases::{design_points, grid, off_axis_freeform, order10_polynomial, Rng};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nalgebra::{Isometry3, Point3, Vector3};
use preston::solver::fit::{fit_xy_polynomial, ConicBase, FitSettings};
use preston::solver::registration::{register, RegisterSettings};
use preston::solver::surface::Surface;

fn fit(c: &mut Criterion) {
    let mut group = c.benchmark_group("fit_order10");
    group.sample_size(10);
    let poly = Surface::XyPolynomial(order10_polynomial(1.0 / 2000.0, -0.5, 100.0));
    for side in [100usize, 317, 1000] {
        let (x, y) = grid(side, side, (-70.0, 70.0), (-70.0, 70.0));
        let mut rng = Rng::new(7);
        let z: Vec<f64> = x
            .iter()
            .zip(&y)
            .map(|(a, b)| poly.sag_mm(*a, *b).unwrap() + 1e-6 * rng.normal())
            .collect();
        let settings = FitSettings {
            order: 10,
            norm_radius_mm: 100.0,
            base: ConicBase::Fixed {
                curvature_per_mm: 1.0 / 2000.0,
                conic: -0.5,
            },
            ..FitSettings::default()
        };
        group.throughput(Throughput::Elements(x.len() as u64));
        group.bench_with_input(BenchmarkId::from_parameter(x.len()), &(), |b, _| {
            b.iter(|| fit_xy_polynomial(&x, &y, &z, &settings).unwrap())
        });
    }
    group.finish();
}

fn registration(c: &mut Criterion) {
    let mut group = c.benchmark_group("register");
    group.sample_size(10);
    let surface = off_axis_freeform();
    // Installation error of 0.2 degree and 0.5 mm, normal form error of 100 nm RMS.
    let axis = Vector3::new(1.0, -2.0, 1.5).normalize();
    let truth = Isometry3::new(
        Vector3::new(0.3, -1.0, 0.6).normalize() * 0.5,
        axis * 0.2f64.to_radians(),
    );
    let inv = truth.inverse();
    for side in [100usize, 317] {
        let (design, normals) = design_points(&surface, side, side);
        let mut rng = Rng::new(11);
        let measured: Vec<[f64; 3]> = design
            .iter()
            .zip(&normals)
            .map(|(s, n)| {
                let e = 1e-4 * rng.normal();
                let q = inv * Point3::new(s[0] + e * n[0], s[1] + e * n[1], s[2] + e * n[2]);
                [q.x, q.y, q.z]
            })
            .collect();
        let settings = RegisterSettings::default();
        group.throughput(Throughput::Elements(measured.len() as u64));
        group.bench_with_input(BenchmarkId::from_parameter(measured.len()), &(), |b, _| {
            b.iter(|| register(&surface, &measured, &settings).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, fit, registration);
criterion_main!(benches);
