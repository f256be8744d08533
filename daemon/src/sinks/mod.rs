//! Where relit frames and raw streams go: the MCAP recorder and PNG snapshots/outputs, written
//! off the render thread ([`writer`]) into regular files only ([`safe_file`]).

pub mod exr_out;
pub mod png_out;
pub mod recorder;
pub mod safe_file;
pub mod writer;
