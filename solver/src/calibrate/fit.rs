//! The calibration fit: variable-projection Levenberg-Marquardt, covariance, held figures
//! (module documentation of [`super`]).

use super::forward::LatticeRemoval;
use super::freeform;
use super::tool::{footprint_moments, SkewForm};
use super::{
    Calibration, CalibrationSettings, ContactMotion, Correlation, HeldFigure, MeasuredChange,
    Nuisance, SpotFootprint, ToolFigures, UNDETERMINED_FRACTION,
};
use crate::error::{Error, Result};
use crate::map::HeightStats;
use crate::status::Status;
use nalgebra::{DMatrix, DVector};
use std::collections::HashMap;

/// The nonlinear figures, in the order of this array: the footprint's (rate aside) and the map
/// shift.
const NONLINEAR: [&str; 9] = [
    "width_factor",
    "offset_x_mm",
    "offset_y_mm",
    "ellipticity",
    "ellipticity_45",
    "skew_x",
    "skew_y",
    "map_shift_x_mm",
    "map_shift_y_mm",
];
const WIDTH: usize = 0;
const SKEW_X: usize = 5;
const SHIFT_X: usize = 7;
const SHIFT_Y: usize = 8;
/// A Levenberg-Marquardt step that moves every free figure by less than this fraction of its
/// finite-difference step ends the fit.
const STEP_REL_TOL: f64 = 1e-3;
/// Relative decrease of the cost below which a step counts as converged.
const COST_REL_TOL: f64 = 1e-7;
/// Largest lag-one correlation of the residual taken into the variance inflation.
const MAX_LAG_CORRELATION: f64 = 0.995;
/// Lattice cells per second-moment radius of the footprint, by default.
const CELLS_PER_RADIUS: f64 = 10.0;

/// The nominal value of nonlinear figure `j`.
fn nominal(j: usize) -> f64 {
    if j == WIDTH {
        1.0
    } else {
        0.0
    }
}

/// The model of one set of free figures.
struct Model<'a> {
    change: &'a MeasuredChange,
    spot: &'a SpotFootprint,
    lattice: LatticeRemoval,
    fit_drift: bool,
    fit_power: bool,
    /// Finite-difference step, bound and prior standard deviation of each nonlinear figure.
    step: [f64; 9],
    bound: [(f64, f64); 9],
    prior: [f64; 9],
    /// Prior standard deviation of the drift, per hour.
    drift_prior: f64,
    /// The data's standard deviation per point (its correlation included): the scale of the
    /// prior rows.
    sd: f64,
    free: Vec<usize>,
    /// The skew's form.
    skew_form: SkewForm,
    /// A removal held fixed beside the parametric one (the free-form correction's), nm.
    extra_nm: Option<Vec<f64>>,
}

/// One evaluation: the residual and the linear coefficients.
struct Eval {
    /// Data residual, then the prior rows (the drift's, then each free figure's).
    residual: Vec<f64>,
    /// Rate, rate times drift (when fitted), piston, tilt x, tilt y, power (when fitted).
    coef: Vec<f64>,
    columns: Vec<Vec<f64>>,
    change: Vec<f64>,
    parts: [Vec<f64>; 2],
}

impl Eval {
    /// The data part of the residual.
    fn data(&self) -> &[f64] {
        &self.residual[..self.change.len()]
    }
}

/// Least squares `min ||M c - d||² + Σ_k (w_k c_k)²` of a few columns (normalised) with ridge
/// rows `ridge` `(k, w_k)`, by SVD.
fn lstsq(columns: &[Vec<f64>], d: &[f64], ridge: &[(usize, f64)]) -> Result<Vec<f64>> {
    let (m, q) = (d.len(), columns.len());
    let norms: Vec<f64> = columns
        .iter()
        .map(|c| {
            c.iter()
                .map(|v| v * v)
                .sum::<f64>()
                .sqrt()
                .max(f64::MIN_POSITIVE)
        })
        .collect();
    let rows = m + ridge.len();
    let mut mat = DMatrix::from_fn(
        rows,
        q,
        |i, j| if i < m { columns[j][i] / norms[j] } else { 0.0 },
    );
    for (r, &(k, w)) in ridge.iter().enumerate() {
        mat[(m + r, k)] = w / norms[k];
    }
    let mut rhs = DVector::zeros(rows);
    rhs.rows_mut(0, m).copy_from_slice(d);
    let svd = mat.svd(true, true);
    let eps = 1e-12 * svd.singular_values.max();
    let c = svd
        .solve(&rhs, eps)
        .map_err(|e| Error::invalid("calibration fit", e.to_string()))?;
    Ok(c.iter().zip(&norms).map(|(v, n)| v / n).collect())
}

