"""Replay of raw recordings through the same receivers (decoders) the drivers use.

A recording holds every chunk a driver read, with the log time of the read, and the port
events that change decoding (open, baud change). Feeding them to a fresh receiver reproduces
the live run's measurements exactly, timestamps included; replaying twice gives the same.
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from devices.driver import Measurement, Receiver
from devices.odometry import OdometryReceiver
from devices.raw import RawReader
from devices.sick import SickReceiver
from devices.sonar import SonarReceiver


def make_receiver(header: dict[str, Any]) -> Receiver:
    """The receiver for a recording's header (its ``device`` kind and options)."""
    kind = header.get("device")
    clock = bool(header.get("device_clock", True))
    if kind == "sick-pls":
        return SickReceiver()
    if kind == "sonar":
        return SonarReceiver(int(header.get("array", 0)), clock)
    if kind == "odometry":
        return OdometryReceiver(clock)
    raise ValueError(f"unknown device kind {kind!r} in raw recording header")


class ReplayFile:
    """Measurements of one raw file, in the order the driver produced them. After
    iteration: ``reader.truncated``, ``reader.skipped_bytes`` and ``receiver.counters()``."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.reader = RawReader(path)
        self.header = self.reader.header
        self.receiver = make_receiver(self.header)

    def __iter__(self) -> Iterator[Measurement]:
        rcv = self.receiver
        for rec in self.reader:
            if rec.tag == "D":
                for item in rcv.feed(rec.t, rec.data):
                    if isinstance(item, Measurement):
                        yield item
            elif rec.tag == "M":
                try:
                    mark = rec.marker
                    if mark.get("event") == "open":
                        rcv.reset(int(mark["baud"]))
                    elif mark.get("event") == "baud":
                        rcv.set_baud(int(mark["baud"]))
                except (ValueError, KeyError, TypeError):
                    continue  # a damaged marker: keep decoding with the current state


def replay_dir(
    raw_dir: str | os.PathLike[str],
    files: list[str] | None = None,
    opened: dict[str, ReplayFile] | None = None,
) -> Iterator[tuple[str, Measurement]]:
    """(name, measurement) of every ``*.raw`` file in ``raw_dir`` (or the named ``files``),
    merged in order of the reads that completed them (then file name): deterministic.
    ``opened``, if given, receives each file's :class:`ReplayFile` (for its counters)."""
    names = files if files is not None else sorted(p.stem for p in Path(raw_dir).glob("*.raw"))
    streams = []
    for idx, name in enumerate(names):
        rf = ReplayFile(Path(raw_dir) / f"{name}.raw")
        if opened is not None:
            opened[name] = rf
        streams.append(_keyed(rf, idx, name))
    for _, _, _, name, m in heapq.merge(*streams, key=lambda x: x[:3]):
        yield name, m


def _keyed(
    rf: ReplayFile, idx: int, name: str
) -> Iterator[tuple[float, int, int, str, Measurement]]:
    for k, m in enumerate(rf):
        yield m.t_host, idx, k, name, m
