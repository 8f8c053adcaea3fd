//! The removals of a contact motion on a flat part whose map lies on a lattice, as lattice
//! products where that pays.
//!
//! An executed raster's samples sit at a few offsets from the map's lattice (each stretch cut
//! into the same pieces): a sample at `p_k = q_k + delta` (`q_k` a lattice point) removes
//! `f(x_i - q_k - delta) tau_k` at map point `x_i`, so the samples that share an offset `delta`
//! are one lattice convolution of their times with the kernel `K[d] = f(d h - delta)`, and every
//! scenario of the sensitivity is the same product with its own perturbed kernel. A sample that
//! stands for a piece of motion of a footprint cut where its rate is not zero is integrated
//! along its piece ([`PieceTif`]): the kernel is then the footprint swept along the piece, and
//! the samples share one only when their pieces agree too (up to direction). Samples are
//! grouped by their offset from the lattice through the map's lowest x and y (the
//! [`FftOperator`]'s), and their piece, to within [`CLASS_TOL_MM`]; a group whose direct sum costs more than its
//! lattice products ([`lattice_pays`]) is served by one operator for all groups (the union of
//! their cells), each group and scenario one kernel transform and one convolution; the other
//! samples are summed directly ([`piece_removals_nm`]). The result is the direct sum to rounding
//! and to the grouping's tolerance: each sample of a group is taken at the group's offset and
//! piece, at most [`CLASS_TOL_MM`] from its own.

use super::direct::piece_removals_nm;
use super::SampledProgram;
use crate::error::Result;
use crate::influence::model::piece::{piece_reach_mm, PieceTif};
use crate::influence::operator::fft::FftOperator;
use crate::observer::Observer;
use crate::tif::{InfluenceFunction, Perturbation};

/// Samples whose offsets from the lattice (and pieces' halves) agree to this, mm, share one
/// kernel: the largest move of a sample to its group's offset (a removal error of at most this
/// times the TIF's steepest slope per second of the sample's time).
pub const CLASS_TOL_MM: f64 = 1e-9;

/// Work of one lattice product per cell and `log2` of the cells, in the units of one direct
/// pair (a bilinear TIF evaluation): a kernel transform and a convolution, three real
/// transforms of the lattice.
const LATTICE_WORK_PER_CELL_LOG2: f64 = 3.0;

/// Whether a group of `samples` samples is cheaper on the lattice of `cells` cells than summed
/// directly at about `pairs_per_sample` map points each (the same scenarios either way).
pub fn lattice_pays(samples: usize, pairs_per_sample: f64, cells: f64) -> bool {
    samples as f64 * pairs_per_sample > LATTICE_WORK_PER_CELL_LOG2 * cells * cells.max(2.0).log2()
}

/// A map keyed by lattice indices, hashed by rustc's multiply-rotate `FxHasher` (hundreds of
/// thousands of look-ups per motion, where SipHash's resistance to chosen keys buys nothing). The
/// maps serve look-ups only: groups and cells are kept in the order of their first sample, so the
/// hash changes no result.
type IndexMap<K, V> = rustc_hash::FxHashMap<K, V>;

/// One group of samples at one offset from the lattice: the offset, mm, and the time summed in
/// each lattice cell (cell indices relative to the lattice origin).
struct Group {
    offset_mm: (f64, f64),
    /// Half of the group's piece, mm (zero: points, or a footprint without a cut disc).
    half_mm: [f64; 2],
    samples: usize,
    cells: Vec<(i64, i64)>,
    time_s: Vec<f64>,
    cell_of: IndexMap<(i64, i64), usize>,
}

