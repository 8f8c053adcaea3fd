//! PNG plots (plotters): maps of scattered values with a colour bar in their unit, tool paths,
//! TIFs and convergence curves. Every plot is drawn into a temporary `.png` next to its
//! destination and renamed into place together with the command's other outputs.
//!
//! Text uses the DejaVu Sans font shipped in `io/assets` (Bitstream Vera licence, see
//! `io/assets/DejaVuSans-LICENSE.txt`), so plots look the same on every machine.

use crate::atomic::{commit_all, Staged};
use crate::error::{Error, Result};
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use std::path::Path;
use std::sync::Once;

/// Plot width and height, pixels.
pub const PLOT_SIZE_PX: (u32, u32) = (900, 700);
/// Width of the colour-bar strip, pixels.
const COLOUR_BAR_PX: u32 = 130;

static FONT: Once = Once::new();

fn register_font() {
    FONT.call_once(|| {
        // The bytes are a valid TrueType font; if registration failed anyway, text would be
        // missing from the plots but nothing else would change.
        let _ = plotters::style::register_font(
            "sans-serif",
            FontStyle::Normal,
            include_bytes!("../assets/DejaVuSans.ttf"),
        );
    });
}

fn plot_error<E: std::fmt::Display>(path: &Path, e: E) -> Error {
    Error::io(path, std::io::Error::other(format!("plotting failed: {e}")))
}

/// Draws into a temporary PNG in `path`'s directory with `draw`, then renames it to `path`.
fn write_png<F>(path: &Path, draw: F) -> Result<Staged>
where
    F: FnOnce(&DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>) -> Result<()>,
{
    register_font();
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "plot".into());
    let temp = tempfile::Builder::new()
        .prefix(&crate::atomic::temp_prefix(&name))
        .suffix(".png")
        .tempfile_in(&dir)
        .map_err(|e| Error::io(path, e))?;
    {
        let root = BitMapBackend::new(temp.path(), PLOT_SIZE_PX).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_error(path, e))?;
        draw(&root)?;
        root.present().map_err(|e| plot_error(path, e))?;
    }
    Ok(crate::atomic::staged_file(temp, path))
}

/// Finite range of `v`, widened when all values are equal; `None` when none is finite.
fn value_range(v: &[f64]) -> Option<(f64, f64)> {
    let (lo, hi) = v
        .iter()
        .filter(|x| x.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    if lo
        .partial_cmp(&hi)
        .is_none_or(|o| o == std::cmp::Ordering::Greater)
    {
        return None;
    }
    if hi - lo > 0.0 {
        Some((lo, hi))
    } else {
        let pad = lo.abs().max(1.0) * 1e-6;
        Some((lo - pad, hi + pad))
    }
}

/// Plots scattered values `v` at `(x, y)` (mm) as squares of the mean point spacing, coloured on
/// the viridis scale, with a colour bar labelled `unit`.
pub fn plot_map(
    path: &Path,
    title: &str,
    unit: &str,
    x: &[f64],
    y: &[f64],
    v: &[f64],
) -> Result<()> {
    commit_all(vec![stage_map_plot(path, title, unit, x, y, v)?])
}

/// [`plot_map`], staged: drawn into its temporary file, renamed by [`commit_all`] with the rest
/// of a command's outputs.
pub fn stage_map_plot(
    path: &Path,
    title: &str,
    unit: &str,
    x: &[f64],
    y: &[f64],
    v: &[f64],
) -> Result<Staged> {
    let n = x.len().min(y.len()).min(v.len());
    let (x0, x1) = value_range(&x[..n]).ok_or_else(|| Error::Empty {
        file: path.to_path_buf(),
        why: "nothing to plot".into(),
    })?;
    let (y0, y1) = value_range(&y[..n]).unwrap_or((x0, x1));
    let (lo, hi) = value_range(&v[..n]).unwrap_or((0.0, 1.0));
    // Half the mean spacing of points spread over the bounding box.
    let half = 0.5 * ((x1 - x0) * (y1 - y0) / n.max(1) as f64).sqrt().max(1e-9);
    write_png(path, |root| {
        let (main, bar) = root.split_horizontally(PLOT_SIZE_PX.0 - COLOUR_BAR_PX);
        let mut chart = ChartBuilder::on(&main)
            .caption(title, ("sans-serif", 24))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0 - half..x1 + half, y0 - half..y1 + half)
            .map_err(|e| plot_error(path, e))?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("x (mm)")
            .y_desc("y (mm)")
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        chart
            .draw_series((0..n).filter(|&i| v[i].is_finite()).map(|i| {
                let c = ViridisRGB::get_color_normalized(v[i], lo, hi);
                Rectangle::new(
                    [(x[i] - half, y[i] - half), (x[i] + half, y[i] + half)],
                    c.filled(),
                )
            }))
            .map_err(|e| plot_error(path, e))?;
        colour_bar(path, &bar, unit, lo, hi)
    })
}