impl Model<'_> {
    fn figures(nl: &[f64; 9]) -> ToolFigures {
        ToolFigures {
            rate_factor: 1.0,
            width_factor: nl[0],
            offset_x_mm: nl[1],
            offset_y_mm: nl[2],
            ellipticity: nl[3],
            ellipticity_45: nl[4],
            skew_x: nl[5],
            skew_y: nl[6],
            drift_per_hour: 0.0,
        }
    }

    /// The removal columns and the measured change at `nl`. The after map's point `x` is the
    /// part's point `x + s` in the before map's frame, where the program ran: the removal there
    /// with the tool `o` off is the removal at `x` with the tool `o - s` off.
    fn parts(&self, nl: &[f64; 9]) -> ([Vec<f64>; 2], Vec<f64>, Vec<f64>) {
        let mut figures = Self::figures(nl);
        figures.offset_x_mm -= nl[SHIFT_X];
        figures.offset_y_mm -= nl[SHIFT_Y];
        let tif = self.spot.transformed_as(&figures, self.skew_form);
        let (mut change, weight) = self.change.weighted_change_nm((nl[SHIFT_X], nl[SHIFT_Y]));
        if let Some(extra) = &self.extra_nm {
            for (c, e) in change.iter_mut().zip(extra) {
                *c -= e;
            }
        }
        (self.lattice.removal_parts(&tif), change, weight)
    }

    /// The weighted data residual of `change` less the columns times `coef`.
    fn data_residual(
        columns: &[Vec<f64>],
        coef: &[f64],
        change: &[f64],
        weight: &[f64],
    ) -> Vec<f64> {
        let mut r = change.to_vec();
        for (col, c) in columns.iter().zip(coef) {
            for (ri, v) in r.iter_mut().zip(col) {
                *ri -= c * v;
            }
        }
        for (ri, w) in r.iter_mut().zip(weight) {
            *ri *= w;
        }
        r
    }

    /// The linear columns: removal, removal drift, piston, tilts, power.
    fn columns(&self, parts: &[Vec<f64>; 2]) -> Vec<Vec<f64>> {
        let c = self.change;
        let mut cols = vec![parts[0].clone()];
        if self.fit_drift {
            cols.push(parts[1].clone());
        }
        cols.push(vec![1.0; c.len()]);
        cols.push(c.x_mm.clone());
        cols.push(c.y_mm.clone());
        if self.fit_power {
            cols.push(
                c.x_mm
                    .iter()
                    .zip(&c.y_mm)
                    .map(|(x, y)| x * x + y * y)
                    .collect(),
            );
        }
        cols
    }

    /// Weight of the drift's prior row on the rate-times-drift coefficient.
    fn drift_weight(&self) -> f64 {
        self.sd / self.drift_prior
    }

    /// The full residual for data residual `data`, coefficients `coef` and figures `nl`.
    fn with_priors(&self, mut data: Vec<f64>, coef: &[f64], nl: &[f64; 9]) -> Vec<f64> {
        if self.fit_drift {
            data.push(self.drift_weight() * coef[1]);
        }
        for &j in &self.free {
            data.push(self.sd / self.prior[j] * (nl[j] - nominal(j)));
        }
        data
    }

    fn eval(&self, nl: &[f64; 9]) -> Result<Eval> {
        let (parts, change, weight) = self.parts(nl);
        let columns = self.columns(&parts);
        let ridge: Vec<(usize, f64)> = if self.fit_drift {
            vec![(1, self.drift_weight())]
        } else {
            Vec::new()
        };
        let weighted: Vec<Vec<f64>> = columns
            .iter()
            .map(|c| c.iter().zip(&weight).map(|(v, w)| v * w).collect())
            .collect();
        let target: Vec<f64> = change.iter().zip(&weight).map(|(v, w)| v * w).collect();
        let coef = lstsq(&weighted, &target, &ridge)?;
        let data = Self::data_residual(&columns, &coef, &change, &weight);
        let residual = self.with_priors(data, &coef, nl);
        Ok(Eval {
            residual,
            coef,
            columns,
            change,
            parts,
        })
    }

    /// The full residual at `nl` with the linear coefficients held at `coef`.
    fn residual_fixed(&self, nl: &[f64; 9], coef: &[f64]) -> Vec<f64> {
        let (parts, change, weight) = self.parts(nl);
        let columns = self.columns(&parts);
        let r = Self::data_residual(&columns, coef, &change, &weight);
        self.with_priors(r, coef, nl)
    }
}

