//! NC output for CAM: tool-centre positions along the surface normal, the per-point CSV and a
//! numbered G-code program.
//!
//! The tool centre of a spherical (or plane-faced, radius `r`) tool touching the part at `P` with
//! unit normal `n` is `A = P + r n / |n|`; with normal-displacement compensation
//! ([`super::compensation`]) it moves towards the part by `delta`: `A = P + (r - delta) n`.
//! The optional tool-axis angle `B` is fixed or follows the normal, `B = atan2(nx, nz)` (degrees,
//! rotation about y).
//!
//! G-code (ISO 6983 / RS-274 style):
//!
//! ```text
//! %
//! (PRESTON DWELL PROGRAM)
//! (UNITS MM, FEED MM/MIN, TIME S)
//! ( ... job summary ... )
//! N1 G21 G90 G94
//! N2 G01 X.. Y.. Z.. [B..] F..      first point at its own feed
//! N3 G01 X.. Y.. Z.. [B..] F..      move to the next point at the mean of the two point feeds
//! ...
//! Nk M30
//! %
//! ```

use super::compensation::NormalDisplacement;
use super::feeds::FeedSchedule;
use super::{fixed, PartGeometry};
use crate::error::{Error, Result};
use crate::path::DwellPath;
use serde::{Deserialize, Serialize};
use std::io::Write;

/// Decimal places of X, Y, Z and B in the program (0.1 um, 0.0001 deg).
pub const COORD_DECIMALS: usize = 4;
/// Decimal places of F (mm/min).
pub const FEED_DECIMALS: usize = 3;

/// Orientation of the tool axis written as the `B` word.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum ToolAxis {
    /// Vertical tool, no `B` word.
    #[default]
    Vertical,
    /// A fixed angle, degrees.
    Fixed {
        /// The angle, degrees.
        b_deg: f64,
    },
    /// Follows the surface normal: `B = atan2(nx, nz)`, degrees.
    Normal,
}

/// Settings of the NC output (a job-file section).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NcSettings {
    /// Tool radius, mm: the tool centre sits this far from the contact point along the normal.
    pub tool_radius_mm: f64,
    /// How the `B` word is written.
    pub tool_axis: ToolAxis,
    /// Machine acceleration, mm/s^2: adds ramps to the machining time in the header.
    pub a_max_mm_per_s2: Option<f64>,
    /// Corner angle, degrees, for stops and lines (see [`crate::dwell::accel`]).
    pub corner_angle_deg: f64,
    /// Normal-displacement compensation; none when absent.
    pub compensation: Option<NormalDisplacement>,
}

impl Default for NcSettings {
    fn default() -> Self {
        Self {
            tool_radius_mm: 0.0,
            tool_axis: ToolAxis::Vertical,
            a_max_mm_per_s2: None,
            corner_angle_deg: 60.0,
            compensation: None,
        }
    }
}

impl NcSettings {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        if !(self.tool_radius_mm.is_finite() && self.tool_radius_mm >= 0.0) {
            return Err(Error::invalid(
                "tool_radius_mm",
                format!("must be >= 0, got {}", self.tool_radius_mm),
            ));
        }
        if let ToolAxis::Fixed { b_deg } = self.tool_axis {
            if !b_deg.is_finite() {
                return Err(Error::invalid(
                    "b_deg",
                    format!("must be finite, got {b_deg}"),
                ));
            }
        }
        if !(0.0..=180.0).contains(&self.corner_angle_deg) {
            return Err(Error::invalid(
                "corner_angle_deg",
                format!("must be in [0, 180], got {}", self.corner_angle_deg),
            ));
        }
        if let Some(c) = &self.compensation {
            c.validate()?;
        }
        Ok(())
    }
}

