//! `preston sample`: writes the sample job (the job of the repository's `data/job.toml`, its map
//! and TIF, and the data's licence notice, all embedded in the program) into a directory, so
//! that a user without a checkout of the sources has a job to solve.

use std::path::PathBuf;

/// Arguments of `preston sample`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Directory to write the sample into (created if missing): job.toml, the map and TIF CSVs
    /// it names (relative to itself) and README.md.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Write over the sample's files where they already exist in DIR (without it an existing
    /// file is an error and nothing is written).
    #[arg(long)]
    pub force: bool,
}

/// Writes the sample; prints the job file's path on stdout and how to solve it on stderr.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let job = preston_io::sample::write_sample(&args.out, args.force)?;
    crate::outln!("{}", job.display());
    crate::errln!(
        "wrote the sample job to {} (solve it: preston solve --job {} --out out/sample --report)",
        args.out.display(),
        job.display()
    );
    Ok(crate::EXIT_OK)
}
