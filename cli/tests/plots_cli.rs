//! `preston solve --plots`: the figure set, committed with the other outputs.

mod common;

use common::{data, preston_cmd};

/// Relative tolerance on the residual map's data-area aspect against the drawn aspect.
const ASPECT_REL_TOL: f64 = 0.05;

#[test]
fn solve_plots_write_every_figure_and_the_psd() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .arg("--plots")
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "error_before.png",
        "removal.png",
        "residual.png",
        "dwell.png",
        "feed.png",
        "tif.png",
        "path.png",
        "psd.png",
        "psd.csv",
        "psd_2d.png",
        "psd_2d.csv",
        "psd_azimuthal.png",
        "psd_azimuthal.csv",
        "dwell.csv",
        "residual.csv",
        "report.json",
    ] {
        assert!(out.path().join(f).is_file(), "{f} missing");
    }
    // No temporary left behind.
    let names: Vec<String> = std::fs::read_dir(out.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert!(names.iter().all(|n| !n.starts_with('.')), "{names:?}");
    // The residual image is as wide as the canvas allows and as tall as the aspect says.
    let decoder = png::Decoder::new(std::fs::File::open(out.path().join("residual.png")).unwrap());
    let reader = decoder.read_info().unwrap();
    let (w, h) = (reader.info().width, reader.info().height);
    let layout = preston_io::plots::MapLayout::for_extent(118.72 + 0.32, 8.0 + 0.32);
    assert_eq!((w, h), layout.canvas_px);
    let (dw, dh) = layout.data_size_px;
    let aspect = dw as f64 / dh as f64;
    // The 118 x 8 mm strip is drawn strip-shaped at the largest drawn aspect, y stretched.
    assert!((aspect / preston_io::plots::MAX_DRAWN_ASPECT - 1.0).abs() < ASPECT_REL_TOL);
    assert!(dh >= 140, "{dh} px tall");
    // psd.csv: the header, frequencies from zero in equal steps, finite non-negative PSDs.
    let psd = std::fs::read_to_string(out.path().join("psd.csv")).unwrap();
    let mut lines = psd.lines();
    assert_eq!(lines.next(), Some(preston_io::figures::PSD_HEADER));
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|c| c.parse().unwrap()).collect())
        .collect();
    assert!(rows.len() > 10);
    assert_eq!(rows[0][0], 0.0);
    let df = rows[1][0];
    for (k, r) in rows.iter().enumerate() {
        assert!((r[0] - k as f64 * df).abs() < 1e-9 * (1.0 + r[0]));
        assert!(r[1] >= 0.0 && r[2] >= 0.0 && r[1].is_finite() && r[2].is_finite());
    }
}

/// The sample's 2-D PSD table: the lattice's frequencies, and the error's PSD equals an
/// independent estimate from `residual.csv` (the periodogram of the windowed heights summed as a
/// DFT at a few frequencies, no FFT) within 5%; its integral is the map's windowed variance.
#[test]
fn psd_2d_of_the_sample_agrees_with_an_independent_estimate() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .arg("--plots")
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (header, rows) = common::csv_rows(&out.path().join("psd_2d.csv"));
    assert_eq!(header, preston_io::figures::PSD_2D_HEADER);
    let cols = common::csv_columns(&out.path().join("residual.csv"), &["x_mm", "y_mm", "z_nm"]);
    let (x, y, z) = (&cols[0], &cols[1], &cols[2]);
    let pitch = 0.32;
    let min = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    let (x0, y0) = (min(x), min(y));
    let ix: Vec<usize> = x
        .iter()
        .map(|a| ((a - x0) / pitch).round() as usize)
        .collect();
    let iy: Vec<usize> = y
        .iter()
        .map(|b| ((b - y0) / pitch).round() as usize)
        .collect();
    let nx = ix.iter().max().unwrap() + 1;
    let ny = iy.iter().max().unwrap() + 1;
    assert_eq!(rows.len(), nx * ny);
    let hann = |k: usize, n: usize| {
        (std::f64::consts::PI * (k as f64 + 0.5) / n as f64)
            .sin()
            .powi(2)
    };
    let mean = z.iter().sum::<f64>() / z.len() as f64;
    let w: Vec<f64> = (0..z.len())
        .map(|q| hann(ix[q], nx) * hann(iy[q], ny))
        .collect();
    let u = w.iter().map(|a| a * a).sum::<f64>() / (nx * ny) as f64;
    let peak = rows.iter().map(|r| r[2]).fold(0.0, f64::max);
    let tau = 2.0 * std::f64::consts::PI;
    let mut checked = 0;
    for r in rows
        .iter()
        .filter(|r| r[2] > 1e-9 * peak)
        .step_by(7)
        .take(25)
    {
        let (fx, fy) = (r[0], r[1]);
        let (mut re, mut im) = (0.0, 0.0);
        for q in 0..z.len() {
            let v = (z[q] - mean) * w[q];
            let phase = -tau * (fx * ix[q] as f64 * pitch + fy * iy[q] as f64 * pitch);
            re += v * phase.cos();
            im += v * phase.sin();
        }
        let direct = pitch * pitch * (re * re + im * im) / ((nx * ny) as f64 * u);
        assert!(
            (direct / r[2] - 1.0).abs() < 0.05,
            "({fx}, {fy}): {direct} vs {}",
            r[2]
        );
        checked += 1;
    }
    assert!(checked >= 10, "{checked}");
    // Parseval: the integral is the windowed variance of the error.
    let (dfx, dfy) = (1.0 / (nx as f64 * pitch), 1.0 / (ny as f64 * pitch));
    let integral: f64 = rows.iter().map(|r| r[2]).sum::<f64>() * dfx * dfy;
    let variance: f64 = z
        .iter()
        .zip(&w)
        .map(|(a, b)| ((a - mean) * b).powi(2))
        .sum::<f64>()
        / ((nx * ny) as f64 * u);
    assert!(
        (integral / variance - 1.0).abs() < 1e-9,
        "{integral} vs {variance}"
    );
    let (aheader, arows) = common::csv_rows(&out.path().join("psd_azimuthal.csv"));
    assert_eq!(aheader, preston_io::figures::PSD_AZIMUTHAL_HEADER);
    assert!(arows.len() > 5 && arows.iter().all(|r| r[1] >= 0.0 && r[3] >= 1.0));
}

