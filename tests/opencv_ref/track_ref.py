#!/usr/bin/env python3
"""Independent marker tracker in OpenCV + NumPy: blob centroids + nearest neighbour.

The reference the tactbench tracker is compared with on real frames (issue 19): the
"30-line OpenCV script" kind of pipeline a lab would write, kept deliberately plain.

Per image: grey level (mean of R, G, B); background removed by a morphological
top-hat (bright markers) or black-hat (dark markers) with an elliptical kernel of
`--kernel` px; Otsu threshold; 8-connected components; components outside
`--min-area`..`--max-area` px or outside the ROI dropped; centroid = centre of mass of
the top-hat values over the component. Matching: each reference blob takes its nearest
frame blob when the two are mutual nearest neighbours and closer than `--gate` times
the reference blob's nearest-neighbour spacing; otherwise it is lost.

Usage (needs `pip install numpy opencv-python-headless`):

    python3 tests/opencv_ref/track_ref.py --appearance bright REF.png FRAME.png [FRAME2.png ...]
        prints, per frame, one CSV block: `frame,x_ref,y_ref,x,y,status`
    python3 tests/opencv_ref/track_ref.py --appearance bright --bench 200 REF.png FRAME.png
        times REPS repetitions of one frame's pipeline (read from memory: blobs +
        matching) and prints `opencv_frames_per_s_cpu=<n>` and `..._wall=<n>`

Used by the `#[ignore]`d tests in `tests/vision_tracking_real.rs`
(`TACTBENCH_PYTHON=python3 cargo test --test integration vision_tracking_real -- --ignored --nocapture`).
"""

import argparse
import sys
import time

import cv2
import numpy as np


def blobs(img, appearance, kernel, min_area, max_area, roi):
    """Centroids (N×2, px) of the markers of one BGR image."""
    grey = img.astype(np.float32).mean(axis=2)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kernel, kernel))
    op = cv2.MORPH_TOPHAT if appearance == "bright" else cv2.MORPH_BLACKHAT
    contrast = cv2.morphologyEx(grey, op, k)
    c8 = np.clip(contrast, 0, 255).astype(np.uint8)
    _, mask = cv2.threshold(c8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    flat = labels.ravel()
    w = contrast.ravel().astype(np.float64)
    ys, xs = np.indices(labels.shape)
    m0 = np.bincount(flat, weights=w, minlength=n)
    mx = np.bincount(flat, weights=w * xs.ravel(), minlength=n)
    my = np.bincount(flat, weights=w * ys.ravel(), minlength=n)
    keep = np.arange(1, n)
    area = stats[keep, cv2.CC_STAT_AREA]
    keep = keep[(area >= min_area) & (area <= max_area) & (m0[keep] > 0)]
    c = np.stack([mx[keep] / m0[keep], my[keep] / m0[keep]], axis=1)
    if roi is not None:
        cx, cy, r = roi
        c = c[np.hypot(c[:, 0] - cx, c[:, 1] - cy) <= r]
    return c


def nearest(a, b):
    """Index in b of the nearest point to each point of a, and the distance."""
    d = np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])
    j = d.argmin(axis=1)
    return j, d[np.arange(len(a)), j]


def match(ref, cur, gate):
    """Frame position per reference blob (NaN when lost) by mutual nearest neighbours."""
    out = np.full_like(ref, np.nan)
    if len(ref) < 2 or len(cur) == 0:
        return out
    dref = np.hypot(ref[:, None, 0] - ref[None, :, 0], ref[:, None, 1] - ref[None, :, 1])
    np.fill_diagonal(dref, np.inf)
    spacing = dref.min(axis=1)
    j, dist = nearest(ref, cur)
    back, _ = nearest(cur, ref)
    ok = (back[j] == np.arange(len(ref))) & (dist <= gate * spacing)
    out[ok] = cur[j[ok]]
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--appearance", choices=["bright", "dark"], required=True)
    p.add_argument("--kernel", type=int, default=15, help="top-hat kernel size, px")
    p.add_argument("--min-area", type=int, default=6)
    p.add_argument("--max-area", type=int, default=2000)
    p.add_argument("--gate", type=float, default=0.5, help="match gate, reference spacings")
    p.add_argument("--roi", type=float, nargs=3, metavar=("CX", "CY", "R"))
    p.add_argument("--bench", type=int, default=0, help="time this many repetitions")
    p.add_argument("reference")
    p.add_argument("frames", nargs="+")
    a = p.parse_args()

    def load(path):
        img = cv2.imread(path, cv2.IMREAD_COLOR)
        if img is None:
            sys.exit(f"cannot read image {path}")
        return img

    args = (a.appearance, a.kernel, a.min_area, a.max_area, a.roi)
    ref = blobs(load(a.reference), *args)
    if a.bench > 0:
        img = load(a.frames[0])
        match(ref, blobs(img, *args), a.gate)  # warm-up
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(a.bench):
            match(ref, blobs(img, *args), a.gate)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        print(f"opencv_blobs={len(ref)}")
        print(f"opencv_frames_per_s_cpu={a.bench / cpu:.1f}")
        print(f"opencv_frames_per_s_wall={a.bench / wall:.1f}")
        return
    print("frame,x_ref,y_ref,x,y,status")
    for path in a.frames:
        m = match(ref, blobs(load(path), *args), a.gate)
        for r, c in zip(ref, m):
            status = "lost" if np.isnan(c[0]) else "ok"
            print(f"{path},{r[0]:.3f},{r[1]:.3f},{c[0]:.3f},{c[1]:.3f},{status}")


if __name__ == "__main__":
    main()
