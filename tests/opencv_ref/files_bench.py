#!/usr/bin/env python3
"""Files in, displacements out: `tactbench track` against the OpenCV pipeline of
`track_ref.py` on the same PNG files, side by side in one run (issue 32, item 1).

Both read every file from disk and decode it (`tactbench track`: its own decoder on
worker threads while the main thread tracks; OpenCV: `cv2.imread`, then blobs and
nearest-neighbour matching as track_ref.py does), and both write nothing but their
result. The files are the TacTip frames of ../shared/real_frames/tactip, copied
`--copies` times into a temporary directory (10 frames × 9 = 90 files by default; the
copies are distinct files, so neither side reads a frame it has decoded before).

Usage (from the repository root, after `cargo build --release`; needs
`pip install numpy opencv-python-headless`):

    python3 tests/opencv_ref/files_bench.py [--copies 9] [--repeat 3] [--bin target/release/tactbench]

Prints, per repetition, the wall time of each side and frames per second, the ratio,
and tactbench with `--decode-threads 1` (decode on one worker, track on the main
thread) for comparison; then checks the CSVs of the two tactbench runs are identical
(the output does not depend on the decoder threads). Not a test: the figures depend on
the machine and its load (the script prints the load average)."""

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from track_ref import blobs, match  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
FRAMES = ROOT.parent / "shared" / "real_frames" / "tactip"
# The TacTip draft of the issue: bright pins, circular ROI, 2.5 mm pitch.
INIT = ["--color", "bright", "--roi", "circle:300,245,205", "--pitch-mm", "2.5"]


# track_ref.py's defaults, with the TacTip ROI.
BLOB_ARGS = ("bright", 15, 6, 2000, (300.0, 245.0, 205.0))


def opencv_pass(reference, files):
    """Pins matched over all files (the result is used, so no step is skipped)."""
    ref = blobs(cv2.imread(str(reference), cv2.IMREAD_COLOR), *BLOB_ARGS)
    found = 0
    for f in files:
        cur = blobs(cv2.imread(str(f), cv2.IMREAD_COLOR), *BLOB_ARGS)
        found += int((~np.isnan(match(ref, cur, 0.5)[:, 0])).sum())
    return found


def tactbench_pass(binary, sensor, reference, files, out, threads):
    cmd = [binary, "track", "--sensor", str(sensor), "--reference", str(reference),
           "--out", str(out), "--max-lost-fraction", "1", *map(str, files)]
    if threads is not None:
        cmd += ["--decode-threads", str(threads)]
    subprocess.run(cmd, check=True, capture_output=True)


def timed(f):
    t0 = time.perf_counter()
    r = f()
    return time.perf_counter() - t0, r


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--copies", type=int, default=9)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "tactbench"))
    a = ap.parse_args()
    sources = sorted(FRAMES.glob("image_*.png"), key=lambda p: int(p.stem.split("_")[1]))
    if not sources:
        sys.exit(f"{FRAMES}: no TacTip frames")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        files = []
        for c in range(a.copies):
            for s in sources:
                d = tmp / f"c{c}_{s.name}"
                shutil.copyfile(s, d)
                files.append(d)
        reference = sources[0]
        sensor = tmp / "tactip.toml"
        subprocess.run([a.bin, "sensor", "init", "--reference", str(reference), *INIT, "--out", str(sensor)],
                       check=True, capture_output=True)
        # The draft's placeholders do not matter to tracking; drafts track as they are.
        print(f"{len(files)} files of {sources[0].parent}, load average {os.getloadavg()[0]:.1f} "
              f"on {os.cpu_count()} cores")
        print("| pass | tactbench s (frames/s) | tactbench --decode-threads 1 s (frames/s) "
              "| OpenCV s (frames/s) | ratio | ratio, 1 decode thread |")
        print("|---|---|---|---|---|---|")
        for r in range(a.repeat):
            t_tb, _ = timed(lambda: tactbench_pass(a.bin, sensor, reference, files, tmp / "a.csv", None))
            t_1, _ = timed(lambda: tactbench_pass(a.bin, sensor, reference, files, tmp / "b.csv", 1))
            t_cv, _ = timed(lambda: opencv_pass(reference, files))
            n = len(files)
            print(f"| {r + 1} | {t_tb:.3f} ({n / t_tb:.1f}) | {t_1:.3f} ({n / t_1:.1f}) "
                  f"| {t_cv:.3f} ({n / t_cv:.1f}) | {t_cv / t_tb:.2f}× | {t_cv / t_1:.2f}× |")
        same = (tmp / "a.csv").read_bytes() == (tmp / "b.csv").read_bytes()
        print(f"CSV with default decode threads identical to --decode-threads 1: {same}")
        if not same:
            sys.exit(1)


if __name__ == "__main__":
    main()
