//! A TIF under a perturbation of how the tool acts: wider or narrower with its volume kept,
//! faster or slower, and landing off where it is programmed, `f'(d) = r f((d - o) / w) / w²`
//! (width factor `w`, rate factor `r`, offset `o`). The scenarios of the sensitivity and of the
//! robust solve ([`crate::setup::sensitivity`], [`crate::setup::robust`]) integrate such a TIF
//! along the same motion.

use super::InfluenceFunction;

/// A TIF scaled in width (volume kept), scaled in rate and offset: `r f((d - o) / w) / w²`.
#[derive(Debug, Clone, Copy)]
pub struct PerturbedTif<'a, T: ?Sized> {
    tif: &'a T,
    width_factor: f64,
    rate_factor: f64,
    offset_mm: (f64, f64),
}

impl<'a, T: InfluenceFunction + ?Sized> PerturbedTif<'a, T> {
    /// `tif` with its width times `width_factor` (volume kept), its rate times `rate_factor`
    /// and its centre moved by `offset_mm`.
    pub fn new(tif: &'a T, width_factor: f64, rate_factor: f64, offset_mm: (f64, f64)) -> Self {
        Self {
            tif,
            width_factor,
            rate_factor,
            offset_mm,
        }
    }
}

impl<T: InfluenceFunction + ?Sized> InfluenceFunction for PerturbedTif<'_, T> {
    fn rate_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let w = self.width_factor;
        self.rate_factor / (w * w)
            * self.tif.rate_nm_per_s(
                (dx_mm - self.offset_mm.0) / w,
                (dy_mm - self.offset_mm.1) / w,
            )
    }

    fn support_radius_mm(&self) -> f64 {
        self.width_factor * self.tif.support_radius_mm() + self.offset_mm.0.hypot(self.offset_mm.1)
    }

    fn nominal_radius_mm(&self) -> f64 {
        self.width_factor * self.tif.nominal_radius_mm()
    }

    fn cut_disc_mm(&self) -> Option<(f64, f64, f64)> {
        let w = self.width_factor;
        self.tif
            .cut_disc_mm()
            .map(|(x, y, r)| (w * x + self.offset_mm.0, w * y + self.offset_mm.1, w * r))
    }
}

/// One scenario of how the tool acts: its TIF `width_factor` times wider (volume kept), its rate
/// `rate_factor` times higher, and the tool landing `offset_mm` away from where it is
/// programmed (in plan, machine axes).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Perturbation {
    /// Width factor of the TIF, its volume kept.
    pub width_factor: f64,
    /// Rate factor.
    pub rate_factor: f64,
    /// Offset of the tool in plan, mm (x, y).
    pub offset_mm: (f64, f64),
}

impl Perturbation {
    /// The nominal tool.
    pub const NONE: Self = Self {
        width_factor: 1.0,
        rate_factor: 1.0,
        offset_mm: (0.0, 0.0),
    };

    /// `tif` under this perturbation, its offset in the TIF's own coordinates (on a flat part
    /// with the TIF in machine axes, the plan offset).
    pub fn of<'a, T: InfluenceFunction + ?Sized>(&self, tif: &'a T) -> PerturbedTif<'a, T> {
        PerturbedTif::new(tif, self.width_factor, self.rate_factor, self.offset_mm)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tif::gaussian::GaussianTif;

    /// Agreement of two evaluations of one closed form.
    const CLOSED_FORM_REL_TOL: f64 = 1e-12;

    fn gaussian(sigma: f64, peak: f64) -> GaussianTif {
        GaussianTif::new(sigma, peak, 4.0 * sigma).unwrap()
    }

    /// A Gaussian widened by `w` with its volume kept is the Gaussian of width `w σ` and peak
    /// `A / w²`; a shifted one is the Gaussian evaluated at the shifted offset.
    #[test]
    fn a_perturbed_gaussian_is_the_gaussian_of_the_perturbed_parameters() {
        let g = gaussian(1.5, 10.0);
        for w in [1.03, 1.0 / 1.03] {
            let p = PerturbedTif::new(&g, w, 1.0, (0.0, 0.0));
            let expect = gaussian(1.5 * w, 10.0 / (w * w));
            for (dx, dy) in [(0.0, 0.0), (0.7, -0.3), (2.1, 1.4), (-3.0, 0.5)] {
                let (a, b) = (p.rate_nm_per_s(dx, dy), expect.rate_nm_per_s(dx, dy));
                assert!(
                    (a - b).abs() <= CLOSED_FORM_REL_TOL * b.abs(),
                    "w {w}: {a} vs {b}"
                );
            }
        }
        let p = PerturbedTif::new(&g, 1.0, 1.03, (0.05, -0.02));
        let (a, b) = (
            p.rate_nm_per_s(1.0, 1.0),
            1.03 * g.rate_nm_per_s(0.95, 1.02),
        );
        assert!((a - b).abs() <= CLOSED_FORM_REL_TOL * b);
        assert!(p.support_radius_mm() > g.support_radius_mm());
    }
}
