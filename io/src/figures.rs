//! The figure set of a solve (`preston solve --plots`): maps of the error, the predicted removal,
//! the residual (the one the report states, [`crate::residual`]; with an executed program also
//! the model's at the programmed feeds, `residual_model`), the dwell and the feed, the TIF, the
//! path, and the PSDs of error and residual: 1-D along the raster direction (`psd.png`, `psd.csv`), where the raster pitch's ripple shows,
//! 2-D (`psd_2d.png`, `psd_2d.csv`) and its azimuthal average (`psd_azimuthal.png`,
//! `psd_azimuthal.csv`), see [`preston_solver::psd`]. A solve with several tools draws the
//! same maps of the error, removal and residual, each tool's dwell and feed (`dwell_tool1`,
//! `feed_tool1`, ...) and the PSDs.

use crate::atomic::{stage, Staged};
use crate::error::{Error, Result};
use crate::plots::{
    stage_grid_plot, stage_map_plot, stage_map_plot_scaled, stage_map_plot_with, stage_path_plot,
    stage_psd_plot, stage_spectrum_plot, ColorLimits, ColourScale, PlotFormat,
};
use preston_solver::psd::{area_psd, line_psd, AreaPsd, LineAxis, LinePsd};
use preston_solver::setup::{Outcome, Setup};
use preston_solver::tif::InfluenceFunction;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Header of `psd.csv`.
pub const PSD_HEADER: &str = "frequency_per_mm,error_psd_nm2_mm,residual_psd_nm2_mm";

/// Header of `psd_2d.csv`: one row per lattice frequency.
pub const PSD_2D_HEADER: &str = "fx_per_mm,fy_per_mm,error_psd_nm2_mm2,residual_psd_nm2_mm2";

/// Header of `psd_azimuthal.csv`.
pub const PSD_AZIMUTHAL_HEADER: &str =
    "frequency_per_mm,error_psd_nm2_mm2,residual_psd_nm2_mm2,frequencies_averaged";

/// How the figures are drawn.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FigureStyle {
    /// Colour range of the height-error maps (the error before and the residual); the other
    /// height maps clip their outliers ([`ColorLimits::Robust`]), dwell, feed and TIF maps keep
    /// their whole range.
    pub color_limits: ColorLimits,
    /// File format of every figure (the CSVs beside them are the same in both).
    pub format: PlotFormat,
}

impl FigureStyle {
    /// The path of the figure `stem` in `out_dir`, in this style's format.
    pub fn path(&self, out_dir: &Path, stem: &str) -> PathBuf {
        out_dir.join(self.format.file_name(stem))
    }
}

/// The caption of a figure by its file name, for the report page.
pub fn caption(name: &str) -> &'static str {
    match name.rsplit_once('.').map_or(name, |(stem, _)| stem) {
        "error_before" => "Surface error before polishing (nm)",
        "removal" => "Predicted removal (nm)",
        "residual" => {
            "Predicted residual, piston removed (nm), as the report states it: \
                       the program as executed where the solve executes it"
        }
        "residual_model" => "Model residual at the programmed feeds, piston removed (nm)",
        "dwell" => "Dwell time per dwell point (s)",
        "feed" => "Feed per dwell point (mm/min)",
        stem if tool_figure(stem, "dwell") => "Dwell time per dwell point of one tool (s)",
        stem if tool_figure(stem, "feed") => "Feed per dwell point of one tool (mm/min)",
        "tif" => "Tool influence function (nm/s)",
        "path" => "Dwell path, start marked",
        "psd" => {
            "1-D PSD along the raster direction (the raster pitch's frequency dashed, \
             or where it lies off the axis, said in the legend)"
        }
        "psd_2d" => "2-D PSD of the residual, log10 of nm^2 mm^2",
        "psd_azimuthal" => "Azimuthally averaged 2-D PSD",
        "dwell_planned_vs_executed" => "Planned and executed dwell per point",
        "executed_dwell" => "Executed dwell per point (s)",
        "convergence" => "Form error per iteration",
        "final_error" => "Measured form error after the last run (nm)",
        _ => "",
    }
}

