//! The GRBL driver's view of the controller's configuration: settings (`$$`), build
//! info (`$I`), work offsets (`$#`, `WCO:`), the travel box derived from `$130..$132`,
//! and the conversion of reported positions to machine coordinates.

use std::collections::BTreeMap;
use std::io::{Read, Write};

use super::codec::{
    active_coordinate_system, Command, MachineState, Offsets, Response, StatusReport,
};
use super::{
    codec, reads_lines, status_state, Grbl, CONNECT_RESYNC_TIMEOUT, DEVICE, UNBOUNDED,
    WCO_POLL_REPORTS,
};
use crate::device::{DeviceError, DeviceResult, ErrorKind, StagePositionMm, TravelLimits};

impl<P: Read + Write> Grbl<P> {
    /// In a state where GRBL reads lines: resync (`$G`, noting the active
    /// coordinate system), version (`$I`), settings (`$$`), offsets (`$#`, when
    /// reports carry `WPos`; in check mode GRBL refuses `$#` and a `WCO:` report is
    /// awaited instead).
    pub(super) fn read_configuration(&mut self, state: MachineState) -> DeviceResult<()> {
        self.resync_within(self.config.reply_timeout.min(CONNECT_RESYNC_TIMEOUT))?;
        // Check mode refuses `$I` and `$#` (error:8), as the real firmware does.
        if state != MachineState::Check {
            self.read_build_info()?;
        }
        self.read_settings()?;
        self.update_limits();
        if self.reports_wpos() && self.wco_mm.is_none() {
            if state == MachineState::Check {
                self.poll_for_wco()?;
            } else {
                self.read_offsets()?;
            }
        }
        Ok(())
    }

    /// True when the controller reports `WPos` (`$10` bit 0 clear).
    pub(super) fn reports_wpos(&self) -> bool {
        self.settings
            .as_ref()
            .and_then(|s| s.get(&10))
            .and_then(|v| v.parse::<u32>().ok())
            .is_some_and(|m| m & 1 == 0)
    }

    /// The travel box: GRBL's soft-limit box `[-$13x, 0]` where homing (`$22=1`) and
    /// soft limits (`$20=1`) are both on, intersected with the configured (bench)
    /// box; otherwise the configured box alone (unbounded without one: GRBL then
    /// accepts any coordinate and so does the driver).
    pub(super) fn update_limits(&mut self) {
        let mut lim = self.config.limits.unwrap_or(UNBOUNDED);
        if let Some(grbl_box) = self.soft_limit_box() {
            for i in 0..3 {
                lim.axes_mm[i][0] = lim.axes_mm[i][0].max(grbl_box.axes_mm[i][0]);
                lim.axes_mm[i][1] = lim.axes_mm[i][1].min(grbl_box.axes_mm[i][1]);
            }
        }
        self.limits = lim;
    }

    /// GRBL's soft-limit box, if the controller enforces one (`$20=1` and `$22=1`).
    pub fn soft_limit_box(&self) -> Option<TravelLimits> {
        let s = self.settings.as_ref()?;
        let flag = |n: u16| s.get(&n).and_then(|v| v.parse::<f64>().ok()) == Some(1.0);
        if !(flag(20) && flag(22)) {
            return None;
        }
        let mut axes_mm = [[0.0; 2]; 3];
        for (i, axis) in axes_mm.iter_mut().enumerate() {
            let v: f64 = s
                .get(&(130 + i as u16))
                .and_then(|v| v.parse().ok())
                .filter(|v: &f64| v.is_finite() && *v > 0.0)?;
            *axis = [-v, 0.0];
        }
        Some(TravelLimits { axes_mm })
    }

