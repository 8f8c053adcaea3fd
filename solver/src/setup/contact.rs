//! The removal of a contact motion on the set-up's part: samples `p_k` of the motion carrying
//! time `tau_k`, `h_i = sum_k f_k(x_i - p_k) tau_k`, summed directly (a motion's samples are used
//! once). On a flat part `f_k` is the TIF in plan ([`crate::influence::model::direct`]), the samples that
//! share an offset from the map's lattice as lattice products ([`super::motion_lattice`]); on a curved
//! part each sample applies the TIF in its own tangent frame of the design surface, oriented as
//! the plan's columns are ([`crate::influence::model::surface::removals_on_surface_with`]), with the
//! sample's own Hertz TIF where the TIF depends on the curvature. Either way a sample that stands
//! for a piece of motion is integrated along it by the one rule of every piece
//! ([`crate::influence::model::piece::piece_rate`]), on a curved part in its tangent frame. The same under the
//! [`Perturbation`]s of the sensitivity: a tool offset moves the samples in plan, where the
//! curved part's frames are then taken.

use super::sensitivity::Perturbation;
use super::{Setup, TifModel};
use crate::error::Result;
use crate::influence::model::curvature::{hertz_tifs_on_surface, largest_support_radius_mm};
use crate::influence::model::direct::piece_removals_nm;
use crate::influence::model::piece::piece_rate;
use crate::influence::model::surface::removals_on_surface_with;
use crate::influence::Stretches;
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::simulate::SampledProgram;
use crate::tif::InfluenceFunction;

impl Setup {
    /// The removal of the motion `samples` at the measured map points, nm.
    pub(super) fn contact_removal(
        &self,
        samples: &SampledProgram,
        observer: &dyn Observer,
    ) -> Result<Vec<f64>> {
        let mut h = self.contact_removals(samples, &[Perturbation::NONE], observer)?;
        Ok(h.pop().unwrap_or_default())
    }

    /// The removals of the motion `samples` at the measured map points under each of
    /// `scenarios`, nm, in their order (module documentation).
    pub(super) fn contact_removals(
        &self,
        samples: &SampledProgram,
        scenarios: &[Perturbation],
        observer: &dyn Observer,
    ) -> Result<Vec<Vec<f64>>> {
        let (mx, my) = (self.map.x_mm(), self.map.y_mm());
        let Some(surface) = &self.surface else {
            if let TifModel::CurvatureDependent(_) = self.tif_model {
                return Err(crate::error::Error::invalid(
                    "TIF model",
                    "a curvature-dependent TIF needs a design surface",
                ));
            }
            // Samples at a common offset from the map's lattice as lattice products, the rest
            // summed directly (the direct sum to rounding).
            return super::motion_lattice::removals_in_plan_on_lattice(
                mx, my, samples, &self.tif, scenarios, observer,
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
            let hertz = match &self.tif_model {
                TifModel::ShiftInvariant => None,
                TifModel::CurvatureDependent(params) => {
                    Some(hertz_tifs_on_surface(surface, &x, &y, params)?)
                }
            };
            let radii: Vec<f64> = (0..group.len())
                .map(|s| match &hertz {
                    None => at(s).of(&self.tif).support_radius_mm(),
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
                    None => piece_rate(&at(s).of(&self.tif), half, u, w),
                    Some(h) => h
                        .get(k)
                        .map_or(0.0, |t| piece_rate(&at(s).of(t), half, u, w)),
                },
                self.tif_frame,
                observer,
            )?;
            for (&s, h) in group.iter().zip(removals) {
                out[s] = h;
                done[s] = true;
            }
        }
        Ok(out)
    }

    /// The motion of the plan `dwell_s` at its programmed feeds ([`path_motion`] of the
    /// set-up's path, with its stretches under the swept model).
    pub(super) fn plan_motion(&self, dwell_s: &[f64]) -> SampledProgram {
        path_motion(&self.path, self.swept.as_ref().map(|s| &s.0), dwell_s)
    }
}

/// The removals of the motion `samples` with `tif` in plan (a flat part) at the map points
/// `(map_x_mm, map_y_mm)` under each of `scenarios`: an offset is the TIF's own shift, so one
/// traversal serves them all, each sample along the piece it stands for ([`piece_removals_nm`]).
pub(super) fn removals_in_plan<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    samples: &SampledProgram,
    tif: &T,
    scenarios: &[Perturbation],
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>> {
    let tifs: Vec<_> = scenarios.iter().map(|p| p.of(tif)).collect();
    let refs: Vec<&dyn InfluenceFunction> =
        tifs.iter().map(|t| t as &dyn InfluenceFunction).collect();
    piece_removals_nm(
        map_x_mm,
        map_y_mm,
        &samples.x_mm,
        &samples.y_mm,
        &samples.half_mm,
        &samples.dwell_s,
        &refs,
        observer,
    )
}

/// Appends dwell point `j`'s stretch on `path` carrying `dwell_s` to `motion`: its samples, each
/// the piece it stands for ([`Stretches::pieces_of`]), carrying the dwell in proportion to their
/// weights.
pub(super) fn push_stretch(
    motion: &mut SampledProgram,
    path: &DwellPath,
    stretches: &Stretches,
    j: usize,
    dwell_s: f64,
) {
    for (&[dx, dy, w], &half) in stretches.of(j).iter().zip(stretches.pieces_of(j)) {
        motion.x_mm.push(path.x_mm()[j] + dx);
        motion.y_mm.push(path.y_mm()[j] + dy);
        motion.dwell_s.push(dwell_s * w);
        motion.half_mm.push(half);
    }
}

/// The motion of dwell times `dwell_s` on `path` at their programmed feeds: each dwell point's
/// stretch samples, each the piece it stands for, carrying its dwell in proportion to their
/// weights (swept model, `stretches`, [`push_stretch`]), or the dwell points themselves (point
/// model).
pub(super) fn path_motion(
    path: &DwellPath,
    stretches: Option<&Stretches>,
    dwell_s: &[f64],
) -> SampledProgram {
    match stretches {
        Some(stretches) => {
            let mut motion = SampledProgram {
                x_mm: Vec::new(),
                y_mm: Vec::new(),
                dwell_s: Vec::new(),
                half_mm: Vec::new(),
            };
            for (j, &tj) in dwell_s.iter().enumerate() {
                push_stretch(&mut motion, path, stretches, j, tj);
            }
            motion
        }
        None => SampledProgram {
            x_mm: path.x_mm().to_vec(),
            y_mm: path.y_mm().to_vec(),
            dwell_s: dwell_s.to_vec(),
            half_mm: Vec::new(),
        },
    }
}
