//! One file per command: its flags turned into a library call, and what it prints.

pub mod autorig;
pub mod calibrate;
pub mod cameras;
pub mod capture;
pub mod check;
pub mod conform;
pub mod daemon;
pub mod demo;
pub mod disparity;
pub mod export;
pub mod import_pair;
pub mod info;
pub mod measure;
pub mod model;
pub mod process;
pub mod reconstruct;
pub mod render;
pub mod simulate;
pub mod template;
pub mod worker;
