#!/usr/bin/env python3
"""The paper's pipeline in NumPy/OpenCV: per-window tracking + pinv solve (issue 19, part 6).

The yardstick `examples/paper_pipeline_side_by_side.rs` runs beside tactbench's
accuracy-vs-time `pinv` row, on the same rendered frames, in one run. Written the way a
competent NumPy programmer would write the paper's method (Section II-A, Eq. 1, 2, 5),
vectorised over markers (no Python loop per marker or per pixel):

* tracking, per window iteration, for all markers at once: score the pixels with the
  layer's colour weights (B - G for the blue layer, R - G for the red one), gather each
  marker's window around its integer centre, fit the background plane
  a + gx*dx + gy*dy on the ring Ra + 1 < r <= Ra + 3, centre of mass of the
  background-corrected score over the aperture r <= Ra; re-centre on the rounded
  centroid until it stays put (at most 8 windows). Windows start at the reference
  centroids (per-window mode). Two variants, both timed: `plain` (integer score of
  the whole image, the whole window square gathered, one reduction per moment: the
  first thing one writes) and `tuned` (float32 score through BLAS, only the aperture
  and ring pixels gathered by flat offsets, the six moments in one matrix product:
  about 5x faster);
* solve: u = (centroid - reference) * mm_per_px, f = P u with P = pinv(H), H from the
  half-space point response (Boussinesq + Cerruti, `fourier_check.point_response`).
  pinv is precomputed (untimed), like tactbench's.

Input: a JSON file (written by the example) with the frames (PNG paths), the
reference centroids (px), each marker's layer, position (mm) and depth (mm), the layers'
aperture radii and colour weights, the force nodes (mm), E (N/mm^2) and nu. Output:
`numpy_markers=`, then per variant V: `numpy_V_us_per_frame_cpu=`,
`numpy_V_us_per_frame_wall=` (medians over `--reps` repetitions, each tracking +
solving one frame), `numpy_V_track_us_cpu=`, `numpy_V_fsum_n=fx,fy,fz` (the force sum,
to check the pipelines compute the same thing).

Run (needs `pip install numpy opencv-python-headless`):
    TACTBENCH_PYTHON=python3 cargo run --release --example paper_pipeline_side_by_side
or by hand: `python3 tests/numpy_ref/paper_pipeline.py case.json --reps 100`.
"""
import argparse
import json
import os
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fourier_check import point_response  # noqa: E402


class PlainWindows:
    """Offsets and masks of one layer's whole window square (the plain variant)."""

    def __init__(self, ra):
        rb, rc = ra + 1.0, ra + 3.0
        self.half = h = int(np.floor(rc))
        dy, dx = np.mgrid[-h : h + 1, -h : h + 1]

        def inside(r):
            d = r * r - dy * dy
            return (d >= 0) & (np.abs(dx) <= np.floor(np.sqrt(np.maximum(d, 0))))

        self.ap = inside(ra).ravel().astype(np.float64)
        self.ring = (inside(rc) & ~inside(rb)).ravel().astype(np.float64)
        self.dx, self.dy = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
        self.offx, self.offy = dx.ravel(), dy.ravel()
        self.n_ap, self.n_bg = self.ap.sum(), self.ring.sum()
        self.sxx_ap, self.syy_ap = (self.dx**2 * self.ap).sum(), (self.dy**2 * self.ap).sum()
        self.sxx_bg, self.syy_bg = (self.dx**2 * self.ring).sum(), (self.dy**2 * self.ring).sum()


def track_plain(img, ref, layer_of, windows, weights, max_iter=8):
    """The plain variant: integer score of the whole image, every window square
    gathered in 2-D, one reduction per moment. `img`: H x W x 3 RGB, int32."""
    out = np.empty_like(ref)
    for l, w in enumerate(windows):
        sel = layer_of == l
        start = ref[sel]
        score = img @ np.asarray(weights[l], dtype=np.int32)
        cx = np.rint(start[:, 0]).astype(np.int64)
        cy = np.rint(start[:, 1]).astype(np.int64)
        cur = start.copy()
        idx = np.arange(len(start))
        for _ in range(max_iter):
            ix, iy = cx[idx], cy[idx]
            s = score[iy[:, None] + w.offy[None, :], ix[:, None] + w.offx[None, :]].astype(
                np.float64
            )
            a = s @ w.ring / w.n_bg
            gx = (s * w.dx) @ w.ring / w.sxx_bg
            gy = (s * w.dy) @ w.ring / w.syy_bg
            m0 = s @ w.ap - a * w.n_ap
            nx = ix + ((s * w.dx) @ w.ap - gx * w.sxx_ap) / m0
            ny = iy + ((s * w.dy) @ w.ap - gy * w.syy_ap) / m0
            cur[idx, 0], cur[idx, 1] = nx, ny
            rx, ry = np.rint(nx).astype(np.int64), np.rint(ny).astype(np.int64)
            moved = (rx != ix) | (ry != iy)
            cx[idx], cy[idx] = rx, ry
            idx = idx[moved]
            if len(idx) == 0:
                break
        out[sel] = cur
    return out


