//! One served run as the live view shows it ([`RunView`]): the record (manifest and
//! journal, read incrementally from the end it last read), the runner's activity
//! (`live.json`, or the runner's events in-process) and the newest evidence (the last
//! measured setpoint's frame, marker statuses and force field). Memory is bounded
//! whatever the run's length: plotted series are decimated to [`MAX_PLOT_POINTS`]
//! (every other point dropped and the stride doubled when full, so a 10 000-setpoint
//! run keeps an even sample of the whole run plus its latest point), and journal
//! rows are not kept (the API reads them from the journal on request).

use std::collections::VecDeque;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use serde::Serialize;
use serde_json::{json, Value};

use super::LiveError;
use crate::bench::journal::{JournalRow, Manifest, RunStatus, JOURNAL_FILE, MANIFEST_FILE};
use crate::bench::live::{parse_rfc3339, LiveDoc, Phase};
use crate::bench::lock::{self, LockState};
use crate::bench::plan::{Plan, Sweep};
use crate::bench::runner::RunEvent;
use crate::report::acceptance::{Criteria, Outcome};
use crate::sensor::{CameraMapping, Sensor};
use crate::units::ForceUnit;

/// Most points kept per plotted series.
pub const MAX_PLOT_POINTS: usize = 1000;

/// Shortest interval between two evidence updates (frame, markers, force field): a
/// run faster than this shows every other setpoint's evidence (decimated), never lags.
pub const EVIDENCE_INTERVAL_S: f64 = 0.5;

/// A series that keeps at most `cap` evenly spaced points of everything pushed.
#[derive(Debug, Clone)]
pub struct Decimated<T> {
    items: Vec<T>,
    stride: usize,
    seen: usize,
    cap: usize,
}

impl<T> Decimated<T> {
    /// An empty series of at most `cap` (≥ 2) points.
    pub fn new(cap: usize) -> Self {
        Decimated {
            items: Vec::new(),
            stride: 1,
            seen: 0,
            cap: cap.max(2),
        }
    }
    /// Adds a point (kept when it falls on the current stride).
    pub fn push(&mut self, t: T) {
        if self.seen.is_multiple_of(self.stride) {
            self.items.push(t);
            if self.items.len() > self.cap {
                let mut i = 0;
                self.items.retain(|_| {
                    i += 1;
                    (i - 1) % 2 == 0
                });
                self.stride *= 2;
            }
        }
        self.seen += 1;
    }
    /// The kept points.
    pub fn items(&self) -> &[T] {
        &self.items
    }
    /// Points pushed in all.
    pub fn seen(&self) -> usize {
        self.seen
    }
    /// Every `stride`-th point is kept.
    pub fn stride(&self) -> usize {
        self.stride
    }
}

/// Applied against measured, one journal row: `[index, applied, measured,
/// applied tangential, measured tangential]` (forces in the plan's unit).
type PlotPoint = [f64; 5];
/// Marker health of one row: `[index, ok, lost, merged, outlier]`.
type HealthPoint = [f64; 5];

/// The newest evidence: one setpoint's first frame, its markers and its force field.
#[derive(Debug, Clone, Serialize)]
pub struct Evidence {
    /// Setpoint index.
    pub index: usize,
    /// The frame, relative to the run directory (`frames/NNNNN_0.png`).
    pub frame: Option<String>,
    /// Image size, px.
    pub size_px: [u32; 2],
    /// Markers: `[x_px, y_px, ux_px, uy_px, status]` (status 0 ok, 1 lost, 2 merged,
    /// 3 outlier; displacement 0 when not measured).
    pub markers: Vec<[f64; 5]>,
    /// Force-grid nodes: `[x_mm, y_mm, fx, fy, fz]` (forces in the plan's unit).
    pub forces: Vec<[f64; 5]>,
    /// What could not be shown, in one line each.
    pub missing: Vec<String>,
}

