//! The removal of a contact motion on a part: samples `p_k` of the motion carrying time `tau_k`,
//! `h_i = sum_k f_k(x_i - p_k) tau_k`, summed directly (a motion's samples are used once). On a
//! flat part `f_k` is the TIF in plan ([`super::direct`]), the samples that share an offset from
//! the map's lattice as lattice products ([`super::motion_lattice`]); on a curved part each sample
//! applies the TIF in its own tangent frame of the design surface, oriented as the plan's columns
//! are ([`crate::influence::model::surface::removals_on_surface_with`]), with the sample's own
//! Hertz TIF where the TIF depends on the curvature. Either way a sample that stands for a piece
//! of motion is integrated along it by the one rule of every piece
//! ([`crate::influence::model::piece::piece_rate`]), on a curved part in its tangent frame. The
//! same under the [`Perturbation`]s of the sensitivity: a tool offset moves the samples in plan,
//! where the curved part's frames are then taken.

use super::SampledProgram;
use crate::error::Result;
use crate::influence::model::curvature::{hertz_tifs_on_surface, largest_support_radius_mm};
use crate::influence::model::piece::piece_rate;
use crate::influence::model::surface::{removals_on_surface_with, TifFrame};
use crate::observer::Observer;
use crate::surface::Surface;
use crate::tif::{HertzParams, InfluenceFunction, Perturbation, Tif};

/// The part a contact motion acts on: where its removal is wanted and how the tool removes there.
#[derive(Debug, Clone, Copy)]
pub struct ContactPart<'a> {
    /// x of the measured map points, mm.
    pub map_x_mm: &'a [f64],
    /// y of the measured map points, mm.
    pub map_y_mm: &'a [f64],
    /// The design surface; none: a flat part.
    pub surface: Option<&'a Surface>,
    /// The TIF, nm/s.
    pub tif: &'a Tif,
    /// Where the TIF depends on the curvature, the Hertz contact that gives each sample its own
    /// (needs a design surface); none: one TIF for every sample.
    pub hertz: Option<&'a HertzParams>,
    /// How the TIF is oriented in each sample's tangent frame on a curved part.
    pub frame: TifFrame,
}

/// The removal of the motion `samples` at the part's map points, nm (module documentation).
pub fn contact_removal(
    part: &ContactPart<'_>,
    samples: &SampledProgram,
    observer: &dyn Observer,
) -> Result<Vec<f64>> {
    let mut h = contact_removals(part, samples, &[Perturbation::NONE], observer)?;
    Ok(h.pop().unwrap_or_default())
}

/// The removals of the motion `samples` at the part's map points under each of `scenarios`, nm,
/// in their order (module documentation).
pub fn contact_removals(
    part: &ContactPart<'_>,
    samples: &SampledProgram,
    scenarios: &[Perturbation],
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>> {
    let (mx, my) = (part.map_x_mm, part.map_y_mm);
    let Some(surface) = part.surface else {
        if part.hertz.is_some() {
            return Err(crate::error::Error::invalid(
                "TIF model",
                "a curvature-dependent TIF needs a design surface",
            ));
        }
        // Samples at a common offset from the map's lattice as lattice products, the rest
        // summed directly (the direct sum to rounding).
        return super::motion_lattice::removals_in_plan_on_lattice(
            mx, my, samples, part.tif, scenarios, observer,
        );
    };
    let mut out = vec![Vec::new(); scenarios.len()];
    // One traversal per distinct offset, the samples moved by it.
    let mut done = vec![false; scenarios.len()];
    for first in 0..scenarios.len() {
        if done[first] {
            continue;
        }
        let (ox, oy) = scenarios[first].offset_mm;
        let group: Vec<usize> = (first..scenarios.len())
            .filter(|&s| !done[s] && scenarios[s].offset_mm == (ox, oy))
            .collect();
        let x: Vec<f64> = samples.x_mm.iter().map(|v| v + ox).collect();
        let y: Vec<f64> = samples.y_mm.iter().map(|v| v + oy).collect();
        let at = |s: usize| Perturbation {
            offset_mm: (0.0, 0.0),
            ..scenarios[group[s]]
        };
        // Where the TIF depends on the curvature, each sample's own where it lands.
        let hertz = match part.hertz {
            None => None,
            Some(params) => Some(hertz_tifs_on_surface(surface, &x, &y, params)?),
        };
        let radii: Vec<f64> = (0..group.len())
            .map(|s| match &hertz {
                None => at(s).of(part.tif).support_radius_mm(),
                Some(h) => at(s).width_factor * largest_support_radius_mm(h),
            })
            .collect();
        // Each sample along the piece it stands for, in its tangent frame, by the flat
        // part's rule.
        let removals = removals_on_surface_with(
            surface,
            mx,
            my,
            &x,
            &y,
            &samples.half_mm,
            &samples.dwell_s,
            &radii,
            |s, k, half, u, w| match &hertz {
                None => piece_rate(&at(s).of(part.tif), half, u, w),
                Some(h) => h
                    .get(k)
                    .map_or(0.0, |t| piece_rate(&at(s).of(t), half, u, w)),
            },
            part.frame,
            observer,
        )?;
        for (&s, h) in group.iter().zip(removals) {
            out[s] = h;
            done[s] = true;
        }
    }
    Ok(out)
}
