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
    assert_outputs_agree(&out);
}

/// Relative rounding of a number the page shows (five significant digits).
const SHOWN_REL: f64 = 5e-5;

/// `(key, value, shown)` of every number on `report.html`: the `data-key` and `data-value` of
/// each `<span class="num">` and the text it shows.
fn page_numbers(html: &str) -> Vec<(String, String, String)> {
    let mut found = Vec::new();
    let mut rest = html;
    while let Some(at) = rest.find("<span class=\"num\" data-key=\"") {
        rest = &rest[at + "<span class=\"num\" data-key=\"".len()..];
        let key_end = rest.find('"').unwrap();
        let key = rest[..key_end].to_string();
        rest = &rest[key_end..];
        let value_at = rest.find("data-value=\"").unwrap() + "data-value=\"".len();
        rest = &rest[value_at..];
        let value_end = rest.find('"').unwrap();
        let value = rest[..value_end].to_string();
        let shown_at = rest.find('>').unwrap() + 1;
        let shown_end = rest.find("</span>").unwrap();
        let shown = rest[shown_at..shown_end].to_string();
        rest = &rest[shown_end..];
        found.push((key, value, shown));
    }
    found
}

/// The value at a dotted key (`executed.rms_after_nm`, `expected_rms_range_nm.0`) of a report.
fn at_key<'a>(r: &'a serde_json::Value, key: &str) -> Option<&'a serde_json::Value> {
    r.pointer(&format!("/{}", key.replace('.', "/")))
}

/// The residual with its least-squares plane removed (what an interferometer reads), nm RMS.
fn rms_without_plane(x: &[f64], y: &[f64], e: &[f64]) -> f64 {
    // Normal equations of e ~ a + b x + c y, centred so that they are well conditioned.
    let n = e.len() as f64;
    let (mx, my, me) = (
        x.iter().sum::<f64>() / n,
        y.iter().sum::<f64>() / n,
        e.iter().sum::<f64>() / n,
    );
    let (mut sxx, mut sxy, mut syy, mut sxe, mut sye) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for ((x, y), e) in x.iter().zip(y).zip(e) {
        let (dx, dy, de) = (x - mx, y - my, e - me);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
        sxe += dx * de;
        sye += dy * de;
    }
    let det = sxx * syy - sxy * sxy;
    let (b, c) = ((sxe * syy - sye * sxy) / det, (sye * sxx - sxe * sxy) / det);
    let left: Vec<f64> = x
        .iter()
        .zip(y)
        .zip(e)
        .map(|((x, y), e)| e - me - b * (x - mx) - c * (y - my))
        .collect();
    rms_about_mean(&left)
}

/// Relative agreement of the expected reading's nominal with the plane-removed residual
/// recomputed here (the same plane fitted by another formula).
const PLANE_REL: f64 = 1e-6;

