//! Reconstruction: what engines need from raw sensor frames, on the CPU.
//!
//! - Geometry: [`depth`] (invalid depth never becomes geometry; guided filter with the colour
//!   image as guide, He et al.), [`temporal`] (warp of the previous filtered depth into the
//!   current view and merge, Knecht et al. Sec. 4.2), [`normals`] from the position map.
//! - Materials: [`albedo`], diffuse albedo of real pixels by DLPV eq. 1, with the room's own
//!   bounce light as the colour camera sees it ([`bounce`]).
//! - Light: [`hdr`] (Robertson response recovery and HDR merge of brackets), [`envmap`]
//!   (fish-eye → equirectangular map through the Kannala–Brandt model), [`median_cut`] (median
//!   cut and variance-minimising median cut), [`irradiance`] (SH9 of a map), and the published
//!   [`estimate::LightingEstimate`], also in Unity's and three.js's conventions ([`sh_conventions`]).
//!
//! The per-frame depth work also runs on the GPU (`relight_engines::recon_gpu`); this crate is
//! its test oracle.

pub mod albedo;
pub mod bounce;
pub mod depth;
pub mod envmap;
pub mod estimate;
pub mod hdr;
pub mod irradiance;
pub mod median_cut;
pub mod normals;
pub mod probe;
pub mod sh_conventions;
pub mod temporal;
pub mod vignetting;
