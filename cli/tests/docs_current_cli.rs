//! The documents say what is true now. No dates or phrases of a measurement's history outside
//! `CHANGELOG.md`: not in `docs/`, the README, `ARCHITECTURE.md`, `data/README.md`, the sample
//! job, the CLI reference generated from every `--help` (`docs/cli.md`), nor the comments and help
//! texts of the sources, tests, benchmarks and scripts. And the figures the README and `docs/report.md` quote for the sample job, and
//! `docs/commands.md` for the undisturbed loop on the shipped freeform, are those the documented
//! commands (`preston solve --job data/job.toml --out DIR`, `preston iterate --surface
//! data/design_freeform.json ...`) give today.

mod common;

use common::{csv_columns, data, preston_cmd};
use std::path::{Path, PathBuf};

/// Month names, as a written-out date would use them ("May" is left out: the verb).
const MONTHS: [&str; 11] = [
    "January",
    "February",
    "March",
    "April",
    "June",
    "July",
    "August",
    "September",
    "October",
    "November",
    "December",
];

/// Phrases that date a measurement or name the host or binary of its day.
const HISTORY_PHRASES: [&str; 6] = [
    "late evening",
    "the afternoon of",
    "the evening of",
    "this machine",
    "this 2-core machine",
    "binary of commit",
];

/// The repository's root.
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every file under `dir` (recursively) whose name ends with one of `exts`.
fn files_under(dir: &Path, exts: &[&str], out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            files_under(&p, exts, out);
        } else if exts.iter().any(|x| p.extension().is_some_and(|e| e == *x)) {
            out.push(p);
        }
    }
}

/// The first ISO date (`20YY-MM-DD`) in `text`.
fn iso_date(text: &str) -> Option<&str> {
    let b = text.as_bytes();
    let digit = |k: usize| b.get(k).is_some_and(u8::is_ascii_digit);
    (0..b.len().saturating_sub(9)).find_map(|k| {
        let shape = b[k] == b'2'
            && b[k + 1] == b'0'
            && digit(k + 2)
            && digit(k + 3)
            && b[k + 4] == b'-'
            && digit(k + 5)
            && digit(k + 6)
            && b[k + 7] == b'-'
            && digit(k + 8)
            && digit(k + 9);
        let alone = (k == 0 || !b[k - 1].is_ascii_digit()) && !digit(k + 10);
        (shape && alone).then(|| &text[k..k + 10])
    })
}

/// The first month name in `text` standing as a word.
fn month(text: &str) -> Option<&'static str> {
    let word = |c: Option<char>| c.is_some_and(char::is_alphanumeric);
    MONTHS.into_iter().find(|m| {
        text.match_indices(m).any(|(k, _)| {
            !word(text[..k].chars().next_back()) && !word(text[k + m.len()..].chars().next())
        })
    })
}

/// What dates `text`, if anything.
fn dating(text: &str) -> Option<String> {
    if let Some(d) = iso_date(text) {
        return Some(format!("the date {d}"));
    }
    if let Some(m) = month(text) {
        return Some(format!("the month name {m}"));
    }
    let lower = text.to_lowercase();
    HISTORY_PHRASES
        .into_iter()
        .find(|p| lower.contains(p))
        .map(|p| format!("\"{p}\""))
}

#[test]
fn the_date_finder_finds_dates_and_only_dates() {
    assert_eq!(
        dating("measured 2026-11-27, evening"),
        Some("the date 2026-11-27".into())
    );
    assert_eq!(
        dating("on 27 November"),
        Some("the month name November".into())
    );
    assert!(dating("the binary of commit 47d6740").is_some());
    assert!(dating("Late evening runs").is_some());
    // Numbers, ranges and words that merely contain a month are not dates.
    for plain in [
        "12026-11-270",
        "2026-11",
        "load 1.5-2, 20 x 30 mm",
        "Marches on",
        "the sample job",
    ] {
        assert_eq!(dating(plain), None, "{plain}");
    }
}