/// One point of the program.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NcPoint {
    /// Contact point x, mm.
    pub x_mm: f64,
    /// Contact point y, mm.
    pub y_mm: f64,
    /// Contact point z (surface sag), mm.
    pub z_mm: f64,
    /// Unit surface normal `(nx, ny, nz)`.
    pub normal: [f64; 3],
    /// Tool centre `A = P + (r - delta) n`, mm.
    pub tool_mm: [f64; 3],
    /// Tool-axis angle, degrees, when written.
    pub b_deg: Option<f64>,
    /// Normal displacement applied, mm (0 without compensation).
    pub delta_mm: f64,
    /// Dwell time, s.
    pub dwell_s: f64,
    /// Feed at the point, mm/min.
    pub feed_mm_per_min: f64,
    /// Programmed feed of the move that ends here (the point's own feed for the first), mm/min.
    pub move_feed_mm_per_min: f64,
}

/// A planned NC program: points and feeds.
#[derive(Debug, Clone, PartialEq)]
pub struct NcProgram {
    /// The points in path order.
    pub points: Vec<NcPoint>,
    /// Feeds and machining time.
    pub schedule: FeedSchedule,
    /// The settings it was planned with.
    pub settings: NcSettings,
}

impl NcProgram {
    /// Plans the program for `dwell_s` on `path` over the part `geometry`.
    pub fn plan(
        path: &DwellPath,
        dwell_s: &[f64],
        geometry: &dyn PartGeometry,
        settings: &NcSettings,
    ) -> Result<Self> {
        settings.validate()?;
        let schedule = FeedSchedule::new(
            path,
            dwell_s,
            settings.a_max_mm_per_s2,
            settings.corner_angle_deg,
        )?;
        let mut points = Vec::with_capacity(path.len());
        for (j, (&x, &y)) in path.x_mm().iter().zip(path.y_mm()).enumerate() {
            let z = geometry.sag_mm(x, y)?;
            let n = unit(geometry.unit_normal(x, y)?, j)?;
            let delta = match &settings.compensation {
                Some(c) => c.at(geometry.curvature_radius_mm(x, y)?)?.delta_mm,
                None => 0.0,
            };
            let off = settings.tool_radius_mm - delta;
            let b_deg = match settings.tool_axis {
                ToolAxis::Vertical => None,
                ToolAxis::Fixed { b_deg } => Some(b_deg),
                ToolAxis::Normal => Some(n[0].atan2(n[2]).to_degrees()),
            };
            let feed = schedule.point_feed_mm_per_min[j];
            let move_feed = if j == 0 {
                feed
            } else {
                schedule.segment_feed_mm_per_min[j - 1]
            };
            points.push(NcPoint {
                x_mm: x,
                y_mm: y,
                z_mm: z,
                normal: n,
                tool_mm: [x + off * n[0], y + off * n[1], z + off * n[2]],
                b_deg,
                delta_mm: delta,
                dwell_s: dwell_s[j],
                feed_mm_per_min: feed,
                move_feed_mm_per_min: move_feed,
            });
        }
        Ok(Self {
            points,
            schedule,
            settings: settings.clone(),
        })
    }

    /// Writes the G-code program (see the module documentation).
    pub fn write_gcode(&self, w: &mut dyn Write) -> std::io::Result<()> {
        self.write_gcode_with_notes(&[], w)
    }

