"""`tactbench.read_run` on the committed fig7_magnitude run (an archive) and on
copies of it made live (a torn last line) or failed (empty force cells, a trailing
`failure` column)."""

import json
import math
import shutil

import numpy as np
import pytest

import tactbench
from conftest import RUN, csv_num


def column(journal, name):
    return np.asarray(journal[name])


def test_read_run_of_an_archived_run():
    run = tactbench.read_run(RUN)
    manifest = json.loads((RUN / "manifest.json").read_text())
    assert run["manifest"] == manifest
    assert run.manifest["status"] == manifest["status"]
    assert run["verdict"] == json.loads((RUN / "verdict.json").read_text())
    lines = (RUN / "journal.csv").read_text().splitlines()
    j = run["journal"]
    assert len(column(j, "index")) == len(lines) - 1
    assert column(j, "index").dtype == np.int64
    assert column(j, "settled").dtype == bool
    last = lines[-1].split(",")
    header = lines[0].split(",")
    for name in ("fsum_z_n", "fz_n", "t_solve_s"):
        want = csv_num(last[header.index(name)])
        assert column(j, name)[-1] == want
    assert np.all(np.isnan(column(j, "fsum_sd_x_n")))
    d = run.displacements(8)
    assert set(d) >= {"layer", "marker", "ux_mm", "uy_mm", "status", "frame"}
    assert d["layer"][0] == "blue" and d["status"].dtype.kind == "U"
    f = run["forces"](8)
    assert list(f)[:7] == ["ix", "iy", "x_mm", "y_mm", "fx_n", "fy_n", "fz_n"]
    text = (RUN / "forces" / "00008.csv").read_text().splitlines()
    assert f["fz_n"][0] == float(text[1].split(",")[6])


def test_missing_run_setpoint_and_manifest_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope"):
        tactbench.read_run(tmp_path / "nope")
    run = tactbench.read_run(RUN)
    with pytest.raises(FileNotFoundError, match="00007.csv"):
        run.displacements(7)
    with pytest.raises(ValueError, match="setpoint -1"):
        run.forces(-1)
    (tmp_path / "manifest.json").write_text("{ not json")
    with pytest.raises(ValueError, match="manifest.json"):
        tactbench.read_run(tmp_path)


def copy_run(tmp_path):
    dst = tmp_path / "run"
    dst.mkdir()
    for name in ("manifest.json", "journal.csv"):
        shutil.copy(RUN / name, dst / name)
    return dst


def test_failed_setpoint_rows_read_empty_forces_as_nan_and_keep_unknown_columns(tmp_path):
    dst = copy_run(tmp_path)
    lines = (dst / "journal.csv").read_text().splitlines()
    header = lines[0].split(",")
    row = lines[-1].split(",")
    for name in ("fsum_x_n", "fsum_y_n", "fsum_z_n"):
        row[header.index(name)] = ""
    lines[0] += ",failure"
    lines[1:] = [l + "," for l in lines[1:-1]] + [",".join(row) + ",\"reconstruction failed, x\""]
    (dst / "journal.csv").write_text("\n".join(lines) + "\n")
    run = tactbench.read_run(dst)
    j = run.journal
    assert math.isnan(column(j, "fsum_z_n")[-1])
    assert not math.isnan(column(j, "fsum_z_n")[-2])
    assert list(column(j, "failure"))[-1] == "reconstruction failed, x"
    assert list(column(j, "failure"))[0] == ""
    assert run.verdict is None


def test_torn_last_line_of_a_live_run_is_skipped(tmp_path):
    dst = copy_run(tmp_path)
    text = (dst / "journal.csv").read_text()
    (dst / "journal.csv").write_text(text + "99,0,1,2")
    run = tactbench.read_run(dst)
    assert len(column(run.journal, "index")) == len(text.splitlines()) - 1


def test_journal_without_pandas_is_a_dict_of_arrays(tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def no_pandas(name, *a, **k):
        if name == "pandas":
            raise ImportError("no pandas")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_pandas)
    run = tactbench.read_run(RUN)
    assert isinstance(run.journal, dict)
    assert isinstance(run.journal["fz_n"], np.ndarray)
