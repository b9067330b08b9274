//! Zaber ASCII xyz stage: codec ([`codec`]), driver ([`Zaber`], generic over
//! `Read + Write`, implementing [`Stage`]) and simulator ([`sim::ZaberSim`]).
//! The spec is `protocols/zaber.md`.
//!
//! Each stage axis (x, y, z) is one Zaber device + axis number with its own
//! resolution (mm per microstep): position_mm = steps × mm_per_step. Positions on
//! the wire are integer microsteps, rounded to the nearest step.
//!
//! Reliability rules:
//! - every command carries a message id (0..=99, rolling) unless disabled; a reply
//!   is matched on device, axis and id, so late replies to an earlier command are
//!   recognised and discarded instead of being taken for the current one;
//! - with checksums on, every command carries `:CC` and a reply with a wrong
//!   checksum is a [`ErrorKind::Protocol`] error;
//! - queries (`get`, the status command, `warnings`) and `stop` are retried with a
//!   new id after a timeout or a garbled reply; moves and `home` are never re-sent;
//! - `RJ` replies are [`ErrorKind::Rejected`] with the device's reason;
//! - warning flags are kept per axis ([`Zaber::warnings`]): `WR` (no reference)
//!   makes [`Stage::state`] report `Alarm` and absolute moves refused until homed;
//!   `WL` (unexpected limit) fails [`Stage::wait_idle`] with [`ErrorKind::Limit`];
//!   faults (`F*`) fail it with [`ErrorKind::Other`]; `NI` (move interrupted) is
//!   reported by `warnings` but is what `stop` is for, so it is not an error;
//! - completion: poll the status command until every axis is `IDLE`.

pub mod codec;
pub mod sim;

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use self::codec::{decode, Command, Message, Reply, ReplyFlag, Status, Warning};
use super::lineio::{open_stage_serial, LinePort};
use super::{
    DeviceError, DeviceResult, ErrorKind, Stage, StagePositionMm, StageState, TravelLimits,
};

/// Device name in errors.
pub const DEVICE: &str = "zaber";

/// Default baud rate (current Zaber devices; older ones use 9600).
pub const DEFAULT_BAUD: u32 = 115_200;

/// Default resolution: 0.047625 µm per microstep (Zaber's common lead-screw stages).
pub const DEFAULT_MM_PER_STEP: f64 = 0.047625e-3;

/// Time for a reply to one command (devices answer within a few ms).
pub const REPLY_TIMEOUT: Duration = Duration::from_millis(500);

/// Time for a homing cycle over the full travel.
pub const HOMING_TIMEOUT: Duration = Duration::from_secs(120);

/// Interval of status polling while waiting for motion to finish.
pub const POLL_INTERVAL: Duration = Duration::from_millis(20);

/// Retries of a query after a timeout or garbled reply.
pub const QUERY_RETRIES: u32 = 2;

/// Velocity unit of `maxspeed`: 1.6384 units per microstep/s.
pub const VELOCITY_UNITS_PER_STEP_S: f64 = sim::VELOCITY_UNITS_PER_STEP_S;

/// One stage axis: which device and axis drives it, and its resolution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ZaberAxis {
    /// Device address (1..=99).
    pub device: u8,
    /// Axis on the device (1.. ; single-axis devices use 1).
    pub axis: u8,
    /// Resolution, mm per microstep.
    pub mm_per_step: f64,
}

/// Driver configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct ZaberConfig {
    /// x, y, z.
    pub axes: [ZaberAxis; 3],
    /// Append and check LRC checksums.
    pub checksums: bool,
    /// Use message ids (recommended: lets late replies be recognised).
    pub message_ids: bool,
    /// Travel box, mm; `None`: from the devices' `limit.min`/`limit.max`.
    pub limits: Option<TravelLimits>,
    /// Timeout per reply.
    pub reply_timeout: Duration,
    /// Timeout of the homing cycle.
    pub homing_timeout: Duration,
}

impl ZaberConfig {
    /// Three single-axis devices at `devices` (x, y, z), axis 1 each, all with
    /// resolution `mm_per_step`; checksums and message ids on.
    pub fn single_axis_devices(devices: [u8; 3], mm_per_step: f64) -> Self {
        ZaberConfig {
            axes: devices.map(|device| ZaberAxis {
                device,
                axis: 1,
                mm_per_step,
            }),
            checksums: true,
            message_ids: true,
            limits: None,
            reply_timeout: REPLY_TIMEOUT,
            homing_timeout: HOMING_TIMEOUT,
        }
    }
}

