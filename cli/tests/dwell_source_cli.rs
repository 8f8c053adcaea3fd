//! "A dwell file or a raster, not both": the command line's flags, a job file and several tools
//! each refuse the pair with the one message of `preston_io::job::DWELL_FILE_OR_RASTER` (exit 2,
//! nothing written); the Python faces are checked against the same message in
//! `python/tests/test_dwell_source.py`.

mod common;
use common::*;
use preston_io::job::DWELL_FILE_OR_RASTER;

/// Two dwell points along x, mm.
const DWELL_CSV: &str = "x_mm,y_mm\n0,0\n1,0\n";

#[test]
fn a_dwell_file_and_a_raster_on_the_command_line_are_refused_with_the_one_message() {
    let d = tempfile::tempdir().unwrap();
    let dwell = write_arg(d.path(), "d.csv", DWELL_CSV);
    let job = data_arg("job.toml");
    expect_failure(
        &["--job", &job, "--dwell", &dwell, "--raster-pitch-mm", "1.0"],
        &[DWELL_FILE_OR_RASTER],
    );
}

#[test]
fn a_dwell_file_and_a_raster_in_a_job_file_are_refused_with_the_one_message() {
    let d = tempfile::tempdir().unwrap();
    write(d.path(), "d.csv", DWELL_CSV);
    let text = std::fs::read_to_string(data("job.toml")).unwrap();
    let data_dir = data("job.toml").parent().unwrap().to_path_buf();
    let text = text
        .replace(
            "file = \"mirror_error_118x8mm.csv\"",
            &format!("file = {:?}", data_dir.join("mirror_error_118x8mm.csv")),
        )
        .replace(
            "file = \"tif_fluid_jet_10mm.csv\"",
            &format!("file = {:?}", data_dir.join("tif_fluid_jet_10mm.csv")),
        )
        .replace(
            "raster_pitch_mm = 0.32",
            "raster_pitch_mm = 0.32\nfile = \"d.csv\"",
        );
    assert!(
        text.contains("file = \"d.csv\""),
        "the sample job changed: {text}"
    );
    let job = write_arg(d.path(), "both.toml", &text);
    expect_failure(&["--job", &job], &[DWELL_FILE_OR_RASTER, "both.toml"]);
}

#[test]
fn a_raster_with_several_tools_is_refused_with_the_one_message() {
    let d = tempfile::tempdir().unwrap();
    let dwell = write_arg(d.path(), "d.csv", DWELL_CSV);
    let tif = data_arg("tif_fluid_jet_10mm.csv");
    let map = data_arg("mirror_error_118x8mm.csv");
    expect_failure(
        &[
            "--map",
            &map,
            "--tif",
            &tif,
            "--dwell",
            &dwell,
            "--tif",
            &tif,
            "--dwell",
            &dwell,
            "--raster-pitch-mm",
            "1.0",
            "--v-max",
            "3000",
        ],
        &[DWELL_FILE_OR_RASTER],
    );
}

#[test]
fn either_source_alone_is_taken() {
    // The rule refuses only the pair: a raster pitch alone replaces the job's file and a file
    // alone the job's raster, each read back from the job as the overrides leave it.
    use preston_io::job::{DwellSource, Job};
    use preston_io::overrides::Overrides;
    use std::path::Path;
    let mut job = Job::default();
    job.dwell.source = DwellSource::File("d.csv".into());
    let raster = Overrides {
        raster_pitch_mm: Some(0.5),
        ..Overrides::default()
    };
    raster.apply(&mut job, Path::new("<test>")).unwrap();
    assert_eq!(job.dwell.source, DwellSource::Raster { pitch_mm: 0.5 });
    let file = Overrides {
        dwell: Some("e.csv".into()),
        ..Overrides::default()
    };
    file.apply(&mut job, Path::new("<test>")).unwrap();
    assert_eq!(job.dwell.source, DwellSource::File("e.csv".into()));
    assert_eq!(
        DwellSource::of(Some("f.csv".into()), Some(1.0)),
        Err(DWELL_FILE_OR_RASTER)
    );
}
