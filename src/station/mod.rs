//! The station: its configuration file (one typed reader for every section) and the
//! pipeline that turns one capture set into one result folder. Everything below the
//! daemon that knows what a station is lives here; it is synchronous and uses no clock
//! but the stage timings.

pub mod config;
pub mod export;
pub mod outcome;
pub mod pipeline;
pub mod placed;
pub mod review;
pub mod view;

pub use config::{ConfigError, StationConfig};
pub use outcome::ProcessOutcome;
pub use pipeline::{Control, Pipeline, PipelineError, Processed, Stage, StageError};
