//! GRBL 1.1 xyz stage: codec ([`codec`]), driver ([`Grbl`], generic over
//! `Read + Write`, implementing [`Stage`](super::Stage)) and simulator ([`sim::GrblSim`]).
//! The spec is `protocols/grbl.md`.
//!
//! The driver is split by responsibility: this file holds its configuration, state and
//! connection; `exchange` the line exchange (replies, retries, resynchronisation,
//! pushed lines, status reports); `settings` the controller's configuration (`$$`,
//! `$I`, `$#`, travel box, MPos conversion); `recovery` the state rules, their errors,
//! reset, unlock and resume; `motion` the `Stage` implementation, jog and probe.
//!
//! Frame: the driver works in GRBL's machine coordinates (MPos), mm. Absolute moves
//! are sent as `G53 G0/G1` (machine coordinates whatever the work offsets are),
//! relative moves and jogs as `G91`; every motion line carries `G21` so a
//! controller left in inches by another program still moves in mm. Status reports
//! in work coordinates (`$10` bit 0 clear) are converted with the last `WCO:` seen.
//!
//! Reliability rules:
//! - every read has a deadline (named constants below, overridable in
//!   [`GrblConfig`]);
//! - queries (`?`, `$$`, `$G`, `G4 P0`) are retried after a timeout or a garbled
//!   reply; commands that move the machine are never re-sent: a lost or garbled
//!   reply to a move is an error, and the reply stream is resynchronised (`$G`, read
//!   up to its `[GC:..]` and `ok`) before the next line;
//! - pushed lines (`ALARM:N`, `[MSG:..]`, the banner, stray status reports) are
//!   handled wherever they arrive: an alarm fails the waiting call with
//!   [`ErrorKind::Limit`], a banner means the controller reset (queued motion lost);
//! - completion: a move's `ok` means queued; [`Stage::wait_idle`](super::Stage::wait_idle) sends `G4 P0`
//!   (answered only when the planner is empty) while polling `?` to see alarms.

pub mod codec;
mod exchange;
mod motion;
mod recovery;
mod settings;
pub mod sim;

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::time::Duration;

use self::codec::{MachineState, StatusReport};
use super::lineio::{open_stage_serial, LinePort};
use super::{DeviceError, DeviceResult, ErrorKind, TravelLimits};

/// Device name in errors.
pub const DEVICE: &str = "grbl";

/// Default baud rate of GRBL 1.1.
pub const DEFAULT_BAUD: u32 = 115_200;

/// Time for `ok`/`error:N` to an ordinary line (GRBL parses a line in < 10 ms; a
/// full planner can delay the `ok` until a block finishes).
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(2);

/// Time for a status report after `?` (GRBL answers within one main-loop pass).
pub const STATUS_TIMEOUT: Duration = Duration::from_millis(500);

/// Time for the banner after a soft reset.
pub const RESET_TIMEOUT: Duration = Duration::from_secs(2);

/// Time for the homing cycle (`$H` is answered when it ends).
pub const HOMING_TIMEOUT: Duration = Duration::from_secs(120);

/// Time to wait for the controller on connect (an Arduino resets when the port
/// opens and its bootloader takes 1–2 s before the banner).
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(4);

/// Interval of the `?` sent at connect until the first report (16 over
/// [`CONNECT_TIMEOUT`]).
pub const CONNECT_STATUS_INTERVAL: Duration = Duration::from_millis(250);

/// Interval of `?` polling while waiting for motion to finish (GRBL recommends
/// at most 5 Hz for GUIs; a bench wants to see alarms sooner, 50 Hz is fine).
pub const POLL_INTERVAL: Duration = Duration::from_millis(20);

/// The rate at which a caller polls `?` while a move runs: GRBL's interface guide
/// recommends status reports at no more than 5 Hz ("10 Hz may be possible"; a report
/// takes ~5-20 ms to generate, and not every `?` is guaranteed an answer).
pub const STATUS_INTERVAL: Duration = Duration::from_millis(200);

/// Time for the controller to come to a stop after a feed hold.
pub const STOP_TIMEOUT: Duration = Duration::from_secs(10);

/// Retries of a query after a timeout or garbled reply.
pub const QUERY_RETRIES: u32 = 2;

/// Time per `$G` answer when resynchronising at connect (a locked controller never
/// answers; a working one answers in milliseconds).
pub const CONNECT_RESYNC_TIMEOUT: Duration = Duration::from_millis(300);

/// Driver configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct GrblConfig {
    /// Travel box the driver enforces, machine coordinates, mm. `None`: derived
    /// from the controller's `$130..$132` as GRBL's own soft-limit box
    /// `[-max_travel, 0]` per axis.
    pub limits: Option<TravelLimits>,
    /// Timeout for line replies.
    pub reply_timeout: Duration,
    /// Timeout for status reports.
    pub status_timeout: Duration,
    /// Timeout for the homing cycle.
    pub homing_timeout: Duration,
}

