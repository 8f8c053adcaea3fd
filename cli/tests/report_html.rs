//! `preston solve --report`: `report.html`, one self-contained page whose numbers are those of
//! `report.json`, opening with a summary in words, with every figure embedded and the inputs'
//! hashes; the sample's residual plot keeps almost all points inside its colour range.

mod common;

use common::{data, preston_cmd};
use std::collections::BTreeMap;
use std::path::Path;

/// Relative tolerance of a number as displayed (five significant digits) against its exact value.
const DISPLAY_REL_TOL: f64 = 1e-4;

/// Every `data-key="K" data-value="V">SHOWN<` of the page, in order.
fn numbers(html: &str) -> Vec<(String, String, String)> {
    let mut out = Vec::new();
    let mut rest = html;
    while let Some(k) = rest.find("data-key=\"") {
        rest = &rest[k + 10..];
        let key_end = rest.find('"').unwrap();
        let key = rest[..key_end].to_string();
        let after = &rest[key_end + 1..];
        if let Some(v) = after.strip_prefix(" data-value=\"") {
            let value_end = v.find('"').unwrap();
            let value = v[..value_end].to_string();
            let shown_start = v.find('>').unwrap() + 1;
            let shown_end = v[shown_start..].find('<').unwrap() + shown_start;
            out.push((key, value, v[shown_start..shown_end].to_string()));
        }
    }
    out
}

/// `report.json`'s value at a dotted key.
fn at<'a>(json: &'a serde_json::Value, key: &str) -> Option<&'a serde_json::Value> {
    json.pointer(&format!("/{}", key.replace('.', "/")))
}

