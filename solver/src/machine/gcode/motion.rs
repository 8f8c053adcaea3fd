//! The motion a controller executes for a read-back [`Program`]: each block's duration, the time
//! spent in each dwell stretch, and the tool's contact positions sampled along the way for the
//! removal integral.
//!
//! Two models:
//! - [`Kinematics::ProgrammedFeed`]: every feed block runs at its programmed feed from start to
//!   end (duration = programmed time), as the program states.
//! - [`Kinematics::Trapezoidal`]: the controller limits the path acceleration to `a` (mm/s^2)
//!   with look-ahead. The speed at a junction is at most the smaller of the two blocks' cruise
//!   speeds, zero where the path turns by more than `corner_angle_deg`, at rapids, pauses and the
//!   program ends; a forward and a backward pass make every junction speed reachable,
//!   `v_out^2 <= v_in^2 + 2 a L` (the standard look-ahead planner, e.g. Altintas, *Manufacturing
//!   Automation*, 2nd ed., ch. 6). Each block then accelerates at `a` from its entry speed to at
//!   most its cruise speed `L / T` and decelerates at `a` to its exit speed.
//!
//! Circular blocks run along their arc ([`Block::point_at`]); their length is the arc length and
//! the turn at a junction is measured between the tangents. The path acceleration limit applies
//! along the arc; the centripetal acceleration `v^2 / r` is not limited by this model.
//!
//! Removal sampling: each contact block is cut into `ceil(L / h)` equal pieces of arc length; a
//! sample at each piece's midpoint carries the time the executed motion spends in that piece
//! (exact for both models: the time at arc length `s` has a closed form on each phase). This is
//! the midpoint rule of the sweep integral, `O(h^2)`; pauses and rotary-only blocks put their
//! time at their position.

use super::program::{Block, BlockKind, Program};
use crate::error::{Error, Result};
use crate::machine::PartGeometry;

pub use crate::kinematics::Kinematics;

/// One block's executed speed profile: accelerate, cruise, decelerate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Profile {
    /// Length of the block's tool-centre move, mm (0 for pauses and rotary-only moves).
    pub length_mm: f64,
    /// Entry, peak and exit speed, mm/s.
    pub speeds_mm_per_s: [f64; 3],
    /// Acceleration used, mm/s^2 (`f64::INFINITY` for the programmed-feed model).
    pub accel_mm_per_s2: f64,
    /// Executed duration, s.
    pub time_s: f64,
}

impl Profile {
    /// Time from the block's start until arc length `s` (mm) is reached.
    pub fn time_at(&self, s: f64) -> f64 {
        let [v0, vp, v1] = self.speeds_mm_per_s;
        let l = self.length_mm;
        if l <= 0.0 {
            return if s <= 0.0 { 0.0 } else { self.time_s };
        }
        if !self.accel_mm_per_s2.is_finite() {
            return self.time_s * (s / l).clamp(0.0, 1.0);
        }
        let a = self.accel_mm_per_s2;
        let s_acc = ((vp * vp - v0 * v0) / (2.0 * a)).max(0.0);
        let s_dec = ((vp * vp - v1 * v1) / (2.0 * a)).max(0.0);
        let s_cru = (l - s_acc - s_dec).max(0.0);
        let s = s.clamp(0.0, l);
        let t_acc = (vp - v0) / a;
        if s <= s_acc {
            return ((v0 * v0 + 2.0 * a * s).sqrt() - v0) / a;
        }
        let t_cru = if vp > 0.0 { s_cru / vp } else { 0.0 };
        if s <= s_acc + s_cru {
            return t_acc + (s - s_acc) / vp;
        }
        // Deceleration: time left from s to the end is ((v1^2 + 2 a (l - s))^0.5 - v1) / a.
        let left = ((v1 * v1 + 2.0 * a * (l - s).max(0.0)).sqrt() - v1) / a;
        let t_dec = (vp - v1) / a;
        t_acc + t_cru + t_dec - left
    }
}