/// Whether `stem` is a several-tool figure `{kind}_tool{k}` (`dwell_tool2`).
pub fn tool_figure(stem: &str, kind: &str) -> bool {
    stem.strip_prefix(kind)
        .and_then(|r| r.strip_prefix("_tool"))
        .is_some_and(|k| !k.is_empty() && k.bytes().all(|b| b.is_ascii_digit()))
}

/// The stems of every figure a solve writes ([`stage_solve_figures`]), in either format.
pub const SOLVE_FIGURES: [&str; 11] = [
    "error_before",
    "removal",
    "residual",
    "residual_model",
    "dwell",
    "feed",
    "path",
    "tif",
    "psd",
    "psd_2d",
    "psd_azimuthal",
];

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
    stage_solve_figures_with(
        setup,
        outcome,
        out_dir,
        axis,
        raster_pitch_mm,
        &FigureStyle::default(),
    )
}

/// [`stage_solve_figures`] drawn in `style`.
pub fn stage_solve_figures_with(
    setup: &Setup,
    outcome: &Outcome,
    out_dir: &Path,
    axis: LineAxis,
    raster_pitch_mm: Option<f64>,
    style: &FigureStyle,
) -> Result<(Vec<Staged>, Vec<String>)> {
    let map = &setup.map;
    let (mx, my, z) = (map.x_mm(), map.y_mm(), map.z_nm());
    // The removal and residual the headline states: the executed program's where the solve
    // executed one, the model's at the programmed feeds drawn beside it.
    let delivered = crate::residual::Delivered::of(z, outcome);
    let residual = &delivered.residual_nm;
    let (px, py) = (setup.path.x_mm(), setup.path.y_mm());
    let mut staged = stage_result_maps(
        out_dir,
        (mx, my, z),
        delivered.removal_nm,
        residual,
        delivered.executed,
        style,
    )?;
    staged.extend(stage_dwell_maps(
        out_dir,
        "",
        (px, py),
        &outcome.solution.dwell_s,
        &outcome.feeds_mm_per_min,
        style,
    )?);
    staged.push(stage_path_plot(
        &style.path(out_dir, "path"),
        "Dwell path",
        px,
        py,
    )?);
    if delivered.executed {
        staged.push(stage_map_plot_scaled(
            &style.path(out_dir, "residual_model"),
            "Model residual at the programmed feeds (piston removed)",
            "nm",
            mx,
            my,
            &outcome.residual_nm,
            style.color_limits,
            ColourScale::Diverging,
        )?);
    }
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
            &style.path(out_dir, "tif"),
            "Tool influence function",
            "nm/s",
            &tx,
            &ty,
            &tv,
        )?);
    }
    let (psd, notes) = stage_psd_figures(
        out_dir,
        mx,
        my,
        z,
        residual,
        axis,
        raster_pitch_mm,
        style.format,
    )?;
    staged.extend(psd);
    Ok((staged, notes))
}

/// Stages the maps of a result at the map points `(x, y)`: the error `z` before, the `removal`
/// and the `residual` the report states (titled as the program as executed where `executed`).
fn stage_result_maps(
    out_dir: &Path,
    (x, y, z): (&[f64], &[f64], &[f64]),
    removal_nm: &[f64],
    residual_nm: &[f64],
    executed: bool,
    style: &FigureStyle,
) -> Result<Vec<Staged>> {
    Ok(vec![
        stage_map_plot_with(
            &style.path(out_dir, "error_before"),
            "Surface error before",
            "nm",
            x,
            y,
            z,
            style.color_limits,
        )?,
        stage_map_plot(
            &style.path(out_dir, "removal"),
            if executed {
                "Predicted removal, program as executed"
            } else {
                "Predicted removal"
            },
            "nm",
            x,
            y,
            removal_nm,
        )?,
        stage_map_plot_scaled(
            &style.path(out_dir, "residual"),
            if executed {
                "Residual, program as executed (piston removed)"
            } else {
                "Residual (piston removed)"
            },
            "nm",
            x,
            y,
            residual_nm,
            style.color_limits,
            ColourScale::Diverging,
        )?,
    ])
}

