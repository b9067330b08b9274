//! Robotiq FT 300 6-axis force/torque sensor: Modbus RTU at 19200 baud plus a binary
//! 100 Hz stream. [`codec`] (pure), [`driver`] (generic over `Read + Write`; polled
//! [`Ft300`] and streaming [`Ft300Stream`]), [`sim`] (Modbus slave and stream from a
//! wrench source). Spec: `protocols/ft300.md`.

pub mod codec;
pub mod driver;
pub mod sim;

pub use driver::{Ft300, Ft300Info, Ft300Stream};
pub use sim::{Ft300Sim, Ft300SimConfig};
