//! The correctable band of a measured error: what a tool of a given TIF can remove in useful time.
//!
//! A tool of influence function `T` removes a pattern of spatial frequency `f` at the gain
//! `|T^(f)| / T^(0)` of its Fourier transform (its transfer function): the dwell needed for an
//! amplitude `a` grows as `a / gain`, and noise and structure beyond the band cost hours for
//! nothing. The measured error is split into a smooth part, the least-squares fit of Legendre
//! products `P_i(u) P_j(v)` over the map's bounding box with `i / n_x + j / n_y <= 1`, and what
//! is left (measurement noise and structure finer than the tool). `n_x = ceil(pi W_x f_c)`
//! matches the local frequency `n / (pi W)` of `P_n` at the centre of a width `W` to the cut-off
//! `f_c`, where the transfer function first falls to `min_gain`: the most the tool can do.
//! Within that cap the data choose how far to go: the terms are taken in order of their level
//! `i / n_x + j / n_y`, and the level kept is the one that minimises the Bayesian information
//! criterion `N ln(RSS / N) + p ln N` (Schwarz 1978) of the nested fits, all read from one QR
//! factor. Noise-free data keep the whole cap; noise stops the fit where further terms explain
//! no more than noise would. The loop plans against the smooth part only and reports the rest as
//! uncorrectable (compare the RISE approach of fitting the correctable part of a measured
//! residual before planning).

use crate::error::{Error, Result};
use crate::lstsq::{tsqr, Reduced};
use crate::modal::legendre;
use crate::tif::InfluenceFunction;
use serde::{Deserialize, Serialize};

/// Samples per support radius when the transfer function is summed.
const TRANSFER_SAMPLES: usize = 64;
/// Frequency steps scanned for the first crossing of the gain before bisection.
const SCAN_STEPS: usize = 400;
/// At most one fitted term per this many map points (the fit then takes little of the noise:
/// a share `sqrt(terms / N)` of its RMS).
const POINTS_PER_TERM: usize = 3;

/// What part of a measured error a run plans against.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum CorrectableBand {
    /// The whole measured map, noise included.
    All,
    /// The smooth fit, at most up to the frequency at which the TIF's transfer function falls
    /// to `min_gain`, as far as the data support it (see the module documentation).
    Tif {
        /// Transfer-function gain at the cap of the band, in (0, 1).
        min_gain: f64,
    },
}

/// Default gain at the cap of the band: the tool still removes a pattern at 5 % of its rate for
/// a uniform layer (twenty times the dwell per nm).
pub const BAND_MIN_GAIN: f64 = 0.05;

impl Default for CorrectableBand {
    fn default() -> Self {
        CorrectableBand::Tif {
            min_gain: BAND_MIN_GAIN,
        }
    }
}

impl CorrectableBand {
    /// Checks the gain.
    pub fn validate(&self) -> Result<()> {
        match *self {
            CorrectableBand::All => Ok(()),
            CorrectableBand::Tif { min_gain } => {
                if min_gain.is_finite() && min_gain > 0.0 && min_gain < 1.0 {
                    Ok(())
                } else {
                    Err(Error::invalid(
                        "band min_gain",
                        format!("must be in (0, 1), got {min_gain}"),
                    ))
                }
            }
        }
    }
}

/// A measured error split into the correctable band and the rest.
#[derive(Debug, Clone, PartialEq)]
pub struct BandSplit {
    /// The smooth part the tool can correct, nm, at the map's points.
    pub correctable_nm: Vec<f64>,
    /// The rest (noise and structure finer than the tool), nm.
    pub uncorrectable_nm: Vec<f64>,
    /// Legendre degrees `[n_x, n_y]` of the fit (`[0, 0]` with [`CorrectableBand::All`]).
    pub degrees: [usize; 2],
    /// The band's cut-off frequency, 1/mm (`None` with [`CorrectableBand::All`]).
    pub cutoff_per_mm: Option<f64>,
}

/// `|sum T(x, y) exp(-2 pi i f d)| / sum T` along x (`along_x`) or y: the TIF's transfer
/// function at frequency `f` (1/mm), from samples on a grid over its support.
fn gain(samples: &[(f64, f64, f64)], total: f64, f: f64, along_x: bool) -> f64 {
    let w = 2.0 * std::f64::consts::PI * f;
    let (mut re, mut im) = (0.0, 0.0);
    for &(x, y, r) in samples {
        let d = if along_x { x } else { y };
        re += r * (w * d).cos();
        im += r * (w * d).sin();
    }
    re.hypot(im) / total
}

