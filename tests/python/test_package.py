"""The package's API and its refusals: sensor loading, frames of the wrong dtype,
shape, size, layout or channel order, solver options."""

import numpy as np
import pytest

import tactbench
from conftest import REFERENCE, FRAMES, SENSOR, imread_bgr


def test_sensor_layers_markers_and_force_grid():
    s = tactbench.Sensor(SENSOR)
    assert s.layers == ["blue", "red"]
    m = s.markers("blue")
    assert m.shape[1] == 2 and m.dtype == np.float64
    assert tuple(m[0]) == (0.0, 0.0)
    assert s.force_grid.shape[1] == 2
    with pytest.raises(ValueError, match='no layer named "green"'):
        s.markers("green")


def test_missing_sensor_file_is_file_not_found_with_the_cli_message(tmp_path):
    with pytest.raises(FileNotFoundError, match="cannot read sensor file .*nope.toml"):
        tactbench.Sensor(tmp_path / "nope.toml")


def test_invalid_sensor_file_is_a_value_error_naming_the_key(tmp_path):
    text = SENSOR.read_text().replace("poisson_ratio = 0.5", "poisson_ratio = 0.7")
    assert text != SENSOR.read_text()
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ValueError, match="poisson_ratio"):
        tactbench.Sensor(p)


@pytest.fixture(scope="module")
def sensor():
    return tactbench.Sensor(SENSOR)


@pytest.fixture(scope="module")
def reference():
    return imread_bgr(REFERENCE)


def test_coloured_sensor_without_channel_order_is_refused_naming_the_layers(sensor, reference):
    with pytest.raises(ValueError, match=r'layer "blue" \(color blue\), layer "red" \(color red\).*channels="rgb" or channels="bgr"'):
        tactbench.Tracker(sensor, reference)
    with pytest.raises(ValueError, match='channels="BGR": expected "rgb" or "bgr"'):
        tactbench.Tracker(sensor, reference, channels="BGR")


@pytest.mark.parametrize(
    "array, message",
    [
        (np.zeros((340, 430, 3), np.float64), "dtype float64: expected uint8 or uint16"),
        (np.full((340, 430, 3), np.nan, np.float32), "dtype float32: expected uint8 or uint16"),
        (np.zeros((340, 430, 3), np.int32), "dtype int32"),
        (np.zeros((340, 430, 3), np.int8), "dtype int8"),
        (np.zeros((0, 430, 3), np.uint8), "empty array of shape \\(0, 430, 3\\)"),
        (np.zeros((340, 430, 2), np.uint8), "shape \\(340, 430, 2\\): expected H×W \\(greyscale\\), H×W×3 or H×W×4"),
        (np.zeros((340,), np.uint8), "shape \\(340\\)"),
        (np.zeros((200, 300, 3), np.uint8), "reference array: image is 300×200 px but \\[camera\\] says 430×340 px"),
        ([[1, 2, 3]], "expected a NumPy array"),
    ],
)
def test_bad_reference_arrays_are_value_errors(sensor, array, message):
    with pytest.raises(ValueError, match=message):
        tactbench.Tracker(sensor, array, channels="bgr")


def test_blank_reference_is_refused_as_blank(sensor):
    with pytest.raises(ValueError, match="blank"):
        tactbench.Tracker(sensor, np.zeros((340, 430, 3), np.uint8), channels="rgb")


def test_greyscale_frames_of_a_coloured_sensor_are_refused_naming_the_layer(sensor, reference):
    grey = np.ascontiguousarray(reference[:, :, 1])
    with pytest.raises(ValueError, match='blue'):
        tactbench.Tracker(sensor, grey)
    with pytest.raises(ValueError, match='blue'):
        tactbench.Tracker(sensor, reference, channels="bgr").track(grey)


@pytest.fixture()
def tracker(sensor, reference):
    return tactbench.Tracker(sensor, reference, channels="bgr")


@pytest.mark.parametrize(
    "frame, message",
    [
        (np.full((340, 430, 3), np.inf), "dtype float64"),
        (np.zeros((341, 430, 3), np.uint8), "frame is 430×341 px but the reference is 430×340 px"),
        (np.zeros((340, 430, 3, 1), np.uint8), "shape"),
        (np.zeros((0, 0, 3), np.uint16), "empty"),
        (None, "expected a NumPy array"),
    ],
)
def test_bad_frames_are_value_errors(tracker, frame, message):
    with pytest.raises(ValueError, match=message):
        tracker.track(frame)


