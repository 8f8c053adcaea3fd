//! NC output for CAM: tool-centre positions along the surface normal, the per-point CSV and a
//! G-code program that delivers every dwell.
//!
//! The tool centre of a spherical (or plane-faced, radius `r`) tool touching the part at `P` with
//! unit normal `n` is `A = P + r n / |n|`; with normal-displacement compensation
//! ([`super::compensation`]) it moves towards the part by `delta`: `A = P + (r - delta) n`.
//! The optional tool-axis angle `B` is fixed or follows the normal, `B = atan2(nx, nz)` (degrees,
//! rotation about y).
//!
//! Dwell point `j` owns the stretch of path from the midpoint of the segment before it to the
//! midpoint of the segment after it (the first and last points own a stretch extended straight
//! beyond the path end by half a segment: run-in and run-out), as the engine assumes
//! ([`crate::path::DwellPath::ds_mm`]). The program crosses each stretch in two blocks, boundary
//! to point and point to boundary, at one feed: both blocks' programmed times add up to `t_j`
//! whatever the neighbouring feeds, computed from the coordinates as written (4 decimals) and the
//! programmed path length of the dialect ([`super::gcode::dialect`]), the 3-D tool-centre move on
//! curved parts. The writer itself is [`super::gcode::write`].

use super::compensation::NormalDisplacement;
use super::feeds::FeedSchedule;
use super::gcode::dialect::{Dialect, FeedMode};
use super::words::{
    check_block, Coolant, SpindleDirection, WorkOffset, MAX_DECIMALS, MIN_DECIMALS,
};
use super::PartGeometry;
use crate::error::{Error, Result};
use crate::path::DwellPath;
use serde::{Deserialize, Serialize};
use std::io::Write;

/// Largest arc tolerance, mm: half the reader's start/end radius limit
/// ([`super::gcode::program::ARC_RADIUS_TOLERANCE_MM`]).
pub const MAX_ARC_TOLERANCE_MM: f64 = 0.5 * super::gcode::program::ARC_RADIUS_TOLERANCE_MM;

/// Decimal places of X, Y, Z and B in the program (0.1 um, 0.0001 deg).
pub const COORD_DECIMALS: usize = 4;

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
    /// Corner angle, degrees, for stops and lines (see [`crate::kinematics`]).
    pub corner_angle_deg: f64,
    /// Normal-displacement compensation; none when absent.
    pub compensation: Option<NormalDisplacement>,
    /// Controller dialect of the program.
    pub dialect: Dialect,
    /// `G94` feeds in mm/min or `G93` inverse time.
    pub feed_mode: FeedMode,
    /// Height of the clearance plane above the highest tool-centre position of the program, mm:
    /// rapid there, above the first point, plunge at `plunge_feed_mm_per_min`, retract at the end.
    pub clearance_mm: f64,
    /// Feed of the plunge from the clearance plane to the run-in start, mm/min.
    pub plunge_feed_mm_per_min: f64,
    /// Shortest block the controller can run, ms: a shorter feed block is an error naming it.
    pub min_block_time_ms: f64,
    /// Fastest feed the machine allows, mm/min: a stretch whose tool-centre move would need more
    /// is programmed at this feed (taking longer than planned, reported); none: no limit.
    pub v_max_mm_per_min: Option<f64>,
    /// Spindle (tool rotation) speed, rpm: `S<rpm> M3` (whole rpm) after the preamble, `M5` at
    /// the end.
    pub spindle_rpm: Option<f64>,
    /// Coolant or slurry during the program (`M8` or `M7`), off (`M9`) at the end; `true` and
    /// `false` are read as flood and off.
    pub coolant: Coolant,
    /// Write `G02`/`G03` where the tool-centre path is a circular arc within this tolerance, mm
    /// ([`super::gcode::write`]); none: straight moves only.
    pub arc_tolerance_mm: Option<f64>,
    /// Work offset selected after the start blocks.
    pub work_offset: WorkOffset,
    /// Blocks written first (none: the dialect's safe-start block, [`Dialect::safe_start`]).
    pub start_blocks: Option<Vec<String>>,
    /// Blocks written just before the program end word.
    pub end_blocks: Vec<String>,
    /// Spindle direction (`M3` or `M4`) when `spindle_rpm` is set.
    pub spindle_direction: SpindleDirection,
    /// Fanuc program number (`O` word), 1 to 9999.
    pub program_number: u32,
    /// Sinumerik program name (`%_N_<NAME>_MPF`).
    pub program_name: String,
    /// Decimals of X, Y, Z, B, I and J ([`MIN_DECIMALS`] to [`MAX_DECIMALS`]).
    pub decimals: usize,
}

