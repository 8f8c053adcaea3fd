//! `preston`: dwell-time computation for deterministic sub-aperture polishing.
//!
//! The command line as a library: [`run_from_args`] is the whole program, called by the
//! `preston` binary (`src/main.rs`) and by the Python package's `preston` console script, so
//! that both run the same code. Each subcommand lives in `cmd/<name>.rs`, parses its arguments
//! with clap, converts them into library settings and calls the library.

mod cmd;
/// Printing that survives a closed stdout or stderr (`outln!`, `errln!`).
mod pipe_safe_print;
mod progress;
/// `--quiet` and `--json`: how the summary of `solve`, `simulate`, `nc` is printed.
mod summary_output;

use clap::{Parser, Subcommand};

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

// Parsed once per run: the size of the largest variant does not matter.
#[allow(clippy::large_enum_variant)]
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
    /// Simulate the removal of a dwell program (the solver's swept model by default, discrete
    /// dwell or continuous motion) or of a G-code program.
    Simulate(cmd::simulate::Args),
    /// Measured maps: convert any format to CSV, remove form terms, fit Zernike/Legendre.
    Map(cmd::map::Args),
    /// The measure-register-solve-polish loop on a virtual part, or one run on a measured map.
    Iterate(cmd::iterate::Args),
    /// Learn the tool that actually ran from the maps before and after a run and its program.
    Calibrate(cmd::calibrate::Args),
    /// A virtual shop: run a program with a tool unlike its spot test, measure like an
    /// interferometer.
    Shop(cmd::shop::Args),
    /// Write the sample job (a mirror's error map, a measured TIF) into a directory.
    Sample(cmd::sample::Args),
    /// Shell completions for bash, zsh, fish or PowerShell, on stdout.
    Completions(CompletionsArgs),
}

/// Arguments of `preston completions`.
#[derive(Debug, clap::Args)]
struct CompletionsArgs {
    /// The shell.
    #[arg(value_enum)]
    shell: ShellArg,
}

/// Shells with completions.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum ShellArg {
    /// bash (`preston completions bash > /etc/bash_completion.d/preston`).
    Bash,
    /// zsh (`preston completions zsh > "${fpath[1]}/_preston"`).
    Zsh,
    /// fish (`preston completions fish > ~/.config/fish/completions/preston.fish`).
    Fish,
    /// PowerShell (`preston completions powershell >> $PROFILE`).
    Powershell,
}

/// Writes the completions of the whole command tree for `shell` on stdout.
fn completions(args: CompletionsArgs) -> anyhow::Result<u8> {
    use clap_complete::Shell;
    let shell = match args.shell {
        ShellArg::Bash => Shell::Bash,
        ShellArg::Zsh => Shell::Zsh,
        ShellArg::Fish => Shell::Fish,
        ShellArg::Powershell => Shell::PowerShell,
    };
    let mut buf = Vec::new();
    clap_complete::generate(shell, &mut command_tree(), "preston", &mut buf);
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    out.write_all(&buf)?;
    out.flush()?;
    Ok(crate::EXIT_OK)
}

/// Exit code of a run that succeeded.
pub const EXIT_OK: u8 = 0;
/// Exit code of bad input: an unusable argument, file or setting (the message says which).
pub const EXIT_BAD_INPUT: u8 = 2;
/// Exit code of a run whose iterative step did not converge (the outputs are written).
pub const EXIT_NOT_CONVERGED: u8 = cmd::EXIT_NOT_CONVERGED;

/// Runs the command line on `args` (the program name first, as `std::env::args_os` gives it)
/// and returns the process's exit code: [`EXIT_OK`], [`EXIT_BAD_INPUT`] or
/// [`EXIT_NOT_CONVERGED`] (clap's own code for `--help`, `--version` and usage errors: 0 and
/// 2). Messages go to stdout and stderr as the binary prints them; a closed pipe ends printing
/// and is not an error. Never exits the process itself.
pub fn run_from_args<I, T>(args: I) -> u8
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    use clap::FromArgMatches;
    let parsed = command_tree()
        .try_get_matches_from(args)
        .and_then(|m| Cli::from_arg_matches(&m));
    let cli = match parsed {
        Ok(cli) => cli,
        Err(e) => {
            // Help and version on stdout, usage errors on stderr; a closed pipe is not an error.
            let _ = e.print();
            return u8::try_from(e.exit_code()).unwrap_or(EXIT_BAD_INPUT);
        }
    };
    let code = run(cli);
    // The caller may not be a Rust `main` that flushes stdout on return (the Python console
    // script exits through the interpreter).
    use std::io::Write;
    let _ = std::io::stdout().lock().flush();
    code
}

