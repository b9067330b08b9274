//! Devices: the capability traits the bench runner drives, and one folder per wire
//! protocol (pure codec, driver generic over `Read + Write` (the Net F/T: over a
//! datagram transport), simulator serving the same protocol; the spec lives in
//! `protocols/`).
//!
//! Drivers never name a concrete port type: they take any `Read + Write` (a
//! `serialport` port on hardware, a pseudo-terminal in tests and in the simulated
//! bench, a byte buffer in transcript replays). Every read has a timeout, so nothing
//! can hang. Each driver keeps a rich error but exposes a small [`ErrorKind`] the
//! runner can act on, and every error carries the command that failed.

pub mod bota;
pub mod camera;
pub mod dynpick;
pub mod ft300;
pub mod ft_common;
pub mod netft;

use std::fmt;
use std::time::{Duration, SystemTime};

/// What went wrong, coarsely: what the runner needs to decide between retrying,
/// recovering and aborting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// No (complete) reply within the time allowed.
    Timeout,
    /// The port is gone (device unplugged, simulator stopped, EOF / EIO).
    Disconnected,
    /// The bytes received do not follow the protocol (bad checksum, garbled line).
    Protocol,
    /// The device understood and refused the command (`error:N`, `RJ`).
    Rejected,
    /// A travel, force or alarm limit was hit (GRBL `ALARM:N`, Zaber limit flags).
    Limit,
    /// Motion is held and waits for the user (GRBL feed hold `Hold:N` or safety
    /// door `Door:N`): resume (GRBL `~`) or abort.
    Held,
    /// Anything else.
    Other,
}

impl fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            ErrorKind::Timeout => "timeout",
            ErrorKind::Disconnected => "disconnected",
            ErrorKind::Protocol => "protocol error",
            ErrorKind::Rejected => "rejected",
            ErrorKind::Limit => "limit",
            ErrorKind::Held => "held",
            ErrorKind::Other => "error",
        })
    }
}

/// A device error: kind, device, the command that failed, what happened, and a hint.
#[derive(Debug, Clone, PartialEq)]
pub struct DeviceError {
    /// Coarse kind for the runner.
    pub kind: ErrorKind,
    /// Device name, e.g. `grbl` or `ft300`.
    pub device: &'static str,
    /// The command that failed, as sent (without line terminator).
    pub command: String,
    /// What happened.
    pub message: String,
    /// What the user can do about it, when known.
    pub hint: Option<String>,
}

impl DeviceError {
    /// A new error.
    pub fn new(
        kind: ErrorKind,
        device: &'static str,
        command: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        DeviceError {
            kind,
            device,
            command: command.into(),
            message: message.into(),
            hint: None,
        }
    }

    /// Adds a hint.
    pub fn with_hint(mut self, hint: impl Into<String>) -> Self {
        self.hint = Some(hint.into());
        self
    }

    /// The coarse kind.
    pub fn kind(&self) -> ErrorKind {
        self.kind
    }
}

impl fmt::Display for DeviceError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}: `{}` failed ({}): {}",
            self.device, self.command, self.kind, self.message
        )?;
        if let Some(h) = &self.hint {
            write!(f, " (hint: {h})")?;
        }
        Ok(())
    }
}

impl std::error::Error for DeviceError {}

/// Result of a device call.
pub type DeviceResult<T> = Result<T, DeviceError>;

/// A position of the stage in its own frame, mm.
pub type StagePositionMm = [f64; 3];

/// The box the stage may travel in, mm, per axis `[min, max]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TravelLimits {
    /// Per axis (x, y, z): `[min, max]` in mm.
    pub axes_mm: [[f64; 2]; 3],
}

impl TravelLimits {
    /// Checks a target, naming the axis and the limit it exceeds.
    pub fn check(&self, target_mm: StagePositionMm) -> Result<(), String> {
        for (i, axis) in ["x", "y", "z"].iter().enumerate() {
            let [lo, hi] = self.axes_mm[i];
            let v = target_mm[i];
            if !v.is_finite() {
                return Err(format!(
                    "requested {axis} = {v} mm is not a finite position"
                ));
            }
            if v < lo {
                return Err(format!(
                    "requested {axis} = {v} mm is below travel limit {lo} mm"
                ));
            }
            if v > hi {
                return Err(format!(
                    "requested {axis} = {v} mm exceeds travel limit {hi} mm"
                ));
            }
        }
        Ok(())
    }
}

/// Motion state of a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageState {
    /// Not moving, ready.
    Idle,
    /// Moving.
    Moving,
    /// Motion held / stopped and waiting (GRBL `Hold`).
    Held,
    /// Homing in progress.
    Homing,
    /// In an alarm or fault state; needs unlock / homing.
    Alarm,
}

