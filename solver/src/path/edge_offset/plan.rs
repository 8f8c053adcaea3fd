//! The lifting-bonnet plan: spot radii shrinking towards the edge, the pressing depth of each,
//! and the spacing of the lines for an equal residual (scallop) height.

use crate::error::{Error, Result};
use crate::tif::bonnet::depth_for_spot_mm;
use serde::{Deserialize, Serialize};

/// How the spot radius shrinks towards the edge.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum SpotProgression {
    /// `r_k = q^k r_max`, `0 < q < 1`.
    Geometric {
        /// Ratio q.
        ratio: f64,
    },
    /// `r_k = r_max - k d`.
    Arithmetic {
        /// Decrement d, mm.
        decrement_mm: f64,
    },
}

/// Settings of the edge-offset trajectory (lengths mm).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EdgeOffsetSettings {
    /// Bonnet radius R, mm.
    pub bonnet_radius_mm: f64,
    /// Spot radius of the innermost line, mm.
    pub spot_max_mm: f64,
    /// Smallest spot radius, mm.
    pub spot_min_mm: f64,
    /// Progression of spot radii.
    pub progression: SpotProgression,
    /// Residual (scallop) height between lines, mm.
    pub residual_height_mm: f64,
    /// How far the edge-most spot may overhang the edge, mm (0: tangent to it).
    pub overhang_mm: f64,
    /// Bezier fit tolerance, mm.
    pub bezier_tolerance_mm: f64,
    /// Point spacing along the offset curves, mm.
    pub step_mm: f64,
}

impl Default for EdgeOffsetSettings {
    fn default() -> Self {
        Self {
            bonnet_radius_mm: 20.0,
            spot_max_mm: 6.0,
            spot_min_mm: 1.5,
            progression: SpotProgression::Geometric { ratio: 0.8 },
            residual_height_mm: 1e-3,
            overhang_mm: 0.0,
            bezier_tolerance_mm: 0.01,
            step_mm: 0.5,
        }
    }
}

impl EdgeOffsetSettings {
    /// Checks ranges: positive lengths, `spot_min <= spot_max < R`, residual below `spot_min`,
    /// ratio in (0, 1) or a positive decrement, overhang in `[0, spot_min)`.
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("edge-offset bonnet_radius_mm", self.bonnet_radius_mm),
            ("edge-offset spot_max_mm", self.spot_max_mm),
            ("edge-offset spot_min_mm", self.spot_min_mm),
            ("edge-offset residual_height_mm", self.residual_height_mm),
            ("edge-offset bezier_tolerance_mm", self.bezier_tolerance_mm),
            ("edge-offset step_mm", self.step_mm),
        ])?;
        if !(self.spot_min_mm <= self.spot_max_mm && self.spot_max_mm < self.bonnet_radius_mm) {
            return Err(Error::invalid(
                "edge-offset spot radii",
                format!(
                    "need spot_min <= spot_max < bonnet radius, got {} <= {} < {}",
                    self.spot_min_mm, self.spot_max_mm, self.bonnet_radius_mm
                ),
            ));
        }
        if self.residual_height_mm >= self.spot_min_mm {
            return Err(Error::invalid(
                "edge-offset residual_height_mm",
                "must be below the smallest spot radius",
            ));
        }
        if !(self.overhang_mm.is_finite()
            && self.overhang_mm >= 0.0
            && self.overhang_mm < self.spot_min_mm)
        {
            return Err(Error::invalid(
                "edge-offset overhang_mm",
                format!("must be in [0, spot_min), got {}", self.overhang_mm),
            ));
        }
        match self.progression {
            SpotProgression::Geometric { ratio } if !(ratio > 0.0 && ratio < 1.0) => {
                Err(Error::invalid(
                    "edge-offset ratio",
                    format!("must be in (0, 1), got {ratio}"),
                ))
            }
            SpotProgression::Arithmetic { decrement_mm }
                if !(decrement_mm.is_finite() && decrement_mm > 0.0) =>
            {
                Err(Error::invalid(
                    "edge-offset decrement_mm",
                    format!("must be positive, got {decrement_mm}"),
                ))
            }
            _ => Ok(()),
        }
    }

    /// Spot radii from `spot_max` down to no less than `spot_min`, mm.
    pub fn spot_radii_mm(&self) -> Result<Vec<f64>> {
        self.validate()?;
        let mut out = Vec::new();
        let mut k = 0usize;
        loop {
            let r = match self.progression {
                SpotProgression::Geometric { ratio } => self.spot_max_mm * ratio.powi(k as i32),
                SpotProgression::Arithmetic { decrement_mm } => {
                    self.spot_max_mm - k as f64 * decrement_mm
                }
            };
            if r < self.spot_min_mm * (1.0 - 1e-12) {
                break;
            }
            out.push(r);
            k += 1;
            if k > 10_000 {
                return Err(Error::invalid(
                    "edge-offset progression",
                    "more than 10000 offset lines",
                ));
            }
        }
        Ok(out)
    }
}

/// Half-width at which a circular profile of radius `r` reaches residual height `e`:
/// `sqrt(2 r e - e^2)`, mm.
pub fn residual_half_width_mm(spot_radius_mm: f64, residual_mm: f64) -> f64 {
    (2.0 * spot_radius_mm * residual_mm - residual_mm * residual_mm)
        .max(0.0)
        .sqrt()
}

/// One offset line of the trajectory.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OffsetLine {
    /// Spot radius, mm.
    pub spot_radius_mm: f64,
    /// Pressing depth giving that spot, mm.
    pub depth_mm: f64,
    /// Set distance of the tool centre inside the edge, mm.
    pub offset_mm: f64,
    /// Distance achieved by the corrected offset curve (mean over its points), mm.
    pub achieved_offset_mm: f64,
    /// Spacing to the next line towards the edge, mm (0 for the edge-most line).
    pub spacing_mm: f64,
}

/// Spot radii, depths, spacings and set offsets of the lines, innermost first.
pub fn plan_offsets(settings: &EdgeOffsetSettings) -> Result<Vec<OffsetLine>> {
    let radii = settings.spot_radii_mm()?;
    let e = settings.residual_height_mm;
    let n = radii.len();
    let mut lines: Vec<OffsetLine> = radii
        .iter()
        .map(|&r| {
            Ok(OffsetLine {
                spot_radius_mm: r,
                depth_mm: depth_for_spot_mm(settings.bonnet_radius_mm, r).ok_or_else(|| {
                    Error::invalid("edge-offset spot radius", "larger than the bonnet")
                })?,
                offset_mm: 0.0,
                achieved_offset_mm: 0.0,
                spacing_mm: 0.0,
            })
        })
        .collect::<Result<_>>()?;
    let mut o = radii[n - 1] - settings.overhang_mm;
    lines[n - 1].offset_mm = o;
    for k in (0..n - 1).rev() {
        let d = residual_half_width_mm(radii[k], e) + residual_half_width_mm(radii[k + 1], e);
        lines[k].spacing_mm = d;
        o += d;
        lines[k].offset_mm = o;
    }
    Ok(lines)
}
