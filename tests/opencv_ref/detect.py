#!/usr/bin/env python3
"""Independent marker detector for the real-frame tests (OpenCV + NumPy).

Used only by the `#[ignore]`d test `vision_real::opencv_reference_agrees_on_real_frames`
(`tests/vision_real.rs`); CI does not need it. Run by hand:

    pip install opencv-python-headless numpy
    python3 tests/opencv_ref/detect.py IMAGE dark|bright [circle:X,Y,R | rect:X0,Y0,X1,Y1]

It shares no code or method with tactbench's detector: the grey image (mean of the
three channels) is background-corrected by OpenCV's morphological black-hat (dark
markers) or top-hat (bright markers) with an elliptical element of 41 px, thresholded
by Otsu's method, split into 8-connected components; components smaller than a fifth
of the median area of the larger half are dropped as specks. The centroid of each
component is the intensity-weighted mean of the corrected image over the component
(pixel centres at integer coordinates, as tactbench). Components whose centroid lies
outside the ROI are dropped (the ROI is applied after detection, not before).

Prints one `x,y` line per marker (px), sorted by row then column.
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
    img = cv2.imread(sys.argv[1], cv2.IMREAD_COLOR)
    if img is None:
        raise SystemExit(f"cannot read {sys.argv[1]}")
    grey = img.astype(np.float32).mean(axis=2)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (41, 41))
    op = cv2.MORPH_BLACKHAT if sys.argv[2] == "dark" else cv2.MORPH_TOPHAT
    corrected = cv2.morphologyEx(grey, op, kernel)
    inside = parse_roi(sys.argv[3]) if len(sys.argv) > 3 else (lambda x, y: True)
    u8 = np.clip(corrected, 0, 255).astype(np.uint8)
    _, mask = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    areas = np.sort(stats[1:, cv2.CC_STAT_AREA])
    if len(areas) == 0:
        return
    big = areas[len(areas) // 2:]
    min_area = 0.2 * big[len(big) // 2]
    ys, xs = np.mgrid[0:grey.shape[0], 0:grey.shape[1]]
    out = []
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] < min_area:
            continue
        sel = labels == k
        w = corrected[sel]
        x = float((xs[sel] * w).sum() / w.sum())
        y = float((ys[sel] * w).sum() / w.sum())
        if inside(x, y):
            out.append((x, y))
    out.sort(key=lambda p: (round(p[1]), p[0]))
    for x, y in out:
        print(f"{x:.3f},{y:.3f}")


if __name__ == "__main__":
    main()
