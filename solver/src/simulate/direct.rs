//! The removal of a motion in plan summed directly, without assembling `R`: `h = R t` for one
//! product with many columns, such as a program sampled along its path (tens of thousands of
//! samples), where the assembled matrix would be held for a single use.
//!
//! `h_i = sum_j TIF(x_i - X_j, y_i - Y_j) t_j` over the dwell points `j` within the TIF's support
//! radius of map point `i` (the pairs [`crate::influence::InfluenceMatrix::assemble`] keeps),
//! found with a strip index over the dwell points ([`crate::influence::model::point`]); a sample
//! that stands for a piece of motion is integrated along it ([`piece_rate`]). Each map point is summed by one task in the index's fixed
//! order, so the result does not depend on the thread count; it equals the assembled `R t` to
//! rounding (the terms are the same, the order differs).

use super::SampledProgram;
use crate::error::{Error, Result};
use crate::influence::model::piece::piece_rate;
use crate::influence::model::point::{check_lengths, sum_near, StripIndex, POINTS_PER_TASK};
use crate::observer::{Observer, Stage};
use crate::tif::{InfluenceFunction, Perturbation};
use rayon::prelude::*;

/// `h = R t`, nm, at the map points `(map_x_mm, map_y_mm)` of dwell times `dwell_s` (s) at
/// `(dwell_x_mm, dwell_y_mm)` with `tif`, without assembling `R` (module documentation).
pub fn removal_nm<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    dwell_s: &[f64],
    tif: &T,
    observer: &dyn Observer,
) -> Result<Vec<f64>> {
    let (m, n) = (map_x_mm.len(), dwell_x_mm.len());
    check_lengths(m, n, map_y_mm, dwell_y_mm, dwell_s)?;
    let radius = tif.support_radius_mm();
    if !(radius.is_finite() && radius > 0.0) {
        return Err(Error::invalid(
            "TIF support radius",
            format!("must be positive and finite, got {radius} mm"),
        ));
    }
    observer.start(Stage::Assembly, n as u64);
    let index = StripIndex::new(dwell_x_mm, dwell_y_mm, radius);
    let r2 = radius * radius;
    let mut h = vec![0.0; m];
    h.par_chunks_mut(POINTS_PER_TASK)
        .enumerate()
        .for_each(|(c, chunk)| {
            // Cancelled: the remaining chunks are skipped, and the sums are not returned.
            if observer.cancelled() {
                return;
            }
            for (k, hi) in chunk.iter_mut().enumerate() {
                let i = c * POINTS_PER_TASK + k;
                let (px, py) = (map_x_mm[i], map_y_mm[i]);
                let mut sum = 0.0;
                index.for_each_near(px, py, radius, |j, cx, cy| {
                    let (dx, dy) = (px - cx, py - cy);
                    if dx * dx + dy * dy <= r2 {
                        sum += tif.rate_nm_per_s(dx, dy) * dwell_s[j];
                    }
                });
                *hi = sum;
            }
        });
    observer.advance(Stage::Assembly, n as u64);
    observer.finish(Stage::Assembly);
    crate::observer::check_cancelled(observer)?;
    Ok(h)
}

/// `h_k = R_k t`, nm, for each TIF `tifs[k]` over the same dwell points, in one traversal of the
/// pairs: the index and the distance test are shared (over the largest support radius), each
/// TIF sums only the pairs within its own radius, as [`removal_nm`] does. The same terms as
/// [`removal_nm`] per TIF; the order differs only with the index's strips (rounding).
pub fn removals_nm<T: InfluenceFunction>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    dwell_s: &[f64],
    tifs: &[T],
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>> {
    let (m, n, k) = (map_x_mm.len(), dwell_x_mm.len(), tifs.len());
    check_lengths(m, n, map_y_mm, dwell_y_mm, dwell_s)?;
    let r2: Vec<f64> = tifs.iter().map(|t| t.support_radius_mm().powi(2)).collect();
    let radius = r2.iter().copied().fold(0.0, f64::max).sqrt();
    if !(radius.is_finite() && radius > 0.0) || r2.iter().any(|r| !(*r > 0.0)) {
        return Err(Error::invalid(
            "TIF support radius",
            format!("must be positive and finite, got {radius} mm"),
        ));
    }
    let sums = sum_near(
        map_x_mm,
        map_y_mm,
        dwell_x_mm,
        dwell_y_mm,
        k,
        radius,
        observer,
        |_, j, dx, dy, sums| {
            let d2 = dx * dx + dy * dy;
            for ((sum, tif), r2) in sums.iter_mut().zip(tifs).zip(&r2) {
                if d2 <= *r2 {
                    *sum += tif.rate_nm_per_s(dx, dy) * dwell_s[j];
                }
            }
        },
    );
    crate::observer::check_cancelled(observer)?;
    Ok(sums)
}