/// Every figure a solve writes for one quantity is the same figure in every file: the residual
/// files against the headline and the model's figures, the expected reading's nominal against
/// the residual with its plane removed, the dwell files against the total dwell and feeds, and
/// every number on the page against `report.json` (and shown to its five significant digits).
fn assert_outputs_agree(out: &Path) {
    let r = report(out);
    let name = out.display();
    let num = |key: &str| -> f64 {
        at_key(&r, key)
            .and_then(serde_json::Value::as_f64)
            .unwrap_or_else(|| panic!("{name}: report.json has no number {key}"))
    };
    // The residual file: the map before, the residual after.
    let residual = residual_of(&out.join("residual.csv"));
    let [x, y, z]: [Vec<f64>; 3] =
        csv_columns(&out.join("residual.csv"), &["x_mm", "y_mm", "z_nm"])
            .try_into()
            .unwrap();
    for (what, value, key) in [
        ("RMS of z_nm", rms_about_mean(&z), "rms_before_nm"),
        ("PV of z_nm", pv(&z), "pv_before_nm"),
        (
            "RMS of residual_nm",
            rms_about_mean(&residual),
            "rms_after_nm",
        ),
        ("PV of residual_nm", pv(&residual), "pv_after_nm"),
    ] {
        assert!(
            close(value, num(key)),
            "{name}: residual.csv {what} {value}, report.json {key} {}",
            num(key)
        );
    }
    if at_key(&r, "executed.rms_after_nm").is_some() {
        assert_eq!(num("executed.rms_after_nm"), num("rms_after_nm"), "{name}");
        assert_eq!(num("executed.pv_after_nm"), num("pv_after_nm"), "{name}");
    }
    if at_key(&r, "model.rms_nm").is_some() {
        let model = residual_of(&out.join("residual_model.csv"));
        assert!(close(rms_about_mean(&model), num("model.rms_nm")), "{name}");
        assert!(close(pv(&model), num("model.pv_nm")), "{name}");
    }
    // The expected reading's nominal tool (without drift) leaves the headline residual, which
    // the interferometer reads with its plane removed.
    if at_key(&r, "expected.nominal_rms_nm").is_some()
        && num("expected.uncertainty.drift_per_hour") == 0.0
    {
        let read = rms_without_plane(&x, &y, &residual);
        let nominal = num("expected.nominal_rms_nm");
        assert!(
            (read - nominal).abs() <= PLANE_REL * nominal.max(read) + RECOMPUTED_ABS_NM,
            "{name}: residual.csv with its plane removed {read} nm, expected.nominal_rms_nm {nominal}"
        );
    }
    // The dwell files: their dwell adds up to the total, their feeds span the reported range.
    let files: Vec<_> = match r["tools"].as_array() {
        Some(tools) => (1..=tools.len())
            .map(|k| out.join(format!("dwell_tool{k}.csv")))
            .collect(),
        None => vec![out.join("dwell.csv")],
    };
    let (mut total, mut slowest, mut fastest) = (0.0, f64::INFINITY, 0.0_f64);
    for (k, file) in files.iter().enumerate() {
        let [t, v]: [Vec<f64>; 2] = csv_columns(file, &["dwell_s", "feed_mm_per_min"])
            .try_into()
            .unwrap();
        let tool_total: f64 = t.iter().sum();
        if let Some(tool) = r["tools"].as_array().map(|tools| &tools[k]) {
            let reported = tool["total_dwell_s"].as_f64().unwrap();
            assert!(
                close(tool_total, reported),
                "{}: {tool_total} s, report.json tools[{k}].total_dwell_s {reported}",
                file.display()
            );
        }
        total += tool_total;
        slowest = v.iter().copied().fold(slowest, f64::min);
        fastest = v.iter().copied().fold(fastest, f64::max);
    }
    assert!(
        close(total, num("total_dwell_s")),
        "{name}: the dwell files hold {total} s, report.json total_dwell_s {}",
        num("total_dwell_s")
    );
    assert!(
        close(slowest, num("min_feed_mm_per_min")),
        "{name}: slowest feed {slowest}"
    );
    assert!(
        close(fastest, num("max_feed_mm_per_min")),
        "{name}: fastest feed {fastest}"
    );
    // The page: each number is report.json's, shown to five significant digits.
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    let numbers = page_numbers(&html);
    assert!(
        numbers.len() > 10,
        "{name}: {} numbers on the page",
        numbers.len()
    );
    for (key, value, shown) in numbers {
        let json = at_key(&r, &key)
            .and_then(serde_json::Value::as_f64)
            .unwrap_or_else(|| panic!("{name}: report.html shows {key}, not in report.json"));
        let value: f64 = value.parse().unwrap();
        assert_eq!(value, json, "{name}: report.html {key}");
        let shown: f64 = shown
            .replace('\u{2212}', "-")
            .parse()
            .unwrap_or_else(|_| panic!("{name}: report.html shows {key} as {shown:?}"));
        assert!(
            (shown - json).abs() <= SHOWN_REL * json.abs(),
            "{name}: report.html shows {key} as {shown}, report.json {json}"
        );
    }
}