/// The docs, the help texts (`docs/cli.md` is generated from them, and the sources that hold
/// them) and the sources' comments carry no date: the history is in `CHANGELOG.md`.
#[test]
fn no_dates_outside_the_changelog() {
    let r = root();
    let mut files = vec![
        r.join("README.md"),
        r.join("ARCHITECTURE.md"),
        r.join("data/README.md"),
    ];
    files_under(&r.join("docs"), &["md", "py"], &mut files);
    for dir in [
        "cli/src",
        "cli/tests",
        "io/src",
        "io/tests",
        "solver/src",
        "python/src",
        "python/preston",
        "python/tests",
        "tests",
        "benches",
        "scripts",
    ] {
        files_under(&r.join(dir), &["rs", "py", "sh"], &mut files);
    }
    // This file names what it looks for.
    files.retain(|f| !f.ends_with("cli/tests/docs_current_cli.rs"));
    files.push(r.join("data/job.toml"));
    assert!(files.len() > 50, "{} files", files.len());
    assert!(files.iter().any(|f| f.ends_with("docs/cli.md")));
    let mut found = Vec::new();
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        for (n, line) in text.lines().enumerate() {
            if let Some(what) = dating(line) {
                found.push(format!("{}:{}: {what}", f.display(), n + 1));
            }
        }
    }
    assert!(
        found.is_empty(),
        "history outside CHANGELOG.md:\n{}",
        found.join("\n")
    );
    assert!(r.join("CHANGELOG.md").is_file());
}

/// `n` with a comma between thousands (`27,542`), as the docs write whole numbers.
fn thousands(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (k, c) in digits.chars().enumerate() {
        if k > 0 && (digits.len() - k).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// `text` with every run of white space (line breaks of wrapped prose included) as one space.
fn one_line(text: &str) -> String {
    text.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// The sample job's figures quoted in the README and `docs/report.md` are today's.
#[test]
fn the_sample_figures_the_docs_quote_are_current() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["solve", "--job"])
        .arg(data("job.toml"))
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = common::report(out.path());
    let f = |k: &str| {
        r.pointer(&format!("/{}", k.replace('.', "/")))
            .and_then(serde_json::Value::as_f64)
            .unwrap_or_else(|| panic!("{k} not in report.json"))
    };
    let readme = one_line(&std::fs::read_to_string(root().join("README.md")).unwrap());
    let report_doc = one_line(&std::fs::read_to_string(root().join("docs/report.md")).unwrap());
    let printed = String::from_utf8_lossy(&o.stderr).to_string();
    // Figures below 0.1 nm to the decimals the executed removal's integration resolves.
    let resolution: preston_solver::setup::IntegrationResolution =
        serde_json::from_value(r["executed"]["integration"].clone())
            .expect("report.json executed.integration");
    let fig = |v: f64| {
        if v < 0.1 {
            format!("{v:.*}", resolution.decimals())
        } else {
            format!("{v:.3}")
        }
    };
    let headline = format!(
        "RMS {:.3} -> {} nm, PV {:.3} -> {} nm as the program executes (model {:.3} nm RMS, {:.3} nm PV), piston {:.3} nm",
        f("rms_before_nm"),
        fig(f("rms_after_nm")),
        f("pv_before_nm"),
        fig(f("pv_after_nm")),
        f("model.rms_nm"),
        f("model.pv_nm"),
        f("piston_nm")
    );
    assert!(
        printed.contains(&headline),
        "the binary no longer prints the headline the README quotes: {printed}"
    );
    let dwell = csv_columns(&out.path().join("dwell.csv"), &["dwell_s"]).remove(0);
    let (dwell_min, dwell_max) = dwell
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &d| (a.min(d), b.max(d)));
    let t = f("machining_time_s");
    for (doc, name, quote) in [
        (&readme, "README.md", headline.clone()),
        (
            &readme,
            "README.md",
            format!(
                "{} nm RMS and {:.2} nm PV from {:.0} nm in {:.1} hours of dwell",
                fig(f("rms_after_nm")),
                f("pv_after_nm"),
                f("rms_before_nm"),
                f("total_dwell_s") / 3600.0
            ),
        ),
        (
            &report_doc,
            "docs/report.md",
            format!(
                "({} s: `{}`",
                thousands(t.round() as u64),
                preston_io::html::hours_minutes(t)
            ),
        ),
        (
            &report_doc,
            "docs/report.md",
            format!(
                "the sample's feeds span {:.1} to {:.0} mm/min and its dwell {:.4} to {:.1} s",
                f("min_feed_mm_per_min"),
                f("max_feed_mm_per_min"),
                dwell_min,
                dwell_max
            ),
        ),
    ] {
        assert!(
            doc.contains(&quote),
            "{name} does not quote today's figures: `{quote}`"
        );
    }
}

