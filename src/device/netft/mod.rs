//! ATI Net F/T (and OnRobot HEX) 6-axis force/torque sensors on the network: RDT
//! records over UDP (port 49152), calibration over TCP (READCALINFO, port 49151).
//! [`codec`] (pure), [`transport`] (the datagram trait the driver is generic over and
//! its UDP implementation), [`driver`] (streaming, losses, duplicates, reordering,
//! deadlines), [`sim`] (the device on loopback sockets). Spec: `protocols/netft.md`.

pub mod codec;
pub mod driver;
pub mod sim;
pub mod transport;

pub use driver::{read_calinfo, NetFt, NetFtOptions, StreamStats};
pub use sim::{NetFtCore, NetFtServer, NetFtSimConfig};
pub use transport::{Datagram, UdpTransport};
