//! A machine profile: what a shop knows about one machine and its controller, written once and
//! shared by every job that runs on it (`[nc]` of a job file, or of a profile file that also holds
//! `[machine]`).
//!
//! ```toml
//! [nc]
//! dialect = "fanuc"                  # iso, linuxcnc, fanuc, sinumerik
//! feed_mode = "inverse-time"         # per-minute (G94) or inverse-time (G93)
//! work_offset = "g54"                # g54 .. g59 (Sinumerik: g54 .. g57), or "none"
//! start_blocks = ["G17 G21 G40 G49 G80 G90 G94"]   # default: the dialect's safe-start block
//! end_blocks = []                    # written before the program end word
//! clearance_mm = 5.0
//! plunge_feed_mm_per_min = 300.0
//! min_block_time_ms = 2.0
//! spindle_rpm = 600.0                # S600 M3 at the start, M5 at the end
//! spindle_direction = "cw"           # cw (M3) or ccw (M4)
//! coolant = "flood"                  # off, flood (M8) or mist (M7); M9 at the end
//! program_number = 1000              # Fanuc O number
//! program_name = "PRESTON"           # Sinumerik %_N_<NAME>_MPF
//! decimals = 4                       # of X Y Z B I J (Fanuc IS-B: 3)
//! tool_radius_mm = 5.0
//! tool_axis = { type = "fixed", b_deg = 10.0 }   # or { type = "normal" }, { type = "vertical" }
//! arc_tolerance_um = 1.0             # write G02/G03 where the path is a circular arc
//! ```
//!
//! Each key may be overridden on the command line; a job's keys override its profile file's.

use super::gcode::dialect::{Dialect, FeedMode};
use super::nc::{NcSettings, ToolAxis};
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

pub use super::words::{
    check_block, Coolant, SpindleDirection, WorkOffset, MAX_BLOCK_CHARS, MAX_DECIMALS, MIN_DECIMALS,
};

/// The machine profile (module documentation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MachineProfile {
    /// Controller dialect.
    pub dialect: Dialect,
    /// `G94` feeds in mm/min or `G93` inverse time.
    pub feed_mode: FeedMode,
    /// Work offset selected at the start.
    pub work_offset: WorkOffset,
    /// Blocks written first (none: the dialect's safe-start block, [`Dialect::safe_start`]).
    pub start_blocks: Option<Vec<String>>,
    /// Blocks written just before the program end word.
    pub end_blocks: Vec<String>,
    /// Height of the clearance plane above the highest tool-centre position, mm.
    pub clearance_mm: f64,
    /// Feed of the plunge from the clearance plane, mm/min.
    pub plunge_feed_mm_per_min: f64,
    /// Shortest block the controller runs, ms.
    pub min_block_time_ms: f64,
    /// Spindle speed, rpm (none: no spindle words).
    pub spindle_rpm: Option<f64>,
    /// Spindle direction.
    pub spindle_direction: SpindleDirection,
    /// Coolant or slurry.
    pub coolant: Coolant,
    /// Fanuc program number (`O` word), 1 to 9999.
    pub program_number: u32,
    /// Sinumerik program name (`%_N_<NAME>_MPF`): two letters, then letters, digits or `_`, at
    /// most 24 characters.
    pub program_name: String,
    /// Decimals of the coordinates and centre offsets, [`MIN_DECIMALS`] to [`MAX_DECIMALS`].
    pub decimals: usize,
    /// Tool radius, mm: tool centre `A = P + r n / |n|`.
    pub tool_radius_mm: f64,
    /// How the `B` word is written.
    pub tool_axis: ToolAxis,
    /// Write `G02`/`G03` where the tool-centre path is a circular arc within this tolerance, um.
    pub arc_tolerance_um: Option<f64>,
}

