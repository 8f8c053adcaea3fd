//! A free-form correction of the footprint: what the parametric figures leave, deconvolved from
//! the residual where the data support it.
//!
//! The correction is `Δf(d) = Σ_c δ_c Λ((d - c) / q)`, bilinear hats `Λ` on nodes `c` of pitch
//! `q` over the calibrated footprint. Each node's removal column is the hat convolved with the
//! run's time density (its drift included), a shift of one convolution. The weights minimise
//! `||J δ - e||² + α (||L δ||² + μ ||δ||²)` (Tikhonov: `e` the parametric fit's residual, the
//! nuisance terms projected out of `J`, `L` the five-point Laplacian of the node grid, zero
//! beyond it, `μ` a tenth of `L`'s mean squared diagonal), `α`
//! chosen by generalised cross-validation, `GCV(α) = m RSS / (m - tr H)²` (Golub, Heath and Wahba
//! 1979). The correction keeps the footprint's volume, centroid and second moment (the
//! parametric figures say those), so it changes only the shape. It is applied only when it
//! lowers the fit's RMS by at least
//! [`MIN_RELATIVE_GAIN`]; its resolution is the node pitch, its effective number of parameters
//! `tr H`.

use super::forward::LatticeRemoval;
use super::{SpotFootprint, ToolFigures};
use crate::error::{Error, Result};
use crate::tif::{GridTif, InfluenceFunction};
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

/// Smallest relative decrease of the fit's RMS for which the correction is applied.
pub const MIN_RELATIVE_GAIN: f64 = 0.05;
/// Node pitch as a fraction of the footprint's second-moment radius.
const NODE_PITCH_PER_RADIUS: f64 = 1.0 / 3.0;

/// The free-form correction and how much the data support it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FreeformCorrection {
    /// Whether the correction is part of the calibrated TIF.
    pub applied: bool,
    /// Pitch of the correction's nodes: its resolution, mm.
    pub node_pitch_mm: f64,
    /// Number of nodes.
    pub nodes: usize,
    /// Effective number of parameters the data determine (`tr H`).
    pub effective_parameters: f64,
    /// Regularisation weight chosen by cross-validation.
    pub regularisation: f64,
    /// Fit RMS before the correction, nm.
    pub fit_rms_before_nm: f64,
    /// Fit RMS with the correction, nm.
    pub fit_rms_after_nm: f64,
    /// Largest correction of the footprint, nm/s.
    pub max_abs_correction_nm_per_s: f64,
    #[serde(skip)]
    node_mm: Vec<(f64, f64)>,
    #[serde(skip)]
    weight_nm_per_s: Vec<f64>,
    #[serde(skip)]
    removal_nm: Vec<f64>,
}

impl FreeformCorrection {
    /// The correction's removal at the calibration's points, nm.
    pub fn removal_nm(&self) -> &[f64] {
        &self.removal_nm
    }

    /// The correction of the footprint at offset `(dx, dy)`, nm/s.
    pub fn correction_nm_per_s(&self, dx_mm: f64, dy_mm: f64) -> f64 {
        let q = self.node_pitch_mm;
        self.node_mm
            .iter()
            .zip(&self.weight_nm_per_s)
            .map(|(&(cx, cy), w)| {
                let (a, b) = (((dx_mm - cx) / q).abs(), ((dy_mm - cy) / q).abs());
                if a < 1.0 && b < 1.0 {
                    w * (1.0 - a) * (1.0 - b)
                } else {
                    0.0
                }
            })
            .sum()
    }
}

/// The bilinear hat of half-width `q`.
struct Hat {
    q: f64,
}

impl InfluenceFunction for Hat {
    fn rate_nm_per_s(&self, dx: f64, dy: f64) -> f64 {
        let (a, b) = ((dx / self.q).abs(), (dy / self.q).abs());
        if a < 1.0 && b < 1.0 {
            (1.0 - a) * (1.0 - b)
        } else {
            0.0
        }
    }

    fn support_radius_mm(&self) -> f64 {
        self.q * std::f64::consts::SQRT_2
    }
}

