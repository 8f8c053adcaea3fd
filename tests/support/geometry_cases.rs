//! Shared test and benchmark cases for the geometry code: an off-axis freeform mirror, a
//! deterministic random generator and transforms with known answers.
#![allow(dead_code)]

use preston::solver::surface::{monomials, Surface, XyPolynomial, XyTerm};

/// Deterministic uniform and Gaussian numbers (the engine's splitmix64 + Box-Muller).
pub use preston::solver::iterate::SplitMix64 as Rng;

/// Aperture of the off-axis mirror: x in [-160, 160] mm, y in [280, 400] mm (320 x 120 mm).
pub const X_RANGE_MM: (f64, f64) = (-160.0, 160.0);
/// See [`X_RANGE_MM`].
pub const Y_RANGE_MM: (f64, f64) = (280.0, 400.0);

/// An off-axis freeform: concave near-paraboloid of vertex radius 3000 mm (26 to 62 mm of sag over
/// the aperture) with non-symmetric XY terms (normalised at 400 mm), so all 6 rigid-body
/// degrees of freedom are observable.
pub fn off_axis_freeform() -> Surface {
    let terms = vec![
        XyTerm {
            m: 2,
            n: 1,
            coef_mm: 0.5,
        },
        XyTerm {
            m: 3,
            n: 0,
            coef_mm: 0.2,
        },
        XyTerm {
            m: 1,
            n: 2,
            coef_mm: -0.3,
        },
        XyTerm {
            m: 0,
            n: 3,
            coef_mm: 0.1,
        },
        XyTerm {
            m: 4,
            n: 0,
            coef_mm: 0.05,
        },
        XyTerm {
            m: 2,
            n: 2,
            coef_mm: -0.08,
        },
        XyTerm {
            m: 1,
            n: 1,
            coef_mm: 0.4,
        },
    ];
    Surface::XyPolynomial(XyPolynomial {
        curvature_per_mm: 1.0 / 3000.0,
        conic: -0.9,
        norm_radius_mm: 400.0,
        terms,
    })
}

/// A full order-10 XY polynomial with known coefficients (for fit recovery).
pub fn order10_polynomial(c: f64, k: f64, norm_radius_mm: f64) -> XyPolynomial {
    XyPolynomial {
        curvature_per_mm: c,
        conic: k,
        norm_radius_mm,
        terms: monomials(10)
            .into_iter()
            .enumerate()
            .map(|(j, (m, n))| XyTerm {
                m,
                n,
                coef_mm: 1e-2 * ((j as f64 + 1.0) * 1.37).sin() / (1.0 + (m + n) as f64),
            })
            .collect(),
    }
}

/// `nx x ny` grid over the rectangle, row-major.
pub fn grid(nx: usize, ny: usize, xr: (f64, f64), yr: (f64, f64)) -> (Vec<f64>, Vec<f64>) {
    let mut x = Vec::with_capacity(nx * ny);
    let mut y = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            x.push(xr.0 + (xr.1 - xr.0) * i as f64 / (nx - 1) as f64);
            y.push(yr.0 + (yr.1 - yr.0) * j as f64 / (ny - 1) as f64);
        }
    }
    (x, y)
}

/// Points of the surface on an `nx x ny` grid over the off-axis aperture, with their normals.
pub fn design_points(surface: &Surface, nx: usize, ny: usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let (x, y) = grid(nx, ny, X_RANGE_MM, Y_RANGE_MM);
    let mut p = Vec::with_capacity(x.len());
    let mut n = Vec::with_capacity(x.len());
    for (&xi, &yi) in x.iter().zip(&y) {
        let d = surface.derivs(xi, yi).unwrap();
        p.push([xi, yi, d.z]);
        n.push(d.normal());
    }
    (p, n)
}