def test_non_contiguous_and_16_bit_frames_track_as_the_contiguous_8_bit_frame(sensor, reference):
    frame = imread_bgr(FRAMES[0])
    want = tactbench.Tracker(sensor, reference, channels="bgr", mode="per-window").track(frame)
    t = tactbench.Tracker(sensor, reference, channels="bgr", mode="per-window")
    # A view with a negative stride over the channels: the same pixels in RGB order.
    rgb_view = frame[:, :, ::-1]
    assert not rgb_view.flags["C_CONTIGUOUS"]
    t_rgb = tactbench.Tracker(sensor, np.ascontiguousarray(reference[:, :, ::-1]), channels="rgb", mode="per-window")
    got = t_rgb.track(rgb_view)
    wide = tactbench.Tracker(sensor, reference.astype(np.uint16) * 257, channels="bgr", mode="per-window")
    got16 = wide.track(frame.astype(np.uint16) * 257)
    for g in (got, t.track(np.asfortranarray(frame))):
        assert list(g["status"]) == list(want["status"])
        np.testing.assert_array_equal(g["ux_px"], want["ux_px"])
        np.testing.assert_array_equal(g["ux_mm"], want["ux_mm"])
    # 16-bit samples (8-bit × 257, as PNG widens them) track like the 8-bit frame.
    assert list(got16["status"]) == list(want["status"])
    np.testing.assert_allclose(got16["ux_px"], want["ux_px"], rtol=1e-9, atol=1e-12)


def test_bgra_frames_track_as_bgr(sensor, reference):
    frame = imread_bgr(FRAMES[1])
    alpha = lambda a: np.dstack([a, np.full(a.shape[:2], 255, np.uint8)])
    want = tactbench.Tracker(sensor, reference, channels="bgr").track(frame)
    got = tactbench.Tracker(sensor, alpha(reference), channels="bgr").track(alpha(frame))
    assert list(got["status"]) == list(want["status"])
    np.testing.assert_array_equal(got["uy_px"], want["uy_px"])


def test_wrong_channel_order_never_tracks_silently_as_the_right_one(sensor, reference):
    # The reference in BGR declared as RGB: blue and red are read from each other's
    # channel; the result must differ from the right order's (no silent swap).
    right = tactbench.Tracker(sensor, reference, channels="bgr")
    try:
        wrong = tactbench.Tracker(sensor, reference, channels="rgb")
    except ValueError:
        return
    frame = imread_bgr(FRAMES[0])
    a, b = right.track(frame), wrong.track(frame)
    assert len(a["status"]) != len(b["status"]) or not np.array_equal(a["x_px"], b["x_px"], equal_nan=True)


def test_solver_options_are_checked():
    s = tactbench.Sensor(SENSOR)
    with pytest.raises(ValueError, match="unknown solver `nope`"):
        tactbench.Solver(s, "nope")
    with pytest.raises(ValueError, match="lam does not apply to the pinv solver"):
        tactbench.Solver(s, "pinv", lam=0.1)
    with pytest.raises(ValueError, match="rank does not apply to the tikhonov solver"):
        tactbench.Solver(s, "tikhonov", rank=3)
    with pytest.raises(ValueError, match="invalid lambda `-1`"):
        tactbench.Solver(s, "tikhonov", lam=-1.0)
    with pytest.raises(ValueError, match="f32.*fourier"):
        tactbench.Solver(s, "fourier", precision="f32")
    with pytest.raises(ValueError, match="needs noise_px"):
        tactbench.Solver(s, uncertainty=True)


def test_solver_pair_of_arrays_in_grid_order_and_lost_markers(sensor):
    n = sum(len(sensor.markers(l)) for l in sensor.layers)
    rng = np.random.default_rng(1)
    ux, uy = rng.normal(0, 0.01, n), rng.normal(0, 0.01, n)
    solver = tactbench.Solver(sensor, uncertainty=True, noise_px=0.1)
    d = solver.diagnostics
    assert d["solver"] == "pinv" and d["rows"] == 2 * n and d["condition_number"] > 1
    out = solver.solve((ux, uy))
    assert out["fz_n"].shape == (len(sensor.force_grid),)
    np.testing.assert_allclose(out["fsum_n"], [out["fx_n"].sum(), out["fy_n"].sum(), out["fz_n"].sum()])
    assert np.all(out["sd_fz_n"] > 0)
    ux[3] = np.nan
    lost = solver.solve((ux, uy))
    assert solver.diagnostics["rows"] == 2 * (n - 1)
    assert not np.array_equal(lost["fz_n"], out["fz_n"])
    zero = solver.solve((np.zeros(n), np.zeros(n)))
    assert np.all(zero["fz_n"] == 0)
    gone = solver.solve((np.full(n, np.nan), np.full(n, np.nan)))
    assert np.all(np.isnan(gone["fz_n"]))
    with pytest.raises(ValueError, match="inputs must be finite"):
        solver.solve((np.full(n, np.inf), np.zeros(n)))
    with pytest.raises(ValueError, match="tracks:"):
        solver.solve((np.zeros(n - 1), np.zeros(n - 1)))