/// Executed motion of a program.
#[derive(Debug, Clone, PartialEq)]
pub struct Executed {
    /// One profile per block of the program (rapids: zero time, not modelled).
    pub profiles: Vec<Profile>,
    /// Time spent in each marked stretch, s.
    pub stretch_time_s: Vec<f64>,
    /// Executed time of the feed blocks and pauses, s.
    pub total_time_s: f64,
}

fn turn_angle_deg(a: &Block, b: &Block) -> f64 {
    // Direction at the end of `a` and at the start of `b` (the chord of a straight move, the
    // tangent of a circular one).
    let da = a.tangent_at(1.0);
    let db = b.tangent_at(0.0);
    let la = (da[0] * da[0] + da[1] * da[1] + da[2] * da[2]).sqrt();
    let lb = (db[0] * db[0] + db[1] * db[1] + db[2] * db[2]).sqrt();
    if la == 0.0 || lb == 0.0 {
        return 180.0;
    }
    let c = (da[0] * db[0] + da[1] * db[1] + da[2] * db[2]) / (la * lb);
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// Executes `program` under `kinematics` (module documentation).
pub fn execute(program: &Program, kinematics: Kinematics) -> Result<Executed> {
    let blocks = &program.blocks;
    let nb = blocks.len();
    let cruise: Vec<f64> = blocks
        .iter()
        .map(|b| {
            let l = b.length_mm();
            if matches!(b.kind, BlockKind::Linear | BlockKind::Circular)
                && l > 0.0
                && b.programmed_time_s > 0.0
            {
                l / b.programmed_time_s
            } else {
                0.0
            }
        })
        .collect();
    let moving = |k: usize| cruise[k] > 0.0;
    let profiles: Vec<Profile> = match kinematics {
        Kinematics::ProgrammedFeed => (0..nb)
            .map(|k| Profile {
                length_mm: if moving(k) {
                    blocks[k].length_mm()
                } else {
                    0.0
                },
                speeds_mm_per_s: [cruise[k]; 3],
                accel_mm_per_s2: f64::INFINITY,
                time_s: blocks[k].programmed_time_s,
            })
            .collect(),
        Kinematics::Trapezoidal {
            a_max_mm_per_s2: a,
            corner_angle_deg,
        } => {
            kinematics.validate()?;
            // Junction k sits before block k (k = 0..=nb).
            let mut junction = vec![0.0f64; nb + 1];
            for k in 1..nb {
                if moving(k - 1)
                    && moving(k)
                    && turn_angle_deg(&blocks[k - 1], &blocks[k]) <= corner_angle_deg
                {
                    junction[k] = cruise[k - 1].min(cruise[k]);
                }
            }
            for k in 0..nb {
                if moving(k) {
                    let reach = (junction[k].powi(2) + 2.0 * a * blocks[k].length_mm()).sqrt();
                    junction[k + 1] = junction[k + 1].min(reach);
                }
            }
            for k in (0..nb).rev() {
                if moving(k) {
                    let reach = (junction[k + 1].powi(2) + 2.0 * a * blocks[k].length_mm()).sqrt();
                    junction[k] = junction[k].min(reach);
                }
            }
            (0..nb)
                .map(|k| {
                    let b = &blocks[k];
                    if !moving(k) {
                        return Profile {
                            length_mm: 0.0,
                            speeds_mm_per_s: [0.0; 3],
                            accel_mm_per_s2: a,
                            time_s: b.programmed_time_s,
                        };
                    }
                    let l = b.length_mm();
                    let (v0, v1) = (junction[k], junction[k + 1]);
                    let vp = cruise[k]
                        .min((0.5 * (2.0 * a * l + v0 * v0 + v1 * v1)).sqrt())
                        .max(v0.max(v1));
                    let s_acc = (vp * vp - v0 * v0) / (2.0 * a);
                    let s_dec = (vp * vp - v1 * v1) / (2.0 * a);
                    let s_cru = (l - s_acc - s_dec).max(0.0);
                    let time = (vp - v0) / a + (vp - v1) / a + s_cru / vp;
                    Profile {
                        length_mm: l,
                        speeds_mm_per_s: [v0, vp, v1],
                        accel_mm_per_s2: a,
                        time_s: time,
                    }
                })
                .collect()
        }
    };
    let stretch_time_s = (0..program.stretches.len())
        .map(|k| program.stretch_blocks(k).map(|i| profiles[i].time_s).sum())
        .collect();
    let total_time_s = profiles.iter().map(|p| p.time_s).sum();
    Ok(Executed {
        profiles,
        stretch_time_s,
        total_time_s,
    })
}

/// Tool-centre samples of the contact motion: position (mm) and time spent (s).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MotionSamples {
    /// Tool-centre x, mm.
    pub x_mm: Vec<f64>,
    /// Tool-centre y, mm.
    pub y_mm: Vec<f64>,
    /// Tool-centre z, mm.
    pub z_mm: Vec<f64>,
    /// Time the tool spends at the sample, s.
    pub time_s: Vec<f64>,
    /// Program time at the middle of the sample, s from the program's start (every block's
    /// executed time counted, in contact or not).
    pub at_s: Vec<f64>,
    /// Half of the sample's piece in plan, from its start to its end over 2, mm: the straight
    /// chord of the piece the sample stands for.
    pub half_mm: Vec<[f64; 2]>,
    /// The tool centre at the start and at the end of the sample's piece, mm (on a curved part
    /// the piece's contact chord is taken between their contact points).
    pub ends_mm: Vec<[[f64; 3]; 2]>,
}