fn cost(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Levenberg-Marquardt over the free nonlinear figures with the linear ones projected out.
fn levenberg_marquardt(
    model: &Model,
    nl: &mut [f64; 9],
    max_iterations: usize,
) -> Result<(Status, usize, Eval)> {
    let free = &model.free;
    let mut current = model.eval(nl)?;
    let mut c0 = cost(&current.residual);
    let mut mu = 1e-3;
    let mut iterations = 0;
    if free.is_empty() {
        return Ok((Status::Converged, 0, current));
    }
    let m = current.residual.len();
    for _ in 0..max_iterations {
        iterations += 1;
        let mut jac = DMatrix::zeros(m, free.len());
        for (col, &j) in free.iter().enumerate() {
            let mut p = *nl;
            p[j] += model.step[j];
            let r = model.eval(&p)?.residual;
            for i in 0..m {
                jac[(i, col)] = (r[i] - current.residual[i]) / model.step[j];
            }
        }
        let r = DVector::from_column_slice(&current.residual);
        let g = jac.tr_mul(&r);
        let h = jac.tr_mul(&jac);
        let mut accepted = None;
        for _ in 0..12 {
            let mut a = h.clone();
            for k in 0..free.len() {
                a[(k, k)] += mu * h[(k, k)].max(1e-12 * h.max());
            }
            let Some(delta) = a.cholesky().map(|ch| ch.solve(&(-&g))) else {
                mu *= 4.0;
                continue;
            };
            let mut p = *nl;
            for (k, &j) in free.iter().enumerate() {
                p[j] = (p[j] + delta[k]).clamp(model.bound[j].0, model.bound[j].1);
            }
            let e = model.eval(&p)?;
            let c1 = cost(&e.residual);
            if c1 < c0 {
                accepted = Some((p, e, c1));
                mu = (mu / 3.0).max(1e-12);
                break;
            }
            mu *= 4.0;
        }
        let Some((p, e, c1)) = accepted else {
            // No step lowers the cost: a stationary point.
            return Ok((Status::Converged, iterations, current));
        };
        // A step below what the finite-difference Jacobian resolves in every figure ends the
        // fit as well: the cost then falls by rounding-level amounts for many steps.
        let resolved = free
            .iter()
            .all(|&j| (p[j] - nl[j]).abs() <= STEP_REL_TOL * model.step[j]);
        *nl = p;
        current = e;
        let decrease = c0 - c1;
        c0 = c1;
        if resolved || decrease <= COST_REL_TOL * c1.max(f64::MIN_POSITIVE) {
            return Ok((Status::Converged, iterations, current));
        }
    }
    Ok((Status::MaxIterations, iterations, current))
}

/// Pairs of neighbouring points along x and along y (on the points' own lattice).
fn neighbour_pairs(x: &[f64], y: &[f64]) -> [Vec<(usize, usize)>; 2] {
    let step = |v: &[f64]| {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        s.windows(2)
            .map(|w| w[1] - w[0])
            .filter(|d| *d > 1e-9)
            .fold(f64::INFINITY, f64::min)
    };
    let (px, py) = (step(x), step(y));
    if !(px.is_finite() && py.is_finite()) {
        return [Vec::new(), Vec::new()];
    }
    let key = |i: usize| ((x[i] / px).round() as i64, (y[i] / py).round() as i64);
    let index: HashMap<(i64, i64), usize> = (0..x.len()).map(|i| (key(i), i)).collect();
    let mut pairs = [Vec::new(), Vec::new()];
    for i in 0..x.len() {
        let (a, b) = key(i);
        if let Some(&j) = index.get(&(a + 1, b)) {
            pairs[0].push((i, j));
        }
        if let Some(&j) = index.get(&(a, b + 1)) {
            pairs[1].push((i, j));
        }
    }
    pairs
}

/// The white noise of one map from its second differences along the lattice lines, nm RMS:
/// `z_{i-1} - 2 z_i + z_{i+1}` has variance `6 σ²` for white noise and is blind to the map's
/// slope, so `σ² = min over the axes of mean (second difference)² / 6` (structure at the pixel
/// scale still counts as noise: an upper bound).
pub(super) fn neighbour_noise(x: &[f64], y: &[f64], z: &[f64]) -> f64 {
    let pairs = neighbour_pairs(x, y);
    let mut best = f64::INFINITY;
    for p in &pairs {
        // Triples i -> j -> k along the axis.
        let next: HashMap<usize, usize> = p.iter().copied().collect();
        let (mut sum, mut count) = (0.0, 0usize);
        for &(i, j) in p {
            if let Some(&k) = next.get(&j) {
                sum += (z[i] - 2.0 * z[j] + z[k]).powi(2);
                count += 1;
            }
        }
        if count >= 8 {
            best = best.min(sum / count as f64 / 6.0);
        }
    }
    if best.is_finite() {
        best.sqrt()
    } else {
        0.0
    }
}

/// The noise of one map (nm RMS) and the variance inflation of the residual's correlation.
fn residual_statistics(x: &[f64], y: &[f64], r: &[f64]) -> (f64, f64) {
    let pairs = neighbour_pairs(x, y);
    let mut noise2 = f64::INFINITY;
    let mut inflation = 1.0;
    let total: f64 = cost(r);
    for p in &pairs {
        if p.len() < 8 {
            continue;
        }
        let diff2 = p.iter().map(|&(i, j)| (r[i] - r[j]).powi(2)).sum::<f64>() / p.len() as f64;
        // The residual holds the noise of both maps: 2 σ² each point, 4 σ² a difference.
        noise2 = noise2.min(diff2 / 4.0);
        let lag = p.iter().map(|&(i, j)| r[i] * r[j]).sum::<f64>()
            / p.len() as f64
            / (total / r.len() as f64).max(f64::MIN_POSITIVE);
        let rho = lag.clamp(0.0, MAX_LAG_CORRELATION);
        inflation *= (1.0 + rho) / (1.0 - rho);
    }
    if !noise2.is_finite() {
        noise2 = total / r.len().max(1) as f64 / 2.0;
    }
    (noise2.sqrt(), inflation)
}

/// The posterior covariance of every free figure and nuisance term, with their names.
struct Covariance {
    names: Vec<String>,
    cov: DMatrix<f64>,
    corr: DMatrix<f64>,
}

fn covariance(model: &Model, nl: &[f64; 9], eval: &Eval) -> Result<Covariance> {
    let free = &model.free;
    let rows = eval.residual.len();
    let m = eval.change.len();
    let q = free.len() + eval.columns.len();
    let mut jac = DMatrix::zeros(rows, q);
    let mut names = Vec::with_capacity(q);
    for (col, &j) in free.iter().enumerate() {
        let mut p = *nl;
        p[j] += model.step[j];
        let r = model.residual_fixed(&p, &eval.coef);
        for i in 0..rows {
            jac[(i, col)] = (r[i] - eval.residual[i]) / model.step[j];
        }
        names.push(NONLINEAR[j].to_string());
    }
    let mut linear_names = vec!["rate_factor"];
    if model.fit_drift {
        linear_names.push("drift_per_hour");
    }
    linear_names.extend(["piston_nm", "tilt_x_nm_per_mm", "tilt_y_nm_per_mm"]);
    if model.fit_power {
        linear_names.push("power_nm_per_mm2");
    }
    let (_, _, weight) = model.parts(nl);
    for (k, (col, name)) in eval.columns.iter().zip(linear_names).enumerate() {
        for i in 0..m {
            jac[(i, free.len() + k)] = -col[i] * weight[i];
        }
        names.push(name.to_string());
    }
    if model.fit_drift {
        jac[(m, free.len() + 1)] = model.drift_weight();
    }
    let norms: Vec<f64> = (0..q)
        .map(|j| jac.column(j).norm().max(f64::MIN_POSITIVE))
        .collect();
    for (j, n) in norms.iter().enumerate() {
        jac.column_mut(j).scale_mut(1.0 / n);
    }
    let normal = jac.tr_mul(&jac);
    let inv = normal
        .try_inverse()
        .ok_or_else(|| Error::invalid("calibration fit", "the figures are not determined"))?;
    let s2 = model.sd * model.sd;
    let cov = DMatrix::from_fn(q, q, |a, b| s2 * inv[(a, b)] / (norms[a] * norms[b]));
    let corr = DMatrix::from_fn(q, q, |a, b| {
        inv[(a, b)] / (inv[(a, a)] * inv[(b, b)]).sqrt().max(f64::MIN_POSITIVE)
    });
    Ok(Covariance { names, cov, corr })
}

/// The lattice pitch: the footprint's radius over [`CELLS_PER_RADIUS`], a whole fraction of the
/// points' pitch where they lie on a lattice.
fn lattice_pitch(change: &MeasuredChange, spot: &SpotFootprint, given: Option<f64>) -> f64 {
    if let Some(p) = given {
        return p;
    }
    let target = spot.radius_mm() / CELLS_PER_RADIUS;
    let step = {
        let mut s = change.x_mm.clone();
        s.sort_by(f64::total_cmp);
        s.windows(2)
            .map(|w| w[1] - w[0])
            .filter(|d| *d > 1e-9)
            .fold(f64::INFINITY, f64::min)
    };
    if step.is_finite() && step > 0.0 {
        step / (step / target).ceil().max(1.0)
    } else {
        target
    }
}

/// Relative change of the data's standard deviation below which the fit is not repeated.
const SD_REL_TOL: f64 = 0.2;
/// Most fits with an updated data standard deviation.
const MAX_PASSES: usize = 3;

pub(super) fn run(
    change: &MeasuredChange,
    motion: &ContactMotion,
    spot: &SpotFootprint,
    settings: &CalibrationSettings,
) -> Result<Calibration> {
    let radius = spot.radius_mm();
    let (bpx, bpy) = change.before.pitch_mm();
    let prior = &settings.prior;
    let shift_sigma = prior.map_shift_sigma_mm.unwrap_or(0.5 * bpx.max(bpy));
    let bound = [
        (0.5, 2.0),
        (-radius, radius),
        (-radius, radius),
        (-0.5, 0.5),
        (-0.5, 0.5),
        (-0.5, 0.5),
        (-0.5, 0.5),
        (-0.9 * bpx, 0.9 * bpx),
        (-0.9 * bpy, 0.9 * bpy),
    ];
    // The lattice holds the widest footprint the bounds allow.
    let widest = spot.transformed(&ToolFigures {
        width_factor: 1.25,
        offset_x_mm: radius,
        offset_y_mm: radius,
        ellipticity: 0.2,
        ..ToolFigures::NOMINAL
    });
    let pitch = lattice_pitch(change, spot, settings.lattice_pitch_mm);
    let lattice = LatticeRemoval::new(
        motion,
        &change.x_mm,
        &change.y_mm,
        crate::tif::InfluenceFunction::support_radius_mm(&widest),
        pitch,
    )?;
    let mut free: Vec<usize> = vec![0, 1, 2];
    if settings.fit_shape {
        free.extend([3, 4, 5, 6]);
    }
    if settings.fit_map_shift {
        free.extend([SHIFT_X, SHIFT_Y]);
    }
    // The data's standard deviation to start from: the measured change's neighbour differences
    // (the noise of both maps, and structure finer than a pixel).
    let (noise0, _) =
        residual_statistics(&change.x_mm, &change.y_mm, &change.change_nm((0.0, 0.0)));
    let mut model = Model {
        change,
        spot,
        lattice,
        fit_drift: settings.fit_drift,
        fit_power: settings.fit_power,
        step: [
            1e-4,
            1e-3 * radius,
            1e-3 * radius,
            1e-4,
            1e-4,
            1e-3,
            1e-3,
            1e-3 * bpx,
            1e-3 * bpy,
        ],
        bound,
        prior: [
            prior.width_sigma,
            prior.offset_sigma_mm,
            prior.offset_sigma_mm,
            prior.shape_sigma,
            prior.shape_sigma,
            prior.shape_sigma,
            prior.shape_sigma,
            shift_sigma,
            shift_sigma,
        ],
        drift_prior: prior.drift_sigma_per_run * 3600.0 / motion.span_s().max(f64::MIN_POSITIVE),
        sd: (2.0f64).sqrt() * noise0.max(f64::MIN_POSITIVE),
        free,
        skew_form: SkewForm::Linear,
        extra_nm: None,
    };
    let mut nl: [f64; 9] = std::array::from_fn(nominal);
    let mut iterations = 0;
    let moments = Moments::new(spot);
    let first = parametric(
        &mut model,
        &mut nl,
        settings.max_iterations,
        &mut iterations,
    )?;
    // The free-form correction of what the figures leave; where applied, the figures are fitted
    // again beside it, and how far they move is their systematic uncertainty: the part of the
    // misfit the parametric model could not tell from its figures.
    let mut freeform = None;
    let mut systematic = [0.0; 10];
    let (status, eval, inflation, noise) = if settings.freeform {
        let (_, eval1, _, noise1) = &first;
        let base = if model.fit_drift { 2 } else { 1 };
        let alpha1 = eval1.coef[0];
        let drift1 = if model.fit_drift {
            eval1.coef[1] / alpha1
        } else {
            0.0
        };
        let mut figures1 = Model::figures(&nl);
        figures1.rate_factor = alpha1;
        figures1.drift_per_hour = drift1;
        let residual: Vec<f64> = (0..change.len())
            .map(|i| {
                let mut v = eval1.change[i];
                for (k, col) in eval1.columns.iter().enumerate() {
                    v -= eval1.coef[k] * col[i];
                }
                v
            })
            .collect();
        let nuisance_columns: Vec<&[f64]> = eval1
            .columns
            .iter()
            .skip(base)
            .map(|c| c.as_slice())
            .collect();
        let correction = freeform::fit(
            &model.lattice,
            spot,
            &figures1,
            &residual,
            &nuisance_columns,
            *noise1,
        )?;
        let applied = correction.applied;
        let before = figure_vector(&moments, &nl, eval1, model.fit_drift, SkewForm::Linear);
        if applied {
            model.extra_nm = Some(correction.removal_nm().to_vec());
            let second = parametric(
                &mut model,
                &mut nl,
                settings.max_iterations,
                &mut iterations,
            )?;
            let after = figure_vector(&moments, &nl, &second.1, model.fit_drift, SkewForm::Linear);
            for k in 0..systematic.len() {
                systematic[k] = (after[k] - before[k]).abs();
            }
            freeform = Some(correction);
            second
        } else {
            freeform = Some(correction);
            first
        }
    } else {
        first
    };
    // The skew's shape is the model's choice: the figures fitted again with the skew less its
    // first-order shift (exact only on a Gaussian footprint), and how far the reported figures
    // move between the two, is the uncertainty that choice leaves.
    if model.free.contains(&SKEW_X) {
        let primary = figure_vector(&moments, &nl, &eval, model.fit_drift, SkewForm::Linear);
        let sd = model.sd;
        model.skew_form = SkewForm::ShiftFree;
        let mut other_nl = nl;
        let mut other_iterations = 0;
        let other = parametric(
            &mut model,
            &mut other_nl,
            settings.max_iterations,
            &mut other_iterations,
        );
        model.skew_form = SkewForm::Linear;
        model.sd = sd;
        let (_, other_eval, _, _) = other?;
        let other = figure_vector(
            &moments,
            &other_nl,
            &other_eval,
            model.fit_drift,
            SkewForm::ShiftFree,
        );
        // Rate, width, offsets, ellipticities and drift mean the same in both forms.
        for k in [0, 1, 2, 3, 4, 5, 8] {
            systematic[k] = systematic[k].hypot(other[k] - primary[k]);
        }
    }
    let cov = covariance(&model, &nl, &eval)?;
    let alpha = eval.coef[0];
    if !(alpha.is_finite() && alpha > 0.0) {
        return Err(Error::invalid(
            "calibration",
            format!(
                "the run's measured change does not look like the program's removal (fitted rate factor {alpha:.4}): check that the maps are before and after this program, in the same frame and sign"
            ),
        ));
    }
    let drift = if model.fit_drift {
        eval.coef[1] / alpha
    } else {
        0.0
    };
    let sd = |name: &str| -> Option<usize> { cov.names.iter().position(|n| n == name) };
    let var = |a: usize, b: usize| cov.cov[(a, b)];
    let sigma_of = |name: &str| sd(name).map_or(0.0, |k| var(k, k).max(0.0).sqrt());
    let drift_sigma = match (sd("rate_factor"), sd("drift_per_hour")) {
        (Some(a), Some(b)) => {
            ((var(b, b) - 2.0 * drift * var(a, b) + drift * drift * var(a, a)).max(0.0)).sqrt()
                / alpha
        }
        _ => 0.0,
    };
    // Figures the run did not narrow much beyond the spot test's uncertainty.
    let mut held = Vec::new();
    let prior_of = |name: &str| -> Option<f64> {
        if name == "drift_per_hour" {
            Some(model.drift_prior)
        } else {
            NONLINEAR
                .iter()
                .position(|n| *n == name)
                .map(|j| model.prior[j])
        }
    };
    for (k, name) in cov.names.iter().enumerate() {
        let Some(prior_sigma) = prior_of(name) else {
            continue;
        };
        let posterior = if name == "drift_per_hour" {
            drift_sigma
        } else {
            var(k, k).max(0.0).sqrt()
        };
        if posterior > UNDETERMINED_FRACTION * prior_sigma {
            let (other, r) = (0..cov.names.len())
                .filter(|&o| o != k)
                .map(|o| (o, cov.corr[(k, o)]))
                .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
                .unwrap_or((k, 0.0));
            held.push(HeldFigure {
                name: name.clone(),
                reason: format!(
                    "not determined by this run: it narrows the spot test's +-{prior_sigma:.3} only to +-{posterior:.3}, confounded with {} (correlation {r:+.3}); it stays near its spot-test value",
                    cov.names[other]
                ),
            });
        }
    }
    // The footprint's own parameters (for the calibrated grid), and the figures reported.
    let mut parameters = Model::figures(&nl);
    parameters.rate_factor = alpha;
    parameters.drift_per_hour = drift;
    let mut figures = parameters;
    // Width and offset as the fitted footprint's moments, their covariance by the delta method
    // over the footprint's figures.
    let [width_ratio, centroid_x, centroid_y] = moments.of(&nl);
    figures.width_factor = width_ratio;
    figures.offset_x_mm = centroid_x;
    figures.offset_y_mm = centroid_y;
    let shape_params: Vec<(usize, usize)> = cov
        .names
        .iter()
        .enumerate()
        .filter_map(|(k, n)| {
            NONLINEAR[..SHIFT_X]
                .iter()
                .position(|m| m == n)
                .map(|j| (k, j))
        })
        .collect();
    let mut moment_jac = vec![[0.0; 3]; shape_params.len()];
    for (row, &(_, j)) in moment_jac.iter_mut().zip(&shape_params) {
        let mut p = nl;
        p[j] += model.step[j];
        let m = moments.of(&p);
        for a in 0..3 {
            row[a] = (m[a] - [width_ratio, centroid_x, centroid_y][a]) / model.step[j];
        }
    }
    let moment_sigma = |a: usize| -> f64 {
        let mut v = 0.0;
        for (r1, &(k1, _)) in moment_jac.iter().zip(&shape_params) {
            for (r2, &(k2, _)) in moment_jac.iter().zip(&shape_params) {
                v += r1[a] * var(k1, k2) * r2[a];
            }
        }
        v.max(0.0).sqrt()
    };
    // The forward model's own error, measured against the direct sum over the samples at a
    // subset of the points: no figure is known better than the model that fits it.
    let model_error = lattice_error(&model.lattice, motion, change, spot, &parameters)?;
    systematic[0] = systematic[0].hypot(model_error);
    systematic[1] = systematic[1].hypot(model_error);
    systematic[2] = systematic[2].hypot(model_error * radius);
    systematic[3] = systematic[3].hypot(model_error * radius);
    let with_systematic = |stat: f64, k: usize| stat.hypot(systematic[k]);
    let sigma = ToolFigures {
        rate_factor: with_systematic(sigma_of("rate_factor"), 0),
        width_factor: with_systematic(moment_sigma(0), 1),
        offset_x_mm: with_systematic(moment_sigma(1), 2),
        offset_y_mm: with_systematic(moment_sigma(2), 3),
        ellipticity: with_systematic(sigma_of("ellipticity"), 4),
        ellipticity_45: with_systematic(sigma_of("ellipticity_45"), 5),
        skew_x: with_systematic(sigma_of("skew_x"), 6),
        skew_y: with_systematic(sigma_of("skew_y"), 7),
        drift_per_hour: with_systematic(drift_sigma, 8),
    };
    // Nuisance coefficients follow the removal (and drift) columns.
    let base = if model.fit_drift { 2 } else { 1 };
    let nuisance = Nuisance {
        piston_nm: eval.coef[base],
        tilt_x_nm_per_mm: eval.coef[base + 1],
        tilt_y_nm_per_mm: eval.coef[base + 2],
        power_nm_per_mm2: if model.fit_power {
            eval.coef[base + 3]
        } else {
            0.0
        },
        map_shift_x_mm: nl[SHIFT_X],
        map_shift_y_mm: nl[SHIFT_Y],
    };
    let mut simulated: Vec<f64> = eval.parts[0]
        .iter()
        .zip(&eval.parts[1])
        .map(|(a, b)| alpha * (a + drift * b))
        .collect();
    let measured: Vec<f64> = (0..change.len())
        .map(|i| {
            let mut v = eval.change[i] + model.extra_nm.as_ref().map_or(0.0, |e| e[i]);
            for (k, col) in eval.columns.iter().enumerate().skip(base) {
                v -= eval.coef[k] * col[i];
            }
            v
        })
        .collect();
    if let Some(correction) = freeform.as_ref().filter(|c| c.applied) {
        for (sim, extra) in simulated.iter_mut().zip(correction.removal_nm()) {
            *sim += extra;
        }
    }
    let residual: Vec<f64> = measured
        .iter()
        .zip(&simulated)
        .map(|(m, s)| m - s)
        .collect();
    let tif = freeform::calibrated_grid(spot, &parameters, freeform.as_ref())?;

    let corr_matrix = (0..cov.names.len())
        .map(|a| (0..cov.names.len()).map(|b| cov.corr[(a, b)]).collect())
        .collect();
    Ok(Calibration {
        status,
        iterations,
        figures,
        sigma,
        held,
        correlation: Correlation {
            names: cov.names.clone(),
            matrix: corr_matrix,
        },
        nuisance,
        measured_change_rms_nm: HeightStats::of(&measured).rms_nm,
        fit_rms_nm: (cost(&residual) / residual.len() as f64).sqrt(),
        noise_rms_nm: noise,
        variance_inflation: inflation,
        points: change.len(),
        skipped: change.skipped,
        lattice_pitch_mm: pitch,
        contact_time_s: motion.contact_time_s(),
        mid_time_s: motion.mid_time_s(),
        freeform,
        map_shift: None,
        tif,
        x_mm: change.x_mm.clone(),
        y_mm: change.y_mm.clone(),
        measured_removal_nm: measured,
        simulated_removal_nm: simulated,
    })
}

/// The footprint's moments under the nonlinear figures `nl` (rate 1): width ratio and centroid
/// offset against the spot test's, which are what a calibration reports.
struct Moments<'a> {
    spot: &'a SpotFootprint,
    pitch_mm: f64,
    nominal: ((f64, f64), f64),
}

