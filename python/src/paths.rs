//! The tool paths of `preston path` that take a region and lines (raster, intersection), with
//! the CLI's options (point step, margin, arc turns, clear-aperture clipping), the chord-height
//! line on a design surface, and the projection of any path onto a surface. Each returns the
//! seven columns `preston path` writes (`x_mm, y_mm, z_mm, tx, ty, tz, ds_mm`) and the summary
//! the CLI prints, with the same keys and values.

use crate::workflow::{summary_json, surface_of};
use crate::{array, columns, engine_to_py, Array, InputError};
use numpy::PyReadonlyArray2;
use preston_solver::map::BoundingBox;
use preston_solver::path::arcs::lines_with_arcs;
use preston_solver::path::chord_height::{chord_height_line, ChordHeightSettings};
use preston_solver::path::intersection::{
    clip_to_aperture, intersection_lines, lines_to_path, raster_lines, Line,
};
use preston_solver::path::raster::RasterAxis;
use preston_solver::path::{project, DwellPath, PathSummary, ProjectedPath};
use preston_solver::surface::Surface;
use pyo3::prelude::*;
use serde_json::Value;

/// The columns of `preston path`'s CSV: `(x_mm, y_mm, z_mm, tx, ty, tz, ds_mm)`.
pub(crate) type Columns<'py> = (
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
    Array<'py>,
);

fn columns_of<'py>(py: Python<'py>, p: &ProjectedPath) -> Columns<'py> {
    (
        array(py, &p.x_mm),
        array(py, &p.y_mm),
        array(py, &p.z_mm),
        array(py, &p.tx),
        array(py, &p.ty),
        array(py, &p.tz),
        array(py, &p.ds_mm),
    )
}

/// Projects `path` onto `surface` (flat at z = 0 with `None`), as `preston path --surface` does.
fn projected(path: &DwellPath, surface: Option<&Surface>) -> PyResult<ProjectedPath> {
    project(path, surface).map_err(|e| engine_to_py("projecting the path onto the surface", e))
}

/// The box `x_range_mm` x `y_range_mm` extended by `margin_mm` on every side, with the size of
/// the path it implies checked against the memory budget before any line is generated (the
/// checks of `preston path raster|intersection`).
fn region(
    kind: &str,
    x_range_mm: (f64, f64),
    y_range_mm: (f64, f64),
    pitch_mm: f64,
    step_mm: f64,
    margin_mm: f64,
) -> PyResult<BoundingBox> {
    if !(margin_mm.is_finite() && margin_mm >= 0.0) {
        return Err(InputError::new_err(format!(
            "margin_mm must be non-negative, got {margin_mm}"
        )));
    }
    let ((a, b), (c, d)) = (x_range_mm, y_range_mm);
    let bbox = BoundingBox {
        x_min_mm: a.min(b),
        x_max_mm: a.max(b),
        y_min_mm: c.min(d),
        y_max_mm: c.max(d),
    }
    .expanded(margin_mm);
    if pitch_mm > 0.0 && step_mm > 0.0 {
        // Lines across the region times points along them (x and y of each, and the lines' own
        // end points).
        let (w, h) = (bbox.x_max_mm - bbox.x_min_mm, bbox.y_max_mm - bbox.y_min_mm);
        let along = |across: f64, length: f64| (across / pitch_mm + 1.0) * (length / step_mm + 1.0);
        let points = along(h, w).max(along(w, h));
        preston_solver::budget::check_f64s(
            "pitch_mm",
            &format!(
                "a path of pitch {pitch_mm} mm and step {step_mm} mm over the region (up to \
                 {points:.3e} points)"
            ),
            points,
            4.0,
        )
        .map_err(|e| engine_to_py(kind, e))?;
    }
    Ok(bbox)
}

/// The path through `lines`: points at most `step_mm` apart, turns joined directly or by arcs
/// of `arc_radius_mm` (chords within `arc_tolerance_um` of the arc), then clipped to the
/// aperture polygon (with `margin_mm`) when one is given.
fn through(
    lines: &[Line],
    step_mm: f64,
    arc: Option<(f64, f64)>,
    aperture: Option<(&[[f64; 2]], f64)>,
) -> preston_solver::Result<DwellPath> {
    let path = match arc {
        Some((r, tol_um)) => lines_with_arcs(lines, step_mm, r, tol_um * 1e-3)?,
        None => lines_to_path(lines, step_mm)?,
    };
    match aperture {
        Some((poly, margin)) => clip_to_aperture(&path, poly, margin),
        None => Ok(path),
    }
}