/// One served run.
pub struct RunView {
    /// The run directory as given.
    pub dir: PathBuf,
    /// Its canonical path (what file requests are confined to).
    pub root: PathBuf,
    manifest: Manifest,
    manifest_mtime: Option<SystemTime>,
    plan: Option<Plan>,
    unit: ForceUnit,
    camera: Option<CameraMapping>,
    criteria: Option<Criteria>,
    /// The runner's activity: from events (in-process) or `live.json`.
    live: LiveDoc,
    in_process: bool,
    /// `live.json` was last seen with this modification time.
    live_mtime: Option<SystemTime>,
    journal_offset: u64,
    journal_header: Option<String>,
    rows: usize,
    /// Rows not plotted: no finite applied or measured force.
    unplotted: usize,
    last_row: Option<JournalRow>,
    points: Decimated<PlotPoint>,
    health: Decimated<HealthPoint>,
    evidence: Option<Evidence>,
    evidence_at: Option<Instant>,
    /// A newer setpoint than the evidence shows was measured.
    evidence_due: bool,
    series_version: u64,
    evidence_version: u64,
    verdict: Option<Value>,
    verdict_rows: usize,
    verdict_cost_s: f64,
    verdict_at: Option<Instant>,
    report: bool,
    /// The directory is gone (or unreadable): why.
    error: Option<String>,
    /// Warnings from the file reads (torn line, bad live.json), newest last.
    notes: VecDeque<String>,
    /// The pid `live.json` names.
    live_pid: Option<u32>,
    /// The pid of the process holding `run.lock`, when it recorded one.
    holder_pid: Option<u32>,
    /// The run is on the simulated bench.
    simulated: bool,
    /// The manifest's `write_failure` (issue 23), when recorded.
    write_failure: Value,
    /// A process holds `run.lock` (or the run is in this process).
    writer_alive: bool,
    /// `live.json` is the lock holder's (not a stale one from an earlier session).
    live_trusted: bool,
}

