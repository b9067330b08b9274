"""Speed of tactbench.Tracker.track against the Rust tracker, side by side in one run.

1. The Rust yardstick: `examples/track_time.rs` (built with the wheel's `python`
   cargo profile, so both sides have the same optimisation) tracks FRAME N times and
   prints its per-frame minimum and median.
2. The same files through Python: the frame read once with OpenCV (BGR, as a camera
   loop would hand it over), `Tracker.track` timed per call (the dict of NumPy arrays
   included).
3. Two threads, each with its own Tracker, tracking two streams: throughput against
   one thread doing the same number of frames (the GIL is released while tracking).

Run from the repository root after `pip install .` and `pip install opencv-python-headless`:
    python experiments/python/bench_tracker.py [--frames N] [--mode per-window]
Not a test: the numbers depend on the machine and its load (report them with `uptime`).
"""

import argparse
import os
import pathlib
import statistics
import subprocess
import threading
import time

import cv2

import tactbench

ROOT = pathlib.Path(__file__).resolve().parents[2]
RUN = ROOT / "reports" / "paper" / "runs" / "fig7_magnitude" / "frames"


def rust_times(sensor, reference, frame, n, mode):
    cmd = ["cargo", "run", "--quiet", "--profile", "python", "--example", "track_time", "--",
           str(sensor), str(reference), str(frame), str(n), mode]
    out = subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True).stdout
    fields = dict(f.split("=") for f in out.split()[1:])
    return float(fields["min"]), float(fields["median"])


def python_times(tracker, frame, n):
    for _ in range(50):
        tracker.track(frame)
    times = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        tracker.track(frame)
        times.append((time.perf_counter_ns() - t0) / 1e3)
    return min(times), statistics.median(times)


def throughput(trackers, frame, n_per_thread):
    """Frames per second of len(trackers) threads, each tracking n_per_thread frames."""
    start = threading.Barrier(len(trackers) + 1)

    def work(t):
        start.wait()
        for _ in range(n_per_thread):
            t.track(frame)

    threads = [threading.Thread(target=work, args=(t,)) for t in trackers]
    for th in threads:
        th.start()
    start.wait()
    t0 = time.perf_counter()
    for th in threads:
        th.join()
    return len(trackers) * n_per_thread / (time.perf_counter() - t0)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sensor", default=ROOT / "experiments" / "paper_sensor.toml")
    p.add_argument("--reference", default=RUN / "reference.png")
    p.add_argument("--frame", default=RUN / "00143_0.png")
    p.add_argument("--frames", type=int, default=5000)
    p.add_argument("--mode", default="per-window", choices=["per-window", "frame-to-frame"])
    p.add_argument("--repeats", type=int, default=3, help="thread runs (best kept)")
    p.add_argument("--no-rust", action="store_true", help="skip the Rust yardstick (no cargo build)")
    a = p.parse_args()

    sensor = tactbench.Sensor(a.sensor)
    reference = cv2.imread(str(a.reference), cv2.IMREAD_COLOR)
    frame = cv2.imread(str(a.frame), cv2.IMREAD_COLOR)
    make = lambda: tactbench.Tracker(sensor, reference, mode=a.mode, channels="bgr")
    print(f"load: {os.getloadavg()[0]:.1f} (1 min average) on {os.cpu_count()} cores")
    p_min, p_med = python_times(make(), frame, a.frames)
    print(f"per frame ({a.mode}, {a.frames} frames): Python min {p_min:.1f} µs median {p_med:.1f} µs")
    if not a.no_rust:
        r_min, r_med = rust_times(a.sensor, a.reference, a.frame, a.frames, a.mode)
        # Python's bgr frame and Rust's rgb PNG decode track identically (tests/python).
        print(f"per frame ({a.mode}, {a.frames} frames): Rust min {r_min:.1f} µs median {r_med:.1f} µs | "
              f"ratio Python/Rust min {p_min / r_min:.3f} median {p_med / r_med:.3f}")
    one = max(throughput([make()], frame, a.frames) for _ in range(a.repeats))
    two = max(throughput([make(), make()], frame, a.frames // 2) for _ in range(a.repeats))
    print(f"throughput: 1 thread {one:.0f} frames/s, 2 threads {two:.0f} frames/s: {two / one:.2f}×")
    print(f"load after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
