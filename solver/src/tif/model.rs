//! The TIF models a user names by their process parameters (a Hertzian sphere, a bonnet, a
//! truncated Gaussian) or a measured grid adjusted to a pitch, centre and rate, each sampled on a
//! grid with the summary `preston tif` prints and the Python package returns.
//!
//! One service for every face: [`ProcessModel::sample`] (and [`GridAdjustment::apply`] with
//! [`TifSummary::of_measured`]) turns the parameters into the [`GridTif`] a solve reads and the
//! [`TifSummary`] of what was sampled; the faces only parse their flags or keywords into the
//! parameters and write or return the result ([`GridTif::columns`]). A new model is a variant of
//! [`ProcessModel`] with its summary fields, and the job schema's entry for it.

use super::bonnet::{BonnetParams, BonnetTif};
use super::gaussian::GaussianTif;
use super::grid::GridTif;
use super::hertz::{sample_on_grid, HertzParams, HertzTif};
use super::InfluenceFunction;
use crate::error::Result;
use serde::{Deserialize, Serialize};

/// Divisions of the bonnet spot's radius in the fine grid whose trapezoid volume stands for the
/// model's volumetric rate (the pressure vanishes linearly at the spot edge, so the trapezoid
/// rule converges as `pitch^2`: 400 divisions put it within about 1e-5 of the limit).
const BONNET_VOLUME_DIVISIONS: f64 = 400.0;

/// Which model a TIF came from (the `model` of a [`TifSummary`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TifModelKind {
    /// A spherical tool in Hertzian contact ([`super::hertz`]).
    Hertz,
    /// A bonnet pressed by a depth and precessed ([`super::bonnet`]).
    Bonnet,
    /// A truncated Gaussian ([`super::gaussian`]).
    Gaussian,
    /// A measured grid, adjusted by [`GridAdjustment`].
    Grid,
    /// A measured removal spot ([`super::spot`]; its summary is [`super::spot::SpotSummary`]).
    Spot,
}

/// The part a Hertzian tool presses on: its curvature sets the effective radius.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum HertzPart {
    /// A flat part.
    #[default]
    Flat,
    /// A sphere of this radius, mm: positive convex, negative concave.
    Sphere {
        /// Radius of curvature, mm.
        radius_mm: f64,
    },
    /// The principal curvatures where the tool sits, 1/mm (the sign convention of
    /// [`crate::surface::SagDerivs::principal_curvatures`]), e.g. a design surface's at a point.
    Curvatures {
        /// First principal curvature, 1/mm.
        k1_per_mm: f64,
        /// Second principal curvature, 1/mm.
        k2_per_mm: f64,
    },
}

/// A TIF process model with its parameters validated.
#[derive(Debug, Clone)]
pub enum ProcessModel {
    /// A spherical tool in Hertzian contact on its part.
    Hertz(HertzTif),
    /// A bonnet tool.
    Bonnet(BonnetTif),
    /// A truncated Gaussian, sampled out to its truncation radius.
    Gaussian(GaussianTif),
}

impl ProcessModel {
    /// A spherical tool in Hertzian contact with `part`.
    pub fn hertz(params: &HertzParams, part: HertzPart) -> Result<Self> {
        let t = match part {
            HertzPart::Flat => HertzTif::flat(params)?,
            HertzPart::Sphere { radius_mm } => HertzTif::with_part_radius(params, radius_mm)?,
            HertzPart::Curvatures {
                k1_per_mm,
                k2_per_mm,
            } => HertzTif::with_curvatures(params, k1_per_mm, k2_per_mm)?,
        };
        Ok(ProcessModel::Hertz(t))
    }

    /// A bonnet tool.
    pub fn bonnet(params: &BonnetParams) -> Result<Self> {
        Ok(ProcessModel::Bonnet(BonnetTif::new(params)?))
    }

    /// A truncated Gaussian (validated).
    pub fn gaussian(g: GaussianTif) -> Result<Self> {
        g.validate()?;
        Ok(ProcessModel::Gaussian(g))
    }

