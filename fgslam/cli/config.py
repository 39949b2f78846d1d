"""``fgslam config``: show or validate a robot configuration, or list every parameter."""

from __future__ import annotations

import argparse
import dataclasses
import json
from typing import Any


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "config",
        help="show or validate a robot configuration",
        description=(
            "Print the effective robot configuration: the shipped default (the paper's "
            "SLAMbot) overridden by --config FILE. Any subset of keys may be overridden; an "
            "unknown key, a missing value or a wrong type is reported with file and key. "
            "Redirect the output to a file to start your own robot configuration. --show "
            "lists every parameter instead, section by section, with its value, default, unit "
            "and meaning; a key that derives its value from the sensor shows the value "
            "derived, a component's parameter set by another key names that key."
        ),
    )
    p.add_argument("--config", metavar="ROBOT.toml", help="TOML file overriding the default")
    p.add_argument("--json", action="store_true", help="print JSON instead of TOML")
    p.add_argument(
        "--show",
        action="store_true",
        help="list every parameter with its value, default, unit and meaning",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import tomli_w

    from fgslam.config import load_config

    cfg = load_config(args.config)
    if args.show:
        return show(cfg, args.json)
    data = cfg.to_dict()
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        print(f"# robot configuration from {cfg.source}")
        print(tomli_w.dumps(data), end="")
    return 0


def show(cfg: Any, as_json: bool = False) -> int:
    """Print every parameter of ``cfg`` (:func:`fgslam.config.entries`)."""
    from fgslam.config import entries

    rows = entries(cfg)
    if as_json:
        print(json.dumps([dict(dataclasses.asdict(e), key=e.key) for e in rows], indent=2))
        return 0
    print(
        f"# every parameter of the robot configuration from {cfg.source}: key = value"
        "  # default; unit; meaning\n"
        "# 'derived': the key holds its derive value (0, or < 0) and the rule gives the value"
        " shown;\n# a commented-out line is a component's parameter set by the key it names"
    )
    section = None
    for e in rows:
        if e.section != section:
            section = e.section
            print(f"\n[{section}]")
        line = f"{e.name} = {_value(e.value)}"
        note = []
        if e.source:
            line = f"# {line}"
            note.append(f"= {e.source}")
        if e.derived is not None:
            note.append(f"derived {_value(e.derived)} ({e.rule})")
        elif e.rule:
            note.append(f"0 derives: {e.rule}" if e.default == 0 else f"< 0 derives: {e.rule}")
        note.append(f"default {_value(e.default)}")
        note.append(e.unit or "-")
        note.append(e.meaning)
        print(f"{line:<36} # {'; '.join(note)}")
    return 0


def _value(v: Any) -> str:
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, float):
        text = f"{v:.6g}"
        return text if any(c in text for c in ".enia") else text + ".0"
    if isinstance(v, tuple | list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    return str(v)
