//! Modal descriptions of a height map: Zernike polynomials (Noll and Fringe orderings) and
//! Legendre products, fitted by least squares over the map's points; form-term removal.
//!
//! Zernike functions are orthonormal over the unit disk (Noll, "Zernike polynomials and
//! atmospheric turbulence", JOSA 66, 1976):
//! `Z_j(rho, theta) = sqrt(n + 1) R_n^0(rho)` for `m = 0`, and
//! `sqrt(2 (n + 1)) R_n^|m|(rho) cos(|m| theta)` (`j` even) or `... sin(|m| theta)` (`j` odd),
//! with `R_n^m(rho) = sum_{s=0}^{(n-m)/2} (-1)^s (n - s)! / (s! ((n+m)/2 - s)! ((n-m)/2 - s)!)
//! rho^(n - 2s)`, so `(1/pi) int_disk Z_j Z_k = delta_jk`. The Fringe (University of Arizona)
//! ordering lists the same functions by `(n + |m|) / 2`, then decreasing `|m|`, cos before sin;
//! coefficients are in the same orthonormal units in both orderings.
//!
//! Legendre products `L_k(u, v) = sqrt((2i + 1)(2j + 1)) P_i(u) P_j(v)` with `u = x / R`,
//! `v = y / R` are orthonormal for the mean over the square `[-1, 1]^2`; they are ordered by total
//! degree `i + j`, then decreasing `i`.

use crate::error::{Error, Result};
use crate::lstsq::{tsqr, Reduced};
use serde::{Deserialize, Serialize};

/// The polynomial family of a modal fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Basis {
    /// Zernike, Noll's ordering (`Z1` piston, `Z2`/`Z3` tilt x/y, `Z4` power, `Z11` spherical).
    ZernikeNoll,
    /// Zernike, Fringe ordering (`Z1` piston, `Z2`/`Z3` tilt, `Z4` power, `Z9` spherical).
    ZernikeFringe,
    /// Products of Legendre polynomials over the square `[-R, R]^2`.
    Legendre,
}

/// `(n, m)` of Noll's index `j >= 1`; `m < 0` is the sine term.
pub fn noll_to_nm(j: usize) -> (usize, i64) {
    let j = j.max(1);
    let mut n = 0usize;
    while (n + 1) * (n + 2) / 2 < j {
        n += 1;
    }
    let p = j - n * (n + 1) / 2 - 1;
    let m = if n.is_multiple_of(2) {
        2 * p.div_ceil(2)
    } else {
        2 * (p / 2) + 1
    } as i64;
    if m == 0 {
        (n, 0)
    } else if j.is_multiple_of(2) {
        (n, m)
    } else {
        (n, -m)
    }
}

/// `(n, m)` of Fringe index `j >= 1`; `m < 0` is the sine term.
pub fn fringe_to_nm(j: usize) -> (usize, i64) {
    let j = j.max(1);
    let mut k = 0usize;
    while (k + 1) * (k + 1) < j {
        k += 1;
    }
    let p = j - k * k - 1;
    if p == 2 * k {
        return (2 * k, 0);
    }
    let am = k - p / 2;
    let n = 2 * k - am;
    if p.is_multiple_of(2) {
        (n, am as i64)
    } else {
        (n, -(am as i64))
    }
}

/// The radial polynomial `R_n^m(rho)` (`m >= 0`, `n - m` even).
pub fn zernike_radial(n: usize, m: usize, rho: f64) -> f64 {
    if m > n || (n - m) % 2 == 1 {
        return 0.0;
    }
    let fact = |k: usize| (1..=k).fold(1.0f64, |a, b| a * b as f64);
    let mut sum = 0.0;
    for s in 0..=(n - m) / 2 {
        let c = fact(n - s) / (fact(s) * fact((n + m) / 2 - s) * fact((n - m) / 2 - s));
        let sign = if s % 2 == 0 { 1.0 } else { -1.0 };
        sum += sign * c * rho.powi((n - 2 * s) as i32);
    }
    sum
}

/// The orthonormal Zernike function of order `(n, m)` at polar `(rho, theta)`.
pub fn zernike_nm(n: usize, m: i64, rho: f64, theta: f64) -> f64 {
    let am = m.unsigned_abs() as usize;
    let r = zernike_radial(n, am, rho);
    if m == 0 {
        ((n + 1) as f64).sqrt() * r
    } else if m > 0 {
        (2.0 * (n + 1) as f64).sqrt() * r * (am as f64 * theta).cos()
    } else {
        (2.0 * (n + 1) as f64).sqrt() * r * (am as f64 * theta).sin()
    }
}