/// A smooth map on an `n x n` grid at `pitch` mm, heights of tens of nm.
fn map_text(n: usize, pitch: f64) -> String {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..n {
        for ix in 0..n {
            let (x, y) = (ix as f64 * pitch, iy as f64 * pitch);
            let z = 40.0 + 25.0 * (0.31 * x).sin() * (0.23 * y).cos() + 0.8 * y;
            t.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    t
}

/// The Gaussian TIF of the small jobs, as flags.
const GAUSSIAN: [&str; 6] = [
    "--gaussian-sigma-mm",
    "1.2",
    "--gaussian-peak-nm-per-s",
    "8",
    "--gaussian-truncation-mm",
    "3.6",
];

/// A later solve into the same directory without `--plots` or `--report` leaves none of the
/// earlier run's page, figures or tables (which would contradict its report.json), and touches
/// no file Preston does not write.
#[test]
fn a_solve_replaces_the_earlier_solves_outputs_and_nothing_else() {
    let d = tempfile::tempdir().unwrap();
    // 17 points a side: enough for the 1-D PSD's table and figure.
    let map = write_arg(d.path(), "map.csv", &map_text(17, 1.0));
    let out = d.path().join("out");
    let run = |extra: &[&str], v_max: &str| {
        let mut args = vec!["solve", "--map", &map, "--raster-pitch-mm", "1"];
        args.extend(GAUSSIAN);
        args.extend(["--v-max", v_max]);
        args.extend(extra);
        args.extend(["--out", s(&out)]);
        ok(&preston(&args));
    };
    run(&["--plots", "--report"], "3000");
    for name in [
        "report.html",
        "residual.png",
        "psd.csv",
        "psd_2d.csv",
        "tif.png",
    ] {
        assert!(out.join(name).is_file(), "{name} not written");
    }
    // The user's own files beside the outputs, one of them a figure of another name.
    write(&out, "notes.txt", "kept");
    write(&out, "residual_before_polishing.png", "kept");
    run(&[], "2500");
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "dwell.csv",
            "notes.txt",
            "report.json",
            "residual.csv",
            "residual_before_polishing.png"
        ],
        "the directory holds the later run's outputs and the user's files only"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "kept"
    );
}

/// Relative agreement of `simulate`'s default residual RMS with the solve's model residual on
/// the same plan: the same swept columns, the solve's through the FFT operator with the exact
/// columns of the stretches that differ from its kernel, the simulation's assembled.
const SWEPT_SIMULATION_REL: f64 = 1e-6;
/// Absolute floor of that agreement, nm.
const SWEPT_SIMULATION_ABS_NM: f64 = 1e-6;

/// A plan solved under the solver's default (swept) model without an acceleration limit,
/// simulated with `simulate`'s defaults, gives the residual the solve predicted; the point
/// model (`--motion discrete`) does not.
#[test]
fn simulate_by_default_reproduces_the_plans_own_prediction() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &map_text(15, 1.0));
    let solved = d.path().join("solved");
    let mut args = vec!["solve", "--map", &map, "--raster-pitch-mm", "1"];
    args.extend(GAUSSIAN);
    args.extend(["--v-max", "3000", "--out", s(&solved)]);
    ok(&preston(&args));
    let planned = report(&solved);
    assert_eq!(planned["influence"], "swept");
    assert!(planned.get("executed").is_none(), "no acceleration limit");
    let predicted = planned["rms_after_nm"].as_f64().unwrap();
    let dwell = solved.join("dwell.csv");
    let simulate = |extra: &[&str], name: &str| {
        let out = d.path().join(name);
        let mut args = vec!["simulate", "--map", &map, "--dwell", s(&dwell)];
        args.extend(GAUSSIAN);
        args.extend(extra);
        args.extend(["--out", s(&out)]);
        ok(&preston(&args));
        report(&out)["rms_after_nm"].as_f64().unwrap()
    };
    let tolerance = SWEPT_SIMULATION_REL * predicted + SWEPT_SIMULATION_ABS_NM;
    let default = simulate(&[], "default");
    assert!(
        (default - predicted).abs() <= tolerance,
        "simulate's default {default} nm against the plan's prediction {predicted} nm"
    );
    let point = simulate(&["--motion", "discrete"], "point");
    assert!(
        (point - predicted).abs() > tolerance,
        "the point model {point} nm is not the plan's model {predicted} nm"
    );
}