/// Largest number of removal samples (each is a TIF column of the simulation).
pub const MAX_SAMPLES: usize = 50_000_000;

/// Samples the contact motion with pieces of at most `step_mm` (module documentation).
pub fn sample_contact(
    program: &Program,
    executed: &Executed,
    step_mm: f64,
) -> Result<MotionSamples> {
    if !(step_mm.is_finite() && step_mm > 0.0) {
        return Err(Error::invalid(
            "sample step",
            format!("must be positive, got {step_mm} mm"),
        ));
    }
    let mut count = 0usize;
    for (b, p) in program.blocks.iter().zip(&executed.profiles) {
        if b.contact {
            let pieces = (p.length_mm / step_mm).ceil().max(1.0);
            if pieces > MAX_SAMPLES as f64 {
                return Err(Error::invalid(
                    "sample step",
                    format!("{step_mm} mm gives more than {MAX_SAMPLES} samples"),
                ));
            }
            count += pieces as usize;
        }
    }
    if count > MAX_SAMPLES {
        return Err(Error::invalid(
            "sample step",
            format!("{step_mm} mm gives {count} samples, more than {MAX_SAMPLES}"),
        ));
    }
    let mut out = MotionSamples {
        x_mm: Vec::with_capacity(count),
        y_mm: Vec::with_capacity(count),
        z_mm: Vec::with_capacity(count),
        time_s: Vec::with_capacity(count),
        at_s: Vec::with_capacity(count),
        half_mm: Vec::with_capacity(count),
        ends_mm: Vec::with_capacity(count),
    };
    let mut block_start_s = 0.0;
    for (b, p) in program.blocks.iter().zip(&executed.profiles) {
        let start_s = block_start_s;
        block_start_s += p.time_s;
        if !b.contact || p.time_s <= 0.0 {
            continue;
        }
        let pieces = (p.length_mm / step_mm).ceil().max(1.0) as usize;
        let l = p.length_mm;
        let mut t_prev = 0.0;
        let mut start = b.point_at(0.0);
        for i in 0..pieces {
            let s1 = l * (i + 1) as f64 / pieces as f64;
            let t1 = if i + 1 == pieces {
                p.time_s
            } else {
                p.time_at(s1)
            };
            let f = (i as f64 + 0.5) / pieces as f64;
            let q = b.point_at(f);
            out.x_mm.push(q[0]);
            out.y_mm.push(q[1]);
            out.z_mm.push(q[2]);
            out.time_s.push(t1 - t_prev);
            out.at_s.push(start_s + 0.5 * (t1 + t_prev));
            let end = b.point_at((i + 1) as f64 / pieces as f64);
            out.half_mm
                .push([0.5 * (end[0] - start[0]), 0.5 * (end[1] - start[1])]);
            out.ends_mm.push([start, end]);
            start = end;
            t_prev = t1;
        }
    }
    Ok(out)
}