impl Default for ZaberConfig {
    fn default() -> Self {
        Self::single_axis_devices([1, 2, 3], DEFAULT_MM_PER_STEP)
    }
}

/// Opens a serial port for a Zaber chain (8N1, short read timeout).
pub fn open_serial(path: &str, baud: u32) -> DeviceResult<Box<dyn serialport::SerialPort>> {
    open_stage_serial(DEVICE, path, baud, "older Zaber devices use 9600 baud")
}

const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

/// A chain of Zaber devices driving an xyz stage.
#[derive(Debug)]
pub struct Zaber<P> {
    port: LinePort<P>,
    config: ZaberConfig,
    limits: TravelLimits,
    next_id: u8,
    warnings: [Warning; 3],
}

impl<P: Read + Write> Zaber<P> {
    /// Connects: checks every configured axis answers, reads its warning flag and
    /// (unless configured) its travel limits.
    pub fn connect(port: P, config: ZaberConfig) -> DeviceResult<Self> {
        for (i, a) in config.axes.iter().enumerate() {
            if !(a.mm_per_step.is_finite() && a.mm_per_step > 0.0) {
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    "connect",
                    format!(
                        "{} resolution {} mm per microstep must be positive",
                        AXIS_NAMES[i], a.mm_per_step
                    ),
                ));
            }
        }
        let mut z = Zaber {
            port: LinePort::new(port, DEVICE),
            limits: config.limits.unwrap_or(TravelLimits {
                axes_mm: [[f64::NEG_INFINITY, f64::INFINITY]; 3],
            }),
            config,
            next_id: 0,
            warnings: [Warning::NONE; 3],
        };
        for i in 0..3 {
            z.request(i, "", true).map_err(|e| {
                let a = z.config.axes[i];
                let hint = format!(
                    "no answer from device {} axis {}: check --zaber-devices, the baud rate and the daisy chain",
                    a.device, a.axis
                );
                DeviceError { hint: Some(hint), ..e }
            })?;
        }
        if z.config.limits.is_none() {
            let mut axes_mm = [[0.0; 2]; 3];
            for (i, axis) in axes_mm.iter_mut().enumerate() {
                let lo = z.get_int(i, "limit.min")?;
                let hi = z.get_int(i, "limit.max")?;
                let k = z.config.axes[i].mm_per_step;
                *axis = [lo as f64 * k, hi as f64 * k];
            }
            z.limits = TravelLimits { axes_mm };
        }
        Ok(z)
    }

    /// The last warning flag seen per axis (x, y, z).
    pub fn warnings(&self) -> [Warning; 3] {
        self.warnings
    }

    /// The port back.
    pub fn into_inner(self) -> P {
        self.port.into_inner()
    }

    fn take_id(&mut self) -> Option<u8> {
        if !self.config.message_ids {
            return None;
        }
        let id = self.next_id;
        self.next_id = (self.next_id + 1) % 100;
        Some(id)
    }

    /// Sends `text` to stage axis `i` and returns the matching reply. Queries are
    /// retried (new id) after a timeout or a garbled line; commands are not.
    fn request(&mut self, i: usize, text: &str, query: bool) -> DeviceResult<Reply> {
        let attempts = if query { QUERY_RETRIES + 1 } else { 1 };
        let mut last = None;
        for _ in 0..attempts {
            match self.request_once(i, text, query) {
                Ok(r) => return Ok(r),
                Err(e) if query && matches!(e.kind(), ErrorKind::Timeout | ErrorKind::Protocol) => {
                    last = Some(e)
                }
                Err(e) => return Err(e),
            }
        }
        Err(last.unwrap_or_else(|| DeviceError::new(ErrorKind::Timeout, DEVICE, text, "no reply")))
    }

    fn request_once(&mut self, i: usize, text: &str, query: bool) -> DeviceResult<Reply> {
        let a = self.config.axes[i];
        let mut cmd = Command::new(a.device, a.axis, text);
        if let Some(id) = self.take_id() {
            cmd = cmd.with_id(id);
        }
        let line = cmd.encode(self.config.checksums);
        self.port
            .send(&cmd.to_bytes(self.config.checksums), &line)?;
        let deadline = Instant::now() + self.config.reply_timeout;
        loop {
            let raw = match self.port.read_line(deadline, &line) {
                Ok(r) => r,
                Err(mut e) => {
                    if e.kind() == ErrorKind::Timeout {
                        e.message = format!(
                            "no reply within {:.1} s from device {} axis {}{}",
                            self.config.reply_timeout.as_secs_f64(),
                            a.device,
                            a.axis,
                            if query {
                                ""
                            } else {
                                "; not re-sent (it may have been executed)"
                            }
                        );
                    }
                    return Err(e);
                }
            };
            let msg = match decode(&raw) {
                Ok(m) => m,
                Err(e) => {
                    return Err(DeviceError::new(
                        ErrorKind::Protocol,
                        DEVICE,
                        line.clone(),
                        format!(
                            "{e}{}",
                            if query {
                                ""
                            } else {
                                "; the command may or may not have been executed and is not re-sent"
                            }
                        ),
                    ))
                }
            };
            match msg {
                Message::Reply(r) => {
                    let matches = r.device == a.device && r.axis == a.axis && r.id == cmd.id;
                    if !matches {
                        // A late reply to an earlier command, or another device's.
                        continue;
                    }
                    self.warnings[i] = r.warning;
                    if r.flag == ReplyFlag::Rejected {
                        let mut e = DeviceError::new(
                            ErrorKind::Rejected,
                            DEVICE,
                            line.clone(),
                            format!(
                                "device {} axis {} rejected the command: {}",
                                a.device, a.axis, r.data
                            ),
                        );
                        e.hint = match r.data.as_str() {
                            "BADDATA" => Some(
                                "value out of range (travel limit.min..limit.max or setting range)"
                                    .into(),
                            ),
                            "BADCOMMAND" => {
                                Some("command not supported by this device/firmware".into())
                            }
                            "BADAXIS" => {
                                Some("no such axis on this device: check --zaber-devices".into())
                            }
                            _ => None,
                        };
                        return Err(e);
                    }
                    return Ok(r);
                }
                Message::Alert {
                    device,
                    axis,
                    warning,
                    ..
                } => {
                    if device == a.device && axis == a.axis {
                        self.warnings[i] = warning;
                    }
                }
                Message::Info { .. } => {}
            }
        }
    }

    fn get_int(&mut self, i: usize, setting: &str) -> DeviceResult<i64> {
        let r = self.request(i, &format!("get {setting}"), true)?;
        r.data.trim().parse().map_err(|_| {
            DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                format!("get {setting}"),
                format!("expected an integer for {setting}, got {:?}", r.data),
            )
        })
    }

    fn steps(&self, i: usize, mm: f64) -> i64 {
        (mm / self.config.axes[i].mm_per_step).round() as i64
    }

    fn set_speed(&mut self, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        let Some(v) = speed_mm_s else { return Ok(()) };
        if !(v.is_finite() && v > 0.0) {
            return Err(DeviceError::new(
                ErrorKind::Other,
                DEVICE,
                "set maxspeed",
                format!("speed {v} mm/s must be a positive finite number"),
            ));
        }
        for i in 0..3 {
            let units = (v / self.config.axes[i].mm_per_step * VELOCITY_UNITS_PER_STEP_S)
                .round()
                .max(1.0) as i64;
            self.request(i, &format!("set maxspeed {units}"), false)?;
        }
        Ok(())
    }

    fn axis_error(&self, i: usize, w: Warning, command: &str) -> Option<DeviceError> {
        let a = self.config.axes[i];
        let what = format!(
            "{} axis (device {} axis {}) reports {} ({})",
            AXIS_NAMES[i],
            a.device,
            a.axis,
            w,
            w.meaning()
        );
        if w == Warning::LIMIT {
            Some(
                DeviceError::new(ErrorKind::Limit, DEVICE, command, what)
                    .with_hint("clear the cause, then `unlock` (warnings clear) and home"),
            )
        } else if w.is_fault() {
            Some(
                DeviceError::new(ErrorKind::Other, DEVICE, command, what)
                    .with_hint("check the device; `unlock` clears the flag"),
            )
        } else {
            None
        }
    }
}

