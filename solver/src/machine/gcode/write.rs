//! The G-code writer: a planned [`NcProgram`] as program text that delivers every dwell.
//!
//! Layout (shown for `iso`; [`super::dialect`] gives the other dialects' words):
//!
//! ```text
//! %                                     (Fanuc: then O<program number>; Sinumerik, unwrapped:
//!                                        %_N_<NAME>_MPF and ;$PATH=/_N_MPF_DIR)
//! (PRESTON DWELL PROGRAM)  (DIALECT ISO FEED MODE PER-MINUTE)  ... header comments ...
//! N1 G17 G21 G40 G80 G90 G94            safe start, or the profile's start blocks
//! N2 G17 G21 G54 G90 G94                plane, units, work offset, absolute, feed mode (G93)
//! [N.. S<rpm> M3|M4] [N.. M8|M7]        spindle, coolant: one M word a block
//! N3 G00 Z<clearance plane>             up first, wherever the tool is
//! N4 G00 X<x0> Y<y0> [B<b0>]            above the run-in start
//! N5 G01 Z<z0> F<plunge feed>           plunge to the run-in start
//! (DWELL 0 <t_0> S AT <x> <y>)          stretch 0: two blocks at one feed
//! N6 G01 X.. Y.. Z.. [B..] F<f_0>       run-in start -> point 0
//! N7 G01 X.. Y.. Z.. [B..] F<f_0>       point 0 -> boundary 1
//! (DWELL 1 <t_1> S AT <x> <y>)
//! ...
//! (END DWELL)
//! Nk G00 Z<clearance plane>             retract
//! [G94] [M9] [M5] [end blocks] M30      feed per minute again after G93; the program end
//! %
//! ```
//!
//! Comments never hold a character that ends a block or a comment in any dialect
//! ([`Dialect::comment`]); times in them have 7 significant digits, coordinates the program's
//! decimals.
//!
//! Stretch `j` (boundary `j` -> point `j` -> boundary `j + 1`, lengths `L1`, `L2` from the
//! coordinates as written) gets `F = 60 (L1 + L2) / t_j` under `G94`, so that both blocks take
//! `t_j` together, or `F = 60 / (t_j L_k / (L1 + L2))` per block under `G93`. `F` keeps at least
//! 3 decimals and as many more as a relative rounding of at most `1e-4` needs (at most 9), so no
//! block time moves by more than 0.01% through formatting; it is never `0` and never above
//! `v_max_mm_per_min`. A stretch whose tool-centre move would need more than `v_max` is written at
//! `v_max` (it then takes longer than planned; counted in [`Written::slowed_stretches`]).
//!
//! # Circular moves
//!
//! With [`crate::machine::nc::NcSettings::arc_tolerance_mm`] the writer looks for runs of at
//! least [`MIN_ARC_POINTS`] consecutive dwell points whose tool centres (as written) lie within
//! the tolerance of one circle in the XY plane (algebraic least-squares circle of Kasa, *IEEE
//! Trans. Instrum. Meas.* 25, 1976, checked point by point), at one Z and one B, turning the same
//! way by less than 90 degrees per step, radius at most [`MAX_ARC_RADIUS_MM`]. Inside a run the
//! stretch boundaries move from the chord midpoints onto the circle (mid-angle, mean radius of
//! the two points) and both blocks of each stretch are `G02`/`G03` with the centre as `I J`
//! offsets (the same 4 decimals as the coordinates). The block lengths are the arc lengths the
//! reader computes from the written words ([`super::program::arc_length_mm`]), so the feed
//! contract above holds per stretch exactly as for straight blocks.

use super::dialect::{Dialect, FeedMode};
use super::program::{arc_length_mm, ArcMove};
use crate::error::{Error, Result};
use crate::machine::fixed;
use crate::machine::nc::{NcProgram, NcSettings};
use rayon::prelude::*;

/// Smallest number of decimals of `F`.
pub const MIN_FEED_DECIMALS: usize = 3;
/// Largest number of decimals of `F`.
pub const MAX_FEED_DECIMALS: usize = 9;
/// Largest relative change of a block time through the formatting of `F`.
pub const FEED_ROUNDING: f64 = 1e-4;

/// Fewest consecutive dwell points written as a circular run.
pub const MIN_ARC_POINTS: usize = 5;
/// Largest radius written as a circular move, mm (flatter runs stay straight).
pub const MAX_ARC_RADIUS_MM: f64 = 1e4;
pub use crate::machine::nc::MAX_ARC_TOLERANCE_MM;

