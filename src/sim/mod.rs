//! Scene simulation: what the tactile sensor's camera would see under a given load.
//!
//! - [`render`]: the ideal renderer (exact per-pixel disc coverage; marker positions in
//!   mm in, float RGB frame out, 8- and 16-bit conversions).

pub mod contact;
pub mod effects;
pub mod render;
pub mod rng;
