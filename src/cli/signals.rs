//! The stop signals of the commands that move things (`run`, `stage move|jog|home`):
//! one SIGINT / SIGTERM / SIGHUP handler that only stores atomics (which signal, that
//! a stop was asked, and when, on the monotonic clock), installed with `sigaction`
//! so the command can stop its motion, say where it stopped and exit 4 instead of
//! dying with the controller still executing its buffered moves.

use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};

use anyhow::bail;

use tactbench::bench::guard::monotonic_ns;

/// The flags the signal handler sets: (stop requested, which signal).
static STOP: OnceLock<(Arc<AtomicBool>, Arc<AtomicI32>)> = OnceLock::new();

/// When the first stop signal arrived, [`monotonic_ns`]; 0 before one did.
static STOP_AT_NS: AtomicU64 = AtomicU64::new(0);

/// SIGINT / SIGTERM / SIGHUP handler: records the first signal and its time and asks
/// the command to stop. Async-signal-safe: `clock_gettime` and atomics only.
extern "C" fn on_stop_signal(signal: libc::c_int) {
    if let Some((stop, which)) = STOP.get() {
        if which
            .compare_exchange(0, signal, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
        {
            STOP_AT_NS.store(monotonic_ns(), Ordering::SeqCst);
        }
        stop.store(true, Ordering::SeqCst);
    }
}

/// The flags [`on_stop_signal`] sets (and the live view's Stop button).
pub fn stop_flags() -> (Arc<AtomicBool>, Arc<AtomicI32>) {
    STOP.get_or_init(|| {
        (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicI32::new(0)),
        )
    })
    .clone()
}

/// When the first stop signal arrived ([`monotonic_ns`]), or 0 (none yet, or a stop
/// asked without a signal): the start of a stop latency.
pub fn stop_signal_time() -> &'static AtomicU64 {
    &STOP_AT_NS
}

/// Installs [`on_stop_signal`] for SIGINT, SIGTERM and SIGHUP; returns the flags.
pub fn install_stop_handlers() -> anyhow::Result<(Arc<AtomicBool>, Arc<AtomicI32>)> {
    let flags = stop_flags();
    for signal in [libc::SIGINT, libc::SIGTERM, libc::SIGHUP] {
        // SAFETY: `action` is fully initialised (zeroed, then handler, empty mask,
        // SA_RESTART) before sigaction reads it; the handler only touches atomics
        // and the monotonic clock.
        let rc = unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_stop_signal as extern "C" fn(libc::c_int) as usize;
            action.sa_flags = libc::SA_RESTART;
            libc::sigemptyset(&mut action.sa_mask);
            libc::sigaction(signal, &action, std::ptr::null_mut())
        };
        if rc != 0 {
            bail!(
                "cannot install the {} handler: {}",
                tactbench::bench::journal::signal_name(signal),
                std::io::Error::last_os_error()
            );
        }
    }
    Ok(flags)
}
