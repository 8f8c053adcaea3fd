//! What the interferometer will read after a run: the plan's executed removal under the tool as
//! it is known (the calibration's figures and their uncertainty, or the spot test's), the
//! measurement's noise, piston and tilt dropped.
//!
//! For draws `θ_k` of the tool (rate, width and centroid offset from their standard deviations,
//! the drift about its estimate), the run leaves `e_k = z - h(θ_k) + n_k`, `h(θ)` the removal of
//! the executed contact motion with the footprint under `θ` and `n_k` white noise; each `e_k`
//! less its least-squares plane is what the interferometer reads. The map planned on is the part
//! plus the measurement's noise, `z = p + n` (RMS `σ`): the part after the run is `z - h - n`,
//! and its reading adds the next measurement's noise. Let `w` be the white noise left in the
//! plan's nominal residual `r = z - h`: `σ` times the share of the map's own white noise that
//! remains in `r`, both seen by the same estimate from second differences ([`map_noise_rms_nm`]),
//! and at most `|r|`.
//! A deconvolution follows the map's noise below the tool's cut-off and leaves the finer noise
//! alone, so the plan has followed `σ_i = sqrt(σ² - w²)` of it, which it leaves on the part with
//! the opposite sign (the noise's imprint), while the `w` left in `r` is on the map only. The
//! reading's mean square is then `|r|² - w² + σ_i² + σ²`, at least `σ²`: `n_k` has the RMS
//! `sqrt(σ² + σ_i² - w²) = √2 σ_i`, about `√2 σ` for a plan that corrects the map to well below
//! its noise and none for a plan that leaves the noise alone (a band plan: the map's noise left
//! in `r` stands in for the next reading's). The
//! expected RMS is `sqrt(mean_k rms(e_k)²)`, the 90% range the 5th to 95th percentile of
//! `rms(e_k)`, the expected PV the median of `pv(e_k)`. The removals are the plan's exact one plus
//! the change the lattice convolution of [`super::forward`] gives for `θ_k` against the nominal
//! tool, so the lattice's own error cancels.

use super::forward::{ContactMotion, LatticeRemoval};
use super::tool::{SpotFootprint, ToolFigures};
use crate::error::{Error, Result};
use crate::map::{remove_plane, HeightStats};
use crate::rng::SplitMix64;
use crate::tif::{GridTif, InfluenceFunction};
use serde::{Deserialize, Serialize};

/// Lattice cells per second-moment radius for the draws.
const CELLS_PER_RADIUS: f64 = 8.0;

/// How well the tool of the next run is known.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ToolUncertainty {
    /// Relative standard deviation of the rate.
    pub rate_sigma: f64,
    /// Relative standard deviation of the width.
    pub width_sigma: f64,
    /// Standard deviation of the centroid offset along x, mm.
    pub offset_x_sigma_mm: f64,
    /// Along y, mm.
    pub offset_y_sigma_mm: f64,
    /// The rate's drift per hour of program time (the plan includes it).
    pub drift_per_hour: f64,
    /// Its standard deviation, per hour.
    pub drift_sigma_per_hour: f64,
    /// Standard deviation of the rate's change over the run, relative (from its first contact
    /// to its last), beside `drift_sigma_per_hour`: the run-to-run scatter of the drift.
    pub drift_sigma_per_run: f64,
    /// Noise of one measurement, nm RMS.
    pub noise_rms_nm: f64,
}

impl Default for ToolUncertainty {
    /// A spot test's: the rate to 7% (a spot test on another day), the width to 5%, the
    /// centroid to 0.2 mm, the rate's change over the run to [`super::DRIFT_SIGMA_PER_RUN`].
    fn default() -> Self {
        Self {
            rate_sigma: 0.07,
            width_sigma: 0.05,
            offset_x_sigma_mm: 0.2,
            offset_y_sigma_mm: 0.2,
            drift_per_hour: 0.0,
            drift_sigma_per_hour: 0.0,
            drift_sigma_per_run: super::DRIFT_SIGMA_PER_RUN,
            noise_rms_nm: 0.0,
        }
    }
}

impl ToolUncertainty {
    /// Checks that every figure is finite and every standard deviation non-negative.
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("rate_sigma", self.rate_sigma),
            ("width_sigma", self.width_sigma),
            ("offset_x_sigma_mm", self.offset_x_sigma_mm),
            ("offset_y_sigma_mm", self.offset_y_sigma_mm),
            ("drift_sigma_per_hour", self.drift_sigma_per_hour),
            ("drift_sigma_per_run", self.drift_sigma_per_run),
            ("noise_rms_nm", self.noise_rms_nm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::invalid(
                    format!("tool uncertainty {name}"),
                    format!("must be finite and >= 0, got {v}"),
                ));
            }
        }
        if !self.drift_per_hour.is_finite() {
            return Err(Error::invalid(
                "tool uncertainty drift_per_hour",
                "must be finite",
            ));
        }
        Ok(())
    }
}

