//! Engine benchmarks: influence-matrix assembly throughput and the sample job end to end.
//!
//! `cargo bench --bench engine` (criterion). Assembly throughput is reported in non-zeros per
//! second ("elements"); `fft_products` times one first-order iteration's products (`R t` and
//! `R^T y`, and `R^T R t` in one pass) with the matrix-free FFT operator on the generated `preston bench` problems;
//! `sample_job_phases` times the shipped sample job (`data/job.toml`) phase by phase.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use preston::io::job::Job;
use preston::io::pipeline;
use preston::solver::influence::InfluenceMatrix;
use preston::solver::observer::Silent;
use preston::solver::path::raster::{serpentine, RasterAxis};
use preston::solver::tif::{GaussianTif, InfluenceFunction, Tif};
use std::path::Path;

/// A `side x side` mm map at 0.5 mm pitch and a 1 mm dwell raster over it.
fn grid_case(side_mm: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>) {
    let n = (side_mm / 0.5) as usize + 1;
    let (mut x, mut y) = (Vec::with_capacity(n * n), Vec::with_capacity(n * n));
    for iy in 0..n {
        for ix in 0..n {
            x.push(ix as f64 * 0.5);
            y.push(iy as f64 * 0.5);
        }
    }
    let bbox = preston::solver::map::BoundingBox::of_points(&x, &y).unwrap();
    let path = serpentine(&bbox, 1.0, RasterAxis::X).unwrap();
    (x, y, path.x_mm().to_vec(), path.y_mm().to_vec())
}

fn assembly(c: &mut Criterion) {
    let mut group = c.benchmark_group("assembly");
    group.sample_size(10);
    let gaussian = Tif::Gaussian(GaussianTif::new(2.0, 10.0, 6.0).unwrap());
    let measured = Tif::Grid(
        preston::io::readers::read_tif(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("data/tif_fluid_jet_10mm.csv"),
        )
        .unwrap(),
    );
    for side in [100.0, 200.0] {
        let (x, y, dx, dy) = grid_case(side);
        for (name, tif) in [("gaussian", &gaussian), ("measured", &measured)] {
            let nnz = InfluenceMatrix::assemble(&x, &y, &dx, &dy, tif, &Silent)
                .unwrap()
                .nnz();
            group.throughput(Throughput::Elements(nnz as u64));
            group.bench_with_input(
                BenchmarkId::new(name, format!("{}map_{}dwell", x.len(), dx.len())),
                &(),
                |b, _| {
                    b.iter(|| InfluenceMatrix::assemble(&x, &y, &dx, &dy, tif, &Silent).unwrap())
                },
            );
            let _ = tif.support_radius_mm();
        }
    }
    group.finish();
}

fn sample_job(c: &mut Criterion) {
    let mut group = c.benchmark_group("sample_job");
    group.sample_size(10);
    let job_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/job_point_1mm.toml");
    let job = Job::load(&job_path).unwrap();
    // Assembly alone, on the sample job's map, dwell raster and measured TIF.
    let prepared = pipeline::prepare(&job, &job_path, &Silent).unwrap();
    let (map, path) = (prepared.map(), prepared.path());
    group.throughput(Throughput::Elements(prepared.problem.nnz() as u64));
    group.bench_function("assembly", |b| {
        b.iter(|| {
            InfluenceMatrix::assemble(
                map.x_mm(),
                map.y_mm(),
                path.x_mm(),
                path.y_mm(),
                prepared.tif(),
                &Silent,
            )
            .unwrap()
        })
    });
    group.bench_function("prepare (read + assemble)", |b| {
        b.iter(|| pipeline::prepare(&job, &job_path, &Silent).unwrap())
    });
    group.bench_function("prepare + solve", |b| {
        b.iter(|| {
            let p = pipeline::prepare(&job, &job_path, &Silent).unwrap();
            pipeline::solve(p, &job, &Silent).unwrap()
        })
    });
    group.finish();
}

/// The shipped sample job (`data/job.toml`: the 0.32 mm raster on the map's lattice, the swept
/// model, correction passes against the program executed at the acceleration limit) phase by
/// phase, in a group named by its size: reading the inputs and building the operator, the whole
/// solve (the L-BFGS, the executed runs and correction passes, the sensitivity), one executed run
/// of the solve's program (the contact motion's removal on the map), and the sensitivity of that
/// run under the five TIF scenarios.
fn sample_job_phases(c: &mut Criterion) {
    use preston::solver::machine::gcode::motion::Kinematics;
    let job_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/job.toml");
    let job = Job::load(&job_path).unwrap();
    let prepared = pipeline::prepare(&job, &job_path, &Silent).unwrap();
    let (setup, problem) = (&prepared.setup, &prepared.problem);
    let mut group = c.benchmark_group(format!(
        "sample_job_phases/{}map_{}dwell",
        problem.m(),
        problem.n()
    ));
    group.sample_size(10);
    group.bench_function("prepare", |b| {
        b.iter(|| pipeline::prepare(&job, &job_path, &Silent).unwrap())
    });
    group.bench_function("solve", |b| {
        b.iter(|| setup.solve(problem, &Silent).unwrap())
    });
    let outcome = setup.solve(problem, &Silent).unwrap();
    let executed = outcome.executed.as_ref().unwrap().as_ref().unwrap();
    let kinematics = Kinematics::Trapezoidal {
        a_max_mm_per_s2: executed.a_max_mm_per_s2,
        corner_angle_deg: executed.settings.corner_angle_deg,
    };
    group.bench_function("executed_run", |b| {
        b.iter(|| {
            setup
                .run_program(&executed.program.program, kinematics, None, None, &Silent)
                .unwrap()
        })
    });
    group.bench_function("sensitivity", |b| {
        b.iter(|| {
            setup
                .sensitivity_of(&executed.run.contact, &executed.run.removal_nm, &Silent)
                .unwrap()
        })
    });
    group.finish();
}

fn fft_products(c: &mut Criterion) {
    use preston::solver::influence::operator::fft::FftOperator;
    use preston::solver::influence::operator::LinearOperator;
    let mut group = c.benchmark_group("fft_products");
    group.sample_size(10);
    for n_target in [20_000, 200_000, 1_000_000] {
        let g = preston::io::bench::generated_inputs(n_target, 1).unwrap();
        let op =
            FftOperator::new(&g.x_mm, &g.y_mm, g.path.x_mm(), g.path.y_mm(), 0.5, &g.tif).unwrap();
        let (m, n) = (op.nrows(), op.ncols());
        let t: Vec<f64> = (0..n).map(|j| 1.0 + (j % 7) as f64 * 0.1).collect();
        let (mut rt, mut rtr) = (vec![0.0; m], vec![0.0; n]);
        group.bench_with_input(
            BenchmarkId::new("rt_and_rtr", format!("{m}map_{n}dwell")),
            &(),
            |b, _| {
                b.iter(|| {
                    op.apply(&t, &mut rt);
                    op.apply_transpose(&rt, &mut rtr);
                })
            },
        );
        group.bench_with_input(
            BenchmarkId::new("normal", format!("{m}map_{n}dwell")),
            &(),
            |b, _| b.iter(|| op.apply_normal(&t, &mut rt, &mut rtr)),
        );
    }
    group.finish();
}

criterion_group!(
    benches,
    assembly,
    sample_job,
    sample_job_phases,
    fft_products
);
criterion_main!(benches);
