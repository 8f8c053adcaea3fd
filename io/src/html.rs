//! `report.html`: one self-contained page a metrologist can hand on. It opens with a one-screen
//! summary (the measured error, the expected result, the machining time in hours and minutes,
//! the tool and path, the solve's status, the warnings' count, and the risks: the RMS the same
//! program leaves under each sensitivity scenario, in words), then the figures in a grid,
//! embedded as base64 PNG (or SVG) so the page needs no other file, the warnings, the model's
//! result, the plan's machine figures, the executed program, the inputs and their provenance
//! (files with size and SHA-256, the map's units, aperture and removed form terms, the job's
//! settings), and, folded, the solver's internals and every field of `report.json` by its key.
//!
//! Every number of `report.json` appears in the page in an element `data-key="PATH"
//! data-value="NUMBER"`, `PATH` the dotted key in `report.json` and `NUMBER` its JSON text
//! unchanged; the element shows it rounded to five significant digits, its unit beside it. The
//! visible labels are words, never the keys (those are in the attributes and the folded list of
//! every field). Tests (and anyone checking a page) read the numbers back from those
//! attributes. A short script marks, once the page has
//! loaded, how many of its images decoded (`data-images-loaded` and `data-images-total` on
//! `<body>`), for checks in a headless browser.

use crate::atomic::{stage, Staged};
use crate::digest::{base64, sha256_file};
use crate::error::{Error, Result};
use crate::job::Job;
use serde_json::Value;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// A figure embedded in the page.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// The file name the figure has (or would have) next to the page, e.g. `residual.png`.
    pub name: String,
    /// The caption under it.
    pub caption: String,
    /// The image: PNG or SVG bytes (by the name's extension).
    pub bytes: Vec<u8>,
}

impl Figure {
    /// The figure staged for `staged`'s destination, read back from its temporary file.
    pub fn from_staged(staged: &Staged, caption: &str) -> Result<Self> {
        let dest = staged.dest();
        Ok(Figure {
            name: dest
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            caption: caption.to_string(),
            bytes: staged.read_back()?,
        })
    }

    fn is_svg(&self) -> bool {
        self.name.ends_with(".svg")
    }
}

/// One input file of a job: its role (`map`, `tif`, ...) and path.
#[derive(Debug, Clone, PartialEq)]
pub struct InputFile {
    /// What the file is to the job.
    pub role: String,
    /// Where it was read from.
    pub path: PathBuf,
}

/// Where a report's inputs came from.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Provenance {
    /// The command line that produced the outputs.
    pub command: Option<String>,
    /// The input files, the job file first when there is one.
    pub inputs: Vec<InputFile>,
    /// The job's settings as resolved (flags applied), as JSON.
    pub settings: Option<Value>,
}

impl Provenance {
    /// The provenance of `job` (read from `job_path` when that file exists): every file it
    /// names, and its settings.
    pub fn of_job(job: &Job, job_path: &Path, command: Option<String>) -> Self {
        let mut inputs = Vec::new();
        if job_path.is_file() {
            inputs.push(InputFile {
                role: "job".into(),
                path: job_path.to_path_buf(),
            });
        }
        let dwell_file = job.dwell.source.file().map(Path::to_path_buf);
        let named = [
            ("map", &job.map.file),
            ("tif", &job.tif.file),
            ("dwell points", &dwell_file),
            ("warm start", &job.dwell.warm_start),
            ("surface", &job.surface.file),
        ];
        for (role, file) in named {
            if let Some(p) = file {
                inputs.push(InputFile {
                    role: role.into(),
                    path: p.clone(),
                });
            }
        }
        for (k, tool) in job.tool.iter().enumerate() {
            let v = serde_json::to_value(tool).unwrap_or(Value::Null);
            for key in ["tif", "dwell"] {
                if let Some(Value::String(p)) = v.get(key).and_then(|t| t.get("file")) {
                    inputs.push(InputFile {
                        role: format!("tool {} {key}", k + 1),
                        path: PathBuf::from(p),
                    });
                }
            }
        }
        Provenance {
            command,
            inputs,
            settings: serde_json::to_value(job).ok(),
        }
    }

    /// The command line of this process, arguments quoted where they need it.
    pub fn command_line() -> String {
        std::env::args()
            .map(|a| {
                if a.is_empty() || a.contains(|c: char| c.is_whitespace() || c == '\'') {
                    format!("'{}'", a.replace('\'', "'\\''"))
                } else {
                    a
                }
            })
            .collect::<Vec<_>>()
            .join(" ")
    }
}

/// Escapes `s` for HTML text and attribute values.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// Five significant digits, without an exponent for everyday magnitudes; integers as they are.
pub fn display_number(v: f64) -> String {
    if !v.is_finite() {
        return format!("{v}");
    }
    if v.fract() == 0.0 && v.abs() < 1e15 {
        return format!("{v:.0}");
    }
    let a = v.abs();
    if (1e-3..1e6).contains(&a) {
        let decimals = (4 - a.log10().floor() as i32).clamp(0, 7) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.4e}")
    }
}

