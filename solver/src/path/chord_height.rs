//! Equal chord-height stepping along a line on a curved surface.
//!
//! Along the line `x = X` from `y = A` to `y = B` on the surface `z = f(x, y)`, consecutive points
//! are a chord `L` apart (3-D chord length). The chord height of a step is the largest distance
//! between the surface curve and its chord. The initial step at a point is
//! `L0 = sqrt(8 R r h / (R + r))` (R local radius of curvature of the curve, r tool radius,
//! h the allowed chord height, taken as the middle of the window; `L0 = sqrt(8 r h)` where the
//! curve is straight), then the step grows by `h_i` while its chord height is below `eps1` and
//! shrinks by `h_d` while it is above `eps2` (bisecting between the last too-short and too-long
//! steps when a grow or shrink would jump past them), until the chord height lies in
//! `[eps1, eps2]`. The last step ends at `B` and may have a smaller chord height.

use super::DwellPath;
use crate::error::{Error, Result};
use crate::surface::Surface;
use serde::{Deserialize, Serialize};

/// Settings of chord-height stepping (lengths mm).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChordHeightSettings {
    /// Tool radius r, mm.
    pub tool_radius_mm: f64,
    /// Smallest accepted chord height eps1, mm.
    pub eps_min_mm: f64,
    /// Largest accepted chord height eps2, mm.
    pub eps_max_mm: f64,
    /// Step growth h_i, mm.
    pub grow_mm: f64,
    /// Step shrink h_d, mm.
    pub shrink_mm: f64,
    /// Most trial steps per point.
    pub max_trials: usize,
}

impl Default for ChordHeightSettings {
    /// The published window and increments: eps in [3.0, 3.2] um, h_i = 0.10 mm, h_d = 0.02 mm.
    fn default() -> Self {
        Self {
            tool_radius_mm: 10.0,
            eps_min_mm: 3.0e-3,
            eps_max_mm: 3.2e-3,
            grow_mm: 0.10,
            shrink_mm: 0.02,
            max_trials: 200,
        }
    }
}

impl ChordHeightSettings {
    /// Checks: all lengths positive, `eps_min < eps_max`, at least one trial.
    pub fn validate(&self) -> Result<()> {
        Error::require_positive(&[
            ("chord-height tool_radius_mm", self.tool_radius_mm),
            ("chord-height eps_min_mm", self.eps_min_mm),
            ("chord-height eps_max_mm", self.eps_max_mm),
            ("chord-height grow_mm", self.grow_mm),
            ("chord-height shrink_mm", self.shrink_mm),
        ])?;
        if self.eps_min_mm >= self.eps_max_mm {
            return Err(Error::invalid(
                "chord-height eps",
                format!(
                    "window [{}, {}] mm is empty",
                    self.eps_min_mm, self.eps_max_mm
                ),
            ));
        }
        if self.max_trials == 0 {
            return Err(Error::invalid(
                "chord-height max_trials",
                "must be at least 1",
            ));
        }
        Ok(())
    }
}

/// A chord-height path and its statistics.
#[derive(Debug, Clone, PartialEq)]
pub struct ChordHeightPath {
    /// The points (plan coordinates, along the line).
    pub path: DwellPath,
    /// 3-D chord length of each step, mm (one fewer than the points).
    pub steps_mm: Vec<f64>,
    /// Chord height of each step, mm.
    pub chord_heights_mm: Vec<f64>,
}

impl ChordHeightPath {
    /// Shortest step, mm (0 without steps).
    pub fn min_step_mm(&self) -> f64 {
        self.steps_mm
            .iter()
            .copied()
            .reduce(f64::min)
            .unwrap_or(0.0)
    }

    /// Longest step, mm.
    pub fn max_step_mm(&self) -> f64 {
        self.steps_mm.iter().copied().fold(0.0, f64::max)
    }
}

/// The surface curve along the line: `(y, z(x, y))`.
struct Curve<'a> {
    surface: &'a Surface,
    x: f64,
}