/// The expected reading of the interferometer after the run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Expected {
    /// Expected RMS, nm.
    pub expected_rms_nm: f64,
    /// Expected PV (median over the draws), nm.
    pub expected_pv_nm: f64,
    /// 90% range of the RMS (5th and 95th percentiles), nm.
    pub expected_rms_range_nm: [f64; 2],
    /// RMS the nominal tool leaves (its drift included), piston and tilt removed, without noise,
    /// nm.
    pub nominal_rms_nm: f64,
    /// RMS of the map measured before the run with piston and tilt removed, as the
    /// interferometer reads it, nm: what a run must beat to pay.
    pub measured_rms_nm: f64,
    /// The uncertainty drawn from.
    pub uncertainty: ToolUncertainty,
    /// Number of draws.
    pub draws: usize,
    /// What the expected reading is made of, in quadrature.
    pub parts: ReadingParts,
}

/// The expected reading's parts, nm RMS, which add in quadrature to it:
/// `expected² = residual² + tool² + noise² + noise_imprint²`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReadingParts {
    /// What the plan leaves on the part with the nominal tool: [`Expected::nominal_rms_nm`] less
    /// the map's noise left in it, `sqrt(max(r² - w², 0))` (module documentation): structure
    /// outside the band the tool can correct, and what the plan chose not to remove.
    pub residual_nm: f64,
    /// What the tool's uncertainty adds: `sqrt(expected² - residual² - noise² -
    /// noise_imprint²)` (zero when the draws fall below the others).
    pub tool_nm: f64,
    /// The measurement's noise.
    pub noise_nm: f64,
    /// The noise of the map planned on that the plan removes as if it were form and leaves on
    /// the part with the opposite sign: `sqrt(σ² - w²)`, `w` the white noise left in the plan's
    /// residual (module documentation).
    pub noise_imprint_nm: f64,
}

/// The largest part of an expected reading: what keeps a run from doing better.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FloorCause {
    /// The plan's residual with the nominal tool: structure outside the tool's band.
    Band,
    /// How well the tool is known: calibrate it.
    ToolUncertainty,
    /// The metrology's noise: read once more, and, where the plan follows the map's noise,
    /// imprinted on the part.
    Noise,
}

impl ReadingParts {
    /// The parts of `expected_rms_nm` given the nominal residual, the noise and its imprint.
    pub fn of(
        expected_rms_nm: f64,
        residual_nm: f64,
        noise_nm: f64,
        noise_imprint_nm: f64,
    ) -> Self {
        let rest = expected_rms_nm.powi(2)
            - residual_nm.powi(2)
            - noise_nm.powi(2)
            - noise_imprint_nm.powi(2);
        Self {
            residual_nm,
            tool_nm: rest.max(0.0).sqrt(),
            noise_nm,
            noise_imprint_nm,
        }
    }

    /// The noise read and imprinted together, in quadrature, nm RMS.
    pub fn all_noise_nm(&self) -> f64 {
        self.noise_nm.hypot(self.noise_imprint_nm)
    }

    /// The largest part (the noise read and the noise imprinted counted together).
    pub fn cause(&self) -> FloorCause {
        let noise = self.all_noise_nm();
        if self.tool_nm >= self.residual_nm && self.tool_nm >= noise {
            FloorCause::ToolUncertainty
        } else if noise >= self.residual_nm {
            FloorCause::Noise
        } else {
            FloorCause::Band
        }
    }
}

impl FloorCause {
    /// Words for a console or a page.
    pub fn describe(self) -> &'static str {
        match self {
            FloorCause::Band => {
                "the structure the tool cannot correct (outside its band, or left by the plan)"
            }
            FloorCause::ToolUncertainty => "how well the tool is known (calibrate it)",
            FloorCause::Noise => "the metrology's noise",
        }
    }
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let f = p * (sorted.len() - 1) as f64;
    let (i, a) = (f.floor() as usize, f - f.floor());
    let j = (i + 1).min(sorted.len() - 1);
    sorted[i] * (1.0 - a) + sorted[j] * a
}

