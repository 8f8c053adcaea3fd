//! The motion of a dwell plan as samples, and the removal it produces in plan.
//!
//! Two models of the tool's motion through the plan, as `preston simulate` runs it:
//! - [`Motion::Discrete`]: the tool stands still at each dwell point `j` for `t_j` (the solver's
//!   model): `h = R t`.
//! - [`Motion::Continuous`]: the tool sweeps along the path at constant speed within the stretch of
//!   path each dwell point stands for. Dwell point `j` owns the arc of length `ds_j` from the
//!   midpoint of the segment before it to the midpoint of the segment after it, `s_{j-1} / 2`
//!   behind and `s_j / 2` ahead (the first and last points own a stretch extended straight beyond
//!   the path end, the tool's run-in and run-out); the stretches tile the path, and the tool
//!   crosses each at speed `ds_j / t_j`, as the G-code of [`crate::machine::gcode::write`] does. The
//!   removal `h(x) = sum_j (t_j / ds_j) * integral over the arc of TIF(x - p(s)) ds` is integrated
//!   by the midpoint rule with `k` samples per arc, each carrying `t_j / k` of dwell at arc offset
//!   `s = -s_{j-1}/2 + (i + 1/2) ds_j / k`. The midpoint rule converges as `O(1/k^2)` for a smooth
//!   TIF; on a raster whose pitch is well below the TIF width, `k = 8` is within a fraction of a
//!   per cent of the converged removal (tested, and reported by `preston simulate`).
//!
//! The set-up's own model of the plan at its programmed feeds ([`path_motion`]): under the swept
//! influence model each dwell point's stretch samples, each the piece of motion it stands for
//! ([`Stretches::pieces_of`]); under the point model the dwell points themselves.

use super::direct::removal_of_samples;
use super::SampledProgram;
use crate::error::{Error, Result};
use crate::influence::{InfluenceMatrix, Stretches};
use crate::observer::Observer;
use crate::path::DwellPath;
use crate::tif::InfluenceFunction;
use serde::{Deserialize, Serialize};

/// How the tool moves through a dwell program.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "mode")]
pub enum Motion {
    /// The tool dwells at the points (the solver's model).
    Discrete,
    /// The tool sweeps the path; `samples_per_point` midpoint samples per dwell point's arc.
    Continuous {
        /// Midpoint-rule samples per dwell point (>= 1).
        samples_per_point: usize,
    },
}

/// The point at signed arc-length offset `s` (mm) from dwell point `j` along the polyline; beyond
/// the ends the first and last segments are extended straight.
fn point_at(x: &[f64], y: &[f64], j: usize, s: f64) -> (f64, f64) {
    let n = x.len();
    // `b + d * (b - a) / |b - a|`: the straight extension past `b` of the segment from `a`.
    let extend = |a: usize, b: usize, d: f64| {
        let len = (x[b] - x[a]).hypot(y[b] - y[a]);
        if len > 0.0 {
            let f = d / len;
            (x[b] + f * (x[b] - x[a]), y[b] + f * (y[b] - y[a]))
        } else {
            (x[b], y[b])
        }
    };
    // `p_from + f (p_to - p_from)` with `f = d / |p_to - p_from|`.
    let towards = |from: usize, to: usize, d: f64, len: f64| {
        if len > 0.0 {
            let f = d / len;
            (
                x[from] + f * (x[to] - x[from]),
                y[from] + f * (y[to] - y[from]),
            )
        } else {
            (x[from], y[from])
        }
    };
    let mut k = j;
    if s >= 0.0 {
        let mut left = s;
        loop {
            if k + 1 >= n {
                return if n >= 2 {
                    extend(n - 2, n - 1, left)
                } else {
                    (x[k], y[k])
                };
            }
            let len = (x[k + 1] - x[k]).hypot(y[k + 1] - y[k]);
            if left <= len {
                return towards(k, k + 1, left, len);
            }
            left -= len;
            k += 1;
        }
    } else {
        let mut left = -s;
        loop {
            if k == 0 {
                return if n >= 2 {
                    extend(1, 0, left)
                } else {
                    (x[0], y[0])
                };
            }
            let len = (x[k] - x[k - 1]).hypot(y[k] - y[k - 1]);
            if left <= len {
                return towards(k, k - 1, left, len);
            }
            left -= len;
            k -= 1;
        }
    }
}

