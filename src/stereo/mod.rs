//! Stereo: the camera model and pod calibrations (OpenCV YAML), disparity by OpenCV's
//! SGBM, and reconstruction of a capture set into a fused scan in the rig frame.

pub mod calib;
pub mod calibrate;
pub mod disparity;
pub mod reconstruct;
pub mod recorded;
pub mod rig;
pub mod truth;