/// Executed against planned dwell over the marked stretches.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct StretchCheck {
    /// Marked stretches.
    pub stretches: usize,
    /// Sum of the planned dwells, s.
    pub planned_total_s: f64,
    /// Sum of the executed stretch times, s.
    pub executed_total_s: f64,
    /// Largest `|executed - planned| / planned` over stretches with planned dwell > 0.
    pub max_relative_error: f64,
    /// The stretch (dwell point index) where it occurs.
    pub worst_point: usize,
    /// Stretches whose executed time is more than 5% off the plan.
    pub over_5_percent: usize,
}

/// Compares the executed stretch times with the planned dwell of the markers.
pub fn check_stretches(program: &Program, executed: &Executed) -> StretchCheck {
    let mut c = StretchCheck {
        stretches: program.stretches.len(),
        ..StretchCheck::default()
    };
    for (m, &t) in program.stretches.iter().zip(&executed.stretch_time_s) {
        c.planned_total_s += m.planned_dwell_s;
        c.executed_total_s += t;
        if m.planned_dwell_s > 0.0 {
            let e = (t - m.planned_dwell_s).abs() / m.planned_dwell_s;
            if e > c.max_relative_error {
                c.max_relative_error = e;
                c.worst_point = m.point;
            }
            if e > 0.05 {
                c.over_5_percent += 1;
            }
        }
    }
    c
}

