use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    rangegan_mcap::model::tune_allocator();
    let args = rangegan_mcap::cli::Args::parse();
    match rangegan_mcap::cli::run(args) {
        Ok(outcome) => outcome.exit_code(),
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::from(1)
        }
    }
}