/// A machine profile's bad value is blamed on the profile and its key, not on the command line
/// or the job.
#[test]
fn a_bad_machine_profile_is_named_with_its_key() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &map_text(9, 1.0));
    let feed = write_arg(
        d.path(),
        "feed_profile.toml",
        "[machine]\nv_max_mm_per_min = -5\n",
    );
    let mut args = vec!["--machine", &feed, "--map", &map, "--raster-pitch-mm", "1"];
    args.extend(GAUSSIAN);
    expect_failure(
        &args,
        &["feed_profile.toml", "[machine]", "v_max_mm_per_min"],
    );
    let o = preston(&[&["solve", "--out", s(&d.path().join("o"))][..], &args[..]].concat());
    assert!(
        !String::from_utf8_lossy(&o.stderr).contains("<command line>"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // An [nc] key of the profile, under a job that has no [nc] table of its own.
    let nc = write_arg(d.path(), "nc_profile.toml", "[nc]\ndecimals = 9\n");
    expect_failure(
        &["--job", &data_arg("job.toml"), "--machine", &nc],
        &["nc_profile.toml", "[nc]", "decimals"],
    );
}

/// A surface JSON saved with a UTF-8 byte-order mark reads as the same surface.
#[test]
fn a_surface_json_with_a_byte_order_mark_is_read() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &map_text(9, 1.0));
    let solve = |surface: &str, name: &str| {
        let out = d.path().join(name);
        let mut args = vec![
            "solve",
            "--map",
            &map,
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "3000",
            "--surface",
            surface,
        ];
        args.extend(GAUSSIAN);
        args.extend(["--out", s(&out)]);
        ok(&preston(&args));
        std::fs::read(out.join("dwell.csv")).unwrap()
    };
    let plain = write_arg(d.path(), "plane.json", r#"{"type":"plane"}"#);
    let bom = write_arg(d.path(), "plane_bom.json", "\u{feff}{\"type\":\"plane\"}");
    assert_eq!(solve(&bom, "bom"), solve(&plain, "plain"));
}

