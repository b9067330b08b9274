//! The HTTP side of the live view, on `tiny_http` (small, blocking, no async
//! runtime: one thread per connection fits a pushed stream per viewer).
//!
//! Routes (run `I` is the I-th run directory given, from 0; the routes without
//! `/runs/I` are run 0's):
//!
//! | route | answer |
//! |---|---|
//! | `GET /` | the page ([`super::page::PAGE`]) |
//! | `GET /api/state`, `/api/runs/I/state` | the run's state (JSON; `runs`: how many are served) |
//! | `GET /api/runs` | every run's state (JSON array) |
//! | `GET /api/journal?from=K&limit=N`, `/api/runs/I/journal` | journal rows with `index ≥ K` (at most N, default 1000, at most 10000), as in `journal.csv` (SI units) |
//! | `GET /api/frame.png`, `/api/runs/I/frame.png` | the newest evidence frame (PNG) |
//! | `GET /api/events` | server-sent events: `state`, `series`, `evidence` per run (JSON) |
//! | `GET /runs/I/FILE` | `report.html`, `summary.csv`, `verdict.json`, `frames/*.png`, `plots/*.png|svg` of the run |
//! | `POST /api/stop`, `/api/runs/I/stop` | stop the run as Ctrl-C does (header `X-Tactbench-Stop: confirm`) |
//!
//! Access ([`check_access`]): every view draws a token (128 bits from the kernel's
//! random source) when it starts. On a loopback address anyone on this machine may
//! read, but only under a loopback name: a `Host` other than the bound address,
//! `localhost`, `127.0.0.1` or `[::1]` with the bound port gets 421 (a page of another
//! site whose name was rebound to 127.0.0.1, "DNS rebinding", can neither read nor
//! drive the view). On any other address every request needs the token printed in the
//! URL (`?token=…`, or the header `Authorization: Bearer …`), else 401. Any request
//! whose `Origin` is not the page's own (`http://` + its `Host`) gets 403, and the
//! Stop needs the token too (the page embeds it; its button sends it as
//! `X-Tactbench-Token`), else 403. No answer carries CORS headers (a page of another
//! origin cannot read one) and every answer says `Cross-Origin-Resource-Policy:
//! same-origin`; the page may not be framed. Files are served only from inside the
//! run directories, only of the kinds above: the decoded path must be relative,
//! without `..`, hidden or empty components, and its canonical path (symlinks
//! resolved) must lie inside the run directory's canonical path; else 404. Nothing
//! here writes to a run directory.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, ToSocketAddrs};
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use tiny_http::{Header, Method, Request, Response, Server};

use super::view::RunView;
use super::{LiveError, EVENT_QUEUE, MAX_CONNECTIONS, MAX_STREAMS};
use crate::bench::journal::read_journal;
use crate::bench::lock::{self, LockState};
use crate::bench::runner::RunEvent;
use crate::report::acceptance::Criteria;

/// How often the run directories are read again.
pub const POLL: Duration = Duration::from_millis(250);
/// Shortest interval between two state pushes to one viewer.
pub const PUSH_INTERVAL: Duration = Duration::from_millis(200);
/// Shortest interval between two series pushes to one viewer.
pub const SERIES_INTERVAL: Duration = Duration::from_secs(1);
/// A comment line keeps idle streams open through proxies.
pub const KEEPALIVE: Duration = Duration::from_secs(15);

/// How to serve.
#[derive(Debug, Clone, Default)]
pub struct ServeOptions {
    /// `HOST:PORT` (port 0: any free port).
    pub addr: String,
    /// Acceptance criteria for the provisional verdict.
    pub criteria: Option<PathBuf>,
}

/// The flags Ctrl-C sets in `run` (stop requested, which signal): the Stop button
/// of an in-process live view sets the first.
#[derive(Debug, Clone)]
pub struct StopHandle {
    /// Stop requested.
    pub stop: Arc<AtomicBool>,
    /// The signal that asked (left 0 by the button: "a stop request").
    pub signal: Arc<AtomicI32>,
}

/// Hands runner events to the live view without ever waiting: a full queue drops
/// the event (counted in the state's `events_dropped`).
#[derive(Clone)]
pub struct EventSender {
    tx: SyncSender<RunEvent>,
    dropped: Arc<AtomicU64>,
}

