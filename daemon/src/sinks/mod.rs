//! Where relit frames and raw streams go: the MCAP recorder and PNG snapshots/outputs.

pub mod exr_out;
pub mod png_out;
pub mod recorder;