impl RunView {
    /// Opens a run directory: it must hold a readable `manifest.json` (a run). The
    /// journal, `live.json` and evidence are read by [`RunView::refresh`].
    pub fn open(dir: &Path, criteria: Option<Criteria>) -> Result<RunView, LiveError> {
        if !dir.is_dir() {
            return Err(LiveError::NotARun {
                dir: dir.to_path_buf(),
                why: "no such directory".into(),
            });
        }
        let manifest = Manifest::read(dir).map_err(|e| LiveError::NotARun {
            dir: dir.to_path_buf(),
            why: if dir.join(MANIFEST_FILE).exists() {
                e.to_string()
            } else {
                "it has no manifest.json (not a directory written by `tactbench run`)".into()
            },
        })?;
        let root = dir.canonicalize().map_err(|source| LiveError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
        let mut v = RunView {
            dir: dir.to_path_buf(),
            root,
            manifest,
            manifest_mtime: None,
            plan: None,
            unit: ForceUnit::Newton,
            camera: None,
            criteria,
            live: LiveDoc::new(),
            in_process: false,
            live_mtime: None,
            journal_offset: 0,
            journal_header: None,
            rows: 0,
            unplotted: 0,
            last_row: None,
            points: Decimated::new(MAX_PLOT_POINTS),
            health: Decimated::new(MAX_PLOT_POINTS),
            evidence: None,
            evidence_at: None,
            evidence_due: false,
            series_version: 1,
            evidence_version: 1,
            verdict: None,
            verdict_rows: usize::MAX,
            verdict_cost_s: 0.0,
            verdict_at: None,
            report: false,
            error: None,
            notes: VecDeque::new(),
            live_pid: None,
            holder_pid: None,
            simulated: false,
            write_failure: Value::Null,
            writer_alive: false,
            live_trusted: false,
        };
        v.take_manifest();
        Ok(v)
    }

    /// The run is fed by the runner's events in this process (`run --serve`):
    /// `live.json` is not read.
    pub fn set_in_process(&mut self) {
        self.in_process = true;
        self.holder_pid = Some(std::process::id());
        self.writer_alive = true;
        self.live_trusted = true;
    }

    fn take_manifest(&mut self) {
        // Fields other issues add to the manifest (`simulated`, `write_failure`),
        // shown when present: read from the raw document, not the typed one.
        let raw: Value = std::fs::read_to_string(self.dir.join(MANIFEST_FILE))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or(Value::Null);
        self.simulated = raw
            .get("simulated")
            .and_then(Value::as_bool)
            .unwrap_or_else(|| simulated(&self.manifest));
        self.write_failure = raw.get("write_failure").cloned().unwrap_or(Value::Null);
        let m = &self.manifest;
        self.plan = Plan::from_toml_str(&m.plan_toml, &m.plan_path).ok();
        self.unit = self
            .plan
            .as_ref()
            .map_or(ForceUnit::Newton, |p| p.force_unit);
        self.camera = Sensor::from_toml_str(&m.sensor_toml, &m.sensor_path)
            .ok()
            .map(|s| s.camera);
        if self.in_process {
            return;
        }
        self.live.setpoints_total = m.setpoints;
        if m.status != RunStatus::Running {
            self.live.state = m.status;
            self.live.end_reason = m.end_reason.clone();
        }
    }

    fn note(&mut self, n: String) {
        if self.notes.back() != Some(&n) {
            if self.notes.len() == 10 {
                self.notes.pop_front();
            }
            self.notes.push_back(n);
        }
    }

    /// Takes a runner event (in-process). Returns whether the record should be read
    /// again now (a row was journalled or the run ended).
    pub fn apply(&mut self, e: &RunEvent) -> bool {
        self.live.apply(e);
        matches!(
            e,
            RunEvent::SetpointMeasured { .. }
                | RunEvent::Finished { .. }
                | RunEvent::Started { .. }
        )
    }

    /// Reads what changed in the run directory: the manifest (when its modification
    /// time changed), new journal lines, `live.json` (another process's run), the
    /// writer's liveness, the newest evidence (rate-limited) and `report.html`.
    /// Returns whether anything the page shows changed.
    pub fn refresh(&mut self) -> bool {
        if !self.dir.is_dir() {
            let was = self.error.is_some();
            self.error = Some(format!(
                "{}: the run directory disappeared while served",
                self.dir.display()
            ));
            return !was;
        }
        let mut changed = false;
        if self.error.take().is_some() {
            changed = true;
        }
        let mpath = self.dir.join(MANIFEST_FILE);
        let mtime = std::fs::metadata(&mpath).and_then(|m| m.modified()).ok();
        if mtime != self.manifest_mtime {
            match Manifest::read(&self.dir) {
                Ok(m) => {
                    self.manifest_mtime = mtime;
                    self.manifest = m;
                    self.take_manifest();
                    changed = true;
                }
                Err(e) => {
                    // Replaced atomically by the runner, so a failure is real.
                    self.error = Some(e.to_string());
                    return true;
                }
            }
        }
        changed |= self.read_journal_tail();
        if !self.in_process {
            changed |= self.read_live_file();
        }
        if self.evidence_due
            && self
                .evidence_at
                .is_none_or(|t| t.elapsed().as_secs_f64() >= EVIDENCE_INTERVAL_S)
        {
            self.read_evidence();
            changed = true;
        }
        let report = self.dir.join("report.html").is_file();
        if report != self.report {
            self.report = report;
            changed = true;
        }
        changed
    }

    /// Whether a newer setpoint's evidence is waiting for the rate limit.
    pub fn evidence_pending(&self) -> bool {
        self.evidence_due
    }

    fn read_journal_tail(&mut self) -> bool {
        let path = self.dir.join(JOURNAL_FILE);
        let mut f = match std::fs::File::open(&path) {
            Ok(f) => f,
            Err(_) => return false,
        };
        let len = f.metadata().map(|m| m.len()).unwrap_or(0);
        if len < self.journal_offset {
            // Cut by a resume (a torn line): read it again from the start.
            self.reset_rows();
        }
        if len == self.journal_offset {
            return false;
        }
        if f.seek(SeekFrom::Start(self.journal_offset)).is_err() {
            return false;
        }
        let mut bytes = Vec::new();
        // At most 4 MiB per refresh, so a huge finished journal is read in steps.
        if f.take(4 << 20).read_to_end(&mut bytes).is_err() {
            return false;
        }
        let Some(end) = bytes.iter().rposition(|&b| b == b'\n') else {
            return false;
        };
        let chunk = &bytes[..=end];
        self.journal_offset += chunk.len() as u64;
        let text = String::from_utf8_lossy(chunk);
        let body = match &self.journal_header {
            Some(h) => format!("{h}\n{text}"),
            None => {
                let (h, _) = text.split_once('\n').unwrap_or((&text, ""));
                self.journal_header = Some(h.trim_end_matches('\r').to_string());
                text.into_owned()
            }
        };
        let mut rdr = csv::Reader::from_reader(body.as_bytes());
        let mut any = false;
        for rec in rdr.deserialize::<JournalRow>() {
            match rec {
                Ok(row) => {
                    self.take_row(row);
                    any = true;
                }
                Err(e) => {
                    let n = format!("{}: a line the live view cannot read: {e}", path.display());
                    self.note(n);
                }
            }
        }
        any
    }

    fn reset_rows(&mut self) {
        self.journal_offset = 0;
        self.journal_header = None;
        self.rows = 0;
        self.unplotted = 0;
        self.last_row = None;
        self.points = Decimated::new(MAX_PLOT_POINTS);
        self.health = Decimated::new(MAX_PLOT_POINTS);
        self.series_version += 1;
    }

    fn take_row(&mut self, row: JournalRow) {
        // A row without a finite value in the plotted series (a failed reconstruction
        // leaves its force sums empty; older journals wrote NaN) is counted, not
        // plotted: serialised, a NaN becomes `null`, which the page drew at 0.
        match plot_point(&row, self.unit) {
            Some(p) => self.points.push(p),
            None => self.unplotted += 1,
        }
        let c = |v: Option<usize>| v.map(|v| v as f64);
        if let (Some(ok), Some(lost), Some(merged), Some(outlier)) = (
            c(row.markers_ok),
            c(row.markers_lost),
            c(row.markers_merged),
            c(row.markers_outlier),
        ) {
            self.health
                .push([row.index as f64, ok, lost, merged, outlier]);
        }
        self.rows += 1;
        self.series_version += 1;
        self.last_row = Some(row);
        self.evidence_due = true;
    }

    fn read_live_file(&mut self) -> bool {
        let mtime = std::fs::metadata(self.dir.join(crate::bench::live::LIVE_FILE))
            .and_then(|m| m.modified())
            .ok();
        let mut changed = false;
        if mtime != self.live_mtime {
            self.live_mtime = mtime;
            match LiveDoc::read(&self.dir) {
                Ok(Some(doc)) => {
                    self.live_pid = Some(doc.pid);
                    self.live = doc;
                    changed = true;
                }
                Ok(None) => {}
                // Replaced by rename, so never half-written: a real problem, shown.
                Err(e) => self.note(e.to_string()),
            }
        }
        // The writer is the process holding run.lock; live.json is trusted only when
        // it is that process's (a stale file of a killed session says nothing).
        let holder = match lock::probe(&self.dir) {
            Ok(LockState::Held(h)) => Some(h.pid),
            _ => None,
        };
        let alive = holder.is_some();
        let trusted = match holder {
            Some(Some(h)) => self.live_pid == Some(h),
            Some(None) => self.live_pid.is_some_and(pid_alive),
            None => false,
        };
        let holder_pid = holder.flatten();
        if (alive, trusted, holder_pid) != (self.writer_alive, self.live_trusted, self.holder_pid) {
            self.writer_alive = alive;
            self.live_trusted = trusted;
            self.holder_pid = holder_pid;
            changed = true;
        }
        changed
    }

    fn read_evidence(&mut self) {
        self.evidence_due = false;
        self.evidence_at = Some(Instant::now());
        let Some(row) = &self.last_row else { return };
        let index = row.index;
        let mut ev = Evidence {
            index,
            frame: None,
            size_px: self.camera.map_or([0, 0], |c| [c.width_px, c.height_px]),
            markers: Vec::new(),
            forces: Vec::new(),
            missing: Vec::new(),
        };
        let dpath = crate::analysis::displacements_path(&self.dir, index);
        match read_markers(&dpath, self.camera.as_ref()) {
            Ok((frame, markers)) => {
                ev.frame = frame;
                ev.markers = markers;
            }
            Err(e) => ev.missing.push(format!("markers: {e}")),
        }
        if ev.frame.is_none() {
            ev.frame = row
                .frames
                .split(';')
                .next()
                .filter(|s| !s.is_empty())
                .map(str::to_string);
        }
        if let Some(f) = &ev.frame {
            if !self.dir.join(f).is_file() {
                ev.missing.push(format!("frame: {f} is missing"));
                ev.frame = None;
            }
        }
        let fpath = crate::analysis::forces_path(&self.dir, index);
        match crate::formats::read_forces(&fpath) {
            Ok(recs) => {
                let u = |v: f64| self.unit.from_newtons(v);
                ev.forces = recs
                    .iter()
                    .map(|r| {
                        [
                            r.position_mm[0],
                            r.position_mm[1],
                            u(r.f_n[0]),
                            u(r.f_n[1]),
                            u(r.f_n[2]),
                        ]
                    })
                    .collect();
            }
            Err(e) => ev.missing.push(format!("force field: {e}")),
        }
        self.evidence = Some(ev);
        self.evidence_version += 1;
    }

    /// Recomputes the provisional verdict when criteria were given and rows were
    /// added, at most once per 20 times its own cost (at least every 2 s): the
    /// analysis of a long run is not free, and the live view must not compete with
    /// the acquisition for the CPU. Returns whether it changed.
    pub fn refresh_verdict(&mut self) -> bool {
        let Some(criteria) = &self.criteria else {
            return false;
        };
        if self.rows == self.verdict_rows || self.rows == 0 {
            return false;
        }
        let wait = (20.0 * self.verdict_cost_s).max(2.0);
        if self
            .verdict_at
            .is_some_and(|t| t.elapsed().as_secs_f64() < wait)
            && self.live.state == RunStatus::Running
        {
            return false;
        }
        let t0 = Instant::now();
        let v = provisional_verdict(&self.dir, criteria);
        self.verdict_cost_s = t0.elapsed().as_secs_f64();
        self.verdict_at = Some(Instant::now());
        self.verdict_rows = self.rows;
        self.verdict = Some(v);
        true
    }

    /// The run's state word: the runner's own while a writer is live (or
    /// in-process), else the manifest's; `killed` when the manifest says running but
    /// no process writes the run (as `report` says), `missing` when the directory is
    /// gone.
    pub fn state_word(&self) -> &'static str {
        if self.error.is_some() && !self.dir.is_dir() {
            return "missing";
        }
        let status = if self.in_process || (self.writer_alive && self.live_trusted) {
            self.live.state
        } else if self.writer_alive {
            RunStatus::Running
        } else {
            self.manifest.status
        };
        match status {
            RunStatus::Running if self.in_process || self.writer_alive => "running",
            RunStatus::Running => "killed",
            RunStatus::Completed => "completed",
            RunStatus::Interrupted => "interrupted",
            RunStatus::Aborted => "aborted",
        }
    }

