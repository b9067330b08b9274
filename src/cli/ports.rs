//! `tactbench ports`: list the serial ports the system knows (USB adapters, built-in
//! UARTs). Pseudo-terminals (simulators) are not listed: use their path directly.
//! Network force sensors (ATI Net F/T, OnRobot HEX) have no port: the listing ends
//! with a line saying how to address them.

use std::process::ExitCode;

use serialport::SerialPortType;

/// List serial ports.
#[derive(Debug, clap::Args)]
pub struct Args {}

/// Runs `tactbench ports`.
pub fn run(_a: Args) -> anyhow::Result<ExitCode> {
    let ports = serialport::available_ports()
        .map_err(|e| anyhow::anyhow!("cannot list serial ports: {e}"))?;
    if ports.is_empty() {
        println!("no serial ports found (is the controller plugged in and powered? simulators on pseudo-terminals are not listed)");
        println!("{NETWORK_NOTE}");
        return Ok(ExitCode::SUCCESS);
    }
    for p in ports {
        let kind = match &p.port_type {
            SerialPortType::UsbPort(u) => {
                let mut s = format!("usb {:04x}:{:04x}", u.vid, u.pid);
                if let Some(m) = &u.manufacturer {
                    s.push_str(&format!(" {m}"));
                }
                if let Some(pr) = &u.product {
                    s.push_str(&format!(" {pr}"));
                }
                if let Some(sn) = &u.serial_number {
                    s.push_str(&format!(" (serial {sn})"));
                }
                s
            }
            SerialPortType::PciPort => "pci".to_string(),
            SerialPortType::BluetoothPort => "bluetooth".to_string(),
            SerialPortType::Unknown => "unknown type".to_string(),
        };
        println!("{}\t{}", p.port_name, kind);
    }
    println!("{NETWORK_NOTE}");
    Ok(ExitCode::SUCCESS)
}

/// How network force sensors are addressed (they are not serial ports).
const NETWORK_NOTE: &str = "network force sensors are not listed: ATI Net F/T (--protocol netft) and OnRobot HEX (--protocol onrobot-hex) take --port HOST (the sensor's address; RDT on UDP 49152, calibration on TCP 49151), bench.toml [force_sensor] host = \"...\"";