/// The unit a report key's suffix names (`_nm`, `_s`, `_mm_per_min`, ...), for the unit column.
fn unit_of(key: &str) -> &'static str {
    let last = key.rsplit('.').next().unwrap_or(key);
    const SUFFIXES: [(&str, &str); 12] = [
        ("_mm_per_min", "mm/min"),
        ("_mm_per_s2", "mm/s²"),
        ("_nm_per_s", "nm/s"),
        ("_nm2_mm2", "nm² mm²"),
        ("_nm2_mm", "nm² mm"),
        ("_per_mm", "1/mm"),
        ("_nm2", "nm²"),
        ("_nm", "nm"),
        ("_mm", "mm"),
        ("_seconds", "s"),
        ("_s", "s"),
        ("_deg", "°"),
    ];
    SUFFIXES
        .iter()
        .find(|(s, _)| last.ends_with(s))
        .map_or("", |(_, u)| u)
}

/// Every leaf of `v` under `prefix` as (dotted key, value); arrays longer than `MAX_ARRAY` are
/// one leaf (shown as a count).
fn flatten(prefix: &str, v: &Value, out: &mut Vec<(String, Value)>) {
    const MAX_ARRAY: usize = 12;
    let key = |k: &str| {
        if prefix.is_empty() {
            k.to_string()
        } else {
            format!("{prefix}.{k}")
        }
    };
    match v {
        Value::Object(map) => {
            for (k, x) in map {
                flatten(&key(k), x, out);
            }
        }
        Value::Array(a) if a.len() <= MAX_ARRAY && !a.is_empty() => {
            for (k, x) in a.iter().enumerate() {
                flatten(&key(&k.to_string()), x, out);
            }
        }
        other => out.push((prefix.to_string(), other.clone())),
    }
}

/// A table cell holding `value` (the key's data attributes on numbers).
fn value_cell(key: &str, value: &Value) -> String {
    match value {
        Value::Number(n) => {
            let shown = n.as_f64().map_or_else(|| n.to_string(), display_number);
            format!(
                "<td class=\"num\" data-key=\"{}\" data-value=\"{}\">{}</td>",
                escape(key),
                escape(&n.to_string()),
                escape(&shown)
            )
        }
        Value::String(s) => format!("<td data-key=\"{}\">{}</td>", escape(key), escape(s)),
        Value::Null => "<td class=\"none\">none</td>".to_string(),
        Value::Bool(b) => format!("<td>{b}</td>"),
        Value::Array(a) => format!("<td>{} values (see report.json)</td>", a.len()),
        Value::Object(_) => "<td>(object)</td>".to_string(),
    }
}

/// An inline element holding the number `value` of `key` with its data attributes (its unit is
/// written after it by the caller); a dash when `key` is not in the report.
fn value_span(json: &Value, key: &str) -> String {
    match json.pointer(&format!("/{}", key.replace('.', "/"))) {
        Some(Value::Number(n)) => {
            let shown = n.as_f64().map_or_else(|| n.to_string(), display_number);
            format!(
                "<span class=\"num\" data-key=\"{}\" data-value=\"{}\">{}</span>",
                escape(key),
                escape(&n.to_string()),
                escape(&shown)
            )
        }
        Some(Value::String(s)) => escape(s),
        _ => "–".to_string(),
    }
}

/// A duration as hours and minutes, rounded to the minute (`27542` s: `7 h 39 min`); under a
/// minute in seconds.
pub fn hours_minutes(seconds: f64) -> String {
    if !(seconds.is_finite() && seconds >= 0.0) {
        return format!("{seconds} s");
    }
    if seconds < 59.5 {
        return format!("{seconds:.0} s");
    }
    let minutes = (seconds / 60.0).round() as u64;
    match (minutes / 60, minutes % 60) {
        (0, m) => format!("{m} min"),
        (h, m) => format!("{h} h {m} min"),
    }
}

