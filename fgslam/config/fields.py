"""The fields of configuration sections: :func:`param` (a default with its unit and meaning
written once), linked fields (set by another section's key) and :class:`ConfigError`."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any

from fgslam.errors import UserError

DEFAULT_CONFIG_NAME = "robot_default.toml"


class ConfigError(UserError, ValueError):
    """A robot configuration file is invalid; the message is one line for the user."""


def param(
    default: Any = dataclasses.MISSING,
    unit: str = "",
    doc: str = "",
    *,
    factory: Any = dataclasses.MISSING,
    derive: str = "",
) -> Any:
    """A configuration key: its default (written here and nowhere else), its unit and its
    one-line meaning, both shown by ``fgslam config --show``. ``derive``: the rule that gives
    the key's value when it holds its "derive" value (0, or negative where 0 is a value)."""
    return field(default=default, default_factory=factory, metadata=_meta(unit, doc, derive))


def _meta(unit: str, doc: str, derive: str = "") -> dict[str, str]:
    """A key's unit, meaning and derivation rule (:func:`param`), for a ``field`` itself."""
    return {"unit": unit, "doc": doc, "derive": derive}


def linked(key: str, default: Any, unit: str, doc: str) -> Any:
    """A component's parameter whose value is the configuration key ``key`` ("section.name",
    resolved by :class:`RobotConfig`: converted, or derived from the sensor), so it is no key
    of its own section. ``default``: its value when the class is built directly, the one the
    default configuration gives it."""
    return field(default=default, metadata={"unit": unit, "doc": doc, "from": key})


def linked_from(base: Any, resolved: Any) -> Any:
    """``base`` (a component's parameters) with the linked fields of ``resolved`` (the same
    class, e.g. a configuration's section), in nested sections too."""
    kw = {}
    for f in dataclasses.fields(base):
        value = getattr(resolved, f.name)
        if "from" in f.metadata:
            kw[f.name] = value
        elif dataclasses.is_dataclass(value):
            kw[f.name] = linked_from(getattr(base, f.name), value)
    return dataclasses.replace(base, **kw)


def keys(cls: type) -> list[dataclasses.Field]:
    """The fields of section ``cls`` that are keys of the TOML file (not linked ones)."""
    return [f for f in dataclasses.fields(cls) if f.name != "source" and "from" not in f.metadata]