    /// Makes sure the settings (and so the travel limits) are known before a move:
    /// a controller connected while busy is asked now (it must be idle or in alarm).
    pub(super) fn ensure_settings(&mut self, command: &str) -> DeviceResult<()> {
        if self.settings.is_some() {
            return Ok(());
        }
        let s = self.status()?;
        let state = status_state(&s);
        if !reads_lines(state) {
            return Err(self.state_error(command, state));
        }
        self.read_configuration(state)
    }

    /// `$I`: the build version (`[VER:1.1h.20190830:]`).
    pub(super) fn read_build_info(&mut self) -> DeviceResult<()> {
        self.last_feedback = None;
        let version = self.query_lines(&Command::BuildInfo, |v: &mut Option<String>, r| {
            if let Response::Feedback(f) = r {
                if let Some(b) = codec::build_version(f) {
                    *v = Some(b.to_string());
                }
            }
        })?;
        if version.is_some() {
            self.build_version = version;
        }
        Ok(())
    }

    /// `$#` (and `$G` for the active coordinate system): the work coordinate offset.
    pub(super) fn read_offsets(&mut self) -> DeviceResult<()> {
        let offsets = self.query_lines(&Command::Offsets, |o: &mut Offsets, r| {
            if let Response::Feedback(f) = r {
                o.take(f);
            }
        })?;
        if self.parser_state.is_none() {
            self.query_lines(&Command::ParserState, |_: &mut (), _| {})?;
        }
        let system = self
            .parser_state
            .as_deref()
            .and_then(active_coordinate_system)
            .unwrap_or(0);
        match offsets.wco_mm(system) {
            Some(w) => {
                self.wco_mm = Some(w);
                Ok(())
            }
            None => Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                "$#",
                "the `$#` listing lacks the active coordinate system, G92 or TLO offset",
            )),
        }
    }

    /// Polls `?` until a report carries `WCO:` (GRBL sends it every 10 reports when
    /// idle, every 30 when busy): works in every state that answers `?`.
    pub(super) fn poll_for_wco(&mut self) -> DeviceResult<()> {
        for _ in 0..WCO_POLL_REPORTS {
            let s = self.status()?;
            if s.mpos_mm.is_some() || self.wco_mm.is_some() {
                return Ok(());
            }
        }
        Err(DeviceError::new(
            ErrorKind::Protocol,
            DEVICE,
            "?",
            format!(
                "no `WCO:` field in {WCO_POLL_REPORTS} status reports: cannot convert the reported work position (WPos) to machine position"
            ),
        )
        .with_hint("set `$10=1` on the controller to report machine positions (MPos)"))
    }

    /// Machine position from a report: MPos, or WPos + WCO when the controller
    /// reports WPos (`$10=0`). A WCO not yet seen is asked for (`$#` where GRBL
    /// answers it, else a report carrying `WCO:`), never assumed zero.
    pub(super) fn mpos_of(&mut self, s: &StatusReport) -> DeviceResult<StagePositionMm> {
        match (s.mpos_mm, s.wpos_mm) {
            (Some(m), _) => Ok(m),
            (None, Some(w)) => {
                if self.wco_mm.is_none() {
                    let state = status_state(s);
                    if matches!(state, MachineState::Idle | MachineState::Alarm) {
                        self.read_offsets()?;
                    } else {
                        self.poll_for_wco()?;
                    }
                }
                let c = self.wco_mm.unwrap_or([0.0; 3]);
                Ok([w[0] + c[0], w[1] + c[1], w[2] + c[2]])
            }
            // parse_status guarantees one of the two.
            (None, None) => Err(DeviceError::new(
                ErrorKind::Protocol,
                DEVICE,
                "?",
                "status report without a position",
            )),
        }
    }

    pub(super) fn read_settings(&mut self) -> DeviceResult<()> {
        let settings =
            self.query_lines(&Command::Settings, |m: &mut BTreeMap<u16, String>, r| {
                if let Response::Setting { number, value } = r {
                    m.insert(*number, value.clone());
                }
            })?;
        self.settings = Some(settings);
        Ok(())
    }
}