    /// Whether a process is writing the run (in-process, or the holder of its lock).
    pub fn writer_alive(&self) -> bool {
        self.in_process || self.writer_alive
    }

    /// The pid of the process writing the run, when one is.
    pub fn writer_pid(&self) -> Option<u32> {
        self.writer_alive()
            .then_some(self.holder_pid.or(self.live_pid))
            .flatten()
    }

    /// Changes of the plotted series (a row added, the journal read again).
    pub fn series_version(&self) -> u64 {
        self.series_version
    }

    /// Changes of the evidence.
    pub fn evidence_version(&self) -> u64 {
        self.evidence_version
    }

    /// The decimated plot series: `{"run", "rows", "unplotted", "points",
    /// "points_stride", "health", "health_stride"}` (points: `[index, applied,
    /// measured, applied tangential, measured tangential]`, every value finite;
    /// `unplotted`: rows without finite forces, left out; health: `[index, ok, lost,
    /// merged, outlier]` of rows with marker counts).
    pub fn series_json(&self, run: usize) -> Value {
        json!({
            "run": run,
            "unit": self.unit.symbol(),
            "points": self.points.items(),
            "points_stride": self.points.stride(),
            "rows": self.rows,
            "unplotted": self.unplotted,
            "health": self.health.items(),
            "health_stride": self.health.stride(),
        })
    }

