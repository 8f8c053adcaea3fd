//! The controller's words a program's settings choose: the work offset, the spindle direction,
//! the coolant, the coordinates' decimals and the user's own start and end blocks (checked by the
//! program reader). Shared by the machine profile ([`super::profile`]) and the NC settings
//! ([`super::nc`]).

use super::gcode::dialect::Dialect;
use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};

/// Work coordinate system selected at the start of the program.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum WorkOffset {
    /// `G54`, the first settable work offset.
    #[default]
    G54,
    /// `G55`.
    G55,
    /// `G56`.
    G56,
    /// `G57`.
    G57,
    /// `G58` (not a settable work offset on Sinumerik).
    G58,
    /// `G59` (not a settable work offset on Sinumerik).
    G59,
    /// No work-offset word: the controller's active offset stays.
    None,
}

impl WorkOffset {
    /// The G word, or `None` for [`WorkOffset::None`].
    pub fn word(self) -> Option<&'static str> {
        match self {
            WorkOffset::G54 => Some("G54"),
            WorkOffset::G55 => Some("G55"),
            WorkOffset::G56 => Some("G56"),
            WorkOffset::G57 => Some("G57"),
            WorkOffset::G58 => Some("G58"),
            WorkOffset::G59 => Some("G59"),
            WorkOffset::None => None,
        }
    }

    /// Whether `dialect` reads the word as a settable work offset: Sinumerik 840D's settable
    /// frames are `G54` to `G57` (`G58`, `G59` are programmable axial offsets there; Sinumerik
    /// 840D sl programming manual, fundamentals, "Settable zero offset").
    pub fn valid_in(self, dialect: Dialect) -> bool {
        !(dialect == Dialect::Sinumerik && matches!(self, WorkOffset::G58 | WorkOffset::G59))
    }
}

/// Direction of the spindle (tool rotation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpindleDirection {
    /// Clockwise seen from the spindle towards the part: `M3`.
    #[default]
    Cw,
    /// Counter-clockwise: `M4`.
    Ccw,
}

impl SpindleDirection {
    /// The M word that starts the spindle this way.
    pub fn word(self) -> &'static str {
        match self {
            SpindleDirection::Cw => "M3",
            SpindleDirection::Ccw => "M4",
        }
    }
}

/// Coolant or slurry supply during the program.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Coolant {
    /// None.
    #[default]
    Off,
    /// Flood: `M8` at the start, `M9` at the end.
    Flood,
    /// Mist: `M7` at the start, `M9` at the end.
    Mist,
}

impl Coolant {
    /// The M word that switches it on, when on.
    pub fn word(self) -> Option<&'static str> {
        match self {
            Coolant::Off => None,
            Coolant::Flood => Some("M8"),
            Coolant::Mist => Some("M7"),
        }
    }
}

impl<'de> Deserialize<'de> for Coolant {
    /// `"off"`, `"flood"`, `"mist"`, or a boolean (`true`: flood).
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Raw {
            Bool(bool),
            Name(String),
        }
        match Raw::deserialize(d)? {
            Raw::Bool(true) => Ok(Coolant::Flood),
            Raw::Bool(false) => Ok(Coolant::Off),
            Raw::Name(n) => match n.as_str() {
                "off" => Ok(Coolant::Off),
                "flood" => Ok(Coolant::Flood),
                "mist" => Ok(Coolant::Mist),
                other => Err(serde::de::Error::custom(format!(
                    "coolant '{other}': expected off, flood, mist, true or false"
                ))),
            },
        }
    }
}

/// Smallest number of decimals of the coordinates (1 um).
pub const MIN_DECIMALS: usize = 3;
/// Largest number of decimals of the coordinates (1 nm).
pub const MAX_DECIMALS: usize = 6;
/// Longest start or end block, characters.
pub const MAX_BLOCK_CHARS: usize = 200;

/// Checks a start or end block: printable ASCII, none of the comment or end-of-block characters
/// of any dialect (`( ) ; %`), at most [`MAX_BLOCK_CHARS`] characters, no motion and no program
/// end, read by the program reader in `dialect` ([`super::gcode::program::Program::parse`]).
pub fn check_block(field: &str, block: &str, dialect: Dialect) -> Result<()> {
    let bad = |why: String| Err(Error::invalid(field, format!("'{block}': {why}")));
    if block.trim().is_empty() {
        return bad("an empty block".into());
    }
    if block.chars().count() > MAX_BLOCK_CHARS {
        return bad(format!("longer than {MAX_BLOCK_CHARS} characters"));
    }
    if let Some(c) = block
        .chars()
        .find(|c| !(c.is_ascii_graphic() || *c == ' ') || matches!(c, '(' | ')' | ';' | '%'))
    {
        return bad(format!(
            "the character {c:?} (comments, end-of-block and control characters are not allowed \
             in a block)"
        ));
    }
    use super::gcode::program::Program;
    // Followed by a positioning move: when the reader stops at the block (a program end), the
    // move is not read.
    let probe = format!("{block}\nG0 X0\n");
    let read = Program::parse(&probe, dialect)
        .map_err(|e| Error::invalid(field, format!("'{block}' cannot be read back: {e}")))?;
    match read.blocks.len() {
        1 => Ok(()),
        0 => bad("ends the program (M2/M30)".into()),
        _ => bad("moves the axes; start and end blocks may not move".into()),
    }
}