/// A serpentine raster (`iteration` None; lines along `along`, `"x"` or `"y"`) or the
/// intersection raster of iteration `iteration` (x, y, x + P/2, y + P/2, repeating) over a box
/// (mm) extended by `margin_mm`, lines `pitch_mm` apart, points at most `step_mm` (default: the
/// pitch) apart, turns by arcs of `arc_radius_mm` (at most P/2) whose chords stay within
/// `arc_tolerance_um` of the arc, clipped to the clear-aperture polygon `aperture_xy` (`(N, 2)`,
/// mm) plus the margin, and projected onto the design surface (JSON): `preston path raster` /
/// `preston path intersection`. Returns the seven columns and the CLI's summary (JSON).
#[pyfunction]
#[pyo3(signature = (x_range_mm, y_range_mm, pitch_mm, along="x", iteration=None, step_mm=None, margin_mm=0.0, arc_radius_mm=None, arc_tolerance_um=1.0, aperture_xy=None, surface_json=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn path_lines<'py>(
    py: Python<'py>,
    x_range_mm: (f64, f64),
    y_range_mm: (f64, f64),
    pitch_mm: f64,
    along: &str,
    iteration: Option<usize>,
    step_mm: Option<f64>,
    margin_mm: f64,
    arc_radius_mm: Option<f64>,
    arc_tolerance_um: f64,
    aperture_xy: Option<PyReadonlyArray2<'py, f64>>,
    surface_json: Option<&str>,
) -> PyResult<(Columns<'py>, String)> {
    let axis: RasterAxis = serde_json::from_value(Value::String(along.to_string()))
        .map_err(|e| InputError::new_err(format!("along: {e}")))?;
    let surface = surface_json.map(surface_of).transpose()?;
    let aperture: Option<Vec<[f64; 2]>> = aperture_xy
        .map(|a| {
            columns(&a, "aperture_xy", 2)
                .map(|c| c[0].iter().zip(&c[1]).map(|(x, y)| [*x, *y]).collect())
        })
        .transpose()?;
    let step = step_mm.unwrap_or(pitch_mm);
    let kind = if iteration.is_some() {
        "intersection"
    } else {
        "raster"
    };
    let bbox = region(kind, x_range_mm, y_range_mm, pitch_mm, step, margin_mm)?;
    let (lines, p) = py
        .detach(|| {
            let lines = match iteration {
                Some(k) => intersection_lines(&bbox, pitch_mm, k)?,
                None => raster_lines(&bbox, pitch_mm, axis, 0.0)?,
            };
            let path = through(
                &lines,
                step,
                arc_radius_mm.map(|r| (r, arc_tolerance_um)),
                aperture.as_deref().map(|a| (a, margin_mm)),
            )?;
            Ok((lines, path))
        })
        .map_err(|e| engine_to_py(kind, e))?;
    let p = py.detach(|| projected(&p, surface.as_ref()))?;
    let summary = match iteration {
        Some(k) => PathSummary::intersection(&p, k, pitch_mm, lines.len()),
        None => PathSummary::raster(&p, lines.len()),
    };
    Ok((columns_of(py, &p), summary_json(&summary)?))
}

/// Equal chord-height points along the line `x = line_x_mm` from `y_range_mm.0` to
/// `y_range_mm.1` (mm) on the design surface (JSON), for a tool of `tool_radius_mm`: each step
/// keeps the chord's height above the surface in the window `eps_um` (um), growing by
/// `grow_mm` and shrinking by `shrink_mm` while searching (`preston path chord-height`). Returns
/// the seven columns (projected onto the surface), the CLI's summary (JSON), and each step's
/// 3-D chord length (mm) and chord height (mm).
#[pyfunction]
#[pyo3(signature = (surface_json, line_x_mm, y_range_mm, tool_radius_mm, eps_um, grow_mm=0.10, shrink_mm=0.02))]
#[allow(clippy::type_complexity, clippy::too_many_arguments)]
pub(crate) fn path_chord_height<'py>(
    py: Python<'py>,
    surface_json: &str,
    line_x_mm: f64,
    y_range_mm: (f64, f64),
    tool_radius_mm: f64,
    eps_um: (f64, f64),
    grow_mm: f64,
    shrink_mm: f64,
) -> PyResult<(Columns<'py>, String, Array<'py>, Array<'py>)> {
    let surface = surface_of(surface_json)?;
    let set = ChordHeightSettings {
        tool_radius_mm,
        eps_min_mm: eps_um.0 * 1e-3,
        eps_max_mm: eps_um.1 * 1e-3,
        grow_mm,
        shrink_mm,
        ..ChordHeightSettings::default()
    };
    let c = py
        .detach(|| chord_height_line(&surface, line_x_mm, y_range_mm.0, y_range_mm.1, &set))
        .map_err(|e| engine_to_py("chord-height line", e))?;
    let p = py.detach(|| projected(&c.path, Some(&surface)))?;
    let summary = summary_json(&PathSummary::chord_height(&p, &c))?;
    Ok((
        columns_of(py, &p),
        summary,
        array(py, &c.steps_mm),
        array(py, &c.chord_heights_mm),
    ))
}

/// Any path's points `(N, 2)` (mm, in path order) projected onto the design surface (JSON; flat
/// at z = 0 without one): the seven columns of `preston path --surface`, the unit tangents and
/// `ds_mm` (the path length each point stands for) measured along the surface.
#[pyfunction]
#[pyo3(signature = (points_xy, surface_json=None))]
pub(crate) fn path_project<'py>(
    py: Python<'py>,
    points_xy: PyReadonlyArray2<'py, f64>,
    surface_json: Option<&str>,
) -> PyResult<Columns<'py>> {
    let surface = surface_json.map(surface_of).transpose()?;
    let mut c = columns(&points_xy, "points_xy", 2)?;
    let (y, x) = (c.pop().unwrap_or_default(), c.pop().unwrap_or_default());
    let path = DwellPath::new(x, y).map_err(|e| engine_to_py("points_xy", e))?;
    let p = py.detach(|| projected(&path, surface.as_ref()))?;
    Ok(columns_of(py, &p))
}
