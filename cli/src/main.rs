//! `preston`: dwell-time computation for deterministic sub-aperture polishing.
//!
//! A thin binary: each subcommand lives in `cmd/<name>.rs`, parses its arguments with clap,
//! converts them into library settings and calls the library.

mod cmd;
mod progress;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Dwell-time computation for deterministic sub-aperture polishing of optics.
#[derive(Debug, Parser)]
#[command(name = "preston", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Memory budget, GB (10^9 bytes): sizes implied by arguments and file headers are checked
    /// against it before anything is allocated [default: 8 GiB = 8.59 GB, or half the physical
    /// memory where less].
    #[arg(long, global = true, value_name = "GB")]
    max_memory_gb: Option<f64>,
    /// Longest line a text input may have, bytes [default: 1048576].
    #[arg(long, global = true, value_name = "BYTES")]
    max_line_bytes: Option<u64>,
    /// Most fields a line of a delimited text input may have [default: 1000].
    #[arg(long, global = true, value_name = "N")]
    max_fields: Option<u64>,
}

/// The command tree with negative numbers accepted as values of every option that takes one
/// (`--rho -1` reaches the option's own validation instead of being taken for a flag).
fn command_tree() -> clap::Command {
    fn negatives(cmd: clap::Command) -> clap::Command {
        cmd.mut_args(|a| {
            if a.get_action().takes_values() {
                a.allow_negative_numbers(true)
            } else {
                a
            }
        })
        .mut_subcommands(negatives)
    }
    use clap::CommandFactory;
    negatives(Cli::command())
}

/// Applies the global limits; an unusable value is an error naming the flag.
fn apply_limits(cli: &Cli) -> anyhow::Result<()> {
    if let Some(gb) = cli.max_memory_gb {
        if !(gb.is_finite() && gb > 0.0 && gb <= 1e6) {
            anyhow::bail!("--max-memory-gb: must be a positive number of GB, got {gb}");
        }
        preston_solver::budget::set_limit_bytes((gb * 1e9) as u64);
    }
    for (flag, v, set) in [
        (
            "--max-line-bytes",
            cli.max_line_bytes,
            preston_io::limits::set_max_line_bytes as fn(u64),
        ),
        (
            "--max-fields",
            cli.max_fields,
            preston_io::limits::set_max_fields as fn(u64),
        ),
    ] {
        match v {
            Some(0) => anyhow::bail!("{flag}: must be at least 1"),
            Some(n) => set(n),
            None => {}
        }
    }
    Ok(())
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Compute dwell times and feeds for a map, a TIF and a dwell path.
    Solve(Box<cmd::solve::Args>),
    /// Fit an XY-polynomial surface to measured points (x_mm,y_mm,z_mm).
    Fit(cmd::fit::Args),
    /// Register measured points to a design surface (ICP): transform and form error map.
    Register(cmd::register::Args),
    /// Solve generated problems and the sample job with each solver; print a table.
    Bench(cmd::bench::Args),
    /// Evaluate a surface (sag, normal, principal curvatures) on a grid or at points.
    Surface(cmd::surface::Args),
    /// Write G-code and a point list for CAM from a solved dwell file.
    Nc(cmd::nc::Args),
    /// Write the NC program of a rotationally symmetric asphere (rotating workpiece).
    Asphere(cmd::asphere::Args),
    /// Tool influence functions: Hertzian sphere, bonnet, Gaussian, measured grid.
    Tif(cmd::tif::Args),
    /// Tool paths: raster, intersection, spiral, chord-height, edge-offset.
    Path(cmd::path::Args),
    /// Simulate the removal of a dwell program (discrete dwell or continuous motion).
    Simulate(cmd::simulate::Args),
    /// Measured maps: convert any format to CSV, remove form terms, fit Zernike/Legendre.
    Map(cmd::map::Args),
    /// The measure-register-solve-polish loop on a virtual part, or one run on a measured map.
    Iterate(cmd::iterate::Args),
}

fn main() -> ExitCode {
    use clap::FromArgMatches;
    let cli = match Cli::from_arg_matches(&command_tree().get_matches()) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    if let Err(e) = apply_limits(&cli) {
        eprintln!("error: {}", message(&e));
        return ExitCode::from(2);
    }
    let result = match cli.command {
        Command::Solve(args) => cmd::solve::run(*args),
        Command::Fit(args) => cmd::fit::run(args),
        Command::Register(args) => cmd::register::run(args),
        Command::Surface(args) => cmd::surface::run(args),
        Command::Nc(args) => cmd::nc::run(args),
        Command::Asphere(args) => cmd::asphere::run(args),
        Command::Tif(args) => cmd::tif::run(args),
        Command::Path(args) => cmd::path::run(args),
        Command::Simulate(args) => cmd::simulate::run(args),
        Command::Iterate(args) => cmd::iterate::run(args),
        Command::Map(args) => cmd::map::run(args),
        Command::Bench(args) => cmd::bench::run(args),
    };
    print_debug_counts();
    match result {
        Ok(code) => code,
        Err(e) => {
            if is_broken_pipe(&e) {
                return ExitCode::SUCCESS;
            }
            eprintln!("error: {}", message(&e));
            ExitCode::from(2)
        }
    }
}

/// The error and its causes, each cause once: library errors already quote their source in their
/// own message (`file: why`), so a cause whose text is already shown is not repeated.
fn message(e: &anyhow::Error) -> String {
    let mut text = e.to_string();
    for cause in e.chain().skip(1) {
        let c = cause.to_string();
        if !text.contains(&c) {
            text.push_str(": ");
            text.push_str(&c);
        }
    }
    text
}

/// With `PRESTON_DEBUG_COUNTS` set: how often this run read a job file and validated its
/// settings (`preston_solver::counts`), one line on stderr.
fn print_debug_counts() {
    if std::env::var_os("PRESTON_DEBUG_COUNTS").is_none() {
        return;
    }
    let counts: Vec<String> = preston_solver::counts::counts()
        .iter()
        .map(|(c, n)| format!("{}={n}", c.name()))
        .collect();
    eprintln!("debug counts: {}", counts.join(" "));
}

/// A closed pipe (for example `preston ... | head`) is not an error.
fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::BrokenPipe)
    })
}

#[cfg(test)]
mod tests {
    /// Every subcommand's flags are distinct and well formed (clap's own consistency checks,
    /// run for the whole command tree, including the shared map-input flags).
    #[test]
    fn the_command_line_definition_is_consistent() {
        super::command_tree().debug_assert();
    }

    /// Every option that takes a value, on every subcommand at every depth, accepts a negative
    /// number as its value, so that `--rho -1` reaches the option's own validation.
    #[test]
    fn every_valued_option_accepts_negative_numbers() {
        fn walk(cmd: &clap::Command, path: &str, checked: &mut usize) {
            for a in cmd.get_arguments() {
                if a.get_action().takes_values() {
                    assert!(a.is_allow_negative_numbers_set(), "{path} --{}", a.get_id());
                    *checked += 1;
                }
            }
            for sub in cmd.get_subcommands() {
                walk(sub, &format!("{path} {}", sub.get_name()), checked);
            }
        }
        let mut checked = 0;
        walk(&super::command_tree(), "preston", &mut checked);
        assert!(checked > 100, "only {checked} options seen");
    }
}