/// The expected reading after a run whose executed contact motion is `motion` and whose exact
/// removal with the nominal tool (no drift) is `removal_nm`, on the map `(x, y, z)`, with the
/// footprint `tif` (module documentation). `draws` draws from a generator seeded with `seed`.
#[allow(clippy::too_many_arguments)]
pub fn expected_reading(
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    removal_nm: &[f64],
    motion: &ContactMotion,
    tif: &GridTif,
    uncertainty: &ToolUncertainty,
    draws: usize,
    seed: u64,
) -> Result<Expected> {
    uncertainty.validate()?;
    let m = z_nm.len();
    for (what, len) in [
        ("x_mm", x_mm.len()),
        ("y_mm", y_mm.len()),
        ("removal_nm", removal_nm.len()),
    ] {
        if len != m {
            return Err(Error::LengthMismatch {
                what,
                got: len,
                expected: m,
            });
        }
    }
    if draws < 2 {
        return Err(Error::invalid(
            "expected reading",
            "needs at least two draws",
        ));
    }
    let spot = SpotFootprint::new(tif.clone())?;
    let u = uncertainty;
    let widest = spot.transformed(&ToolFigures {
        width_factor: 1.0 + 4.0 * u.width_sigma,
        offset_x_mm: 4.0 * u.offset_x_sigma_mm,
        offset_y_mm: 4.0 * u.offset_y_sigma_mm,
        ..ToolFigures::NOMINAL
    });
    let lattice = LatticeRemoval::new(
        motion,
        x_mm,
        y_mm,
        widest.support_radius_mm(),
        spot.radius_mm() / CELLS_PER_RADIUS,
    )?;
    let nominal_parts = lattice.removal_parts(&spot.transformed(&ToolFigures::NOMINAL));
    let reading = |h: &[f64], noise: Option<(&mut SplitMix64, f64)>| -> Result<Vec<f64>> {
        let mut e: Vec<f64> = z_nm.iter().zip(h).map(|(z, h)| z - h).collect();
        if let Some((rng, noise_rms_nm)) = noise {
            for v in e.iter_mut() {
                *v += noise_rms_nm * rng.normal();
            }
        }
        remove_plane(x_mm, y_mm, &mut e)?;
        Ok(e)
    };
    // The nominal tool with its drift: the exact removal plus the drift's lattice part.
    let nominal: Vec<f64> = (0..m)
        .map(|i| removal_nm[i] + u.drift_per_hour * nominal_parts[1][i])
        .collect();
    let residual = reading(&nominal, None)?;
    let nominal_rms_nm = HeightStats::of(&residual).rms_nm;
    let measured_rms_nm = HeightStats::of(&reading(&vec![0.0; m], None)?).rms_nm;
    // The share of the map's white noise the plan leaves, the same estimate on both sides.
    let map_white_nm = map_noise_rms_nm(x_mm, y_mm, z_nm);
    let left_share = if map_white_nm > 0.0 {
        (map_noise_rms_nm(x_mm, y_mm, &residual) / map_white_nm).min(1.0)
    } else {
        1.0
    };
    // No more noise left in the residual than the residual holds: the part is never read
    // below the next measurement's noise.
    let left_noise_nm = (u.noise_rms_nm * left_share).min(nominal_rms_nm);
    let noise_imprint_nm = (u.noise_rms_nm.powi(2) - left_noise_nm.powi(2))
        .max(0.0)
        .sqrt();
    let residual_nm = (nominal_rms_nm.powi(2) - left_noise_nm.powi(2))
        .max(0.0)
        .sqrt();
    let noise_rms_nm = std::f64::consts::SQRT_2 * noise_imprint_nm;
    // The drift's standard deviation per hour of this run: the known one and the run's own
    // scatter over its span.
    let span_s = motion.span_s();
    let drift_sigma_per_hour = if span_s > 0.0 {
        u.drift_sigma_per_hour
            .hypot(u.drift_sigma_per_run * 3600.0 / span_s)
    } else {
        u.drift_sigma_per_hour
    };
    let mut rng = SplitMix64::new(seed);
    let mut rms = Vec::with_capacity(draws);
    let mut pv = Vec::with_capacity(draws);
    for _ in 0..draws {
        let figures = ToolFigures {
            rate_factor: (1.0 + u.rate_sigma * rng.normal()).max(0.0),
            width_factor: (1.0 + u.width_sigma * rng.normal()).max(0.1),
            offset_x_mm: u.offset_x_sigma_mm * rng.normal(),
            offset_y_mm: u.offset_y_sigma_mm * rng.normal(),
            ..ToolFigures::NOMINAL
        };
        let drift = u.drift_per_hour + drift_sigma_per_hour * rng.normal();
        let rate = figures.rate_factor;
        let parts = lattice.removal_parts(&spot.transformed(&ToolFigures {
            rate_factor: 1.0,
            ..figures
        }));
        let h: Vec<f64> = (0..m)
            .map(|i| {
                let lattice_change =
                    rate * (parts[0][i] + drift * parts[1][i]) - nominal_parts[0][i];
                removal_nm[i] + lattice_change
            })
            .collect();
        let e = reading(&h, Some((&mut rng, noise_rms_nm)))?;
        let s = HeightStats::of(&e);
        rms.push(s.rms_nm);
        pv.push(s.pv_nm);
    }
    let mean_square = rms.iter().map(|r| r * r).sum::<f64>() / draws as f64;
    rms.sort_by(f64::total_cmp);
    pv.sort_by(f64::total_cmp);
    Ok(Expected {
        parts: ReadingParts::of(
            mean_square.sqrt(),
            residual_nm,
            u.noise_rms_nm,
            noise_imprint_nm,
        ),
        expected_rms_nm: mean_square.sqrt(),
        expected_pv_nm: percentile(&pv, 0.5),
        expected_rms_range_nm: [percentile(&rms, 0.05), percentile(&rms, 0.95)],
        nominal_rms_nm,
        measured_rms_nm,
        uncertainty: *uncertainty,
        draws,
    })
}

