//! The `conformd` command line, apart from `main`: its arguments (`args`) and the
//! progress bars it shows during long work (`progress`).

pub mod args;
pub mod progress;