/// `h_k`, nm, for each TIF `tifs[k]` of dwell samples that stand for pieces of motion, `half_mm`
/// from each sample to its piece's end, the tool at constant feed along each: every pair summed
/// by [`piece_rate`] (a footprint cut where its rate is not zero integrated exactly where its
/// cut circle crosses a piece). No pieces (`half_mm` empty: points), or a footprint without a
/// cut disc: the same terms as [`removals_nm`].
#[allow(clippy::too_many_arguments)]
pub fn piece_removals_nm<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    dwell_x_mm: &[f64],
    dwell_y_mm: &[f64],
    half_mm: &[[f64; 2]],
    dwell_s: &[f64],
    tifs: &[&T],
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>> {
    let (m, n, k) = (map_x_mm.len(), dwell_x_mm.len(), tifs.len());
    check_lengths(m, n, map_y_mm, dwell_y_mm, dwell_s)?;
    if !half_mm.is_empty() && half_mm.len() != n {
        return Err(Error::LengthMismatch {
            what: "dwell half_mm",
            got: half_mm.len(),
            expected: n,
        });
    }
    // A cut footprint reaches a map point from a piece whose midpoint is up to the piece's
    // half farther than its support radius.
    let longest_mm = half_mm.iter().map(|h| h[0].hypot(h[1])).fold(0.0, f64::max);
    let r2: Vec<f64> = tifs
        .iter()
        .map(|t| {
            let along = if t.cut_disc_mm().is_some() {
                longest_mm
            } else {
                0.0
            };
            (t.support_radius_mm() + along).powi(2)
        })
        .collect();
    let radius = r2.iter().copied().fold(0.0, f64::max).sqrt();
    if !(radius.is_finite() && radius > 0.0) || r2.iter().any(|r| !(*r > 0.0)) {
        return Err(Error::invalid(
            "TIF support radius",
            format!("must be positive and finite, got {radius} mm"),
        ));
    }
    let sums = sum_near(
        map_x_mm,
        map_y_mm,
        dwell_x_mm,
        dwell_y_mm,
        k,
        radius,
        observer,
        |_, j, dx, dy, sums| {
            let d2 = dx * dx + dy * dy;
            for ((sum, tif), r2) in sums.iter_mut().zip(tifs).zip(&r2) {
                if d2 <= *r2 {
                    let half = half_mm.get(j).copied().unwrap_or([0.0, 0.0]);
                    *sum += piece_rate(*tif, half, dx, dy) * dwell_s[j];
                }
            }
        },
    );
    crate::observer::check_cancelled(observer)?;
    Ok(sums)
}

/// Removal (nm) at the map points of dwell samples (positions and the time the tool spends at
/// each), `h(x) = sum_k TIF(x - s_k) tau_k`, summed directly (module documentation): no
/// matrix is held, and the result does not depend on the thread count. Samples that stand for
/// pieces of motion are integrated along them ([`piece_rate`]).
pub fn removal_of_samples<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    program: &SampledProgram,
    tif: &T,
    observer: &dyn Observer,
) -> Result<Vec<f64>> {
    if !program.half_mm.is_empty() {
        let mut h = piece_removals_nm(
            map_x_mm,
            map_y_mm,
            &program.x_mm,
            &program.y_mm,
            &program.half_mm,
            &program.dwell_s,
            &[tif],
            observer,
        )?;
        return Ok(h.pop().unwrap_or_default());
    }
    removal_nm(
        map_x_mm,
        map_y_mm,
        &program.x_mm,
        &program.y_mm,
        &program.dwell_s,
        tif,
        observer,
    )
}

