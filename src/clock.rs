//! This thread's CPU time, for timing on shared machines: wall-clock medians are
//! inflated by time spent waiting for a core, CPU time is not. Used by the
//! accuracy-against-time study and the criterion benches that report CPU time.
//!
//! Linux only (`clock_gettime(CLOCK_THREAD_CPUTIME_ID)` from the C library std already
//! links; 64-bit `timespec` layout); elsewhere the clock reports `None`.

/// This thread's CPU time, ns; `None` where the clock is unavailable.
#[cfg(all(target_os = "linux", target_pointer_width = "64"))]
pub fn thread_cpu_ns() -> Option<u64> {
    #[repr(C)]
    struct Timespec {
        tv_sec: i64,
        tv_nsec: i64,
    }
    extern "C" {
        fn clock_gettime(clock: i32, tp: *mut Timespec) -> i32;
    }
    const CLOCK_THREAD_CPUTIME_ID: i32 = 3;
    let mut t = Timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid, writable timespec for the duration of the call.
    let rc = unsafe { clock_gettime(CLOCK_THREAD_CPUTIME_ID, &mut t) };
    if rc != 0 || t.tv_sec < 0 || t.tv_nsec < 0 {
        return None;
    }
    Some(t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64)
}

/// This thread's CPU time, ns: not available on this platform.
#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
pub fn thread_cpu_ns() -> Option<u64> {
    None
}

/// This thread's CPU time, s; NaN where the clock is unavailable.
pub fn thread_cpu_s() -> f64 {
    thread_cpu_ns().map_or(f64::NAN, |ns| ns as f64 * 1e-9)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(target_os = "linux")]
    fn thread_cpu_time_advances_with_work_and_not_with_sleep() {
        let t0 = thread_cpu_ns().expect("linux has the thread CPU clock");
        // Busy work: at least a few ms of CPU.
        let mut x = 0u64;
        let start = std::time::Instant::now();
        while start.elapsed() < std::time::Duration::from_millis(20) {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
        }
        std::hint::black_box(x);
        let t1 = thread_cpu_ns().unwrap();
        assert!(t1 > t0, "CPU clock did not advance over 20 ms of work");
        std::thread::sleep(std::time::Duration::from_millis(50));
        let t2 = thread_cpu_ns().unwrap();
        // Sleeping costs (almost) no CPU: far less than the 50 ms slept.
        assert!(
            t2 - t1 < 10_000_000,
            "sleeping 50 ms cost {} ns CPU",
            t2 - t1
        );
    }
}
