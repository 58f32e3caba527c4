"""Resuming a study: each point's row is kept in a file of its own as soon as it is done.

A study writes the row of every point (one model, duration, method and resolution) to
``DIR/<settings>/<model>_<duration>s_<method>_N<n>.json``, where ``<settings>`` is a digest of
the settings a row depends on (the runs, the seed, the resolutions, the reference step...,
and float32 when JAX computes in it; not the lists of models, durations and methods, which only
choose the points), so that rows of other settings are never mixed in; a row is taken only if
its model, duration, method and resolution are its file's. A study started again with the same directory loads
the rows it finds and computes only the others. Files are written whole (to a temporary name,
then renamed), so a study stopped at any moment leaves only complete rows behind.

With several processes, process 0 alone reads and writes the files (the others may not even
see its disk) and sends the rows it found to the others.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os

import jax
import numpy as np

from ._config import CSV_COLUMNS, StudyConfig

__all__ = ["ChunkStore"]

#: The columns that do not choose the point: the row's numbers.
_NUMBERS = tuple(c for c in CSV_COLUMNS if c not in ("model", "method"))
#: Settings that choose points but do not change a point's row.
_CHOOSERS = ("models", "durations", "methods")


def _settings(config: StudyConfig) -> dict:
    """The settings a row of ``config`` depends on, with the precision JAX computes in: float32
    (``jax_enable_x64`` off) named, float64 not (the digests of float64 studies stay as they
    were before the precision was part of them)."""
    settings = {k: v for k, v in dataclasses.asdict(config).items() if k not in _CHOOSERS}
    if not jax.config.read("jax_enable_x64"):
        settings["precision"] = "float32"
    return settings


def settings_digest(config: StudyConfig) -> str:
    """A short digest of the settings that a row of ``config`` depends on (and the precision)."""
    text = json.dumps(_settings(config), sort_keys=True, default=list)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


class ChunkStore:
    """The rows of a study kept under ``directory`` (see the module's description).

    Args:
        directory: where the rows are kept (created by process 0 when it writes the first).
        config: the study's settings.
    """

    def __init__(self, directory: str | os.PathLike, config: StudyConfig):
        self.folder = os.path.join(os.fspath(directory), settings_digest(config))
        self._settings = _settings(config)
        self._writer = jax.process_index() == 0

    def path(self, point: tuple[str, float, str, int]) -> str:
        model, duration, method, n = point
        short = f"{duration:g}"  # the name of every duration of 6 digits or fewer; else all of them
        name = short if float(short) == float(duration) else repr(float(duration))
        return os.path.join(self.folder, f"{model}_{name}s_{method}_N{n}.json")

    def save(self, point: tuple[str, float, str, int], row: dict) -> None:
        """Keep ``row`` (process 0 only; the others do nothing)."""
        if not self._writer:
            return
        os.makedirs(self.folder, exist_ok=True)
        settings = os.path.join(self.folder, "settings.json")
        if not os.path.exists(settings):
            _write(settings, self._settings)
        _write(self.path(point), row)

    def load(self, points: list[tuple[str, float, str, int]]) -> dict[int, dict]:
        """The rows already kept, by index in ``points``: read by process 0 and sent to the
        others (every process must call this at the same point of the study)."""
        found = self._read(points) if self._writer else {}
        if jax.process_count() == 1:
            return found
        from jax.experimental import multihost_utils

        numbers = np.full((len(points), len(_NUMBERS) + 1), np.nan)
        for i, row in found.items():
            numbers[i] = [1.0, *(float(row[c]) for c in _NUMBERS)]
        numbers = np.asarray(multihost_utils.broadcast_one_to_all(numbers))
        rows = {}
        for i, point in enumerate(points):
            if numbers[i, 0] == 1.0:
                values = dict(zip(_NUMBERS, numbers[i, 1:].tolist()))
                rows[i] = _typed({"model": point[0], "method": point[2], **values})
        return rows

    def _read(self, points) -> dict[int, dict]:
        rows = {}
        for i, point in enumerate(points):
            try:
                with open(self.path(point)) as fh:
                    row = json.load(fh)
            except (OSError, ValueError):  # absent, or not a row: computed again
                continue
            if isinstance(row, dict) and set(CSV_COLUMNS) <= set(row) and _is_row_of(row, point):
                rows[i] = _typed({c: row[c] for c in CSV_COLUMNS})
        return rows


def _is_row_of(row: dict, point: tuple[str, float, str, int]) -> bool:
    """Whether ``row`` is the row of ``point`` (not of another that a file name was given to)."""
    model, duration, method, n = point
    try:
        return (row["model"], row["method"], int(row["n_steps"])) == (model, method, int(n)) and float(
            row["duration"]
        ) == float(duration)
    except (TypeError, ValueError):
        return False


def _typed(row: dict) -> dict:
    """A row with the study's types: counts and ``n_steps`` as ints, the rest as floats."""
    ints = ("n_steps", "runs", "failures", "nonfinite", "singular", "not_converged", "blowup")
    out = {}
    for c in CSV_COLUMNS:
        v = row[c]
        out[c] = v if c in ("model", "method") else (int(v) if c in ints else float(v))
    return out


def _write(path: str, data: dict) -> None:
    """Write ``data`` as JSON to ``path`` whole: to a temporary file, then renamed."""
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")
    os.replace(tmp, path)
