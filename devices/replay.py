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
from devices.raw import RawFormatError, RawReader, integer, show
from devices.sick import SickReceiver
from devices.sonar import SonarReceiver

DEVICE_KINDS = ("sick-pls", "sonar", "odometry")
MAX_ARRAY = 255  # a sonar array's index (its INFO device id is one byte)


def make_receiver(header: dict[str, Any]) -> Receiver:
    """The receiver for a recording's header (its ``device`` kind and options):
    RawFormatError for a kind not in :data:`DEVICE_KINDS`, a ``device_clock`` that is not a
    boolean, an ``array`` that is not an integer in 0..:data:`MAX_ARRAY`."""
    kind = header.get("device")
    if not isinstance(kind, str) or kind not in DEVICE_KINDS:
        raise RawFormatError(f"unknown device kind {show(kind)} (known: {', '.join(DEVICE_KINDS)})")
    clock = header.get("device_clock", True)
    if not isinstance(clock, bool):
        raise RawFormatError(f"device_clock must be true or false, got {show(clock)}")
    if kind == "sick-pls":
        return SickReceiver()
    if kind == "sonar":
        try:
            array = integer(header.get("array", 0), "array", 0, MAX_ARRAY)
        except ValueError as exc:
            raise RawFormatError(str(exc)) from None
        return SonarReceiver(array, clock)
    return OdometryReceiver(clock)


class ReplayFile:
    """Measurements of one raw file, in the order the driver produced them. After
    iteration: ``reader.truncated``, ``reader.skipped_bytes`` and ``receiver.counters()``.
    RawFormatError (naming the file) for a bad file, header or record."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.reader = RawReader(path)
        self.header = self.reader.header
        try:
            self.receiver = make_receiver(self.header)
        except RawFormatError as exc:
            raise RawFormatError(f"{path}, line 2 (header): {exc}") from None

    def __iter__(self) -> Iterator[Measurement]:
        rcv = self.receiver
        for rec in self.reader:
            if rec.tag == "D":
                for item in rcv.feed(rec.t, rec.data):
                    if isinstance(item, Measurement):
                        yield item
            elif rec.tag == "M":  # checked by the reader: a known event, a plausible baud
                mark = rec.marker
                if mark["event"] == "open":
                    rcv.reset(mark["baud"])
                elif mark["event"] == "baud":
                    rcv.set_baud(mark["baud"])


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