/// Legendre polynomial `P_k(t)` by Bonnet's recurrence `(k+1) P_{k+1} = (2k+1) t P_k - k P_{k-1}`.
pub fn legendre(k: usize, t: f64) -> f64 {
    let (mut p0, mut p1) = (1.0, t);
    if k == 0 {
        return p0;
    }
    for i in 1..k {
        let p2 = ((2 * i + 1) as f64 * t * p1 - i as f64 * p0) / (i + 1) as f64;
        p0 = p1;
        p1 = p2;
    }
    p1
}

/// Degrees `(i, j)` of Legendre term `k` (0-based): by total degree, then decreasing `i`.
pub fn legendre_degrees(k: usize) -> (usize, usize) {
    let mut d = 0;
    let mut start = 0;
    while start + d < k {
        start += d + 1;
        d += 1;
    }
    let off = k - start;
    (d - off, off)
}

impl Basis {
    /// Value of term `k` (1-based index in the basis's ordering) at `(x, y)` scaled by the
    /// normalisation radius (`u = x / R`, `v = y / R`).
    pub fn eval(self, k: usize, u: f64, v: f64) -> f64 {
        match self {
            Basis::ZernikeNoll | Basis::ZernikeFringe => {
                let (n, m) = if self == Basis::ZernikeNoll {
                    noll_to_nm(k)
                } else {
                    fringe_to_nm(k)
                };
                zernike_nm(n, m, u.hypot(v), v.atan2(u))
            }
            Basis::Legendre => {
                let (i, j) = legendre_degrees(k.saturating_sub(1));
                (((2 * i + 1) * (2 * j + 1)) as f64).sqrt() * legendre(i, u) * legendre(j, v)
            }
        }
    }
}

/// A least-squares modal fit of heights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModalFit {
    /// The basis.
    pub basis: Basis,
    /// Normalisation radius, mm.
    pub norm_radius_mm: f64,
    /// Coefficients, nm, of terms `1..=N` in the basis's ordering.
    pub coefficients_nm: Vec<f64>,
    /// Heights minus the fitted sum, nm (same order as the points).
    pub residual_nm: Vec<f64>,
}

/// Largest acceptable condition number of the column-scaled fit.
const MAX_CONDITION: f64 = 1e12;

/// Fits `z ~ sum_k c_k B_k(x / R, y / R)` over the points by least squares (TSQR, then the SVD
/// of the triangular factor), for the given term indices (1-based in the basis's ordering).
pub fn fit_terms(
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    basis: Basis,
    terms: &[usize],
    norm_radius_mm: f64,
) -> Result<(Vec<f64>, Vec<f64>)> {
    if !(norm_radius_mm > 0.0 && norm_radius_mm.is_finite()) {
        return Err(Error::invalid(
            "norm_radius_mm",
            format!("{norm_radius_mm} must be positive and finite"),
        ));
    }
    if x_mm.len() != z_nm.len() || y_mm.len() != z_nm.len() {
        return Err(Error::LengthMismatch {
            what: "fit points",
            got: y_mm.len().min(z_nm.len()),
            expected: x_mm.len(),
        });
    }
    let p = terms.len();
    if p == 0 {
        return Ok((Vec::new(), z_nm.to_vec()));
    }
    let inv = 1.0 / norm_radius_mm;
    let r = tsqr(z_nm.len(), p + 1, |i, row| {
        let (u, v) = (x_mm[i] * inv, y_mm[i] * inv);
        for (slot, &k) in row.iter_mut().zip(terms) {
            *slot = basis.eval(k, u, v);
        }
        row[p] = z_nm[i];
        Ok(())
    })?;
    let red = Reduced::new(&r, p, "modal fit")?;
    if red.condition() > MAX_CONDITION {
        return Err(Error::Geometry(format!(
            "modal fit: the {p} terms are not determined by the {} points (condition {:.2e})",
            z_nm.len(),
            red.condition()
        )));
    }
    let c = red.solve(0.0, 0.0);
    let residual = (0..z_nm.len())
        .map(|i| {
            let (u, v) = (x_mm[i] * inv, y_mm[i] * inv);
            z_nm[i]
                - terms
                    .iter()
                    .zip(&c)
                    .map(|(&k, ck)| ck * basis.eval(k, u, v))
                    .sum::<f64>()
        })
        .collect();
    Ok((c, residual))
}

