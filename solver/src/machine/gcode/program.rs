//! A G-code program as the machine runs it: motion blocks with their programmed durations and
//! the dwell stretches they cross, read back from the text ([`Program::parse`]).
//!
//! The reader follows the subset of ISO 6983 that Preston writes and a shop's edits keep:
//! `%` and `O` lines, `N` numbers, `( )` and `;` comments, `G0`/`G1` (`G00`/`G01`), `G4` pauses,
//! `G17`, `G40`, `G43`, `G49`, `G54` to `G59`, `G61`, `G64`, `G80` (no motion), `G20`/`G21` (`G70`/`G71`, `G700`/`G710`), `G90`/`G91`, `G93`/`G94`, axis words `X Y Z`
//! and one rotary axis `A`, `B` or `C`, `F`, and the `M` and `S` words (ignored). Circular moves
//! `G2` (clockwise) and `G3` (counter-clockwise, seen from +Z) in the `G17` plane with the centre
//! as `I J` offsets from the start (incremental in `G90` and `G91`, as on ISO, Fanuc, LinuxCNC and
//! Sinumerik controllers; `Z` makes a helix) are read into [`ArcMove`]s: the end radius may differ
//! from the start radius by at most [`ARC_RADIUS_TOLERANCE_MM`], the radius then varies linearly
//! with the angle, and start = end is a full circle. The radius form, `R` (`CR=` on Sinumerik,
//! where `R` is an arithmetic parameter), gives the centre instead ([`arc_centre_from_radius`]):
//! a positive radius the arc of at most 180 degrees, a negative one the arc of more; a radius
//! shorter than half the chord (beyond [`ARC_RADIUS_TOLERANCE_MM`], within which the arc is the
//! half circle), a zero radius, start = end and `R` with `I J` in one block are refused. `K`,
//! other planes, a rotary axis on an arc and feed per revolution are refused with the line that
//! holds them.
//!
//! A circular block's programmed path length is its arc length ([`arc_length_mm`]): the sweep
//! times the mean of the start and end radii, combined with the `Z` travel of a helix as
//! `sqrt((S r)^2 + dZ^2)`; `G94` gives it the time `60 L / F`, `G93` `60 / F`.
//!
//! Dwell stretches are marked by comments that `preston nc` writes before the blocks of each
//! stretch, `DWELL <j> <t_s> S AT <x_mm> <y_mm>` (the dwell point's index, its planned dwell and
//! its contact point), and `END DWELL` after the last; the tool touches the part on the linear
//! moves and pauses between the first marker and the end marker. A program without markers is
//! in contact on every linear move and pause.

use super::dialect::{Dialect, FeedMode};
use crate::error::{Error, Result};

/// Largest program text read, bytes (a dwell program of 10^6 points is about 120 MB).
pub const MAX_PROGRAM_BYTES: usize = 1 << 30;

/// What a block does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockKind {
    /// `G0`: positioning at the machine's rapid rate (duration not programmed).
    Rapid,
    /// `G1`: a straight move at the programmed feed.
    Linear,
    /// `G2`/`G3`: a circular move at the programmed feed ([`Block::arc`]).
    Circular,
    /// `G4`: the axes stand still for the programmed time.
    Pause,
}

/// One block that moves the tool (or pauses it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Block {
    /// What the block does.
    pub kind: BlockKind,
    /// 1-based line of the program text.
    pub line: usize,
    /// Tool-centre position at the start, mm (machine coordinates as programmed).
    pub start_mm: [f64; 3],
    /// Tool-centre position at the end, mm.
    pub end_mm: [f64; 3],
    /// Rotary-axis angle at the start and end, degrees (0 when never written).
    pub rotary_deg: [f64; 2],
    /// Programmed duration, s: path length / F (G94), 60 / F (G93) or the pause; 0 for rapids.
    pub programmed_time_s: f64,
    /// Whether the tool touches the part during the block (module documentation).
    pub contact: bool,
    /// The circle of a `G2`/`G3` block; `None` for straight moves and pauses.
    pub arc: Option<ArcMove>,
}