impl<'a> Moments<'a> {
    fn new(spot: &'a SpotFootprint) -> Self {
        let (px, py) = spot.grid().pitch_mm();
        let pitch_mm = px.min(py).min(spot.radius_mm() / 20.0);
        let (_, c, r) = footprint_moments(&spot.transformed(&ToolFigures::NOMINAL), pitch_mm);
        Self {
            spot,
            pitch_mm,
            nominal: (c, r),
        }
    }

    /// `(width ratio, offset x, offset y)` of the footprint under `nl`, its skew linear.
    fn of(&self, nl: &[f64; 9]) -> [f64; 3] {
        self.of_as(nl, SkewForm::Linear)
    }

    /// The same with the skew of the form `skew_form`.
    fn of_as(&self, nl: &[f64; 9], skew_form: SkewForm) -> [f64; 3] {
        let (_, c, r) = footprint_moments(
            &self.spot.transformed_as(&Model::figures(nl), skew_form),
            self.pitch_mm,
        );
        let ((c0x, c0y), r0) = self.nominal;
        [r / r0, c.0 - c0x, c.1 - c0y]
    }
}

/// The reported figures in the order of [`ToolFigures::NAMES`] (rate and drift from the linear
/// coefficients, width and offset the footprint's moments), and a slot spare.
fn figure_vector(
    moments: &Moments,
    nl: &[f64; 9],
    eval: &Eval,
    fit_drift: bool,
    skew_form: SkewForm,
) -> [f64; 10] {
    let alpha = eval.coef[0];
    let drift = if fit_drift { eval.coef[1] / alpha } else { 0.0 };
    let [w, ox, oy] = moments.of_as(nl, skew_form);
    [alpha, w, ox, oy, nl[3], nl[4], nl[5], nl[6], drift, 0.0]
}