impl EventSender {
    /// Queues a copy of `e`, or drops it when the queue is full.
    pub fn send(&self, e: &RunEvent) {
        match self.tx.try_send(e.clone()) {
            Ok(()) | Err(TrySendError::Disconnected(_)) => {}
            Err(TrySendError::Full(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

/// One run's published state: serialised once, copied to every viewer.
#[derive(Debug, Clone, Default)]
struct RunPub {
    state: Arc<String>,
    state_v: u64,
    series: Arc<String>,
    series_v: u64,
    evidence: Arc<String>,
    evidence_v: u64,
    /// Canonical run directory (`None` until the run exists: `run --serve` binds
    /// before the runner creates it).
    root: Option<PathBuf>,
    frame: Option<String>,
    writer_pid: Option<u32>,
    running: bool,
}

#[derive(Debug, Default)]
struct Published {
    version: u64,
    runs: Vec<RunPub>,
    closing: bool,
}

struct Shared {
    published: Mutex<Published>,
    cv: Condvar,
    /// Drawn at start: needed by every request on a non-loopback address
    /// (`token_required`), by the Stop on every address.
    token: String,
    token_required: bool,
    /// On loopback, the `Host` values accepted (lowercase).
    hosts: Option<Vec<String>>,
    stop: Option<StopHandle>,
    dirs: Vec<PathBuf>,
    streams: AtomicUsize,
    connections: AtomicUsize,
    dropped: Arc<AtomicU64>,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, Published> {
        // A poisoned lock only means a connection thread panicked mid-copy; the data
        // (whole strings swapped under the lock) is still consistent.
        self.published.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A running live view.
pub struct LiveServer {
    url: String,
    addr: SocketAddr,
    shared: Arc<Shared>,
    http: Arc<Server>,
    sender: Option<EventSender>,
    ingest: Option<JoinHandle<()>>,
    accept: Option<JoinHandle<()>>,
}

impl LiveServer {
    /// Binds `options.addr` and starts serving `dirs`. With `in_process` (the
    /// `run --serve` case) there is one directory, which may not hold a run yet, and
    /// [`LiveServer::sender`] feeds the runner's events; otherwise every directory must
    /// hold a run.
    pub fn start(
        dirs: &[PathBuf],
        options: &ServeOptions,
        in_process: Option<StopHandle>,
    ) -> Result<LiveServer, LiveError> {
        quiet_reset_connections();
        let addr = parse_addr(&options.addr)?;
        let criteria = match &options.criteria {
            Some(p) => Some(Criteria::from_path(p)?),
            None => None,
        };
        // Runs of `serve` are checked before binding: a bad directory is the error.
        let mut views: Vec<Option<RunView>> = Vec::with_capacity(dirs.len());
        for d in dirs {
            views.push(if in_process.is_some() {
                None
            } else {
                Some(RunView::open(d, criteria.clone())?)
            });
        }
        let listener = TcpListener::bind(addr).map_err(|e| bind_error(addr, e))?;
        let local = listener.local_addr().map_err(|e| bind_error(addr, e))?;
        let http =
            Arc::new(
                Server::from_listener(listener, None).map_err(|e| LiveError::Bind {
                    addr: addr.to_string(),
                    source: std::io::Error::other(e.to_string()),
                })?,
            );
        let token = random_token().map_err(|source| LiveError::Io {
            path: PathBuf::from("(the kernel's random source: getrandom, /dev/urandom)"),
            source,
        })?;
        let token_required = !local.ip().is_loopback();
        let hosts = local.ip().is_loopback().then(|| loopback_hosts(local));
        let host = if local.ip().is_unspecified() {
            lock::hostname()
        } else {
            match local {
                SocketAddr::V4(a) => a.ip().to_string(),
                SocketAddr::V6(a) => format!("[{}]", a.ip()),
            }
        };
        let url = format!(
            "http://{host}:{}/{}",
            local.port(),
            if token_required {
                format!("?token={token}")
            } else {
                String::new()
            }
        );
        let dropped = Arc::new(AtomicU64::new(0));
        let shared = Arc::new(Shared {
            published: Mutex::new(Published {
                version: 0,
                runs: vec![RunPub::default(); dirs.len()],
                closing: false,
            }),
            cv: Condvar::new(),
            token,
            token_required,
            hosts,
            stop: in_process.clone(),
            dirs: dirs.to_vec(),
            streams: AtomicUsize::new(0),
            connections: AtomicUsize::new(0),
            dropped: Arc::clone(&dropped),
        });
        let (sender, rx) = if in_process.is_some() {
            let (tx, rx) = std::sync::mpsc::sync_channel(EVENT_QUEUE);
            (
                Some(EventSender {
                    tx,
                    dropped: Arc::clone(&dropped),
                }),
                Some(rx),
            )
        } else {
            (None, None)
        };
        let ingest = {
            let shared = Arc::clone(&shared);
            let in_process = in_process.is_some();
            std::thread::Builder::new()
                .name("live-ingest".into())
                .spawn(move || {
                    lower_priority();
                    ingest_loop(&shared, views, rx, criteria, in_process)
                })
                .map_err(|source| LiveError::Io {
                    path: PathBuf::from("(thread)"),
                    source,
                })?
        };
        let accept = {
            let shared = Arc::clone(&shared);
            let http = Arc::clone(&http);
            std::thread::Builder::new()
                .name("live-accept".into())
                .spawn(move || {
                    lower_priority();
                    accept_loop(&http, &shared)
                })
                .map_err(|source| LiveError::Io {
                    path: PathBuf::from("(thread)"),
                    source,
                })?
        };
        Ok(LiveServer {
            url,
            addr: local,
            shared,
            http,
            sender,
            ingest: Some(ingest),
            accept: Some(accept),
        })
    }

    /// The page's URL (with the token when one is needed).
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The bound address.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The in-process event queue's sending end (`run --serve`).
    pub fn sender(&self) -> Option<EventSender> {
        self.sender.clone()
    }

    /// Events dropped because the queue was full.
    pub fn events_dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    /// Ends an in-process live view after the run: waits (at most `linger`) until
    /// the run's final state is published and viewers have had a moment to receive
    /// it, then closes every stream and stops serving.
    pub fn finish(mut self, linger: Duration) {
        self.sender = None;
        let t0 = Instant::now();
        loop {
            let done = {
                let p = self.shared.lock();
                p.runs.iter().all(|r| !r.running && r.state_v > 0)
            };
            if done || t0.elapsed() >= linger {
                break;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        // Viewers get the final state within one push interval.
        std::thread::sleep((PUSH_INTERVAL * 2).min(linger.saturating_sub(t0.elapsed())));
        self.close();
    }

    /// Serves until the process ends (`tactbench serve`).
    pub fn wait(mut self) {
        if let Some(h) = self.accept.take() {
            let _ = h.join();
        }
    }

    fn close(&mut self) {
        {
            let mut p = self.shared.lock();
            p.closing = true;
        }
        self.shared.cv.notify_all();
        self.http.unblock();
        if let Some(h) = self.accept.take() {
            let _ = h.join();
        }
        if let Some(h) = self.ingest.take() {
            let _ = h.join();
        }
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        if self.accept.is_some() || self.ingest.is_some() {
            self.close();
        }
    }
}

/// `HOST:PORT` to a socket address (the first the name resolves to).
pub fn parse_addr(s: &str) -> Result<SocketAddr, LiveError> {
    if let Ok(a) = s.parse::<SocketAddr>() {
        return Ok(a);
    }
    let bad = || LiveError::BadAddr {
        addr: s.to_string(),
    };
    if !s.contains(':') {
        return Err(bad());
    }
    s.to_socket_addrs()
        .ok()
        .and_then(|mut it| it.next())
        .ok_or_else(bad)
}

fn bind_error(addr: SocketAddr, e: std::io::Error) -> LiveError {
    let addr = addr.to_string();
    match e.kind() {
        std::io::ErrorKind::AddrInUse => LiveError::AddrInUse { addr },
        std::io::ErrorKind::AddrNotAvailable => LiveError::NotLocal { addr },
        _ => LiveError::Bind { addr, source: e },
    }
}

/// 128 random bits from the kernel (`getrandom`, else `/dev/urandom`), as hex. No
/// weaker fallback: without either the view does not start.
fn random_token() -> std::io::Result<String> {
    let mut b = [0u8; 16];
    let mut filled = 0;
    while filled < b.len() {
        // SAFETY: writes at most `len - filled` bytes into the rest of `b`.
        let n = unsafe {
            libc::getrandom(
                b[filled..].as_mut_ptr().cast::<libc::c_void>(),
                b.len() - filled,
                0,
            )
        };
        match usize::try_from(n) {
            Ok(n) => filled += n,
            Err(_) if std::io::Error::last_os_error().kind() == std::io::ErrorKind::Interrupted => {
            }
            Err(_) => {
                std::fs::File::open("/dev/urandom").and_then(|mut f| f.read_exact(&mut b))?;
                break;
            }
        }
    }
    Ok(b.iter().map(|v| format!("{v:02x}")).collect())
}

/// The `Host` values a loopback view answers to: its bound address, `localhost`,
/// `127.0.0.1` and `[::1]`, each with the bound port (and without it on port 80,
/// where browsers leave it out).
fn loopback_hosts(local: SocketAddr) -> Vec<String> {
    let bound = match local {
        SocketAddr::V4(a) => a.ip().to_string(),
        SocketAddr::V6(a) => format!("[{}]", a.ip()),
    };
    let mut names: Vec<String> = vec![bound];
    for n in ["localhost", "127.0.0.1", "[::1]"] {
        if !names.iter().any(|m| m == n) {
            names.push(n.to_string());
        }
    }
    let port = local.port();
    let mut hosts: Vec<String> = names.iter().map(|n| format!("{n}:{port}")).collect();
    if port == 80 {
        hosts.extend(names);
    }
    hosts
}

/// A client that resets its connection before `tiny_http` has asked for its peer's
/// address makes `tiny_http` 0.12 panic in its own connection thread
/// (`client.rs`: `remote_addr.unwrap()` on `NotConnected`; upstream
/// tiny-http/tiny-http#180, unfixed), which printed a panic and a backtrace into the
/// operator's terminal although nothing was wrong: the connection was already gone
/// and only that thread ends. This hook keeps exactly that panic quiet (a closed
/// connection, nothing to report) and hands every other panic to the hook installed
/// before it.
fn quiet_reset_connections() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let in_tiny_http = info
                .location()
                .is_some_and(|l| l.file().contains("tiny_http") && l.file().ends_with("client.rs"));
            let payload = info
                .payload()
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| info.payload().downcast_ref::<&str>().copied())
                .unwrap_or("");
            if !(in_tiny_http && payload.contains("NotConnected")) {
                previous(info);
            }
        }));
    });
}

/// The live view's threads run at the lowest priority (nice 19): on a loaded
/// machine the acquisition loop gets the CPU first.
fn lower_priority() {
    // SAFETY: plain syscalls on this thread's own id; failures are harmless.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        let _ = libc::setpriority(libc::PRIO_PROCESS, tid, 19);
    }
}

fn ingest_loop(
    shared: &Shared,
    mut views: Vec<Option<RunView>>,
    rx: Option<Receiver<RunEvent>>,
    criteria: Option<Criteria>,
    in_process: bool,
) {
    let mut rx = rx;
    let mut last_refresh: Option<Instant> = None;
    let mut published_v: Vec<(u64, u64, u64)> = vec![(0, 0, 0); views.len()];
    let mut state_at: Vec<Option<Instant>> = vec![None; views.len()];
    let mut dirty = vec![true; views.len()];
    loop {
        let closing = shared.lock().closing;
        let mut urgent = false;
        match &rx {
            Some(r) => match r.recv_timeout(POLL) {
                Ok(e) => {
                    let mut next = Some(e);
                    while let Some(e) = next {
                        if views[0].is_none() {
                            views[0] = RunView::open(&shared.dirs[0], criteria.clone()).ok().map(
                                |mut v| {
                                    v.set_in_process();
                                    v
                                },
                            );
                        }
                        if let Some(v) = views[0].as_mut() {
                            urgent |= v.apply(&e);
                            dirty[0] = true;
                        }
                        next = r.try_recv().ok();
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => rx = None,
            },
            None => std::thread::sleep(if closing { Duration::ZERO } else { POLL }),
        }
        if in_process && views[0].is_none() {
            views[0] = RunView::open(&shared.dirs[0], criteria.clone())
                .ok()
                .map(|mut v| {
                    v.set_in_process();
                    v
                });
        }
        if urgent || closing || last_refresh.is_none_or(|t| t.elapsed() >= POLL) {
            last_refresh = Some(Instant::now());
            for (i, v) in views.iter_mut().enumerate() {
                if let Some(v) = v {
                    dirty[i] |= v.refresh();
                    dirty[i] |= v.refresh_verdict();
                }
            }
        }
        // Publish what changed; a state at most every PUSH_INTERVAL / 2 unless urgent.
        let mut updates = Vec::new();
        for (i, v) in views.iter().enumerate() {
            let Some(v) = v else { continue };
            let due = urgent || state_at[i].is_none_or(|t| t.elapsed() >= PUSH_INTERVAL / 2);
            let (sv, ev) = (v.series_version(), v.evidence_version());
            let state = (dirty[i] && due).then(|| {
                let mut s = v.state_json(i);
                s["runs"] = json!(views.len());
                s["events_dropped"] = json!(shared.dropped.load(Ordering::Relaxed));
                s.to_string()
            });
            if state.is_some() {
                dirty[i] = false;
                state_at[i] = Some(Instant::now());
            }
            let series = (sv != published_v[i].1).then(|| v.series_json(i).to_string());
            let evidence = (ev != published_v[i].2).then(|| v.evidence_json(i).to_string());
            if state.is_some() || series.is_some() || evidence.is_some() {
                published_v[i].1 = sv;
                published_v[i].2 = ev;
                updates.push((
                    i,
                    state,
                    series,
                    evidence,
                    v.root.clone(),
                    v.evidence_frame().map(str::to_string),
                    v.writer_pid(),
                    v.state_word() == "running",
                ));
            }
        }
        if !updates.is_empty() {
            let mut p = shared.lock();
            p.version += 1;
            let version = p.version;
            for (i, state, series, evidence, root, frame, pid, running) in updates {
                let r = &mut p.runs[i];
                if let Some(s) = state {
                    r.state = Arc::new(s);
                    r.state_v = version;
                }
                if let Some(s) = series {
                    r.series = Arc::new(s);
                    r.series_v = version;
                }
                if let Some(s) = evidence {
                    r.evidence = Arc::new(s);
                    r.evidence_v = version;
                }
                r.root = Some(root);
                r.frame = frame;
                r.writer_pid = pid;
                r.running = running;
            }
            drop(p);
            shared.cv.notify_all();
        }
        if closing {
            return;
        }
    }
}

fn accept_loop(http: &Server, shared: &Arc<Shared>) {
    loop {
        let req = match http.recv() {
            Ok(r) => r,
            // `unblock` (closing), or a failed accept (e.g. out of file descriptors):
            // the latter must not end the view.
            Err(_) if shared.lock().closing => return,
            Err(_) => {
                std::thread::sleep(Duration::from_millis(50));
                continue;
            }
        };
        if shared.lock().closing {
            let _ = req.respond(text(503, "the live view is shutting down"));
            return;
        }
        if shared.connections.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
            shared.connections.fetch_sub(1, Ordering::SeqCst);
            let _ = req.respond(text(503, "too many connections"));
            continue;
        }
        let shared = Arc::clone(shared);
        let spawned = std::thread::Builder::new()
            .name("live-conn".into())
            .spawn(move || {
                lower_priority();
                handle(req, &shared);
                shared.connections.fetch_sub(1, Ordering::SeqCst);
            });
        if spawned.is_err() {
            // The request went with the closure; nothing more can be done for it.
            continue;
        }
    }
}

fn header(name: &str, value: &str) -> Header {
    Header::from_bytes(name.as_bytes(), value.as_bytes()).unwrap_or_else(|_| {
        Header::from_bytes(&b"X-Invalid"[..], &b"1"[..]).expect("static header")
    })
}

fn text(code: u16, body: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    Response::from_data(format!("{body}\n").into_bytes())
        .with_status_code(code)
        .with_header(header("Content-Type", "text/plain; charset=utf-8"))
        .with_header(header("Cache-Control", "no-store"))
        .with_header(header("X-Content-Type-Options", "nosniff"))
        .with_header(header("Cross-Origin-Resource-Policy", "same-origin"))
}

fn json_response(code: u16, body: &str) -> Response<std::io::Cursor<Vec<u8>>> {
    Response::from_data(body.as_bytes().to_vec())
        .with_status_code(code)
        .with_header(header("Content-Type", "application/json"))
        .with_header(header("Cache-Control", "no-store"))
        .with_header(header("X-Content-Type-Options", "nosniff"))
        .with_header(header("Cross-Origin-Resource-Policy", "same-origin"))
}

/// Percent-decoding of a URL path or query value; `None` for a malformed escape,
/// a NUL or text that is not UTF-8.
pub fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'%' => {
                let h = std::str::from_utf8(b.get(i + 1..i + 3)?).ok()?;
                out.push(u8::from_str_radix(h, 16).ok()?);
                i += 3;
            }
            b'+' => {
                out.push(b' ');
                i += 1;
            }
            c => {
                out.push(c);
                i += 1;
            }
        }
    }
    if out.contains(&0) {
        return None;
    }
    String::from_utf8(out).ok()
}