/// The samples that model `motion` for dwell times `dwell_s` on `path`.
///
/// Errors: a dwell list of another length, negative or non-finite dwell, zero samples.
pub fn sample_program(path: &DwellPath, dwell_s: &[f64], motion: Motion) -> Result<SampledProgram> {
    if dwell_s.len() != path.len() {
        return Err(Error::LengthMismatch {
            what: "dwell_s",
            got: dwell_s.len(),
            expected: path.len(),
        });
    }
    if let Some((j, t)) = dwell_s
        .iter()
        .enumerate()
        .find(|(_, t)| !(t.is_finite() && **t >= 0.0))
    {
        return Err(Error::invalid(
            "dwell_s",
            format!("dwell point {j} has dwell {t} s; dwell times must be finite and >= 0"),
        ));
    }
    let (x, y) = (path.x_mm(), path.y_mm());
    match motion {
        Motion::Discrete => Ok(SampledProgram {
            x_mm: x.to_vec(),
            y_mm: y.to_vec(),
            dwell_s: dwell_s.to_vec(),
            half_mm: Vec::new(),
        }),
        Motion::Continuous { samples_per_point } => {
            if samples_per_point == 0 {
                return Err(Error::invalid(
                    "samples_per_point",
                    "continuous motion needs at least 1 sample per dwell point",
                ));
            }
            let k = samples_per_point;
            let n = path.len();
            crate::budget::check_f64s(
                "--samples-per-point",
                &format!(
                    "{k} samples for each of {n} dwell points (x, y, dwell and removal terms)"
                ),
                n as f64 * k as f64,
                4.0,
            )?;
            let seg: Vec<f64> = (1..n)
                .map(|j| (x[j] - x[j - 1]).hypot(y[j] - y[j - 1]))
                .collect();
            let total = n.saturating_mul(k);
            let mut out = SampledProgram {
                x_mm: Vec::with_capacity(total),
                y_mm: Vec::with_capacity(total),
                dwell_s: Vec::with_capacity(total),
                half_mm: Vec::new(),
            };
            for (j, &t) in dwell_s.iter().enumerate() {
                // The stretch runs from the midpoint of the segment before to the midpoint of
                // the segment after (the end points: half their one segment on either side).
                let (back, ahead) = match (j.checked_sub(1).map(|i| seg[i]), seg.get(j)) {
                    (Some(b), Some(&a)) => (0.5 * b, 0.5 * a),
                    (Some(b), None) => (0.5 * b, 0.5 * b),
                    (None, Some(&a)) => (0.5 * a, 0.5 * a),
                    (None, None) => (0.0, 0.0),
                };
                let d = back + ahead;
                for i in 0..k {
                    let s = -back + (i as f64 + 0.5) * d / k as f64;
                    let (px, py) = point_at(x, y, j, s);
                    out.x_mm.push(px);
                    out.y_mm.push(py);
                    out.dwell_s.push(t / k as f64);
                }
            }
            Ok(out)
        }
    }
}

/// Removal (nm) at the map points `(map_x_mm, map_y_mm)` produced by the dwell program under
/// `motion` with `tif`; the result does not depend on the thread count, and discrete motion equals
/// `R t` of the solver bit for bit.
pub fn removal_nm<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    path: &DwellPath,
    dwell_s: &[f64],
    tif: &T,
    motion: Motion,
    observer: &dyn Observer,
) -> Result<Vec<f64>> {
    let program = sample_program(path, dwell_s, motion)?;
    if matches!(motion, Motion::Discrete) {
        let r = InfluenceMatrix::assemble(
            map_x_mm,
            map_y_mm,
            &program.x_mm,
            &program.y_mm,
            tif,
            observer,
        )?;
        return r.removal_nm(&program.dwell_s);
    }
    removal_of_samples(map_x_mm, map_y_mm, &program, tif, observer)
}

/// Appends dwell point `j`'s stretch on `path` carrying `dwell_s` to `motion`: its samples, each
/// the piece it stands for ([`Stretches::pieces_of`]), carrying the dwell in proportion to their
/// weights.
pub fn push_stretch(
    motion: &mut SampledProgram,
    path: &DwellPath,
    stretches: &Stretches,
    j: usize,
    dwell_s: f64,
) {
    for (&[dx, dy, w], &half) in stretches.of(j).iter().zip(stretches.pieces_of(j)) {
        motion.x_mm.push(path.x_mm()[j] + dx);
        motion.y_mm.push(path.y_mm()[j] + dy);
        motion.dwell_s.push(dwell_s * w);
        motion.half_mm.push(half);
    }
}