/// An xyz stage. Moves return once the device has accepted them; use
/// [`Stage::wait_idle`] (or poll [`Stage::state`], as the safety watchdog does) for
/// completion.
pub trait Stage {
    /// Runs the homing cycle and waits for it to finish.
    fn home(&mut self) -> DeviceResult<()>;
    /// Starts an absolute move to `target_mm` at `speed_mm_s` (None = device default).
    fn move_to(&mut self, target_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()>;
    /// Starts a relative move by `delta_mm`.
    fn move_by(&mut self, delta_mm: StagePositionMm, speed_mm_s: Option<f64>) -> DeviceResult<()>;
    /// Current position, mm.
    fn position(&mut self) -> DeviceResult<StagePositionMm>;
    /// Current motion state.
    fn state(&mut self) -> DeviceResult<StageState>;
    /// Blocks until the stage is idle, or fails with [`ErrorKind::Timeout`].
    fn wait_idle(&mut self, timeout: Duration) -> DeviceResult<()>;
    /// Stops motion as fast as the protocol allows (GRBL feed hold, Zaber `stop`).
    fn stop(&mut self) -> DeviceResult<()>;
    /// Clears an alarm / fault state so the stage accepts moves again.
    fn unlock(&mut self) -> DeviceResult<()>;
    /// The travel box the driver enforces before sending any move.
    fn limits(&self) -> TravelLimits;
    /// How often a caller may ask for [`Stage::state`] / [`Stage::position`] while a
    /// move runs: the rate the controller's documentation supports (GRBL: 5 Hz;
    /// Zaber: its driver's polling interval). The runner's motion loop paces its
    /// status queries to it (`src/bench/runner/motion.rs`).
    fn status_interval(&self) -> Duration;
    /// The stage's position resolution per axis, mm: a controller that moves in whole
    /// steps (Marlin) stops up to half of it from a target off its step grid, and the
    /// runner's "reached" check allows for that. Default: 0 (positions are exact to
    /// the reported decimals).
    fn resolution_mm(&self) -> [f64; 3] {
        [0.0; 3]
    }
}

/// A force/torque reading: force in N, torque in N·m, in the sensor's frame.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Wrench {
    /// Fx, Fy, Fz in N.
    pub force_n: [f64; 3],
    /// Mx, My, Mz in N·m.
    pub torque_nm: [f64; 3],
}

impl Wrench {
    /// Component-wise mean of `samples` (the zero wrench for none).
    pub fn mean(samples: &[Wrench]) -> Wrench {
        let n = samples.len().max(1) as f64;
        let mut m = Wrench::default();
        for w in samples {
            for i in 0..3 {
                m.force_n[i] += w.force_n[i] / n;
                m.torque_nm[i] += w.torque_nm[i] / n;
            }
        }
        m
    }
}

/// A 6-axis force/torque sensor.
pub trait ForceSensor {
    /// One reading (polled, or the newest streamed sample).
    fn read(&mut self) -> DeviceResult<Wrench>;
    /// One reading in a single attempt, without the driver's own retries: for a
    /// watchdog, which must stop the stage at the first failed reading instead of
    /// moving blind while the driver retries. Default: [`ForceSensor::read`].
    fn read_once(&mut self) -> DeviceResult<Wrench> {
        self.read()
    }
    /// Zeroes the sensor's offset at the current load.
    fn tare(&mut self) -> DeviceResult<()>;
    /// Nominal sample rate in Hz of [`ForceSensor::read`] at full speed.
    fn sample_rate_hz(&self) -> f64;
    /// What the sensor reported since the last call that a reading alone does not
    /// show (status flags such as overrange, records lost on the network, samples left
    /// out of a mean), as one line for the journal; `None` when there was nothing.
    /// Default: `None` (sensors without status words).
    fn take_status(&mut self) -> Option<String> {
        None
    }
}

/// A captured camera frame.
#[derive(Debug, Clone)]
pub struct CameraFrame {
    /// 8-bit RGB pixels.
    pub image: image::RgbImage,
    /// When the frame was captured.
    pub timestamp: SystemTime,
}

/// A camera.
pub trait Camera {
    /// Grabs one RGB frame.
    fn grab(&mut self) -> DeviceResult<CameraFrame>;

    /// A frame to check the exposure on before a run moves anything (blank or
    /// saturated?); it is not one of the run's frames. A live camera grabs one
    /// (the default); a recorded directory shows its next frame without consuming it;
    /// the simulated bench serves its unloaded frame, which does not advance its frame
    /// counter, so the run's frames (and their seeded noise) stay the same.
    fn preview(&mut self) -> DeviceResult<CameraFrame> {
        self.grab()
    }
}

pub mod fault;
pub mod grbl;
pub mod lineio;
pub mod marlin;
pub mod pty;
pub mod replay;
pub mod zaber;