/// Contact point `(x, y)` of a tool centre `A` on `geometry` with the centre `offset_mm` along
/// the unit normal: solves `P + offset n(P) = A` in the plane by the fixed-point iteration
/// `P <- A - offset n_xy(P)`, which contracts while the offset is below the local curvature
/// radius. Errors name the tool centre when it does not converge in 100 steps.
pub fn contact_xy(
    geometry: &dyn PartGeometry,
    offset_mm: f64,
    tool_mm: [f64; 3],
) -> Result<(f64, f64)> {
    const STEP_TOL_MM: f64 = 1e-10;
    let (mut x, mut y) = (tool_mm[0], tool_mm[1]);
    if offset_mm == 0.0 {
        return Ok((x, y));
    }
    for _ in 0..100 {
        let n = geometry.unit_normal(x, y)?;
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let (nx, ny) = (
            tool_mm[0] - offset_mm * n[0] / len,
            tool_mm[1] - offset_mm * n[1] / len,
        );
        let step = (nx - x).hypot(ny - y);
        (x, y) = (nx, ny);
        if step < STEP_TOL_MM {
            return Ok((x, y));
        }
    }
    Err(Error::Geometry(format!(
        "no contact point found for the tool centre {tool_mm:?} with offset {offset_mm} mm"
    )))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::machine::gcode::dialect::Dialect;
    use crate::machine::gcode::program::StretchMark;

    const TOL: f64 = 1e-12;

    /// The stretch statistics against a hand count: executed times 0%, 4.9%, 5.1%, 30%, 49% and
    /// 60% off their plan (over and under) are 4 stretches more than 5% off, the worst 60%.
    #[test]
    fn stretch_statistics_count_the_stretches_more_than_5_percent_off() {
        let planned = [10.0, 2.0, 4.0, 1.0, 5.0, 0.5, 0.0];
        let executed = [10.0, 2.098, 3.796, 1.3, 2.55, 0.8, 0.1];
        let program = Program {
            dialect: Dialect::Iso,
            blocks: Vec::new(),
            stretches: planned
                .iter()
                .enumerate()
                .map(|(k, &t)| StretchMark {
                    point: 10 + k,
                    x_mm: 0.0,
                    y_mm: 0.0,
                    planned_dwell_s: t,
                    first_block: 0,
                })
                .collect(),
            contact_end: 0,
        };
        let run = Executed {
            profiles: Vec::new(),
            stretch_time_s: executed.to_vec(),
            total_time_s: executed.iter().sum(),
        };
        let c = check_stretches(&program, &run);
        assert_eq!(c.stretches, 7);
        assert_eq!(c.over_5_percent, 4, "{c:?}");
        assert_eq!(c.worst_point, 15);
        assert!((c.max_relative_error - 0.6).abs() < 1e-12, "{c:?}");
        assert!((c.planned_total_s - planned.iter().sum::<f64>()).abs() < TOL);
        assert!((c.executed_total_s - executed.iter().sum::<f64>()).abs() < TOL);
    }

    fn line_program(text: &str) -> Program {
        Program::parse(text, Dialect::Iso).unwrap()
    }

    #[test]
    fn a_limit_is_trapezoidal_no_limit_the_programmed_feed_and_a_bad_one_refused() {
        assert_eq!(
            Kinematics::of_limit(None, 60.0),
            Ok(Kinematics::ProgrammedFeed)
        );
        assert_eq!(
            Kinematics::of_limit(Some(500.0), 45.0),
            Ok(Kinematics::Trapezoidal {
                a_max_mm_per_s2: 500.0,
                corner_angle_deg: 45.0
            })
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = Kinematics::of_limit(Some(bad), 60.0).unwrap_err();
            assert!(e.to_string().contains("a_max_mm_per_s2"), "{e}");
            // The executor refuses the same limit.
            let k = Kinematics::Trapezoidal {
                a_max_mm_per_s2: bad,
                corner_angle_deg: 60.0,
            };
            assert_eq!(
                execute(&line_program("G0 X0 Y0 Z0\nG1 X10 F600\n"), k).unwrap_err(),
                e
            );
        }
    }

    #[test]
    fn trapezoid_on_one_block_against_closed_form() {
        // 10 mm at F600 (10 mm/s) from rest to rest at a = 20 mm/s^2:
        // ramps 0.5 s and 2.5 mm each, cruise 5 mm in 0.5 s: 1.5 s in all.
        let p = line_program("G0 X0 Y0 Z0\nG1 X10 F600\n");
        let e = execute(
            &p,
            Kinematics::Trapezoidal {
                a_max_mm_per_s2: 20.0,
                corner_angle_deg: 60.0,
            },
        )
        .unwrap();
        let prof = e.profiles[1];
        assert!((prof.time_s - 1.5).abs() < TOL, "{prof:?}");
        assert!((prof.time_at(2.5) - 0.5).abs() < TOL);
        assert!((prof.time_at(7.5) - 1.0).abs() < TOL);
        assert!((prof.time_at(10.0) - 1.5).abs() < TOL);
        // Too short to cruise: triangle, peak sqrt(a L) over 1 mm at a = 20: 2 sqrt(L / a).
        let p = line_program("G0 X0 Y0 Z0\nG1 X1 F600\n");
        let e = execute(
            &p,
            Kinematics::Trapezoidal {
                a_max_mm_per_s2: 20.0,
                corner_angle_deg: 60.0,
            },
        )
        .unwrap();
        assert!((e.profiles[1].time_s - 2.0 * (1.0f64 / 20.0).sqrt()).abs() < TOL);
    }

    #[test]
    fn samples_carry_the_executed_time() {
        let p = line_program("G0 X0 Y0 Z0\nG1 X10 F600\nG1 X10 Y3 F60\n");
        for k in [
            Kinematics::ProgrammedFeed,
            Kinematics::Trapezoidal {
                a_max_mm_per_s2: 50.0,
                corner_angle_deg: 60.0,
            },
        ] {
            let e = execute(&p, k).unwrap();
            let s = sample_contact(&p, &e, 0.1).unwrap();
            assert_eq!(s.time_s.len(), 100 + 30);
            let total: f64 = s.time_s.iter().sum();
            assert!((total - e.total_time_s).abs() < 1e-9);
        }
        // Programmed feed: 1 s + 3 s, uniform in each block.
        let e = execute(&p, Kinematics::ProgrammedFeed).unwrap();
        assert!((e.total_time_s - 4.0).abs() < TOL);
        let s = sample_contact(&p, &e, 0.1).unwrap();
        assert!((s.time_s[0] - 0.01).abs() < TOL && (s.time_s[129] - 0.1).abs() < TOL);
        assert!((s.x_mm[0] - 0.05).abs() < TOL && (s.y_mm[129] - 2.95).abs() < TOL);
    }
}
