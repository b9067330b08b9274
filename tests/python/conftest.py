"""Shared set-up of the Python package's tests (run: `pip install . pytest numpy
opencv-python-headless pandas`, then `pytest tests/python` from the repository root;
the CLI comparisons need the `tactbench` binary: target/debug or target/release after
`cargo build`, or TACTBENCH_BIN)."""

import math
import os
import pathlib
import shutil

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
SENSOR = ROOT / "experiments" / "paper_sensor.toml"
RUN = ROOT / "reports" / "paper" / "runs" / "fig7_magnitude"
REFERENCE = RUN / "frames" / "reference.png"
FRAMES = [RUN / "frames" / f for f in ("00008_0.png", "00143_0.png", "00159_0.png")]


def cli_binary():
    env = os.environ.get("TACTBENCH_BIN")
    if env:
        return env
    for profile in ("debug", "release"):
        p = ROOT / "target" / profile / "tactbench"
        if p.exists():
            return str(p)
    found = shutil.which("tactbench")
    if found:
        return found
    pytest.skip("no tactbench binary (cargo build, or set TACTBENCH_BIN)")


def imread_bgr(path):
    """The file as OpenCV reads it (H×W×3 uint8, BGR)."""
    cv2 = pytest.importorskip("cv2")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img


def csv_round(v):
    """A value as tactbench's CSVs write it (formats::csv_round): 12 significant
    digits, |v| < 1e-12 as 0; Python's formatting rounds correctly, as Rust's does."""
    if not math.isfinite(v):
        return v
    if abs(v) < 1e-12:
        return 0.0
    return float(f"{v:.11e}")


def csv_num(text):
    return math.nan if text in ("", "NaN") else float(text)
