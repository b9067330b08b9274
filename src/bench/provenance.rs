//! Provenance is earned: which of a run's devices were real. A run is a real-bench run
//! only when every device is: a camera reading recorded frames (`dir:`), a device that
//! reports a simulator's firmware (the tactbench simulators name themselves: `DynPick
//! simulator 1.0 (tactbench)`, `Marlin 2.1.2.1 (tactbench simulator)`), a network
//! sensor on a loopback address (nothing but a simulator answers there) or the
//! built-in simulated bench make it SIMULATED (or REPLAYED), and the device that did
//! is named.
//!
//! Judged from the identities the devices reported (`manifest.json` `devices`) when the
//! run starts; recorded as `device_provenance`.

use serde_json::Value;

use super::journal::{DeviceProvenance, Provenance};

/// The devices a manifest's `devices` names, in this order.
pub const DEVICES: [&str; 3] = ["stage", "force_sensor", "camera"];

/// Each device's provenance from the identities it reported; `simulated_bench`: the
/// run is on the built-in simulated bench (every device is then simulated).
pub fn judge(devices: &Value, simulated_bench: bool) -> Vec<DeviceProvenance> {
    DEVICES
        .iter()
        .map(|&device| {
            let id = devices.get(device).cloned().unwrap_or(Value::Null);
            let identity = match &id {
                Value::String(s) => s.clone(),
                Value::Null => "not recorded".to_string(),
                other => other.to_string(),
            };
            let (provenance, why) = if simulated_bench {
                (
                    Provenance::Simulated,
                    Some("the built-in simulated bench (`run --sim` or a [sim] bench file)".into()),
                )
            } else {
                judge_one(device, &id, &identity)
            };
            DeviceProvenance {
                device: device.to_string(),
                identity,
                provenance,
                why,
            }
        })
        .collect()
}

fn judge_one(device: &str, id: &Value, text: &str) -> (Provenance, Option<String>) {
    let lower = text.to_ascii_lowercase();
    if device == "camera" {
        // `format!("{spec:?}")` of the camera spec: `Dir("…")`, `Sim("…")`, `V4l(0)`.
        if lower.starts_with("dir(") || lower.starts_with("dir:") {
            return (
                Provenance::Replayed,
                Some(format!("the camera reads recorded frames ({text})")),
            );
        }
        if lower.starts_with("sim") {
            return (
                Provenance::Simulated,
                Some(format!("the camera is the simulated bench's ({text})")),
            );
        }
    }
    if lower.contains("tactbench") || lower.contains("simulator") {
        return (
            Provenance::Simulated,
            Some(format!(
                "the {} reports a simulator's firmware ({text})",
                device.replace('_', " ")
            )),
        );
    }
    if lower.contains("replay") || lower.contains("transcript") {
        return (
            Provenance::Replayed,
            Some(format!(
                "the {} is a replayed transcript ({text})",
                device.replace('_', " ")
            )),
        );
    }
    if let Some(host) = find_host(id) {
        let h = host.trim_matches(|c| c == '[' || c == ']');
        let loopback = h == "localhost"
            || h.parse::<std::net::IpAddr>()
                .is_ok_and(|ip| ip.is_loopback());
        if loopback {
            return (
                Provenance::Simulated,
                Some(format!(
                    "the {} answers on the loopback address {h} (a simulator; a real sensor is on the network)",
                    device.replace('_', " ")
                )),
            );
        }
    }
    if text == "not recorded" {
        return (
            Provenance::Simulated,
            Some(format!(
                "the {} did not report an identity",
                device.replace('_', " ")
            )),
        );
    }
    (Provenance::Real, None)
}

/// A `host` (or `ip`, `address`) string anywhere in an identity.
fn find_host(v: &Value) -> Option<String> {
    match v {
        Value::Object(m) => {
            for key in ["host", "ip", "address"] {
                if let Some(Value::String(s)) = m.get(key) {
                    return Some(s.clone());
                }
            }
            m.values().find_map(find_host)
        }
        Value::Array(a) => a.iter().find_map(find_host),
        _ => None,
    }
}

/// The run's provenance in one word (`real`, `replayed`, `simulated`: the least real
/// device's) and the devices that made it so, `"camera: why"` each.
pub fn overall(devices: &[DeviceProvenance]) -> (Provenance, Vec<String>) {
    let worst = devices
        .iter()
        .map(|d| d.provenance)
        .max()
        .unwrap_or(Provenance::Real);
    let why = devices
        .iter()
        .filter(|d| d.provenance != Provenance::Real)
        .map(|d| {
            format!(
                "{}: {}",
                d.device,
                d.why.clone().unwrap_or_else(|| d.provenance.word().into())
            )
        })
        .collect();
    (worst, why)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_dir_camera_and_a_simulator_firmware_are_not_a_real_bench() {
        let ids = json!({
            "stage": {"protocol": "marlin", "port": "/dev/ttyACM0", "firmware": "Marlin 2.1.2.1 (tactbench simulator)"},
            "force_sensor": {"protocol": "dynpick", "port": "/dev/ttyUSB0", "firmware": "DynPick 2.0"},
            "camera": "Dir(\"frames\")",
        });
        let p = judge(&ids, false);
        assert_eq!(p[0].provenance, Provenance::Simulated);
        assert_eq!(p[1].provenance, Provenance::Real);
        assert_eq!(p[2].provenance, Provenance::Replayed);
        let (w, why) = overall(&p);
        assert_eq!(w, Provenance::Simulated);
        assert!(why[0].starts_with("stage: the stage reports a simulator's firmware"));
        assert!(why[1].starts_with("camera: the camera reads recorded frames"));
        let net = json!({"stage": {"protocol": "grbl", "version": "1.1h"},
            "force_sensor": {"protocol": "netft", "host": "127.0.0.1"}, "camera": "V4l(0)"});
        let p = judge(&net, false);
        assert_eq!(p[1].provenance, Provenance::Simulated, "{:?}", p[1]);
        assert_eq!(p[0].provenance, Provenance::Real);
        assert_eq!(p[2].provenance, Provenance::Real);
    }
}
