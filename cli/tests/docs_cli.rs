//! The reference documents are current: every key `report.json` carries for the sample job (a
//! solve, and the program it writes simulated as written) is described in `docs/formats.md`, and
//! every subcommand the binary has is in the README's command table; the install instructions
//! install the wheel the build writes, whatever the order of its platform tags.

mod common;

use common::{data_arg, ok, preston};
use std::collections::BTreeSet;
use std::path::Path;

/// Every key of a JSON object as a dotted path (`executed.rms_after_nm`); arrays are leaves.
fn key_paths(value: &serde_json::Value, prefix: &str, out: &mut BTreeSet<String>) {
    if let serde_json::Value::Object(map) = value {
        for (k, v) in map {
            let path = if prefix.is_empty() {
                k.clone()
            } else {
                format!("{prefix}.{k}")
            };
            key_paths(v, &path, out);
            out.insert(path);
        }
    }
}

fn repo_file(name: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Keys of `report.json` that `docs/formats.md` does not name in backticks.
fn undocumented(report: &serde_json::Value, doc: &str) -> Vec<String> {
    let mut keys = BTreeSet::new();
    key_paths(report, "", &mut keys);
    keys.into_iter()
        .filter(|k| !doc.contains(&format!("`{k}`")))
        .collect()
}

#[test]
fn every_report_key_of_the_sample_job_is_in_the_formats_reference() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sample");
    let job = data_arg("job_point_1mm.toml");
    ok(&preston(&[
        "solve",
        "--job",
        &job,
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]));
    let program = dir.path().join("prog.nc");
    ok(&preston(&[
        "nc",
        "--dwell",
        out.join("dwell.csv").to_str().unwrap(),
        "--job",
        &job,
        "--out",
        program.to_str().unwrap(),
        "--quiet",
    ]));
    let sim = dir.path().join("sim");
    ok(&preston(&[
        "simulate",
        "--job",
        &job,
        "--program",
        program.to_str().unwrap(),
        "--out",
        sim.to_str().unwrap(),
        "--quiet",
    ]));
    let doc = repo_file("docs/formats.md");
    for dir in [&out, &sim] {
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("report.json")).unwrap())
                .unwrap();
        let missing = undocumented(&report, &doc);
        assert!(
            missing.is_empty(),
            "{}: report.json keys not described in docs/formats.md: {missing:?}",
            dir.display()
        );
    }
}

#[test]
fn the_readme_command_table_names_every_subcommand() {
    let help = preston(&["--help"]);
    let text = String::from_utf8_lossy(&help.stdout).to_string();
    let readme = repo_file("README.md");
    let commands: Vec<&str> = text
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next())
        .filter(|c| *c != "help")
        .collect();
    assert!(commands.len() >= 10, "parsed {commands:?} from --help");
    for c in commands {
        assert!(
            readme.contains(&format!("| `preston {c}` |")),
            "README's command table lacks `preston {c}`"
        );
    }
}

/// Whether `name` matches the shell glob `pattern` (`*` any run of characters, no other
/// metacharacters).
fn glob_matches(pattern: &str, name: &str) -> bool {
    let parts: Vec<&str> = pattern.split('*').collect();
    let (first, last) = (parts[0], parts[parts.len() - 1]);
    if parts.len() == 1 {
        return pattern == name;
    }
    if !name.starts_with(first) || !name[first.len()..].ends_with(last) {
        return false;
    }
    let mut rest = &name[first.len()..name.len() - last.len()];
    for p in &parts[1..parts.len() - 1] {
        match rest.find(p) {
            Some(at) => rest = &rest[at + p.len()..],
            None => return false,
        }
    }
    true
}

#[test]
fn the_install_instructions_install_the_wheel_the_build_writes() {
    // maturin 1.9 names the manylinux2014 wheel with this tag order; other versions the reverse.
    let built = [
        "preston_dwell-0.1.0-cp39-abi3-manylinux2014_x86_64.manylinux_2_17_x86_64.whl",
        "preston_dwell-0.1.0-cp39-abi3-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
    ];
    assert!(glob_matches("a*c", "abbc") && !glob_matches("a*c", "abcd"));
    for doc in ["docs/install.md", "README.md"] {
        let text = repo_file(doc);
        let wheels: Vec<&str> = text
            .lines()
            .filter_map(|l| l.split("pip install").nth(1))
            .flat_map(|rest| rest.split(|c: char| c.is_whitespace() || c == '`'))
            .filter(|w| w.ends_with(".whl"))
            .collect();
        assert!(!wheels.is_empty(), "{doc} installs no wheel");
        for w in wheels {
            let file = w.rsplit('/').next().unwrap_or(w);
            for b in built {
                assert!(glob_matches(file, b), "{doc}: '{w}' does not match {b}");
            }
        }
    }
    let install = repo_file("docs/install.md");
    for needed in ["Rust 1.89", "crates.io", "PyPI"] {
        assert!(
            install.contains(needed),
            "docs/install.md does not say it needs {needed}"
        );
    }
    // The wheel check compares versions without building the command line again.
    let script = repo_file("scripts/build-wheels.sh");
    assert!(
        !script
            .lines()
            .any(|l| l.trim_start().starts_with("cargo build")),
        "scripts/build-wheels.sh builds the command line"
    );
}
