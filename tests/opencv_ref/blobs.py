#!/usr/bin/env python3
"""OpenCV SimpleBlobDetector, the independent yardstick of issue 29 item 6 (faint and
small markers). Used by the `#[ignore]`d test `vision_faint::opencv_blob_detector_on_faint_frames`
and by hand on real frames; CI does not need it:

    pip install opencv-python-headless numpy
    python3 tests/opencv_ref/blobs.py IMAGE dark|bright [circle:X,Y,R | rect:X0,Y0,X1,Y1]

The grey image (mean of the three channels) goes to cv2.SimpleBlobDetector with the
settings a user of OpenCV would pick for small pins: thresholds from 5 to 250 in
steps of 5, a blob must persist over 2 thresholds, area 3 px and up, circularity
>= 0.5, convexity >= 0.6, inertia ratio >= 0.2; blobColor 255 for bright markers, 0
for dark. Blobs whose centre lies outside the ROI are dropped.

Prints one `x,y` line per blob (px, pixel centres at integers), sorted by row then
column. It shares no code or method with tactbench's detector.
"""
import sys

import cv2
import numpy as np


def parse_roi(text):
    kind, _, nums = text.partition(":")
    v = [float(x) for x in nums.split(",")]
    if kind == "circle" and len(v) == 3:
        return lambda x, y: (x - v[0]) ** 2 + (y - v[1]) ** 2 <= v[2] ** 2
    if kind == "rect" and len(v) == 4:
        return lambda x, y: v[0] <= x <= v[2] and v[1] <= y <= v[3]
    raise SystemExit(f"bad ROI {text!r}: circle:X,Y,R or rect:X0,Y0,X1,Y1")


def main():
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    img = cv2.imread(sys.argv[1], cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"cannot read {sys.argv[1]}")
    img = img.astype(np.float64)
    if img.ndim == 3:
        img = img[:, :, :3].mean(axis=2)
    if img.max() > 255:
        img = img / 257.0
    grey = np.clip(np.round(img), 0, 255).astype(np.uint8)
    p = cv2.SimpleBlobDetector_Params()
    p.minThreshold, p.maxThreshold, p.thresholdStep = 5, 250, 5
    p.minRepeatability = 2
    p.filterByColor = True
    p.blobColor = 255 if sys.argv[2] == "bright" else 0
    p.filterByArea, p.minArea, p.maxArea = True, 3, 5000
    p.filterByCircularity, p.minCircularity = True, 0.5
    p.filterByConvexity, p.minConvexity = True, 0.6
    p.filterByInertia, p.minInertiaRatio = True, 0.2
    keep = parse_roi(sys.argv[3]) if len(sys.argv) > 3 else (lambda x, y: True)
    pts = [k.pt for k in cv2.SimpleBlobDetector_create(p).detect(grey)]
    pts = sorted((x, y) for x, y in pts if keep(x, y))
    pts.sort(key=lambda q: (round(q[1]), q[0]))
    for x, y in pts:
        print(f"{x:.3f},{y:.3f}")


if __name__ == "__main__":
    main()