    /// The newest evidence: `{"run", "evidence": {index, frame, size_px, markers,
    /// forces, missing} | null}`.
    pub fn evidence_json(&self, run: usize) -> Value {
        json!({ "run": run, "unit": self.unit.symbol(), "evidence": self.evidence })
    }

    /// The newest evidence frame, relative to the run directory.
    pub fn evidence_frame(&self) -> Option<&str> {
        self.evidence.as_ref().and_then(|e| e.frame.as_deref())
    }

    /// The state document of `GET /api/state` (and of each pushed `state` update).
    pub fn state_json(&self, run: usize) -> Value {
        let m = &self.manifest;
        // The runner's own fields (phase, readings) only from a live, trusted source.
        let live_run = self.writer_alive()
            && (self.in_process || self.live_trusted)
            && self.state_word() == "running";
        let done = self.rows.max(if self.in_process {
            self.live.setpoints_done
        } else {
            0
        });
        let total = if self.live.setpoints_total > 0 && live_run {
            self.live.setpoints_total
        } else {
            m.setpoints
        };
        let now = now_s();
        // Elapsed and remaining time over this session (the last start or resume).
        let session_start = m
            .resumed_at
            .last()
            .or(Some(&m.started_at))
            .and_then(|s| parse_rfc3339(s));
        let end = m.ended_at.as_deref().and_then(parse_rfc3339);
        let elapsed_s = session_start.map(|s| {
            if live_run {
                now - s
            } else {
                end.unwrap_or(now) - s
            }
        });
        let measured_session = done.saturating_sub(m.measured_setpoints.min(done));
        let session_done = if m.resumed_at.is_empty() {
            done
        } else {
            measured_session
        };
        let remaining_s = match (elapsed_s, live_run) {
            (Some(e), true) if session_done > 0 => {
                Some(e / session_done as f64 * total.saturating_sub(done) as f64)
            }
            _ => None,
        };
        let phase = if live_run {
            self.live.phase
        } else {
            Phase::Idle
        };
        let phase_s = parse_rfc3339(&self.live.phase_started_at).map(|t| (now - t).max(0.0));
        json!({
            "run": run,
            "dir": self.dir.display().to_string(),
            "plan": m.plan_name,
            "sweep": self.plan.as_ref().map(sweep_kind),
            "unit": self.unit.symbol(),
            "state": self.state_word(),
            "setpoints_done": done,
            "setpoints_total": total,
            "setpoint_index": if live_run { self.live.setpoint_index } else { None },
            "phase": phase.name(),
            "phase_s": if live_run { phase_s } else { None },
            "elapsed_s": elapsed_s,
            "remaining_s": remaining_s,
            "started_at": m.started_at,
            "ended_at": m.ended_at,
            "ft": if live_run { self.live.ft } else { None },
            "stage_mm": if live_run { self.live.stage_mm } else { None },
            "warnings": self.live.warnings,
            "end_reason": m.end_reason.clone().or_else(|| self.live.end_reason.clone()),
            "writer_pid": self.writer_pid(),
            "stop_allowed": live_run,
            "build_id": m.build_id,
            "simulated": self.simulated,
            "write_failure": self.write_failure,
            "report": self.report.then_some("report.html"),
            "notes": self.notes,
            "error": self.error,
            "last_row": self.last_row.as_ref().map(|r| row_json(r, self.unit)),
            "verdict": self.verdict,
        })
    }