impl Default for MachineProfile {
    fn default() -> Self {
        let nc = NcSettings::default();
        Self {
            dialect: nc.dialect,
            feed_mode: nc.feed_mode,
            work_offset: nc.work_offset,
            start_blocks: nc.start_blocks,
            end_blocks: nc.end_blocks,
            clearance_mm: nc.clearance_mm,
            plunge_feed_mm_per_min: nc.plunge_feed_mm_per_min,
            min_block_time_ms: nc.min_block_time_ms,
            spindle_rpm: nc.spindle_rpm,
            spindle_direction: nc.spindle_direction,
            coolant: nc.coolant,
            program_number: nc.program_number,
            program_name: nc.program_name,
            decimals: nc.decimals,
            tool_radius_mm: nc.tool_radius_mm,
            tool_axis: nc.tool_axis,
            arc_tolerance_um: None,
        }
    }
}

impl MachineProfile {
    /// The NC settings of this profile, with the plan-side settings (acceleration, feed limit,
    /// compensation) at their defaults.
    pub fn nc_settings(&self) -> NcSettings {
        NcSettings {
            tool_radius_mm: self.tool_radius_mm,
            tool_axis: self.tool_axis,
            dialect: self.dialect,
            feed_mode: self.feed_mode,
            work_offset: self.work_offset,
            start_blocks: self.start_blocks.clone(),
            end_blocks: self.end_blocks.clone(),
            clearance_mm: self.clearance_mm,
            plunge_feed_mm_per_min: self.plunge_feed_mm_per_min,
            min_block_time_ms: self.min_block_time_ms,
            spindle_rpm: self.spindle_rpm,
            spindle_direction: self.spindle_direction,
            coolant: self.coolant,
            program_number: self.program_number,
            program_name: self.program_name.clone(),
            decimals: self.decimals,
            arc_tolerance_mm: self.arc_tolerance_um.map(|u| 1e-3 * u),
            ..NcSettings::default()
        }
    }

    /// Checks every field ([`NcSettings::validate`]).
    pub fn validate(&self) -> Result<()> {
        if let Some(u) = self.arc_tolerance_um {
            if !(u.is_finite() && u > 0.0) {
                return Err(Error::invalid(
                    "arc_tolerance_um",
                    format!("must be positive, got {u}"),
                ));
            }
        }
        self.nc_settings().validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_profile_is_the_default_settings() {
        let p = MachineProfile::default();
        p.validate().unwrap();
        assert_eq!(p.nc_settings(), NcSettings::default());
    }

    #[test]
    fn profiles_read_from_toml_and_refuse_bad_values() {
        let p: MachineProfile = toml::from_str(
            "dialect = 'fanuc'\nfeed_mode = 'inverse-time'\nwork_offset = 'g55'\ncoolant = true\n\
             spindle_rpm = 600\nprogram_number = 42\ndecimals = 3\n",
        )
        .unwrap();
        p.validate().unwrap();
        assert_eq!(p.coolant, Coolant::Flood);
        assert_eq!(p.work_offset, WorkOffset::G55);
        let s = p.nc_settings();
        assert_eq!(
            (s.dialect, s.feed_mode, s.decimals),
            (Dialect::Fanuc, FeedMode::InverseTime, 3)
        );
        for bad in [
            "decimals = 9",
            "program_number = 0",
            "program_name = '1X'",
            "dialect = 'sinumerik'\nwork_offset = 'g58'",
            "start_blocks = ['G0 X1']",
            "start_blocks = ['G90 (x)']",
            "end_blocks = ['M30']",
            "end_blocks = ['G90; M3']",
            "start_blocks = ['']",
            "arc_tolerance_um = -1",
        ] {
            let p: MachineProfile = toml::from_str(bad).unwrap();
            assert!(p.validate().is_err(), "{bad}");
        }
        assert!(toml::from_str::<MachineProfile>("coolant = 'soup'").is_err());
        assert!(toml::from_str::<MachineProfile>("dialekt = 'iso'").is_err());
    }
}