/// A label for the key `key` below `section` in words: the key's parts without the unit suffix,
/// underscores as spaces (`map_input.pitch_mm` under `map_input`: `pitch`).
fn words_of(key: &str, section: &str) -> String {
    const UNIT_SUFFIXES: [&str; 12] = [
        "_mm_per_min",
        "_mm_per_s2",
        "_nm_per_s",
        "_nm2_mm2",
        "_nm2_mm",
        "_per_mm",
        "_nm2",
        "_nm",
        "_mm",
        "_seconds",
        "_s",
        "_deg",
    ];
    let rest = key
        .strip_prefix(section)
        .map(|r| r.trim_start_matches('.'))
        .filter(|r| !r.is_empty())
        .unwrap_or(key);
    rest.split('.')
        .map(|part| {
            let part = UNIT_SUFFIXES
                .iter()
                .find_map(|u| part.strip_suffix(u).filter(|p| !p.is_empty()))
                .unwrap_or(part);
            part.replace('_', " ")
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// Rows for every leaf of `json` under `section`, labelled by `labels` (key below the section,
/// label) or else by the key in words.
fn labelled_leaf_rows(
    json: &Value,
    section: &str,
    labels: &[(&str, &str)],
) -> Vec<(String, String, Value)> {
    leaf_rows(json, section)
        .into_iter()
        .map(|(_, key, v)| {
            let below = key
                .strip_prefix(section)
                .unwrap_or(&key)
                .trim_start_matches('.');
            let label = labels
                .iter()
                .find(|(k, _)| *k == below)
                .map_or_else(|| words_of(&key, section), |(_, l)| l.to_string());
            (label, key, v)
        })
        .collect()
}

/// A two- or three-column table of `rows` (label, key, value).
fn table(out: &mut String, rows: &[(String, String, Value)]) {
    out.push_str("<table>\n<tr><th>quantity</th><th>value</th><th>unit</th></tr>\n");
    for (label, key, value) in rows {
        let _ = writeln!(
            out,
            "<tr><th scope=\"row\">{}</th>{}<td class=\"unit\">{}</td></tr>",
            escape(label),
            value_cell(key, value),
            unit_of(key)
        );
    }
    out.push_str("</table>\n");
}

/// Rows for `keys` (key, label) of `json` that are present.
fn rows_of(json: &Value, keys: &[(&str, &str)]) -> Vec<(String, String, Value)> {
    keys.iter()
        .filter_map(|(k, label)| {
            let v = json.pointer(&format!("/{}", k.replace('.', "/")))?;
            Some((label.to_string(), k.to_string(), v.clone()))
        })
        .collect()
}

/// Rows for every leaf of `json` under `key`, labelled by their key.
fn leaf_rows(json: &Value, key: &str) -> Vec<(String, String, Value)> {
    let mut leaves = Vec::new();
    if let Some(v) = json.get(key) {
        flatten(key, v, &mut leaves);
    }
    leaves.into_iter().map(|(k, v)| (k.clone(), k, v)).collect()
}

const STYLE: &str = "body{font-family:'DejaVu Sans',Arial,sans-serif;margin:2em auto;max-width:70em;\
padding:0 1em;color:#222}h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.25em;border-bottom:1px solid #bbb;\
margin-top:1.6em}table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.2em .6em;\
text-align:left;vertical-align:top}th[scope=row]{font-weight:normal;background:#f4f4f4}td.num{text-align:right;\
font-variant-numeric:tabular-nums}td.unit{color:#555}td.hash{font-family:monospace;font-size:.85em;\
word-break:break-all}.warn{color:#8a3b00}figure{margin:1em 0}\
figure img{max-width:100%;height:auto;border:1px solid #eee}figure svg{max-width:100%;height:auto}\
figcaption{color:#444;font-size:.9em}pre{background:#f7f7f7;padding:.6em;overflow-x:auto;font-size:.85em}\
.figs{display:grid;grid-template-columns:repeat(auto-fill,minmax(30em,1fr));gap:.4em 1.2em}.figs figure{margin:.4em 0}\
table.summary th[scope=row]{width:11em}details{margin:1em 0}summary{cursor:pointer;font-weight:bold}\
@media print{figure{break-inside:avoid}}";

const SCRIPT: &str = "window.addEventListener('load',function(){var im=document.images,k=0;\
for(var i=0;i<im.length;i++){if(im[i].complete&&im[i].naturalWidth>0)k++;}\
document.body.setAttribute('data-images-loaded',String(k));\
document.body.setAttribute('data-images-total',String(im.length));});";

/// What a page shows beyond `report.json`.
#[derive(Debug, Clone, Default)]
pub struct PageExtras<'a> {
    /// Where the inputs came from.
    pub provenance: Option<&'a Provenance>,
    /// The figures.
    pub figures: &'a [Figure],
    /// Notes (figures left out and the like), listed with the warnings.
    pub notes: &'a [String],
}

fn head(out: &mut String, title: &str) {
    let _ = write!(
        out,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n\
         <meta name=\"generator\" content=\"preston {}\">\n<title>{}</title>\n<style>{STYLE}</style>\n\
         <script>{SCRIPT}</script>\n</head>\n<body>\n",
        env!("CARGO_PKG_VERSION"),
        escape(title)
    );
}

fn provenance_section(out: &mut String, p: &Provenance, report: &Value) {
    out.push_str("<h2 id=\"inputs\">Inputs and provenance</h2>\n");
    if let Some(c) = &p.command {
        let _ = writeln!(out, "<p>Command:</p><pre>{}</pre>", escape(c));
    }
    if !p.inputs.is_empty() {
        out.push_str(
            "<table>\n<tr><th>input</th><th>file</th><th>bytes</th><th>SHA-256</th></tr>\n",
        );
        for f in &p.inputs {
            let (hash, size) = match sha256_file(&f.path) {
                Ok((h, n)) => (h, n.to_string()),
                Err(e) => (format!("unreadable: {e}"), String::new()),
            };
            let _ = writeln!(
                out,
                "<tr><th scope=\"row\">{}</th><td>{}</td><td class=\"num\">{}</td>\
                 <td class=\"hash\" data-file=\"{}\">{}</td></tr>",
                escape(&f.role),
                escape(&f.path.display().to_string()),
                size,
                escape(&f.path.display().to_string()),
                escape(&hash)
            );
        }
        out.push_str("</table>\n");
    }
    let map_source = p.settings.as_ref().and_then(|s| s.get("map"));
    let text = |v: Option<&Value>| match v {
        None | Some(Value::Null) => None,
        Some(Value::String(s)) => Some(s.clone()),
        Some(other) => Some(other.to_string()),
    };
    let mut rows: Vec<(String, String)> = Vec::new();
    if let Some(mi) = report.get("map_input") {
        if let Some(f) = text(mi.get("format")) {
            rows.push(("map format".into(), f));
        }
    }
    let units = text(map_source.and_then(|m| m.get("units")))
        .unwrap_or_else(|| "from the file's header, else x, y in mm and z in nm".into());
    rows.push(("map units".into(), units));
    let aperture = text(map_source.and_then(|m| m.get("aperture")))
        .unwrap_or_else(|| "none (every valid point)".into());
    rows.push(("clear aperture".into(), aperture));
    let removed = match report.pointer("/map_input/removed") {
        Some(Value::Object(r)) => {
            let mut parts = Vec::new();
            for (k, v) in r {
                parts.push(format!("{k}: {v}"));
            }
            parts.join("; ")
        }
        _ => {
            let asked = map_source.and_then(|m| m.get("remove"));
            match asked {
                Some(Value::Array(a)) if !a.is_empty() => a
                    .iter()
                    .filter_map(|t| t.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
                _ => "none".into(),
            }
        }
    };
    rows.push(("form terms removed".into(), removed));
    out.push_str("<table>\n");
    for (k, v) in rows {
        let _ = writeln!(
            out,
            "<tr><th scope=\"row\">{}</th><td>{}</td></tr>",
            escape(&k),
            escape(&v)
        );
    }
    out.push_str("</table>\n");
    let mut map_rows = labelled_leaf_rows(report, "map_input", &[]);
    map_rows.retain(|(_, k, _)| !k.starts_with("map_input.notes"));
    if !map_rows.is_empty() {
        out.push_str("<p>How the map was read:</p>\n");
        table(out, &map_rows);
    }
    if let Some(s) = &p.settings {
        let pretty = serde_json::to_string_pretty(s).unwrap_or_default();
        let _ = writeln!(
            out,
            "<details><summary>The job's settings as run (flags applied)</summary><pre>{}</pre></details>",
            escape(&pretty)
        );
    }
}

fn figures_section(out: &mut String, figures: &[Figure]) {
    if figures.is_empty() {
        return;
    }
    out.push_str("<h2 id=\"figures\">Figures</h2>\n<div class=\"figs\">\n");
    for f in figures {
        let alt = escape(&f.caption);
        if f.is_svg() {
            // The SVG as an image (not inline markup): its ids cannot collide with the page's.
            let _ = writeln!(
                out,
                "<figure><img alt=\"{alt}\" src=\"data:image/svg+xml;base64,{}\"><figcaption>{} ({})</figcaption></figure>",
                base64(&f.bytes),
                alt,
                escape(&f.name)
            );
        } else {
            let _ = writeln!(
                out,
                "<figure><img alt=\"{alt}\" src=\"data:image/png;base64,{}\"><figcaption>{} ({})</figcaption></figure>",
                base64(&f.bytes),
                alt,
                escape(&f.name)
            );
        }
    }
    out.push_str("</div>\n");
}

fn warnings_section(out: &mut String, warnings: &[String]) {
    out.push_str("<h2 id=\"warnings\">Warnings</h2>\n");
    if warnings.is_empty() {
        out.push_str("<p>None.</p>\n");
    } else {
        out.push_str("<ul class=\"warn\">\n");
        for w in warnings {
            let _ = writeln!(out, "<li>{}</li>", escape(w));
        }
        out.push_str("</ul>\n");
    }
}

/// Keys of the result section.
const RESULT_KEYS: [(&str, &str); 8] = [
    ("rms_before_nm", "RMS of the error before"),
    ("pv_before_nm", "PV of the error before"),
    ("rms_after_nm", "RMS of the predicted residual"),
    ("pv_after_nm", "PV of the predicted residual"),
    ("model.rms_nm", "RMS of the plan's model residual"),
    ("model.pv_nm", "PV of the plan's model residual"),
    ("piston_nm", "piston (uniform extra removal)"),
    ("total_dwell_s", "total dwell"),
];

/// Keys of the plan-and-machine section.
const PLAN_KEYS: [(&str, &str); 14] = [
    ("m", "measurement points"),
    ("skipped_rows", "map points skipped (empty or NaN)"),
    ("n", "dwell points"),
    ("edge", "edge model"),
    ("edge_points", "edge extension points"),
    ("min_feed_mm_per_min", "slowest feed"),
    ("max_feed_mm_per_min", "fastest feed"),
    ("machining_time_s", "machining time"),
    ("a_max_mm_per_s2", "acceleration limit"),
    ("max_accel_mm_per_s2", "largest acceleration"),
    (
        "rms_feed_limited_only_nm",
        "RMS without the acceleration limit",
    ),
    ("max_neighbour_feed_ratio", "largest neighbour feed ratio"),
    ("dwell_outside_map_s", "dwell outside the map"),
    ("unreachable_dwell_points", "unreachable dwell points"),
];

/// Keys of the folded solver-internals section.
const INTERNAL_KEYS: [(&str, &str); 14] = [
    ("solver", "solver"),
    ("status", "status"),
    ("converged_by", "converged by"),
    ("iterations", "iterations"),
    ("objective", "objective 0.5 |R t - z - c|²"),
    ("objective_gap_bound", "proven objective gap bound"),
    ("gap_bound_reason", "why no gap bound"),
    ("kkt_residual", "KKT residual"),
    ("max_bound_violation_s", "largest dwell-bound violation"),
    ("accel_iterations", "acceleration-limit iterations"),
    ("operator", "how R was applied"),
    ("nnz", "non-zeros of R"),
    ("build_seconds", "build time"),
    ("solve_seconds", "solve time"),
];

/// Labels of the executed program's fields.
const EXECUTED_LABELS: [(&str, &str); 12] = [
    ("a_max_mm_per_s2", "acceleration limit"),
    ("rms_after_nm", "RMS of the residual as executed"),
    ("pv_after_nm", "PV of the residual as executed"),
    ("rms_ratio_to_plan", "RMS as executed over the model's RMS"),
    ("stretch_time_s", "time in the dwell stretches"),
    (
        "max_stretch_error",
        "largest stretch-time error (fraction of its dwell)",
    ),
    (
        "stretches_over_5_percent",
        "stretches more than 5% off their dwell",
    ),
    ("correction_passes", "correction passes kept"),
    (
        "integration.sample_step_mm",
        "removal integrated along the motion in samples of at most",
    ),
    ("integration.samples", "removal samples"),
    (
        "integration.rms_change_nm",
        "RMS change of the residual at half that step",
    ),
    (
        "integration.pv_change_nm",
        "PV change of the residual at half that step",
    ),
];

/// The sensitivity scenarios of `report.json` `sensitivity` in words.
const SCENARIOS: [(&str, &str); 5] = [
    ("tif_wider_3pct", "TIF 3% wider"),
    ("tif_narrower_3pct", "TIF 3% narrower"),
    ("rate_plus_3pct", "rate 3% high"),
    ("offset_x_0p05mm", "tool 0.05 mm off in x"),
    ("offset_y_0p05mm", "tool 0.05 mm off in y"),
];

/// The file name of a path given in the job's settings.
fn file_name_of(v: &Value) -> Option<String> {
    let p = Path::new(v.as_str()?);
    Some(p.file_name().map_or_else(
        || p.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    ))
}

/// The tool and the path in words, from the job's settings and the report.
fn tool_and_path(report: &Value, settings: Option<&Value>) -> String {
    let mut parts = Vec::new();
    let number = |v: Option<&Value>| v.and_then(Value::as_f64).map(display_number);
    let tools = settings
        .and_then(|s| s.get("tool"))
        .and_then(Value::as_array)
        .map_or(0, Vec::len);
    if tools > 0 {
        parts.push(format!("{tools} tools"));
    } else if let Some(tif) = settings.and_then(|s| s.get("tif")) {
        if let Some(f) = tif.get("file").and_then(file_name_of) {
            parts.push(format!("measured TIF {}", escape(&f)));
        } else if let Some(g) = tif.get("gaussian").filter(|g| !g.is_null()) {
            let sigma = number(g.get("sigma_mm")).unwrap_or_else(|| "?".into());
            let peak = number(g.get("peak_rate_nm_per_s")).unwrap_or_else(|| "?".into());
            parts.push(format!("Gaussian TIF, σ {sigma} mm, peak {peak} nm/s"));
        } else if tif.get("hertz").is_some_and(|h| !h.is_null()) {
            let varying = tif
                .get("curvature_dependent")
                .and_then(Value::as_bool)
                .unwrap_or(false);
            parts.push(
                if varying {
                    "Hertz contact TIF, following the surface's curvature"
                } else {
                    "Hertz contact TIF"
                }
                .to_string(),
            );
        }
    }
    if let Some(d) = settings.and_then(|s| s.get("dwell")) {
        if let Some(f) = d.get("file").and_then(file_name_of) {
            parts.push(format!("dwell points from {}", escape(&f)));
        } else if let Some(p) = number(d.get("raster_pitch_mm")) {
            let along = d.get("raster_along").and_then(Value::as_str).unwrap_or("x");
            parts.push(format!("raster along {}, {p} mm pitch", escape(along)));
        }
    }
    let mut path = Vec::new();
    if report.get("n").is_some() {
        path.push(format!("{} dwell points", value_span(report, "n")));
    }
    if report.get("min_feed_mm_per_min").is_some() && report.get("max_feed_mm_per_min").is_some() {
        path.push(format!(
            "feed {} to {} mm/min",
            value_span(report, "min_feed_mm_per_min"),
            value_span(report, "max_feed_mm_per_min")
        ));
    }
    if !path.is_empty() {
        parts.push(path.join(", "));
    }
    parts.join("; ")
}

/// A summary row: the label and the cell's HTML.
fn summary_row(out: &mut String, label: &str, html: &str) {
    let _ = writeln!(
        out,
        "<tr><th scope=\"row\">{}</th><td>{html}</td></tr>",
        escape(label)
    );
}

/// The one-screen summary at the top of the page.
fn summary_section(out: &mut String, report: &Value, extras: &PageExtras<'_>, warnings: usize) {
    let has = |k: &str| {
        report
            .pointer(&format!("/{}", k.replace('.', "/")))
            .is_some()
    };
    let rms_pv = |rms: &str, pv: &str| {
        format!(
            "RMS {} nm, PV {} nm",
            value_span(report, rms),
            value_span(report, pv)
        )
    };
    out.push_str("<h2 id=\"summary\">Summary</h2>\n<table class=\"summary\">\n");
    if has("rms_before_nm") {
        summary_row(
            out,
            "Measured error",
            &rms_pv("rms_before_nm", "pv_before_nm"),
        );
    }
    // With `model` present the predicted residual is the program's as executed.
    if has("model.rms_nm") && has("executed.a_max_mm_per_s2") {
        summary_row(
            out,
            "Expected result",
            &format!(
                "{} as the program executes at {} mm/s², piston removed{} (the plan's model: {})",
                rms_pv("rms_after_nm", "pv_after_nm"),
                value_span(report, "executed.a_max_mm_per_s2"),
                if has("executed.integration.rms_change_nm") {
                    format!(
                        "; integrated along the motion to within {} nm RMS",
                        value_span(report, "executed.integration.rms_change_nm")
                    )
                } else {
                    String::new()
                },
                rms_pv("model.rms_nm", "model.pv_nm")
            ),
        );
    } else if has("rms_after_nm") {
        summary_row(
            out,
            "Expected result",
            &format!("{}, piston removed", rms_pv("rms_after_nm", "pv_after_nm")),
        );
    }
    if has("expected_rms_nm") && has("expected_rms_range_nm") {
        summary_row(
            out,
            "Expected reading",
            &format!(
                "RMS {} nm (90% range {} to {} nm), PV {} nm: what the interferometer should read \
                 after the run, piston and tilt removed, the tool as it is known (its rate, width and \
                 offset uncertain) and the measurement's noise included",
                value_span(report, "expected_rms_nm"),
                value_span(report, "expected_rms_range_nm.0"),
                value_span(report, "expected_rms_range_nm.1"),
                value_span(report, "expected_pv_nm")
            ),
        );
    }
    if let Some(t) = report.get("machining_time_s").and_then(Value::as_f64) {
        summary_row(
            out,
            "Machining time",
            &format!(
                "{} ({} s)",
                hours_minutes(t),
                value_span(report, "machining_time_s")
            ),
        );
    }
    let tool = tool_and_path(report, extras.provenance.and_then(|p| p.settings.as_ref()));
    if !tool.is_empty() {
        summary_row(out, "Tool and path", &tool);
    }
    if let Some(s) = report.get("status").and_then(Value::as_str) {
        let words = match s {
            "converged" => "converged".to_string(),
            "simulated" => "simulated as given".to_string(),
            other => format!("{} (the outputs hold the best iterate)", escape(other)),
        };
        summary_row(out, "Solve", &words);
    }
    summary_row(
        out,
        "Warnings",
        &match warnings {
            0 => "none".to_string(),
            1 => "<a href=\"#warnings\">1 warning, listed below</a>".to_string(),
            n => format!("<a href=\"#warnings\">{n} warnings, listed below</a>"),
        },
    );
    out.push_str("</table>\n");
    if let Some(Value::Object(_)) = report.get("sensitivity") {
        out.push_str(
            "<h3 id=\"sensitivity\">Risks</h3>\n<p>The residual the same program leaves when the \
             tool is not quite what the plan assumes (piston removed):</p>\n\
             <table>\n<tr><th>if the</th><th>RMS left</th><th>PV left</th></tr>\n",
        );
        for (key, words) in SCENARIOS {
            let base = format!("sensitivity.{key}");
            if !has(&base) {
                continue;
            }
            let _ = writeln!(
                out,
                "<tr><th scope=\"row\">{}</th><td class=\"num\">{} nm</td><td class=\"num\">{} nm</td></tr>",
                escape(words),
                value_span(report, &format!("{base}.rms_nm")),
                value_span(report, &format!("{base}.pv_nm"))
            );
        }
        out.push_str("</table>\n");
    }
}

/// The warnings of a report page: the report's, the map reader's notes, unreachable points, a
/// status other than converged, and `notes`.
fn page_warnings(report: &Value, notes: &[String]) -> Vec<String> {
    let mut warnings: Vec<String> = report
        .get("warnings")
        .and_then(|w| w.as_array())
        .map(|a| {
            a.iter()
                .filter_map(|s| s.as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default();
    if let Some(Value::Array(notes)) = report.pointer("/map_input/notes") {
        warnings.extend(
            notes
                .iter()
                .filter_map(|s| s.as_str().map(|s| format!("map: {s}"))),
        );
    }
    if let Some(n) = report
        .get("unreachable_dwell_points")
        .and_then(Value::as_u64)
        .filter(|n| *n > 0)
    {
        warnings.push(format!(
            "{n} dwell points have no map point in the tool's reach (their dwell is at its lower \
             bound; indices in report.json)"
        ));
    }
    if let Some(s) = report.get("status").and_then(Value::as_str) {
        if !matches!(s, "converged" | "simulated") {
            warnings.push(format!(
                "the solver stopped with status {s}: the outputs hold its best iterate"
            ));
        }
    }
    warnings.extend(notes.iter().cloned());
    warnings
}

/// The page of a solve (or a simulation): `report` is `report.json`'s content as JSON.
pub fn report_page(title: &str, report: &Value, extras: &PageExtras<'_>) -> String {
    let mut out = String::with_capacity(1 << 20);
    head(&mut out, title);
    let _ = writeln!(out, "<h1>{}</h1>", escape(title));
    let _ = writeln!(
        out,
        "<p>Written by preston {}. Every number below is the one in <code>report.json</code> \
         (rounded for display; the exact value is in the element's <code>data-value</code>).</p>",
        env!("CARGO_PKG_VERSION")
    );
    let warnings = page_warnings(report, extras.notes);
    summary_section(&mut out, report, extras, warnings.len());
    figures_section(&mut out, extras.figures);
    warnings_section(&mut out, &warnings);
    out.push_str("<h2 id=\"result\">Result</h2>\n");
    table(&mut out, &rows_of(report, &RESULT_KEYS));
    out.push_str("<h2 id=\"plan\">Plan and machine</h2>\n");
    table(&mut out, &rows_of(report, &PLAN_KEYS));
    out.push_str("<h2 id=\"executed\">Executed program</h2>\n");
    match report.get("executed") {
        Some(Value::Object(_)) => {
            out.push_str(
                "<p>The default program (ISO, G94) run at the acceleration limit, its removal \
                 integrated along the motion:</p>\n",
            );
            table(
                &mut out,
                &labelled_leaf_rows(report, "executed", &EXECUTED_LABELS),
            );
        }
        _ => out.push_str(
            "<p>Not computed: the executed program is simulated with an acceleration limit on a \
             flat part (<code>[machine] a_max_mm_per_s2</code>).</p>\n",
        ),
    }
    if let Some(p) = extras.provenance {
        provenance_section(&mut out, p, report);
    }
    out.push_str("<details id=\"internals\"><summary>Solver internals</summary>\n");
    table(&mut out, &rows_of(report, &INTERNAL_KEYS));
    out.push_str("</details>\n");
    out.push_str("<details id=\"all\"><summary>Every field of report.json, by its key</summary>\n");
    let mut leaves = Vec::new();
    flatten("", report, &mut leaves);
    let rows: Vec<_> = leaves.into_iter().map(|(k, v)| (k.clone(), k, v)).collect();
    table(&mut out, &rows);
    out.push_str("</details>\n</body>\n</html>\n");
    out
}

/// One row of a polishing loop's table: the measured error before run `iteration`.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopRow {
    /// The iteration.
    pub iteration: usize,
    /// PV of the measured error, nm.
    pub pv_nm: f64,
    /// RMS of the measured error, nm.
    pub rms_nm: f64,
    /// Polishing time of the run, s.
    pub time_s: f64,
    /// RMS the solver predicted for the run, nm.
    pub predicted_rms_nm: Option<f64>,
}

/// The page of a polishing loop (`preston iterate`): the convergence table, the inner steps that
/// did not converge, the warnings and the figures.
pub fn loop_page(
    title: &str,
    rows: &[LoopRow],
    met_spec: bool,
    failures: &[String],
    extras: &PageExtras<'_>,
) -> String {
    let mut out = String::with_capacity(1 << 20);
    head(&mut out, title);
    let _ = writeln!(out, "<h1>{}</h1>", escape(title));
    let _ = writeln!(
        out,
        "<p>Written by preston {}. The numbers are those of <code>convergence.csv</code>.</p>",
        env!("CARGO_PKG_VERSION")
    );
    let _ = writeln!(
        out,
        "<p>Specification {}.</p>",
        if met_spec { "met" } else { "not met" }
    );
    if let Some(p) = extras.provenance {
        provenance_section(&mut out, p, &Value::Null);
    }
    out.push_str("<h2 id=\"convergence\">Convergence</h2>\n<table>\n<tr><th>iteration</th><th>PV (nm)</th><th>RMS (nm)</th><th>run time (s)</th><th>predicted RMS (nm)</th></tr>\n");
    for r in rows {
        let num = |key: &str, v: f64| {
            value_cell(
                &format!("convergence.{}.{key}", r.iteration),
                &serde_json::Number::from_f64(v).map_or(Value::Null, Value::Number),
            )
        };
        let _ = writeln!(
            out,
            "<tr><td class=\"num\">{}</td>{}{}{}{}</tr>",
            r.iteration,
            num("pv_nm", r.pv_nm),
            num("rms_nm", r.rms_nm),
            num("time_s", r.time_s),
            r.predicted_rms_nm
                .map_or_else(|| "<td></td>".to_string(), |v| num("predicted_rms_nm", v))
        );
    }
    out.push_str("</table>\n");
    let mut warnings: Vec<String> = failures.to_vec();
    warnings.extend(extras.notes.iter().cloned());
    warnings_section(&mut out, &warnings);
    figures_section(&mut out, extras.figures);
    out.push_str("</body>\n</html>\n");
    out
}

/// Stages `html` for `path` (committed together with the other outputs).
pub fn stage_html(path: &Path, html: &str) -> Result<Staged> {
    stage(path, |w| w.write_all(html.as_bytes()))
}

/// Stages the page of a solve for `path`: `report` with `provenance`, the staged `figures`
/// (PNG or SVG) embedded with their captions and `notes` on figures left out among the
/// warnings.
pub fn stage_report_page(
    path: &Path,
    report: &crate::report::Report,
    provenance: &Provenance,
    figures: &[Staged],
    notes: &[String],
) -> Result<Staged> {
    let mut embedded = Vec::new();
    for f in figures {
        let name = f
            .dest()
            .file_name()
            .map(|n| n.to_string_lossy().into_owned());
        if let Some(name) = name.filter(|n| n.ends_with(".png") || n.ends_with(".svg")) {
            embedded.push(Figure::from_staged(f, crate::figures::caption(&name))?);
        }
    }
    let json = report_json(report, path)?;
    let page = report_page(
        "Preston job report",
        &json,
        &PageExtras {
            provenance: Some(provenance),
            figures: &embedded,
            notes,
        },
    );
    stage_html(path, &page)
}

/// `report.json`'s content as JSON.
pub fn report_json(report: &crate::report::Report, path: &Path) -> Result<Value> {
    serde_json::to_value(report)
        .map_err(|e| Error::io(path, std::io::Error::other(format!("report as JSON: {e}"))))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_keep_five_significant_digits() {
        assert_eq!(display_number(12.3456789), "12.346");
        assert_eq!(display_number(0.0123456), "0.012346");
        assert_eq!(display_number(1234.0), "1234");
        assert_eq!(display_number(3.0e-7), "3.0000e-7");
        assert_eq!(display_number(-56.25), "-56.250");
    }

    #[test]
    fn every_number_gets_its_key_and_exact_text() {
        let report = serde_json::json!({
            "rms_after_nm": 1.25e-3, "pv_after_nm": 7.5, "status": "converged",
            "executed": {"rms_after_nm": 2.5, "pv_after_nm": 9.0},
            "sensitivity": {"tif_rate_plus_5_percent": {"rms_after_nm": 3.5}},
            "warnings": ["a <warning>"]
        });
        let page = report_page("t", &report, &PageExtras::default());
        for (k, v) in [
            ("rms_after_nm", "0.00125"),
            ("executed.rms_after_nm", "2.5"),
            ("sensitivity.tif_rate_plus_5_percent.rms_after_nm", "3.5"),
        ] {
            assert!(
                page.contains(&format!("data-key=\"{k}\" data-value=\"{v}\"")),
                "{k}"
            );
        }
        assert!(page.contains("id=\"sensitivity\""));
        assert!(page.contains("a &lt;warning&gt;"));
        assert!(!page.contains("<warning>"));
    }

    #[test]
    fn durations_read_as_hours_and_minutes() {
        assert_eq!(hours_minutes(27_542.0), "7 h 39 min");
        assert_eq!(hours_minutes(27_570.0), "7 h 40 min");
        assert_eq!(hours_minutes(3_599.9), "1 h 0 min");
        assert_eq!(hours_minutes(600.0), "10 min");
        assert_eq!(hours_minutes(42.4), "42 s");
        assert_eq!(hours_minutes(59.6), "1 min");
    }

    #[test]
    fn labels_are_words_not_keys() {
        assert_eq!(words_of("map_input.pitch_mm", "map_input"), "pitch");
        assert_eq!(
            words_of("map_input.removed.coefficients", "map_input"),
            "removed, coefficients"
        );
        assert_eq!(
            words_of("executed.max_stretch_error", "executed"),
            "max stretch error"
        );
    }

    /// The summary comes first with the risks in words; the keys stay in the attributes.
    #[test]
    fn the_summary_leads_and_names_the_risks_in_words() {
        let report = serde_json::json!({
            "rms_before_nm": 922.4, "pv_before_nm": 3025.8, "rms_after_nm": 0.36,
            "pv_after_nm": 3.97, "machining_time_s": 27_542.3, "status": "converged",
            "n": 22_971, "min_feed_mm_per_min": 1.4, "max_feed_mm_per_min": 3000.0,
            "kkt_residual": 1e-9,
            "sensitivity": {
                "tif_wider_3pct": {"rms_nm": 4.1, "pv_nm": 40.0},
                "tif_narrower_3pct": {"rms_nm": 3.9, "pv_nm": 38.0},
                "rate_plus_3pct": {"rms_nm": 28.0, "pv_nm": 90.0},
                "offset_x_0p05mm": {"rms_nm": 1.6, "pv_nm": 20.0},
                "offset_y_0p05mm": {"rms_nm": 1.7, "pv_nm": 21.0}
            }
        });
        let figures = [Figure {
            name: "residual.png".into(),
            caption: "Residual".into(),
            bytes: vec![1, 2, 3],
        }];
        let page = report_page(
            "t",
            &report,
            &PageExtras {
                figures: &figures,
                ..PageExtras::default()
            },
        );
        let summary = page.find("id=\"summary\"").unwrap();
        assert!(summary < page.find("<figure").unwrap());
        assert!(page.contains("7 h 39 min ("));
        assert!(page.contains(
            "<th scope=\"row\">tool 0.05 mm off in x</th><td class=\"num\"><span class=\"num\" \
             data-key=\"sensitivity.offset_x_0p05mm.rms_nm\" data-value=\"1.6\">1.6000</span> nm</td>"
        ));
        let folded = page.find("<details id=\"internals\">").unwrap();
        assert!(page.find("KKT residual").unwrap() > folded);
    }
}