    /// The manifest as last read.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }
}

/// Whether the bench description names a `[sim]` scene (manifests without issue
/// 23's `simulated` field).
fn simulated(m: &Manifest) -> bool {
    m.bench.get("sim").is_some_and(|s| !s.is_null())
}

fn sweep_kind(p: &Plan) -> &'static str {
    match p.sweep {
        Sweep::Magnitude { .. } => "magnitude",
        Sweep::Angle { .. } => "angle",
        Sweep::Spatial { .. } => "spatial",
        Sweep::Displacement { .. } => "displacement",
        Sweep::Setpoints(_) => "setpoints",
        Sweep::Hold { .. } => "hold",
    }
}

/// A journal force column as an `Option` (empty or not finite: `None`), whether the
/// journal row holds it as `f64` (NaN when missing) or as `Option<f64>`.
trait Column {
    fn get(self) -> Option<f64>;
}

impl Column for f64 {
    fn get(self) -> Option<f64> {
        finite(self)
    }
}

impl Column for Option<f64> {
    fn get(self) -> Option<f64> {
        self.and_then(finite)
    }
}

/// One row's point of the applied-against-measured plot (plan's unit), or `None`
/// when a value of it is missing or not finite.
fn plot_point(r: &JournalRow, unit: ForceUnit) -> Option<PlotPoint> {
    let u = |v: f64| finite(unit.from_newtons(v));
    let (fx, fy, fz) = (r.fx_n.get()?, r.fy_n.get()?, r.fz_n.get()?);
    let (sx, sy, sz) = (r.fsum_x_n.get()?, r.fsum_y_n.get()?, r.fsum_z_n.get()?);
    Some([
        r.index as f64,
        u(fz)?,
        u(sz)?,
        u(fx.hypot(fy))?,
        u(sx.hypot(sy))?,
    ])
}

