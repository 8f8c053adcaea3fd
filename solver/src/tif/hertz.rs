//! Spherical polishing tool in Hertzian contact, spinning about an axis tilted from the part
//! normal: pressure, sliding speed and Preston removal rate over the contact patch.
//!
//! # Contact (Hertz; Johnson, *Contact Mechanics*, 1985, eqs. 4.22-4.23)
//!
//! Effective modulus `1/E* = (1 - nu1^2)/E1 + (1 - nu2^2)/E2`; effective radius
//! `1/R_eff = 1/R_tool - kappa_part`, where `kappa_part` (1/mm) is the part's curvature with the
//! sign convention of [`crate::surface::SagDerivs::principal_curvatures`] (positive for a bowl
//! opening towards the tool, i.e. concave; negative for a convex part; 0 for a flat). With two
//! different principal curvatures the equivalent radius `R_e = sqrt(R' R'')` of the two principal
//! relative radii is used with a circular patch (Johnson eq. 4.31 approximation). Contact radius
//! `a = (3 F R_eff / (4 E*))^(1/3)`, peak pressure `p0 = 3 F / (2 pi a^2)`, pressure
//! `p(r) = p0 sqrt(1 - r^2/a^2)`.
//!
//! # Sliding speed of the tilted spinning sphere
//!
//! Put the contact point at the origin with the part normal along `+z`; the sphere centre is at
//! `C = (0, 0, R)` (the Hertz approach `a^2/R_eff` is neglected against `R`). The spindle spins at
//! `omega` about the unit axis `u = (0, sin alpha, cos alpha)` through `C`, tilted by `alpha` from
//! the normal in the `y-z` plane. A tool point `P = (x, y, 0)` of the flattened patch moves with
//! `v = omega u x (P - C)`:
//!
//! ```text
//! P - C = (x, y, -R)
//! u x (P - C) = (-R sin a - y cos a,  x cos a,  -x sin a)
//! ```
//!
//! The part is still (the TIF is the removal rate of the tool held in place), so the sliding
//! speed is the component of `v` in the contact plane:
//! `v_t(x, y) = omega sqrt((R sin a + y cos a)^2 + x^2 cos^2 a)`. (The full 3-D speed is
//! `omega sqrt((R sin a + y cos a)^2 + x^2)`; its extra part `-omega x sin a` is normal to the part
//! and does no sliding.) At the patch centre `v_t = omega R sin a`; for `a = 0` it is
//! `omega r` (pure spin about the normal).
//!
//! # Removal
//!
//! Preston: `rate = K p v` with `K` in mm^2/N, `p` in MPa (N/mm^2), `v` in mm/s, giving mm/s,
//! stored as nm/s (`x 1e6`).

use super::grid::GridTif;
use super::InfluenceFunction;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// nm per mm.
const NM_PER_MM: f64 = 1e6;
/// MPa per GPa.
const MPA_PER_GPA: f64 = 1e3;

/// Parameters of a spherical tool pressed on a part (settings: all fields public, defaults are the
/// published deterministic freeform polishing case: 10 N, 16 mm sponge tool, 104.72 rad/s, 15 deg).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HertzParams {
    /// Normal force, N.
    pub force_n: f64,
    /// Tool (sphere) radius, mm.
    pub tool_radius_mm: f64,
    /// Spindle speed, rad/s.
    pub spindle_rad_s: f64,
    /// Tilt of the spindle axis from the part normal, degrees (in the y-z plane).
    pub tilt_deg: f64,
    /// Young's modulus of the tool, GPa.
    pub tool_e_gpa: f64,
    /// Poisson ratio of the tool.
    pub tool_nu: f64,
    /// Young's modulus of the part, GPa.
    pub part_e_gpa: f64,
    /// Poisson ratio of the part.
    pub part_nu: f64,
    /// Preston coefficient, mm^2/N (rate mm/s = K * p MPa * v mm/s).
    pub preston_k_mm2_per_n: f64,
}

impl Default for HertzParams {
    fn default() -> Self {
        Self {
            force_n: 10.0,
            tool_radius_mm: 16.0,
            spindle_rad_s: 104.72,
            tilt_deg: 15.0,
            tool_e_gpa: 0.005,
            tool_nu: 0.4,
            part_e_gpa: 72.0,
            part_nu: 0.2,
            preston_k_mm2_per_n: 1e-7,
        }
    }
}