/// The motion of dwell times `dwell_s` on `path` at their programmed feeds: each dwell point's
/// stretch samples, each the piece it stands for, carrying its dwell in proportion to their
/// weights (swept model, `stretches`, [`push_stretch`]), or the dwell points themselves (point
/// model).
pub fn path_motion(
    path: &DwellPath,
    stretches: Option<&Stretches>,
    dwell_s: &[f64],
) -> SampledProgram {
    match stretches {
        Some(stretches) => {
            let mut motion = SampledProgram {
                x_mm: Vec::new(),
                y_mm: Vec::new(),
                dwell_s: Vec::new(),
                half_mm: Vec::new(),
            };
            for (j, &tj) in dwell_s.iter().enumerate() {
                push_stretch(&mut motion, path, stretches, j, tj);
            }
            motion
        }
        None => SampledProgram {
            x_mm: path.x_mm().to_vec(),
            y_mm: path.y_mm().to_vec(),
            dwell_s: dwell_s.to_vec(),
            half_mm: Vec::new(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::tif::GaussianTif;

    fn line_path(n: usize, step: f64) -> DwellPath {
        DwellPath::new((0..n).map(|i| i as f64 * step).collect(), vec![0.0; n]).unwrap()
    }

    #[test]
    fn samples_cover_each_arc_and_keep_the_dwell() {
        // A serpentine corner: along x, then up, then back.
        let p =
            DwellPath::new(vec![0.0, 1.0, 2.0, 2.0, 1.0], vec![0.0, 0.0, 0.0, 1.0, 1.0]).unwrap();
        let t = [1.0, 2.0, 3.0, 4.0, 5.0];
        let s = sample_program(
            &p,
            &t,
            Motion::Continuous {
                samples_per_point: 4,
            },
        )
        .unwrap();
        assert_eq!(s.dwell_s.len(), 20);
        let total: f64 = s.dwell_s.iter().sum();
        assert!((total - 15.0).abs() < 1e-12);
        // Point 1 (interior, straight): samples at 0.625, 0.875, 1.125, 1.375 on y = 0.
        let xs = &s.x_mm[4..8];
        for (x, want) in xs.iter().zip([0.625, 0.875, 1.125, 1.375]) {
            assert!((x - want).abs() < 1e-12, "{xs:?}");
        }
        // Point 2 sits on the corner: its arc runs from (1.5, 0) to (2, 0.5).
        assert!((s.x_mm[8] - 1.625).abs() < 1e-12 && s.y_mm[8] == 0.0);
        assert!((s.x_mm[11] - 2.0).abs() < 1e-12 && (s.y_mm[11] - 0.375).abs() < 1e-12);
        // The first point owns [-0.5, 0.5] (run-in extends the first segment backwards).
        assert!((s.x_mm[0] + 0.375).abs() < 1e-12);
        // The last point (ds = 1) owns [1.5, 0.5] along the last segment, extended past its end.
        assert!((s.x_mm[19] - 0.625).abs() < 1e-12 && (s.y_mm[19] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn continuous_removal_converges_quadratically_to_the_sweep() {
        let tif = GaussianTif::new(2.0, 10.0, 8.0).unwrap();
        let path = line_path(21, 1.0);
        let t: Vec<f64> = (0..21)
            .map(|j| 1.0 + 0.5 * (j as f64 * 0.4).sin())
            .collect();
        let mx: Vec<f64> = (0..81).map(|i| -2.0 + 0.3 * i as f64).collect();
        let my: Vec<f64> = mx.iter().map(|_| 0.7).collect();
        let run = |k| {
            removal_nm(
                &mx,
                &my,
                &path,
                &t,
                &tif,
                Motion::Continuous {
                    samples_per_point: k,
                },
                &Silent,
            )
            .unwrap()
        };
        let (h4, h8, h16, h64) = (run(4), run(8), run(16), run(64));
        let dist = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max)
        };
        let (e4, e8, e16) = (dist(&h4, &h64), dist(&h8, &h64), dist(&h16, &h64));
        // Midpoint rule: halving the sample spacing divides the error by about 4.
        assert!(e8 < 0.35 * e4 && e16 < 0.35 * e8, "{e4} {e8} {e16}");
        let peak = h64.iter().copied().fold(0.0, f64::max);
        assert!(e8 < 1e-3 * peak, "{e8} vs peak {peak}");
        // The sweep matches the closed form on the interior: for a uniform sweep of a Gaussian
        // along x, the removal far from the ends is (t/ds) * peak * sigma * sqrt(2 pi) * exp(..).
        let uniform = vec![1.0; 21];
        let h = removal_nm(
            &[10.0],
            &[0.7],
            &path,
            &uniform,
            &tif,
            Motion::Continuous {
                samples_per_point: 64,
            },
            &Silent,
        )
        .unwrap();
        let sigma = 2.0f64;
        // Line integral of the truncated Gaussian over x (truncation at r = 8 mm: |dx| <= sqrt(64 - 0.49)).
        let half = (64.0f64 - 0.49).sqrt();
        let mut want = 0.0;
        let steps = 200_000;
        for i in 0..steps {
            let x = -half + (i as f64 + 0.5) * 2.0 * half / steps as f64;
            want +=
                10.0 * (-(x * x + 0.49) / (2.0 * sigma * sigma)).exp() * 2.0 * half / steps as f64;
        }
        assert!((h[0] - want).abs() < 1e-4 * want, "{} vs {want}", h[0]);
    }

    #[test]
    fn discrete_motion_is_r_times_t() {
        let tif = GaussianTif::new(1.5, 7.0, 4.5).unwrap();
        let path = line_path(9, 0.8);
        let t: Vec<f64> = (0..9).map(|j| 0.5 + j as f64 * 0.1).collect();
        let mx: Vec<f64> = (0..30).map(|i| -1.0 + 0.3 * i as f64).collect();
        let my = vec![0.3; 30];
        let r =
            InfluenceMatrix::assemble(&mx, &my, path.x_mm(), path.y_mm(), &tif, &Silent).unwrap();
        let want = r.removal_nm(&t).unwrap();
        let got = removal_nm(&mx, &my, &path, &t, &tif, Motion::Discrete, &Silent).unwrap();
        assert_eq!(got, want);
        assert!(sample_program(&path, &t[..3], Motion::Discrete).is_err());
        let mut bad = t.clone();
        bad[2] = -1.0;
        assert!(sample_program(&path, &bad, Motion::Discrete).is_err());
    }
}