/// The removals of the motion `samples` with `tif` in plan (a flat part) at the map points
/// `(map_x_mm, map_y_mm)` under each of `scenarios`: an offset is the TIF's own shift, so one
/// traversal serves them all, each sample along the piece it stands for ([`piece_removals_nm`]).
pub fn removals_in_plan<T: InfluenceFunction + ?Sized>(
    map_x_mm: &[f64],
    map_y_mm: &[f64],
    samples: &SampledProgram,
    tif: &T,
    scenarios: &[Perturbation],
    observer: &dyn Observer,
) -> Result<Vec<Vec<f64>>> {
    let tifs: Vec<_> = scenarios.iter().map(|p| p.of(tif)).collect();
    let refs: Vec<&dyn InfluenceFunction> =
        tifs.iter().map(|t| t as &dyn InfluenceFunction).collect();
    piece_removals_nm(
        map_x_mm,
        map_y_mm,
        &samples.x_mm,
        &samples.y_mm,
        &samples.half_mm,
        &samples.dwell_s,
        &refs,
        observer,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::influence::model::piece::piece_rate;
    use crate::influence::model::surface::{removals_on_surface_with, TifFrame};
    use crate::influence::InfluenceMatrix;
    use crate::observer::Silent;
    use crate::surface::{Plane, Surface};
    use crate::tif::{GaussianTif, GridTif};

    /// Direct sum against the assembled `R t`: the same terms in another order.
    const DIRECT_VS_ASSEMBLED_RTOL: f64 = 1e-13;

    /// Scattered points in a box (a deterministic sequence).
    fn scattered(
        n: usize,
        seed: u64,
        (x0, y0, w, h): (f64, f64, f64, f64),
    ) -> (Vec<f64>, Vec<f64>) {
        let mut s = seed;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n).map(|_| (x0 + w * next(), y0 + h * next())).unzip()
    }

    #[test]
    fn direct_removal_equals_the_assembled_product() {
        let tif = GaussianTif::new(1.1, 12.0, 4.0).unwrap();
        let (mx, my) = scattered(900, 3, (0.0, 0.0, 20.0, 12.0));
        // Dwell points beyond the map on every side, so some reach no map point.
        let (dx, dy) = scattered(1500, 7, (-6.0, -6.0, 32.0, 24.0));
        let t: Vec<f64> = (0..dx.len())
            .map(|j| 0.1 + (j % 17) as f64 * 0.05)
            .collect();
        let r = InfluenceMatrix::assemble(&mx, &my, &dx, &dy, &tif, &Silent).unwrap();
        let want = r.removal_nm(&t).unwrap();
        let got = removal_nm(&mx, &my, &dx, &dy, &t, &tif, &Silent).unwrap();
        let scale = want.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
        assert!(scale > 0.0);
        for (i, (a, b)) in got.iter().zip(&want).enumerate() {
            assert!(
                (a - b).abs() <= DIRECT_VS_ASSEMBLED_RTOL * scale,
                "point {i}: direct {a} against assembled {b}"
            );
        }
    }

    #[test]
    fn direct_removal_is_identical_for_one_and_two_threads() {
        let tif = GaussianTif::new(0.8, 5.0, 3.0).unwrap();
        let (mx, my) = scattered(3000, 11, (0.0, 0.0, 30.0, 30.0));
        let (dx, dy) = scattered(4000, 13, (0.0, 0.0, 30.0, 30.0));
        let t: Vec<f64> = (0..dx.len()).map(|j| 1.0 + (j % 5) as f64).collect();
        let run = |threads: usize| {
            crate::test_support::on_threads(threads, || {
                removal_nm(&mx, &my, &dx, &dy, &t, &tif, &Silent).unwrap()
            })
        };
        assert_eq!(run(1), run(2));
    }

    #[test]
    fn mismatched_lengths_are_refused() {
        let tif = GaussianTif::new(1.0, 1.0, 3.0).unwrap();
        let e = removal_nm(
            &[0.0],
            &[0.0],
            &[0.0, 1.0],
            &[0.0, 1.0],
            &[1.0],
            &tif,
            &Silent,
        );
        assert!(matches!(
            e,
            Err(Error::LengthMismatch {
                what: "dwell_s",
                ..
            })
        ));
    }

    /// Several TIFs in one traversal: each the single-TIF direct sum, to rounding.
    #[test]
    fn several_tifs_in_one_pass_are_each_the_direct_sum() {
        let tifs = [
            GaussianTif::new(1.1, 12.0, 4.0).unwrap(),
            GaussianTif::new(0.9, 10.0, 2.5).unwrap(),
            GaussianTif::new(1.4, 7.0, 6.0).unwrap(),
        ];
        let (mx, my) = scattered(700, 5, (0.0, 0.0, 20.0, 12.0));
        let (dx, dy) = scattered(1200, 9, (-6.0, -6.0, 32.0, 24.0));
        let t: Vec<f64> = (0..dx.len()).map(|j| 0.2 + (j % 7) as f64 * 0.1).collect();
        let all = removals_nm(&mx, &my, &dx, &dy, &t, &tifs, &Silent).unwrap();
        assert_eq!(all.len(), tifs.len());
        for (tif, got) in tifs.iter().zip(&all) {
            let want = removal_nm(&mx, &my, &dx, &dy, &t, tif, &Silent).unwrap();
            let scale = want.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
            assert!(scale > 0.0);
            for (i, (a, b)) in got.iter().zip(&want).enumerate() {
                assert!(
                    (a - b).abs() <= DIRECT_VS_ASSEMBLED_RTOL * scale,
                    "point {i}: {a} against {b}"
                );
            }
        }
    }

    /// The curved part's direct sum ([`removals_on_surface_with`]) on a plane with the machine-x
    /// frame is the plan's direct sum, for points and for pieces of motion: the same terms in
    /// another order.
    #[test]
    fn direct_sum_on_a_plane_is_the_plan_direct_sum() {
        /// The same terms in another order.
        const ON_PLANE_RTOL: f64 = 1e-12;
        let assert_close = |got: &[f64], want: &[f64], what: &str| {
            let scale = want.iter().fold(0.0_f64, |a, &b| a.max(b.abs()));
            assert!(scale > 0.0, "{what}: nothing removed");
            for (i, (a, b)) in got.iter().zip(want).enumerate() {
                assert!(
                    (a - b).abs() <= ON_PLANE_RTOL * scale,
                    "{what}, point {i}: tangent-frame sum {a} against plan sum {b}"
                );
            }
        };
        let (mx, my): (Vec<f64>, Vec<f64>) = (0..36 * 36)
            .map(|k| ((k % 36) as f64 * 0.3 - 0.37, (k / 36) as f64 * 0.3 + 0.11))
            .unzip();
        // A curved motion crossing the map: samples 0.07 mm apart.
        let (sx, sy): (Vec<f64>, Vec<f64>) = (0..160)
            .map(|k| {
                let a = k as f64 * 0.07;
                (0.5 + a, 3.0 + 2.0 * (0.4 * a).sin())
            })
            .unzip();
        let t: Vec<f64> = (0..sx.len())
            .map(|k| 0.2 + 0.1 * (k as f64 * 0.37).cos().abs())
            .collect();
        let rates: Vec<f64> = (0..35)
            .map(|k| 1.0 + (k as f64 * 0.77).sin().abs() * k as f64)
            .collect();
        let grid_tif = GridTif::new(-1.9, -1.3, 0.6, 0.5, 7, 5, rates).unwrap();
        let gauss = GaussianTif::new(0.9, 4.0, 2.7).unwrap();
        let plane = Surface::Plane(Plane {});
        let got = removals_on_surface_with(
            &plane,
            &mx,
            &my,
            &sx,
            &sy,
            &[],
            &t,
            &[grid_tif.support_radius_mm()],
            |_, _, _, u, w| grid_tif.rate_nm_per_s(u, w),
            TifFrame::MachineX,
            &Silent,
        )
        .unwrap();
        let want = removal_nm(&mx, &my, &sx, &sy, &t, &grid_tif, &Silent).unwrap();
        assert_close(&got[0], &want, "plane");
        // Samples standing for pieces of the motion (half the way to the next sample), a cut
        // Gaussian integrated along them: on the plane, the plan's piece sums.
        let halves: Vec<[f64; 2]> = (0..sx.len())
            .map(|k| {
                let j = (k + 1).min(sx.len() - 1);
                let i = j - 1;
                [0.5 * (sx[j] - sx[i]), 0.5 * (sy[j] - sy[i])]
            })
            .collect();
        let got = removals_on_surface_with(
            &plane,
            &mx,
            &my,
            &sx,
            &sy,
            &halves,
            &t,
            &[gauss.support_radius_mm()],
            |_, _, h, u, w| piece_rate(&gauss, h, u, w),
            TifFrame::MachineX,
            &Silent,
        )
        .unwrap();
        let want = piece_removals_nm(&mx, &my, &sx, &sy, &halves, &t, &[&gauss], &Silent).unwrap();
        assert_close(&got[0], &want[0], "plane, pieces");
    }
}
