//! conformd: the software of a photogrammetry capture station. Reads and writes meshes,
//! conforms a generic template mesh onto scans (Ju et al. 2004, improved), and makes
//! synthetic subjects with ground truth for tests and demos. See DESIGN.md for the data
//! path and the layout.

pub mod conform;
pub mod jobs;
pub mod mesh;
pub mod model;
pub mod render;
pub mod rig;
pub mod stereo;
pub mod synth;