/// A journal row for the page (forces in the plan's unit).
pub fn row_json(r: &JournalRow, unit: ForceUnit) -> Value {
    let u = |v: f64| finite(unit.from_newtons(v));
    let c = |v: Option<f64>| v.and_then(u);
    json!({
        "index": r.index,
        "trial": r.trial,
        "target": [u(r.target_tx_n), u(r.target_ty_n), u(r.target_normal_n)],
        "ft": [c(r.fx_n.get()), c(r.fy_n.get()), c(r.fz_n.get())],
        "fsum": [c(r.fsum_x_n.get()), c(r.fsum_y_n.get()), c(r.fsum_z_n.get())],
        "stage_mm": [finite(r.stage_x_mm), finite(r.stage_y_mm), finite(r.stage_z_mm)],
        "settled": r.settled,
        "markers": [r.markers_ok, r.markers_lost, r.markers_merged, r.markers_outlier],
        "quality": r.quality,
        "completed_at": r.completed_at,
    })
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// Whether a process with this pid exists (signal 0 checks without sending).
pub fn pid_alive(pid: u32) -> bool {
    let Ok(pid) = libc::pid_t::try_from(pid) else {
        return false;
    };
    if pid <= 0 {
        return false;
    }
    // SAFETY: kill with signal 0 only checks whether the process exists.
    let rc = unsafe { libc::kill(pid, 0) };
    rc == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM)
}