fn query_value(query: &str, key: &str) -> Option<String> {
    query
        .split('&')
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| *k == key)
        .and_then(|(_, v)| percent_decode(v))
}

/// Constant-time comparison (the token must not leak through timing).
fn same(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// The token given with a request: `?token=…`, `Authorization: Bearer …` or
/// `X-Tactbench-Token: …`.
fn authorised(req: &Request, query: &str, token: &str) -> bool {
    if query_value(query, "token").is_some_and(|t| same(&t, token)) {
        return true;
    }
    req.headers().iter().any(|h| {
        let given = if h.field.equiv("Authorization") {
            h.value.as_str().strip_prefix("Bearer ")
        } else if h.field.equiv("X-Tactbench-Token") {
            Some(h.value.as_str())
        } else {
            None
        };
        given.is_some_and(|t| same(t.trim(), token))
    })
}

fn header_value<'r>(req: &'r Request, name: &'static str) -> Option<&'r str> {
    req.headers()
        .iter()
        .find(|h| h.field.equiv(name))
        .map(|h| h.value.as_str().trim())
}

/// Who may ask, before anything is read: on loopback only under a loopback `Host`
/// (421: a rebound name is refused), on other addresses only with the token (401),
/// and from no other origin than the page's own (403). `Err` is (status, body).
fn check_access(req: &Request, query: &str, shared: &Shared) -> Result<(), (u16, String)> {
    let host = header_value(req, "Host").map(str::to_ascii_lowercase);
    if let Some(allowed) = &shared.hosts {
        if !host.as_ref().is_some_and(|h| allowed.contains(h)) {
            let given = host
                .as_deref()
                .map_or("none".to_string(), |h| format!("{h:?}"));
            return Err((
                421,
                format!(
                    "421 misdirected request: this live view answers only to Host {} (got {given}); a page under another name cannot read or stop it",
                    allowed.join(", ")
                ),
            ));
        }
    }
    if shared.token_required && !authorised(req, query, &shared.token) {
        return Err((
            401,
            "401 unauthorised: this live view needs the token printed in its URL (?token=...)"
                .into(),
        ));
    }
    if let Some(origin) = header_value(req, "Origin") {
        let own = host.map(|h| format!("http://{h}"));
        if own.as_deref() != Some(origin.to_ascii_lowercase().as_str()) {
            return Err((
                403,
                format!(
                    "403 forbidden: a request from {origin:?} (another site's page) may not read or stop this live view; open {} itself",
                    own.as_deref().unwrap_or("the live view's URL")
                ),
            ));
        }
    }
    Ok(())
}

/// A run file a request may read: `rel` (decoded) must be one of the served kinds
/// and resolve (symlinks followed) to a file inside `root` (canonical).
pub fn run_file(root: &Path, rel: &str) -> Option<PathBuf> {
    let kind_ok = matches!(rel, "report.html" | "summary.csv" | "verdict.json")
        || (rel.starts_with("frames/") && rel.ends_with(".png"))
        || (rel.starts_with("plots/") && (rel.ends_with(".png") || rel.ends_with(".svg")));
    if !kind_ok || rel.contains('\\') {
        return None;
    }
    let p = Path::new(rel);
    let plain = p.components().all(|c| match c {
        Component::Normal(s) => s
            .to_str()
            .is_some_and(|s| !s.is_empty() && !s.starts_with('.')),
        _ => false,
    });
    if !plain || rel.split('/').any(str::is_empty) {
        return None;
    }
    let full = root.join(p).canonicalize().ok()?;
    (full.starts_with(root) && full.is_file()).then_some(full)
}

fn content_type(p: &Path) -> &'static str {
    match p.extension().and_then(|e| e.to_str()) {
        Some("html") => "text/html; charset=utf-8",
        Some("png") => "image/png",
        Some("svg") => "image/svg+xml",
        Some("csv") => "text/csv; charset=utf-8",
        Some("json") => "application/json",
        _ => "application/octet-stream",
    }
}

