//! What a run writes agrees with what it states: the residual in every file is the one the
//! headline gives, a directory holds one run's outputs, a plan simulated as given reproduces the
//! plan's own prediction, and a message names the file, key or flag at fault.

mod common;

use common::*;
use std::path::Path;

/// Relative agreement of an RMS or PV recomputed here from a written CSV (every value in its
/// shortest round-trip form) with the one `report.json` gives: the same numbers, summed in
/// another order.
const RECOMPUTED_REL: f64 = 1e-9;
/// Absolute floor of that agreement, nm.
const RECOMPUTED_ABS_NM: f64 = 1e-9;

/// RMS about the mean, nm.
fn rms_about_mean(v: &[f64]) -> f64 {
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / v.len() as f64).sqrt()
}

/// Peak to valley, nm.
fn pv(v: &[f64]) -> f64 {
    let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
    hi - lo
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= RECOMPUTED_REL * a.abs().max(b.abs()) + RECOMPUTED_ABS_NM
}

/// The residual of a `residual.csv`-format file, checked to be `z - removal` about its mean.
fn residual_of(path: &Path) -> Vec<f64> {
    let [z, h, r]: [Vec<f64>; 3] = csv_columns(path, &["z_nm", "removal_nm", "residual_nm"])
        .try_into()
        .unwrap();
    let e: Vec<f64> = z.iter().zip(&h).map(|(z, h)| z - h).collect();
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    for (i, (e, r)) in e.iter().zip(&r).enumerate() {
        assert!(
            close(e - mean, *r),
            "{}: row {i}: residual_nm {r} is not z - removal about its mean ({})",
            path.display(),
            e - mean
        );
    }
    r
}

/// The sample job executes its program at the acceleration limit, so its headline residual is
/// the executed one: `residual.csv` (and the figure and page drawn from it) must be that one,
/// and the model's residual at the programmed feeds comes under its own name.
#[test]
fn the_residual_files_hold_the_residual_the_report_states() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("sample");
    let job = data_arg("job.toml");
    ok(&preston(&[
        "solve",
        "--job",
        &job,
        "--plots",
        "--report",
        "--out",
        s(&out),
    ]));
    let r = report(&out);
    assert!(
        r["executed"].is_object(),
        "the sample job executes its program"
    );
    let headline_rms = r["rms_after_nm"].as_f64().unwrap();
    let headline_pv = r["pv_after_nm"].as_f64().unwrap();
    let residual = residual_of(&out.join("residual.csv"));
    let (rms, spread) = (rms_about_mean(&residual), pv(&residual));
    assert!(
        close(rms, headline_rms),
        "residual.csv RMS {rms} nm, report.json rms_after_nm {headline_rms} nm"
    );
    assert!(
        close(spread, headline_pv),
        "residual.csv PV {spread} nm, report.json pv_after_nm {headline_pv} nm"
    );
    // The model's residual at the programmed feeds, labelled as such, is the report's `model`.
    let model = residual_of(&out.join("residual_model.csv"));
    let model_rms = r["model"]["rms_nm"].as_f64().unwrap();
    assert!(
        close(rms_about_mean(&model), model_rms),
        "residual_model.csv RMS {} nm, report.json model.rms_nm {model_rms} nm",
        rms_about_mean(&model)
    );
    assert!(
        !close(model_rms, headline_rms),
        "the sample's model and executed residuals differ"
    );
    // Both figures are drawn and the page says which is which.
    for name in ["residual.png", "residual_model.png"] {
        assert!(out.join(name).is_file(), "{name} not written");
    }
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(
        html.contains("Model residual at the programmed feeds"),
        "report.html does not label the model's residual"
    );
    assert!(
        html.contains("the program as executed"),
        "report.html does not say which residual residual.png is"
    );
}