/// A flag's bad value is blamed on the flag, not on the job whose key it replaces.
#[test]
fn a_bad_raster_pitch_flag_is_named_as_the_flag() {
    let job = data_arg("job.toml");
    for pitch in ["-1", "0", "nan"] {
        let d = tempfile::tempdir().unwrap();
        let o = preston(&[
            "solve",
            "--job",
            &job,
            "--raster-pitch-mm",
            pitch,
            "--out",
            s(&d.path().join("o")),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{pitch}: {err}");
        assert!(err.contains("--raster-pitch-mm"), "{pitch}: {err}");
        assert!(!err.contains("job.toml"), "{pitch}: blames the job: {err}");
        assert!(
            !d.path().join("o").exists(),
            "output written despite the error"
        );
    }
}

/// Largest `|v_{j+1}^2 - v_j^2| / (2 s_j)` over the segments of a written dwell file whose
/// ends do not both turn by more than 60 degrees (the connecting moves), `v = ds / t`, mm/s^2.
fn max_accel_of(dwell_csv: &Path) -> f64 {
    let [x, y, ds, t]: [Vec<f64>; 4] =
        csv_columns(dwell_csv, &["x_mm", "y_mm", "ds_mm", "dwell_s"])
            .try_into()
            .unwrap();
    let n = x.len();
    let turn = |j: usize| -> f64 {
        if j == 0 || j + 1 >= n {
            return 0.0;
        }
        let (ax, ay) = (x[j] - x[j - 1], y[j] - y[j - 1]);
        let (bx, by) = (x[j + 1] - x[j], y[j + 1] - y[j]);
        let (la, lb) = (ax.hypot(ay), bx.hypot(by));
        ((ax * bx + ay * by) / (la * lb))
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    };
    let mut worst: f64 = 0.0;
    for j in 0..n - 1 {
        let seg = (x[j + 1] - x[j]).hypot(y[j + 1] - y[j]);
        if turn(j) > 60.0 && turn(j + 1) > 60.0 {
            continue;
        }
        let (v0, v1) = (ds[j] / t[j], ds[j + 1] / t[j + 1]);
        worst = worst.max((v1 * v1 - v0 * v0).abs() / (2.0 * seg));
    }
    worst
}

/// Relative agreement of an acceleration recomputed from the written dwell with the report's.
const ACCEL_REL: f64 = 1e-9;

/// Serpentine dwell points `x_mm,y_mm` over `[0, side]^2` at `pitch`.
fn raster_text(side: f64, pitch: f64) -> String {
    let k = (side / pitch).round() as usize;
    let mut t = String::from("x_mm,y_mm\n");
    for j in 0..=k {
        for i in 0..=k {
            let i = if j % 2 == 0 { i } else { k - i };
            t.push_str(&format!("{},{}\n", i as f64 * pitch, j as f64 * pitch));
        }
    }
    t
}

/// A job of two tools (a coarse Gaussian on a 1.5 mm raster, a fine one on 0.75 mm) on a
/// 13 x 13 map at 1 mm, written into `dir`; returns the job file.
fn two_tool_job(dir: &Path) -> std::path::PathBuf {
    write(dir, "map.csv", &map_text(13, 1.0));
    write(dir, "coarse.csv", &raster_text(12.0, 1.5));
    write(dir, "fine.csv", &raster_text(12.0, 0.75));
    write(
        dir,
        "tools.toml",
        "[map]\nfile = \"map.csv\"\n[machine]\nv_max_mm_per_min = 4000\n\
         [[tool]]\ndwell = \"coarse.csv\"\ntif = { gaussian = { sigma_mm = 2.0, peak_rate_nm_per_s = 6.0, truncation_radius_mm = 6.0 } }\n\
         [[tool]]\ndwell = \"fine.csv\"\ntif = { gaussian = { sigma_mm = 0.8, peak_rate_nm_per_s = 3.0, truncation_radius_mm = 2.4 } }\n",
    )
}

/// Several tools: the report's largest acceleration is the largest any tool's written feeds
/// ask for, and each tool's own is given.
#[test]
fn a_multi_tool_report_gives_the_largest_acceleration_of_its_tools() {
    let d = tempfile::tempdir().unwrap();
    let job = two_tool_job(d.path());
    let out = d.path().join("out");
    ok(&preston(&["solve", "--job", s(&job), "--out", s(&out)]));
    let r = report(&out);
    let tools = r["tools"].as_array().unwrap();
    assert_eq!(tools.len(), 2);
    let mut largest: f64 = 0.0;
    for (k, tool) in tools.iter().enumerate() {
        let written = max_accel_of(&out.join(format!("dwell_tool{}.csv", k + 1)));
        let reported = tool["max_accel_mm_per_s2"].as_f64().unwrap();
        assert!(
            (reported - written).abs() <= ACCEL_REL * written,
            "tool {}: reported {reported} mm/s^2, its dwell file asks {written}",
            k + 1
        );
        largest = largest.max(written);
    }
    assert!(largest > 0.0);
    let reported = r["max_accel_mm_per_s2"].as_f64().unwrap();
    assert!(
        (reported - largest).abs() <= ACCEL_REL * largest,
        "report.json max_accel_mm_per_s2 {reported}, the tools' dwell files ask {largest}"
    );
}

/// Relative amount by which a dwell may fall short of its lower bound `ds / v_max` (the
/// interior point's tolerance, before the dwell is projected onto its bounds).
const BOUND_REL: f64 = 1e-9;

/// Problems that `t = ds / v_max` makes feasible are never reported infeasible: a map with a
/// single spike a million times its other heights, and a feed limit so low that every point
/// is held at a million seconds or more.
#[test]
fn the_qp_never_calls_a_feasible_problem_infeasible() {
    let d = tempfile::tempdir().unwrap();
    // The smooth map with one point (5, 5) mm raised to 1e6 nm.
    let spiky: String = map_text(11, 1.0)
        .lines()
        .map(|l| {
            if l.starts_with("5,5,") {
                "5,5,1000000".to_string()
            } else {
                l.to_string()
            }
        })
        .map(|l| l + "\n")
        .collect();
    let spike = write_arg(d.path(), "spike.csv", &spiky);
    let smooth = write_arg(d.path(), "smooth.csv", &map_text(11, 1.0));
    let run = |map: &str, v_max: &str, name: &str| {
        let out = d.path().join(name);
        let mut args = vec![
            "solve",
            "--map",
            map,
            "--raster-pitch-mm",
            "1",
            "--solver",
            "qp",
            "--v-max",
            v_max,
        ];
        args.extend(GAUSSIAN);
        args.extend(["--out", s(&out)]);
        let o = preston(&args);
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(!err.contains("infeasible"), "{name}: {err}");
        ok(&o);
        let r = report(&out);
        assert_eq!(r["status"], "converged", "{name}");
        out
    };
    run(&spike, "3000", "spike");
    let out = run(&smooth, "1e-6", "slow");
    // The plan keeps every feed within the limit: each dwell at least `ds / v_max`.
    let [ds, t]: [Vec<f64>; 2] = csv_columns(&out.join("dwell.csv"), &["ds_mm", "dwell_s"])
        .try_into()
        .unwrap();
    for (j, (ds, t)) in ds.iter().zip(&t).enumerate() {
        let bound = ds / (1e-6 / 60.0);
        assert!(
            *t >= bound * (1.0 - BOUND_REL),
            "point {j}: {t} s below the bound {bound} s"
        );
    }
}

/// Feeds from 1 to 3000 mm/min, the program executed at 1000 mm/s², as flags.
const EXECUTED_AT_LIMIT: [&str; 6] = [
    "--v-max",
    "3000",
    "--v-min",
    "1",
    "--a-max-mm-per-s2",
    "1000",
];

/// A robust plan executed at an acceleration limit: its files and page agree with its report.
#[test]
fn a_robust_plans_figures_agree_in_every_file() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &map_text(17, 1.0));
    let out = d.path().join("robust");
    let mut args = vec!["solve", "--map", &map, "--raster-pitch-mm", "1"];
    args.extend(GAUSSIAN);
    args.extend(EXECUTED_AT_LIMIT);
    args.extend(["--robust", "--report", "--out", s(&out)]);
    ok(&preston(&args));
    assert!(report(&out)["robust"].is_object());
    assert_outputs_agree(&out);
}