impl Default for NcSettings {
    fn default() -> Self {
        Self {
            tool_radius_mm: 0.0,
            tool_axis: ToolAxis::Vertical,
            a_max_mm_per_s2: None,
            corner_angle_deg: crate::kinematics::DEFAULT_CORNER_ANGLE_DEG,
            compensation: None,
            dialect: Dialect::Iso,
            feed_mode: FeedMode::PerMinute,
            clearance_mm: 5.0,
            plunge_feed_mm_per_min: 300.0,
            min_block_time_ms: 2.0,
            v_max_mm_per_min: None,
            spindle_rpm: None,
            coolant: Coolant::Off,
            arc_tolerance_mm: None,
            work_offset: WorkOffset::G54,
            start_blocks: None,
            end_blocks: Vec::new(),
            spindle_direction: SpindleDirection::Cw,
            program_number: 1000,
            program_name: "PRESTON".into(),
            decimals: COORD_DECIMALS,
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
        crate::kinematics::check_corner_angle_deg(self.corner_angle_deg)?;
        if let Some(c) = &self.compensation {
            c.validate()?;
        }
        Error::require_positive(&[
            ("clearance_mm", self.clearance_mm),
            ("plunge_feed_mm_per_min", self.plunge_feed_mm_per_min),
        ])?;
        if !(self.min_block_time_ms.is_finite() && self.min_block_time_ms >= 0.0) {
            return Err(Error::invalid(
                "min_block_time_ms",
                format!("must be >= 0, got {}", self.min_block_time_ms),
            ));
        }
        if let Some(v) = self.v_max_mm_per_min {
            Error::require_positive(&[("v_max_mm_per_min", v)])?;
        }
        if let Some(s) = self.spindle_rpm {
            Error::require_positive(&[("spindle_rpm", s)])?;
        }
        if let Some(t) = self.arc_tolerance_mm {
            let most = MAX_ARC_TOLERANCE_MM;
            if !(t.is_finite() && t > 0.0 && t <= most) {
                return Err(Error::invalid(
                    "arc_tolerance_mm",
                    format!("must be in (0, {most}] mm, got {t}"),
                ));
            }
        }
        if !(MIN_DECIMALS..=MAX_DECIMALS).contains(&self.decimals) {
            return Err(Error::invalid(
                "decimals",
                format!(
                    "must be {MIN_DECIMALS} to {MAX_DECIMALS}, got {}",
                    self.decimals
                ),
            ));
        }
        if !self.work_offset.valid_in(self.dialect) {
            return Err(Error::invalid(
                "work_offset",
                format!(
                    "{} is not a settable work offset on {} (G54 to G57)",
                    self.work_offset.word().unwrap_or("none"),
                    self.dialect.name()
                ),
            ));
        }
        if !(1..=9999).contains(&self.program_number) {
            return Err(Error::invalid(
                "program_number",
                format!("must be 1 to 9999, got {}", self.program_number),
            ));
        }
        let name = &self.program_name;
        let ok = name.len() <= 24
            && name.len() >= 2
            && name.chars().take(2).all(|c| c.is_ascii_alphabetic())
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !ok {
            return Err(Error::invalid(
                "program_name",
                format!(
                    "'{name}': two letters, then letters, digits or '_', at most 24 characters"
                ),
            ));
        }
        for b in self.start_blocks.iter().flatten() {
            check_block("start_blocks", b, self.dialect)?;
        }
        for b in &self.end_blocks {
            check_block("end_blocks", b, self.dialect)?;
        }
        Ok(())
    }

    /// The start blocks as written: the given ones, or the dialect's safe-start block.
    pub fn start_blocks_or_default(&self) -> Vec<String> {
        match &self.start_blocks {
            Some(b) => b.clone(),
            None => vec![self.dialect.safe_start().to_string()],
        }
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
    /// Feed at the point, `60 ds_j / t_j` on the planar path, mm/min.
    pub feed_mm_per_min: f64,
}

/// A tool pose at a stretch boundary.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoundaryPose {
    /// Contact point x, mm.
    pub x_mm: f64,
    /// Contact point y, mm.
    pub y_mm: f64,
    /// Tool centre, mm.
    pub tool_mm: [f64; 3],
    /// Tool-axis angle, degrees, when written.
    pub b_deg: Option<f64>,
}

/// A planned NC program: points and feeds.
#[derive(Debug, Clone, PartialEq)]
pub struct NcProgram {
    /// The points in path order.
    pub points: Vec<NcPoint>,
    /// Stretch boundaries: `n + 1` poses, boundary `j` between stretches `j - 1` and `j` (the
    /// run-in start first, the run-out end last).
    pub boundaries: Vec<BoundaryPose>,
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
        let pose = Poser { geometry, settings };
        let mut points = Vec::with_capacity(path.len());
        for (j, (&x, &y)) in path.x_mm().iter().zip(path.y_mm()).enumerate() {
            let (z, n, delta, tool, b_deg) = pose.at(x, y, j)?;
            points.push(NcPoint {
                x_mm: x,
                y_mm: y,
                z_mm: z,
                normal: n,
                tool_mm: tool,
                b_deg,
                delta_mm: delta,
                dwell_s: dwell_s[j],
                feed_mm_per_min: schedule.point_feed_mm_per_min[j],
            });
        }
        let boundaries = stretch_boundaries(&pose, &points)?;
        Ok(Self {
            points,
            boundaries,
            schedule,
            settings: settings.clone(),
        })
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

/// Tool poses on the part.
struct Poser<'a> {
    geometry: &'a dyn PartGeometry,
    settings: &'a NcSettings,
}

impl Poser<'_> {
    /// Sag, unit normal, normal displacement, tool centre and `B` at contact point `(x, y)`;
    /// `j` names the dwell point in errors.
    #[allow(clippy::type_complexity)]
    fn at(&self, x: f64, y: f64, j: usize) -> Result<(f64, [f64; 3], f64, [f64; 3], Option<f64>)> {
        let g = self.geometry;
        let z = g.sag_mm(x, y)?;
        let n = unit(g.unit_normal(x, y)?, j)?;
        let delta = match &self.settings.compensation {
            Some(c) => c.at(g.curvature_radius_mm(x, y)?)?.delta_mm,
            None => 0.0,
        };
        let off = self.settings.tool_radius_mm - delta;
        let b_deg = match self.settings.tool_axis {
            ToolAxis::Vertical => None,
            ToolAxis::Fixed { b_deg } => Some(b_deg),
            ToolAxis::Normal => Some(n[0].atan2(n[2]).to_degrees()),
        };
        Ok((
            z,
            n,
            delta,
            [x + off * n[0], y + off * n[1], z + off * n[2]],
            b_deg,
        ))
    }
}

