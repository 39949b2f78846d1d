"""Raw recordings: every byte a driver receives (and sends), timestamped, crash safe.

One file per device (documented in ``docs/devices.md``)::

    FGSLAM-RAW 1\\n                 magic line
    {"device": "sick-pls", ...}\\n   header: one line of JSON (device kind, name, port, ...)
    record*                         binary records, each written with one write() call

    record = tag (1 byte: D received, T transmitted by the host, M marker)
             | t (f64 LE, log time of the read or write, s) | n (u32 LE) | n bytes
             | crc32 (u32 LE, zlib CRC-32 of tag .. the n bytes)

A marker's bytes are a JSON object ``{"event": "open", "baud": 9600, ...}``: the port was
opened ("open"), its line rate changed ("baud"), or it was closed ("close").

The file is opened unbuffered and each record goes out in a single ``write``: a killed process
loses at most the record being written, and the reader stops cleanly at a truncated last
record. A record whose CRC fails (a damaged file) is skipped by scanning forward for the next
record that checks. A record that checks but cannot be true (a time that is not finite or
beyond :data:`MAX_TIME`, a marker that is not such an object, a baud that is not an integer in
:data:`MIN_BAUD`..:data:`MAX_BAUD`) was written so: :class:`RawFormatError`, naming the file,
the record's byte offset and the cause, as for an unreadable file or header.
"""

from __future__ import annotations

import json
import math
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MAGIC = b"FGSLAM-RAW 1\n"
RECEIVED, SENT, MARKER = b"D", b"T", b"M"
_TAGS = (RECEIVED, SENT, MARKER)
_HEAD = struct.Struct("<cdI")
_CRC = struct.Struct("<I")
MAX_RECORD = 1 << 24  # bytes; longer lengths are damage
MAX_TIME = 1e9  # s: a record's log time beyond +-MAX_TIME (31 years) is not a time
MIN_BAUD, MAX_BAUD = 50, 20_000_000  # plausible serial line rates
MARKER_EVENTS = ("open", "baud", "close")

StrPath = str | os.PathLike[str]


class RawFormatError(ValueError):
    """A raw recording that cannot be read: unreadable, not a raw recording, a bad header or
    a record that cannot be true. The message names the file, the place (header line or
    record offset) and the cause; ``fgslam.online.ports`` passes it on as the CLI's UserError."""


def show(value: Any) -> str:
    """A short repr of a value read from a file, for an error message."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def integer(value: Any, what: str, lo: int, hi: int) -> int:
    """``value`` if it is an integer (not a bool) in ``lo..hi``; else ValueError naming
    ``what``."""
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{what} must be an integer in {lo}..{hi}, got {show(value)}")
    return value


def parse_json_object(data: bytes, what: str) -> dict[str, Any]:
    """The JSON object in ``data``; ValueError naming ``what`` if it is not one."""
    try:
        obj = json.loads(data)
    except RecursionError:
        raise ValueError(f"{what} is nested too deeply") from None
    except ValueError as exc:  # UnicodeDecodeError and JSONDecodeError among them
        raise ValueError(f"{what} is not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{what} is not a JSON object")
    return obj


def check_marker(data: bytes) -> dict[str, Any]:
    """A marker's JSON object, checked: an ``event`` of :data:`MARKER_EVENTS`, and for
    "open" and "baud" a ``baud`` in ``MIN_BAUD..MAX_BAUD``. ValueError otherwise."""
    mark = parse_json_object(data, "marker")
    event = mark.get("event")
    if not isinstance(event, str) or event not in MARKER_EVENTS:
        raise ValueError(
            f"marker event must be one of {', '.join(MARKER_EVENTS)}, got {show(event)}"
        )
    if event in ("open", "baud"):
        integer(mark.get("baud"), f"{event} marker's baud", MIN_BAUD, MAX_BAUD)
    return mark


@dataclass(frozen=True)
class RawRecord:
    """One record: ``tag`` is 'D', 'T' or 'M'; ``t`` log time (s); ``data`` the bytes;
    ``offset`` where it starts in the file."""

    tag: str
    t: float
    data: bytes
    offset: int = field(default=-1, compare=False)

    @property
    def marker(self) -> dict[str, Any]:
        """A marker record's JSON object."""
        return json.loads(self.data)