/// Stages the dwell and feed maps of one tool's dwell points `(x, y)`: `dwell{suffix}` and
/// `feed{suffix}` (`suffix` empty for a single tool, `_tool2` for the second of several).
fn stage_dwell_maps(
    out_dir: &Path,
    suffix: &str,
    (x, y): (&[f64], &[f64]),
    dwell_s: &[f64],
    feeds_mm_per_min: &[f64],
    style: &FigureStyle,
) -> Result<Vec<Staged>> {
    let tool = suffix.strip_prefix("_tool").map(|k| format!(", tool {k}"));
    let tool = tool.as_deref().unwrap_or("");
    Ok(vec![
        stage_map_plot(
            &style.path(out_dir, &format!("dwell{suffix}")),
            &format!("Dwell time{tool}"),
            "s",
            x,
            y,
            dwell_s,
        )?,
        stage_map_plot(
            &style.path(out_dir, &format!("feed{suffix}")),
            &format!("Feed{tool}"),
            "mm/min",
            x,
            y,
            feeds_mm_per_min,
        )?,
    ])
}

/// One tool of a several-tool solve, for its figures: its dwell points, dwell and feeds.
#[derive(Debug, Clone, Copy)]
pub struct ToolFigureData<'a> {
    /// Dwell point x, mm.
    pub x_mm: &'a [f64],
    /// Dwell point y, mm.
    pub y_mm: &'a [f64],
    /// Dwell per point, s.
    pub dwell_s: &'a [f64],
    /// Feed per point, mm/min.
    pub feeds_mm_per_min: &'a [f64],
}

