//! The `preston` binary: the command line of [`preston_cli::run_from_args`].

fn main() -> std::process::ExitCode {
    std::process::ExitCode::from(preston_cli::run_from_args(std::env::args_os()))
}
