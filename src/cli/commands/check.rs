//! `conformd check`: a station file checked and shown as resolved.

use crate::cli::args::CheckArgs;
use conformd::commands;

pub fn run(a: CheckArgs) -> Result<(), commands::CommandError> {
    let CheckArgs { config } = a;
    let cfg = commands::check(&config)?;
    println!("{} is a valid station file; resolved:", config.display());
    print!(
        "{}",
        toml::to_string(&cfg.shown()).expect("a station config serialises")
    );
    Ok(())
}
