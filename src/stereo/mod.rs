//! Stereo: pod calibrations and (to come with the stereo issue) rectification, disparity
//! through OpenCV, reprojection and fusion. For now it owns the camera model the virtual
//! rig renders with and the calibration files in OpenCV's YAML form.

pub mod calib;