/// Largest difference between the end and the start radius of a circular move, mm.
pub const ARC_RADIUS_TOLERANCE_MM: f64 = 0.002;

/// A circular move in the XY plane (`G17`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArcMove {
    /// Centre `(x, y)`, mm.
    pub centre_mm: [f64; 2],
    /// Counter-clockwise seen from +Z (`G3`); clockwise (`G2`) when false.
    pub ccw: bool,
}

/// Why a radius-form arc ([`arc_centre_from_radius`]) has no centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RadiusArcError {
    /// The radius is zero.
    ZeroRadius,
    /// Start and end coincide in XY: the radius form cannot give a full circle.
    FullCircle,
    /// The radius is shorter than half the chord (beyond [`ARC_RADIUS_TOLERANCE_MM`]).
    TooShort {
        /// The programmed radius, mm (its magnitude).
        radius_mm: f64,
        /// Half the distance from start to end, mm.
        half_chord_mm: f64,
    },
}

impl std::fmt::Display for RadiusArcError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RadiusArcError::ZeroRadius => write!(f, "circular move: the radius is zero"),
            RadiusArcError::FullCircle => write!(
                f,
                "circular move: start and end coincide, which the radius form cannot program \
                 (a full circle needs I J)"
            ),
            RadiusArcError::TooShort {
                radius_mm,
                half_chord_mm,
            } => write!(
                f,
                "circular move: radius {radius_mm} mm is shorter than half the chord, \
                 {half_chord_mm} mm, so no circle joins start and end"
            ),
        }
    }
}

/// Centre `(x, y)`, mm, of the radius-form arc from `start` to `end` with the signed radius
/// `radius_mm` turning counter-clockwise (`G3`) when `ccw`: on the chord's perpendicular
/// bisector at `sqrt(R^2 - (c/2)^2)` from the chord's midpoint (`c` the chord), to the left of
/// the chord (seen along the motion) for a counter-clockwise arc of at most 180 degrees
/// (`R > 0`), to the right for a clockwise one, and on the other side for `R < 0` (the arc of
/// more than 180 degrees). A radius shorter than half the chord by at most
/// [`ARC_RADIUS_TOLERANCE_MM`] gives the half circle about the midpoint.
pub fn arc_centre_from_radius(
    start: [f64; 2],
    end: [f64; 2],
    radius_mm: f64,
    ccw: bool,
) -> std::result::Result<[f64; 2], RadiusArcError> {
    if radius_mm == 0.0 {
        return Err(RadiusArcError::ZeroRadius);
    }
    let d = [end[0] - start[0], end[1] - start[1]];
    let chord = d[0].hypot(d[1]);
    if chord == 0.0 {
        return Err(RadiusArcError::FullCircle);
    }
    let (r, half) = (radius_mm.abs(), 0.5 * chord);
    if half - r > ARC_RADIUS_TOLERANCE_MM {
        return Err(RadiusArcError::TooShort {
            radius_mm: r,
            half_chord_mm: half,
        });
    }
    // (R - c/2)(R + c/2) keeps the difference exact near the half circle.
    let h = ((r - half) * (r + half)).max(0.0).sqrt();
    let left = [-d[1] / chord, d[0] / chord];
    let side = if ccw == (radius_mm > 0.0) { 1.0 } else { -1.0 };
    Ok([
        start[0] + 0.5 * d[0] + side * h * left[0],
        start[1] + 0.5 * d[1] + side * h * left[1],
    ])
}