/// The parametric fit, repeated while the data's standard deviation (the priors' scale) settles.
fn parametric(
    model: &mut Model,
    nl: &mut [f64; 9],
    max_iterations: usize,
    iterations: &mut usize,
) -> Result<(Status, Eval, f64, f64)> {
    let change = model.change;
    let mut pass = 0;
    loop {
        pass += 1;
        let (status, its, eval) = levenberg_marquardt(model, nl, max_iterations)?;
        *iterations += its;
        let data = eval.data();
        let (noise, inflation) = residual_statistics(&change.x_mm, &change.y_mm, data);
        let dof = (data.len() as f64 - (model.free.len() + eval.columns.len()) as f64).max(1.0);
        let sd = (cost(data) / dof * inflation).sqrt().max(f64::MIN_POSITIVE);
        let settled = (sd / model.sd - 1.0).abs() < SD_REL_TOL;
        model.sd = sd;
        if settled || pass >= MAX_PASSES {
            // The covariance at the final scale: the fit is kept, its priors' weight updated.
            let eval = model.eval(nl)?;
            return Ok((status, eval, inflation, noise));
        }
    }
}

/// Points of the direct-sum check of the lattice removal.
const CHECK_POINTS: usize = 256;

/// Relative RMS difference of the lattice removal from the direct sum over the contact samples,
/// with the fitted footprint and drift, at up to [`CHECK_POINTS`] points spread over the map.
fn lattice_error(
    lattice: &LatticeRemoval,
    motion: &ContactMotion,
    change: &MeasuredChange,
    spot: &SpotFootprint,
    parameters: &ToolFigures,
) -> Result<f64> {
    let m = change.len();
    let stride = m.div_ceil(CHECK_POINTS).max(1);
    let idx: Vec<usize> = (0..m).step_by(stride).collect();
    let (x, y): (Vec<f64>, Vec<f64>) = idx
        .iter()
        .map(|&i| (change.x_mm[i], change.y_mm[i]))
        .unzip();
    let mut figures = *parameters;
    figures.drift_per_hour = 0.0;
    let tif = spot.transformed(&figures);
    let mid = motion.mid_time_s();
    let dwell: Vec<f64> = motion
        .dwell_s
        .iter()
        .zip(&motion.time_s)
        .map(|(d, t)| d * (1.0 + parameters.drift_per_hour * (t - mid) / 3600.0))
        .collect();
    let direct = crate::simulate::direct::removal_nm(
        &x,
        &y,
        &motion.x_mm,
        &motion.y_mm,
        &dwell,
        &tif,
        &crate::observer::Silent,
    )?;
    let parts = lattice.removal_parts(&tif);
    let (mut diff2, mut norm2) = (0.0, 0.0);
    for (k, &i) in idx.iter().enumerate() {
        let lat = parts[0][i] + parameters.drift_per_hour * parts[1][i];
        diff2 += (lat - direct[k]).powi(2);
        norm2 += direct[k].powi(2);
    }
    Ok(if norm2 > 0.0 {
        (diff2 / norm2).sqrt()
    } else {
        0.0
    })
}
