"""What ``fgslam config --show`` lists: every parameter with its value, default, unit and
meaning, and the values derived from the sensor."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from fgslam.config.load import load_config
from fgslam.config.robot import RobotConfig, frontend_thresholds


def derived_values(cfg: RobotConfig) -> dict[str, Any]:
    """The value each key with a derivation rule (``param(derive=...)``) takes for ``cfg``
    when it holds its "derive" value ("section.key" -> value in the key's unit)."""
    th = frontend_thresholds(cfg)
    m = cfg.matcher
    ticks = (cfg.odometry.metres_per_tick_right, cfg.odometry.metres_per_tick_left)
    out: dict[str, Any] = {f"frontend.{k}": th[k] for k in _DERIVED_FRONTEND}
    out.update(
        {
            "odometry.resolution": ticks[0] if ticks[0] == ticks[1] else ticks,
            "scanmatch.match_resolution": m.resolution,
            "scanmatch.match_link_distance": m.link_distance,
            "scanmatch.match_corr_distance": m.corr_distance,
            "scanmatch.match_normal_radius": m.normal_radius,
            "scanmatch.model_error_xy": m.floor_xy,
            "scanmatch.model_error_theta_deg": math.degrees(m.floor_theta),
            "map.confirm_sigma_m": cfg.map.max_range / 4,
        }
    )
    return out


_DERIVED_FRONTEND = ("min_points", "outlier", "spread", "max_line_range", "map_max_range")


@dataclass(frozen=True)
class Entry:
    """One parameter as ``fgslam config --show`` lists it: ``key`` ("section.name"), its
    ``value`` in ``cfg`` and its ``default`` (the shipped configuration's), ``unit`` and
    ``meaning`` (the field's :func:`param`), ``derived`` (the value its rule gives, when the
    key holds its "derive" value; else None) and ``source`` (a linked field's key)."""

    section: str
    name: str
    value: Any
    default: Any
    unit: str
    meaning: str
    rule: str = ""
    derived: Any = None
    source: str = ""

    @property
    def key(self) -> str:
        return f"{self.section}.{self.name}"


def entries(cfg: RobotConfig | None = None) -> list[Entry]:
    """Every parameter of ``cfg`` (default: the shipped configuration), section by section:
    each key and each linked field, nested sections and each sonar array in turn."""
    default = load_config()
    cfg = cfg or default
    derived = derived_values(cfg)
    out: list[Entry] = []

    def walk(obj: Any, base: Any, section: str) -> None:
        later = []
        for f in dataclasses.fields(obj):
            if f.name == "source":
                continue
            value = getattr(obj, f.name)
            dflt = getattr(base, f.name, None) if base is not None else None
            path = f"{section}.{f.name}" if section else f.name
            if dataclasses.is_dataclass(value):
                later.append((value, dflt, path))
                continue
            if isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
                for i, item in enumerate(value):
                    other = dflt[i] if dflt is not None and i < len(dflt) else None
                    later.append((item, other, f"{path}.{i}"))
                continue
            meta = f.metadata
            rule = meta.get("derive", "")
            holds = rule and (value < 0 if (dflt or 0) < 0 else value == 0)
            out.append(
                Entry(
                    section,
                    f.name,
                    value,
                    dflt,
                    meta.get("unit", ""),
                    meta.get("doc", ""),
                    rule,
                    derived.get(path) if holds else None,
                    meta.get("from", ""),
                )
            )
        for value, dflt, path in later:
            walk(value, dflt, path)

    walk(cfg, default, "")
    return out