#[test]
fn report_html_holds_the_numbers_of_report_json_and_every_figure() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(["--plots", "--report", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(out.path().join("report.html")).unwrap();
    let json = common::report(out.path());
    let found = numbers(&html);
    assert!(found.len() > 40, "{} numbers", found.len());
    let mut seen = BTreeMap::new();
    for (key, value, shown) in &found {
        let expected = at(&json, key).unwrap_or_else(|| panic!("{key} not in report.json"));
        let exact: f64 = value.parse().unwrap();
        assert_eq!(Some(exact), expected.as_f64(), "{key}");
        let displayed: f64 = shown.parse().unwrap();
        assert!(
            (displayed - exact).abs() <= DISPLAY_REL_TOL * exact.abs(),
            "{key}: shown {shown}, exact {exact}"
        );
        seen.insert(key.clone(), exact);
    }
    // The figures a metrologist looks for first, and every number of report.json.
    for key in [
        "pv_before_nm",
        "rms_before_nm",
        "pv_after_nm",
        "rms_after_nm",
        "total_dwell_s",
        "machining_time_s",
        "executed.rms_after_nm",
        "executed.pv_after_nm",
        "executed.stretch_time_s",
    ] {
        assert!(seen.contains_key(key), "{key} missing from the page");
    }
    fn leaves(prefix: String, v: &serde_json::Value, out: &mut Vec<String>) {
        match v {
            serde_json::Value::Object(m) => {
                for (k, x) in m {
                    let p = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    leaves(p, x, out);
                }
            }
            serde_json::Value::Number(_) => out.push(prefix),
            _ => {}
        }
    }
    let mut all = Vec::new();
    leaves(String::new(), &json, &mut all);
    for key in all {
        assert!(
            seen.contains_key(&key),
            "{key} of report.json not on the page"
        );
    }
    // Self-contained: every figure written is embedded byte for byte, nothing is linked.
    for name in [
        "error_before.png",
        "removal.png",
        "residual.png",
        "dwell.png",
        "feed.png",
        "tif.png",
        "path.png",
        "psd.png",
        "psd_2d.png",
        "psd_azimuthal.png",
    ] {
        let bytes = std::fs::read(out.path().join(name)).unwrap();
        let embedded = format!(
            "src=\"data:image/png;base64,{}\"",
            preston_io::digest::base64(&bytes)
        );
        assert!(html.contains(&embedded), "{name} not embedded");
    }
    assert!(!html.contains("src=\"http") && !html.contains("href=\"http"));
    // Provenance: the inputs with their SHA-256, the aperture and the removed terms.
    for input in [
        "mirror_error_118x8mm.csv",
        "tif_fluid_jet_10mm.csv",
        "job_point_1mm.toml",
    ] {
        let (hash, _) = preston_io::digest::sha256_file(&data(input)).unwrap();
        assert!(html.contains(&hash), "{input}'s hash missing");
    }
    for label in [
        "clear aperture",
        "form terms removed",
        "map units",
        "Warnings",
    ] {
        assert!(html.contains(label), "{label} missing");
    }
    // Written atomically with the rest: no temporary left, and without --report no page.
    let names: Vec<String> = std::fs::read_dir(out.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert!(names.iter().all(|n| !n.starts_with('.')), "{names:?}");
}

/// The report page without --plots still embeds the figures, and writes no figure file.
#[test]
fn report_without_plots_embeds_figures_but_writes_none() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(["--report", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(out.path().join("report.html")).unwrap();
    assert!(html.matches("data:image/png;base64,").count() >= 8);
    let mut names: Vec<String> = std::fs::read_dir(out.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    names.sort();
    // The job executes its program at an acceleration limit: residual.csv is that run's
    // residual, residual_model.csv the model's at the programmed feeds.
    assert_eq!(
        names,
        [
            "dwell.csv",
            "report.html",
            "report.json",
            "residual.csv",
            "residual_model.csv"
        ]
    );
}

/// Pixels of the residual map's data area, and of those the ones in the out-of-range colours.
fn out_of_range_share(png_path: &Path) -> f64 {
    let decoder = png::Decoder::new(std::fs::File::open(png_path).unwrap());
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    let bpp = info.color_type.samples();
    let layout = preston_io::plots::MapLayout::for_extent(118.72 + 0.32, 8.0 + 0.32);
    let (ox, oy) = layout.data_origin_px;
    let (dw, dh) = layout.data_size_px;
    let (mut outside, mut total) = (0usize, 0usize);
    let (u, o) = (
        preston_io::plots::UNDER_RANGE,
        preston_io::plots::OVER_RANGE,
    );
    for r in oy + 1..oy + dh - 1 {
        for c in ox + 1..ox + dw - 1 {
            let k = (r * info.width + c) as usize * bpp;
            let p = (buf[k], buf[k + 1], buf[k + 2]);
            total += 1;
            if p == (u.0, u.1, u.2) || p == (o.0, o.1, o.2) {
                outside += 1;
            }
        }
    }
    outside as f64 / total as f64
}

/// The sample's residual: at least 95% of the map inside the colour range (the edge spikes
/// marked, not setting the scale), the range written under the colour bar's unit; given limits
/// are taken as given.
#[test]
fn residual_colours_span_the_bulk_of_the_sample() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(["--plots", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let share = out_of_range_share(&out.path().join("residual.png"));
    assert!(
        share > 0.0 && share < 0.05,
        "{share} of the pixels out of range"
    );
    // Given limits far inside the data: most of the map is out of range.
    let tight = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(["--plots", "--color-limits", "-1,1", "--out"])
        .arg(tight.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let share = out_of_range_share(&tight.path().join("residual.png"));
    assert!(share > 0.5, "{share}");
    // Bad limits are refused before anything runs.
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(["--color-limits", "5,1", "--out"])
        .arg(tight.path().join("never"))
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(!tight.path().join("never").exists());
}

/// The text a reader sees on the page: no tags, no script or style, no folded `<details>`.
fn visible_text(html: &str) -> String {
    let mut text = html.to_string();
    for (open, close) in [
        ("<script", "</script>"),
        ("<style", "</style>"),
        ("<details", "</details>"),
    ] {
        while let Some(a) = text.find(open) {
            let b = text[a..].find(close).map(|b| a + b + close.len()).unwrap();
            text.replace_range(a..b, " ");
        }
    }
    let mut out = String::new();
    let mut in_tag = false;
    for c in text.chars() {
        match c {
            '<' => in_tag = true,
            '>' => {
                in_tag = false;
                out.push(' ');
            }
            c if !in_tag => out.push(c),
            _ => {}
        }
    }
    out
}

/// Every key path of `report.json` (dotted below the top level).
fn key_paths(prefix: &str, v: &serde_json::Value, out: &mut Vec<String>) {
    if let serde_json::Value::Object(m) = v {
        for (k, x) in m {
            let p = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            key_paths(&p, x, out);
            out.push(p);
        }
    }
}

/// The page opens with the summary a shop reads first (measured error, expected result,
/// machining time in hours and minutes, tool and path, the risks in words), before the first
/// figure; the solver's internals are folded; no key of report.json is in the visible text.
#[test]
fn the_page_opens_with_a_summary_in_words() {
    assert_eq!(preston_io::html::hours_minutes(27_542.0), "7 h 39 min");
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job_point_1mm.toml"))
        .args(["--report", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(out.path().join("report.html")).unwrap();
    let json = common::report(out.path());
    let summary = html.find("id=\"summary\"").expect("no summary");
    let first_figure = html.find("<figure").expect("no figure");
    assert!(summary < first_figure);
    let top = visible_text(&html[..first_figure]);
    let t = json["machining_time_s"].as_f64().unwrap();
    for words in [
        "Measured error",
        "Expected result",
        "Machining time",
        &preston_io::html::hours_minutes(t),
        "Tool and path",
        "measured TIF tif_fluid_jet_10mm.csv",
        "TIF 3% wider",
        "rate 3% high",
        "tool 0.05 mm off in x",
    ] {
        assert!(top.contains(words), "'{words}' not in the summary: {top}");
    }
    // The summary's numbers are report.json's, each with its unit.
    for (key, unit) in [
        ("rms_before_nm", "nm"),
        ("rms_after_nm", "nm"),
        ("model.rms_nm", "nm"),
        ("sensitivity.rate_plus_3pct.rms_nm", "nm"),
        ("machining_time_s", "s"),
    ] {
        let v = at(&json, key).unwrap();
        let cell = format!("data-key=\"{key}\" data-value=\"{v}\"");
        let at_cell = html[..first_figure]
            .find(&cell)
            .unwrap_or_else(|| panic!("{key}"));
        let after = &html[at_cell..];
        let shown_end = after.find("</span>").unwrap() + "</span>".len();
        assert!(
            after[shown_end..].starts_with(&format!(" {unit}")),
            "{key}: no unit after it"
        );
    }
    // Solver internals folded, not gone.
    let visible = visible_text(&html);
    assert!(html.contains("KKT residual") && !visible.contains("KKT residual"));
    let mut keys = Vec::new();
    key_paths("", &json, &mut keys);
    let raw: Vec<&String> = keys
        .iter()
        .filter(|k| k.contains('.') || k.contains('_'))
        .filter(|k| visible.contains(k.as_str()))
        .collect();
    assert!(raw.is_empty(), "raw keys in the visible text: {raw:?}");
}

/// Words that may follow a number in the summary: its unit, a count's noun, or `to` (a range,
/// the unit after its end).
const SUMMARY_UNITS: [&str; 11] = [
    "nm", "s", "mm/min", "mm/s²", "mm", "h", "min", "dwell", "warning", "warnings", "to",
];

/// The sample job's page (`preston solve --job data/job.toml --report`): the summary comes first
/// (the measured error, the expected result and the expected reading with its 90% range, the
/// machining time in hours and minutes, the tool and path, the risks), every number in it is
/// followed by its unit, and no key of report.json is visible anywhere on the page.
#[test]
fn the_sample_page_leads_with_a_summary_whose_numbers_carry_units() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job.toml"))
        .args(["--report", "--out"])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(out.path().join("report.html")).unwrap();
    let json = common::report(out.path());
    let summary = html.find("id=\"summary\"").expect("no summary");
    let first_figure = html.find("<figure").expect("no figure");
    assert!(summary < first_figure, "the summary is not first");
    // Nothing but the title and one line of provenance before the summary.
    assert!(visible_text(&html[..summary]).split_whitespace().count() < 40);
    let top = visible_text(&html[summary..first_figure]);
    let t = json["machining_time_s"].as_f64().unwrap();
    let range = json["expected_rms_range_nm"].as_array().unwrap();
    for words in [
        "Measured error",
        "Expected result",
        "Expected reading",
        "90% range",
        "Machining time",
        &preston_io::html::hours_minutes(t),
        "Tool and path",
        "measured TIF tif_fluid_jet_10mm.csv",
        "raster along x",
        "Risks",
        "TIF 3% wider",
        "rate 3% high",
        "tool 0.05 mm off in y",
    ] {
        assert!(top.contains(words), "'{words}' not in the summary: {top}");
    }
    // The range brackets the expected reading, and both are the report's.
    let (lo, hi) = (range[0].as_f64().unwrap(), range[1].as_f64().unwrap());
    let expected = json["expected_rms_nm"].as_f64().unwrap();
    assert!(lo <= expected && expected <= hi, "{lo} {expected} {hi}");
    for key in [
        "expected_rms_nm",
        "expected_rms_range_nm.0",
        "expected_rms_range_nm.1",
        "expected_pv_nm",
    ] {
        let v = at(&json, key).unwrap();
        let cell = format!("data-key=\"{key}\" data-value=\"{v}\"");
        assert!(html[summary..first_figure].contains(&cell), "{key}");
    }
    // Every number a reader sees in the summary is followed by its unit.
    let tokens: Vec<&str> = top
        .split_whitespace()
        .map(|w| w.trim_matches(|c: char| "(),;:".contains(c)))
        .filter(|w| !w.is_empty())
        .collect();
    let mut bare = Vec::new();
    for (k, w) in tokens.iter().enumerate() {
        if w.parse::<f64>().is_ok() {
            let next = tokens.get(k + 1).copied().unwrap_or("");
            if !SUMMARY_UNITS.contains(&next) {
                bare.push(format!("{w} {next}"));
            }
        }
    }
    assert!(bare.is_empty(), "numbers without a unit: {bare:?} in {top}");
    // No key of report.json in the visible text of the whole page.
    let visible = visible_text(&html);
    let mut keys = Vec::new();
    key_paths("", &json, &mut keys);
    let raw: Vec<&String> = keys
        .iter()
        .filter(|k| k.contains('.') || k.contains('_'))
        .filter(|k| visible.contains(k.as_str()))
        .collect();
    assert!(raw.is_empty(), "raw keys in the visible text: {raw:?}");
}
