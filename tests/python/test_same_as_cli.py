"""The same numbers as the CLI: `Tracker.track` against `tactbench track`'s CSV, and
`Solver.solve` against `tactbench reconstruct`'s, on the paper sensor's frames of the
committed fig7_magnitude run (read with OpenCV, BGR, and converted to RGB).

The CSVs carry 12 significant digits (formats::csv_round): each Python value rounded
that way must equal the CSV's text read back, and NaN must be where the CSV is empty;
statuses must be equal. Equal after the same rounding means the unrounded values
differ by at most the rounding (5e-12 relative)."""

import csv
import math
import subprocess

import numpy as np
import pytest

import tactbench
from conftest import FRAMES, REFERENCE, SENSOR, cli_binary, csv_num, csv_round, imread_bgr

NUMERIC = ["x_mm", "y_mm", "ux_mm", "uy_mm", "x_px", "y_px", "ux_px", "uy_px"]


def cli_track(tmp_path, mode):
    out = tmp_path / f"tracks_{mode}.csv"
    subprocess.run(
        [cli_binary(), "track", "--sensor", str(SENSOR), "--reference", str(REFERENCE),
         "--out", str(out), "--mode", mode, *map(str, FRAMES)],
        check=True, capture_output=True,
    )
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))
    frames = {}
    for r in rows:
        frames.setdefault(r["frame"], []).append(r)
    return out, [frames[str(p)] for p in FRAMES]


def assert_same_as_csv(got, rows):
    assert len(got["status"]) == len(rows)
    for k, r in enumerate(rows):
        assert got["layer"][k] == r["layer"]
        assert got["marker"][k] == int(r["marker"])
        assert got["status"][k] == r["status"], (k, r)
        for c in NUMERIC:
            v, want = float(got[c][k]), csv_num(r[c])
            if math.isnan(want):
                assert math.isnan(v), (k, c, v, r)
            else:
                assert csv_round(v) == want, (k, c, v, r[c])


@pytest.mark.parametrize("mode", ["frame-to-frame", "per-window"])
@pytest.mark.parametrize("order", ["bgr", "rgb"])
def test_tracker_gives_the_track_csv_values_and_statuses(tmp_path, mode, order):
    _, expected = cli_track(tmp_path, mode)
    convert = (lambda a: a) if order == "bgr" else (lambda a: np.ascontiguousarray(a[:, :, ::-1]))
    sensor = tactbench.Sensor(SENSOR)
    tracker = tactbench.Tracker(sensor, convert(imread_bgr(REFERENCE)), mode=mode, channels=order)
    for path, rows in zip(FRAMES, expected):
        assert_same_as_csv(tracker.track(convert(imread_bgr(path))), rows)


def forces_by_frame(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    frames = {}
    for r in rows:
        frames.setdefault(r.get("frame", ""), []).append(r)
    return list(frames.values())


@pytest.mark.parametrize(
    "method, flags, kwargs",
    [
        ("pinv", [], {}),
        ("tikhonov", ["--lambda", "gcv"], {"lam": "gcv"}),
        ("tikhonov", ["--lambda", "0.002"], {"lam": 0.002}),
        ("tsvd", ["--rank", "40"], {"rank": 40}),
    ],
)
def test_solver_gives_the_reconstruct_csv_forces(tmp_path, method, flags, kwargs):
    tracks, _ = cli_track(tmp_path, "frame-to-frame")
    out = tmp_path / "forces.csv"
    subprocess.run(
        [cli_binary(), "reconstruct", "--sensor", str(SENSOR), "--displacements", str(tracks),
         "--out", str(out), "--solver", method, *flags,
         "--uncertainty", "--noise-px", "0.1"],
        check=True, capture_output=True,
    )
    expected = forces_by_frame(out)
    # The displacements as reconstruct read them: the track CSV's values.
    with open(tracks, newline="") as f:
        rows = list(csv.DictReader(f))
    sensor = tactbench.Sensor(SENSOR)
    solver = tactbench.Solver(sensor, method, uncertainty=True, noise_px=0.1, **kwargs)
    worst = 0.0
    for path, want in zip(FRAMES, expected):
        fr = [r for r in rows if r["frame"] == str(path)]
        tracks_dict = {
            "layer": np.array([r["layer"] for r in fr]),
            "marker": np.array([int(r["marker"]) for r in fr]),
            "x_mm": np.array([csv_num(r["x_mm"]) for r in fr]),
            "y_mm": np.array([csv_num(r["y_mm"]) for r in fr]),
            "ux_mm": np.array([csv_num(r["ux_mm"]) for r in fr]),
            "uy_mm": np.array([csv_num(r["uy_mm"]) for r in fr]),
        }
        got = solver.solve(tracks_dict)
        assert len(want) == len(got["fz_n"])
        for col, sd in (("fx_n", "sfx_n"), ("fy_n", "sfy_n"), ("fz_n", "sfz_n")):
            want_f = np.array([float(r[col]) for r in want])
            scale = np.abs(got[col]).max()
            worst = max(worst, np.abs(got[col] - want_f).max() / scale)
            for v, w in zip(got[col], want_f):
                # NumRel: below 1e-12 of the column's largest magnitude is written 0.
                assert (w == 0 and abs(v) < 1e-12 * scale) or csv_round(v) == w, (col, v, w)
            want_sd = np.array([float(r[sd]) for r in want])
            np.testing.assert_array_equal([csv_round(v) for v in got["sd_" + col]], want_sd)
        np.testing.assert_array_equal([csv_round(v) for v in got["x_mm"]], [float(r["x_mm"]) for r in want])
    assert worst <= 5e-12
    d = solver.diagnostics
    assert d["solver"] == method and d["condition_number"] > 1
