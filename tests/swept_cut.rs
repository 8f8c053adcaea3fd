//! The swept columns of a TIF cut where its rate is not zero (a truncated Gaussian), against the
//! closed form of the truncated Gaussian integrated along a straight stretch, and a plan with no
//! time weight against the closed-form removal of its own dwell.

use preston::solver::dwell::{self, DwellBounds, FeedLimits, Settings, SolverChoice};
use preston::solver::influence::{assemble_swept, Stretches};
use preston::solver::observer::Silent;
use preston::solver::path::raster::{serpentine, RasterAxis};
use preston::solver::path::DwellPath;
use preston::solver::tif::{GaussianTif, InfluenceFunction};

/// Largest error of a swept column entry, relative to the peak rate: the midpoint rule's smooth
/// error at 1/64 of the support radius is `h^2 / 24 |TIF''|`, below 7e-5 of the peak for this
/// Gaussian; a piece crossed by the cut circle integrated by its midpoint alone is off by up to
/// `h / ds` times the rate at the cut, 1.5e-3 of the peak here.
const ENTRY_TOL: f64 = 2e-4;

/// `erf` by its Maclaurin series (arguments below 2 here: within 1e-15).
fn erf(x: f64) -> f64 {
    let mut term = x;
    let mut sum = x;
    for n in 1..400 {
        term *= -x * x / n as f64;
        let add = term / (2 * n + 1) as f64;
        sum += add;
        if add.abs() < 1e-18 {
            break;
        }
    }
    2.0 / std::f64::consts::PI.sqrt() * sum
}

/// The removal rate at `(px, py)` per second of dwell of `tif` swept at constant feed along the
/// straight segments `blocks` (`[(x0, y0), (x1, y1)]`) of total length `ds`: the truncated
/// Gaussian integrated in closed form over the part of each segment within its cut.
fn closed_form(tif: &GaussianTif, blocks: &[[(f64, f64); 2]], px: f64, py: f64) -> f64 {
    let ds: f64 = blocks
        .iter()
        .map(|[a, b]| (b.0 - a.0).hypot(b.1 - a.1))
        .sum();
    let (sigma, cut) = (tif.sigma_mm, tif.support_radius_mm());
    let s2 = sigma * std::f64::consts::SQRT_2;
    let mut total = 0.0;
    for [a, b] in blocks {
        let len = (b.0 - a.0).hypot(b.1 - a.1);
        if len == 0.0 {
            continue;
        }
        let (ux, uy) = ((b.0 - a.0) / len, (b.1 - a.1) / len);
        // The map point in the segment's frame: `along` from a, `d` across.
        let along = (px - a.0) * ux + (py - a.1) * uy;
        let d = (px - a.0) * uy - (py - a.1) * ux;
        if d.abs() >= cut {
            continue;
        }
        let half_chord = (cut * cut - d * d).sqrt();
        // Arc length s along the segment within the cut: |s - along| <= half_chord.
        let (lo, hi) = ((along - half_chord).max(0.0), (along + half_chord).min(len));
        if hi <= lo {
            continue;
        }
        total += tif.peak_rate_nm_per_s
            * (-d * d / (2.0 * sigma * sigma)).exp()
            * (std::f64::consts::PI / 2.0).sqrt()
            * sigma
            * (erf((hi - along) / s2) - erf((lo - along) / s2));
    }
    total / ds
}

/// The segments of dwell point `j`'s stretch: from the midpoint with the point before to the
/// point, and on to the midpoint with the point after (the path's ends mirrored).
fn stretch_blocks(path: &DwellPath, j: usize) -> Vec<[(f64, f64); 2]> {
    let (x, y) = (path.x_mm(), path.y_mm());
    let n = x.len();
    let p = (x[j], y[j]);
    let half = |k: usize| (0.5 * (x[k] + p.0), 0.5 * (y[k] + p.1));
    let (a, b) = match (j > 0, j + 1 < n) {
        (true, true) => (half(j - 1), half(j + 1)),
        (true, false) => {
            let a = half(j - 1);
            (a, (2.0 * p.0 - a.0, 2.0 * p.1 - a.1))
        }
        (false, true) => {
            let b = half(j + 1);
            ((2.0 * p.0 - b.0, 2.0 * p.1 - b.1), b)
        }
        (false, false) => (p, p),
    };
    vec![[a, p], [p, b]]
}

fn tif() -> GaussianTif {
    GaussianTif::new(0.417, 10.0, 1.05).unwrap()
}