    /// Which model this is.
    pub fn kind(&self) -> TifModelKind {
        match self {
            ProcessModel::Hertz(_) => TifModelKind::Hertz,
            ProcessModel::Bonnet(_) => TifModelKind::Bonnet,
            ProcessModel::Gaussian(_) => TifModelKind::Gaussian,
        }
    }

    /// The model sampled on the square grid `k * pitch_mm` that covers its contact (spot,
    /// truncation) radius.
    pub fn grid(&self, pitch_mm: f64) -> Result<GridTif> {
        match self {
            ProcessModel::Hertz(t) => t.to_grid(pitch_mm),
            ProcessModel::Bonnet(t) => t.to_grid(pitch_mm),
            ProcessModel::Gaussian(g) => sample_on_grid(g, g.truncation_radius_mm, pitch_mm),
        }
    }

    /// The model sampled at `pitch_mm` ([`ProcessModel::grid`]) with its summary.
    pub fn sample(&self, pitch_mm: f64) -> Result<SampledTif> {
        let grid = self.grid(pitch_mm)?;
        let summary = TifSummary::of_model(self, &grid)?;
        Ok(SampledTif { grid, summary })
    }
}

/// A measured grid's adjustments, applied in this order: resampled (bilinear) onto a pitch,
/// recentred on its rate-weighted centroid, scaled to a peak rate or a volumetric rate.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GridAdjustment {
    /// Resample onto this pitch, mm.
    pub pitch_mm: Option<f64>,
    /// Move the origin to the rate-weighted centroid.
    pub recentre: bool,
    /// Scale to this peak rate, nm/s.
    pub peak_nm_per_s: Option<f64>,
    /// Scale to this volumetric rate, mm^3/min.
    pub volume_mm3_per_min: Option<f64>,
}

impl GridAdjustment {
    /// `g` with the adjustments applied ([`GridTif::resampled`], [`GridTif::recentred`],
    /// [`GridTif::scaled_to_peak`], [`GridTif::scaled_to_volume`]).
    pub fn apply(&self, mut g: GridTif) -> Result<GridTif> {
        if let Some(p) = self.pitch_mm {
            g = g.resampled(p)?;
        }
        if self.recentre {
            g = g.recentred()?;
        }
        if let Some(p) = self.peak_nm_per_s {
            g = g.scaled_to_peak(p)?;
        }
        if let Some(v) = self.volume_mm3_per_min {
            g = g.scaled_to_volume(v / 60.0)?;
        }
        Ok(g)
    }
}

/// A TIF sampled on a grid, with its summary.
#[derive(Debug, Clone)]
pub struct SampledTif {
    /// The grid a solve reads (`x_mm,y_mm,rate_nm_per_s`).
    pub grid: GridTif,
    /// What was sampled.
    pub summary: TifSummary,
}

/// What `preston tif` prints (JSON) and the Python package's `tif_*` functions return: the
/// model's own figures and those of the grid written. Fields a model does not have are `null`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TifSummary {
    /// The model.
    pub model: TifModelKind,
    /// Contact (spot, truncation, support) radius, mm.
    pub contact_radius_mm: f64,
    /// Peak contact pressure, MPa (null for Gaussian and measured grids).
    pub peak_pressure_mpa: Option<f64>,
    /// Largest rate in the grid, nm/s.
    pub peak_rate_nm_per_s: f64,
    /// Volumetric removal rate of the model, mm^3/min: in closed form or by quadrature (Hertz,
    /// Gaussian), by a fine grid (bonnet), of the grid itself (measured).
    pub volume_rate_mm3_per_min: f64,
    /// Volumetric rate of the grid (bilinear, exact trapezoid), mm^3/min.
    pub grid_volume_rate_mm3_per_min: f64,
    /// Equivalent-circle FWHM of the grid, mm.
    pub fwhm_mm: f64,
    /// Sliding speed at the contact centre, mm/s (process models).
    pub centre_speed_mm_per_s: Option<f64>,
    /// Effective Hertz radius, mm (Hertz only).
    pub effective_radius_mm: Option<f64>,
    /// Grid nodes along x.
    pub nx: usize,
    /// Grid nodes along y.
    pub ny: usize,
    /// Grid pitch along x, mm.
    pub pitch_mm: f64,
}

