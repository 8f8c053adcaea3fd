//! The sample job shipped inside the programs: the job of `data/job.toml` with its map and TIF
//! and the data's licence notice, embedded at build time, so that `preston sample --out DIR` and
//! `preston.sample_job(dir)` give a job that solves without a checkout of the sources.
//!
//! The job names its files relative to itself (a job's relative paths are relative to the job
//! file), so the directory can be moved or copied as a whole.

use crate::atomic;
use crate::error::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The name of the sample's job file in the directory written.
pub const JOB_FILE: &str = "job.toml";

/// The sample's files: name in the directory and content, the job first.
pub const FILES: [(&str, &[u8]); 4] = [
    (JOB_FILE, include_bytes!("../../data/job.toml")),
    (
        "mirror_error_118x8mm.csv",
        include_bytes!("../../data/mirror_error_118x8mm.csv"),
    ),
    (
        "tif_fluid_jet_10mm.csv",
        include_bytes!("../../data/tif_fluid_jet_10mm.csv"),
    ),
    // The map and the TIF are MIT-licensed data of another project: the notice goes with them.
    ("README.md", include_bytes!("../../data/README.md")),
];

/// Writes the sample into `dir` (created with its parents if missing) and returns the path of
/// its job file. The files are staged and renamed into place together, so a failure leaves none
/// of them. Unless `overwrite`, a file of the sample that already exists in `dir` is an
/// [`Error::Exists`] naming it, and nothing is written.
pub fn write_sample(dir: &Path, overwrite: bool) -> Result<PathBuf> {
    if dir.exists() && !dir.is_dir() {
        return Err(Error::Exists {
            file: dir.to_path_buf(),
            why: "the sample needs a directory there".into(),
        });
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    if !overwrite {
        for (name, _) in FILES {
            let path = dir.join(name);
            // `symlink_metadata`: a dangling link is a file too, and is not written through.
            if path.symlink_metadata().is_ok() {
                return Err(Error::Exists {
                    file: path,
                    why: "the sample is written over existing files only when asked \
                          (`preston sample --force`, `preston.sample_job(dir, overwrite=True)`)"
                        .into(),
                });
            }
        }
    }
    let staged = FILES
        .iter()
        .map(|(name, bytes)| atomic::stage(&dir.join(name), |w: &mut dyn Write| w.write_all(bytes)))
        .collect::<Result<Vec<_>>>()?;
    atomic::commit_all(staged)?;
    Ok(dir.join(JOB_FILE))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The files written are the repository's `data/` files byte for byte, and the job read from
    /// the written directory names the written map and TIF.
    #[test]
    fn the_sample_is_the_repository_data_and_its_job_names_its_own_files() {
        let d = tempfile::tempdir().unwrap();
        let dir = d.path().join("new").join("sample");
        let job = write_sample(&dir, false).unwrap();
        assert_eq!(job, dir.join(JOB_FILE));
        let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data");
        for (name, _) in FILES {
            assert_eq!(
                std::fs::read(dir.join(name)).unwrap(),
                std::fs::read(data.join(name)).unwrap(),
                "{name}"
            );
        }
        let text = std::fs::read_to_string(&job).unwrap();
        let parsed: toml::Table = toml::from_str(&text).unwrap();
        for (section, file) in [
            ("map", "mirror_error_118x8mm.csv"),
            ("tif", "tif_fluid_jet_10mm.csv"),
        ] {
            assert_eq!(parsed[section]["file"].as_str(), Some(file), "[{section}]");
            assert!(dir.join(file).is_file());
        }
    }

    /// An existing file of the sample stops the write (nothing is changed) unless overwriting is
    /// asked for; a file in the way of the directory is refused either way.
    #[test]
    fn existing_files_are_written_over_only_when_asked() {
        let d = tempfile::tempdir().unwrap();
        let dir = d.path();
        let map = dir.join("mirror_error_118x8mm.csv");
        std::fs::write(&map, "mine").unwrap();
        let e = write_sample(dir, false).unwrap_err();
        assert!(
            matches!(&e, Error::Exists { file, .. } if *file == map),
            "{e}"
        );
        assert!(e.to_string().contains("--force"), "{e}");
        assert_eq!(std::fs::read_to_string(&map).unwrap(), "mine");
        assert!(!dir.join(JOB_FILE).exists());
        write_sample(dir, true).unwrap();
        assert_eq!(std::fs::read(&map).unwrap(), FILES[1].1);

        let file = dir.join("a_file");
        std::fs::write(&file, "x").unwrap();
        let e = write_sample(&file, true).unwrap_err();
        assert!(matches!(e, Error::Exists { .. }), "{e}");
    }
}