/// The undisturbed loop on the shipped freeform that `docs/commands.md` quotes (`preston iterate
/// --surface data/design_freeform.json --gaussian-sigma-mm 2.5 --gaussian-peak-nm-per-s 10`): the
/// measured RMS of each run, the first run's prediction, its dwell and the floor it stops at.
#[test]
fn the_undisturbed_loop_docs_commands_quotes_is_current() {
    let out = tempfile::tempdir().unwrap();
    let o = preston_cmd()
        .args(["iterate", "--surface"])
        .arg(data("design_freeform.json"))
        .args([
            "--gaussian-sigma-mm",
            "2.5",
            "--gaussian-peak-nm-per-s",
            "10",
            "--out",
        ])
        .arg(out.path())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // convergence.csv: one row per measurement, empty cells where a figure does not apply.
    let text = std::fs::read_to_string(out.path().join("convergence.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    let col = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .unwrap_or_else(|| panic!("convergence.csv has no column {name}: {header:?}"))
    };
    let cell = |row: usize, name: &str| -> f64 {
        rows[row][col(name)]
            .parse()
            .unwrap_or_else(|_| panic!("row {row} has no {name}"))
    };
    assert_eq!(rows.len(), 2, "the doc quotes one run: {text}");
    let doc = one_line(&std::fs::read_to_string(root().join("docs/commands.md")).unwrap());
    for quote in [
        format!(
            "measured RMS {:.3} then {:.3} nm against a prediction of {:.3} nm",
            cell(0, "rms_nm"),
            cell(1, "rms_nm"),
            cell(0, "predicted_rms_nm")
        ),
        format!("dwell {} s", thousands(cell(0, "time_s").round() as u64)),
        format!(
            "floor {:.3} nm outside the TIF's correctable band",
            cell(1, "uncorrectable_rms_nm")
        ),
    ] {
        assert!(
            doc.contains(&quote),
            "docs/commands.md does not quote today's loop: `{quote}`"
        );
    }
}

/// Every source path the architecture notes, the README and the docs name (a backticked
/// `solver/...`, `io/...`, `cli/...` or `python/...`) exists: a moved file is followed in the docs.
#[test]
fn every_source_path_the_docs_name_exists() {
    let r = root();
    let mut files = vec![r.join("README.md"), r.join("ARCHITECTURE.md")];
    files_under(&r.join("docs"), &["md"], &mut files);
    let mut missing = Vec::new();
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for quoted in text.split('`').skip(1).step_by(2) {
            let is_path = ["solver/", "io/", "cli/", "python/"]
                .iter()
                .any(|p| quoted.starts_with(p))
                && quoted
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "_/.-".contains(c));
            if is_path && !r.join(quoted).exists() {
                missing.push(format!("{}: {quoted}", file.display()));
            }
        }
    }
    assert!(missing.is_empty(), "paths that do not exist: {missing:#?}");
}