/// Start radius, end radius, start angle and sweep (positive, radians; `2 pi` when start and end
/// coincide) of the arc from `start` to `end` about `centre`.
pub fn arc_sweep(start: [f64; 2], end: [f64; 2], centre: [f64; 2], ccw: bool) -> [f64; 4] {
    let (u, v) = (
        [start[0] - centre[0], start[1] - centre[1]],
        [end[0] - centre[0], end[1] - centre[1]],
    );
    let (a0, a1) = (u[1].atan2(u[0]), v[1].atan2(v[0]));
    let tau = std::f64::consts::TAU;
    let mut d = if ccw { a1 - a0 } else { a0 - a1 };
    d = d.rem_euclid(tau);
    if d == 0.0 {
        d = tau;
    }
    [u[0].hypot(u[1]), v[0].hypot(v[1]), a0, d]
}

/// Programmed path length of a circular move, mm: `sqrt((S (r0 + r1) / 2)^2 + dZ^2)` with the
/// sweep `S` and radii of [`arc_sweep`] (a circle's `r theta` when `r0 = r1`, `dZ = 0`).
pub fn arc_length_mm(start: [f64; 3], end: [f64; 3], arc: &ArcMove) -> f64 {
    let [r0, r1, _, sweep] = arc_sweep(
        [start[0], start[1]],
        [end[0], end[1]],
        arc.centre_mm,
        arc.ccw,
    );
    (sweep * 0.5 * (r0 + r1)).hypot(end[2] - start[2])
}

impl Block {
    /// Tool-centre path length, mm: the straight distance, or the arc length of a circular move.
    pub fn length_mm(&self) -> f64 {
        if let Some(a) = &self.arc {
            return arc_length_mm(self.start_mm, self.end_mm, a);
        }
        let d = [
            self.end_mm[0] - self.start_mm[0],
            self.end_mm[1] - self.start_mm[1],
            self.end_mm[2] - self.start_mm[2],
        ];
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
    }

    /// Tool-centre position at the fraction `f` of the block (of the sweep for a circular move:
    /// angle, radius and Z linear in it), mm.
    pub fn point_at(&self, f: f64) -> [f64; 3] {
        let (s, e) = (self.start_mm, self.end_mm);
        match &self.arc {
            None => [0, 1, 2].map(|k| s[k] + f * (e[k] - s[k])),
            Some(a) => {
                let [r0, r1, a0, sweep] = arc_sweep([s[0], s[1]], [e[0], e[1]], a.centre_mm, a.ccw);
                let sign = if a.ccw { 1.0 } else { -1.0 };
                let ang = a0 + sign * f * sweep;
                let r = r0 + f * (r1 - r0);
                [
                    a.centre_mm[0] + r * ang.cos(),
                    a.centre_mm[1] + r * ang.sin(),
                    s[2] + f * (e[2] - s[2]),
                ]
            }
        }
    }

    /// Direction of motion (not normalised) at the fraction `f` of the block.
    pub fn tangent_at(&self, f: f64) -> [f64; 3] {
        let (s, e) = (self.start_mm, self.end_mm);
        match &self.arc {
            None => [e[0] - s[0], e[1] - s[1], e[2] - s[2]],
            Some(a) => {
                let [r0, r1, a0, sweep] = arc_sweep([s[0], s[1]], [e[0], e[1]], a.centre_mm, a.ccw);
                let sign = if a.ccw { 1.0 } else { -1.0 };
                let ang = a0 + sign * f * sweep;
                let r = r0 + f * (r1 - r0);
                let w = sign * sweep * r;
                [
                    (r1 - r0) * ang.cos() - w * ang.sin(),
                    (r1 - r0) * ang.sin() + w * ang.cos(),
                    e[2] - s[2],
                ]
            }
        }
    }
}

/// A dwell stretch marked in the program.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StretchMark {
    /// The dwell point's index in the plan.
    pub point: usize,
    /// Contact point of the dwell point, mm.
    pub x_mm: f64,
    /// See `x_mm`.
    pub y_mm: f64,
    /// Planned dwell, s.
    pub planned_dwell_s: f64,
    /// Index in [`Program::blocks`] of the stretch's first block; the stretch runs to the next
    /// stretch's first block (the last one to the end of the contact section).
    pub first_block: usize,
}