/// A circular run of dwell points `first..=last` about `centre`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArcRun {
    /// First dwell point of the run.
    pub first: usize,
    /// Last dwell point of the run.
    pub last: usize,
    /// Centre, mm.
    pub centre_mm: [f64; 2],
    /// Radius, mm.
    pub radius_mm: f64,
    /// Counter-clockwise seen from +Z.
    pub ccw: bool,
}

/// Algebraic least-squares circle (Kasa) through `pts` (shifted to the first for conditioning):
/// centre and radius, or `None` when the points are (nearly) collinear.
fn kasa_circle(pts: &[[f64; 2]]) -> Option<([f64; 2], f64)> {
    let o = *pts.first()?;
    let mut m = [[0.0f64; 3]; 3];
    let mut rhs = [0.0f64; 3];
    for p in pts {
        let (u, v) = (p[0] - o[0], p[1] - o[1]);
        let z = u * u + v * v;
        let row = [u, v, 1.0];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] += row[i] * row[j];
            }
            rhs[i] -= row[i] * z;
        }
    }
    let det3 = |a: &[[f64; 3]; 3]| {
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    };
    let d = det3(&m);
    let scale = m[0][0].max(m[1][1]).max(1.0);
    if !(d.abs() > 1e-12 * scale * scale * m[2][2]) {
        return None;
    }
    let mut sol = [0.0; 3];
    for (k, s) in sol.iter_mut().enumerate() {
        let mut a = m;
        for i in 0..3 {
            a[i][k] = rhs[i];
        }
        *s = det3(&a) / d;
    }
    let c = [-0.5 * sol[0], -0.5 * sol[1]];
    let r2 = c[0] * c[0] + c[1] * c[1] - sol[2];
    (r2 > 0.0).then(|| ([c[0] + o[0], c[1] + o[1]], r2.sqrt()))
}

