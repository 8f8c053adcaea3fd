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
    /// Smallest distance of the line's points to the fitted edge less the spot radius, mm:
    /// how far the spot's rim stays inside the part (negative: it overhangs by that much).
    pub clearance_mm: f64,
    /// Spacing to the next line towards the edge, mm (0 for the edge-most line).
    pub spacing_mm: f64,
}

/// Spot radii, depths, spacings and set offsets of the lines, innermost first.
///
/// The edge-most line (spot `r_N`) sits at `o_N = r_N - overhang`; going inwards line `k`
/// sits at `o_k = max(o_{k+1} + d_k, r_k)` with `d_k = w(r_k) + w(r_{k+1})`
/// ([`residual_half_width_mm`]), so every spot lies inside the edge. Where containment
/// pushes line `k` further in than the equal-residual spacing, the gap is filled with lines of
/// the smaller spot `r_{k+1}` evenly spaced at most `2 w(r_{k+1})` apart (the last one `d_k`
/// from line `k`), so the
/// residual height between neighbours stays at most `e` and the spot still shrinks
/// monotonically towards the edge.
pub fn plan_offsets(settings: &EdgeOffsetSettings) -> Result<Vec<OffsetLine>> {
    let radii = settings.spot_radii_mm()?;
    let e = settings.residual_height_mm;
    let n = radii.len();
    let line = |r: f64, o: f64| -> Result<OffsetLine> {
        Ok(OffsetLine {
            spot_radius_mm: r,
            depth_mm: depth_for_spot_mm(settings.bonnet_radius_mm, r).ok_or_else(|| {
                Error::invalid("edge-offset spot radius", "larger than the bonnet")
            })?,
            offset_mm: o,
            achieved_offset_mm: 0.0,
            clearance_mm: 0.0,
            spacing_mm: 0.0,
        })
    };
    // Built edge-most first, reversed at the end.
    let mut o = radii[n - 1] - settings.overhang_mm;
    let mut out = vec![line(radii[n - 1], o)?];
    for k in (0..n - 1).rev() {
        let (r_in, r_out) = (radii[k], radii[k + 1]);
        let d = residual_half_width_mm(r_in, e) + residual_half_width_mm(r_out, e);
        let fill = 2.0 * residual_half_width_mm(r_out, e);
        if o + d < r_in {
            // Fill lines evenly spaced, at most `fill` apart, the last `d` from line `k`.
            let span = r_in - d - o;
            let m = (span / fill).ceil().max(1.0);
            if m > 100_000.0 {
                return Err(Error::invalid(
                    "edge-offset progression",
                    "more than 100000 fill lines keep the spots inside the edge",
                ));
            }
            let base = o;
            for j in 1..=m as usize {
                o = base + span * j as f64 / m;
                out.push(line(r_out, o)?);
            }
        }
        let next = (o + d).max(r_in);
        o = next;
        out.push(line(r_in, o)?);
    }
    out.reverse();
    let m = out.len();
    for i in 0..m {
        out[i].spacing_mm = if i + 1 < m {
            out[i].offset_mm - out[i + 1].offset_mm
        } else {
            0.0
        };
    }
    Ok(out)
}
