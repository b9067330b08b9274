//! WACOH DynPick 6-axis force/torque sensor: ASCII single-byte-command protocol at
//! 921600 baud. [`codec`] (pure), [`driver`] (generic over `Read + Write`), [`sim`]
//! (serves the same protocol from a wrench source). Spec: `protocols/dynpick.md`.

pub mod codec;
pub mod driver;
pub mod sim;

pub use driver::DynPick;
pub use sim::{DynPickSim, DynPickSimConfig};
