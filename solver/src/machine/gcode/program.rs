//! A G-code program as the machine runs it: motion blocks with their programmed durations and
//! the dwell stretches they cross, read back from the text ([`Program::parse`]).
//!
//! The reader follows the subset of ISO 6983 that Preston writes and a shop's edits keep:
//! `%` and `O` lines, `N` numbers, `( )` and `;` comments, `G0`/`G1` (`G00`/`G01`), `G4` pauses,
//! `G17`, `G20`/`G21` (`G70`/`G71`, `G700`/`G710`), `G90`/`G91`, `G93`/`G94`, axis words `X Y Z`
//! and one rotary axis `A`, `B` or `C`, `F`, and the `M` and `S` words (ignored). Circular moves
//! and feed per revolution are refused with the line that holds them.
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
}

impl Block {
    /// Straight-line tool-centre distance, mm.
    pub fn length_mm(&self) -> f64 {
        let d = [
            self.end_mm[0] - self.start_mm[0],
            self.end_mm[1] - self.start_mm[1],
            self.end_mm[2] - self.start_mm[2],
        ];
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
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
                'I' | 'J' | 'K' | 'R' => {
                    return Err(program_error(
                        line,
                        "circular moves (I, J, K, R words) are not supported by the read-back",
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
        let mut pause = false;
        for &g in &w.g {
            match g {
                0 => self.motion = Some(BlockKind::Rapid),
                1 => self.motion = Some(BlockKind::Linear),
                2 | 3 => {
                    return Err(program_error(
                        line,
                        "circular moves (G2, G3) are not supported by the read-back",
                    ))
                }
                4 => pause = true,
                17 | 40 | 49 | 54..=59 | 64 | 61 | 80 => {}
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
        if pause {
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
            });
            if w.m_end {
                self.ended = true;
            }
            return Ok(());
        }
        if self.feed_mode == FeedMode::PerMinute {
            if let Some(f) = w.f {
                self.feed = Some(f * self.mm_per_unit);
            }
        }
        let moves = w.axes.iter().any(Option::is_some) || w.rotary.is_some();
        if moves {
            let kind = self
                .motion
                .ok_or_else(|| program_error(line, "axis words before any G0 or G1 motion mode"))?;
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
            let time = match kind {
                BlockKind::Rapid => 0.0,
                _ if first => {
                    return Err(program_error(
                        line,
                        "the first move is a feed move from an unknown position; position with G0 first",
                    ))
                }
                _ => {
                    let d = [end[0] - start[0], end[1] - start[1], end[2] - start[2]];
                    let len = self.dialect.path_length_mm(d, b1 - b0);
                    match self.feed_mode {
                        FeedMode::PerMinute => {
                            let f = self.feed.ok_or_else(|| {
                                program_error(line, "feed move before any F word")
                            })?;
                            if !(f > 0.0) {
                                return Err(program_error(line, format!("feed F{f} is not positive")));
                            }
                            60.0 * len / f
                        }
                        FeedMode::InverseTime => {
                            let f = w.f.ok_or_else(|| {
                                program_error(line, "a G93 (inverse time) move needs its own F word")
                            })?;
                            if !(f > 0.0) {
                                return Err(program_error(line, format!("inverse-time F{f} is not positive")));
                            }
                            60.0 / f
                        }
                    }
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
            });
            self.position_mm = Some(end);
            self.rotary_deg = b1;
        }
        if w.m_end {
            self.ended = true;
        }
        Ok(())
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