impl Curve<'_> {
    fn z(&self, y: f64) -> Result<f64> {
        self.surface.sag_mm(self.x, y)
    }

    /// Radius of curvature of the plane curve at `y`, mm (infinite where straight):
    /// `(1 + z'^2)^(3/2) / |z''|`.
    fn radius(&self, y: f64) -> Result<f64> {
        let d = self.surface.derivs(self.x, y)?;
        let k = d.zyy.abs() / (1.0 + d.zy * d.zy).powf(1.5);
        Ok(if k > 0.0 { 1.0 / k } else { f64::INFINITY })
    }

    /// Largest distance from the curve between `ya` and `yb` to their chord: 24 samples, then a
    /// golden-section refinement around the best.
    fn chord_height(&self, ya: f64, yb: f64) -> Result<f64> {
        let (za, zb) = (self.z(ya)?, self.z(yb)?);
        let (dy, dz) = (yb - ya, zb - za);
        let len = dy.hypot(dz);
        if len == 0.0 {
            return Ok(0.0);
        }
        let dist = |y: f64| -> Result<f64> {
            let z = self.z(y)?;
            Ok(((y - ya) * dz - (z - za) * dy).abs() / len)
        };
        const SAMPLES: usize = 24;
        let mut best = (0.0, 0usize);
        for k in 1..SAMPLES {
            let y = ya + dy * k as f64 / SAMPLES as f64;
            let d = dist(y)?;
            if d > best.0 {
                best = (d, k);
            }
        }
        let h = dy / SAMPLES as f64;
        let c = ya + h * best.1 as f64;
        let (mut lo, mut hi) = (c - h, c + h);
        let g = 0.5 * (5f64.sqrt() - 1.0);
        let mut m1 = hi - g * (hi - lo);
        let mut m2 = lo + g * (hi - lo);
        let (mut f1, mut f2) = (dist(m1)?, dist(m2)?);
        for _ in 0..40 {
            if f1 > f2 {
                hi = m2;
                m2 = m1;
                f2 = f1;
                m1 = hi - g * (hi - lo);
                f1 = dist(m1)?;
            } else {
                lo = m1;
                m1 = m2;
                f1 = f2;
                m2 = lo + g * (hi - lo);
                f2 = dist(m2)?;
            }
        }
        Ok(best.0.max(f1).max(f2))
    }

    /// The `y` whose point is a 3-D chord `l` from `(ya, z(ya))` in the direction `sign`,
    /// clamped to `y_end`: fixed point `dy = l / sqrt(1 + (dz/dy)^2)`.
    fn advance(&self, ya: f64, l: f64, sign: f64, y_end: f64) -> Result<f64> {
        let za = self.z(ya)?;
        let mut dy = l;
        for _ in 0..8 {
            let yb = ya + sign * dy;
            let slope = (self.z(yb)? - za) / dy;
            dy = l / (1.0 + slope * slope).sqrt();
        }
        let yb = ya + sign * dy;
        Ok(if (yb - y_end) * sign > 0.0 { y_end } else { yb })
    }
}