impl HertzParams {
    /// Checks ranges: force, radius, moduli and K positive; Poisson ratios in [0, 0.5];
    /// tilt in [0, 90] degrees; spindle speed finite and non-negative.
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("hertz force_n", self.force_n),
            ("hertz tool_radius_mm", self.tool_radius_mm),
            ("hertz tool_e_gpa", self.tool_e_gpa),
            ("hertz part_e_gpa", self.part_e_gpa),
            ("hertz preston_k_mm2_per_n", self.preston_k_mm2_per_n),
        ])?;
        for (name, v) in [
            ("hertz tool_nu", self.tool_nu),
            ("hertz part_nu", self.part_nu),
        ] {
            if !(v.is_finite() && (0.0..=0.5).contains(&v)) {
                return Err(Error::invalid(
                    name,
                    format!("must be in [0, 0.5], got {v}"),
                ));
            }
        }
        if !(self.tilt_deg.is_finite() && (0.0..=90.0).contains(&self.tilt_deg)) {
            return Err(Error::invalid(
                "hertz tilt_deg",
                format!("must be in [0, 90], got {}", self.tilt_deg),
            ));
        }
        if !(self.spindle_rad_s.is_finite() && self.spindle_rad_s >= 0.0) {
            return Err(Error::invalid(
                "hertz spindle_rad_s",
                format!("must be non-negative, got {}", self.spindle_rad_s),
            ));
        }
        Ok(())
    }

    /// Effective modulus `E*`, MPa: `1/E* = (1 - nu1^2)/E1 + (1 - nu2^2)/E2`.
    pub fn effective_modulus_mpa(&self) -> f64 {
        let inv = (1.0 - self.tool_nu * self.tool_nu) / (self.tool_e_gpa * MPA_PER_GPA)
            + (1.0 - self.part_nu * self.part_nu) / (self.part_e_gpa * MPA_PER_GPA);
        1.0 / inv
    }

    /// Effective radius, mm, for part principal curvatures `(k1, k2)` (1/mm, positive concave):
    /// `R' = 1/(1/R_tool - k1)`, `R'' = 1/(1/R_tool - k2)`, `R_eff = sqrt(R' R'')`. Errors when
    /// the part is more concave than the tool (conformal contact, no Hertz solution).
    pub fn effective_radius_mm(&self, k1_per_mm: f64, k2_per_mm: f64) -> Result<f64> {
        let inv_t = 1.0 / self.tool_radius_mm;
        let (c1, c2) = (inv_t - k1_per_mm, inv_t - k2_per_mm);
        if !(c1.is_finite() && c2.is_finite() && c1 > 0.0 && c2 > 0.0) {
            return Err(Error::invalid(
                "part curvature",
                format!(
                    "principal curvatures ({k1_per_mm}, {k2_per_mm}) 1/mm are not below the tool's 1/{} 1/mm: the part is more concave than the tool, no Hertz contact",
                    self.tool_radius_mm
                ),
            ));
        }
        Ok(1.0 / (c1 * c2).sqrt())
    }
}

/// A Hertzian spherical-tool TIF at one part curvature. Evaluates the model analytically;
/// [`HertzTif::to_grid`] samples it for `preston solve`.
#[derive(Debug, Clone, PartialEq)]
pub struct HertzTif {
    params: HertzParams,
    contact_radius_mm: f64,
    peak_pressure_mpa: f64,
    effective_radius_mm: f64,
    sin_tilt: f64,
    cos_tilt: f64,
    /// `K p0 * 1e6`: nm/s per (mm/s of speed) at the patch centre.
    k_p0_nm: f64,
}

impl HertzTif {
    /// The TIF on a flat part.
    pub fn flat(params: &HertzParams) -> Result<Self> {
        Self::with_curvatures(params, 0.0, 0.0)
    }

    /// The TIF on a sphere of radius `part_radius_mm` (positive convex, negative concave,
    /// infinite for flat).
    pub fn with_part_radius(params: &HertzParams, part_radius_mm: f64) -> Result<Self> {
        if part_radius_mm == 0.0 || part_radius_mm.is_nan() {
            return Err(Error::invalid(
                "part_radius_mm",
                format!("must be non-zero, got {part_radius_mm}"),
            ));
        }
        // Convex (positive radius) is a negative curvature in the surface convention.
        let k = -1.0 / part_radius_mm;
        Self::with_curvatures(params, k, k)
    }

