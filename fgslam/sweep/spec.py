"""A sweep's specification (``fgslam sweep SPEC.toml``; docs/sweeps.md): which runs to make.

A TOML file with

- ``[run]``: the settings every cell shares (scalars);
- ``[grid]``: settings to vary, each a list: one cell per combination;
- ``[[cells]]`` (instead of or beside the grid): cells listed one by one, each a table of
  settings over ``[run]``;
- ``name`` (optional): the sweep's title.

A setting is one of :data:`RUN_KEYS` (the input: ``log`` a log file, or ``seed`` with
``world`` and ``duration`` a simulated run; ``backend``, ``sensors``, ``association``;
``relations``: a relations file to score against, default the log's sibling ``X.relations``)
or a configuration key written ``"section.key"`` (``"scanmatch.odometry"``), as in a robot
file. Every cell is checked before anything runs: its input, its choices and its
configuration (against the built-in configuration's keys).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fgslam.config import ConfigError, load_config, with_options
from fgslam.errors import UserError
from fgslam.slam.association import METHODS
from fgslam.slam.runner import BACKENDS, SENSORS

# the run's own settings and their types; the rest are "section.key" configuration keys
RUN_KEYS: dict[str, type | tuple[type, ...]] = {
    "log": str,
    "seed": int,
    "world": str,
    "duration": (int, float),
    "backend": str,
    "sensors": str,
    "association": str,
    "relations": str,
}
DEFAULTS = {"backend": "isam2", "sensors": "fused", "world": "corridor"}


class SweepError(UserError, ValueError):
    """A sweep specification or folder that cannot be used; the message says why."""


@dataclass(frozen=True)
class Cell:
    """One run of a sweep: its settings (:data:`RUN_KEYS` and ``"section.key"``
    configuration keys) and the names of the settings the sweep varies (they name it)."""

    settings: dict[str, Any]
    varying: tuple[str, ...] = ()

    @property
    def id(self) -> str:
        """The cell's folder name: the varying settings, readable, and a hash of all."""
        text = json.dumps(self.settings, sort_keys=True)
        digest = hashlib.sha1(text.encode()).hexdigest()[:8]
        parts = []
        for k in self.varying:
            v = self.settings.get(k)
            v = Path(v).name.split(".")[0] if k == "log" and isinstance(v, str) else v
            parts.append(f"{k.rpartition('.')[2]}={v}")
        readable = re.sub(r"[^A-Za-z0-9=._-]+", "-", "_".join(parts))[:80]
        return f"{readable}-{digest}" if readable else digest

    @property
    def group(self) -> dict[str, Any]:
        """The varying settings but the seed: the setting a cell's result is one sample of."""
        return {k: self.settings[k] for k in self.varying if k != "seed"}

    def overrides(self) -> dict[str, dict[str, Any]]:
        """The configuration keys as sections ({"scanmatch": {"odometry": "both"}})."""
        out: dict[str, dict[str, Any]] = {}
        for k, v in self.settings.items():
            if k not in RUN_KEYS and "." in k:
                section, _, key = k.partition(".")
                out.setdefault(section, {})[key] = v
        return out


@dataclass
class SweepSpec:
    """A sweep: its name, the file it came from and its cells, in order."""

    name: str
    cells: list[Cell]
    source: Path | None = None
    varying: tuple[str, ...] = field(default=())


def load_spec(path: str | Path) -> SweepSpec:
    """Read and check a sweep specification (module doc); :class:`SweepError` naming the
    file and the problem."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SweepError(f"{path}: no such sweep specification") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise SweepError(f"{path}: not a TOML sweep specification ({e})") from None
    try:
        return spec_from_dict(data, path)
    except SweepError as e:
        raise SweepError(f"{path}: {e}") from None


def spec_from_dict(
    data: dict[str, Any], source: Path | None = None, extra: tuple[str, ...] = ()
) -> SweepSpec:
    """A :class:`SweepSpec` from the TOML's content (module doc); ``extra``: more setting
    names, taken as they are (an experiment's own cell function reads them)."""
    unknown = set(data) - {"name", "run", "grid", "cells"}
    if unknown:
        raise SweepError(f"unknown top-level keys {sorted(unknown)} (name, run, grid, cells)")
    run = data.get("run", {})
    grid = data.get("grid", {})
    listed = data.get("cells", [])
    if not isinstance(run, dict) or not isinstance(grid, dict) or not isinstance(listed, list):
        raise SweepError("[run] and [grid] must be tables, [[cells]] a list of tables")
    for k, v in grid.items():
        if not isinstance(v, list) or not v:
            raise SweepError(f"[grid] {k} must be a non-empty list, got {v!r}")
    if not all(isinstance(c, dict) for c in listed):
        raise SweepError("every [[cells]] entry must be a table of settings")
    varying = tuple(sorted(set(grid) | {k for c in listed for k in c}))
    combos = [dict(zip(grid, values, strict=True)) for values in itertools.product(*grid.values())]
    if not grid and not listed:
        combos = [{}]
    rows = [{**run, **g} for g in combos] if grid or not listed else []
    rows += [{**run, **c} for c in listed]
    cells = [_cell({**DEFAULTS, **r}, varying, extra) for r in rows]
    ids = [c.id for c in cells]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})
        raise SweepError(f"the same cell more than once: {dup[:3]}")
    name = data.get("name", source.stem if source else "sweep")
    return SweepSpec(str(name), cells, source, varying)


def _cell(s: dict[str, Any], varying: tuple[str, ...], extra: tuple[str, ...] = ()) -> Cell:
    for k, v in s.items():
        if k in extra:
            continue
        if k in RUN_KEYS:
            want = RUN_KEYS[k]
            if isinstance(v, bool) or not isinstance(v, want):
                raise SweepError(f"{k} = {v!r}: expected {_type_name(want)}")
        elif "." not in k:
            raise SweepError(f"unknown setting {k!r}: one of {sorted(RUN_KEYS)} or section.key")
    if ("log" in s) == ("seed" in s):
        raise SweepError(f"a cell needs a log or a seed (a simulated run), not both: {s}")
    if s["backend"] not in BACKENDS:
        raise SweepError(f"backend = {s['backend']!r}: one of {BACKENDS}")
    if s["sensors"] not in SENSORS:
        raise SweepError(f"sensors = {s['sensors']!r}: one of {SENSORS}")
    if "association" in s and s["association"] not in METHODS:
        raise SweepError(f"association = {s['association']!r}: one of {METHODS}")
    if "log" in s:
        for k in ("log", "relations"):
            if k in s and not Path(s[k]).is_file():
                raise SweepError(f"{k} = {s[k]!r}: no such file")
    elif "duration" in s and not s["duration"] > 0:
        raise SweepError(f"duration = {s['duration']!r}: must be > 0 s")
    cell = Cell(dict(sorted(s.items())), tuple(k for k in varying if k in s))
    try:
        with_options(load_config(None), cell.overrides())
    except (ConfigError, KeyError, ValueError) as e:
        raise SweepError(f"configuration of cell {cell.id}: {e}") from None
    return cell


def _type_name(t: type | tuple[type, ...]) -> str:
    ts = t if isinstance(t, tuple) else (t,)
    return " or ".join(
        {"str": "a string", "int": "an integer", "float": "a number"}[x.__name__] for x in ts
    )