/// A program read back from its text.
#[derive(Debug, Clone, PartialEq)]
pub struct Program {
    /// The dialect it was read in.
    pub dialect: Dialect,
    /// Every motion block and pause in program order.
    pub blocks: Vec<Block>,
    /// The marked dwell stretches in program order (empty for a program without markers).
    pub stretches: Vec<StretchMark>,
    /// One past the last block of the contact section.
    pub contact_end: usize,
}

impl Program {
    /// The blocks of stretch `k` (indices into [`Program::blocks`]).
    pub fn stretch_blocks(&self, k: usize) -> std::ops::Range<usize> {
        let start = self.stretches[k].first_block;
        let end = self
            .stretches
            .get(k + 1)
            .map_or(self.contact_end, |s| s.first_block);
        start..end.max(start)
    }

    /// Indices of the blocks in contact with the part (feed moves and pauses of the contact
    /// section), in program order.
    pub fn contact_blocks(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.blocks.len()).filter(|&k| self.blocks[k].contact)
    }

    /// Time each marked stretch takes at the programmed feeds, s.
    pub fn programmed_stretch_times_s(&self) -> Vec<f64> {
        (0..self.stretches.len())
            .map(|k| {
                self.blocks[self.stretch_blocks(k)]
                    .iter()
                    .map(|b| b.programmed_time_s)
                    .sum()
            })
            .collect()
    }

    /// Sum of the programmed durations of the feed moves and pauses, s (rapids have none).
    pub fn programmed_time_s(&self) -> f64 {
        self.blocks.iter().map(|b| b.programmed_time_s).sum()
    }

    /// The dialect named in a Preston program header (`DIALECT <name>`), if any.
    pub fn detect_dialect(text: &str) -> Option<Dialect> {
        text.lines().take(40).find_map(|l| {
            let at = l.find("DIALECT ")?;
            let rest = &l[at + "DIALECT ".len()..];
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric())
                .collect();
            Dialect::from_name(&name)
        })
    }

    /// Reads a program written in `dialect` (module documentation).
    pub fn parse(text: &str, dialect: Dialect) -> Result<Self> {
        if text.len() > MAX_PROGRAM_BYTES {
            return Err(Error::Program {
                line: 0,
                why: format!(
                    "{} bytes is more than the {MAX_PROGRAM_BYTES}-byte limit",
                    text.len()
                ),
            });
        }
        let mut state = State::new(dialect);
        for (i, raw) in text.lines().enumerate() {
            state.line(i + 1, raw)?;
        }
        state.finish()
    }
}

/// The reader's modal state.
struct State {
    dialect: Dialect,
    position_mm: Option<[f64; 3]>,
    rotary_deg: f64,
    mm_per_unit: f64,
    absolute: bool,
    feed_mode: FeedMode,
    feed: Option<f64>,
    motion: Option<BlockKind>,
    ccw: bool,
    blocks: Vec<Block>,
    stretches: Vec<StretchMark>,
    marked: bool,
    contact_end: Option<usize>,
    ended: bool,
}

/// The words of one block.
#[derive(Default)]
struct Words {
    g: Vec<u32>,
    axes: [Option<f64>; 3],
    rotary: Option<f64>,
    f: Option<f64>,
    p: Option<f64>,
    centre: [Option<f64>; 2],
    /// The radius word of a radius-form arc (`R`, or `CR=` on Sinumerik), in program units.
    radius: Option<f64>,
    x_for_pause: Option<f64>,
    m_end: bool,
}

fn program_error(line: usize, why: impl Into<String>) -> Error {
    Error::Program {
        line,
        why: why.into(),
    }
}

/// At most this many characters of user text are quoted in an error.
const QUOTE_CHARS: usize = 40;