/// Signed turn of the chords `a b`, `b c` (cross product) if the turn is below 90 degrees.
fn turn_sign(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> Option<f64> {
    let u = [b[0] - a[0], b[1] - a[1]];
    let v = [c[0] - b[0], c[1] - b[1]];
    let dot = u[0] * v[0] + u[1] * v[1];
    let cross = u[0] * v[1] - u[1] * v[0];
    (dot > 0.0 && cross != 0.0).then_some(cross.signum())
}

/// Whether every point of `pts` lies within `tol` of the circle and the run turns one way.
fn run_fits(pts: &[[f64; 2]], c: [f64; 2], r: f64, tol: f64, sign: f64) -> bool {
    pts.iter()
        .all(|p| ((p[0] - c[0]).hypot(p[1] - c[1]) - r).abs() <= tol)
        && pts
            .windows(3)
            .all(|w| turn_sign(w[0], w[1], w[2]) == Some(sign))
}

/// Circular runs of `xy` (tool centres as written) with equal `level` (Z and B as written) within
/// `tol` (module documentation): greedy, each run grown point by point while the refitted circle
/// holds every point.
pub fn find_arc_runs(xy: &[[f64; 2]], level: &[(f64, Option<f64>)], tol: f64) -> Vec<ArcRun> {
    let n = xy.len();
    let mut runs = Vec::new();
    let mut a = 0usize;
    while a + MIN_ARC_POINTS <= n {
        let mut e = a + MIN_ARC_POINTS - 1;
        let same = |i: usize| level[i] == level[a];
        let ok = |e: usize| -> Option<([f64; 2], f64, f64)> {
            if !(a..=e).all(same) {
                return None;
            }
            let pts = &xy[a..=e];
            let (c, r) = kasa_circle(pts)?;
            let sign = turn_sign(pts[0], pts[1], pts[2])?;
            (r <= MAX_ARC_RADIUS_MM && run_fits(pts, c, r, tol, sign)).then_some((c, r, sign))
        };
        let Some(mut fit) = ok(e) else {
            a += 1;
            continue;
        };
        while e + 1 < n {
            match ok(e + 1) {
                Some(f) => {
                    fit = f;
                    e += 1;
                }
                None => break,
            }
        }
        runs.push(ArcRun {
            first: a,
            last: e,
            centre_mm: fit.0,
            radius_mm: fit.1,
            ccw: fit.2 > 0.0,
        });
        a = e + 1;
    }
    runs
}

/// A written program and what the writer had to change.
#[derive(Debug, Clone, PartialEq)]
pub struct Written {
    /// The program text.
    pub text: String,
    /// Feed blocks (linear moves) in the program.
    pub feed_blocks: usize,
    /// Stretches programmed at `v_max` because their tool-centre move needed more than
    /// `v_max (1 + FEED_ROUNDING)`.
    pub slowed_stretches: usize,
    /// Stretches written as one block (boundary to boundary through their collinear point)
    /// because a half would have been shorter than the block time.
    pub merged_stretches: usize,
    /// Largest programmed / planned time of a slowed stretch (1 when none).
    pub max_slowdown: f64,
    /// Programmed time of the dwell stretches, s.
    pub stretch_time_s: f64,
    /// Programmed time of the plunge, s.
    pub plunge_time_s: f64,
    /// Circular blocks (`G02`/`G03`) among the feed blocks.
    pub arc_blocks: usize,
    /// Circular runs of dwell points written with them.
    pub arc_runs: usize,
}

/// The text of `program` with `notes` as extra header comments (module documentation).
pub fn program_text(program: &NcProgram, notes: &[String]) -> Result<String> {
    write_program(program, notes).map(|w| w.text)
}

/// A pose as written: coordinates rounded to the program's decimals, and their words.
#[derive(Debug, Clone)]
struct Pose {
    xyz: [f64; 3],
    b: Option<f64>,
    words: String,
}

/// `v` as written with `decimals` and the value it stands for.
fn as_written(v: f64, decimals: usize) -> (String, f64) {
    let text = fixed(v, decimals);
    let value = text.parse().unwrap_or(v);
    (text, value)
}

impl Pose {
    fn new(tool_mm: [f64; 3], b_deg: Option<f64>, decimals: usize) -> Self {
        let [(xs, x), (ys, y), (zs, z)] = tool_mm.map(|v| as_written(v, decimals));
        let mut words = format!("X{xs} Y{ys} Z{zs}");
        let b = b_deg.map(|b| {
            let (bs, bv) = as_written(b, decimals);
            words.push_str(" B");
            words.push_str(&bs);
            bv
        });
        Self {
            xyz: [x, y, z],
            b,
            words,
        }
    }

    /// Programmed path length of the move from `self` to `to` in `dialect`.
    fn length_to(&self, to: &Pose, dialect: Dialect) -> f64 {
        let d = [
            to.xyz[0] - self.xyz[0],
            to.xyz[1] - self.xyz[1],
            to.xyz[2] - self.xyz[2],
        ];
        let db = match (self.b, to.b) {
            (Some(a), Some(b)) => b - a,
            _ => 0.0,
        };
        dialect.path_length_mm(d, db)
    }
}

/// Whether `p` lies on the segment `a -> b` to the written resolution (half a unit of the
/// last coordinate decimal, per axis) and the rotary axis moves uniformly.
fn collinear(a: &Pose, p: &Pose, b: &Pose, decimals: usize) -> bool {
    let tol = 0.5 * 10f64.powi(-(decimals as i32)) * 3f64.sqrt();
    let ab = [
        b.xyz[0] - a.xyz[0],
        b.xyz[1] - a.xyz[1],
        b.xyz[2] - a.xyz[2],
    ];
    let ap = [
        p.xyz[0] - a.xyz[0],
        p.xyz[1] - a.xyz[1],
        p.xyz[2] - a.xyz[2],
    ];
    let l2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2];
    if l2 == 0.0 {
        return false;
    }
    let f = (ap[0] * ab[0] + ap[1] * ab[1] + ap[2] * ab[2]) / l2;
    if !(0.0..=1.0).contains(&f) {
        return false;
    }
    let off = (0..3)
        .map(|k| (ap[k] - f * ab[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    let rotary = match (a.b, p.b, b.b) {
        (Some(x), Some(y), Some(z)) => (y - (x + f * (z - x))).abs() <= 1e-3,
        _ => true,
    };
    off <= tol && rotary
}

/// `F` as written and its value: at least [`MIN_FEED_DECIMALS`], enough for a relative rounding
/// of [`FEED_ROUNDING`]; rounded down when `cap` would be exceeded.
pub fn feed_word(f: f64, cap: Option<f64>) -> Result<(String, f64)> {
    if !(f.is_finite() && f > 0.0) {
        return Err(Error::invalid("feed", format!("{f} cannot be programmed")));
    }
    let need = (-(2.0 * FEED_ROUNDING * f).log10()).ceil();
    let d = if need.is_finite() && need > MIN_FEED_DECIMALS as f64 {
        (need as usize).min(MAX_FEED_DECIMALS)
    } else {
        MIN_FEED_DECIMALS
    };
    let mut text = fixed(f, d);
    let mut value: f64 = text.parse().unwrap_or(f);
    if let Some(c) = cap {
        if value > c {
            let scale = 10f64.powi(d as i32);
            text = fixed((f.min(c) * scale).floor() / scale, d);
            value = text.parse().unwrap_or(c);
        }
    }
    if !(value > 0.0) || ((value - f) / f).abs() > 10.0 * FEED_ROUNDING {
        return Err(Error::invalid(
            "feed",
            format!(
                "{f} needs more than {MAX_FEED_DECIMALS} decimals of F; \
                 use --feed-mode inverse-time or re-solve with a higher v_min"
            ),
        ));
    }
    Ok((text, value))
}

/// A time in a comment: at least 3 decimals and 7 significant digits, at most 9 decimals.
fn time_text(t: f64) -> String {
    let digits = if t > 0.0 && t.is_finite() {
        (6.0 - t.log10().floor()).clamp(3.0, 9.0) as usize
    } else {
        3
    };
    fixed(t, digits)
}

/// The spindle speed as an `S` word: whole rpm (Fanuc refuses a decimal point in `S`).
fn spindle_word(rpm: f64) -> String {
    format!("{}", rpm.round().max(1.0) as u64)
}

/// Writes the program (module documentation).
pub fn write_program(program: &NcProgram, notes: &[String]) -> Result<Written> {
    let mut w = Writer::new(program)?;
    w.place_arcs();
    for j in 0..w.at.len() {
        w.stretch(j)?;
    }
    let plane = w.clearance_plane();
    let plunge_word = w.plunge_word(plane)?;
    let code = w.blocks(plane, &plunge_word);
    let header = w.header(notes, plane);
    let text = w.numbered_text(&header, &code);
    w.written.text = text;
    Ok(w.written)
}

/// The writer's state while it turns one program into text: the poses as written, the
/// circular runs, the stretches' blocks so far and what had to change.
struct Writer<'a> {
    program: &'a NcProgram,
    s: &'a NcSettings,
    d: Dialect,
    fm: FeedMode,
    dec: usize,
    /// Stretch boundaries as written (moved onto the circle inside a circular run).
    bnd: Vec<Pose>,
    /// Dwell points as written.
    at: Vec<Pose>,
    /// The circular run of each dwell point.
    arc_of: Vec<Option<ArcRun>>,
    /// The dwell blocks and their comments, unnumbered.
    body: Vec<String>,
    written: Written,
    /// Smallest and largest programmed tool-centre feed of a stretch, mm/min.
    f_lo: f64,
    f_hi: f64,
}

/// The feed blocks of one stretch before they are written: their lengths, feed words and
/// times, and whether the stretch is one block (boundary to boundary) instead of two.
struct StretchBlocks {
    lens: [f64; 2],
    words: [String; 2],
    times: [f64; 2],
    count: usize,
    merged: bool,
}

impl<'a> Writer<'a> {
    fn new(program: &'a NcProgram) -> Result<Self> {
        let s = &program.settings;
        let dec = s.decimals;
        let n = program.points.len();
        if n == 0 || program.boundaries.len() != n + 1 {
            return Err(Error::invalid("program", "no dwell points to write"));
        }
        // Each pose on its own (formatting and reading back its words), in parallel; the
        // collected order is the points' own.
        let bnd: Vec<Pose> = program
            .boundaries
            .par_iter()
            .map(|b| Pose::new(b.tool_mm, b.b_deg, dec))
            .collect();
        let at: Vec<Pose> = program
            .points
            .par_iter()
            .map(|p| Pose::new(p.tool_mm, p.b_deg, dec))
            .collect();
        Ok(Self {
            program,
            s,
            d: s.dialect,
            fm: s.feed_mode,
            dec,
            bnd,
            at,
            arc_of: vec![None; n],
            body: Vec::with_capacity(3 * n + 8),
            written: Written {
                text: String::new(),
                feed_blocks: 0,
                slowed_stretches: 0,
                merged_stretches: 0,
                max_slowdown: 1.0,
                stretch_time_s: 0.0,
                plunge_time_s: 0.0,
                arc_blocks: 0,
                arc_runs: 0,
            },
            f_lo: f64::INFINITY,
            f_hi: 0.0,
        })
    }

    /// Circular runs: boundaries inside a run move onto its circle; `arc_of[j]` is the run of
    /// dwell point j (module documentation).
    fn place_arcs(&mut self) {
        let Some(tol) = self.s.arc_tolerance_mm else {
            return;
        };
        let at = &self.at;
        let xy: Vec<[f64; 2]> = at.iter().map(|p| [p.xyz[0], p.xyz[1]]).collect();
        let level: Vec<(f64, Option<f64>)> = at.iter().map(|p| (p.xyz[2], p.b)).collect();
        for run in find_arc_runs(&xy, &level, tol) {
            self.written.arc_runs += 1;
            let c = run.centre_mm;
            self.arc_of[run.first..=run.last].fill(Some(run));
            for j in run.first + 1..=run.last {
                let (p, q) = (xy[j - 1], xy[j]);
                let (ap, aq) = (
                    (p[1] - c[1]).atan2(p[0] - c[0]),
                    (q[1] - c[1]).atan2(q[0] - c[0]),
                );
                let mut d = aq - ap;
                d -= std::f64::consts::TAU * (d / std::f64::consts::TAU).round();
                let ang = ap + 0.5 * d;
                let r = 0.5 * ((p[0] - c[0]).hypot(p[1] - c[1]) + (q[0] - c[0]).hypot(q[1] - c[1]));
                self.bnd[j] = Pose::new(
                    [c[0] + r * ang.cos(), c[1] + r * ang.sin(), at[j].xyz[2]],
                    at[j].b,
                    self.dec,
                );
            }
        }
    }

    /// The circle of the first (`second == false`) or second block of stretch `j` when both
    /// its ends lie on one run, with its I J words.
    fn arc_block(&self, j: usize, second: bool) -> Option<(ArcMove, String)> {
        let run = self.arc_of[j]?;
        let inside = if second { j < run.last } else { j > run.first };
        if !inside {
            return None;
        }
        let start = if second { &self.at[j] } else { &self.bnd[j] };
        let (is, iv) = as_written(run.centre_mm[0] - start.xyz[0], self.dec);
        let (js, jv) = as_written(run.centre_mm[1] - start.xyz[1], self.dec);
        Some((
            ArcMove {
                centre_mm: [start.xyz[0] + iv, start.xyz[1] + jv],
                ccw: run.ccw,
            },
            format!(" I{is} J{js}"),
        ))
    }

    /// Writes stretch `j`: its dwell comment and its feed blocks.
    fn stretch(&mut self, j: usize) -> Result<()> {
        let p = &self.program.points[j];
        let t = p.dwell_s;
        self.body.push(self.d.comment(&format!(
            "DWELL {j} {} S AT {} {}",
            time_text(t),
            fixed(p.x_mm, self.dec),
            fixed(p.y_mm, self.dec)
        )));
        let arcs = [self.arc_block(j, false), self.arc_block(j, true)];
        let lens = self.half_lengths(j, &arcs);
        let len = lens[0] + lens[1];
        if len == 0.0 {
            if t > 0.0 {
                return Err(Error::invalid(
                    "dwell_s",
                    format!(
                        "dwell point {j}: {t} s on a stretch of zero length (the path repeats \
                         the point or has a single point); a feed move cannot deliver it"
                    ),
                ));
            }
            return Ok(());
        }
        if !(t > 0.0 && t.is_finite()) {
            return Err(Error::invalid(
                "dwell_s",
                format!("dwell point {j}: {t} s over {len} mm needs an infinite feed"),
            ));
        }
        let t_run = self.run_time(t, len);
        let blocks = self.feed_blocks(j, lens, t_run, &arcs)?;
        self.emit(j, &blocks, &arcs)
    }

    /// Programmed lengths of the two blocks of stretch `j` (boundary -> point -> boundary).
    fn half_lengths(&self, j: usize, arcs: &[Option<(ArcMove, String)>; 2]) -> [f64; 2] {
        let halves = [(&self.bnd[j], &self.at[j]), (&self.at[j], &self.bnd[j + 1])];
        let mut lens = [0.0; 2];
        for k in 0..2 {
            let (a, b) = halves[k];
            lens[k] = match &arcs[k] {
                Some((m, _)) => arc_length_mm(a.xyz, b.xyz, m),
                None => a.length_to(b, self.d),
            };
        }
        lens
    }

    /// The time the stretch of planned time `t` and length `len` runs: `t`, or longer when its
    /// feed would exceed `v_max` (counted as slowed).
    fn run_time(&mut self, t: f64, len: f64) -> f64 {
        let mut t_run = t;
        let need = 60.0 * len / t;
        if let Some(v_max) = self.s.v_max_mm_per_min {
            if need > v_max {
                t_run = 60.0 * len / v_max;
                // Within the rounding of F (a solver's bound met to its tolerance) this is the
                // cap of the F word, not a slowed stretch.
                if need > v_max * (1.0 + FEED_ROUNDING) {
                    self.written.slowed_stretches += 1;
                    self.written.max_slowdown = self.written.max_slowdown.max(t_run / t);
                }
            }
        }
        t_run
    }

    /// The blocks of stretch `j`: boundary -> point -> boundary, or one block boundary ->
    /// boundary when a half would be shorter than the controller's block time and the point
    /// lies on the straight line between the boundaries (within the written resolution); with
    /// their feed words and times.
    fn feed_blocks(
        &mut self,
        j: usize,
        lens: [f64; 2],
        t_run: f64,
        arcs: &[Option<(ArcMove, String)>; 2],
    ) -> Result<StretchBlocks> {
        let min_block_s = 1e-3 * self.s.min_block_time_ms;
        let len = lens[0] + lens[1];
        let shortest_s = lens
            .iter()
            .filter(|&&l| l > 0.0)
            .map(|l| t_run * l / len)
            .fold(f64::INFINITY, f64::min);
        let merged = shortest_s < min_block_s * (1.0 - FEED_ROUNDING)
            && arcs.iter().all(Option::is_none)
            && collinear(&self.bnd[j], &self.at[j], &self.bnd[j + 1], self.dec);
        let (blens, count) = if merged {
            self.written.merged_stretches += 1;
            let l = self.bnd[j].length_to(&self.bnd[j + 1], self.d);
            ([l, 0.0], 1)
        } else {
            (lens, 2)
        };
        let len_run: f64 = blens.iter().sum();
        let mut times = [0.0; 2];
        let mut words = [String::new(), String::new()];
        match self.fm {
            FeedMode::PerMinute => {
                let (w, f) = feed_word(60.0 * len_run / t_run, self.s.v_max_mm_per_min)?;
                for k in 0..count {
                    times[k] = 60.0 * blens[k] / f;
                    words[k] = w.clone();
                }
            }
            FeedMode::InverseTime => {
                for k in 0..count {
                    if blens[k] > 0.0 {
                        let (w, f) = feed_word(60.0 / (t_run * blens[k] / len_run), None)?;
                        times[k] = 60.0 / f;
                        words[k] = w;
                    }
                }
            }
        }
        Ok(StretchBlocks {
            lens: blens,
            words,
            times,
            count,
            merged,
        })
    }

    /// Appends the blocks of stretch `j` to the body, refusing a block shorter than the
    /// controller's block time.
    fn emit(
        &mut self,
        j: usize,
        blocks: &StretchBlocks,
        arcs: &[Option<(ArcMove, String)>; 2],
    ) -> Result<()> {
        let (s, d) = (self.s, self.d);
        let p = &self.program.points[j];
        let min_block_s = 1e-3 * s.min_block_time_ms;
        let ends = if blocks.merged {
            [&self.bnd[j + 1], &self.bnd[j + 1]]
        } else {
            [&self.at[j], &self.bnd[j + 1]]
        };
        let StretchBlocks {
            lens: blens,
            words,
            times,
            count,
            merged,
        } = blocks;
        for k in 0..*count {
            if blens[k] == 0.0 {
                continue;
            }
            if times[k] < min_block_s * (1.0 - FEED_ROUNDING) {
                return Err(Error::invalid(
                    "min_block_time_ms",
                    format!(
                        "dwell point {j} (x {} y {} mm): a block of {:.3} ms is shorter than the \
                         {} ms the controller needs; lower v_max, coarsen the path or set \
                         --min-block-time-ms",
                        p.x_mm,
                        p.y_mm,
                        1e3 * times[k],
                        s.min_block_time_ms
                    ),
                ));
            }
            match (&arcs[k], merged) {
                (Some((m, ij)), false) => {
                    self.body.push(format!(
                        "{} {}{ij} F{}",
                        d.arc_word(m.ccw),
                        ends[k].words,
                        words[k]
                    ));
                    self.written.arc_blocks += 1;
                }
                _ => self.body.push(format!(
                    "{} {} F{}",
                    d.linear_word(),
                    ends[k].words,
                    words[k]
                )),
            }
            self.written.feed_blocks += 1;
            self.written.stretch_time_s += times[k];
        }
        let len_run: f64 = blens.iter().sum();
        let programmed = 60.0 * len_run / (times[0] + times[1]);
        self.f_lo = self.f_lo.min(programmed);
        self.f_hi = self.f_hi.max(programmed);
        Ok(())
    }

    /// The clearance plane as written: the highest tool-centre Z plus the clearance.
    fn clearance_plane(&self) -> f64 {
        let program = self.program;
        let top = program
            .points
            .iter()
            .map(|p| p.tool_mm[2])
            .chain(program.boundaries.iter().map(|b| b.tool_mm[2]))
            .fold(f64::NEG_INFINITY, f64::max);
        as_written(top + self.s.clearance_mm, self.dec).1
    }

    /// The `F` word of the plunge from the clearance plane to the first boundary, with its
    /// time counted.
    fn plunge_word(&mut self, plane: f64) -> Result<String> {
        let s = self.s;
        let drop = plane - self.bnd[0].xyz[2];
        Ok(match self.fm {
            FeedMode::PerMinute => {
                let (w, f) = feed_word(s.plunge_feed_mm_per_min, None)?;
                self.written.plunge_time_s = 60.0 * drop / f;
                w
            }
            FeedMode::InverseTime => {
                let (w, f) = feed_word(s.plunge_feed_mm_per_min / drop, None)?;
                self.written.plunge_time_s = 60.0 / f;
                w
            }
        })
    }

    /// The program's blocks, unnumbered: start, approach, the dwell body, retract and end.
    fn blocks(&mut self, plane: f64, plunge_word: &str) -> Vec<String> {
        let (s, d, fm, dec) = (self.s, self.d, self.fm, self.dec);
        let start = &self.bnd[0];
        let body = std::mem::take(&mut self.body);
        let mut code: Vec<String> = Vec::with_capacity(body.len() + 12);
        // Safe start (or the profile's start blocks), then plane, units, work offset, absolute and
        // the feed mode whatever the start blocks left; spindle and coolant one M word a block (the
        // Fanuc default allows one M code per block).
        code.extend(s.start_blocks_or_default());
        let mut modes = format!("G17 {}", d.metric_word());
        if let Some(w) = s.work_offset.word() {
            modes.push(' ');
            modes.push_str(w);
        }
        modes.push_str(&format!(" G90 {}", fm.word()));
        code.push(modes);
        if let Some(rpm) = s.spindle_rpm {
            code.push(format!(
                "S{} {}",
                spindle_word(rpm),
                s.spindle_direction.word()
            ));
        }
        if let Some(m) = s.coolant.word() {
            code.push(m.to_string());
        }
        code.push(format!("{} Z{}", d.rapid_word(), fixed(plane, dec)));
        let mut above = format!(
            "{} X{} Y{}",
            d.rapid_word(),
            fixed(start.xyz[0], dec),
            fixed(start.xyz[1], dec)
        );
        if let Some(b) = start.b {
            above.push_str(&format!(" B{}", fixed(b, dec)));
        }
        code.push(above);
        code.push(format!(
            "{} Z{} F{plunge_word}",
            d.linear_word(),
            fixed(start.xyz[2], dec)
        ));
        code.extend(body);
        code.push(d.comment("END DWELL"));
        code.push(format!("{} Z{}", d.rapid_word(), fixed(plane, dec)));
        // Modal states back to the safe-start state: feed per minute after inverse time.
        if fm == FeedMode::InverseTime {
            code.push(FeedMode::PerMinute.word().to_string());
        }
        if s.coolant.word().is_some() {
            code.push("M9".into());
        }
        if s.spindle_rpm.is_some() {
            code.push("M5".into());
        }
        code.extend(s.end_blocks.iter().cloned());
        code.push(d.program_end().to_string());
        code
    }

    /// The header comments (without their comment delimiters).
    fn header(&self, notes: &[String], plane: f64) -> Vec<String> {
        let (s, d, fm, dec) = (self.s, self.d, self.fm, self.dec);
        let written = &self.written;
        let pts = &self.program.points;
        let sched = &self.program.schedule;
        let mut header = vec![
            "PRESTON DWELL PROGRAM".to_string(),
            format!(
                "DIALECT {} FEED MODE {}",
                d.name().to_uppercase(),
                fm.name().to_uppercase()
            ),
            match fm {
                FeedMode::PerMinute => "UNITS MM, F MM/MIN, TIME S, ANGLE DEG".into(),
                FeedMode::InverseTime => {
                    "UNITS MM, F = 1 / BLOCK TIME IN MINUTES, TIME S, ANGLE DEG".into()
                }
            },
        ];
        header.extend(notes.iter().cloned());
        header.push(format!("POINTS {}", pts.len()));
        header.push(format!(
            "TOOL RADIUS {} MM, TOOL CENTRE = CONTACT + R * NORMAL",
            fixed(s.tool_radius_mm, dec)
        ));
        if let Some(t) = s.arc_tolerance_mm {
            header.push(format!(
                "CIRCULAR MOVES G17 I J: {} RUNS, {} BLOCKS, TOLERANCE {} MM",
                written.arc_runs,
                written.arc_blocks,
                fixed(t, 6)
            ));
        }
        if s.compensation.is_some() {
            let (lo, hi) = pts.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| {
                (a.min(p.delta_mm), b.max(p.delta_mm))
            });
            header.push(format!(
                "NORMAL DISPLACEMENT {} .. {} MM",
                fixed(lo, dec),
                fixed(hi, dec)
            ));
        }
        header.push(format!("TOTAL DWELL {} S", fixed(sched.total_dwell_s, 3)));
        header.push(format!(
            "MACHINING TIME {} S: DWELL STRETCHES {} S, PLUNGE {} S, RAPIDS NOT INCLUDED",
            fixed(written.stretch_time_s + written.plunge_time_s, 3),
            fixed(written.stretch_time_s, 3),
            fixed(written.plunge_time_s, 3)
        ));
        if self.f_hi > 0.0 {
            header.push(format!(
                "TOOL-CENTRE FEED {} .. {} MM/MIN",
                fixed(self.f_lo, 3),
                fixed(self.f_hi, 3)
            ));
        }
        header.push(format!("CLEARANCE PLANE Z {} MM", fixed(plane, dec)));
        header.push(format!(
            "WORK OFFSET {}",
            s.work_offset
                .word()
                .unwrap_or("AS ACTIVE ON THE CONTROLLER")
        ));
        header
            .push("EACH DWELL COMMENT: POINT, PLANNED S, CONTACT X Y MM, ITS BLOCKS FOLLOW".into());
        header
    }

    /// The program text: the dialect's wrapper, the header as comments, then the blocks,
    /// numbered when the dialect's block numbers reach.
    fn numbered_text(&self, header: &[String], code: &[String]) -> String {
        let (s, d) = (self.s, self.d);
        let mut out = String::with_capacity(40 * code.len() + 1024);
        let mut line = |text: &str| {
            out.push_str(text);
            out.push('\n');
        };
        if d.percent_wrapped() {
            line("%");
        }
        match d {
            Dialect::Fanuc => line(&format!("O{:04}", s.program_number)),
            Dialect::Sinumerik => {
                line(&format!("%_N_{}_MPF", s.program_name.to_uppercase()));
                line(";$PATH=/_N_MPF_DIR");
            }
            _ => {}
        }
        for h in header {
            line(&d.comment(h));
        }
        let numbered = code.len() as u64 <= d.max_block_number();
        let mut k = 0u64;
        for c in code {
            if c.starts_with('(') || c.starts_with(';') || !numbered {
                line(c);
            } else {
                k += 1;
                line(&format!("N{k} {c}"));
            }
        }
        if d.percent_wrapped() {
            line("%");
        }
        out
    }
}

/// The program's G-code, where the program model meets the writer.
impl NcProgram {
    /// Writes the G-code program ([`program_text`]).
    pub fn write_gcode(&self, w: &mut dyn std::io::Write) -> Result<()> {
        self.write_gcode_with_notes(&[], w)
    }

    /// As [`NcProgram::write_gcode`], with extra comment lines (the job summary: input files,
    /// surface) in the header.
    pub fn write_gcode_with_notes(
        &self,
        notes: &[String],
        w: &mut dyn std::io::Write,
    ) -> Result<()> {
        let text = program_text(self, notes)?;
        w.write_all(text.as_bytes())
            .map_err(|e| Error::invalid("program output", e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feed_words_keep_four_significant_figures() {
        for f in [0.0173, 0.5, 3.17159, 17.0, 2999.99, 1e-4] {
            let (w, v) = feed_word(f, None).unwrap();
            assert!(((v - f) / f).abs() <= FEED_ROUNDING, "{f} -> {w}");
            assert!(w.contains('.'));
        }
        let (w, v) = feed_word(3000.0004, Some(3000.0)).unwrap();
        assert!(v <= 3000.0, "{w}");
        assert!(feed_word(0.0, None).is_err());
        assert!(feed_word(1e-12, None).is_err());
    }
}