fn send_file(req: Request, path: &Path) {
    match std::fs::File::open(path) {
        Ok(f) => {
            let len = f
                .metadata()
                .ok()
                .and_then(|m| usize::try_from(m.len()).ok());
            let resp = Response::new(
                200.into(),
                vec![
                    header("Content-Type", content_type(path)),
                    header("Cache-Control", "no-store"),
                    header("X-Content-Type-Options", "nosniff"),
                    header("Cross-Origin-Resource-Policy", "same-origin"),
                ],
                f,
                len,
                None,
            );
            let _ = req.respond(resp);
        }
        Err(_) => {
            let _ = req.respond(text(404, "not found"));
        }
    }
}

fn handle(req: Request, shared: &Shared) {
    let url = req.url().to_string();
    let (raw_path, query) = url.split_once('?').unwrap_or((&url, ""));
    if let Err((code, why)) = check_access(&req, query, shared) {
        let _ = req.respond(text(code, &why));
        return;
    }
    let Some(path) = percent_decode(raw_path) else {
        let _ = req.respond(text(400, "malformed path"));
        return;
    };
    let nruns = shared.dirs.len();
    // `/api/runs/I/...` and `/runs/I/...` name a run; the rest are run 0's.
    let (run, rest): (usize, String) = {
        let strip = |p: &str| -> Option<(usize, String)> {
            let (i, rest) = p.split_once('/').unwrap_or((p, ""));
            Some((i.parse().ok()?, rest.to_string()))
        };
        if let Some(r) = path.strip_prefix("/api/runs/").and_then(strip) {
            (r.0, format!("/api/{}", r.1))
        } else if let Some(r) = path.strip_prefix("/runs/").and_then(strip) {
            (r.0, format!("/file/{}", r.1))
        } else {
            (0, path.clone())
        }
    };
    if run >= nruns {
        let _ = req.respond(text(404, &format!("no run {run}: {nruns} served")));
        return;
    }
    let method = req.method().clone();
    match (method, rest.as_str()) {
        (Method::Get | Method::Head, "/" | "/index.html") => {
            let resp = Response::from_data(super::page::page(&shared.token).into_bytes())
                .with_header(header("Content-Type", "text/html; charset=utf-8"))
                .with_header(header("Cache-Control", "no-store"))
                .with_header(header("Cross-Origin-Resource-Policy", "same-origin"))
                .with_header(header("X-Frame-Options", "DENY"))
                .with_header(header("Referrer-Policy", "no-referrer"))
                .with_header(header(
                    "Content-Security-Policy",
                    "default-src 'self'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; img-src 'self' data:; frame-ancestors 'none'",
                ));
            let _ = req.respond(resp);
        }
        (Method::Get | Method::Head, "/api/state") => {
            let s = state_of(shared, run);
            let _ = req.respond(json_response(200, &s));
        }
        (Method::Get | Method::Head, "/api/runs") => {
            let all: Vec<String> = (0..nruns).map(|i| state_of(shared, i)).collect();
            let _ = req.respond(json_response(200, &format!("[{}]", all.join(","))));
        }
        (Method::Get | Method::Head, "/api/journal") => {
            let from = query_value(query, "from")
                .and_then(|v| v.parse::<usize>().ok())
                .unwrap_or(0);
            let limit = query_value(query, "limit")
                .and_then(|v| v.parse::<usize>().ok())
                .unwrap_or(1000)
                .clamp(1, 10_000);
            let (code, body) = journal_json(&shared.dirs[run], from, limit);
            let _ = req.respond(json_response(code, &body));
        }
        (Method::Get | Method::Head, "/api/frame.png") => {
            let (root, frame) = {
                let p = shared.lock();
                (p.runs[run].root.clone(), p.runs[run].frame.clone())
            };
            match root.zip(frame).and_then(|(r, f)| run_file(&r, &f)) {
                Some(p) => send_file(req, &p),
                None => {
                    let _ = req.respond(text(404, "no frame yet"));
                }
            }
        }
        (Method::Get, "/api/events") => {
            if shared.streams.fetch_add(1, Ordering::SeqCst) >= MAX_STREAMS {
                shared.streams.fetch_sub(1, Ordering::SeqCst);
                let _ = req.respond(text(503, "too many live viewers"));
                return;
            }
            stream(req, shared);
            shared.streams.fetch_sub(1, Ordering::SeqCst);
        }
        (Method::Post, "/api/stop") => {
            let confirmed = req
                .headers()
                .iter()
                .any(|h| h.field.equiv("X-Tactbench-Stop") && h.value.as_str() == "confirm");
            if !confirmed {
                let _ = req.respond(text(
                    400,
                    "a stop needs the header X-Tactbench-Stop: confirm (the page's Stop button sends it after its confirmation)",
                ));
                return;
            }
            if !authorised(&req, query, &shared.token) {
                let _ = req.respond(text(
                    403,
                    "403 forbidden: a stop needs this live view's token (header X-Tactbench-Token; the page's Stop button sends it)",
                ));
                return;
            }
            let peer = req.remote_addr().map(|a| a.to_string()).unwrap_or_default();
            let (code, body) = stop(shared, run, &peer);
            let _ = req.respond(json_response(code, &body.to_string()));
        }
        (_, "/api/stop") => {
            let _ = req.respond(text(405, "POST only"));
        }
        (Method::Get | Method::Head, f) if f.starts_with("/file/") => {
            let rel = &f["/file/".len()..];
            let root = shared.lock().runs[run].root.clone();
            match root.and_then(|r| run_file(&r, rel)) {
                Some(p) => send_file(req, &p),
                None => {
                    let _ = req.respond(text(404, "not found"));
                }
            }
        }
        (Method::Get | Method::Head, _) => {
            let _ = req.respond(text(404, "not found"));
        }
        _ => {
            let _ = req.respond(text(405, "the live view is read-only"));
        }
    }
}