/// `simulate --program --plots` of the sample's program: the maps, the PSDs and the planned
/// against the executed dwell per point.
#[test]
fn simulate_program_plots_show_the_psd_and_the_dwell_as_executed() {
    let out = tempfile::tempdir().unwrap();
    let solved = out.path().join("solve");
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .arg("--out")
        .arg(&solved)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let prog = out.path().join("p.nc");
    let o = preston_cmd()
        .arg("nc")
        .arg("--dwell")
        .arg(solved.join("dwell.csv"))
        .arg("--out")
        .arg(&prog)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let sim = out.path().join("sim");
    let o = preston_cmd()
        .arg("simulate")
        .arg("--map")
        .arg(data("mirror_error_118x8mm.csv"))
        .arg("--tif")
        .arg(data("tif_fluid_jet_10mm.csv"))
        .arg("--program")
        .arg(&prog)
        .arg("--plots")
        .arg("--out")
        .arg(&sim)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "residual.png",
        "psd.png",
        "psd.csv",
        "psd_2d.csv",
        "psd_azimuthal.csv",
        "dwell_planned_vs_executed.png",
        "executed_dwell.csv",
    ] {
        assert!(sim.join(f).is_file(), "{f} missing");
    }
    assert_eq!(
        common::png_size(&sim.join("dwell_planned_vs_executed.png")),
        (1200, 600)
    );
    // The same figures as SVG: each one an SVG document of the PNG's size, no PNG written, the
    // CSVs the same bytes.
    let svg_dir = out.path().join("sim_svg");
    let o = preston_cmd()
        .arg("simulate")
        .arg("--map")
        .arg(data("mirror_error_118x8mm.csv"))
        .arg("--tif")
        .arg(data("tif_fluid_jet_10mm.csv"))
        .arg("--program")
        .arg(&prog)
        .args(["--plots", "--plot-format", "svg", "--out"])
        .arg(&svg_dir)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for entry in std::fs::read_dir(&sim).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if let Some(stem) = name.strip_suffix(".png") {
            let svg = std::fs::read_to_string(svg_dir.join(format!("{stem}.svg")))
                .unwrap_or_else(|e| panic!("{stem}.svg: {e}"));
            let (w, h) = common::png_size(&sim.join(&name));
            assert!(
                svg.starts_with(&format!("<svg width=\"{w}\" height=\"{h}\"")),
                "{stem}.svg: {}",
                &svg[..svg.len().min(80)]
            );
            assert!(svg.trim_end().ends_with("</svg>"), "{stem}.svg");
            assert!(
                !svg_dir.join(&name).exists(),
                "{name} written with --plot-format svg"
            );
        } else if name.ends_with(".csv") {
            assert_eq!(
                std::fs::read(sim.join(&name)).unwrap(),
                std::fs::read(svg_dir.join(&name)).unwrap(),
                "{name}"
            );
        }
    }
}