/// Two tools: the dwell of each tool's file adds up to its own and to the report's total, and
/// the page agrees with the report.
#[test]
fn a_multi_tool_plans_figures_agree_in_every_file() {
    let d = tempfile::tempdir().unwrap();
    let job = two_tool_job(d.path());
    let out = d.path().join("out");
    ok(&preston(&[
        "solve",
        "--job",
        s(&job),
        "--report",
        "--out",
        s(&out),
    ]));
    assert_eq!(report(&out)["tools"].as_array().map(Vec::len), Some(2));
    assert_outputs_agree(&out);
}

/// A clear aperture (a diamond inside the map) executed at an acceleration limit: the files
/// hold the aperture's points and agree with the report and the page.
#[test]
fn an_aperture_plans_figures_agree_in_every_file() {
    let d = tempfile::tempdir().unwrap();
    let map = write_arg(d.path(), "map.csv", &map_text(21, 1.0));
    write(
        d.path(),
        "diamond.csv",
        "x_mm,y_mm\n10,1\n19,10\n10,19\n1,10\n",
    );
    let aperture = format!(
        "--aperture=polygon:{}",
        d.path().join("diamond.csv").display()
    );
    let out = d.path().join("aperture");
    let mut args = vec!["solve", "--map", &map, &aperture, "--raster-pitch-mm", "1"];
    args.extend(GAUSSIAN);
    args.extend(EXECUTED_AT_LIMIT);
    args.extend(["--report", "--out", s(&out)]);
    ok(&preston(&args));
    let r = report(&out);
    let inside = csv_columns(&out.join("residual.csv"), &["x_mm"])[0].len();
    assert!(
        inside < 21 * 21 && inside as u64 == r["m"].as_u64().unwrap(),
        "{inside} residual rows, m = {}",
        r["m"]
    );
    assert_outputs_agree(&out);
}