fn colour_bar(
    path: &Path,
    area: &DrawingArea<BitMapBackend<'_>, plotters::coord::Shift>,
    unit: &str,
    lo: f64,
    hi: f64,
) -> Result<()> {
    let mut chart = ChartBuilder::on(area)
        .margin_top(50)
        .margin_bottom(52)
        .margin_right(10)
        .y_label_area_size(70)
        .caption(unit, ("sans-serif", 16))
        .build_cartesian_2d(0.0..1.0, lo..hi)
        .map_err(|e| plot_error(path, e))?;
    chart
        .configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .label_style(("sans-serif", 13))
        .draw()
        .map_err(|e| plot_error(path, e))?;
    let steps = 200;
    chart
        .draw_series((0..steps).map(|k| {
            let a = lo + (hi - lo) * k as f64 / steps as f64;
            let b = lo + (hi - lo) * (k + 1) as f64 / steps as f64;
            let c = ViridisRGB::get_color_normalized(0.5 * (a + b), lo, hi);
            Rectangle::new([(0.0, a), (1.0, b)], c.filled())
        }))
        .map_err(|e| plot_error(path, e))?;
    Ok(())
}

/// Plots a tool path (mm) as a polyline with its start marked.
pub fn plot_path(path: &Path, title: &str, x: &[f64], y: &[f64]) -> Result<()> {
    commit_all(vec![stage_path_plot(path, title, x, y)?])
}

/// [`plot_path`], staged (see [`stage_map_plot`]).
pub fn stage_path_plot(path: &Path, title: &str, x: &[f64], y: &[f64]) -> Result<Staged> {
    let n = x.len().min(y.len());
    let (x0, x1) = value_range(&x[..n]).ok_or_else(|| Error::Empty {
        file: path.to_path_buf(),
        why: "nothing to plot".into(),
    })?;
    let (y0, y1) = value_range(&y[..n]).unwrap_or((x0, x1));
    write_png(path, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 24))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(|e| plot_error(path, e))?;
        chart
            .configure_mesh()
            .x_desc("x (mm)")
            .y_desc("y (mm)")
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        chart
            .draw_series(LineSeries::new((0..n).map(|i| (x[i], y[i])), BLUE))
            .map_err(|e| plot_error(path, e))?;
        if n > 0 {
            chart
                .draw_series(std::iter::once(Circle::new((x[0], y[0]), 5, RED.filled())))
                .map_err(|e| plot_error(path, e))?;
        }
        Ok(())
    })
}

/// One curve of a convergence plot: label and `(iteration, value)` points.
pub type Curve<'a> = (&'a str, Vec<(f64, f64)>);

