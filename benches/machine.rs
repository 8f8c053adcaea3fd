//! Machine benchmarks: the acceleration-limited dwell solve by size (squared speed, and the
//! SCP-QP reference where it is small enough), and NC planning and G-code writing for 1e5 points.
//!
//! `cargo bench --bench machine` (criterion).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use preston::solver::dwell::accel::{self, AccelLimits, AccelMethod};
use preston::solver::dwell::{self, DwellBounds, FeedLimits, Problem, Settings};
use preston::solver::influence::InfluenceMatrix;
use preston::solver::kinematics::lines::max_acceleration_mm_per_s2;
use preston::solver::machine::gcode::dialect::Dialect;
use preston::solver::machine::gcode::motion::{execute, Kinematics};
use preston::solver::machine::gcode::program::Program;
use preston::solver::machine::nc::{NcProgram, NcSettings, ToolAxis};
use preston::solver::map::BoundingBox;
use preston::solver::observer::Silent;
use preston::solver::path::raster::{serpentine, RasterAxis};
use preston::solver::path::DwellPath;
use preston::solver::surface::{Conic, Surface};
use preston::solver::tif::GaussianTif;

/// A `width x height` mm map at 0.5 mm pitch with a Gaussian trench across x = width/2 on a
/// 50 nm base, a 1 mm serpentine dwell raster over it and a Gaussian TIF (sigma 1 mm).
fn trench_case(width_mm: f64, height_mm: f64) -> (Problem, DwellPath) {
    let (nx, ny) = (
        (width_mm / 0.5) as usize + 1,
        (height_mm / 0.5) as usize + 1,
    );
    let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
    for iy in 0..ny {
        for ix in 0..nx {
            let (px, py) = (ix as f64 * 0.5, iy as f64 * 0.5);
            x.push(px);
            y.push(py);
            z.push(50.0 + 400.0 * (-(px - 0.5 * width_mm).powi(2) / 2.0).exp());
        }
    }
    let path = if height_mm == 0.0 {
        let n = (width_mm / 0.5) as usize + 1;
        DwellPath::new((0..n).map(|j| j as f64 * 0.5).collect(), vec![0.0; n]).unwrap()
    } else {
        let bbox = BoundingBox::of_points(&x, &y).unwrap();
        serpentine(&bbox, 1.0, RasterAxis::X).unwrap()
    };
    let tif = GaussianTif::new(1.0, 100.0, 3.0).unwrap();
    let r = InfluenceMatrix::assemble(&x, &y, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
    let lim = FeedLimits {
        v_max_mm_per_min: 600.0,
        v_min_mm_per_min: 6.0,
    };
    let b = DwellBounds::from_feeds(&path.ds_mm(), &lim).unwrap();
    (Problem::new(r, z, b, 0.0, 0.0).unwrap(), path)
}

/// The acceleration-limited solve at a fifth of the feed-limited optimum's acceleration, by size:
/// the squared-speed method on every case, the SCP-QP reference on the two small ones.
fn accel_limit(c: &mut Criterion) {
    let mut group = c.benchmark_group("accel_limit");
    group.sample_size(10);
    let settings = Settings::default();
    for (name, w, h) in [
        ("small_line", 20.0, 0.0),
        ("medium_raster", 40.0, 10.0),
        ("large_raster", 80.0, 40.0),
    ] {
        let (problem, path) = trench_case(w, h);
        let free = dwell::solve(&problem, &settings, &Silent).unwrap();
        let a_free = max_acceleration_mm_per_s2(&path, &free.dwell_s, 60.0);
        let methods: &[AccelMethod] = if problem.n() <= 500 {
            &[AccelMethod::SquaredSpeed, AccelMethod::ScpQp]
        } else {
            &[AccelMethod::SquaredSpeed]
        };
        for &method in methods {
            let limits = AccelLimits {
                method,
                ..AccelLimits::new(0.2 * a_free)
            };
            let out = accel::solve(&problem, &path, &limits, &settings, &Silent).unwrap();
            eprintln!(
                "{name} {method:?}: m {} n {}, a_max {:.1} mm/s^2, {} SCP iterations, {} gradient \
                 steps, status {:?}, RMS {:.3} -> {:.3} nm",
                problem.m(),
                problem.n(),
                limits.a_max_mm_per_s2,
                out.report.scp_iterations,
                out.report.gradient_steps,
                out.report.status,
                out.report.rms_after_reference_nm,
                out.report.rms_after_nm
            );
            group.bench_with_input(
                BenchmarkId::new(
                    format!("{name}_{method:?}"),
                    format!("{}map_{}dwell", problem.m(), problem.n()),
                ),
                &(),
                |b, _| {
                    b.iter(|| accel::solve(&problem, &path, &limits, &settings, &Silent).unwrap())
                },
            );
        }
    }
    group.finish();
}

fn nc_planning(c: &mut Criterion) {
    let mut group = c.benchmark_group("nc");
    group.sample_size(10);
    // 1e5 points: a 0.2 mm serpentine over 63.2 x 63.2 mm on a sphere R = 500 mm.
    let bbox = BoundingBox::of_points(&[-31.6, 31.6], &[-31.6, 31.6]).unwrap();
    let path = serpentine(&bbox, 0.2, RasterAxis::X).unwrap();
    let n = path.len();
    let dwell_s: Vec<f64> = (0..n)
        .map(|j| 0.01 * (1.5 + (j as f64 * 0.01).sin()))
        .collect();
    let sphere = Surface::Conic(Conic {
        curvature_per_mm: 1.0 / 500.0,
        conic: 0.0,
    });
    let settings = NcSettings {
        tool_radius_mm: 5.0,
        tool_axis: ToolAxis::Normal,
        a_max_mm_per_s2: Some(500.0),
        ..NcSettings::default()
    };
    group.throughput(Throughput::Elements(n as u64));
    group.bench_with_input(BenchmarkId::new("plan", n), &(), |b, _| {
        b.iter(|| NcProgram::plan(&path, &dwell_s, &sphere, &settings).unwrap())
    });
    let program = NcProgram::plan(&path, &dwell_s, &sphere, &settings).unwrap();
    let mut buf = Vec::with_capacity(64 * n);
    group.bench_with_input(BenchmarkId::new("write_gcode", n), &(), |b, _| {
        b.iter(|| {
            buf.clear();
            program.write_gcode(&mut buf).unwrap();
            buf.len()
        })
    });
    // Read the program back and execute it with the acceleration limit (what `nc` and
    // `simulate --program` do before integrating the removal).
    let text = String::from_utf8(buf.clone()).unwrap();
    group.bench_with_input(BenchmarkId::new("read_back_execute", n), &(), |b, _| {
        b.iter(|| {
            let p = Program::parse(&text, Dialect::Iso).unwrap();
            let e = execute(
                &p,
                Kinematics::Trapezoidal {
                    a_max_mm_per_s2: 500.0,
                    corner_angle_deg: 60.0,
                },
            )
            .unwrap();
            e.total_time_s
        })
    });
    group.finish();
}

criterion_group!(benches, accel_limit, nc_planning);
criterion_main!(benches);
