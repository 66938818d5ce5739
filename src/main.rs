//! The `cubecal` binary: parse arguments, run, map errors to exit codes. No logic lives here.

mod cli;

fn main() -> std::process::ExitCode {
    cli::main()
}