/// Plots curves against the iteration with a logarithmic value axis (`unit` labels it).
pub fn plot_convergence(path: &Path, title: &str, unit: &str, curves: &[Curve<'_>]) -> Result<()> {
    commit_all(vec![stage_convergence_plot(path, title, unit, curves)?])
}

/// [`plot_convergence`], staged (see [`stage_map_plot`]).
pub fn stage_convergence_plot(
    path: &Path,
    title: &str,
    unit: &str,
    curves: &[Curve<'_>],
) -> Result<Staged> {
    let all: Vec<f64> = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.1))
        .filter(|v| *v > 0.0 && v.is_finite())
        .collect();
    let (lo, hi) = value_range(&all).unwrap_or((1e-3, 1.0));
    let it_max = curves
        .iter()
        .flat_map(|(_, c)| c.iter().map(|p| p.0))
        .fold(1.0, f64::max);
    write_png(path, |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, ("sans-serif", 24))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..it_max, (lo * 0.8..hi * 1.25).log_scale())
            .map_err(|e| plot_error(path, e))?;
        chart
            .configure_mesh()
            .x_desc("iteration")
            .y_desc(unit)
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        let palette = [BLUE, RED, GREEN, MAGENTA, BLACK];
        for (k, (label, pts)) in curves.iter().enumerate() {
            let colour = palette[k % palette.len()];
            let pts: Vec<(f64, f64)> = pts.iter().copied().filter(|p| p.1 > 0.0).collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
                .map_err(|e| plot_error(path, e))?
                .label(*label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour));
            chart
                .draw_series(pts.into_iter().map(|p| Circle::new(p, 4, colour.filled())))
                .map_err(|e| plot_error(path, e))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(path, e))?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Decodes a PNG: (width, height, RGB(A) bytes, bytes per pixel).
    fn decode(path: &Path) -> (u32, u32, Vec<u8>, usize) {
        let decoder = png::Decoder::new(std::fs::File::open(path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf, info.color_type.samples())
    }

    fn grid() -> (Vec<f64>, Vec<f64>) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for j in 0..30 {
            for i in 0..30 {
                x.push(i as f64);
                y.push(j as f64);
            }
        }
        (x, y)
    }

    #[test]
    fn map_plots_are_png_of_the_size_and_follow_the_data() {
        let dir = tempfile::tempdir().unwrap();
        let (x, y) = grid();
        let v: Vec<f64> = x.iter().zip(&y).map(|(a, b)| a + b).collect();
        let a = dir.path().join("a.png");
        plot_map(&a, "error before", "nm", &x, &y, &v).unwrap();
        let (w, h, pa, bpp) = decode(&a);
        assert_eq!((w, h), PLOT_SIZE_PX);
        // Change the data in the lower-left quarter only: pixels change, and only some of them.
        let mut v2 = v.clone();
        for (k, val) in v2.iter_mut().enumerate() {
            if x[k] < 10.0 && y[k] < 10.0 {
                *val = 18.0 - *val; // mirrored within the quarter: the colour range stays
            }
        }
        let b = dir.path().join("b.png");
        plot_map(&b, "error before", "nm", &x, &y, &v2).unwrap();
        let (_, _, pb, _) = decode(&b);
        let changed = pa
            .chunks(bpp)
            .zip(pb.chunks(bpp))
            .filter(|(p, q)| p != q)
            .count();
        let total = (w * h) as usize;
        assert!(
            changed > total / 100 && changed < total / 3,
            "{changed} of {total}"
        );
        // The same data give the same pixels.
        let c = dir.path().join("c.png");
        plot_map(&c, "error before", "nm", &x, &y, &v).unwrap();
        assert_eq!(decode(&c).2, pa);
        // Several colours are used (a colour scale, not a flat fill).
        let mut colours: Vec<&[u8]> = pa.chunks(bpp).collect();
        colours.sort();
        colours.dedup();
        assert!(colours.len() > 50, "{} colours", colours.len());
    }

    #[test]
    fn path_and_convergence_plots_are_written_whole() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("path.png");
        plot_path(&p, "path", &[0.0, 1.0, 1.0, 0.0], &[0.0, 0.0, 1.0, 1.0]).unwrap();
        assert_eq!(decode(&p).0, PLOT_SIZE_PX.0);
        let c = dir.path().join("conv.png");
        plot_convergence(
            &c,
            "convergence",
            "nm",
            &[
                ("RMS", vec![(0.0, 50.0), (1.0, 2.0), (2.0, 0.5)]),
                ("PV", vec![(0.0, 300.0), (1.0, 20.0), (2.0, 4.0)]),
            ],
        )
        .unwrap();
        assert_eq!(decode(&c).1, PLOT_SIZE_PX.1);
        // Nothing but the two plots in the directory (no temporary left).
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
        // Nothing to plot is an error, and writes nothing.
        let e = dir.path().join("empty.png");
        assert!(plot_map(&e, "t", "nm", &[], &[], &[]).is_err());
        assert!(!e.exists());
    }
}
