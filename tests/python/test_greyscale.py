"""Greyscale frames from Python (issue 31): a sensor whose layer is `dark` or `bright`
tracks 8- and 16-bit H×W arrays, with the same values and statuses as `tactbench track`
on the same frames written as greyscale PNGs, and with the displacements the renderer
says are true.

The frames come from `tactbench sim render` (a hemisphere pressed at the sensor centre,
16-bit RGB), made grey as the brightness score reads them: g = round((R + G + B) / 3).
The truth is the renderer's markers.csv (what an ideal tracker measures)."""

import csv
import math
import subprocess

import numpy as np
import pytest

import tactbench
from conftest import cli_binary, csv_num
from test_same_as_cli import assert_same_as_csv

SENSOR = """[elastomer]
young_modulus_kpa = 1000.0
poisson_ratio = 0.5
thickness_mm = 40.0

[[layers]]
name = "dots"
color = "{color}"
depth_mm = 3.0
[layers.markers]
nx = 13
ny = 10
pitch_mm = 1.5
origin_mm = [0.0, 0.0]
diameter_mm = 0.6

[force_grid]
nx = 10
ny = 8
pitch_mm = 2.2
origin_mm = [-0.9, -0.95]

[camera]
mm_per_px = 0.05
origin_px = [25.0, 25.0]
width_px = 430
height_px = 340
"""

SCENE = """sensor = "sensor.toml"
[indenter]
kind = "hemisphere"
radius_mm = 2.5
[load]
position_mm = [9.0, 6.75]
normal_force_n = 4.0
"""


def rendered(tmp_path, color):
    (tmp_path / "sensor.toml").write_text(SENSOR.format(color=color))
    (tmp_path / "scene.toml").write_text(SCENE)
    out = tmp_path / "render"
    subprocess.run([cli_binary(), "sim", "render", "--scene", str(tmp_path / "scene.toml"),
                    "--out", str(out)], check=True, capture_output=True)
    return out


def grey(path, bits):
    """The rendered RGB PNG as an H×W grey array of `bits` bits."""
    cv2 = pytest.importorskip("cv2")
    rgb = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
    scale = (2 ** bits - 1) / (65535.0 if rgb.max() > 255 else 255.0)
    g = np.rint(rgb.mean(axis=2) * scale)
    return g.astype(np.uint16 if bits == 16 else np.uint8)


def truth(render_dir):
    with open(render_dir / "markers.csv", newline="") as f:
        return {int(r["marker"]): (float(r["ux_px"]), float(r["uy_px"])) for r in csv.DictReader(f)}


@pytest.mark.parametrize("color", ["dark", "bright"])
@pytest.mark.parametrize("bits", [8, 16])
def test_greyscale_frames_track_as_the_cli_and_as_the_truth(tmp_path, color, bits):
    cv2 = pytest.importorskip("cv2")
    render = rendered(tmp_path, color)
    ref, frame = grey(render / "reference.png", bits), grey(render / "frame_000.png", bits)
    assert ref.ndim == 2 and ref.dtype == (np.uint16 if bits == 16 else np.uint8)
    ref_png, frame_png = tmp_path / "ref_grey.png", tmp_path / "frame_grey.png"
    cv2.imwrite(str(ref_png), ref)
    cv2.imwrite(str(frame_png), frame)
    out = tmp_path / "tracks.csv"
    subprocess.run([cli_binary(), "track", "--sensor", str(tmp_path / "sensor.toml"),
                    "--reference", str(ref_png), "--out", str(out), str(frame_png)],
                   check=True, capture_output=True)
    with open(out, newline="") as f:
        rows = list(csv.DictReader(f))

    sensor = tactbench.Sensor(tmp_path / "sensor.toml")
    got = tactbench.Tracker(sensor, ref).track(frame)
    assert_same_as_csv(got, rows)

    # Positive: every marker found, and moved as the renderer says (the load moves the
    # markers near the centre by several pixels).
    assert list(got["status"]) == ["ok"] * 130
    want = truth(render)
    err = [math.hypot(got["ux_px"][k] - want[m][0], got["uy_px"][k] - want[m][1])
           for k, m in enumerate(got["marker"])]
    largest = max(math.hypot(*want[m]) for m in want)
    assert largest > 2.0, largest
    assert max(err) < 0.1, max(err)
    assert all(not math.isnan(csv_num(r["ux_px"])) for r in rows)