/// Runs the parsed command line.
fn run(cli: Cli) -> u8 {
    if let Err(e) = apply_limits(&cli) {
        crate::errln!("error: {}", message(&e));
        return EXIT_BAD_INPUT;
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
        Command::Calibrate(args) => cmd::calibrate::run(args),
        Command::Shop(args) => cmd::shop::run(args),
        Command::Map(args) => cmd::map::run(args),
        Command::Bench(args) => cmd::bench::run(args),
        Command::Sample(args) => cmd::sample::run(args),
        Command::Completions(args) => completions(args),
    };
    print_debug_counts();
    match result {
        Ok(code) => code,
        Err(e) => {
            if is_broken_pipe(&e) {
                return EXIT_OK;
            }
            crate::errln!("error: {}", message(&e));
            EXIT_BAD_INPUT
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
    crate::errln!("debug counts: {}", counts.join(" "));
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
    /// `docs/cli.md` is the command-line reference generated from this definition (every
    /// subcommand, flag, default and help text); it must equal what the definition generates
    /// now. Regenerate with `PRESTON_UPDATE_DOCS=1 cargo test -p preston-cli cli_reference`.
    #[test]
    fn cli_reference_in_docs_is_current() {
        let generated = format!(
            "<!-- Generated from the clap definition by `PRESTON_UPDATE_DOCS=1 cargo test -p preston-cli cli_reference`; do not edit. -->\n\n{}",
            clap_markdown::help_markdown_command(&super::command_tree())
        );
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/cli.md");
        if std::env::var_os("PRESTON_UPDATE_DOCS").is_some() {
            std::fs::write(&path, &generated).unwrap();
        }
        let committed = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            committed == generated,
            "docs/cli.md is not the reference the CLI definition generates; run \
             PRESTON_UPDATE_DOCS=1 cargo test -p preston-cli cli_reference"
        );
    }

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

    /// The help text of `--flag` of `preston <sub>`, with its default where clap shows one.
    fn help_of(sub: &str, flag: &str) -> String {
        let tree = super::command_tree();
        let cmd = tree
            .find_subcommand(sub)
            .unwrap_or_else(|| panic!("no subcommand {sub}"));
        let arg = cmd
            .get_arguments()
            .find(|a| a.get_long() == Some(flag))
            .unwrap_or_else(|| panic!("preston {sub} has no --{flag}"));
        let help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
        let defaults: Vec<String> = arg
            .get_default_values()
            .iter()
            .map(|v| v.to_string_lossy().into_owned())
            .collect();
        format!("{help} [default: {}]", defaults.join(","))
    }

    /// The kebab-case name a choice has in job files and on the command line.
    fn name_of<T: serde::Serialize>(value: T) -> String {
        match serde_json::to_value(value) {
            Ok(serde_json::Value::String(s)) => s,
            other => panic!("not a unit enum: {other:?}"),
        }
    }

    fn assert_says(sub: &str, flag: &str, expected: &str) {
        let help = help_of(sub, flag);
        assert!(
            help.contains(expected),
            "preston {sub} --{flag}: help {help:?} does not say {expected:?}"
        );
    }

    /// Every default the help states agrees with the library's `Default` value: the defaults
    /// written as prose (options whose absence means the job's value) are read back from the
    /// help text, those clap shows are derived from the library's `Default` impls.
    #[test]
    fn help_states_the_library_defaults() {
        use preston_solver::dwell::accel::{AccelLimits, AccelMethod};
        use preston_solver::dwell::{
            FirstOrderMethod, OperatorChoice, Settings, SolverChoice, DEFAULT_LBFGS_MEMORY,
            DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS,
        };
        use preston_solver::edge::EdgeMethod;
        use preston_solver::machine::nc::NcSettings;
        let s = Settings::default();
        assert_says(
            "solve",
            "edge",
            &format!("else {})", name_of(EdgeMethod::default())),
        );
        assert_says(
            "solve",
            "accel-method",
            &format!("{} (default;", name_of(AccelMethod::default())),
        );
        let corner = AccelLimits::default().corner_angle_deg;
        assert_says("solve", "corner-angle-deg", &format!("(default {corner})"));
        assert_says(
            "solve",
            "min-time-tolerance",
            &format!("(default {})", s.min_time_tolerance),
        );
        assert_says(
            "solve",
            "tolerance",
            &format!(
                "defaults {:e} and {:e}",
                s.tolerance, s.first_order_tolerance
            ),
        );
        assert_says(
            "solve",
            "first-order-method",
            &format!("else {})", name_of(FirstOrderMethod::default())),
        );
        assert_says(
            "solve",
            "lbfgs-memory",
            &format!("else {DEFAULT_LBFGS_MEMORY}, or {DEFAULT_LBFGS_MEMORY_CHEAP_PRODUCTS}"),
        );
        assert_says(
            "solve",
            "solver",
            &format!("else {})", name_of(SolverChoice::default())),
        );
        assert_says(
            "solve",
            "operator",
            &format!("else {})", name_of(OperatorChoice::default())),
        );
        assert_says(
            "solve",
            "spread-tolerance",
            &format!("else {:e})", s.spread_tolerance),
        );
        let nc = NcSettings::default();
        // Options a machine profile can set state its default in prose: the profile's, else
        // the library's.
        let profile = preston_solver::machine::profile::MachineProfile::default();
        assert_says(
            "nc",
            "corner-angle-deg",
            &format!("(default {})", nc.corner_angle_deg),
        );
        assert_says(
            "nc",
            "clearance-mm",
            &format!("else {})", profile.clearance_mm),
        );
        assert_says(
            "nc",
            "plunge-feed-mm-per-min",
            &format!("else {})", profile.plunge_feed_mm_per_min),
        );
        assert_says(
            "nc",
            "min-block-time-ms",
            &format!("else {})", profile.min_block_time_ms),
        );
        // Each flag's text is its own: the point list's text is not on --arcs.
        assert_says("nc", "arcs", "G02/G03");
        assert!(!help_of("nc", "arcs").contains("Point list"));
        assert_says("nc", "points-out", "Point list");
    }
}