/// The first frame's markers of a track file (`displacements/NNNNN.csv`) and that
/// frame's path: `[x_px, y_px, ux_px, uy_px, status]` per marker.
#[allow(clippy::type_complexity)]
fn read_markers(
    path: &Path,
    cam: Option<&CameraMapping>,
) -> Result<(Option<String>, Vec<[f64; 5]>), String> {
    let mut rd = csv::Reader::from_path(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let headers = rd
        .headers()
        .map_err(|e| format!("{}: {e}", path.display()))?
        .clone();
    let col = |name: &str| headers.iter().position(|h| h == name);
    let (Some(cf), Some(cx), Some(cy), Some(cux), Some(cuy), Some(cs)) = (
        col("frame"),
        col("x_px"),
        col("y_px"),
        col("ux_px"),
        col("uy_px"),
        col("status"),
    ) else {
        return Err(format!("{} has no tracker columns", path.display()));
    };
    let (cxm, cym) = (col("x_mm"), col("y_mm"));
    let num = |s: Option<&str>| {
        s.and_then(|s| s.trim().parse::<f64>().ok())
            .filter(|v| v.is_finite())
    };
    let mut frame: Option<String> = None;
    let mut out = Vec::new();
    for rec in rd.records() {
        let rec = rec.map_err(|e| format!("{}: {e}", path.display()))?;
        let f = rec.get(cf).unwrap_or("").to_string();
        match &frame {
            None => frame = Some(f),
            Some(first) if *first != f => break,
            _ => {}
        }
        let xy = match (num(rec.get(cx)), num(rec.get(cy))) {
            (Some(x), Some(y)) => [x, y],
            _ => match (
                cam,
                cxm.and_then(|c| num(rec.get(c))),
                cym.and_then(|c| num(rec.get(c))),
            ) {
                (Some(c), Some(xm), Some(ym)) => [
                    xm / c.mm_per_px + c.origin_px[0],
                    ym / c.mm_per_px + c.origin_px[1],
                ],
                _ => continue,
            },
        };
        let u = [
            num(rec.get(cux)).unwrap_or(0.0),
            num(rec.get(cuy)).unwrap_or(0.0),
        ];
        let status = match rec.get(cs).unwrap_or("").trim() {
            "ok" => 0.0,
            "lost" => 1.0,
            "merged" => 2.0,
            _ => 3.0,
        };
        out.push([xy[0], xy[1], u[0], u[1], status]);
    }
    Ok((frame.filter(|f| !f.is_empty()), out))
}

/// The verdict so far: the run directory analysed as it is now and judged by the
/// criteria, every outcome marked provisional while the run is not complete.
fn provisional_verdict(dir: &Path, criteria: &Criteria) -> Value {
    let analysis = match crate::analysis::RunAnalysis::load(dir, &Default::default()) {
        Ok(a) => a,
        Err(e) => return json!({ "error": format!("not judged yet: {e}") }),
    };
    let metrics = analysis.metrics();
    match criteria.evaluate(&metrics, analysis.run.sweep_kind(), &analysis.absent) {
        Ok(vs) => {
            // A criterion nothing judged (no fit during a run) keeps it NOT JUDGED.
            let mut worst =
                (!vs.is_empty()).then(|| Outcome::combine(vs.iter().map(|v| v.outcome)));
            // Failed rows (no force) are skipped and counted: at most MARGINAL.
            let failed: Vec<String> = analysis.run.failed.iter().map(|f| f.describe()).collect();
            if !failed.is_empty() {
                worst = worst.map(|o| Outcome::combine([o, Outcome::Marginal]));
            }
            json!({
                "criteria": criteria.path.display().to_string(),
                "overall": worst.map(|o| o.word()),
                "failed_rows": failed,
                "rows": vs.iter().map(|v| {
                    let (lo, hi) = v.limits();
                    json!({
                        "metric": v.criterion.metric,
                        "value": finite(v.value),
                        "unit": v.unit,
                        "min": lo,
                        "max": hi,
                        "marginal_min": v.criterion.marginal_min,
                        "marginal_max": v.criterion.marginal_max,
                        "outcome": v.outcome.word(),
                        "note": v.note,
                    })
                }).collect::<Vec<_>>(),
            })
        }
        Err(e) => json!({ "error": e.to_string() }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_decimated_series_stays_bounded_and_even_over_ten_thousand_points() {
        let mut d = Decimated::new(100);
        for i in 0..10_000 {
            d.push(i);
        }
        assert!(d.items().len() <= 100, "{}", d.items().len());
        assert!(d.items().len() > 50);
        assert_eq!(d.seen(), 10_000);
        let s = d.stride();
        assert!(d.items().iter().enumerate().all(|(k, v)| *v == k * s));
    }
}