/// The `n + 1` stretch boundaries of `points` (module documentation): segment midpoints inside,
/// half a segment beyond each end. Each boundary is posed on the surface; a run-in or run-out
/// point outside the surface's domain is extrapolated straight from the end point's pose.
fn stretch_boundaries(pose: &Poser, points: &[NcPoint]) -> Result<Vec<BoundaryPose>> {
    let n = points.len();
    let at = |x: f64, y: f64, j: usize| -> Result<BoundaryPose> {
        let (_, _, _, tool_mm, b_deg) = pose.at(x, y, j)?;
        Ok(BoundaryPose {
            x_mm: x,
            y_mm: y,
            tool_mm,
            b_deg,
        })
    };
    let own = |p: &NcPoint| BoundaryPose {
        x_mm: p.x_mm,
        y_mm: p.y_mm,
        tool_mm: p.tool_mm,
        b_deg: p.b_deg,
    };
    if n < 2 {
        return Ok(points.iter().flat_map(|p| [own(p), own(p)]).collect());
    }
    let mut out = Vec::with_capacity(n + 1);
    out.push(own(&points[0]));
    for j in 1..n {
        let (a, b) = (&points[j - 1], &points[j]);
        out.push(at(0.5 * (a.x_mm + b.x_mm), 0.5 * (a.y_mm + b.y_mm), j)?);
    }
    out.push(own(&points[n - 1]));
    // Run-in and run-out: half a segment beyond the end, on the surface where it is defined.
    let beyond = |end: &NcPoint, inner: &BoundaryPose, j: usize| -> BoundaryPose {
        let (x, y) = (2.0 * end.x_mm - inner.x_mm, 2.0 * end.y_mm - inner.y_mm);
        at(x, y, j).unwrap_or(BoundaryPose {
            x_mm: x,
            y_mm: y,
            tool_mm: [
                2.0 * end.tool_mm[0] - inner.tool_mm[0],
                2.0 * end.tool_mm[1] - inner.tool_mm[1],
                2.0 * end.tool_mm[2] - inner.tool_mm[2],
            ],
            b_deg: match (end.b_deg, inner.b_deg) {
                (Some(a), Some(b)) => Some(2.0 * a - b),
                (a, _) => a,
            },
        })
    };
    out[0] = beyond(&points[0], &out[1], 0);
    out[n] = beyond(&points[n - 1], &out[n - 1], n - 1);
    Ok(out)
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
        // Boundaries: run-in half a segment before, the midpoint, run-out half a segment after.
        let bx: Vec<f64> = prog.boundaries.iter().map(|b| b.tool_mm[0]).collect();
        assert_eq!(bx, vec![-0.5, 0.5, 1.5]);
        let mut out = Vec::new();
        prog.write_gcode(&mut out).unwrap();
        let text = String::from_utf8(out).unwrap();
        // Each stretch is 1 mm long and takes 0.1 s: F = 600 mm/min on both of its blocks.
        assert!(
            text.contains("G01 X0.0000 Y2.0000 Z5.0000 F600.000\n"),
            "{text}"
        );
        assert!(text.contains("G01 X1.5000 Y2.0000 Z5.0000 F600.000\n"));
        assert!(
            text.contains("(DWELL 1 0.1000000 S AT 1.0000 2.0000)"),
            "{text}"
        );
        assert!(text.trim_end().ends_with("M30\n%"));
    }
}
