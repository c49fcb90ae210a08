use std::process::ExitCode;

use clap::Parser;

/// Ends the process quietly when stdout is closed early (`rangegan-mcap info x.mcap | head`),
/// as Unix tools do, instead of panicking inside `println!`.
fn default_sigpipe() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: restores the default disposition of one signal; nothing else changes.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

fn main() -> ExitCode {
    default_sigpipe();
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
