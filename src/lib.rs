//! conformd: the software of a photogrammetry capture station: stereo reconstruction of
//! capture sets, conformation of a generic template mesh onto every scan (Ju et al. 2004,
//! improved), shape models, and the station pipeline that runs them per capture.
//! `ARCHITECTURE.md` has the data path and what each module owns.

pub mod commands;
pub mod conform;
pub mod daemon;
pub mod devices;
pub mod files;
pub mod measure;
pub mod mesh;
pub mod model;
pub mod paths;
pub mod render;
pub mod station;
pub mod stereo;
pub mod synth;
pub mod template;