/// The white noise of a map on a lattice, nm RMS, from its second differences along the lattice
/// lines (blind to the map's slope; structure at the pixel scale counts as noise, so this bounds
/// it from above).
pub fn map_noise_rms_nm(x_mm: &[f64], y_mm: &[f64], z_nm: &[f64]) -> f64 {
    super::fit::neighbour_noise(x_mm, y_mm, z_nm)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative tolerance of a 32-draw RMS of white noise on 400 points.
    const DRAW_TOL: f64 = 0.05;

    /// A 20 x 20 map at 1 mm of seeded white noise of `sigma` nm RMS, a 5 x 5 Gaussian grid
    /// footprint, and a motion with contact time.
    fn case(sigma: f64) -> (Vec<f64>, Vec<f64>, Vec<f64>, ContactMotion, GridTif) {
        let mut rng = SplitMix64::new(7);
        let (mut x, mut y, mut z) = (Vec::new(), Vec::new(), Vec::new());
        for j in 0..20 {
            for i in 0..20 {
                x.push(i as f64);
                y.push(j as f64);
                z.push(sigma * rng.normal());
            }
        }
        remove_plane(&x, &y, &mut z).unwrap();
        let rates = (0..25)
            .map(|k| {
                let (dx, dy) = ((k % 5) as f64 - 2.0, (k / 5) as f64 - 2.0);
                (-(dx * dx + dy * dy) / 2.0).exp()
            })
            .collect();
        let tif = GridTif::new(-2.0, -2.0, 1.0, 1.0, 5, 5, rates).unwrap();
        let motion = ContactMotion {
            x_mm: vec![10.0],
            y_mm: vec![10.0],
            dwell_s: vec![1.0],
            time_s: vec![0.5],
        };
        (x, y, z, motion, tif)
    }

    fn exact_tool(noise_rms_nm: f64) -> ToolUncertainty {
        ToolUncertainty {
            rate_sigma: 0.0,
            width_sigma: 0.0,
            offset_x_sigma_mm: 0.0,
            offset_y_sigma_mm: 0.0,
            drift_sigma_per_run: 0.0,
            noise_rms_nm,
            ..ToolUncertainty::default()
        }
    }

    /// With the tool known exactly, on a map that is the measurement's noise alone (the part is
    /// flat): a plan that removes the map's noise (`h = z`) leaves the noise on the part with the
    /// opposite sign, and the next reading adds its own: `√2 σ`. A plan that removes nothing
    /// leaves the flat part as it is, and the next reading reads its noise: `σ`, none imprinted.
    #[test]
    fn a_plan_that_follows_the_noise_imprints_it() {
        let sigma = 0.3;
        let (x, y, z, motion, tif) = case(sigma);
        let map_rms = HeightStats::of(&z).rms_nm;
        let u = exact_tool(map_rms);
        let follows = expected_reading(&x, &y, &z, &z, &motion, &tif, &u, 32, 1).unwrap();
        assert!(follows.nominal_rms_nm < 1e-9, "{follows:?}");
        assert!(
            (follows.parts.noise_imprint_nm - map_rms).abs() < 1e-12,
            "{follows:?}"
        );
        let root2 = std::f64::consts::SQRT_2 * map_rms;
        assert!(
            (follows.expected_rms_nm - root2).abs() <= DRAW_TOL * root2,
            "{follows:?}"
        );
        assert_eq!(follows.parts.cause(), FloorCause::Noise);

        let idle =
            expected_reading(&x, &y, &z, &vec![0.0; z.len()], &motion, &tif, &u, 32, 1).unwrap();
        assert!((idle.nominal_rms_nm - map_rms).abs() < 1e-12, "{idle:?}");
        assert_eq!(idle.parts.noise_imprint_nm, 0.0, "{idle:?}");
        assert!(
            (idle.expected_rms_nm - map_rms).abs() <= DRAW_TOL * map_rms,
            "{idle:?}"
        );
        assert_eq!(idle.parts.cause(), FloorCause::Noise);
    }
}