/// The correction of the residual `residual` (module documentation).
pub(super) fn fit(
    lattice: &LatticeRemoval,
    spot: &SpotFootprint,
    figures: &ToolFigures,
    residual: &[f64],
    nuisance: &[&[f64]],
    noise_rms_nm: f64,
) -> Result<FreeformCorrection> {
    let h = lattice.pitch_mm();
    let cells = (spot.radius_mm() * NODE_PITCH_PER_RADIUS / h)
        .round()
        .max(1.0) as i64;
    let q = cells as f64 * h;
    let (cx, cy) = spot.centroid_mm();
    let centre = (cx + figures.offset_x_mm, cy + figures.offset_y_mm);
    let reach = figures.width_factor * spot_reach(spot) + q;
    let span = (reach / q).ceil() as i64 + 1;
    let (ax, ay) = ((centre.0 / q).round() as i64, (centre.1 / q).round() as i64);
    let mut nodes = Vec::new();
    for b in -span..=span {
        for a in -span..=span {
            let (x, y) = ((ax + a) as f64 * q, (ay + b) as f64 * q);
            if (x - centre.0).hypot(y - centre.1) <= reach {
                nodes.push((ax + a, ay + b));
            }
        }
    }
    let m = residual.len();
    let n = nodes.len();
    crate::budget::check_f64s(
        "free-form correction",
        &format!("{m} points by {n} nodes"),
        m as f64 * n as f64,
        2.0,
    )?;
    let [g0, g1] = lattice.convolved_grids(&Hat { q });
    let drift = figures.drift_per_hour;
    let grid: Vec<f64> = g0.iter().zip(&g1).map(|(a, b)| a + drift * b).collect();
    let mut jac = DMatrix::from_fn(m, n, |i, k| {
        let (a, b) = nodes[k];
        lattice.read_shifted(&grid, i, a * cells, b * cells)
    });
    // Project the nuisance terms out of the columns.
    if !nuisance.is_empty() {
        let nmat = DMatrix::from_fn(m, nuisance.len(), |i, k| nuisance[k][i]);
        let gram = nmat.tr_mul(&nmat);
        if let Some(ch) = gram.cholesky() {
            let coef = ch.solve(&nmat.tr_mul(&jac));
            jac -= &nmat * coef;
        }
    }
    let e = DVector::from_column_slice(residual);
    // The correction changes the footprint's shape only: its volume, centroid and second moment
    // (those of the hats about the calibrated centroid) are held at zero by projecting onto the
    // null space of the constraints `C δ = 0`, `P = I - Cᵀ (C Cᵀ)⁻¹ C`.
    let constraints = DMatrix::from_fn(4, n, |r, k| {
        let (x, y) = (
            nodes[k].0 as f64 * q - centre.0,
            nodes[k].1 as f64 * q - centre.1,
        );
        [1.0, x, y, x * x + y * y][r]
    });
    let cct = &constraints * constraints.transpose();
    let projector = match cct.try_inverse() {
        Some(inv) => DMatrix::identity(n, n) - constraints.transpose() * inv * &constraints,
        None => DMatrix::identity(n, n),
    };
    let gram = &projector * jac.tr_mul(&jac) * &projector;
    let rhs = &projector * jac.tr_mul(&e);
    let index: std::collections::HashMap<(i64, i64), usize> =
        nodes.iter().enumerate().map(|(k, &c)| (c, k)).collect();
    let mut lap: DMatrix<f64> = DMatrix::zeros(n, n);
    for (k, &(a, b)) in nodes.iter().enumerate() {
        lap[(k, k)] = 4.0;
        for d in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
            if let Some(&o) = index.get(&(a + d.0, b + d.1)) {
                lap[(k, o)] = -1.0;
            }
        }
    }
    // Roughness, and a tenth of it on the size of the correction (the smooth directions the
    // run cannot tell apart).
    let mut penalty = lap.tr_mul(&lap);
    let ridge = 0.1 * penalty.trace() / n.max(1) as f64;
    for k in 0..n {
        penalty[(k, k)] += ridge;
    }
    let penalty = &projector * penalty * &projector;
    let scale = gram.trace() / penalty.trace().max(f64::MIN_POSITIVE);
    // Keeps the constrained directions (zero in both terms) solvable; they stay zero.
    let floor = 1e-12 * scale * penalty.trace() / n.max(1) as f64;
    let rss0 = e.norm_squared();
    let mut best: Option<(f64, f64, DVector<f64>, f64)> = None;
    for k in -9..=3 {
        let alpha = scale * 10f64.powi(k);
        let mut a = &gram + alpha * &penalty;
        for d in 0..n {
            a[(d, d)] += floor.max(f64::MIN_POSITIVE);
        }
        let Some(ch) = a.cholesky() else {
            continue;
        };
        let delta = &projector * ch.solve(&rhs);
        let fit = &jac * &delta;
        let rss = (&e - &fit).norm_squared();
        let trace_h = ch.solve(&gram).trace();
        let dof = m as f64 - trace_h;
        if dof <= 0.0 {
            continue;
        }
        let gcv = m as f64 * rss / (dof * dof);
        if best.as_ref().is_none_or(|b| gcv < b.0) {
            best = Some((gcv, alpha, delta, trace_h));
        }
    }
    let Some((_, alpha, delta, trace_h)) = best else {
        return Err(Error::invalid(
            "free-form correction",
            "no regularisation gave a solvable system",
        ));
    };
    let removal: Vec<f64> = (&jac * &delta).iter().copied().collect();
    let rss = residual
        .iter()
        .zip(&removal)
        .map(|(r, v)| (r - v).powi(2))
        .sum::<f64>();
    let before = (rss0 / m as f64).sqrt();
    let after = (rss / m as f64).sqrt();
    // Applied only where it explains clearly more than the noise would by chance.
    let applied = after <= (1.0 - MIN_RELATIVE_GAIN) * before && before > noise_rms_nm;
    let weights: Vec<f64> = delta.iter().copied().collect();
    Ok(FreeformCorrection {
        applied,
        node_pitch_mm: q,
        nodes: n,
        effective_parameters: trace_h,
        regularisation: alpha,
        fit_rms_before_nm: before,
        fit_rms_after_nm: after,
        max_abs_correction_nm_per_s: weights.iter().fold(0.0, |a, w| a.max(w.abs())),
        node_mm: nodes
            .iter()
            .map(|&(a, b)| (a as f64 * q, b as f64 * q))
            .collect(),
        weight_nm_per_s: weights,
        removal_nm: removal,
    })
}