/// Fits the first `n_terms` of `basis` (see [`fit_terms`]).
pub fn fit(
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    basis: Basis,
    n_terms: usize,
    norm_radius_mm: f64,
) -> Result<ModalFit> {
    if n_terms == 0 {
        return Err(Error::invalid("terms", "must be at least 1"));
    }
    // The dense fit holds a block of rows per thread and the stacked factors, each with
    // n_terms + 1 columns (see `lstsq::tsqr`): at least rows x (n_terms + 1) values.
    crate::budget::check_f64s(
        "--terms",
        &format!("{n_terms} terms fitted to {} points", z_nm.len()),
        (z_nm.len().min(4096) as f64) * (n_terms as f64 + 1.0),
        1.0,
    )?;
    let terms: Vec<usize> = (1..=n_terms).collect();
    let (coefficients_nm, residual_nm) =
        fit_terms(x_mm, y_mm, z_nm, basis, &terms, norm_radius_mm)?;
    Ok(ModalFit {
        basis,
        norm_radius_mm,
        coefficients_nm,
        residual_nm,
    })
}

/// Low-order form terms removed from a measured map before it is used (alignment and set-up
/// errors rather than figure error). Each is a group of Noll Zernike terms.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FormTerm {
    /// `Z1`.
    Piston,
    /// `Z2`, `Z3` (tip/tilt).
    Tilt,
    /// `Z4` (defocus).
    Power,
    /// `Z5`, `Z6`.
    Astig,
    /// `Z7`, `Z8`.
    Coma,
    /// `Z9`, `Z10`.
    Trefoil,
    /// `Z11`.
    Spherical,
}

impl FormTerm {
    /// Every form term, in Noll order.
    pub const ALL: [FormTerm; 7] = [
        FormTerm::Piston,
        FormTerm::Tilt,
        FormTerm::Power,
        FormTerm::Astig,
        FormTerm::Coma,
        FormTerm::Trefoil,
        FormTerm::Spherical,
    ];

    /// The term's name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            FormTerm::Piston => "piston",
            FormTerm::Tilt => "tilt",
            FormTerm::Power => "power",
            FormTerm::Astig => "astig",
            FormTerm::Coma => "coma",
            FormTerm::Trefoil => "trefoil",
            FormTerm::Spherical => "spherical",
        }
    }

    /// Noll indices of the term.
    pub fn noll(self) -> &'static [usize] {
        match self {
            FormTerm::Piston => &[1],
            FormTerm::Tilt => &[2, 3],
            FormTerm::Power => &[4],
            FormTerm::Astig => &[5, 6],
            FormTerm::Coma => &[7, 8],
            FormTerm::Trefoil => &[9, 10],
            FormTerm::Spherical => &[11],
        }
    }
}

impl std::str::FromStr for FormTerm {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        FormTerm::ALL
            .into_iter()
            .find(|t| t.name() == s.trim())
            .ok_or_else(|| {
                Error::invalid(
                    "form term",
                    format!(
                        "`{s}` is not one of {}",
                        FormTerm::ALL.map(FormTerm::name).join(", ")
                    ),
                )
            })
    }
}

/// One removed Zernike term.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RemovedTerm {
    /// Noll index.
    pub noll: usize,
    /// The form term it belongs to.
    pub term: FormTerm,
    /// Coefficient (orthonormal Zernike over the normalisation disk), nm.
    pub coefficient_nm: f64,
}

/// What [`remove_form`] took out of a map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FormRemoval {
    /// Normalisation radius of the Zernike terms, mm.
    pub norm_radius_mm: f64,
    /// The removed terms and their coefficients.
    pub terms: Vec<RemovedTerm>,
}

/// The radius of the smallest origin-centred disk holding every point, mm.
pub fn enclosing_radius_mm(x_mm: &[f64], y_mm: &[f64]) -> f64 {
    x_mm.iter()
        .zip(y_mm)
        .map(|(x, y)| x.hypot(*y))
        .fold(0.0, f64::max)
}