impl<P: Read + Write> Stage for Zaber<P> {
    fn home(&mut self) -> DeviceResult<()> {
        for i in 0..3 {
            self.request(i, "home", false)?;
        }
        self.wait_idle(self.config.homing_timeout)
    }

    fn move_to(&mut self, target_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        self.limits.check(target_mm).map_err(|m| {
            DeviceError::new(ErrorKind::Limit, DEVICE, "move abs", m)
                .with_hint("the move was not sent")
        })?;
        for (i, name) in AXIS_NAMES.iter().enumerate() {
            if self.warnings[i] == Warning::NOT_HOMED {
                let a = self.config.axes[i];
                return Err(DeviceError::new(
                    ErrorKind::Other,
                    DEVICE,
                    "move abs",
                    format!(
                        "{} axis (device {} axis {}) has no reference position (WR): absolute targets are meaningless",
                        name, a.device, a.axis
                    ),
                )
                .with_hint("home the stage first"));
            }
        }
        self.set_speed(speed_mm_s)?;
        for (i, t) in target_mm.iter().enumerate() {
            let steps = self.steps(i, *t);
            self.request(i, &format!("move abs {steps}"), false)?;
        }
        Ok(())
    }

    fn move_by(&mut self, delta_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()> {
        let here = self.position()?;
        let target = [
            here[0] + delta_mm[0],
            here[1] + delta_mm[1],
            here[2] + delta_mm[2],
        ];
        self.limits.check(target).map_err(|m| {
            DeviceError::new(ErrorKind::Limit, DEVICE, "move rel", m)
                .with_hint("the move was not sent")
        })?;
        self.set_speed(speed_mm_s)?;
        for (i, d) in delta_mm.iter().enumerate() {
            let steps = self.steps(i, *d);
            if steps != 0 {
                self.request(i, &format!("move rel {steps}"), false)?;
            }
        }
        Ok(())
    }

    fn position(&mut self) -> DeviceResult<StagePositionMm> {
        let mut p = [0.0; 3];
        for (i, v) in p.iter_mut().enumerate() {
            *v = self.get_int(i, "pos")? as f64 * self.config.axes[i].mm_per_step;
        }
        Ok(p)
    }

    fn state(&mut self) -> DeviceResult<StageState> {
        let mut busy = false;
        let mut alarm = false;
        for i in 0..3 {
            let r = self.request(i, "", true)?;
            busy |= r.status == Status::Busy;
            alarm |= r.warning == Warning::LIMIT
                || r.warning.is_fault()
                || r.warning == Warning::NOT_HOMED;
        }
        Ok(if alarm {
            StageState::Alarm
        } else if busy {
            StageState::Moving
        } else {
            StageState::Idle
        })
    }

    fn wait_idle(&mut self, timeout: Duration) -> DeviceResult<()> {
        let deadline = Instant::now() + timeout;
        loop {
            let mut busy = false;
            for i in 0..3 {
                let r = self.request(i, "", true)?;
                if let Some(e) = self.axis_error(i, r.warning, "wait idle") {
                    return Err(e);
                }
                busy |= r.status == Status::Busy;
            }
            if !busy {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(DeviceError::new(
                    ErrorKind::Timeout,
                    DEVICE,
                    "wait idle",
                    format!("still moving after {:.1} s", timeout.as_secs_f64()),
                ));
            }
            std::thread::sleep(POLL_INTERVAL);
        }
    }

    fn stop(&mut self) -> DeviceResult<()> {
        // `stop` is idempotent: retrying it is safe.
        for i in 0..3 {
            self.request(i, "stop", true)?;
        }
        Ok(())
    }

    fn unlock(&mut self) -> DeviceResult<()> {
        for i in 0..3 {
            self.request(i, "warnings clear", false)?;
            // The reply lists the flags before clearing; read the state after.
            let r = self.request(i, "", true)?;
            self.warnings[i] = r.warning;
        }
        Ok(())
    }

    fn limits(&self) -> TravelLimits {
        self.limits
    }

    /// Zaber documents no status rate: every status request is an ordinary command
    /// answered at once, and motion completion is "poll until `IDLE`"; the runner polls
    /// as often as the driver's own [`wait_idle`](Stage::wait_idle) does.
    fn status_interval(&self) -> Duration {
        POLL_INTERVAL
    }
}
