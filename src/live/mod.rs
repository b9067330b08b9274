//! The live view: a small read-only web server that shows runs while they run
//! (`tactbench run … --serve [ADDR]`, `tactbench serve RUN_DIR… [--addr ADDR]`).
//!
//! **Never in the run's way.** In-process, the runner's event callback only
//! `try_send`s a clone of each [`RunEvent`] into a bounded queue ([`EVENT_QUEUE`]); a
//! full queue drops the event (counted), it never blocks. Everything else runs in the
//! server's own threads at the lowest scheduling priority (nice 19): one *ingest*
//! thread owns the [`view::RunView`]s, applies events, reads the run directories
//! (journal tail, manifest, `live.json`, newest evidence), and publishes each run's
//! state as serialised JSON; connection threads only copy those shared strings to
//! their viewers. A slow or hung viewer blocks only its own thread (it is sent the
//! newest state when it drains, intermediate ones are skipped); at most
//! [`MAX_STREAMS`] pushed streams and [`MAX_CONNECTIONS`] connections exist at once.
//!
//! **Access** ([`server`]): loopback by default, answered only under a loopback `Host`
//! (421 otherwise: no DNS rebinding); any other address needs the view's random token
//! on every request (in the printed URL; 401 without). A foreign `Origin` gets 403, no
//! answer carries CORS headers. Everything is read-only except `POST /api/stop`, which
//! does what Ctrl-C does and needs the token (the page carries it).
//!
//! **Pages and API**: [`server`] documents the routes; the page is [`page::PAGE`],
//! self-contained (no external script, font or stylesheet).

pub mod page;
pub mod server;
pub mod view;

use std::path::PathBuf;

use thiserror::Error;

pub use server::{LiveServer, ServeOptions, StopHandle};

/// Capacity of the in-process event queue (runner -> live view).
pub const EVENT_QUEUE: usize = 1024;
/// Most pushed (server-sent events) streams at once.
pub const MAX_STREAMS: usize = 64;
/// Most open connections being served at once.
pub const MAX_CONNECTIONS: usize = 128;
/// The default address.
pub const DEFAULT_ADDR: &str = "127.0.0.1:7878";

/// Why the live view cannot serve.
#[derive(Debug, Error)]
pub enum LiveError {
    /// The address is not `HOST:PORT`.
    #[error("--serve/--addr {addr:?}: not an address (give HOST:PORT, e.g. 127.0.0.1:7878; port 0 = any free port)")]
    BadAddr {
        /// As given.
        addr: String,
    },
    /// Another process listens there.
    #[error("cannot serve on {addr}: the address is in use (another server, or an earlier `tactbench serve`); choose another port, or port 0 for any free one")]
    AddrInUse {
        /// The address.
        addr: String,
    },
    /// The address is not one of this machine's.
    #[error("cannot serve on {addr}: not an address of this machine (use 127.0.0.1, 0.0.0.0 for every interface, or one of this machine's addresses)")]
    NotLocal {
        /// The address.
        addr: String,
    },
    /// Any other bind failure.
    #[error("cannot serve on {addr}: {source}")]
    Bind {
        /// The address.
        addr: String,
        /// The cause.
        source: std::io::Error,
    },
    /// A directory given to `serve` that is not a run.
    #[error("{dir}: not a run directory: {why}")]
    NotARun {
        /// The directory.
        dir: PathBuf,
        /// Why not.
        why: String,
    },
    /// A file the live view needs.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The acceptance criteria file.
    #[error(transparent)]
    Criteria(#[from] crate::report::acceptance::AcceptanceError),
}
