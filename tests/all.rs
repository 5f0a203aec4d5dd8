//! The one integration-test binary: every file beside this one is a module of it (one
//! link of the library, OpenCV, tokio and PostgreSQL instead of one per file), the
//! helpers they share in `common/`. Run one file's tests with
//! `cargo test --profile ci --test all <file>::`.

mod common;

#[path = "articulated.rs"]
mod articulated;
#[path = "bad_input.rs"]
mod bad_input;
#[path = "calibration.rs"]
mod calibration;
#[path = "capture.rs"]
mod capture;
#[path = "cli.rs"]
mod cli;
#[path = "daemon.rs"]
mod daemon;
#[path = "devset.rs"]
mod devset;
#[path = "hostile.rs"]
mod hostile;
#[path = "journal.rs"]
mod journal;
#[path = "layering.rs"]
mod layering;
#[path = "measure.rs"]
mod measure;
#[path = "mesh_io.rs"]
mod mesh_io;
#[path = "package.rs"]
mod package;
#[path = "paper_cases.rs"]
mod paper_cases;
#[path = "pipeline.rs"]
mod pipeline;
#[path = "readers_fuzz.rs"]
mod readers_fuzz;
#[path = "render.rs"]
mod render;
#[path = "shape_model.rs"]
mod shape_model;
#[path = "stereo.rs"]
mod stereo;
#[path = "templates.rs"]
mod templates;
#[path = "trigger_box.rs"]
mod trigger_box;
#[path = "trigger_firmware.rs"]
mod trigger_firmware;
#[path = "v4l2_hardware.rs"]
mod v4l2_hardware;
#[path = "virtual_rig.rs"]
mod virtual_rig;
#[path = "workers.rs"]
mod workers;