/// Stages the figures of a several-tool solve: the error before, the removal and residual of
/// all tools together, each tool's dwell and feed (`dwell_tool1`, `feed_tool1`, ...) and the
/// PSDs of error and residual along `axis`. Returns the staged files and notes on figures left
/// out.
pub fn stage_tool_figures(
    out_dir: &Path,
    map: (&[f64], &[f64], &[f64]),
    removal_nm: &[f64],
    residual_nm: &[f64],
    tools: &[ToolFigureData<'_>],
    axis: LineAxis,
    style: &FigureStyle,
) -> Result<(Vec<Staged>, Vec<String>)> {
    let mut staged = stage_result_maps(out_dir, map, removal_nm, residual_nm, false, style)?;
    for (k, t) in tools.iter().enumerate() {
        staged.extend(stage_dwell_maps(
            out_dir,
            &format!("_tool{}", k + 1),
            (t.x_mm, t.y_mm),
            t.dwell_s,
            t.feeds_mm_per_min,
            style,
        )?);
    }
    let (x, y, z) = map;
    let (psd, notes) = stage_psd_figures(out_dir, x, y, z, residual_nm, axis, None, style.format)?;
    staged.extend(psd);
    Ok((staged, notes))
}

/// Stages the PSD figures and tables of a map `z` and its residual at `(x, y)`: the 1-D PSD along
/// `axis` (`raster_pitch_mm` marked), the 2-D PSD and its azimuthal average. Returns the staged
/// files and notes on those left out (a PSD needs the map on a lattice). The figures are drawn
/// in `format`.
#[allow(clippy::too_many_arguments)]
pub fn stage_psd_figures(
    out_dir: &Path,
    x: &[f64],
    y: &[f64],
    z: &[f64],
    residual: &[f64],
    axis: LineAxis,
    raster_pitch_mm: Option<f64>,
    format: PlotFormat,
) -> Result<(Vec<Staged>, Vec<String>)> {
    let style = FigureStyle {
        format,
        ..FigureStyle::default()
    };
    let mut staged = Vec::new();
    let mut notes = Vec::new();
    match (line_psd(x, y, z, axis), line_psd(x, y, residual, axis)) {
        (Ok(before), Ok(after)) => {
            staged.push(stage_psd_csv(&out_dir.join("psd.csv"), &before, &after)?);
            let marker = raster_pitch_mm
                .filter(|p| *p > 0.0)
                .map(|p| (1.0 / p, "raster pitch"));
            staged.push(stage_psd_plot(
                &style.path(out_dir, "psd"),
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
    match (area_psd(x, y, z), area_psd(x, y, residual)) {
        (Ok(before), Ok(after)) => {
            staged.push(stage_area_psd_csv(
                &out_dir.join("psd_2d.csv"),
                &before,
                &after,
            )?);
            staged.push(stage_grid_plot(
                &style.path(out_dir, "psd_2d"),
                "2-D PSD of the residual (log10 of nm^2 mm^2)",
                "log10 PSD",
                &after.fx_per_mm,
                &after.fy_per_mm,
                &log_area_psd(&after),
                ("fx (1/mm)", "fy (1/mm)"),
            )?);
            let (ab, aa) = (before.azimuthal(), after.azimuthal());
            staged.push(stage(&out_dir.join("psd_azimuthal.csv"), |w| {
                writeln!(w, "{PSD_AZIMUTHAL_HEADER}")?;
                for k in 0..ab.frequency_per_mm.len() {
                    writeln!(
                        w,
                        "{},{},{},{}",
                        ab.frequency_per_mm[k], ab.psd_nm2_mm2[k], aa.psd_nm2_mm2[k], ab.cells[k]
                    )?;
                }
                Ok(())
            })?);
            let marker = raster_pitch_mm
                .filter(|p| *p > 0.0)
                .map(|p| (1.0 / p, "raster pitch"));
            staged.push(stage_spectrum_plot(
                &style.path(out_dir, "psd_azimuthal"),
                "Azimuthally averaged 2-D PSD",
                "PSD (nm^2 mm^2)",
                &ab.frequency_per_mm,
                &[
                    ("error before", &ab.psd_nm2_mm2),
                    ("residual", &aa.psd_nm2_mm2),
                ],
                marker,
            )?);
        }
        // The reason is the 1-D PSD's when both are left out: one note.
        (Err(e), _) | (_, Err(e)) if notes.is_empty() => notes.push(format!("no 2-D PSD: {e}")),
        _ => {
            if let Some(n) = notes.first_mut() {
                *n = n.replacen(
                    "no psd.png / psd.csv",
                    "no psd.png / psd.csv (nor the 2-D PSDs)",
                    1,
                );
            }
        }
    }
    Ok((staged, notes))
}

/// `log10` of the 2-D PSD (values at or below `1e-12` of the peak floored there), the zero
/// frequency (the removed mean) left blank.
fn log_area_psd(p: &AreaPsd) -> Vec<f64> {
    let peak = p.psd_nm2_mm2.iter().copied().fold(0.0, f64::max);
    let floor = (peak * 1e-12).max(f64::MIN_POSITIVE);
    let nx = p.fx_per_mm.len();
    let mut v = Vec::with_capacity(p.psd_nm2_mm2.len());
    for (l, y) in p.fy_per_mm.iter().enumerate() {
        for (k, x) in p.fx_per_mm.iter().enumerate() {
            v.push(if *x == 0.0 && *y == 0.0 {
                f64::NAN
            } else {
                p.psd_nm2_mm2[l * nx + k].max(floor).log10()
            });
        }
    }
    v
}

/// Stages `psd_2d.csv`: every lattice frequency (1/mm) with the 2-D PSD (nm^2 mm^2) of the error
/// and the residual.
fn stage_area_psd_csv(path: &Path, before: &AreaPsd, after: &AreaPsd) -> Result<Staged> {
    let nx = before.fx_per_mm.len();
    stage(path, |w: &mut dyn Write| {
        writeln!(w, "{PSD_2D_HEADER}")?;
        for (l, fy) in before.fy_per_mm.iter().enumerate() {
            for (k, fx) in before.fx_per_mm.iter().enumerate() {
                writeln!(
                    w,
                    "{fx},{fy},{},{}",
                    before.psd_nm2_mm2[l * nx + k],
                    after.psd_nm2_mm2[l * nx + k]
                )?;
            }
        }
        Ok(())
    })
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
