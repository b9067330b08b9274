//! Frames decoded ahead of the tracker (issue 32): reading and decoding a PNG costs
//! ten times what tracking it does, so `track` and `reconstruct` decode the next frames
//! on worker threads while the caller's thread tracks the last one.
//!
//! [`decode_ahead`] hands the results to the caller in the order of the inputs, the
//! same values a sequential loop would get (decoding is deterministic), so the output
//! is bit for bit that of a sequential run. At most `window` decoded frames wait at any
//! time (memory stays bounded however many files are given); a worker that is that far
//! ahead of the caller waits for it.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Condvar, Mutex};

/// Decoder threads for `n` frames on this machine: one per core (the caller's thread
/// only tracks, a tenth of the work), at least one, never more than the frames.
pub fn decoder_threads(n: usize) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    cores.clamp(1, n.max(1))
}

/// Runs `decode` on every input on `threads` worker threads, at most `window` results
/// ahead of the caller, and calls `consume(index, result)` on the caller's thread in
/// input order. `consume` returning `false` stops the work (the workers finish the
/// frame they hold and exit); the results not yet consumed are dropped.
pub fn decode_ahead<I, T, D, C>(
    inputs: &[I],
    threads: usize,
    window: usize,
    decode: D,
    mut consume: C,
) where
    I: Sync,
    T: Send,
    D: Fn(&I) -> T + Sync,
    C: FnMut(usize, T) -> bool,
{
    if inputs.is_empty() {
        return;
    }
    let threads = threads.clamp(1, inputs.len());
    let window = window.max(threads);
    let next = AtomicUsize::new(0);
    // The index the caller consumes next, and a flag to stop; workers wait on it.
    let progress = (Mutex::new((0usize, false)), Condvar::new());
    let (tx, rx) = mpsc::channel::<(usize, T)>();
    std::thread::scope(|scope| {
        for _ in 0..threads {
            let tx = tx.clone();
            let (next, progress, decode) = (&next, &progress, &decode);
            scope.spawn(move || loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                if i >= inputs.len() {
                    return;
                }
                {
                    let (lock, cv) = progress;
                    let mut g = lock.lock().unwrap_or_else(|p| p.into_inner());
                    while !g.1 && i >= g.0 + window {
                        g = cv.wait(g).unwrap_or_else(|p| p.into_inner());
                    }
                    if g.1 {
                        return;
                    }
                }
                if tx.send((i, decode(&inputs[i]))).is_err() {
                    return;
                }
            });
        }
        drop(tx);
        let stop = |p: &(Mutex<(usize, bool)>, Condvar), consumed: usize, stopped: bool| {
            let mut g = p.0.lock().unwrap_or_else(|e| e.into_inner());
            *g = (consumed, stopped);
            p.1.notify_all();
        };
        let mut waiting = BTreeMap::new();
        let mut expected = 0;
        while expected < inputs.len() {
            let item = match waiting.remove(&expected) {
                Some(t) => t,
                None => match rx.recv() {
                    Ok((i, t)) if i == expected => t,
                    Ok((i, t)) => {
                        waiting.insert(i, t);
                        continue;
                    }
                    // Every worker has gone (a panic in `decode`): the scope re-raises it.
                    Err(_) => break,
                },
            };
            expected += 1;
            if !consume(expected - 1, item) {
                stop(&progress, expected, true);
                return;
            }
            stop(&progress, expected, false);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_arrive_in_input_order_whatever_order_the_workers_finish_in() {
        let inputs: Vec<u64> = (0..200).collect();
        let mut got = Vec::new();
        decode_ahead(
            &inputs,
            4,
            3,
            |&i| {
                // Later inputs finish first now and then.
                std::thread::sleep(std::time::Duration::from_micros((200 - i) % 7 * 50));
                i * i
            },
            |k, v| {
                got.push((k, v));
                true
            },
        );
        let want: Vec<(usize, u64)> = (0..200).map(|i| (i as usize, i * i)).collect();
        assert_eq!(got, want);
    }

    #[test]
    fn workers_stay_within_the_window_of_the_caller() {
        let inputs: Vec<usize> = (0..50).collect();
        let consumed = AtomicUsize::new(0);
        let ahead = AtomicUsize::new(0);
        decode_ahead(
            &inputs,
            3,
            4,
            |&i| {
                let c = consumed.load(Ordering::SeqCst);
                ahead.fetch_max(i.saturating_sub(c), Ordering::SeqCst);
                i
            },
            |_, _| {
                std::thread::sleep(std::time::Duration::from_micros(200));
                consumed.fetch_add(1, Ordering::SeqCst);
                true
            },
        );
        assert!(
            ahead.load(Ordering::SeqCst) < 4,
            "{}",
            ahead.load(Ordering::SeqCst)
        );
    }

    #[test]
    fn a_consumer_that_stops_stops_the_workers() {
        let inputs: Vec<usize> = (0..10_000).collect();
        let decoded = AtomicUsize::new(0);
        let mut seen = 0;
        decode_ahead(
            &inputs,
            2,
            4,
            |&i| {
                decoded.fetch_add(1, Ordering::SeqCst);
                i
            },
            |_, _| {
                seen += 1;
                seen < 5
            },
        );
        assert_eq!(seen, 5);
        assert!(
            decoded.load(Ordering::SeqCst) < 5 + 4 + 2,
            "{}",
            decoded.load(Ordering::SeqCst)
        );
    }

    #[test]
    fn no_inputs_no_calls() {
        let inputs: Vec<u8> = Vec::new();
        decode_ahead(&inputs, 2, 2, |_| 0, |_, _: i32| panic!("called"));
    }
}