/// The lowest frequency (1/mm) at which the TIF's transfer function, along x or along y
/// (whichever falls first), drops to `min_gain`.
pub fn transfer_cutoff_per_mm(tif: &dyn InfluenceFunction, min_gain: f64) -> Result<f64> {
    let radius = tif.support_radius_mm();
    if !(radius.is_finite() && radius > 0.0) {
        return Err(Error::invalid(
            "TIF",
            format!("support radius must be positive, got {radius} mm"),
        ));
    }
    let h = radius / TRANSFER_SAMPLES as f64;
    let n = TRANSFER_SAMPLES as i64;
    let mut samples = Vec::with_capacity(((2 * n + 1) * (2 * n + 1)) as usize);
    for j in -n..=n {
        for i in -n..=n {
            let (x, y) = (i as f64 * h, j as f64 * h);
            let r = tif.rate_nm_per_s(x, y);
            if r != 0.0 {
                samples.push((x, y, r));
            }
        }
    }
    let total: f64 = samples.iter().map(|s| s.2).sum();
    if !(total.is_finite() && total > 0.0) {
        return Err(Error::invalid(
            "TIF",
            "removes nothing: its transfer function is undefined",
        ));
    }
    let g = |f: f64| gain(&samples, total, f, true).min(gain(&samples, total, f, false));
    let nyquist = 0.5 / h;
    let step = nyquist / SCAN_STEPS as f64;
    let mut lo = 0.0;
    let mut hi = None;
    for k in 1..=SCAN_STEPS {
        let f = k as f64 * step;
        if g(f) < min_gain {
            hi = Some(f);
            break;
        }
        lo = f;
    }
    let Some(mut hi) = hi else {
        return Ok(nyquist);
    };
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if g(mid) < min_gain {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    Ok(0.5 * (lo + hi))
}

/// The Legendre degree pairs `(i, j)` with level `i / n_x + j / n_y <= 1`, by level (a pair
/// with a zero degree cap has level infinity unless its degree is zero), with the level of each.
fn terms(nx: usize, ny: usize) -> Vec<((usize, usize), f64)> {
    let level = |d: usize, n: usize| {
        if d == 0 {
            0.0
        } else if n == 0 {
            f64::INFINITY
        } else {
            d as f64 / n as f64
        }
    };
    let mut out = Vec::new();
    for i in 0..=nx {
        for j in 0..=ny {
            let l = level(i, nx) + level(j, ny);
            if l <= 1.0 + 1e-12 {
                out.push(((i, j), l));
            }
        }
    }
    out.sort_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
    out
}

/// Splits the error `z_nm` at the points into the band `band` of `tif` and the rest.
pub fn split(
    x_mm: &[f64],
    y_mm: &[f64],
    z_nm: &[f64],
    tif: &dyn InfluenceFunction,
    band: CorrectableBand,
) -> Result<BandSplit> {
    band.validate()?;
    let min_gain = match band {
        CorrectableBand::All => {
            return Ok(BandSplit {
                correctable_nm: z_nm.to_vec(),
                uncorrectable_nm: vec![0.0; z_nm.len()],
                degrees: [0, 0],
                cutoff_per_mm: None,
            })
        }
        CorrectableBand::Tif { min_gain } => min_gain,
    };
    let n = z_nm.len();
    if x_mm.len() != n || y_mm.len() != n {
        return Err(Error::LengthMismatch {
            what: "band fit points",
            got: x_mm.len().min(y_mm.len()),
            expected: n,
        });
    }
    let fc = transfer_cutoff_per_mm(tif, min_gain)?;
    let (x0, x1) = min_max(x_mm);
    let (y0, y1) = min_max(y_mm);
    let degree = |w: f64| (std::f64::consts::PI * w * fc).ceil().max(0.0) as usize;
    let (mut nx, mut ny) = (degree(x1 - x0), degree(y1 - y0));
    while terms(nx, ny).len() * POINTS_PER_TERM > n && (nx > 0 || ny > 0) {
        if nx >= ny {
            nx -= 1;
        } else {
            ny -= 1;
        }
    }
    let all = terms(nx, ny);
    let t: Vec<(usize, usize)> = all.iter().map(|a| a.0).collect();
    let p = t.len();
    let centre = [0.5 * (x0 + x1), 0.5 * (y0 + y1)];
    let half = [
        (0.5 * (x1 - x0)).max(f64::MIN_POSITIVE),
        (0.5 * (y1 - y0)).max(f64::MIN_POSITIVE),
    ];
    let basis = |i: usize, row: &mut [f64]| {
        let u = (x_mm[i] - centre[0]) / half[0];
        let v = (y_mm[i] - centre[1]) / half[1];
        for (slot, &(a, b)) in row.iter_mut().zip(&t) {
            *slot = legendre(a, u) * legendre(b, v);
        }
    };
    let r = tsqr(n, p + 1, |i, row| {
        basis(i, row);
        row[p] = z_nm[i];
        Ok(())
    })?;
    // Nested fits: the first `q` terms leave RSS_q = r[p][p]^2 + sum_{k >= q} r[k][p]^2. Cut at
    // the end of a level (so that x and y are treated alike), by the smallest BIC.
    let rhs = |k: usize| r[(k, p)];
    let floor = if r.nrows() > p {
        r[(p, p)].powi(2)
    } else {
        0.0
    };
    let mut tail = vec![floor; p + 1];
    for k in (0..p).rev() {
        tail[k] = tail[k + 1] + rhs(k).powi(2);
    }
    let ln_n = (n as f64).ln();
    let tiny = f64::MIN_POSITIVE * n as f64;
    let bic = |q: usize| n as f64 * (tail[q].max(tiny) / n as f64).ln() + q as f64 * ln_n;
    let mut best = p;
    for q in 1..=p {
        let level_ends = q == p || all[q].1 > all[q - 1].1 + 1e-12;
        if level_ends && bic(q) < bic(best) {
            best = q;
        }
    }
    let q = best;
    let sub = faer::Mat::from_fn(q + 1, q + 1, |i, j| {
        if i == q {
            if j == q {
                tail[q].sqrt()
            } else {
                0.0
            }
        } else if j < q {
            r[(i, j)]
        } else {
            rhs(i)
        }
    });
    let mut coef = Reduced::new(&sub, q, "correctable band fit")?.solve(0.0, 0.0);
    coef.resize(p, 0.0);
    let (nx, ny) = t[..q]
        .iter()
        .fold((0, 0), |(a, b), &(i, j)| (a.max(i), b.max(j)));
    let mut row = vec![0.0; p];
    let mut correctable = Vec::with_capacity(n);
    for i in 0..n {
        basis(i, &mut row);
        correctable.push(row.iter().zip(&coef).map(|(b, c)| b * c).sum::<f64>());
    }
    let uncorrectable = z_nm.iter().zip(&correctable).map(|(z, c)| z - c).collect();
    Ok(BandSplit {
        correctable_nm: correctable,
        uncorrectable_nm: uncorrectable,
        degrees: [nx, ny],
        cutoff_per_mm: Some(fc),
    })
}

fn min_max(v: &[f64]) -> (f64, f64) {
    v.iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tif::GaussianTif;

    /// Relative tolerance of the transfer function's cut-off against the closed form.
    const CUTOFF_REL_TOL: f64 = 1e-3;

    #[test]
    fn gaussian_cutoff_matches_the_closed_form() {
        // The transform of a Gaussian of standard deviation s is exp(-2 pi^2 s^2 f^2): it falls
        // to g at f = sqrt(-ln g / 2) / (pi s). Truncated at 5 s the tails do not matter.
        let s = 2.5;
        let tif = GaussianTif::new(s, 10.0, 5.0 * s).unwrap();
        for g in [0.5, 0.25] {
            let want = (-f64::ln(g) / 2.0).sqrt() / (std::f64::consts::PI * s);
            let got = transfer_cutoff_per_mm(&tif, g).unwrap();
            assert!(
                (got - want).abs() < CUTOFF_REL_TOL * want,
                "{got} vs {want}"
            );
        }
    }

    #[test]
    fn the_band_keeps_smooth_error_and_leaves_fine_structure() {
        // A 50 mm square: a smooth error of 1.5 cycles lies inside the band of a sigma 2.5 mm
        // Gaussian (cut-off 0.075 / mm), a 1 mm checkerboard far outside it.
        let tif = GaussianTif::new(2.5, 10.0, 7.5).unwrap();
        let (mut x, mut y, mut smooth, mut fine) = (vec![], vec![], vec![], vec![]);
        for j in 0..51 {
            for i in 0..51 {
                let (xi, yj) = (-25.0 + i as f64, -25.0 + j as f64);
                x.push(xi);
                y.push(yj);
                smooth.push(
                    30.0 * (2.0 * std::f64::consts::PI * 1.5 * xi / 50.0 + 0.3).cos()
                        + 10.0 * (yj / 25.0).powi(2),
                );
                fine.push(if (i + j) % 2 == 0 { 1.0 } else { -1.0 });
            }
        }
        let z: Vec<f64> = smooth.iter().zip(&fine).map(|(a, b)| a + b).collect();
        let s = split(&x, &y, &z, &tif, CorrectableBand::Tif { min_gain: 0.5 }).unwrap();
        let rms = |v: &[f64]| (v.iter().map(|a| a * a).sum::<f64>() / v.len() as f64).sqrt();
        let err: Vec<f64> = s
            .correctable_nm
            .iter()
            .zip(&smooth)
            .map(|(c, w)| c - w)
            .collect();
        // The fit of 1.5 cycles by degree 12 is exact; what it takes of the unit checkerboard
        // is at most its share sqrt(p / N) of the 91 terms of degree 12 over 2601 points.
        let leakage = (91.0f64 / 2601.0).sqrt();
        assert!(rms(&err) < leakage, "{}", rms(&err));
        let left: Vec<f64> = s
            .uncorrectable_nm
            .iter()
            .zip(&fine)
            .map(|(u, f)| u - f)
            .collect();
        assert!(rms(&left) < leakage, "{}", rms(&left));
        // The cap at gain 0.5 is degree 12 (pi 50 0.075 = 11.8); the data ask for less or all.
        assert!(s.degrees[0] <= 12 && s.degrees[1] <= 12, "{:?}", s.degrees);
        // The split is exact: the parts add up to the map.
        for ((c, u), z) in s.correctable_nm.iter().zip(&s.uncorrectable_nm).zip(&z) {
            assert!((c + u - z).abs() < 1e-9);
        }
        // `All` keeps everything.
        let all = split(&x, &y, &z, &tif, CorrectableBand::All).unwrap();
        assert_eq!(all.correctable_nm, z);
    }
}
