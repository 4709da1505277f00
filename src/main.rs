//! `pipe`: the command-line entry point. Parses arguments, dispatches, and maps errors to exit
//! codes: 0 ok, 1 a stage failed (or the work could not be done), 2 bad usage or configuration.

use clap::Parser;
use pipe::error::Classify;

fn main() {
    let cli = pipe::cli::Cli::parse();
    let code = match pipe::cli::dispatch(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", pipe::error::chain(&e));
            e.exit_code()
        }
    };
    std::process::exit(code);
}