impl Default for GrblConfig {
    fn default() -> Self {
        GrblConfig {
            limits: None,
            reply_timeout: REPLY_TIMEOUT,
            status_timeout: STATUS_TIMEOUT,
            homing_timeout: HOMING_TIMEOUT,
        }
    }
}

/// A GRBL 1.1 controller driving an xyz stage.
#[derive(Debug)]
pub struct Grbl<P> {
    port: LinePort<P>,
    config: GrblConfig,
    limits: TravelLimits,
    /// Settings (`$$`), read at connect when the controller reads lines, else
    /// before the first move.
    settings: Option<BTreeMap<u16, String>>,
    /// Work coordinate offset (from `WCO:` or `$#`), to convert WPos to MPos;
    /// `None` until known (never assumed zero).
    wco_mm: Option<[f64; 3]>,
    /// The controller announced an alarm we have not cleared.
    alarm: Option<u8>,
    /// A critical alarm ("Reset to continue"): only reset gets out.
    needs_reset: bool,
    /// The reply stream may hold stale replies (a reply was lost or garbled).
    needs_resync: bool,
    /// Banners seen (controller resets).
    resets_seen: u32,
    /// Last `[...]` feedback (e.g. `PRB:..`) and `[MSG:..]` seen.
    last_feedback: Option<String>,
    last_message: Option<String>,
    version: Option<String>,
    /// Version from `$I` (`1.1h.20190830`).
    build_version: Option<String>,
    /// State in the last status report.
    last_state: Option<MachineState>,
    /// The connection began with a soft reset of a silent controller.
    reset_at_connect: bool,
    /// Last `[GC:..]` parser state.
    parser_state: Option<String>,
}

/// No travel limit.
const UNBOUNDED: TravelLimits = TravelLimits {
    axes_mm: [[f64::NEG_INFINITY, f64::INFINITY]; 3],
};

/// Consecutive malformed status reports tolerated while waiting (each is re-queried).
pub const MALFORMED_STATUS_RETRIES: u32 = 3;

/// Status reports polled at most for a `WCO:` field (GRBL sends one every 10 reports
/// when idle, every 30 when busy).
pub const WCO_POLL_REPORTS: u32 = 32;

/// True in the states where GRBL's main loop reads lines (and so answers `$G`,
/// `$$`, ...). In Run and Jog it reads them too, but refuses `$$`/`$#`/`$I` with
/// `error:8`; in Hold, Door, Home and Sleep it reads none.
fn reads_lines(s: MachineState) -> bool {
    matches!(
        s,
        MachineState::Idle | MachineState::Alarm | MachineState::Check
    )
}

/// What [`Grbl::unlock_report`] did.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnlockReport {
    /// The steps taken, in order, in words (e.g. "soft reset (0x18): ...").
    pub actions: Vec<String>,
}

/// Opens a serial port for a GRBL controller (8N1, short read timeout).
pub fn open_serial(path: &str, baud: u32) -> DeviceResult<Box<dyn serialport::SerialPort>> {
    open_stage_serial(DEVICE, path, baud, "check permissions (dialout group)")
}

fn status_state(s: &StatusReport) -> MachineState {
    s.state.unwrap_or(MachineState::Idle)
}

/// True for a line that was meant to be a status report (`<...>`, possibly cut).
fn looks_like_status(line: &[u8]) -> bool {
    line.first() == Some(&b'<') || line.last() == Some(&b'>')
}

impl<P: Read + Write> Grbl<P> {
    /// Connects in whatever state the controller is in, without changing it: waits
    /// for a status report (`?`, answered in every state but a critical alarm and a
    /// homing cycle); then, only where GRBL reads lines (Idle, Alarm, Check),
    /// resynchronises the reply stream (`$G`), reads the version (`$I`), the settings
    /// (`$$`) and, when reports carry `WPos`, the work offsets (`$#`). In a busy
    /// state (Run, Jog, Hold, Door, Home, Sleep) only `?` is used; the settings are
    /// read before the first move, once the controller is idle.
    ///
    /// A controller that answers nothing was most likely left in a critical alarm
    /// (hard or soft limit: it ignores everything but a soft reset): the error says so
    /// and that [`Grbl::connect_resetting`] (the CLI's `unlock`) resets it.
    pub fn connect(port: P, config: GrblConfig) -> DeviceResult<Self> {
        Self::connect_with(port, config, false)
    }

    /// [`Grbl::connect`], but a controller that answers no status report is sent a
    /// soft reset (0x18), the only thing a critical alarm answers; the reset is
    /// reported by [`Grbl::reset_at_connect`]. For `unlock`, not for `status`.
    pub fn connect_resetting(port: P, config: GrblConfig) -> DeviceResult<Self> {
        Self::connect_with(port, config, true)
    }

