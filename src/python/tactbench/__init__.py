"""tactbench from Python: the tracker, the solvers and run directories.

The bindings (``tactbench._native``) wrap the Rust crate; this module re-exports
them and adds :func:`read_run`. Reference: docs/python.md.
"""

from __future__ import annotations

import json
import os

from ._native import Sensor, Solver, Tracker, __version__
from . import _native

__all__ = ["Sensor", "Tracker", "Solver", "Run", "read_run", "__version__"]


def _table(columns):
    """A pandas DataFrame when pandas is installed, else the dict of arrays."""
    try:
        import pandas
    except ImportError:
        return columns
    return pandas.DataFrame(columns)


class Run(dict):
    """A run directory: a dict with ``manifest``, ``journal``, ``verdict``,
    ``displacements`` and ``forces`` (the last two are the methods below); keys are
    also attributes."""

    def __init__(self, path, manifest, journal, verdict):
        super().__init__(
            path=path,
            manifest=manifest,
            journal=journal,
            verdict=verdict,
            displacements=self.displacements,
            forces=self.forces,
        )

    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None

    def displacements(self, setpoint):
        """Setpoint ``setpoint``'s ``displacements/NNNNN.csv`` as a dict of arrays
        (the columns of ``tactbench track``; ``Solver.solve`` takes it)."""
        return _native.read_csv_columns(self["path"], "displacements", _index(setpoint))

    def forces(self, setpoint):
        """Setpoint ``setpoint``'s ``forces/NNNNN.csv`` as a dict of arrays."""
        return _native.read_csv_columns(self["path"], "forces", _index(setpoint))


def _index(setpoint):
    try:
        i = int(setpoint)
    except (TypeError, ValueError):
        raise ValueError(f"setpoint {setpoint!r}: expected a setpoint index >= 0") from None
    if i != setpoint or i < 0:
        raise ValueError(f"setpoint {setpoint!r}: expected a setpoint index >= 0")
    return i


def read_run(path) -> Run:
    """Reads a run directory (live, finished or archived): ``manifest`` (dict),
    ``journal`` (pandas DataFrame, or a dict of arrays without pandas; empty cells are
    NaN, unknown columns kept), ``verdict`` (dict or None), ``displacements(setpoint)``
    and ``forces(setpoint)``."""
    path = os.fspath(path)
    manifest, journal, verdict = _native.read_run_parts(path)
    return Run(
        path,
        json.loads(manifest),
        _table(journal),
        json.loads(verdict) if verdict is not None else None,
    )
