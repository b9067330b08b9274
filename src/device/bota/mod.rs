//! Bota Systems 6-axis force/torque sensors on a serial port (460800 baud): text
//! configuration commands and a binary stream of CRC-16/X-25 checked frames.
//! [`codec`] (pure), [`driver`] (generic over `Read + Write`), [`sim`] (the sensor on
//! a pseudo-terminal). Spec: `protocols/bota.md`.

pub mod codec;
pub mod driver;
pub mod sim;

pub use driver::{Bota, BotaOptions, BotaStats};
pub use sim::{BotaSim, BotaSimConfig};
