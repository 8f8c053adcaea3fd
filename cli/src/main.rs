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
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Compute dwell times and feeds for a map, a TIF and a dwell path.
    Solve(cmd::solve::Args),
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
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Solve(args) => cmd::solve::run(args),
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
        use clap::CommandFactory;
        super::Cli::command().debug_assert();
    }
}
