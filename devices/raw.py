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
record that checks.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

MAGIC = b"FGSLAM-RAW 1\n"
RECEIVED, SENT, MARKER = b"D", b"T", b"M"
_TAGS = (RECEIVED, SENT, MARKER)
_HEAD = struct.Struct("<cdI")
_CRC = struct.Struct("<I")
MAX_RECORD = 1 << 24  # bytes; longer lengths are damage

StrPath = str | os.PathLike[str]


class RawFormatError(ValueError):
    """Not a raw recording, or its header is unreadable."""


@dataclass(frozen=True)
class RawRecord:
    """One record: ``tag`` is 'D', 'T' or 'M'; ``t`` log time (s); ``data`` the bytes."""

    tag: str
    t: float
    data: bytes

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
    how many bytes of damaged records were skipped.
    """

    def __init__(self, path: StrPath) -> None:
        self.path = Path(path)
        data = self.path.read_bytes()
        if not data.startswith(MAGIC):
            raise RawFormatError(f"{path}: not an fgslam raw recording (no {MAGIC!r} line)")
        end = data.find(b"\n", len(MAGIC))
        try:
            if end < 0:
                raise ValueError("no end of line")
            header = json.loads(data[len(MAGIC) : end])
            if not isinstance(header, dict):
                raise ValueError("not a JSON object")
        except (ValueError, UnicodeDecodeError) as exc:
            raise RawFormatError(f"{path}: bad header line ({exc})") from None
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
        return RawRecord(tag.decode(), t, bytes(data[i + _HEAD.size : j])), j + _CRC.size

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
            yield rec