fn quote(s: &str) -> String {
    let q: String = s.chars().take(QUOTE_CHARS).collect();
    if s.chars().count() > QUOTE_CHARS {
        format!("{q}...")
    } else {
        q
    }
}

impl State {
    fn new(dialect: Dialect) -> Self {
        Self {
            dialect,
            position_mm: None,
            rotary_deg: 0.0,
            mm_per_unit: 1.0,
            absolute: true,
            feed_mode: FeedMode::PerMinute,
            feed: None,
            motion: None,
            ccw: false,
            blocks: Vec::new(),
            stretches: Vec::new(),
            marked: false,
            contact_end: None,
            ended: false,
        }
    }

    fn line(&mut self, line: usize, raw: &str) -> Result<()> {
        let trimmed = raw.trim();
        if trimmed.is_empty() || trimmed.starts_with('%') || self.ended {
            return Ok(());
        }
        // Split code and comments.
        let mut code = String::with_capacity(trimmed.len());
        let mut comments: Vec<String> = Vec::new();
        let mut chars = trimmed.chars();
        while let Some(c) = chars.next() {
            match c {
                '(' => {
                    let mut body = String::new();
                    let mut closed = false;
                    for d in chars.by_ref() {
                        if d == ')' {
                            closed = true;
                            break;
                        }
                        body.push(d);
                    }
                    if !closed {
                        return Err(program_error(line, "comment '(' is never closed"));
                    }
                    comments.push(body);
                }
                ';' => {
                    comments.push(chars.by_ref().collect());
                }
                c => code.push(c),
            }
        }
        for c in &comments {
            self.marker(line, c.trim())?;
        }
        let words = self.words(line, &code)?;
        self.apply(line, words)
    }

    /// Reads a `DWELL` or `END DWELL` marker comment.
    fn marker(&mut self, line: usize, c: &str) -> Result<()> {
        if c == "END DWELL" {
            self.contact_end = Some(self.blocks.len());
            return Ok(());
        }
        // A marker is `DWELL` followed by the point index; other comments are free text.
        let Some(rest) = c
            .strip_prefix("DWELL ")
            .filter(|r| r.starts_with(|ch: char| ch.is_ascii_digit()))
        else {
            return Ok(());
        };
        let f: Vec<&str> = rest.split_whitespace().collect();
        let bad = || {
            program_error(
                line,
                format!(
                    "dwell marker '{}' is not 'DWELL <point> <seconds> S AT <x_mm> <y_mm>'",
                    quote(c)
                ),
            )
        };
        if f.len() != 6 || f[2] != "S" || f[3] != "AT" {
            return Err(bad());
        }
        let point: usize = f[0].parse().map_err(|_| bad())?;
        let num = |s: &str| -> Result<f64> {
            s.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(bad)
        };
        let (t, x, y) = (num(f[1])?, num(f[4])?, num(f[5])?);
        if t < 0.0 {
            return Err(bad());
        }
        self.marked = true;
        self.stretches.push(StretchMark {
            point,
            x_mm: x,
            y_mm: y,
            planned_dwell_s: t,
            first_block: self.blocks.len(),
        });
        Ok(())
    }