/// Equal chord-height points along `x = line_x_mm` from `y_start_mm` to `y_end_mm` on `surface`.
pub fn chord_height_line(
    surface: &Surface,
    line_x_mm: f64,
    y_start_mm: f64,
    y_end_mm: f64,
    settings: &ChordHeightSettings,
) -> Result<ChordHeightPath> {
    settings.validate()?;
    if !(line_x_mm.is_finite() && y_start_mm.is_finite() && y_end_mm.is_finite())
        || y_start_mm == y_end_mm
    {
        return Err(Error::invalid(
            "chord-height line",
            format!("needs finite x and two different y limits, got x={line_x_mm}, y=[{y_start_mm}, {y_end_mm}] mm"),
        ));
    }
    let curve = Curve {
        surface,
        x: line_x_mm,
    };
    let sign = (y_end_mm - y_start_mm).signum();
    let target = 0.5 * (settings.eps_min_mm + settings.eps_max_mm);
    let r_tool = settings.tool_radius_mm;
    let mut ys = vec![y_start_mm];
    let mut steps = Vec::new();
    let mut heights = Vec::new();
    let mut y = y_start_mm;
    let max_points = 10_000_000usize;
    while (y_end_mm - y) * sign > 0.0 {
        let big_r = curve.radius(y)?;
        let mut l = if big_r.is_finite() {
            (8.0 * big_r * r_tool * target / (big_r + r_tool)).sqrt()
        } else {
            (8.0 * r_tool * target).sqrt()
        };
        let (mut short, mut long): (Option<f64>, Option<f64>) = (None, None);
        let mut accepted = None;
        for _ in 0..settings.max_trials {
            let yb = curve.advance(y, l, sign, y_end_mm)?;
            let e = curve.chord_height(y, yb)?;
            let at_end = yb == y_end_mm;
            if (e >= settings.eps_min_mm && e <= settings.eps_max_mm)
                || (at_end && e < settings.eps_min_mm)
            {
                accepted = Some((yb, e));
                break;
            }
            let next = if e < settings.eps_min_mm {
                short = Some(l);
                let g = l + settings.grow_mm;
                match long {
                    Some(lg) if g >= lg => 0.5 * (l + lg),
                    _ => g,
                }
            } else {
                long = Some(l);
                let s = l - settings.shrink_mm;
                match short {
                    Some(sh) if s <= sh => 0.5 * (l + sh),
                    _ if s <= 0.0 => 0.5 * l,
                    _ => s,
                }
            };
            l = next;
        }
        let Some((yb, e)) = accepted else {
            return Err(Error::Numerical {
                stage: "chord-height stepping",
                why: format!(
                    "no step with chord height in [{}, {}] mm after {} trials at y={y} mm (x={line_x_mm} mm)",
                    settings.eps_min_mm, settings.eps_max_mm, settings.max_trials
                ),
            });
        };
        let (za, zb) = (curve.z(y)?, curve.z(yb)?);
        steps.push((yb - y).hypot(zb - za));
        heights.push(e);
        ys.push(yb);
        y = yb;
        if ys.len() > max_points {
            return Err(Error::invalid(
                "chord-height line",
                format!("more than {max_points} points"),
            ));
        }
    }
    let xs = vec![line_x_mm; ys.len()];
    Ok(ChordHeightPath {
        path: DwellPath::new(xs, ys)?,
        steps_mm: steps,
        chord_heights_mm: heights,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surface::{Conic, XyPolynomial, XyTerm};

    /// Independent chord height: dense sampling (20001 points) of the curve between the ends.
    fn dense_chord_height(s: &Surface, x: f64, ya: f64, yb: f64) -> f64 {
        let (za, zb) = (s.sag_mm(x, ya).unwrap(), s.sag_mm(x, yb).unwrap());
        let (dy, dz) = (yb - ya, zb - za);
        let len = dy.hypot(dz);
        (0..=20_000)
            .map(|k| {
                let y = ya + dy * k as f64 / 20_000.0;
                let z = s.sag_mm(x, y).unwrap();
                ((y - ya) * dz - (z - za) * dy).abs() / len
            })
            .fold(0.0, f64::max)
    }

    fn check(s: &Surface, x: f64, a: f64, b: f64) -> ChordHeightPath {
        let set = ChordHeightSettings::default();
        let p = chord_height_line(s, x, a, b, &set).unwrap();
        let ys = p.path.y_mm();
        let n = ys.len();
        assert!(n > 5);
        assert_eq!((ys[0], ys[n - 1]), (a, b));
        // Every step but the last (which ends at the line end) within [eps1, eps2], measured
        // independently; sampling resolution allows 1e-4 relative.
        for k in 0..n - 1 {
            let e = dense_chord_height(s, x, ys[k], ys[k + 1]);
            assert!((e - p.chord_heights_mm[k]).abs() < 1e-4 * e.max(1e-6));
            if k + 2 < n {
                assert!(
                    e >= set.eps_min_mm * (1.0 - 1e-4) && e <= set.eps_max_mm * (1.0 + 1e-4),
                    "step {k}: chord height {e} mm"
                );
            } else {
                assert!(e <= set.eps_max_mm * (1.0 + 1e-4));
            }
        }
        assert!(p.min_step_mm() > 0.0 && p.max_step_mm() >= p.min_step_mm());
        p
    }

    #[test]
    fn chord_heights_within_window_on_ellipsoid_and_freeform() {
        // Oblate ellipsoid (conic constant > 0), vertex radius 100 mm.
        let ell = Surface::Conic(Conic {
            curvature_per_mm: 0.01,
            conic: 0.6,
        });
        let p = check(&ell, 15.0, -40.0, 40.0);
        // The curvature varies along the line, so the steps do too.
        assert!(p.max_step_mm() > p.min_step_mm());
        let free = Surface::XyPolynomial(XyPolynomial {
            curvature_per_mm: 1.0 / 150.0,
            conic: -0.5,
            norm_radius_mm: 30.0,
            terms: vec![
                XyTerm {
                    m: 0,
                    n: 3,
                    coef_mm: 0.4,
                },
                XyTerm {
                    m: 1,
                    n: 2,
                    coef_mm: -0.2,
                },
                XyTerm {
                    m: 0,
                    n: 4,
                    coef_mm: 0.3,
                },
            ],
        });
        check(&free, -5.0, 25.0, -25.0);
        assert!(chord_height_line(
            &ell,
            0.0,
            0.0,
            1.0,
            &ChordHeightSettings {
                eps_min_mm: 2.0,
                eps_max_mm: 1.0,
                ..Default::default()
            }
        )
        .is_err());
    }
}
