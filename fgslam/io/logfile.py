"""The native fgslam log: a versioned, line-oriented UTF-8 text file, optionally gzip-compressed.

The format is documented in ``docs/log-format.md``. Times are in s, lengths in m, angles in
rad; frames are those of :mod:`fgslam.events`. Numbers are written with ``repr`` so that a
round trip is exact. :class:`LogWriter` (:mod:`fgslam.io.logwriter`) writes incrementally and
deterministically (the same events give byte-identical files, gzip included);
:class:`LogReader` streams events in constant memory and reports every problem as a one-line
:class:`LogFormatError` naming file and line. The records themselves (one event, one line) are
:mod:`fgslam.io.logrecords`. A :class:`LogReader` is a
:class:`~fgslam.io.readers.source.LogSource`, the interface of every reader.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from array import array
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from fgslam.config import ConfigError, RobotConfig, from_dict
from fgslam.errors import ReaderError
from fgslam.events import Event, OdometryEvent
from fgslam.io.logrecords import (
    _PARSERS,
    _STREAMS,
    CLOCKS,
    FORMAT_NAME,
    FORMAT_VERSION,
    HEADER_TAGS,
    MAX_LINE_BYTES,
    READ_VERSIONS,
    UNIX_CLOCK,
    LogFormatError,
    LogHeader,
    StrPath,
    _Bad,
    _clip,
    _open_binary,
    _stamp,
    _strict_loads,
    _strip_eol,
)
from fgslam.io.readers.plausibility import Findings, Rules, check_events
from fgslam.io.readers.sanity import (
    BACKWARDS_TOLERANCE,
    choose_clock,
    index_stamps,
    stream_defects,
)
from fgslam.io.readers.source import Problems


class LogReader:
    """Reads a log: the header on construction, then events by iteration (single pass, in
    constant memory). Gzip is detected by its magic bytes.

    A :class:`~fgslam.io.readers.source.LogSource`, as every reader: what went wrong is in
    ``problems`` (a :class:`~fgslam.io.readers.source.Problems`, the foreign readers' type).
    Strict mode raises :class:`LogFormatError` at the first bad line. With ``tolerant=True``
    bad records are skipped and counted in ``skipped`` and ``skipped_by_reason``, the first
    :data:`fgslam.io.readers.source.MAX_PROBLEMS` messages kept in ``problems.messages``; header
    and gzip errors are always
    fatal. Records stamped earlier than the record of the same type before them are passed on
    as they are (the SLAM pipeline puts them back in order or drops them) and counted in
    ``backwards`` (by record type: odometry, laser, sonar, truth).

    ``timestamps`` checks the log's clock before reading (docs/readers.md, "Timestamps"):
    ``None`` (default) does not; ``"auto"`` refuses a log whose stamps are stamped 0,
    wrapped, quantised, junk or going backwards by more than ``backwards_tolerance`` s
    (:func:`fgslam.io.readers.sanity.stream_defects`) with a one-line :class:`LogFormatError`
    naming the defect and its first line, drops the records with sporadic bad stamps
    (counted in ``backwards``; an odometry record's ticks are added to the next one);
    ``"log"`` uses the stamps as they are whatever their defects; ``"index"`` stamps scan k
    at ``k * INDEX_PERIOD`` and spreads the other records between scans. What was done is in
    ``clock_record`` and ``summary()["timestamps"]``. The check reads the file once more
    (it needs a regular file).

    ``checks`` applies the plausibility rules to the events (laser ranges, scans without a
    valid beam, odometry beyond ``limits``, implausible truth, stamps out of order:
    :mod:`fgslam.io.readers.plausibility`), what they find in ``findings`` and
    ``summary()["plausibility"]``, one warning per kind in ``summary()["warnings"]``;
    ``strict`` makes the first finding an error naming the line (and a record with a
    sporadic bad stamp, otherwise dropped, too). ``LogReader(path)`` alone checks nothing.
    """

    def __init__(
        self,
        path: StrPath,
        tolerant: bool = False,
        timestamps: str | None = None,
        backwards_tolerance: float = BACKWARDS_TOLERANCE,
        checks: bool = False,
        strict: bool = False,
        limits: Any = None,
    ) -> None:
        self.path = path
        self.name = str(path)
        self.tolerant = tolerant
        self.strict = strict
        # records out of order are passed on; the counts are report.json's "input" section
        self.problems = Problems(
            passes_out_of_order=True, report_keys=("timestamps", "plausibility", "warnings")
        )
        self._last_t: dict[str, float] = {}
        self.clock: str | None = None  # the clock used, when checked
        self._index: tuple[np.ndarray, np.ndarray] | None = None  # lines, stamps (index)
        self._bad_lines: set[int] = set()  # records with sporadic bad stamps
        self._carry = (0, 0)  # ticks of dropped odometry records, for the next one
        self._lineno = 0  # the line of the record last read
        try:
            self._file, self._gzipped = _open_binary(path, "r")
        except OSError as exc:
            raise LogFormatError(f"{self.name}: cannot open log: {exc.strerror or exc}") from None
        try:
            self._lines = self._read_lines()
            self._pending: tuple[int, bytes | None] | None = None
            self._read_header()
            if timestamps is not None:
                self._check_clock(timestamps, backwards_tolerance)
        except BaseException:
            self.close()
            raise
        self._events = self._iter_events()
        if checks:
            rules = Rules.of(self.config, limits, clock=self.clock != "index")
            order = {"order": "passed on as stamped (the pipeline puts them back in order)"}
            self.problems.findings = Findings(self.name, strict, self._skip, rules, order)
            self._events = check_events(
                self._events, rules, self.problems.findings, lambda: self._lineno
            )

    # -- lines

    def _read_lines(self, file: IO[bytes] | None = None) -> Iterator[tuple[int, bytes | None]]:
        """(line number, bytes without EOL) pairs; None for a line longer than MAX_LINE_BYTES."""
        file = self._file if file is None else file
        n = 0
        while True:
            try:
                raw = file.readline(MAX_LINE_BYTES + 1)
                too_long = len(raw) > MAX_LINE_BYTES and not raw.endswith(b"\n")
                while too_long and raw and not raw.endswith(b"\n"):
                    raw = file.readline(MAX_LINE_BYTES)
            except (EOFError, zlib.error, OSError) as exc:  # BadGzipFile is an OSError
                where = f"after line {n}" if n else "at the start"
                what = "corrupt or truncated gzip data" if self._gzipped else "read error"
                raise LogFormatError(f"{self.name}: {what} {where} ({exc})") from None
            if not raw and not too_long:
                return
            n += 1
            yield n, None if too_long else _strip_eol(raw)

    def _fatal(self, lineno: int, message: str) -> LogFormatError:
        return LogFormatError(f"{self.name}:{lineno}: {message}")

    # -- header

    def _read_header(self) -> None:
        expected = f"expected first line '{FORMAT_NAME} {FORMAT_VERSION}'"
        first = next(self._lines, None)
        if first is None:
            raise LogFormatError(f"{self.name}: empty file, not an fgslam log ({expected})")
        try:
            text = (first[1] or b"").decode("utf-8")
        except UnicodeDecodeError:
            text = "\ufffd"
        f = text.split()
        if len(f) != 2 or f[0] != FORMAT_NAME:
            raise self._fatal(1, f"not an fgslam log ({expected}, got {_clip(text)})")
        if not (f[1].isascii() and f[1].isdigit() and len(f[1]) < 10):
            raise self._fatal(1, f"bad format version {_clip(f[1])} (expected an integer)")
        self.version = int(f[1])
        if self.version not in READ_VERSIONS:
            raise self._fatal(
                1,
                f"unsupported log format version {self.version} "
                f"(this fgslam reads versions {', '.join(map(str, READ_VERSIONS))})",
            )
        config_data: tuple[int, Any] | None = None
        world: str | None = None
        self.meta: dict[str, Any] = {}
        lineno = 1
        for lineno, raw in self._lines:
            try:
                f = raw.decode("utf-8").split(None, 1) if raw is not None else None
            except UnicodeDecodeError:
                f = None
            if f is not None and (not f or f[0].startswith("#")):
                continue  # blank line or comment
            if f is None or f[0] not in HEADER_TAGS:
                self._pending = (lineno, raw)  # the first record: the header has ended
                break
            tag = f[0]
            rest = raw.decode("utf-8").lstrip()[len(tag) + 1 :]
            if tag == "WORLD":
                if world is not None:
                    raise self._fatal(lineno, "second WORLD header line")
                world = rest
                continue
            try:
                data = _strict_loads(rest)
            except (ValueError, RecursionError) as exc:
                raise self._fatal(lineno, f"{tag} header: expected a JSON object ({exc})") from None
            if not isinstance(data, dict):
                raise self._fatal(
                    lineno, f"{tag} header: expected a JSON object, got {type(data).__name__}"
                )
            if tag == "CONFIG":
                if config_data is not None:
                    raise self._fatal(lineno, "second CONFIG header line")
                config_data = (lineno, data)
            else:
                for key in data:
                    if key in self.meta:
                        raise self._fatal(lineno, f"META header: key {key!r} given twice")
                self.meta.update(data)
        where = f"{self.name}:{lineno}" if self._pending else f"{self.name}"
        if config_data is None:
            raise LogFormatError(f"{where}: missing CONFIG header line (before the first record)")
        if world is None:
            raise LogFormatError(f"{where}: missing WORLD header line (before the first record)")
        self.world = world
        self.config = self._config(*config_data)

    def _config(self, lineno: int, data: dict[str, Any]) -> RobotConfig:
        source = f"{self.name} (CONFIG header)"
        try:
            return from_dict(data, source=source)
        except ConfigError as exc:
            msg = str(exc).removeprefix(f"{source}:").strip()
        except (ValueError, TypeError, OverflowError, RecursionError) as exc:
            msg = f"invalid value ({exc})"
        raise self._fatal(lineno, f"CONFIG header: {msg}")

    # -- the reader interface (fgslam.io.readers.source.LogSource)

    format = "fgslam"
    reference_kind: str | None = None  # the format does not say (a simulator's truth)

    @property
    def clock_record(self) -> dict[str, Any] | None:
        """What the clock check found and chose (None: not checked)."""
        return self.problems.notes.get("timestamps")

    @clock_record.setter
    def clock_record(self, record: dict[str, Any] | None) -> None:
        if record is None:
            self.problems.notes.pop("timestamps", None)
        else:
            self.problems.notes["timestamps"] = record

    @property
    def skipped(self) -> int:
        return self.problems.skipped

    @property
    def skipped_by_reason(self) -> dict[str, int]:
        return dict(self.problems.skipped_by_reason)

    @property
    def backwards(self) -> Counter[str]:
        return self.problems.backwards

    @property
    def findings(self) -> Findings | None:
        return self.problems.findings

    def summary(self) -> dict[str, Any]:
        """``problems.summary()``: what was skipped or found out of order so far, the clock
        record (``"timestamps"``) and, with ``checks``, the plausibility findings and the
        warnings."""
        return self.problems.summary()

    # -- clock

    def _check_clock(self, requested: str, tolerance: float) -> None:
        """One pass over the records' stamps (tag and stamp only): the defects of the log's
        clock per stream, the clock chosen (:func:`fgslam.io.readers.sanity.choose_clock`), the
        records with sporadic bad stamps, and with ``index`` every record's stamp."""
        if requested not in CLOCKS:
            raise LogFormatError(
                f"unknown --timestamps {requested!r} for an fgslam log; expected one of {CLOCKS}"
            )
        if not Path(self.path).is_file():  # a FIFO or a device: it cannot be read twice
            if requested == "index":
                raise LogFormatError(f"{self.name}: --timestamps index needs a regular file")
            self.clock = "log"
            self.clock_record = {
                "requested": requested,
                "used": "log",
                "checked": False,
                "why": "not a regular file",
            }
            return
        lines, stamps, kinds = array("q"), array("d"), []
        first = self._pending[0] if self._pending is not None else math.inf
        f, _ = _open_binary(self.path, "r")
        try:
            for lineno, raw in self._read_lines(f):
                if lineno < first or raw is None:
                    continue
                tok = raw.split(None, 2)
                if len(tok) < 2 or tok[0] not in (b"O", b"L", b"S", b"T"):
                    continue
                tag = tok[0].decode()
                try:
                    t = _stamp(tok[1].decode("ascii"), "")
                except (_Bad, UnicodeDecodeError):
                    continue  # a bad record: the reading pass reports it
                lines.append(lineno)
                stamps.append(t)
                kinds.append(_STREAMS[tag])
        except LogFormatError:
            pass  # damaged gzip data: the reading pass raises when it gets there
        finally:
            f.close()
        ln, ts, kd = np.asarray(lines, dtype=int), np.asarray(stamps), np.array(kinds)
        unix = bool(len(ts)) and float(np.median(np.abs(ts))) > UNIX_CLOCK
        streams = {k: (ln[kd == k], ts[kd == k]) for k in _STREAMS.values() if (kd == k).any()}
        report = stream_defects(streams, tolerance, scans="laser", zero_is_junk=unix)
        try:
            clock, record = choose_clock(
                self.name,
                {"log": report},
                requested,
                choices=CLOCKS,
                labels={"log": "stamps"},
                hint="index|log",
            )
        except ReaderError as exc:
            raise LogFormatError(str(exc)) from None
        record["unix_time"] = unix
        self.clock, self.clock_record = clock, record
        if clock == "index":
            kinds_index = ["scan" if k == "laser" else k for k in kinds]
            self._index = (ln, np.asarray(index_stamps(kinds_index)))
        else:
            for bad in report.sporadic.values():
                self._bad_lines |= bad

    @property
    def header(self) -> LogHeader:
        return LogHeader(self.version, self.config, self.world, dict(self.meta))

    # -- records

    def _record(self, lineno: int, raw: bytes | None) -> Event | None:
        try:
            if raw is None:
                raise _Bad("line too long", f"line longer than {MAX_LINE_BYTES} bytes")
            try:
                f = raw.decode("utf-8").split()
            except UnicodeDecodeError:
                raise _Bad("not UTF-8", "not UTF-8 text") from None
            if not f or f[0].startswith("#"):
                return None
            parser = _PARSERS.get(f[0])
            if parser is None:
                if f[0] in HEADER_TAGS:
                    raise _Bad("misplaced header line", f"{f[0]} header line after a record")
                raise _Bad(
                    "unknown record tag",
                    f"unknown record tag {_clip(f[0])} (expected O, L, S or T)",
                )
            event = parser(f, self.config)
            stream = _STREAMS[f[0]]
            if self._index is not None:
                lines, stamps = self._index
                i = int(np.searchsorted(lines, lineno))
                if i < len(lines) and lines[i] == lineno:
                    event = dataclasses.replace(event, t=float(stamps[i]))
            elif lineno in self._bad_lines:  # a sporadic junk or far-backward stamp
                what = f"{stream} record stamped {event.t:.6g} s (junk or far back)"
                self.problems.backward(stream, what, line=lineno)
                if isinstance(event, OdometryEvent):
                    r, left = self._carry
                    self._carry = (r + event.ticks_right, left + event.ticks_left)
                return None
            if isinstance(event, OdometryEvent) and self._carry != (0, 0):
                r, left = self._carry
                event = OdometryEvent(event.t, event.ticks_right + r, event.ticks_left + left)
                self._carry = (0, 0)
            if event.t < self._last_t.get(stream, -math.inf):
                self.backwards[stream] += 1
            else:
                self._last_t[stream] = event.t
            return event
        except _Bad as bad:
            message = f"{self.name}:{lineno}: {bad.message}"
            if not self.tolerant:
                raise LogFormatError(message) from None
            self._skip(bad.reason, message)
            return None

    def _skip(self, reason: str, message: str) -> None:
        """Count a record not turned into an event (or dropped by the plausibility rules)."""
        self.problems.skip(reason, message)

    def _iter_events(self) -> Iterator[Event]:
        try:
            if self._pending is not None:
                self._lineno = self._pending[0]
                event = self._record(*self._pending)
                if event is not None:
                    yield event
            for lineno, raw in self._lines:
                self._lineno = lineno
                event = self._record(lineno, raw)
                if event is not None:
                    yield event
        finally:
            self.close()

    def __iter__(self) -> Iterator[Event]:
        return self._events

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_log(path: StrPath, tolerant: bool = False) -> tuple[LogHeader, list[Event]]:
    """The header and all events of a log, in memory (for tests and small logs)."""
    with LogReader(path, tolerant=tolerant) as reader:
        return reader.header, list(reader)