/// Map points whose cut disc crosses a 0.46 mm stretch anywhere along it, from deep inside to
/// grazing: every swept entry within [`ENTRY_TOL`] of the closed form.
#[test]
fn swept_columns_integrate_the_cut_exactly() {
    let tif = tif();
    let path = DwellPath::new(vec![-0.46, 0.0, 0.46], vec![0.0; 3]).unwrap();
    let stretches = Stretches::of_path(&path, tif.support_radius_mm() / 64.0).unwrap();
    let (mut mx, mut my) = (Vec::new(), Vec::new());
    for d in [0.0, 0.5, 0.9, 1.0, 1.03, 1.045, 1.049] {
        for i in 0..=200 {
            mx.push(-1.4 + 0.014 * i as f64);
            my.push(d);
        }
    }
    let r = assemble_swept(&mx, &my, &path, &stretches, &tif, &Silent).unwrap();
    let col = r.removal_nm(&[0.0, 1.0, 0.0]).unwrap();
    let blocks = stretch_blocks(&path, 1);
    let peak = tif.peak_rate_nm_per_s;
    let mut worst = 0.0f64;
    for (i, (&x, &y)) in mx.iter().zip(&my).enumerate() {
        let exact = closed_form(&tif, &blocks, x, y);
        let e = (col[i] - exact).abs() / peak;
        if e > 1e-4 {
            eprintln!("x {x} y {y}: {} vs {exact}: {e:e}", col[i]);
        }
        worst = worst.max(e);
    }
    assert!(
        worst <= ENTRY_TOL,
        "worst entry off by {worst:e} of the peak rate"
    );
}

/// A 21 x 18 map at 0.4 mm, the Gaussian cut at 1.05 mm, a 0.46 mm raster reaching the cut past
/// the map and no time weight (more dwell points than map points): the plan's residual, and the
/// residual of the same dwell integrated in closed form along every stretch, agree to within
/// the map's RMS times the entries' tolerance, and the plan holds its dwell to what the map needs
/// rather than a piston of many microns.
#[test]
fn a_plan_without_time_weight_is_its_own_closed_form_removal() {
    let tif = tif();
    let (mut mx, mut my, mut mz) = (Vec::new(), Vec::new(), Vec::new());
    for iy in 0..18 {
        for ix in 0..21 {
            let (x, y) = (0.4 * ix as f64, 0.4 * iy as f64);
            let (u, v) = ((x - 4.0) / 8.0, (y - 3.4) / 6.8);
            let bump = 60.0 * (-((x - 5.0).powi(2) + (y - 3.0).powi(2)) / (2.0 * 0.64)).exp();
            mx.push(x);
            my.push(y);
            mz.push(30.0 * u * u + 20.0 * u * v - 25.0 * v * v + 10.0 * u + bump);
        }
    }
    // Scaled to 70 nm RMS about its mean.
    let mean = mz.iter().sum::<f64>() / mz.len() as f64;
    let rms0 = (mz.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / mz.len() as f64).sqrt();
    mz.iter_mut().for_each(|z| *z = (*z - mean) * 70.0 / rms0);
    let bbox = preston::solver::map::BoundingBox::of_points(&mx, &my)
        .unwrap()
        .expanded(tif.truncation_radius_mm);
    let path = serpentine(&bbox, 0.46, RasterAxis::X).unwrap();
    assert!(path.len() > mx.len());
    let stretches = Stretches::of_path(&path, tif.support_radius_mm() / 64.0).unwrap();
    let r = assemble_swept(&mx, &my, &path, &stretches, &tif, &Silent).unwrap();
    let limits = FeedLimits {
        v_max_mm_per_min: 3000.0,
        v_min_mm_per_min: 0.0,
    };
    let bounds = DwellBounds::from_feeds(&path.ds_mm(), &limits).unwrap();
    let problem = dwell::Problem::new(r, mz.clone(), bounds, 0.0, 0.0).unwrap();
    let settings = Settings {
        solver: SolverChoice::Qp,
        ..Settings::default()
    };
    let s = dwell::solve(&problem, &settings, &Silent).unwrap();
    let model = problem.removal_nm(&s.dwell_s).unwrap();
    let exact: Vec<f64> = (0..mx.len())
        .map(|i| {
            (0..path.len())
                .filter(|&j| s.dwell_s[j] != 0.0)
                .map(|j| {
                    let blocks = stretch_blocks(&path, j);
                    s.dwell_s[j] * closed_form(&tif, &blocks, mx[i], my[i])
                })
                .sum()
        })
        .collect();
    let rms = |h: &[f64]| {
        let d: Vec<f64> = h.iter().zip(&mz).map(|(h, z)| z - h).collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt()
    };
    let zero = vec![0.0; mz.len()];
    let (before, planned, integrated) = (rms(&zero), rms(&model), rms(&exact));
    let total: f64 = s.dwell_s.iter().sum();
    eprintln!("RMS {before} -> planned {planned}, integrated {integrated}; dwell {total} s");
    assert!(
        (integrated - planned).abs() <= ENTRY_TOL * before,
        "planned {planned} nm, its dwell integrated in closed form {integrated} nm (map {before} nm)"
    );
}
