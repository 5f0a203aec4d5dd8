//! The station's devices: cameras (the `Camera` trait, V4L2 and replay), the serial trigger box and its
//! line protocol, and capture sessions that fire every camera once and write one atomic
//! capture set. This module (with `daemon/`) is the only one that knows about devices,
//! clocks and the station's directories.

pub mod camera;
pub mod capture;
pub mod capture_set;
pub mod replay;
pub mod setup;
pub mod trigger;
pub mod v4l2;

pub use camera::{Camera, CameraError, CameraInfo, CameraSettings, Frame, FrameData, PixelFormat};