    fn connect_with(port: P, config: GrblConfig, reset_if_silent: bool) -> DeviceResult<Self> {
        let mut g = Grbl {
            port: LinePort::new(port, DEVICE),
            limits: config.limits.unwrap_or(UNBOUNDED),
            config,
            settings: None,
            wco_mm: None,
            alarm: None,
            needs_reset: false,
            needs_resync: true,
            resets_seen: 0,
            last_feedback: None,
            last_message: None,
            version: None,
            build_version: None,
            last_state: None,
            reset_at_connect: false,
            parser_state: None,
        };
        let status = match g.first_status() {
            Ok(s) => s,
            Err(e) if reset_if_silent && e.kind() == ErrorKind::Timeout => {
                g.soft_reset()?;
                g.reset_at_connect = true;
                g.status()?
            }
            Err(e) => return Err(e),
        };
        let state = status_state(&status);
        if state == MachineState::Alarm && g.alarm.is_none() {
            g.alarm = Some(0);
        }
        if reads_lines(state) {
            g.read_configuration(state)?;
        } else if status.wpos_mm.is_some() && g.wco_mm.is_none() {
            g.poll_for_wco()?;
        }
        Ok(g)
    }

    /// The first status report, asking every 250 ms for up to [`CONNECT_TIMEOUT`].
    fn first_status(&mut self) -> DeviceResult<StatusReport> {
        // A fixed number of attempts (not a deadline), so a recorded session
        // replays with the same number of `?`.
        let per_try = CONNECT_STATUS_INTERVAL.min(self.config.status_timeout);
        let tries = (CONNECT_TIMEOUT.as_millis() / CONNECT_STATUS_INTERVAL.as_millis()).max(1);
        let mut garbage = None;
        for _ in 0..tries {
            match self.status_once(per_try) {
                Ok(s) => return Ok(s),
                Err(e) if e.kind() == ErrorKind::Disconnected => return Err(e),
                Err(e) if e.kind() == ErrorKind::Protocol => garbage = Some(e.message),
                Err(_) => {}
            }
        }
        let secs = CONNECT_TIMEOUT.as_secs_f64();
        Err(match garbage {
            Some(g) => DeviceError::new(
                ErrorKind::Timeout,
                DEVICE,
                "?",
                format!("no status report within {secs} s; only unreadable bytes: {g}"),
            )
            .with_hint("is this a GRBL controller, at the right baud rate (115200)?"),
            None => DeviceError::new(
                ErrorKind::Timeout,
                DEVICE,
                "?",
                format!(
                    "no status report within {secs} s: the controller answers nothing. Likely cause: \
                     a critical alarm (ALARM:1 hard limit or ALARM:2 soft limit, \"Reset to continue\"), \
                     in which GRBL ignores everything, even `?`, until a soft reset"
                ),
            )
            .with_hint(
                "`tactbench stage --port PORT --protocol grbl unlock` resets it (0x18) and clears the alarm ($X); \
                 clear the cause first (limit switch, out-of-travel target). If that does not help: \
                 is this a GRBL controller, at 115200 baud?",
            ),
        })
    }

    /// True if the connection began with a soft reset of a silent controller
    /// ([`Grbl::connect_resetting`]).
    pub fn reset_at_connect(&self) -> bool {
        self.reset_at_connect
    }

    /// The state in the last status report seen.
    pub fn last_state(&self) -> Option<MachineState> {
        self.last_state
    }

    /// The work coordinate offset in use (MPos = WPos + WCO), once known.
    pub fn wco_mm(&self) -> Option<[f64; 3]> {
        self.wco_mm
    }

    /// The alarm code seen (0: the controller is in alarm, raised before this
    /// connection, code unknown); `None` when not in alarm.
    pub fn alarm(&self) -> Option<u8> {
        self.alarm
    }

    /// The firmware version: from `$I` (`1.1h.20190830`) when the controller answered
    /// it, else from the last banner seen (`1.1h`).
    pub fn version(&self) -> Option<&str> {
        self.build_version.as_deref().or(self.version.as_deref())
    }

    /// Settings (`$N` → value text); empty until read (a controller busy at
    /// connect is asked once it is idle).
    pub fn settings(&self) -> BTreeMap<u16, String> {
        self.settings.clone().unwrap_or_default()
    }

    /// Number of controller resets (banners) seen since connect.
    pub fn resets_seen(&self) -> u32 {
        self.resets_seen
    }

    /// The last `[MSG:..]` the controller pushed.
    pub fn last_message(&self) -> Option<&str> {
        self.last_message.as_deref()
    }

    /// The port back.
    pub fn into_inner(self) -> P {
        self.port.into_inner()
    }
}
