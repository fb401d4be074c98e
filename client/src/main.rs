//! `c4g`: the command-line client of the c4g service. Upload a clip, then decode, export, render
//! and stream its Gaussians, fit its scene to its own frames (`c4g fit`), and refine novel views
//! (`c4g refine`). `c4g --help` lists the commands; `src/cli/` has one file per command.

mod cli;

use std::process::ExitCode;

use clap::Parser;

#[tokio::main(flavor = "current_thread")]
async fn main() -> ExitCode {
    let args = cli::Cli::parse();
    match cli::run(args).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            // `{:#}` prints the cause chain: "request to the server failed: ...: Connection refused".
            eprintln!("error: {error:#}");
            ExitCode::FAILURE
        }
    }
}
