//! The `conformd` command line: each command's flags go to its file in `cli/commands/`,
//! which makes one library call and prints its summary. Errors are printed as one
//! sentence naming the file and what was wrong.

mod cli;

use clap::Parser;
use cli::args::{Cli, Cmd};
use cli::commands;
use conformd::commands::CommandError;
use std::process::ExitCode;

fn run(cli: Cli) -> Result<(), CommandError> {
    match cli.cmd {
        Cmd::Conform(a) => commands::conform::run(a),
        Cmd::Check(a) => commands::check::run(a),
        Cmd::Process(a) => commands::process::run(a),
        Cmd::Daemon(a) => commands::daemon::run(a),
        Cmd::Worker(a) => commands::worker::run(a),
        Cmd::Demo(a) => commands::demo::run(a),
        Cmd::Template(a) => commands::template::run(a),
        Cmd::Autorig(a) => commands::autorig::run(a),
        Cmd::Render(a) => commands::render::run(a),
        Cmd::Capture(a) => commands::capture::run(a),
        Cmd::Simulate(a) => commands::simulate::run(a),
        Cmd::Calibrate(a) => commands::calibrate::run(a),
        Cmd::Reconstruct(a) => commands::reconstruct::run(a),
        Cmd::ImportPair(a) => commands::import_pair::run(a),
        Cmd::Disparity(a) => commands::disparity::run(a),
        Cmd::Cameras => commands::cameras::run(),
        Cmd::Model { cmd } => commands::model::run(cmd),
        Cmd::Measure(a) => commands::measure::run(a),
        Cmd::Export(a) => commands::export::run(a),
        Cmd::Info(a) => commands::info::run(a),
    }
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("conformd: {e}");
            ExitCode::FAILURE
        }
    }
}