/// The removals of the motion `samples` with `tif` in plan under each of `scenarios` at the map
/// points `(map_x_mm, map_y_mm)`, nm, in the scenarios' order (module documentation). The
/// direct sum of [`piece_removals_nm`] wherever the map is not on a lattice or no group pays.
pub fn removals_in_plan_on_lattice<T: InfluenceFunction>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    samples: &SampledProgram,
    tif: &T,
    scenarios: &[Perturbation],
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>> {
    let direct = |s: &SampledProgram| {
        let tifs: Vec<_> = scenarios.iter().map(|p| p.of(tif)).collect();
        let refs: Vec<&dyn InfluenceFunction> =
            tifs.iter().map(|t| t as &dyn InfluenceFunction).collect();
        piece_removals_nm(
            map_x_mm, map_y_mm, &s.x_mm, &s.y_mm, &s.half_mm, &s.dwell_s, &refs, observer,
        )
    };
    let n = samples.dwell_s.len();
    let pitch_mm = match FftOperator::lattice_pitch_mm(map_x_mm, map_y_mm) {
        Some(p) if p > 0.0 && !scenarios.is_empty() && n > 0 => p,
        _ => return direct(samples),
    };
    if samples.x_mm.len() != n
        || samples.y_mm.len() != n
        || !(samples.half_mm.is_empty() || samples.half_mm.len() == n)
    {
        return direct(samples);
    }
    // The pieces matter only for a footprint with a cut disc; a piece and its reverse are one.
    let pieces = !samples.half_mm.is_empty() && tif.cut_disc_mm().is_some();
    let half_of = |k: usize| -> [f64; 2] {
        if !pieces {
            return [0.0, 0.0];
        }
        let h = samples.half_mm[k];
        if h[0] < 0.0 || (h[0] == 0.0 && h[1] < 0.0) {
            [-h[0], -h[1]]
        } else {
            h
        }
    };
    let x0 = map_x_mm.iter().copied().fold(f64::INFINITY, f64::min);
    let y0 = map_y_mm.iter().copied().fold(f64::INFINITY, f64::min);
    // Groups in the order of their first sample; each sample's group, or none (off any usable
    // lattice cell: a non-finite position or one beyond the lattice's index range).
    let mut groups: Vec<Group> = Vec::new();
    let mut group_of: IndexMap<[i64; 4], usize> = IndexMap::default();
    let mut sample_group: Vec<Option<(usize, (i64, i64))>> = Vec::with_capacity(n);
    let cell_and_offset = |v: f64, origin: f64| -> Option<(i64, f64)> {
        let u = ((v - origin) / pitch_mm).round();
        (u.is_finite() && u.abs() < 1e9).then_some((u as i64, v - (origin + u * pitch_mm)))
    };
    for k in 0..n {
        let (Some((i, ox)), Some((j, oy))) = (
            cell_and_offset(samples.x_mm[k], x0),
            cell_and_offset(samples.y_mm[k], y0),
        ) else {
            sample_group.push(None);
            continue;
        };
        let half_mm = half_of(k);
        let key = [ox, oy, half_mm[0], half_mm[1]].map(|v| (v / CLASS_TOL_MM).round() as i64);
        let g = *group_of.entry(key).or_insert_with(|| {
            groups.push(Group {
                offset_mm: (ox, oy),
                half_mm,
                samples: 0,
                cells: Vec::new(),
                time_s: Vec::new(),
                cell_of: IndexMap::default(),
            });
            groups.len() - 1
        });
        groups[g].samples += 1;
        sample_group.push(Some((g, (i, j))));
    }
    // The lattice the products would take: the map's and the samples' cells padded by the
    // widest kernel's reach.
    let longest_half = groups
        .iter()
        .map(|g| piece_reach_mm(tif, g.half_mm))
        .fold(0.0, f64::max);
    let widest_mm = scenarios
        .iter()
        .map(|p| p.of(tif).support_radius_mm())
        .fold(0.0, f64::max)
        + longest_half
        + pitch_mm;
    let reach = (widest_mm / pitch_mm).ceil();
    let span = |v: &mut dyn Iterator<Item = f64>| {
        let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
            (a.min(x), b.max(x))
        });
        (hi - lo) / pitch_mm + 2.0 * reach + 1.0
    };
    let cells = span(&mut map_x_mm.iter().chain(&samples.x_mm).copied())
        * span(&mut map_y_mm.iter().chain(&samples.y_mm).copied());
    let pairs_per_sample = std::f64::consts::PI * (widest_mm / pitch_mm).powi(2);
    let on_lattice: Vec<bool> = groups
        .iter()
        .map(|g| cells.is_finite() && lattice_pays(g.samples, pairs_per_sample, cells))
        .collect();
    if !on_lattice.iter().any(|&b| b) {
        return direct(samples);
    }
    // Each lattice group's time per cell; the other samples summed directly.
    let mut rest = SampledProgram {
        x_mm: Vec::new(),
        y_mm: Vec::new(),
        dwell_s: Vec::new(),
        half_mm: Vec::new(),
    };
    for (k, sg) in sample_group.iter().enumerate() {
        match *sg {
            Some((g, cell)) if on_lattice[g] => {
                let group = &mut groups[g];
                let c = *group.cell_of.entry(cell).or_insert_with(|| {
                    group.cells.push(cell);
                    group.time_s.push(0.0);
                    group.cells.len() - 1
                });
                group.time_s[c] += samples.dwell_s[k];
            }
            _ => {
                rest.x_mm.push(samples.x_mm[k]);
                rest.y_mm.push(samples.y_mm[k]);
                rest.dwell_s.push(samples.dwell_s[k]);
                if let Some(&h) = samples.half_mm.get(k) {
                    rest.half_mm.push(h);
                }
            }
        }
    }
    // One operator over the union of the lattice groups' cells.
    let mut union: Vec<(i64, i64)> = Vec::new();
    let mut union_of: IndexMap<(i64, i64), usize> = IndexMap::default();
    for (g, group) in groups.iter().enumerate() {
        if on_lattice[g] {
            for &cell in &group.cells {
                union_of.entry(cell).or_insert_with(|| {
                    union.push(cell);
                    union.len() - 1
                });
            }
        }
    }
    let ux: Vec<f64> = union.iter().map(|c| x0 + c.0 as f64 * pitch_mm).collect();
    let uy: Vec<f64> = union.iter().map(|c| y0 + c.1 as f64 * pitch_mm).collect();
    // Every lattice group's kernel under every scenario: the scenario's offset plus the group's.
    let kernels = |group: &Group| -> Vec<_> {
        scenarios
            .iter()
            .map(|p| Perturbation {
                offset_mm: (
                    p.offset_mm.0 + group.offset_mm.0,
                    p.offset_mm.1 + group.offset_mm.1,
                ),
                ..*p
            })
            .collect()
    };
    let all: Vec<PieceTif<_>> = groups
        .iter()
        .zip(&on_lattice)
        .filter(|&(_, &l)| l)
        .flat_map(|(g, _)| {
            kernels(g)
                .into_iter()
                .map(|p| PieceTif::new(p.of(tif), g.half_mm))
        })
        .collect();
    let Some(widest) = all
        .iter()
        .max_by(|a, b| a.support_radius_mm().total_cmp(&b.support_radius_mm()))
    else {
        return direct(samples);
    };
    let operator = match FftOperator::for_products(map_x_mm, map_y_mm, &ux, &uy, pitch_mm, widest) {
        Ok(op) => op,
        // A map off the lattice after all, or a lattice beyond the memory budget.
        Err(_) => return direct(samples),
    };
    let m = map_x_mm.len();
    let mut out = vec![vec![0.0; m]; scenarios.len()];
    for (group, _) in groups.iter().zip(&on_lattice).filter(|&(_, &l)| l) {
        let mut t = vec![0.0; union.len()];
        for (cell, &time) in group.cells.iter().zip(&group.time_s) {
            if let Some(&u) = union_of.get(cell) {
                t[u] = time;
            }
        }
        let perturbed: Vec<_> = kernels(group)
            .iter()
            .map(|p| PieceTif::new(p.of(tif), group.half_mm))
            .collect();
        let refs: Vec<&dyn InfluenceFunction> = perturbed
            .iter()
            .map(|k| k as &dyn InfluenceFunction)
            .collect();
        let removals = operator.removals_with(&t, &refs)?;
        for (sum, h) in out.iter_mut().zip(removals) {
            sum.iter_mut().zip(h).for_each(|(s, v)| *s += v);
        }
    }
    if !rest.dwell_s.is_empty() {
        let removals = direct(&rest)?;
        for (sum, h) in out.iter_mut().zip(removals) {
            sum.iter_mut().zip(h).for_each(|(s, v)| *s += v);
        }
    }
    crate::observer::check_cancelled(observer)?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observer::Silent;
    use crate::simulate::direct::removals_nm;
    use crate::tif::{GaussianTif, GridTif};

    /// The lattice products against the direct sum: rounding (the transforms') and the
    /// grouping's tolerance, relative to the largest removal.
    const LATTICE_VS_DIRECT_REL_TOL: f64 = 1e-10;

    /// A map on a 0.25 mm lattice and a motion along its rows cut into three pieces per
    /// stretch, each piece its own time, with the rows' ends joined by moves along y and a few
    /// samples anywhere (summed directly).
    fn raster_motion(pitch_mm: f64) -> (Vec<f64>, Vec<f64>, SampledProgram) {
        let (mut mx, mut my) = (Vec::new(), Vec::new());
        for j in 0..24 {
            for i in 0..60 {
                mx.push(-3.0 + i as f64 * pitch_mm);
                my.push(2.0 + j as f64 * pitch_mm);
            }
        }
        let mut s = SampledProgram {
            x_mm: Vec::new(),
            y_mm: Vec::new(),
            dwell_s: Vec::new(),
            half_mm: Vec::new(),
        };
        let mut push = |x: f64, y: f64, t: f64| {
            s.x_mm.push(x);
            s.y_mm.push(y);
            s.dwell_s.push(t);
        };
        for j in -8..32 {
            let y = 2.0 + j as f64 * pitch_mm;
            for i in -10..70 {
                let x = -3.0 + i as f64 * pitch_mm;
                for (piece, f) in [1.0 / 6.0, 0.5, 5.0 / 6.0].iter().enumerate() {
                    let t = 0.01 * (1.0 + 0.3 * ((i * 3 + j * 7 + piece as i32) as f64).sin());
                    push(x + f * pitch_mm, y, t);
                }
            }
            // The row's end: a move along y.
            push(-3.0 + 70.0 * pitch_mm, y + 0.5 * pitch_mm, 0.004);
        }
        for k in 0..40 {
            let a = k as f64 * 0.7371;
            push(
                -1.0 + 12.0 * (a.sin() * 0.5 + 0.5),
                3.0 + 4.0 * (a.cos() * 0.5 + 0.5),
                0.002,
            );
        }
        (mx, my, s)
    }

    fn assert_close(got: &[Vec<f64>], want: &[Vec<f64>]) {
        assert_eq!(got.len(), want.len());
        for (g, w) in got.iter().zip(want) {
            let scale = w.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
            assert!(scale > 0.0);
            for (i, (a, b)) in g.iter().zip(w).enumerate() {
                assert!(
                    (a - b).abs() <= LATTICE_VS_DIRECT_REL_TOL * scale,
                    "point {i}: lattice {a} against direct {b}"
                );
            }
        }
    }

    /// The nominal tool and the sensitivity's scenarios: TIF 3% wider, narrower, the tool
    /// 0.05 mm off in x, in y.
    fn scenarios() -> Vec<Perturbation> {
        let p = Perturbation::NONE;
        vec![
            p,
            Perturbation {
                width_factor: 1.0 + 0.03,
                ..p
            },
            Perturbation {
                width_factor: 1.0 / (1.0 + 0.03),
                ..p
            },
            Perturbation {
                offset_mm: (0.05, 0.0),
                ..p
            },
            Perturbation {
                offset_mm: (0.0, 0.05),
                ..p
            },
        ]
    }

    /// A measured (bilinear) grid TIF: the lattice products are the direct sums of the
    /// bilinear evaluation under every scenario.
    #[test]
    fn grid_tif_lattice_products_are_the_direct_sums() {
        let pitch = 0.25;
        let (mx, my, s) = raster_motion(pitch);
        // A grid of 0.13 mm (off the map's lattice), a smooth bump.
        let (nx, ny, p) = (31usize, 29usize, 0.13);
        let rates: Vec<f64> = (0..ny)
            .flat_map(|j| {
                (0..nx).map(move |i| {
                    let (x, y) = ((i as f64 - 15.0) * p, (j as f64 - 14.0) * p + 0.05);
                    (10.0 - x * x - 1.3 * y * y).max(0.0) + 0.1 * x
                })
            })
            .collect();
        let tif = GridTif::new(-15.0 * p, -14.0 * p, p, p, nx, ny, rates).unwrap();
        let scen = scenarios();
        let tifs: Vec<_> = scen.iter().map(|q| q.of(&tif)).collect();
        let want = removals_nm(&mx, &my, &s.x_mm, &s.y_mm, &s.dwell_s, &tifs, &Silent).unwrap();
        let got = removals_in_plan_on_lattice(&mx, &my, &s, &tif, &scen, &Silent).unwrap();
        assert_close(&got, &want);
    }

    /// A cut Gaussian: the same.
    #[test]
    fn gaussian_lattice_products_are_the_direct_sums() {
        let pitch = 0.25;
        let (mx, my, s) = raster_motion(pitch);
        let tif = GaussianTif::new(0.7, 20.0, 2.1).unwrap();
        let scen = scenarios();
        let tifs: Vec<_> = scen.iter().map(|q| q.of(&tif)).collect();
        let want = removals_nm(&mx, &my, &s.x_mm, &s.y_mm, &s.dwell_s, &tifs, &Silent).unwrap();
        let got = removals_in_plan_on_lattice(&mx, &my, &s, &tif, &scen, &Silent).unwrap();
        assert_close(&got, &want);
    }

    /// A cut Gaussian along pieces of motion (every seventh run the other way): the lattice
    /// products of the pieces are the direct sums of the pieces integrated along them.
    #[test]
    fn gaussian_pieces_lattice_products_are_the_direct_piece_sums() {
        let pitch = 0.25;
        let (mx, my, mut s) = raster_motion(pitch);
        s.half_mm = (0..s.dwell_s.len())
            .map(|k| {
                let h = if k % 7 == 0 {
                    -pitch / 6.0
                } else {
                    pitch / 6.0
                };
                [h, 0.0]
            })
            .collect();
        let tif = GaussianTif::new(0.7, 20.0, 2.1).unwrap();
        let scen = scenarios();
        let tifs: Vec<_> = scen.iter().map(|q| q.of(&tif)).collect();
        let refs: Vec<&dyn InfluenceFunction> =
            tifs.iter().map(|t| t as &dyn InfluenceFunction).collect();
        let want = piece_removals_nm(
            &mx, &my, &s.x_mm, &s.y_mm, &s.half_mm, &s.dwell_s, &refs, &Silent,
        )
        .unwrap();
        let points = removals_nm(&mx, &my, &s.x_mm, &s.y_mm, &s.dwell_s, &tifs, &Silent).unwrap();
        // The pieces differ from their midpoints at the cut.
        assert!(want[0].iter().zip(&points[0]).any(|(a, b)| a != b));
        let got = removals_in_plan_on_lattice(&mx, &my, &s, &tif, &scen, &Silent).unwrap();
        assert_close(&got, &want);
    }

    /// A group pays on the lattice only when its direct pairs outweigh the lattice's work.
    #[test]
    fn a_lone_sample_is_summed_directly_and_a_full_raster_on_the_lattice() {
        let cells = 500.0 * 150.0;
        assert!(!lattice_pays(1, 1500.0, cells));
        assert!(lattice_pays(30_000, 1500.0, cells));
    }
}