    fn words(&self, line: usize, code: &str) -> Result<Words> {
        let mut w = Words::default();
        let b = code.as_bytes();
        let mut i = 0;
        // An `O` program-number line carries no motion.
        let first = code.trim_start();
        if first.starts_with(['O', 'o']) && first[1..].starts_with(|c: char| c.is_ascii_digit()) {
            return Ok(w);
        }
        while i < b.len() {
            let c = b[i] as char;
            if c.is_ascii_whitespace() {
                i += 1;
                continue;
            }
            if !c.is_ascii_alphabetic() {
                return Err(program_error(
                    line,
                    format!("unexpected '{c}' in '{}'", quote(code.trim())),
                ));
            }
            let letter = c.to_ascii_uppercase();
            i += 1;
            // Sinumerik's radius word `CR=`.
            let cr = self.dialect == Dialect::Sinumerik
                && letter == 'C'
                && b.get(i).is_some_and(|n| n.eq_ignore_ascii_case(&b'R'));
            if cr {
                i += 1;
            }
            while i < b.len() && (b[i] == b' ' || b[i] == b'=') {
                i += 1;
            }
            let start = i;
            while i < b.len() && (b[i].is_ascii_digit() || matches!(b[i], b'.' | b'-' | b'+')) {
                i += 1;
            }
            let text = &code[start..i];
            let value: f64 = text.parse().map_err(|_| {
                program_error(
                    line,
                    format!("word {letter} has no number in '{}'", quote(code.trim())),
                )
            })?;
            if !value.is_finite() {
                return Err(program_error(line, format!("word {letter} is not finite")));
            }
            if cr {
                w.radius = Some(value);
                continue;
            }
            match letter {
                'N' => {}
                'G' => {
                    if value.fract() != 0.0 || value < 0.0 {
                        return Err(program_error(line, format!("G{text} is not supported")));
                    }
                    w.g.push(value as u32);
                }
                'M' => {
                    if matches!(value as i64, 2 | 30) {
                        w.m_end = true;
                    }
                }
                'S' | 'T' | 'D' | 'H' => {}
                'X' => {
                    w.axes[0] = Some(value);
                    w.x_for_pause = Some(value);
                }
                'Y' => w.axes[1] = Some(value),
                'Z' => w.axes[2] = Some(value),
                'A' | 'B' | 'C' => {
                    if w.rotary.is_some() {
                        return Err(program_error(line, "more than one rotary axis in a block"));
                    }
                    w.rotary = Some(value);
                }
                'F' => w.f = Some(value),
                'P' => w.p = Some(value),
                'I' => w.centre[0] = Some(value),
                'J' => w.centre[1] = Some(value),
                'R' if self.dialect == Dialect::Sinumerik => {
                    return Err(program_error(
                        line,
                        "R is an arithmetic parameter on Sinumerik, which the read-back does \
                         not evaluate; a circular move's radius is CR=",
                    ))
                }
                'R' => w.radius = Some(value),
                'K' => {
                    return Err(program_error(
                        line,
                        "circular moves are read in the G17 plane (I J centre offsets or a \
                         radius); the K word is not supported by the read-back",
                    ))
                }
                other => {
                    return Err(program_error(
                        line,
                        format!("word {other} is not supported"),
                    ))
                }
            }
        }
        Ok(w)
    }

    fn apply(&mut self, line: usize, w: Words) -> Result<()> {
        if self.modes(line, &w.g)? {
            return self.pause(line, &w);
        }
        if self.feed_mode == FeedMode::PerMinute {
            if let Some(f) = w.f {
                self.feed = Some(f * self.mm_per_unit);
            }
        }
        let moves = w.axes.iter().any(Option::is_some)
            || w.rotary.is_some()
            || (self.motion == Some(BlockKind::Circular)
                && (w.centre.iter().any(Option::is_some) || w.radius.is_some()));
        if moves {
            self.motion_block(line, &w)?;
        }
        if w.m_end {
            self.ended = true;
        }
        Ok(())
    }

    /// Applies the block's G words to the modal state; true when the block is a `G4` pause.
    fn modes(&mut self, line: usize, g: &[u32]) -> Result<bool> {
        let mut pause = false;
        for &g in g {
            match g {
                0 => self.motion = Some(BlockKind::Rapid),
                1 => self.motion = Some(BlockKind::Linear),
                2 => {
                    self.motion = Some(BlockKind::Circular);
                    self.ccw = false;
                }
                3 => {
                    self.motion = Some(BlockKind::Circular);
                    self.ccw = true;
                }
                4 => pause = true,
                17 | 40 | 43 | 49 | 54..=59 | 64 | 61 | 80 => {}
                20 | 70 | 700 => self.mm_per_unit = 25.4,
                21 | 71 | 710 => self.mm_per_unit = 1.0,
                90 => self.absolute = true,
                91 => self.absolute = false,
                93 => self.feed_mode = FeedMode::InverseTime,
                94 => self.feed_mode = FeedMode::PerMinute,
                95 => {
                    return Err(program_error(
                        line,
                        "feed per revolution (G95) has no duration without the spindle speed",
                    ))
                }
                other => return Err(program_error(line, format!("G{other} is not supported"))),
            }
        }
        Ok(pause)
    }

