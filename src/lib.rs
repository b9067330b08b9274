//! tactbench: a hardware-in-the-loop test bench controller for vision-based tactile
//! sensors (two layers of coloured markers in a transparent elastomer, photographed
//! from below; surface force vectors reconstructed with the elastic half-space model).
//!
//! The library holds all logic; the `tactbench` binary is a thin CLI over it. See
//! `ARCHITECTURE.md` for the module map and `README.md` for commands and file formats.

#![warn(missing_docs)]

pub mod analysis;
pub mod bench;
pub mod clock;
pub mod config;
pub mod device;
pub mod fit;
pub mod formats;
pub mod frame_size;
pub mod live;
pub mod model;
pub mod report;
pub mod sensor;
pub mod sim;
pub mod solve;
pub mod units;
pub mod vision;

// The Python package `tactbench` (PyO3; built by maturin from pyproject.toml).
#[cfg(feature = "python")]
mod python;