class RawRecorder:
    """Appends records to a new raw file (overwrites an existing one). Thread safe enough
    for one driver: each record is one unbuffered write."""

    def __init__(self, path: StrPath, header: dict[str, Any]) -> None:
        self.path = Path(path)
        self._f = open(self.path, "wb", buffering=0)
        self._f.write(MAGIC + json.dumps(header, sort_keys=True).encode() + b"\n")

    def _write(self, tag: bytes, t: float, data: bytes) -> None:
        head = _HEAD.pack(tag, t, len(data))
        crc = zlib.crc32(data, zlib.crc32(head))
        self._f.write(head + data + _CRC.pack(crc))

    def received(self, t: float, data: bytes) -> None:
        """Bytes read from the device at log time ``t``."""
        self._write(RECEIVED, t, bytes(data))

    def sent(self, t: float, data: bytes) -> None:
        """Bytes the host wrote to the device."""
        self._write(SENT, t, bytes(data))

    def marker(self, t: float, event: str, **info: Any) -> None:
        """A port event: "open" (with baud), "baud" (new baud), "close" (with reason)."""
        self._write(MARKER, t, json.dumps({"event": event, **info}, sort_keys=True).encode())

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> RawRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RawReader:
    """Reads a raw file: ``header`` on construction, records by iteration.

    ``truncated`` tells whether the file ended inside a record (a crash), ``skipped_bytes``
    how many bytes of damaged records were skipped. A file that cannot be read or has no
    valid header raises :class:`RawFormatError` here, a record that checks but cannot be true
    (see the module) during iteration.
    """

    def __init__(self, path: StrPath) -> None:
        self.path = Path(path)
        try:
            data = self.path.read_bytes()
        except OSError as exc:
            raise RawFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
        if not data.startswith(MAGIC):
            raise RawFormatError(f"{path}: not an fgslam raw recording (no {MAGIC!r} line)")
        end = data.find(b"\n", len(MAGIC))
        try:
            if end < 0:
                raise ValueError("no end of line")
            header = parse_json_object(data[len(MAGIC) : end], "header")
        except ValueError as exc:
            raise RawFormatError(f"{path}, line 2: bad header line ({exc})") from None
        self.header: dict[str, Any] = header
        self._data = data
        self._start = end + 1
        self.truncated = False
        self.skipped_bytes = 0

    def _record_at(self, i: int) -> tuple[RawRecord, int] | bool | None:
        """The record at i and the next offset; None if the file ends inside it; False if
        the bytes at i are not a valid record."""
        data = self._data
        if len(data) - i < _HEAD.size:
            return None
        tag, t, n = _HEAD.unpack_from(data, i)
        if tag not in _TAGS or n > MAX_RECORD:
            return False
        j = i + _HEAD.size + n
        if len(data) < j + _CRC.size:
            return None
        (crc,) = _CRC.unpack_from(data, j)
        if zlib.crc32(data[i:j]) != crc:
            return False
        return RawRecord(tag.decode(), t, bytes(data[i + _HEAD.size : j]), i), j + _CRC.size

    def _check(self, rec: RawRecord) -> None:
        """RawFormatError if a record that passed its CRC cannot be true."""
        try:
            if not (math.isfinite(rec.t) and abs(rec.t) <= MAX_TIME):
                raise ValueError(f"time {rec.t!r} s is not a log time (|t| <= {MAX_TIME:g})")
            if rec.tag == "M":
                check_marker(rec.data)
        except ValueError as exc:
            raise RawFormatError(f"{self.path}, record at byte {rec.offset}: {exc}") from None

    def _next_valid(self, i: int) -> int:
        """Offset of the first valid record after i (the file's length if there is none)."""
        n = len(self._data)
        k = i + 1
        while k < n:
            got = self._record_at(k)
            if got is not None and got is not False:
                return k
            k += 1
        return n

    def __iter__(self) -> Iterator[RawRecord]:
        i, n = self._start, len(self._data)
        while i < n:
            got = self._record_at(i)
            if got is False or got is None:
                # damage, or a record cut off at the end of the file (a crash): a damaged
                # length also looks like the latter, so look for a valid record further on
                k = self._next_valid(i)
                self.skipped_bytes += k - i
                if k == n and got is None:
                    self.truncated = True
                i = k
                continue
            rec, i = got
            self._check(rec)
            yield rec