    /// The TIF where the part has principal curvatures `(k1, k2)`, 1/mm (surface convention:
    /// positive concave).
    pub fn with_curvatures(params: &HertzParams, k1_per_mm: f64, k2_per_mm: f64) -> Result<Self> {
        params.validate()?;
        let r_eff = params.effective_radius_mm(k1_per_mm, k2_per_mm)?;
        let e_star = params.effective_modulus_mpa();
        let a = (3.0 * params.force_n * r_eff / (4.0 * e_star)).cbrt();
        let p0 = 3.0 * params.force_n / (2.0 * PI * a * a);
        let tilt = params.tilt_deg.to_radians();
        Ok(Self {
            params: params.clone(),
            contact_radius_mm: a,
            peak_pressure_mpa: p0,
            effective_radius_mm: r_eff,
            sin_tilt: tilt.sin(),
            cos_tilt: tilt.cos(),
            k_p0_nm: params.preston_k_mm2_per_n * p0 * NM_PER_MM,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &HertzParams {
        &self.params
    }

    /// Contact radius `a`, mm.
    pub fn contact_radius_mm(&self) -> f64 {
        self.contact_radius_mm
    }

    /// Peak pressure `p0 = 3F/(2 pi a^2)`, MPa.
    pub fn peak_pressure_mpa(&self) -> f64 {
        self.peak_pressure_mpa
    }

    /// Effective radius used, mm.
    pub fn effective_radius_mm(&self) -> f64 {
        self.effective_radius_mm
    }

    /// Contact pressure `p0 sqrt(1 - r^2/a^2)` at offset `(x, y)`, MPa; 0 outside the patch.
    #[inline]
    pub fn pressure_mpa(&self, x_mm: f64, y_mm: f64) -> f64 {
        let s = 1.0 - (x_mm * x_mm + y_mm * y_mm) / (self.contact_radius_mm.powi(2));
        if s > 0.0 {
            self.peak_pressure_mpa * s.sqrt()
        } else {
            0.0
        }
    }

    /// Sliding speed of the tool over the still part at `(x, y)`, mm/s:
    /// `omega sqrt((R sin a + y cos a)^2 + x^2 cos^2 a)` (see the module documentation).
    #[inline]
    pub fn sliding_speed_mm_per_s(&self, x_mm: f64, y_mm: f64) -> f64 {
        tilted_spin_speed(
            x_mm,
            y_mm,
            self.params.spindle_rad_s,
            self.params.tool_radius_mm,
            self.sin_tilt,
            self.cos_tilt,
        )
    }

    /// Volumetric removal rate, mm^3/s, by quadrature in polar coordinates with `r = a sin(theta)`
    /// (which removes the square-root edge of the pressure): midpoint rule, 400 x 512 nodes.
    pub fn volume_rate_mm3_per_s(&self) -> f64 {
        let a = self.contact_radius_mm;
        let (nt, nphi) = (400usize, 512usize);
        let (dt, dphi) = (0.5 * PI / nt as f64, 2.0 * PI / nphi as f64);
        let mut s = 0.0;
        for it in 0..nt {
            let th = (it as f64 + 0.5) * dt;
            let (st, ct) = th.sin_cos();
            let r = a * st;
            // p = p0 cos(th); dA = r dr dphi = a sin(th) a cos(th) dth dphi.
            let w = ct * r * a * ct;
            let mut ring = 0.0;
            for ip in 0..nphi {
                let (sp, cp) = ((ip as f64 + 0.5) * dphi).sin_cos();
                ring += self.sliding_speed_mm_per_s(r * cp, r * sp);
            }
            s += w * ring;
        }
        s * dt * dphi * self.k_p0_nm / NM_PER_MM
    }

    /// Samples the TIF on a square grid of pitch `pitch_mm` centred on the contact point and
    /// reaching at least the contact radius (nodes at `k * pitch`, `|k| <= ceil(a / pitch)`).
    pub fn to_grid(&self, pitch_mm: f64) -> Result<GridTif> {
        sample_on_grid(self, self.contact_radius_mm, pitch_mm)
    }
}

/// In-plane sliding speed, mm/s, at `(x, y)` of a sphere whose spin axis through the centre at
/// height `h` above the contact plane is tilted by angle `a` (given as `sin a`, `cos a`) in the y-z
/// plane: `omega sqrt((h sin a + y cos a)^2 + x^2 cos^2 a)`.
#[inline]
pub fn tilted_spin_speed(
    x_mm: f64,
    y_mm: f64,
    omega_rad_s: f64,
    centre_height_mm: f64,
    sin_tilt: f64,
    cos_tilt: f64,
) -> f64 {
    let vy = centre_height_mm * sin_tilt + y_mm * cos_tilt;
    let vx = x_mm * cos_tilt;
    omega_rad_s * (vx * vx + vy * vy).sqrt()
}

/// Samples `tif` on the square grid `k * pitch`, `|k| <= ceil(radius / pitch)` in x and y.
pub fn sample_on_grid<T: InfluenceFunction + ?Sized>(
    tif: &T,
    radius_mm: f64,
    pitch_mm: f64,
) -> Result<GridTif> {
    if !(pitch_mm.is_finite() && pitch_mm > 0.0) {
        return Err(Error::invalid(
            "TIF pitch_mm",
            format!("must be positive, got {pitch_mm}"),
        ));
    }
    let half = (radius_mm / pitch_mm - 1e-9).ceil().max(1.0);
    if half > 5000.0 {
        return Err(Error::invalid(
            "TIF pitch_mm",
            format!("{pitch_mm} mm gives more than 10001 x 10001 nodes over radius {radius_mm} mm"),
        ));
    }
    let half = half as i64;
    let n = (2 * half + 1) as usize;
    let mut rates = Vec::with_capacity(n * n);
    for iy in -half..=half {
        for ix in -half..=half {
            rates.push(tif.rate_nm_per_s(ix as f64 * pitch_mm, iy as f64 * pitch_mm));
        }
    }
    let x0 = -(half as f64) * pitch_mm;
    GridTif::new(x0, x0, pitch_mm, pitch_mm, n, n, rates)
}

impl InfluenceFunction for HertzTif {
    #[inline]
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let a2 = self.contact_radius_mm * self.contact_radius_mm;
        let s = 1.0 - (dx_mm * dx_mm + dy_mm * dy_mm) / a2;
        if s > 0.0 {
            self.k_p0_nm * s.sqrt() * self.sliding_speed_mm_per_s(dx_mm, dy_mm)
        } else {
            0.0
        }
    }

    fn support_radius_mm(&self) -> f64 {
        self.contact_radius_mm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative tolerance of closed-form contact quantities (pure arithmetic).
    const CLOSED_FORM_REL_TOL: f64 = 1e-12;
    /// Relative tolerance of two independent quadratures of the removal volume.
    const VOLUME_REL_TOL: f64 = 2e-3;

    fn published() -> HertzParams {
        HertzParams {
            preston_k_mm2_per_n: 2e-6,
            ..HertzParams::default()
        }
    }

    #[test]
    fn contact_radius_and_peak_pressure_closed_form() {
        let p = published();
        // E* by hand: 1 / ((1 - 0.16)/5 + (1 - 0.04)/72000) MPa.
        let e_star = 1.0 / (0.84 / 5.0 + 0.96 / 72_000.0);
        assert!((p.effective_modulus_mpa() - e_star).abs() < CLOSED_FORM_REL_TOL * e_star);
        let flat = HertzTif::flat(&p).unwrap();
        let a = (3.0 * 10.0 * 16.0 / (4.0 * e_star)).powf(1.0 / 3.0);
        assert!((flat.contact_radius_mm() - a).abs() < CLOSED_FORM_REL_TOL * a);
        let p0 = 3.0 * 10.0 / (2.0 * PI * a * a);
        assert!((flat.peak_pressure_mpa() - p0).abs() < CLOSED_FORM_REL_TOL * p0);
        // The pressure integrates to the force: int p0 sqrt(1 - r^2/a^2) dA = 2/3 pi a^2 p0 = F.
        assert!((2.0 / 3.0 * PI * a * a * p0 - 10.0).abs() < 1e-12);
        // Convex sphere of radius 50: 1/R_eff = 1/16 + 1/50.
        let convex = HertzTif::with_part_radius(&p, 50.0).unwrap();
        let r_eff = 1.0 / (1.0 / 16.0 + 1.0 / 50.0);
        let a_c = (3.0 * 10.0 * r_eff / (4.0 * e_star)).powf(1.0 / 3.0);
        assert!((convex.contact_radius_mm() - a_c).abs() < CLOSED_FORM_REL_TOL * a_c);
        assert!(convex.contact_radius_mm() < flat.contact_radius_mm());
        // Concave radius 50 gives a larger patch; concave smaller than the tool has no Hertz contact.
        let concave = HertzTif::with_part_radius(&p, -50.0).unwrap();
        let r_eff = 1.0 / (1.0 / 16.0 - 1.0 / 50.0);
        let a_cc = (3.0 * 10.0 * r_eff / (4.0 * e_star)).powf(1.0 / 3.0);
        assert!((concave.contact_radius_mm() - a_cc).abs() < CLOSED_FORM_REL_TOL * a_cc);
        assert!(HertzTif::with_part_radius(&p, -10.0).is_err());
        // Two principal curvatures: geometric mean of the relative radii.
        let t = HertzTif::with_curvatures(&p, -0.01, -0.03).unwrap();
        let re = (1.0_f64 / (1.0 / 16.0 + 0.01) / (1.0 / 16.0 + 0.03)).sqrt();
        assert!((t.effective_radius_mm() - re).abs() < CLOSED_FORM_REL_TOL * re);
    }

    #[test]
    fn speed_hand_checked_points() {
        let p = published();
        let t = HertzTif::flat(&p).unwrap();
        let (w, r) = (104.72, 16.0);
        let (s, c) = (15f64.to_radians().sin(), 15f64.to_radians().cos());
        // Centre: omega R sin(15 deg) = 104.72 * 16 * 0.258819 = 433.66 mm/s.
        let v0 = t.sliding_speed_mm_per_s(0.0, 0.0);
        assert!(
            (v0 - w * r * s).abs() < 1e-9 && (v0 - 433.66).abs() < 0.01,
            "{v0}"
        );
        // On the y axis the speed is omega |R sin a + y cos a|.
        let v = t.sliding_speed_mm_per_s(0.0, -1.0);
        assert!((v - w * (r * s - c)).abs() < 1e-9);
        // At (1, 0): omega sqrt((R sin a)^2 + cos^2 a).
        let v = t.sliding_speed_mm_per_s(1.0, 0.0);
        assert!((v - w * ((r * s).powi(2) + c * c).sqrt()).abs() < 1e-9);
        // Independent check: tangential part of omega u x (P - C) with vectors.
        let u = [0.0, s, c];
        for (x, y) in [(0.7, -1.3), (-2.0, 0.4), (1.1, 1.9)] {
            let d = [x, y, -r];
            let v = [
                u[1] * d[2] - u[2] * d[1],
                u[2] * d[0] - u[0] * d[2],
                u[0] * d[1] - u[1] * d[0],
            ];
            let want = w * (v[0] * v[0] + v[1] * v[1]).sqrt();
            assert!((t.sliding_speed_mm_per_s(x, y) - want).abs() < 1e-9 * want);
        }
        // No tilt: pure spin about the normal, v = omega r.
        let flat0 = HertzTif::flat(&HertzParams { tilt_deg: 0.0, ..p }).unwrap();
        assert!((flat0.sliding_speed_mm_per_s(0.3, 0.4) - w * 0.5).abs() < 1e-12);
    }

    #[test]
    fn volume_rate_against_independent_integrations() {
        // Zero tilt has a closed form: int K p0 sqrt(1 - r^2/a^2) omega r dA
        // = 2 pi K p0 omega a^3 int_0^1 s^2 sqrt(1 - s^2) ds = 2 pi K p0 omega a^3 pi / 16.
        let p = HertzParams {
            tilt_deg: 0.0,
            ..published()
        };
        let t = HertzTif::flat(&p).unwrap();
        let a = t.contact_radius_mm();
        let closed = 2.0
            * PI
            * p.preston_k_mm2_per_n
            * t.peak_pressure_mpa()
            * p.spindle_rad_s
            * a.powi(3)
            * PI
            / 16.0;
        let v = t.volume_rate_mm3_per_s();
        assert!((v - closed).abs() < 1e-6 * closed, "{v} vs {closed}");
        // Tilted: against a Cartesian midpoint rule on a fine grid (independent of the polar
        // substitution) and against the sampled grid's trapezoid volume.
        let t = HertzTif::flat(&published()).unwrap();
        let a = t.contact_radius_mm();
        let n = 1500usize;
        let h = 2.0 * a / n as f64;
        let mut s = 0.0;
        for iy in 0..n {
            for ix in 0..n {
                let x = -a + (ix as f64 + 0.5) * h;
                let y = -a + (iy as f64 + 0.5) * h;
                s += t.rate_nm_per_s(x, y);
            }
        }
        let cart = s * h * h * 1e-6;
        let v = t.volume_rate_mm3_per_s();
        assert!((v - cart).abs() < VOLUME_REL_TOL * v, "{v} vs {cart}");
        let g = t.to_grid(a / 200.0).unwrap();
        assert!((g.volume_rate_mm3_per_s() - v).abs() < VOLUME_REL_TOL * v);
        // The sliding speed grows with +y (R sin a + y cos a), so the footprint leans to +y.
        assert!(t.rate_nm_per_s(0.0, 0.3 * a) > t.rate_nm_per_s(0.0, -0.3 * a));
        assert_eq!(t.rate_nm_per_s(a * 1.0001, 0.0), 0.0);
    }
}