    /// A `G4` pause at the current position, its time in the dialect's word.
    fn pause(&mut self, line: usize, w: &Words) -> Result<()> {
        let seconds = match self.dialect {
            Dialect::Sinumerik => w.f,
            Dialect::Fanuc => w.x_for_pause.or(w.p.map(|ms| ms / 1000.0)),
            Dialect::Iso | Dialect::Linuxcnc => w.p,
        };
        let t = seconds
            .filter(|t| *t >= 0.0)
            .ok_or_else(|| program_error(line, "G4 pause without a non-negative time"))?;
        let at = self
            .position_mm
            .ok_or_else(|| program_error(line, "G4 pause before any position is known"))?;
        self.blocks.push(Block {
            kind: BlockKind::Pause,
            line,
            start_mm: at,
            end_mm: at,
            rotary_deg: [self.rotary_deg; 2],
            programmed_time_s: t,
            contact: false,
            arc: None,
        });
        if w.m_end {
            self.ended = true;
        }
        Ok(())
    }

    /// A move in the current motion mode: its end, rotary angle, circle and programmed time.
    fn motion_block(&mut self, line: usize, w: &Words) -> Result<()> {
        let kind = self.motion.ok_or_else(|| {
            program_error(line, "axis words before any G0, G1, G2 or G3 motion mode")
        })?;
        let start = match self.position_mm {
            Some(p) => p,
            None if kind == BlockKind::Rapid || self.absolute => {
                // The first positioning move starts wherever the machine is; axes it does
                // not name are taken as unchanged.
                [0.0; 3]
            }
            None => {
                return Err(program_error(
                    line,
                    "incremental move from an unknown position",
                ))
            }
        };
        let first = self.position_mm.is_none();
        let mut end = start;
        for (k, a) in w.axes.iter().enumerate() {
            if let Some(v) = a {
                let v = v * self.mm_per_unit;
                end[k] = if self.absolute { v } else { start[k] + v };
            }
        }
        let b0 = self.rotary_deg;
        let b1 = match w.rotary {
            Some(v) if self.absolute => v,
            Some(v) => b0 + v,
            None => b0,
        };
        let arc = if kind == BlockKind::Circular {
            Some(self.arc_move(line, w, start, end)?)
        } else {
            if w.centre.iter().any(Option::is_some) {
                return Err(program_error(line, "I or J words outside a circular move"));
            }
            if w.radius.is_some() {
                return Err(program_error(line, "a radius word outside a circular move"));
            }
            None
        };
        let time = match kind {
            BlockKind::Rapid => 0.0,
            _ if first => return Err(program_error(
                line,
                "the first move is a feed move from an unknown position; position with G0 first",
            )),
            _ => {
                let len = match &arc {
                    Some(a) => arc_length_mm(start, end, a),
                    None => {
                        let d = [end[0] - start[0], end[1] - start[1], end[2] - start[2]];
                        self.dialect.path_length_mm(d, b1 - b0)
                    }
                };
                self.feed_time(line, w.f, len)?
            }
        };
        self.blocks.push(Block {
            kind,
            line,
            start_mm: start,
            end_mm: end,
            rotary_deg: [b0, b1],
            programmed_time_s: time,
            contact: false,
            arc,
        });
        self.position_mm = Some(end);
        self.rotary_deg = b1;
        Ok(())
    }