    /// As [`NcProgram::write_gcode`], with extra comment lines (the job summary: input files,
    /// surface) after the units line; parentheses in a note become brackets.
    pub fn write_gcode_with_notes(
        &self,
        notes: &[String],
        w: &mut dyn Write,
    ) -> std::io::Result<()> {
        let s = &self.schedule;
        let (f_lo, f_hi) = s.feed_range_mm_per_min();
        writeln!(w, "%")?;
        writeln!(w, "(PRESTON DWELL PROGRAM)")?;
        writeln!(w, "(UNITS MM, FEED MM/MIN, TIME S, ANGLE DEG)")?;
        for note in notes {
            let clean: String = note
                .chars()
                .map(|c| match c {
                    '(' => '[',
                    ')' => ']',
                    '\n' | '\r' => ' ',
                    c => c,
                })
                .collect();
            writeln!(w, "({clean})")?;
        }
        writeln!(w, "(POINTS {})", self.points.len())?;
        writeln!(
            w,
            "(TOOL RADIUS {} MM, TOOL CENTRE = CONTACT + R * NORMAL)",
            fixed(self.settings.tool_radius_mm, COORD_DECIMALS)
        )?;
        if self.settings.compensation.is_some() {
            let (lo, hi) = self
                .points
                .iter()
                .fold((f64::INFINITY, 0.0f64), |(a, b), p| {
                    (a.min(p.delta_mm), b.max(p.delta_mm))
                });
            writeln!(
                w,
                "(NORMAL DISPLACEMENT {} .. {} MM)",
                fixed(lo, COORD_DECIMALS),
                fixed(hi, COORD_DECIMALS)
            )?;
        }
        writeln!(w, "(TOTAL DWELL {} S)", fixed(s.total_dwell_s, 3))?;
        match self.settings.a_max_mm_per_s2 {
            Some(a) => writeln!(
                w,
                "(MACHINING TIME {} S WITH RAMPS AT {} MM/S2)",
                fixed(s.machining_time_s, 3),
                fixed(a, 1)
            )?,
            None => writeln!(w, "(MACHINING TIME {} S)", fixed(s.machining_time_s, 3))?,
        }
        writeln!(
            w,
            "(FEED {} .. {} MM/MIN)",
            fixed(f_lo, FEED_DECIMALS),
            fixed(f_hi, FEED_DECIMALS)
        )?;
        writeln!(w, "N1 G21 G90 G94")?;
        let mut k = 2usize;
        for p in &self.points {
            write!(
                w,
                "N{k} G01 X{} Y{} Z{}",
                fixed(p.tool_mm[0], COORD_DECIMALS),
                fixed(p.tool_mm[1], COORD_DECIMALS),
                fixed(p.tool_mm[2], COORD_DECIMALS)
            )?;
            if let Some(b) = p.b_deg {
                write!(w, " B{}", fixed(b, COORD_DECIMALS))?;
            }
            writeln!(w, " F{}", fixed(p.move_feed_mm_per_min, FEED_DECIMALS))?;
            k += 1;
        }
        writeln!(w, "N{k} M30")?;
        writeln!(w, "%")
    }

    /// Writes the point list `x_mm,y_mm,z_mm,nx,ny,nz,dwell_s,feed_mm_per_min` (contact points,
    /// unit normals, dwell and point feed; shortest round-trip numbers).
    pub fn write_points_csv(&self, w: &mut dyn Write) -> std::io::Result<()> {
        writeln!(w, "x_mm,y_mm,z_mm,nx,ny,nz,dwell_s,feed_mm_per_min")?;
        for p in &self.points {
            writeln!(
                w,
                "{},{},{},{},{},{},{},{}",
                p.x_mm,
                p.y_mm,
                p.z_mm,
                p.normal[0],
                p.normal[1],
                p.normal[2],
                p.dwell_s,
                p.feed_mm_per_min
            )?;
        }
        Ok(())
    }
}

/// Normalises `n`; a zero or non-finite normal is an error naming the point.
fn unit(n: [f64; 3], j: usize) -> Result<[f64; 3]> {
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if !(len.is_finite() && len > 0.0) {
        return Err(Error::Geometry(format!(
            "dwell point {j}: surface normal {n:?} cannot be normalised"
        )));
    }
    Ok([n[0] / len, n[1] / len, n[2] / len])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::machine::Flat;

    #[test]
    fn flat_offsets_straight_up() {
        let p = DwellPath::new(vec![0.0, 1.0], vec![2.0, 2.0]).unwrap();
        let s = NcSettings {
            tool_radius_mm: 5.0,
            ..NcSettings::default()
        };
        let prog = NcProgram::plan(&p, &[0.1, 0.1], &Flat, &s).unwrap();
        assert_eq!(prog.points[1].tool_mm, [1.0, 2.0, 5.0]);
        let mut out = Vec::new();
        prog.write_gcode(&mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        assert!(
            text.contains("N3 G01 X1.0000 Y2.0000 Z5.0000 F600.000"),
            "{text}"
        );
        assert!(text.contains("N4 M30"));
    }
}