/// Removes the form terms from the heights by a joint least-squares fit of their Noll Zernike
/// terms over the points (normalised by `norm_radius_mm`, by default the radius of the smallest
/// origin-centred disk holding the points). Returns the residual heights and the coefficients.
pub fn remove_form(
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    terms: &[FormTerm],
    norm_radius_mm: Option<f64>,
) -> Result<(Vec<f64>, FormRemoval)> {
    let mut sorted: Vec<FormTerm> = terms.to_vec();
    sorted.sort();
    sorted.dedup();
    let radius = norm_radius_mm.unwrap_or_else(|| enclosing_radius_mm(x_mm, y_mm));
    let noll: Vec<(usize, FormTerm)> = sorted
        .iter()
        .flat_map(|t| t.noll().iter().map(move |&j| (j, *t)))
        .collect();
    let idx: Vec<usize> = noll.iter().map(|(j, _)| *j).collect();
    let (c, residual) = fit_terms(x_mm, y_mm, z_nm, Basis::ZernikeNoll, &idx, radius)?;
    Ok((
        residual,
        FormRemoval {
            norm_radius_mm: radius,
            terms: noll
                .iter()
                .zip(c)
                .map(|(&(noll, term), coefficient_nm)| RemovedTerm {
                    noll,
                    term,
                    coefficient_nm,
                })
                .collect(),
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};

    const TOL_ORTHO: f64 = 2e-4;

    #[test]
    fn noll_and_fringe_orders_match_the_published_tables() {
        // Noll 1976, table 1.
        let noll = [
            (0, 0),
            (1, 1),
            (1, -1),
            (2, 0),
            (2, -2),
            (2, 2),
            (3, -1),
            (3, 1),
            (3, -3),
            (3, 3),
            (4, 0),
        ];
        for (j, nm) in noll.iter().enumerate() {
            assert_eq!(noll_to_nm(j + 1), *nm, "Noll j = {}", j + 1);
        }
        // Fringe: piston, tilt x, tilt y, power, astig 0/45, coma x/y, spherical, trefoil.
        let fringe = [
            (0, 0),
            (1, 1),
            (1, -1),
            (2, 0),
            (2, 2),
            (2, -2),
            (3, 1),
            (3, -1),
            (4, 0),
            (3, 3),
            (3, -3),
        ];
        for (j, nm) in fringe.iter().enumerate() {
            assert_eq!(fringe_to_nm(j + 1), *nm, "Fringe j = {}", j + 1);
        }
        assert_eq!(fringe_to_nm(16), (6, 0));
        assert_eq!(fringe_to_nm(36), (10, 0));
    }

    #[test]
    fn closed_forms_of_low_orders() {
        let (rho, th) = (0.7f64, 0.4f64);
        let (u, v) = (rho * th.cos(), rho * th.sin());
        let b = Basis::ZernikeNoll;
        assert!((b.eval(4, u, v) - 3f64.sqrt() * (2.0 * rho * rho - 1.0)).abs() < 1e-14);
        assert!(
            (b.eval(11, u, v) - 5f64.sqrt() * (6.0 * rho.powi(4) - 6.0 * rho * rho + 1.0)).abs()
                < 1e-13
        );
        assert!(
            (b.eval(7, u, v) - 8f64.sqrt() * (3.0 * rho.powi(3) - 2.0 * rho) * th.sin()).abs()
                < 1e-13
        );
        assert!((legendre(3, 0.3) - 0.5 * (5.0 * 0.027 - 0.9)).abs() < 1e-15);
        assert_eq!(legendre_degrees(0), (0, 0));
        assert_eq!(legendre_degrees(1), (1, 0));
        assert_eq!(legendre_degrees(2), (0, 1));
        assert_eq!(legendre_degrees(5), (0, 2));
    }

    #[test]
    fn zernikes_are_orthonormal_on_the_unit_disk() {
        // Midpoint rule in (rho^2, theta): area element uniform in rho^2.
        let (nr, nt) = (400, 256);
        let mut pts = Vec::new();
        for i in 0..nr {
            let rho = ((i as f64 + 0.5) / nr as f64).sqrt();
            for k in 0..nt {
                let th = 2.0 * std::f64::consts::PI * (k as f64 + 0.5) / nt as f64;
                pts.push((rho * th.cos(), rho * th.sin()));
            }
        }
        for a in [1, 2, 4, 5, 8, 11, 15, 22] {
            for b in [1, 3, 4, 6, 8, 11, 16, 22] {
                let s: f64 = pts
                    .iter()
                    .map(|&(u, v)| {
                        Basis::ZernikeNoll.eval(a, u, v) * Basis::ZernikeNoll.eval(b, u, v)
                    })
                    .sum::<f64>()
                    / pts.len() as f64;
                let want = if a == b { 1.0 } else { 0.0 };
                assert!((s - want).abs() < TOL_ORTHO, "<Z{a}, Z{b}> = {s}");
            }
        }
    }

    /// A holed 100 mm disk sampled at 1 mm.
    fn holed_disk() -> (Vec<f64>, Vec<f64>) {
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for i in -50..=50 {
            for j in -50..=50 {
                let (xi, yj) = (i as f64, j as f64);
                let r = xi.hypot(yj);
                let hole = (xi - 10.0).hypot(yj + 15.0) < 6.0 || (i * 7 + j * 3) % 23 == 0;
                if r <= 50.0 && !hole {
                    x.push(xi);
                    y.push(yj);
                }
            }
        }
        (x, y)
    }

    #[test]
    fn fit_recovers_spherical_on_a_holed_disk() {
        let (x, y) = holed_disk();
        let z: Vec<f64> = x
            .iter()
            .zip(&y)
            .map(|(&a, &b)| {
                let rho2 = (a * a + b * b) / 2500.0;
                let sph = 5f64.sqrt() * (6.0 * rho2 * rho2 - 6.0 * rho2 + 1.0);
                12.0 + 0.3 * a - 0.2 * b + 40.0 * rho2 + 20.0 * sph
            })
            .collect();
        let f = fit(&x, &y, &z, Basis::ZernikeNoll, 37, 50.0).unwrap();
        let z11 = f.coefficients_nm[10];
        assert!((z11 - 20.0).abs() / 20.0 < 1e-9, "Z11 = {z11}");
        for (k, c) in f.coefficients_nm.iter().enumerate() {
            if ![0, 1, 2, 3, 10].contains(&k) {
                assert!(c.abs() < 1e-9, "Z{} = {c}", k + 1);
            }
        }
        // Piston/tilt/power in Noll units: 40 rho^2 = 40 (Z4 / sqrt3 + 1) / 2.
        assert!((f.coefficients_nm[3] - 20.0 / 3f64.sqrt()).abs() < 1e-9);
        assert!((f.coefficients_nm[1] - 0.3 * 50.0 / 2.0).abs() < 1e-9);
        assert!(f.residual_nm.iter().all(|r| r.abs() < 1e-9));
    }

    #[test]
    fn detrend_matches_normal_equations() {
        // Independent reference: the normal equations of [1, x, y, x^2 + y^2] solved by nalgebra.
        let (x, y) = holed_disk();
        let z: Vec<f64> = x
            .iter()
            .zip(&y)
            .map(|(&a, &b)| {
                let rho2 = (a * a + b * b) / 2500.0;
                3.0 + 0.05 * a + 0.02 * b - 15.0 * rho2
                    + 20.0 * 5f64.sqrt() * (6.0 * rho2 * rho2 - 6.0 * rho2 + 1.0)
                    + 2.0 * (0.3 * a).sin()
            })
            .collect();
        let (res, removal) = remove_form(
            &x,
            &y,
            &z,
            &[FormTerm::Power, FormTerm::Piston, FormTerm::Tilt],
            None,
        )
        .unwrap();
        assert_eq!(removal.terms.len(), 4);
        assert!((removal.norm_radius_mm - 50.0).abs() < 1e-12);
        let n = x.len();
        let a = DMatrix::from_fn(n, 4, |i, c| match c {
            0 => 1.0,
            1 => x[i],
            2 => y[i],
            _ => x[i] * x[i] + y[i] * y[i],
        });
        let zb = DVector::from_vec(z.clone());
        let coef = (a.transpose() * &a)
            .lu()
            .solve(&(a.transpose() * &zb))
            .unwrap();
        let want = &zb - &a * coef;
        let worst = res
            .iter()
            .zip(want.iter())
            .map(|(r, w)| (r - w).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-9, "largest difference {worst} nm");
    }

    #[test]
    fn legendre_fit_recovers_a_product() {
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for i in 0..30 {
            for j in 0..20 {
                x.push(-10.0 + 20.0 * i as f64 / 29.0);
                y.push(-10.0 + 20.0 * j as f64 / 29.0);
            }
        }
        // 7 L_4 (term index of (i, j) = (1, 1) is 5, 1-based).
        let z: Vec<f64> = x
            .iter()
            .zip(&y)
            .map(|(&a, &b)| 7.0 * 3.0 * (a / 10.0) * (b / 10.0) - 2.0)
            .collect();
        let f = fit(&x, &y, &z, Basis::Legendre, 10, 10.0).unwrap();
        assert!((f.coefficients_nm[4] - 7.0).abs() < 1e-10);
        assert!((f.coefficients_nm[0] + 2.0).abs() < 1e-10);
    }

    #[test]
    fn too_many_terms_for_the_points_is_an_error() {
        let x = vec![0.0, 1.0, 0.0];
        let y = vec![0.0, 0.0, 1.0];
        assert!(fit(&x, &y, &[1.0, 2.0, 3.0], Basis::ZernikeNoll, 6, 1.0).is_err());
        assert!("focus".parse::<FormTerm>().is_err());
        assert_eq!("power".parse::<FormTerm>().unwrap(), FormTerm::Power);
    }
}