class Windows:
    """Offsets and masks of one layer's window (aperture, ring), like tactbench's."""

    def __init__(self, ra, width):
        rb, rc = ra + 1.0, ra + 3.0
        self.half = h = int(np.floor(rc))
        dy, dx = np.mgrid[-h : h + 1, -h : h + 1]

        # Row-wise half-widths floor(sqrt(r^2 - dy^2)), as tactbench's window rows.
        def inside(r):
            d = r * r - dy * dy
            return (d >= 0) & (np.abs(dx) <= np.floor(np.sqrt(np.maximum(d, 0))))

        ap = inside(ra).ravel()
        ring = (inside(rc) & ~inside(rb)).ravel()
        fx, fy = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
        # Only the pixels of the aperture or the ring are read: their flat offsets in
        # the image, and the six moment weights per pixel (one matrix product).
        use = ap | ring
        self.offset = (dy.ravel() * width + dx.ravel())[use]
        a, r, fx, fy = ap[use].astype(np.float64), ring[use].astype(np.float64), fx[use], fy[use]
        self.basis = np.stack([r, r * fx, r * fy, a, a * fx, a * fy], axis=1).astype(np.float32)
        self.n_ap, self.n_bg = a.sum(), r.sum()
        self.sxx_ap, self.syy_ap = (fx**2 * a).sum(), (fy**2 * a).sum()
        self.sxx_bg, self.syy_bg = (fx**2 * r).sum(), (fy**2 * r).sum()


def track(img, ref, layer_of, windows, weights, max_iter=8):
    """The tuned variant: float32 score (BLAS), only the aperture and ring pixels
    gathered by flat offsets, all six moments in one matrix product. Per-window
    centroids (M x 2) of all markers in img (H x W x 3, RGB, float32)."""
    out = np.empty_like(ref)
    width = img.shape[1]
    for l, w in enumerate(windows):
        sel = layer_of == l
        start = ref[sel]
        # This layer's colour score, whole image (float32: BLAS-backed).
        score = (img @ np.asarray(weights[l], dtype=np.float32)).ravel()
        cx = np.rint(start[:, 0]).astype(np.int64)
        cy = np.rint(start[:, 1]).astype(np.int64)
        cur = start.copy()
        idx = np.arange(len(start))
        for _ in range(max_iter):
            ix, iy = cx[idx], cy[idx]
            s = score[(iy * width + ix)[:, None] + w.offset[None, :]]
            mom = (s @ w.basis).astype(np.float64)
            a = mom[:, 0] / w.n_bg
            gx, gy = mom[:, 1] / w.sxx_bg, mom[:, 2] / w.syy_bg
            m0 = mom[:, 3] - a * w.n_ap
            nx = ix + (mom[:, 4] - gx * w.sxx_ap) / m0
            ny = iy + (mom[:, 5] - gy * w.syy_ap) / m0
            cur[idx, 0], cur[idx, 1] = nx, ny
            rx, ry = np.rint(nx).astype(np.int64), np.rint(ny).astype(np.int64)
            moved = (rx != ix) | (ry != iy)
            cx[idx], cy[idx] = rx, ry
            idx = idx[moved]
            if len(idx) == 0:
                break
        out[sel] = cur
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("case")
    p.add_argument("--reps", type=int, default=100)
    a = p.parse_args()
    with open(a.case) as f:
        case = json.load(f)
    ref = np.array(case["reference_px"], dtype=np.float64)
    layer_of = np.array(case["layer"], dtype=np.int64)
    pos = np.array(case["position_mm"], dtype=np.float64)
    depth = np.array(case["depth_mm"], dtype=np.float64)
    nodes = np.array(case["force_nodes_mm"], dtype=np.float64)
    weights = [l["weights"] for l in case["layers"]]
    mm_per_px = case["mm_per_px"]

    # Precompute (untimed, as tactbench's): H (2M x 3N) and P = pinv(H).
    m, n = len(ref), len(nodes)
    H = np.zeros((2 * m, 3 * n))
    for i in range(m):
        for j in range(n):
            H[2 * i : 2 * i + 2, 3 * j : 3 * j + 3] = point_response(
                pos[i, 0] - nodes[j, 0], pos[i, 1] - nodes[j, 1], depth[i],
                case["young_n_per_mm2"], case["poisson"],
            )
    P = np.linalg.pinv(H)

    def load(path):
        img = cv2.imread(path, cv2.IMREAD_COLOR)
        if img is None:
            sys.exit(f"cannot read image {path}")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)

    rgb = load(case["frame"])  # frames are read from memory, as tactbench's
    variants = {
        "plain": (
            rgb.astype(np.int32),
            track_plain,
            [PlainWindows(l["aperture_px"]) for l in case["layers"]],
        ),
        "tuned": (
            rgb.astype(np.float32),
            track,
            [Windows(l["aperture_px"], rgb.shape[1]) for l in case["layers"]],
        ),
    }
    print(f"numpy_markers={m}")
    for name, (frame, tracker, windows) in variants.items():
        tracker(frame, ref, layer_of, windows, weights)  # warm-up
        totals, totals_wall, tracks = [], [], []
        for _ in range(a.reps):
            t0, c0 = time.perf_counter(), time.process_time()
            c = tracker(frame, ref, layer_of, windows, weights)
            c1 = time.process_time()
            u = ((c - ref) * mm_per_px).ravel()
            f = P @ u
            c2, t2 = time.process_time(), time.perf_counter()
            totals.append(c2 - c0)
            totals_wall.append(t2 - t0)
            tracks.append(c1 - c0)
        fsum = f.reshape(-1, 3).sum(axis=0)
        print(f"numpy_{name}_us_per_frame_cpu={np.median(totals) * 1e6:.1f}")
        print(f"numpy_{name}_us_per_frame_wall={np.median(totals_wall) * 1e6:.1f}")
        print(f"numpy_{name}_track_us_cpu={np.median(tracks) * 1e6:.1f}")
        print(f"numpy_{name}_fsum_n={fsum[0]:.6f},{fsum[1]:.6f},{fsum[2]:.6f}")


if __name__ == "__main__":
    main()