impl TifSummary {
    /// The summary of `model` sampled as `grid`. The bonnet's volumetric rate is that of a grid
    /// of [`BONNET_VOLUME_DIVISIONS`] per spot radius, sampled here.
    pub fn of_model(model: &ProcessModel, grid: &GridTif) -> Result<Self> {
        let mut s = Self::of_grid(model.kind(), grid);
        match model {
            ProcessModel::Hertz(t) => {
                s.contact_radius_mm = t.contact_radius_mm();
                s.peak_pressure_mpa = Some(t.peak_pressure_mpa());
                s.volume_rate_mm3_per_min = t.volume_rate_mm3_per_s() * 60.0;
                s.centre_speed_mm_per_s = Some(t.sliding_speed_mm_per_s(0.0, 0.0));
                s.effective_radius_mm = Some(t.effective_radius_mm());
            }
            ProcessModel::Bonnet(t) => {
                let fine = t.to_grid(t.spot_radius_mm() / BONNET_VOLUME_DIVISIONS)?;
                s.contact_radius_mm = t.spot_radius_mm();
                s.peak_pressure_mpa = Some(t.peak_pressure_mpa());
                s.volume_rate_mm3_per_min = fine.volume_rate_mm3_per_s() * 60.0;
                s.centre_speed_mm_per_s = Some(t.sliding_speed_mm_per_s(0.0, 0.0));
            }
            ProcessModel::Gaussian(g) => {
                s.contact_radius_mm = g.truncation_radius_mm;
                s.volume_rate_mm3_per_min = g.volume_rate_mm3_per_s() * 60.0;
            }
        }
        Ok(s)
    }

    /// The summary of a measured grid: its support radius and its own volumetric rate.
    pub fn of_measured(grid: &GridTif) -> Self {
        let mut s = Self::of_grid(TifModelKind::Grid, grid);
        s.contact_radius_mm = grid.support_radius_mm();
        s.volume_rate_mm3_per_min = s.grid_volume_rate_mm3_per_min;
        s
    }

