//! Controller dialects and feed modes: comment syntax, program start and end, and how a
//! controller turns the `F` word of a linear move into the block's duration.
//!
//! | dialect | follows | comments | start / end | `G93` `F` | `G04` pause |
//! |---|---|---|---|---|---|
//! | `iso` | ISO 6983-1 (RS-274) | `( )` | `%` ... `M30` `%` | 1 / minutes | `P` seconds |
//! | `linuxcnc` | LinuxCNC G-code reference (`G93`, `G94`, `G4`) | `( )` | `%` ... `M2` `%` | 1 / minutes | `P` seconds |
//! | `fanuc` | Fanuc Series 0i-MF operator's manual (feed functions, `G93`) | `( )` | `%`, `O` number ... `M30` `%` | 1 / minutes | `X` seconds |
//! | `sinumerik` | Sinumerik 840D sl programming manual, fundamentals (`G93`, `G94`, `G4`) | `;` | ... `M30` | 1 / minutes | `F` seconds |
//!
//! Under `G94` the block time is `60 L / F` s with `L` the programmed path length: the
//! tool-centre `XYZ` distance on ISO, LinuxCNC and Sinumerik controllers (rotary axes follow the
//! linear ones), and on Fanuc controllers the composite `sqrt(dX^2 + dY^2 + dZ^2 + dB^2)` with the
//! rotary axis counted in degrees as if millimetres. A block that moves only the rotary axis has
//! `L = |dB|` everywhere. Under `G93` (inverse time) the block time is `60 / F` s on all four.

use serde::{Deserialize, Serialize};

/// A controller's dialect of ISO G-code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Dialect {
    /// Plain ISO 6983 / RS-274: `( )` comments, `%` wrapped, `M30`.
    #[default]
    Iso,
    /// LinuxCNC: `( )` comments, `%` wrapped, `M2`.
    Linuxcnc,
    /// Fanuc: `%` wrapped, `O` program number, `( )` comments, decimal points always written.
    Fanuc,
    /// Siemens Sinumerik 840D: `;` comments (no parentheses anywhere), `G71` metric, `M30`.
    Sinumerik,
}

/// How the `F` word of a linear move is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum FeedMode {
    /// `G94`: `F` is the path feed, mm/min.
    #[default]
    PerMinute,
    /// `G93`: `F` is the inverse of the block's duration, 1/min.
    InverseTime,
}

impl Dialect {
    /// Every dialect, in documentation order.
    pub const ALL: [Dialect; 4] = [
        Dialect::Iso,
        Dialect::Linuxcnc,
        Dialect::Fanuc,
        Dialect::Sinumerik,
    ];