fn state_of(shared: &Shared, run: usize) -> String {
    let p = shared.lock();
    let s = &p.runs[run].state;
    if s.is_empty() {
        json!({
            "run": run,
            "dir": shared.dirs[run].display().to_string(),
            "state": "starting",
            "setpoints_done": 0,
            "setpoints_total": Value::Null,
            "runs": shared.dirs.len(),
        })
        .to_string()
    } else {
        s.as_str().to_string()
    }
}

fn journal_json(dir: &Path, from: usize, limit: usize) -> (u16, String) {
    match read_journal(dir) {
        Ok(j) => {
            let total = j.rows.len();
            let rows: Vec<&crate::bench::journal::JournalRow> = j
                .rows
                .iter()
                .filter(|r| r.index >= from)
                .take(limit)
                .collect();
            let next = rows.last().map(|r| r.index + 1);
            (
                200,
                json!({ "total": total, "from": from, "next": next, "rows": rows }).to_string(),
            )
        }
        Err(e) => (404, json!({ "error": e.to_string() }).to_string()),
    }
}

/// The Stop button: in-process, the flag Ctrl-C sets; for a run written by another
/// process, SIGINT to that process (what Ctrl-C sends), after checking that it is
/// the process holding the run's lock.
fn stop(shared: &Shared, run: usize, peer: &str) -> (u16, Value) {
    let (running, pid) = {
        let p = shared.lock();
        (p.runs[run].running, p.runs[run].writer_pid)
    };
    if !running {
        return (409, json!({ "error": "the run is not running" }));
    }
    if let (0, Some(h)) = (run, &shared.stop) {
        h.stop.store(true, Ordering::SeqCst);
        eprintln!("live view: Stop requested by {peer}: stopping the run as Ctrl-C does");
        return (
            202,
            json!({ "stopping": true, "how": "stop flag (as Ctrl-C): motion stops, the stage retracts, the run is marked interrupted and can be resumed" }),
        );
    }
    let dir = &shared.dirs[run];
    let holder = match lock::probe(dir) {
        Ok(LockState::Held(h)) => h.pid,
        _ => None,
    };
    match (pid, holder) {
        (Some(p), Some(h)) if p == h => {
            let Ok(pid) = libc::pid_t::try_from(p) else {
                return (500, json!({ "error": "bad pid" }));
            };
            // SAFETY: sending SIGINT to the verified writer of this run.
            let rc = unsafe { libc::kill(pid, libc::SIGINT) };
            if rc == 0 {
                eprintln!(
                    "live view: Stop requested by {peer}: SIGINT sent to PID {p} writing {}",
                    dir.display()
                );
                (
                    202,
                    json!({ "stopping": true, "how": format!("SIGINT to PID {p} (as Ctrl-C): motion stops, the stage retracts, the run is marked interrupted and can be resumed") }),
                )
            } else {
                (
                    500,
                    json!({ "error": format!("cannot signal PID {p}: {}", std::io::Error::last_os_error()) }),
                )
            }
        }
        _ => (
            409,
            json!({ "error": "no live process holds the run's lock: nothing to stop" }),
        ),
    }
}