    /// The grid's figures; the model's left blank.
    fn of_grid(model: TifModelKind, grid: &GridTif) -> Self {
        let (nx, ny) = grid.shape();
        Self {
            model,
            contact_radius_mm: 0.0,
            peak_pressure_mpa: None,
            peak_rate_nm_per_s: grid.peak_rate_nm_per_s(),
            volume_rate_mm3_per_min: 0.0,
            grid_volume_rate_mm3_per_min: grid.volume_rate_mm3_per_s() * 60.0,
            fwhm_mm: grid.fwhm_mm(),
            centre_speed_mm_per_s: None,
            effective_radius_mm: None,
            nx,
            ny,
            pitch_mm: grid.pitch_mm().0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative agreement of two evaluations of the same closed form.
    const REL: f64 = 1e-12;

    #[test]
    fn gaussian_summary_holds_its_closed_form_volume_and_the_grid_figures() {
        let g = GaussianTif::new(2.0, 10.0, 6.0).unwrap();
        let s = ProcessModel::gaussian(g.clone())
            .unwrap()
            .sample(0.25)
            .unwrap();
        // 6 mm / 0.25 mm = 24 steps each side: 49 x 49 nodes.
        assert_eq!((s.summary.nx, s.summary.ny), (49, 49));
        assert_eq!(s.grid.shape(), (49, 49));
        assert_eq!(s.summary.model, TifModelKind::Gaussian);
        let closed =
            2.0 * std::f64::consts::PI * 4.0 * 10.0 * 1e-6 * (1.0 - (-36.0f64 / 8.0).exp()) * 60.0;
        assert!((s.summary.volume_rate_mm3_per_min - closed).abs() <= REL * closed);
        // The grid's trapezoid volume is close to the model's (second order in the pitch).
        let rel = (s.summary.grid_volume_rate_mm3_per_min / closed - 1.0).abs();
        assert!(rel < 1e-2, "grid volume off by {rel}");
        // The centre node is sampled exactly: the peak.
        assert_eq!(s.summary.peak_rate_nm_per_s, 10.0);
        assert_eq!(s.summary.contact_radius_mm, 6.0);
        assert_eq!(s.summary.peak_pressure_mpa, None);
        assert_eq!(s.summary.effective_radius_mm, None);
    }

    #[test]
    fn hertz_summary_is_the_model_on_its_part() {
        let p = HertzParams {
            tool_e_gpa: 0.005,
            tool_nu: 0.4,
            part_e_gpa: 70.0,
            part_nu: 0.17,
            preston_k_mm2_per_n: 1e-7,
            ..HertzParams::default()
        };
        let flat = ProcessModel::hertz(&p, HertzPart::Flat).unwrap();
        let s = flat.sample(0.1).unwrap().summary;
        // On a flat part the effective radius is the tool's.
        assert_eq!(s.effective_radius_mm, Some(p.tool_radius_mm));
        let t = HertzTif::flat(&p).unwrap();
        assert_eq!(s.contact_radius_mm, t.contact_radius_mm());
        assert_eq!(s.peak_pressure_mpa, Some(t.peak_pressure_mpa()));
        // A convex sphere of the tool's radius halves the effective radius; curvatures of a
        // concave sphere of twice it give 1/R_eff = 1/R - 1/(2R).
        let r = p.tool_radius_mm;
        let convex = ProcessModel::hertz(&p, HertzPart::Sphere { radius_mm: r }).unwrap();
        let s = convex.sample(0.1).unwrap().summary;
        assert!((s.effective_radius_mm.unwrap() - r / 2.0).abs() <= REL * r);
        let k = 1.0 / (2.0 * r);
        let concave = ProcessModel::hertz(
            &p,
            HertzPart::Curvatures {
                k1_per_mm: k,
                k2_per_mm: k,
            },
        )
        .unwrap();
        let s = concave.sample(0.1).unwrap().summary;
        assert!((s.effective_radius_mm.unwrap() - 2.0 * r).abs() <= REL * r);
    }

    #[test]
    fn measured_grid_summary_is_the_grid_adjusted() {
        let g = ProcessModel::gaussian(GaussianTif::new(1.0, 5.0, 3.0).unwrap())
            .unwrap()
            .grid(0.1)
            .unwrap();
        let adjust = GridAdjustment {
            pitch_mm: Some(0.2),
            recentre: true,
            volume_mm3_per_min: Some(0.5),
            ..GridAdjustment::default()
        };
        let a = adjust.apply(g).unwrap();
        let s = TifSummary::of_measured(&a);
        assert_eq!(s.model, TifModelKind::Grid);
        assert_eq!(s.pitch_mm, 0.2);
        assert!((s.volume_rate_mm3_per_min - 0.5).abs() <= 1e-12);
        assert_eq!(s.volume_rate_mm3_per_min, s.grid_volume_rate_mm3_per_min);
        assert_eq!(s.contact_radius_mm, a.support_radius_mm());
    }

    #[test]
    fn summary_prints_every_key_with_nulls_for_what_a_model_lacks() {
        let g = GaussianTif::new(1.0, 5.0, 3.0).unwrap();
        let s = ProcessModel::gaussian(g)
            .unwrap()
            .sample(0.5)
            .unwrap()
            .summary;
        let v = serde_json::to_value(&s).unwrap();
        let keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        let mut expected = vec![
            "model",
            "contact_radius_mm",
            "peak_pressure_mpa",
            "peak_rate_nm_per_s",
            "volume_rate_mm3_per_min",
            "grid_volume_rate_mm3_per_min",
            "fwhm_mm",
            "centre_speed_mm_per_s",
            "effective_radius_mm",
            "nx",
            "ny",
            "pitch_mm",
        ];
        let mut got = keys.clone();
        got.sort_unstable();
        expected.sort_unstable();
        assert_eq!(got, expected);
        assert_eq!(v["model"], "gaussian");
        assert!(v["peak_pressure_mpa"].is_null());
    }
}