    /// The name used on the command line and in the program header.
    pub fn name(self) -> &'static str {
        match self {
            Dialect::Iso => "iso",
            Dialect::Linuxcnc => "linuxcnc",
            Dialect::Fanuc => "fanuc",
            Dialect::Sinumerik => "sinumerik",
        }
    }

    /// The dialect of a name ([`Dialect::name`]), case-insensitive.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL
            .into_iter()
            .find(|d| d.name().eq_ignore_ascii_case(name.trim()))
    }

    /// A comment line (or a comment appended to a block) with `text`; characters no dialect's
    /// comment may hold become others: `(` `)` brackets, `;` (the block end of the Fanuc family
    /// and Sinumerik's comment start, which ends a parenthesised comment for many readers) a
    /// comma, `%` (the end-of-record character of ISO tapes) `PCT`, and control or non-ASCII
    /// characters `?`.
    pub fn comment(self, text: &str) -> String {
        let mut clean = String::with_capacity(text.len() + 8);
        for c in text.chars() {
            match c {
                '(' => clean.push('['),
                ')' => clean.push(']'),
                ';' => clean.push(','),
                '%' => clean.push_str("PCT"),
                '\n' | '\r' | '\t' => clean.push(' '),
                c if c.is_ascii_graphic() || c == ' ' => clean.push(c),
                _ => clean.push('?'),
            }
        }
        match self {
            Dialect::Sinumerik => format!("; {clean}"),
            _ => format!("({clean})"),
        }
    }

    /// The safe-start block written first unless the machine profile gives its own: plane,
    /// metric units, cutter compensation off, tool length offset off where the dialect has
    /// `G49`, canned cycles off where it has `G80`, absolute, feed per minute.
    pub fn safe_start(self) -> &'static str {
        match self {
            Dialect::Iso => "G17 G21 G40 G80 G90 G94",
            Dialect::Linuxcnc | Dialect::Fanuc => "G17 G21 G40 G49 G80 G90 G94",
            Dialect::Sinumerik => "G17 G71 G40 G90 G94",
        }
    }

    /// The word that stops the program.
    pub fn program_end(self) -> &'static str {
        match self {
            Dialect::Linuxcnc => "M2",
            _ => "M30",
        }
    }

    /// The metric-units word.
    pub fn metric_word(self) -> &'static str {
        match self {
            Dialect::Sinumerik => "G71",
            _ => "G21",
        }
    }

    /// Motion words: `G00`/`G01` or, on Sinumerik, `G0`/`G1`.
    pub fn rapid_word(self) -> &'static str {
        match self {
            Dialect::Sinumerik => "G0",
            _ => "G00",
        }
    }

    /// See [`Dialect::rapid_word`].
    pub fn linear_word(self) -> &'static str {
        match self {
            Dialect::Sinumerik => "G1",
            _ => "G01",
        }
    }

    /// Circular-move words: `G02`/`G03` or, on Sinumerik, `G2`/`G3` (counter-clockwise seen
    /// from +Z when `ccw`).
    pub fn arc_word(self, ccw: bool) -> &'static str {
        match (self, ccw) {
            (Dialect::Sinumerik, false) => "G2",
            (Dialect::Sinumerik, true) => "G3",
            (_, false) => "G02",
            (_, true) => "G03",
        }
    }

    /// Whether the whole program is wrapped in `%` lines.
    pub fn percent_wrapped(self) -> bool {
        !matches!(self, Dialect::Sinumerik)
    }

    /// Largest block number the dialect accepts (LinuxCNC and Fanuc: five digits).
    pub fn max_block_number(self) -> u64 {
        match self {
            Dialect::Sinumerik => 2_147_483_647,
            _ => 99_999,
        }
    }

    /// Whether the rotary axis counts in the `G94` path length (Fanuc's composite feed).
    pub fn rotary_in_path_length(self) -> bool {
        matches!(self, Dialect::Fanuc)
    }

    /// Programmed path length of a move by `(dx, dy, dz)` mm and `db` degrees that `G94` divides
    /// by `F` (module documentation).
    pub fn path_length_mm(self, d_mm: [f64; 3], db_deg: f64) -> f64 {
        let linear = (d_mm[0] * d_mm[0] + d_mm[1] * d_mm[1] + d_mm[2] * d_mm[2]).sqrt();
        if self.rotary_in_path_length() {
            (linear * linear + db_deg * db_deg).sqrt()
        } else if linear > 0.0 {
            linear
        } else {
            db_deg.abs()
        }
    }
}

impl FeedMode {
    /// The modal G word.
    pub fn word(self) -> &'static str {
        match self {
            FeedMode::PerMinute => "G94",
            FeedMode::InverseTime => "G93",
        }
    }

    /// The name used on the command line and in the program header.
    pub fn name(self) -> &'static str {
        match self {
            FeedMode::PerMinute => "per-minute",
            FeedMode::InverseTime => "inverse-time",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_comment_syntax() {
        for d in Dialect::ALL {
            assert_eq!(Dialect::from_name(d.name()), Some(d));
        }
        assert_eq!(Dialect::from_name("bogus"), None);
        assert_eq!(Dialect::Sinumerik.comment("a (b)"), "; a [b]");
        assert_eq!(Dialect::Fanuc.comment("a (b)"), "(a [b])");
        assert_eq!(Dialect::Fanuc.comment("x; y 5% \u{b0}"), "(x, y 5PCT ?)");
        assert_eq!(Dialect::Sinumerik.comment("x; y"), "; x, y");
    }

    #[test]
    fn path_length_conventions() {
        // 3-4-0 move with 12 degrees of B.
        let d = [3.0, 4.0, 0.0];
        assert_eq!(Dialect::Iso.path_length_mm(d, 12.0), 5.0);
        assert_eq!(Dialect::Fanuc.path_length_mm(d, 12.0), 13.0);
        assert_eq!(Dialect::Linuxcnc.path_length_mm([0.0; 3], -7.0), 7.0);
    }
}
