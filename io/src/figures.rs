//! The figure set of a solve (`preston solve --plots`): maps of the error, the predicted removal,
//! the residual, the dwell and the feed, the TIF, the path, and the 1-D PSD of error and residual
//! along the raster direction (`psd.png`, `psd.csv`), where the raster pitch's ripple shows.

use crate::atomic::{stage, Staged};
use crate::error::{Error, Result};
use crate::plots::{stage_map_plot, stage_path_plot, stage_psd_plot};
use crate::report::centred_residual_nm;
use preston_solver::psd::{line_psd, LineAxis, LinePsd};
use preston_solver::setup::{Outcome, Setup};
use preston_solver::tif::InfluenceFunction;
use std::io::Write;
use std::path::Path;

/// Header of `psd.csv`.
pub const PSD_HEADER: &str = "frequency_per_mm,error_psd_nm2_mm,residual_psd_nm2_mm";

/// Samples per side of the TIF plot's grid.
const TIF_SAMPLES: usize = 121;

/// Stages every figure of a solve (`setup` solved into `outcome`) into `out_dir`. `axis` is the raster direction and
/// `raster_pitch_mm` its line spacing (marked on the PSD plot). Returns the staged files and
/// notes on figures left out (a PSD needs the map on a lattice).
pub fn stage_solve_figures(
    setup: &Setup,
    outcome: &Outcome,
    out_dir: &Path,
    axis: LineAxis,
    raster_pitch_mm: Option<f64>,
) -> Result<(Vec<Staged>, Vec<String>)> {
    let map = &setup.map;
    let (mx, my, z) = (map.x_mm(), map.y_mm(), map.z_nm());
    let residual = centred_residual_nm(z, &outcome.removal_nm);
    let (px, py) = (setup.path.x_mm(), setup.path.y_mm());
    let dwell = &outcome.solution.dwell_s;
    let feeds = &outcome.feeds_mm_per_min;
    let mut staged = vec![
        stage_map_plot(
            &out_dir.join("error_before.png"),
            "Surface error before",
            "nm",
            mx,
            my,
            z,
        )?,
        stage_map_plot(
            &out_dir.join("removal.png"),
            "Predicted removal",
            "nm",
            mx,
            my,
            &outcome.removal_nm,
        )?,
        stage_map_plot(
            &out_dir.join("residual.png"),
            "Residual (piston removed)",
            "nm",
            mx,
            my,
            &residual,
        )?,
        stage_map_plot(&out_dir.join("dwell.png"), "Dwell time", "s", px, py, dwell)?,
        stage_map_plot(&out_dir.join("feed.png"), "Feed", "mm/min", px, py, feeds)?,
        stage_path_plot(&out_dir.join("path.png"), "Dwell path", px, py)?,
    ];
    let radius = setup.tif.support_radius_mm();
    if radius.is_finite() && radius > 0.0 {
        let (mut tx, mut ty, mut tv) = (Vec::new(), Vec::new(), Vec::new());
        let step = 2.0 * radius / (TIF_SAMPLES - 1) as f64;
        for j in 0..TIF_SAMPLES {
            for i in 0..TIF_SAMPLES {
                let (dx, dy) = (-radius + i as f64 * step, -radius + j as f64 * step);
                tx.push(dx);
                ty.push(dy);
                tv.push(setup.tif.rate_nm_per_s(dx, dy));
            }
        }
        staged.push(stage_map_plot(
            &out_dir.join("tif.png"),
            "Tool influence function",
            "nm/s",
            &tx,
            &ty,
            &tv,
        )?);
    }
    let mut notes = Vec::new();
    match (line_psd(mx, my, z, axis), line_psd(mx, my, &residual, axis)) {
        (Ok(before), Ok(after)) => {
            staged.push(stage_psd_csv(&out_dir.join("psd.csv"), &before, &after)?);
            let marker = raster_pitch_mm
                .filter(|p| *p > 0.0)
                .map(|p| (1.0 / p, "raster pitch"));
            staged.push(stage_psd_plot(
                &out_dir.join("psd.png"),
                &format!(
                    "PSD along {} ({} segments of {} points)",
                    match axis {
                        LineAxis::X => "x",
                        LineAxis::Y => "y",
                    },
                    before.segments,
                    before.segment_points
                ),
                &before.frequency_per_mm,
                &[
                    ("error before", &before.psd_nm2_mm),
                    ("residual", &after.psd_nm2_mm),
                ],
                marker,
            )?);
        }
        (Err(e), _) | (_, Err(e)) => notes.push(format!("no psd.png / psd.csv: {e}")),
    }
    Ok((staged, notes))
}

/// Stages `psd.csv`: frequency (1/mm) and the PSD (nm^2 mm) of the error and the residual.
fn stage_psd_csv(path: &Path, before: &LinePsd, after: &LinePsd) -> Result<Staged> {
    if before.frequency_per_mm != after.frequency_per_mm {
        return Err(Error::io(
            path,
            std::io::Error::other("the two PSDs have different frequencies"),
        ));
    }
    stage(path, |w: &mut dyn Write| {
        writeln!(w, "{PSD_HEADER}")?;
        for ((f, a), b) in before
            .frequency_per_mm
            .iter()
            .zip(&before.psd_nm2_mm)
            .zip(&after.psd_nm2_mm)
        {
            writeln!(w, "{f},{a},{b}")?;
        }
        Ok(())
    })
}
