//! The figures of a solve (`preston solve --plots`) and the 1-D PSDs behind `psd.png` /
//! `psd.csv`, from a finished solve: the same functions of `preston_io::figures` and
//! `preston_solver::psd` the CLI calls, on the same set-up and outcome.

use crate::{array, to_py, Array, InputError};
use preston_io::atomic::commit_all;
use preston_io::figures::{stage_solve_figures_with, FigureStyle};
use preston_io::pipeline::Solved;
use preston_io::plots::PlotFormat;
use preston_solver::path::raster::RasterAxis;
use preston_solver::psd::{line_psd, LineAxis};
use pyo3::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};

/// The PSD's lines run along the raster's lines.
pub(crate) fn line_axis_of(along: RasterAxis) -> LineAxis {
    match along {
        RasterAxis::X => LineAxis::X,
        RasterAxis::Y => LineAxis::Y,
    }
}

/// The PSD line direction: `along` (`"x"` or `"y"`) when given, else the job's raster direction.
pub(crate) fn line_axis(along: Option<&str>, job_along: RasterAxis) -> PyResult<LineAxis> {
    Ok(line_axis_of(match along {
        None => job_along,
        Some(a) => serde_json::from_value(serde_json::Value::String(a.to_string()))
            .map_err(|e| InputError::new_err(format!("along: {e}")))?,
    }))
}

/// The figure format of the keyword `plot_format` (`"png"` or `"svg"`).
pub(crate) fn plot_format(plot_format: &str) -> PyResult<PlotFormat> {
    plot_format
        .parse()
        .map_err(|e| InputError::new_err(format!("plot_format: {e}")))
}

/// Writes the figure set of `preston solve --plots` for `solved` into `out_dir` (created if
/// needed) in `format`, all files committed together under the directory's lock. Returns the
/// files written and the notes on figures left out (no PSD for a map off a lattice).
pub(crate) fn write_figures(
    solved: &Solved,
    out_dir: &Path,
    axis: LineAxis,
    raster_pitch_mm: Option<f64>,
    format: PlotFormat,
) -> preston_io::Result<(Vec<PathBuf>, Vec<String>)> {
    std::fs::create_dir_all(out_dir).map_err(|e| preston_io::Error::io(out_dir, e))?;
    let style = FigureStyle {
        format,
        ..FigureStyle::default()
    };
    let (staged, notes) = stage_solve_figures_with(
        &solved.prepared.setup,
        &solved.outcome,
        out_dir,
        axis,
        raster_pitch_mm,
        &style,
    )?;
    let files = staged.iter().map(|s| s.dest().to_path_buf()).collect();
    commit_all(staged)?;
    Ok((files, notes))
}

/// The one-sided 1-D PSDs (Welch, along lattice lines in `axis`) of the map error and of the
/// residual: `(frequency_per_mm, error_psd_nm2_mm, residual_psd_nm2_mm, info_json)`, the columns
/// of `psd.csv`; `info_json` holds `along`, `segments`, `segment_points` and `pitch_mm`.
pub(crate) fn psd<'py>(
    py: Python<'py>,
    solved: &Solved,
    axis: LineAxis,
) -> PyResult<(Array<'py>, Array<'py>, Array<'py>, String)> {
    let map = solved.prepared.map();
    let (x, y, z) = (map.x_mm(), map.y_mm(), map.z_nm());
    let residual = &solved.delivered().residual_nm;
    let (before, after) = py
        .detach(|| Ok((line_psd(x, y, z, axis)?, line_psd(x, y, residual, axis)?)))
        .map_err(|e| to_py(preston_io::Error::engine("psd", e)))?;
    let info = json!({
        "along": match axis { LineAxis::X => "x", LineAxis::Y => "y" },
        "segments": before.segments,
        "segment_points": before.segment_points,
        "pitch_mm": before.pitch_mm,
    });
    Ok((
        array(py, &before.frequency_per_mm),
        array(py, &before.psd_nm2_mm),
        array(py, &after.psd_nm2_mm),
        info.to_string(),
    ))
}
