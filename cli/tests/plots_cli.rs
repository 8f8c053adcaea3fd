//! `preston solve --plots`: the figure set, committed with the other outputs.

mod common;

use common::{data, preston_cmd};

/// Relative tolerance on the residual map's data-area aspect against the mirror's 118 x 8 mm.
const ASPECT_REL_TOL: f64 = 0.05;

#[test]
fn solve_plots_write_every_figure_and_the_psd() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job.toml"))
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
    assert!((aspect / (118.0 / 8.0) - 1.0).abs() < ASPECT_REL_TOL);
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