/// One viewer's server-sent event stream: the newest state of every run, pushed when
/// it changes (a slow viewer skips intermediate states).
fn stream(req: Request, shared: &Shared) {
    let mut w = req.into_writer();
    let head = "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\nCross-Origin-Resource-Policy: same-origin\r\nConnection: close\r\nX-Accel-Buffering: no\r\n\r\nretry: 2000\n\n";
    if w.write_all(head.as_bytes())
        .and_then(|_| w.flush())
        .is_err()
    {
        return;
    }
    let n = shared.dirs.len();
    let mut sent = vec![(0u64, 0u64, 0u64); n];
    let mut series_at: Vec<Option<Instant>> = vec![None; n];
    let mut seen = 0u64;
    let mut deferred = false;
    loop {
        let (msgs, closing) = {
            let p = shared.lock();
            let wait = if deferred {
                SERIES_INTERVAL / 2
            } else {
                KEEPALIVE
            };
            let (p, _) = shared
                .cv
                .wait_timeout_while(p, wait, |p| p.version == seen && !p.closing)
                .unwrap_or_else(|e| e.into_inner());
            seen = p.version;
            deferred = false;
            let mut msgs: Vec<(&'static str, Arc<String>)> = Vec::new();
            for (i, r) in p.runs.iter().enumerate() {
                if r.state_v > sent[i].0 {
                    msgs.push(("state", Arc::clone(&r.state)));
                    sent[i].0 = r.state_v;
                }
                if r.series_v > sent[i].1 {
                    if p.closing || series_at[i].is_none_or(|t| t.elapsed() >= SERIES_INTERVAL) {
                        msgs.push(("series", Arc::clone(&r.series)));
                        sent[i].1 = r.series_v;
                        series_at[i] = Some(Instant::now());
                    } else {
                        deferred = true;
                    }
                }
                if r.evidence_v > sent[i].2 {
                    msgs.push(("evidence", Arc::clone(&r.evidence)));
                    sent[i].2 = r.evidence_v;
                }
            }
            (msgs, p.closing)
        };
        let mut out = String::new();
        for (name, data) in &msgs {
            out.push_str("event: ");
            out.push_str(name);
            out.push_str("\ndata: ");
            out.push_str(data);
            out.push_str("\n\n");
        }
        if msgs.is_empty() {
            out.push_str(": keepalive\n\n");
        }
        if closing {
            out.push_str("event: end\ndata: {}\n\n");
        }
        if w.write_all(out.as_bytes()).and_then(|_| w.flush()).is_err() || closing {
            return;
        }
        std::thread::sleep(PUSH_INTERVAL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percent_decoding_and_its_malformed_cases() {
        assert_eq!(percent_decode("/a%2e%2E/b+c").as_deref(), Some("/a../b c"));
        assert_eq!(percent_decode("%zz"), None);
        assert_eq!(percent_decode("%2"), None);
        assert_eq!(percent_decode("a%00b"), None);
        assert_eq!(percent_decode("%ff"), None);
    }

    #[test]
    fn run_files_are_confined_to_the_run_directory_and_the_served_kinds() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("run");
        std::fs::create_dir_all(root.join("frames")).unwrap();
        std::fs::write(root.join("frames/00000_0.png"), b"png").unwrap();
        std::fs::write(root.join("report.html"), b"html").unwrap();
        std::fs::write(root.join("manifest.json"), b"{}").unwrap();
        std::fs::write(dir.path().join("secret.png"), b"secret").unwrap();
        std::os::unix::fs::symlink(dir.path().join("secret.png"), root.join("frames/link.png"))
            .unwrap();
        let root = root.canonicalize().unwrap();
        assert!(run_file(&root, "frames/00000_0.png").is_some());
        assert!(run_file(&root, "report.html").is_some());
        for bad in [
            "manifest.json",
            "../secret.png",
            "frames/../../secret.png",
            "frames/link.png",
            "/etc/passwd",
            "frames//00000_0.png",
            "frames/.hidden.png",
            "frames\\..\\..\\secret.png",
            "frames/missing.png",
        ] {
            assert!(run_file(&root, bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn addresses_parse_or_say_what_is_wrong() {
        assert_eq!(parse_addr("127.0.0.1:0").unwrap().port(), 0);
        assert!(parse_addr("[::1]:7878").is_ok());
        assert!(parse_addr("localhost:7878").is_ok());
        let e = parse_addr("plan.toml").unwrap_err().to_string();
        assert!(e.contains("plan.toml") && e.contains("HOST:PORT"), "{e}");
    }

    #[test]
    fn a_loopback_view_answers_each_loopback_name_once_with_its_port() {
        let h = loopback_hosts("127.0.0.1:7878".parse().unwrap());
        assert_eq!(h, ["127.0.0.1:7878", "localhost:7878", "[::1]:7878"]);
        let h = loopback_hosts("127.0.0.2:80".parse().unwrap());
        assert!(h.contains(&"127.0.0.2:80".to_string()) && h.contains(&"localhost".to_string()));
    }

    #[test]
    fn tokens_are_random_hex_and_compared_whole() {
        let (a, b) = (random_token().unwrap(), random_token().unwrap());
        assert_eq!(a.len(), 32);
        assert_ne!(a, b);
        assert!(same(&a, &a.clone()));
        assert!(!same(&a, &b));
        assert!(!same(&a, &a[..31]));
    }
}