    /// The circle of a `G2`/`G3` move from `start` to `end` (I J offsets from the start, or the
    /// radius form), refused when its radii at the two ends differ beyond the tolerance.
    fn arc_move(&self, line: usize, w: &Words, start: [f64; 3], end: [f64; 3]) -> Result<ArcMove> {
        if w.rotary.is_some() {
            return Err(program_error(
                line,
                "a rotary axis on a circular move is not supported by the read-back",
            ));
        }
        let has_centre = w.centre.iter().any(Option::is_some);
        let centre = match w.radius {
            Some(_) if has_centre => {
                return Err(program_error(
                    line,
                    "a circular move gives its centre by I J or by its radius, not both",
                ))
            }
            Some(r) => arc_centre_from_radius(
                [start[0], start[1]],
                [end[0], end[1]],
                r * self.mm_per_unit,
                self.ccw,
            )
            .map_err(|e| program_error(line, e.to_string()))?,
            None if !has_centre => {
                return Err(program_error(
                    line,
                    "a circular move needs I or J, or a radius",
                ))
            }
            None => [
                start[0] + w.centre[0].unwrap_or(0.0) * self.mm_per_unit,
                start[1] + w.centre[1].unwrap_or(0.0) * self.mm_per_unit,
            ],
        };
        let a = ArcMove {
            centre_mm: centre,
            ccw: self.ccw,
        };
        let [r0, r1, _, _] = arc_sweep([start[0], start[1]], [end[0], end[1]], centre, a.ccw);
        if !(r0 > 0.0) || (r1 - r0).abs() > ARC_RADIUS_TOLERANCE_MM {
            return Err(program_error(
                line,
                format!(
                    "circular move: start radius {r0} mm and end radius {r1} mm differ by \
                     more than {ARC_RADIUS_TOLERANCE_MM} mm"
                ),
            ));
        }
        Ok(a)
    }

    /// Programmed time of a feed move of `len` mm, s: from the modal feed (`G94`) or the
    /// block's own `F` (`G93`).
    fn feed_time(&self, line: usize, f_word: Option<f64>, len: f64) -> Result<f64> {
        Ok(match self.feed_mode {
            FeedMode::PerMinute => {
                let f = self
                    .feed
                    .ok_or_else(|| program_error(line, "feed move before any F word"))?;
                if !(f > 0.0) {
                    return Err(program_error(line, format!("feed F{f} is not positive")));
                }
                60.0 * len / f
            }
            FeedMode::InverseTime => {
                let f = f_word.ok_or_else(|| {
                    program_error(line, "a G93 (inverse time) move needs its own F word")
                })?;
                if !(f > 0.0) {
                    return Err(program_error(
                        line,
                        format!("inverse-time F{f} is not positive"),
                    ));
                }
                60.0 / f
            }
        })
    }

    fn finish(self) -> Result<Program> {
        let mut blocks = self.blocks;
        let (from, to) = if self.marked {
            let from = self.stretches.first().map_or(0, |s| s.first_block);
            let to = self.contact_end.ok_or_else(|| {
                program_error(0, "the program has DWELL markers but no END DWELL marker")
            })?;
            (from, to)
        } else {
            (0, blocks.len())
        };
        if to < from {
            return Err(program_error(
                0,
                "END DWELL comes before the first DWELL marker",
            ));
        }
        for b in &mut blocks[from..to] {
            b.contact = b.kind != BlockKind::Rapid;
        }
        if let Some(b) = blocks[from..to].iter().find(|b| b.kind == BlockKind::Rapid) {
            if self.marked {
                return Err(program_error(
                    b.line,
                    "a rapid move inside the dwell section would skip dwell",
                ));
            }
        }
        Ok(Program {
            dialect: self.dialect,
            blocks,
            stretches: self.stretches,
            contact_end: to,
        })
    }
}