/// Largest distance of a positive node of the spot test from its centroid, mm.
fn spot_reach(spot: &SpotFootprint) -> f64 {
    let g = spot.grid();
    let (nx, _) = g.shape();
    let (px, py) = g.pitch_mm();
    let (x0, y0) = g.origin_mm();
    let (cx, cy) = spot.centroid_mm();
    g.rates_nm_per_s()
        .iter()
        .enumerate()
        .filter(|(_, r)| **r > 0.0)
        .map(|(k, _)| (x0 + (k % nx) as f64 * px - cx).hypot(y0 + (k / nx) as f64 * py - cy))
        .fold(0.0, f64::max)
}

/// The calibrated footprint on a grid at the spot test's pitch: the figures applied to the spot
/// test, plus the free-form correction where applied, negative rates set to zero.
pub(super) fn calibrated_grid(
    spot: &SpotFootprint,
    figures: &ToolFigures,
    correction: Option<&FreeformCorrection>,
) -> Result<GridTif> {
    let (px, py) = spot.grid().pitch_mm();
    let pitch = px.min(py);
    let tif = spot.transformed(figures);
    let (cx, cy) = spot.centroid_mm();
    let centre = (cx + figures.offset_x_mm, cy + figures.offset_y_mm);
    let stretch = figures.ellipticity.hypot(figures.ellipticity_45).exp();
    let reach = figures.width_factor * stretch * spot_reach(spot)
        + correction.map_or(0.0, |c| 2.0 * c.node_pitch_mm)
        + pitch;
    let half = (reach / pitch).ceil() as i64;
    let (ax, ay) = (
        (centre.0 / pitch).round() as i64,
        (centre.1 / pitch).round() as i64,
    );
    let side = (2 * half + 1) as usize;
    let x0 = (ax - half) as f64 * pitch;
    let y0 = (ay - half) as f64 * pitch;
    let rates: Vec<f64> = (0..side * side)
        .map(|k| {
            let (x, y) = (
                x0 + (k % side) as f64 * pitch,
                y0 + (k / side) as f64 * pitch,
            );
            let extra = correction
                .filter(|c| c.applied)
                .map_or(0.0, |c| c.correction_nm_per_s(x, y));
            (tif.rate_nm_per_s(x, y) + extra).max(0.0)
        })
        .collect();
    // Cropped to the nodes with a rate, and one node beyond.
    let positive = |k: usize| rates[k] > 0.0;
    let (mut i0, mut i1, mut j0, mut j1) = (side, 0, side, 0);
    for k in (0..side * side).filter(|&k| positive(k)) {
        let (i, j) = (k % side, k / side);
        (i0, i1, j0, j1) = (i0.min(i), i1.max(i), j0.min(j), j1.max(j));
    }
    if i0 > i1 {
        return Err(Error::invalid("calibrated TIF", "every rate is zero"));
    }
    let (i0, j0) = (i0.saturating_sub(1), j0.saturating_sub(1));
    let (i1, j1) = ((i1 + 1).min(side - 1), (j1 + 1).min(side - 1));
    let (nx, ny) = (i1 - i0 + 1, j1 - j0 + 1);
    let cropped = (j0..=j1)
        .flat_map(|j| (i0..=i1).map(move |i| (i, j)))
        .map(|(i, j)| rates[j * side + i])
        .collect();
    GridTif::new(
        x0 + i0 as f64 * pitch,
        y0 + j0 as f64 * pitch,
        pitch,
        pitch,
        nx,
        ny,
        cropped,
    )
}
