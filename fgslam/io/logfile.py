"""The native fgslam log: a versioned, line-oriented UTF-8 text file, optionally gzip-compressed.

The format is documented in ``docs/log-format.md``. Times are in s, lengths in m, angles in
rad; frames are those of :mod:`fgslam.events`. Numbers are written with ``repr`` so that a
round trip is exact. :class:`LogWriter` writes incrementally and deterministically (the same
events give byte-identical files, gzip included); :class:`LogReader` streams events in constant
memory and reports every problem as a one-line :class:`LogFormatError` naming file and line.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gzip
import io
import json
import math
import operator
import os
import zlib
from array import array
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import IO, Any

import numpy as np

from fgslam.config import ConfigError, RobotConfig, from_dict
from fgslam.errors import ReaderError, UserError
from fgslam.events import (
    SONAR_KINDS,
    Event,
    LaserScan,
    OdometryEvent,
    SonarEcho,
    SonarReading,
    TruthPose,
)
from fgslam.io.readers.sanity import (
    BACKWARDS_TOLERANCE,
    choose_clock,
    index_stamps,
    stream_defects,
)
from fgslam.io.safeio import is_special, temp_path

FORMAT_NAME = "FGSLAM-LOG"
FORMAT_VERSION = 2  # written; 2 added a scan's own bearings to the laser record
READ_VERSIONS = (1, 2)  # read
BEARINGS_TAG = "B"  # in a laser record: the scan's own bearings follow
GZIP_MAGIC = b"\x1f\x8b"
MAX_LINE_BYTES = 1 << 23  # longer lines are bad records (bounds memory on corrupt input)
MAX_PROBLEMS = 20  # messages kept in LogReader.problems in tolerant mode
# Stamps beyond this (s) are not times (1e10 s is the year 2286 as Unix time); such a record
# would make every later one look late and be dropped.
MAX_ABS_STAMP = 1e10
KIND_LETTERS = {"plane": "P", "corner": "C", "edge": "E"}
LETTER_KINDS = {v: k for k, v in KIND_LETTERS.items()}
HEADER_TAGS = ("CONFIG", "WORLD", "META")
CLOCKS = ("auto", "log", "index")  # LogReader(timestamps=...), docs/readers.md
UNIX_CLOCK = 1e8  # s: a log whose median stamp is beyond runs on UNIX time (0 is then junk)
assert set(KIND_LETTERS) == set(SONAR_KINDS)

StrPath = str | PathLike[str]


class LogFormatError(UserError, ValueError):
    """A log file is malformed; the message is one line naming file, line and what was expected."""


@dataclass(frozen=True)
class LogHeader:
    """What a log's header says: format version, robot configuration, world name, metadata."""

    version: int
    config: RobotConfig
    world: str
    meta: dict[str, Any]


# ---------------------------------------------------------------------------------------------
# Files


class _OwningGzipFile(gzip.GzipFile):
    """A GzipFile on an open file object that also closes that file."""

    def __init__(self, raw: IO[bytes], mode: str, **kwargs: Any) -> None:
        self._raw = raw
        super().__init__(filename="", mode=mode, fileobj=raw, **kwargs)

    def close(self) -> None:
        try:
            super().close()
        finally:
            raw = getattr(self, "_raw", None)
            if raw is not None:
                raw.close()


def _open_binary(path: StrPath, mode: str) -> tuple[IO[bytes], bool]:
    """Open ``path`` for binary reading ('r', gzip detected by magic bytes) or writing ('w',
    gzip if the name ends in ``.gz``, deterministic: no name, mtime 0). Returns (file, gzipped)."""
    if mode == "r":
        raw = open(path, "rb")
        if raw.peek(2)[:2] == GZIP_MAGIC:
            return _OwningGzipFile(raw, "rb"), True
        return raw, False
    if mode == "w":
        raw = open(path, "wb")
        if str(path).endswith(".gz"):
            return _OwningGzipFile(raw, "wb", mtime=0, compresslevel=6), True
        return raw, False
    raise ValueError(f"mode must be 'r' or 'w', got {mode!r}")


def open_text(path: StrPath, mode: str) -> IO[str]:
    """Open a (possibly gzipped) UTF-8 text file: mode 'r' detects gzip by its magic bytes,
    mode 'w' compresses if the name ends in ``.gz`` (deterministically). Lines end in LF."""
    binary, _ = _open_binary(path, mode.replace("t", ""))
    return io.TextIOWrapper(binary, encoding="utf-8", newline="\n" if mode[0] == "w" else None)


# ---------------------------------------------------------------------------------------------
# Writing


def _fmt(x: Any, what: str) -> str:
    """A finite number written exactly (shortest round-trip repr)."""
    v = float(x)
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {v!r}")
    return repr(v)


def format_record(event: Event) -> str:
    """One record line (without newline) for ``event``; ValueError if it cannot be represented."""
    t = _fmt(event.t, "timestamp")
    if abs(event.t) > MAX_ABS_STAMP:
        raise ValueError(f"timestamp {event.t!r} is not a plausible time (|t| > {MAX_ABS_STAMP:g})")
    if isinstance(event, OdometryEvent):
        return f"O {t} {operator.index(event.ticks_right)} {operator.index(event.ticks_left)}"
    if isinstance(event, LaserScan):
        r = np.asarray(event.ranges, dtype=float)
        if r.ndim != 1 or np.isinf(r).any():
            raise ValueError("laser ranges must be a 1-D array of finite numbers or NaN")
        line = ["L", t, str(r.size), *map(repr, r.tolist())]
        if event.bearings is not None:  # LaserScan checked them: finite, increasing
            b = np.asarray(event.bearings, dtype=float)
            line += [BEARINGS_TAG, *map(repr, b.tolist())]
        return " ".join(line)
    if isinstance(event, SonarReading):
        parts = [
            f"S {t} {operator.index(event.array)} {_fmt(event.pan, 'pan')} {len(event.echoes)}"
        ]
        for e in event.echoes:
            if e.kind not in KIND_LETTERS:
                raise ValueError(f"sonar echo kind must be one of {SONAR_KINDS}, got {e.kind!r}")
            parts.append(
                f"{KIND_LETTERS[e.kind]} {_fmt(e.range, 'range')} {_fmt(e.bearing, 'bearing')}"
            )
        return " ".join(parts)
    if isinstance(event, TruthPose):
        return f"T {t} {_fmt(event.x, 'x')} {_fmt(event.y, 'y')} {_fmt(event.theta, 'theta')}"
    raise TypeError(f"not a log event: {type(event).__name__}")


def _finite_float(text: str) -> float:
    v = float(text)
    if not math.isfinite(v):
        raise ValueError(f"number {text} is not finite")
    return v


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def _strict_loads(text: str) -> Any:
    """Strict JSON, as :func:`_json` writes it: no NaN, Infinity or numbers beyond a float."""
    return json.loads(text, parse_float=_finite_float, parse_constant=_no_constant)


def _json(data: Any, sort_keys: bool = False) -> str:
    """Compact one-line strict JSON."""
    return json.dumps(data, separators=(",", ":"), allow_nan=False, sort_keys=sort_keys)


class LogWriter:
    """Writes a log incrementally: the header on construction, one line per :meth:`write`.

    A ``.gz`` name gives a gzip file; output is deterministic (byte-identical for the same
    arguments and events). The log is written to a temporary file in the same folder and
    renamed to ``path`` by :meth:`close`, so ``path`` never holds a partial log; leaving the
    context manager by an exception (or :meth:`abort`) deletes the temporary file instead.
    """

    def __init__(
        self, path: StrPath, config: RobotConfig, world: str, meta: dict[str, Any] | None = None
    ) -> None:
        if "\n" in world or "\r" in world:
            raise ValueError("world name must not contain a line break")
        lines = [f"{FORMAT_NAME} {FORMAT_VERSION}", f"CONFIG {_json(config.to_dict())}"]
        lines.append(f"WORLD {world}")
        if meta:
            lines.append(f"META {_json(meta, sort_keys=True)}")
        self.path = path
        self.config = config
        self._n_beams = config.laser.n_beams
        self._n_arrays = len(config.sonar.arrays)
        self._tmp = path if is_special(path) else temp_path(path)
        self._f = open_text(self._tmp, "w")
        self._done = False
        self._f.write("\n".join(lines) + "\n")

    def write(self, event: Event) -> None:
        """Append one event; ValueError if it does not fit the configuration or the format (a
        scan without its own bearings must have the configured beam count)."""
        if (
            isinstance(event, LaserScan)
            and event.bearings is None
            and np.size(event.ranges) != self._n_beams
        ):
            raise ValueError(
                f"laser scan has {np.size(event.ranges)} ranges, configuration has "
                f"n_beams={self._n_beams}"
            )
        if isinstance(event, SonarReading) and not 0 <= event.array < self._n_arrays:
            raise ValueError(f"sonar array {event.array} not in the configuration")
        self._f.write(format_record(event) + "\n")

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        """Finish the log: flush, close and rename it into place."""
        if self._done:
            return
        self._done = True
        try:
            self._f.close()
            if self._tmp != self.path:
                os.replace(self._tmp, self.path)
        except BaseException:
            self._discard()
            raise

    def abort(self) -> None:
        """Give up: delete the temporary file, leave ``path`` as it was."""
        if self._done:
            return
        self._done = True
        try:
            self._f.close()
        finally:
            self._discard()

    def _discard(self) -> None:
        if self._tmp != self.path:
            with contextlib.suppress(OSError):
                os.unlink(self._tmp)

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# ---------------------------------------------------------------------------------------------
# Reading


class _Bad(Exception):
    """A bad record: ``reason`` is its category (for counting), ``message`` the explanation."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.message = message


def _clip(tok: str) -> str:
    return repr(tok if len(tok) <= 30 else tok[:27] + "...")


def _float(tok: str, what: str, rec: str, allow_nan: bool = False) -> float:
    try:
        if not tok.isascii() or "_" in tok:
            raise ValueError
        v = float(tok)
    except ValueError:
        raise _Bad(rec, f"{rec}: {what}: expected a number, got {_clip(tok)}") from None
    if not (math.isfinite(v) or (allow_nan and math.isnan(v))):
        raise _Bad(rec, f"{rec}: {what}: expected a finite number, got {_clip(tok)}")
    return v


def _int(tok: str, what: str, rec: str, minimum: int | None = None) -> int:
    try:
        if not tok.isascii() or "_" in tok:
            raise ValueError
        v = int(tok)
    except ValueError:
        raise _Bad(rec, f"{rec}: {what}: expected an integer, got {_clip(tok)}") from None
    if minimum is not None and v < minimum:
        raise _Bad(rec, f"{rec}: {what}: expected an integer >= {minimum}, got {v}")
    return v


def _count(f: list[str], n: int, syntax: str, rec: str) -> None:
    if len(f) != n:
        raise _Bad(rec, f"{rec}: expected {n} fields '{syntax}', got {len(f)}")


def _stamp(tok: str, rec: str) -> float:
    t = _float(tok, "timestamp", rec)
    if abs(t) > MAX_ABS_STAMP:
        raise _Bad(
            "absurd timestamp",
            f"{rec}: timestamp: {_clip(tok)} is not a plausible time "
            f"(expected |t| <= {MAX_ABS_STAMP:g} s)",
        )
    return t


def _odometry(f: list[str], cfg: RobotConfig) -> OdometryEvent:
    rec = "odometry record"
    _count(f, 4, "O t ticks_right ticks_left", rec)
    t = _stamp(f[1], rec)
    return OdometryEvent(t, _int(f[2], "ticks_right", rec), _int(f[3], "ticks_left", rec))


def _numbers(toks: list[str], what: str, rec: str, allow_nan: bool) -> np.ndarray:
    """Tokens as an array of finite numbers (or NaN, ``allow_nan``); _Bad naming the first
    bad one (``what`` and its index from 1)."""
    joined = "".join(toks)
    try:  # fast path; on any doubt, check token by token for a precise message
        if not joined.isascii() or "_" in joined:
            raise ValueError
        v = np.array([float(x) for x in toks], dtype=float)
        if np.isinf(v).any() or (not allow_nan and np.isnan(v).any()):
            raise ValueError
    except ValueError:
        v = np.array(
            [_float(x, f"{what} {i + 1}", rec, allow_nan=allow_nan) for i, x in enumerate(toks)]
        )
    return v


def _laser(f: list[str], cfg: RobotConfig) -> LaserScan:
    rec = "laser record"
    if len(f) < 3:
        raise _Bad(rec, f"{rec}: expected 'L t n r_1 ... r_n', got {len(f)} fields")
    t = _stamp(f[1], rec)
    n = _int(f[2], "n", rec, minimum=0)
    toks = f[3:]
    bearings = None
    if len(toks) == 2 * n + 1 and toks[n] == BEARINGS_TAG:  # the scan's own bearings
        bearings = _numbers(toks[n + 1 :], "bearing", rec, allow_nan=False)
        if (np.diff(bearings) <= 0).any():
            raise _Bad(rec, f"{rec}: bearings must increase strictly")
        toks = toks[:n]
    elif n != cfg.laser.n_beams:
        raise _Bad(rec, f"{rec}: n={n} but the configuration has n_beams={cfg.laser.n_beams}")
    if len(toks) != n:
        raise _Bad(rec, f"{rec}: expected {n} ranges after n={n}, got {len(toks)}")
    return LaserScan(t, _numbers(toks, "range", rec, allow_nan=True), bearings)


def _sonar(f: list[str], cfg: RobotConfig) -> SonarReading:
    rec = "sonar record"
    if len(f) < 5:
        raise _Bad(
            rec, f"{rec}: expected 'S t array pan n kind_1 r_1 b_1 ...', got {len(f)} fields"
        )
    t = _stamp(f[1], rec)
    array = _int(f[2], "array", rec, minimum=0)
    if array >= len(cfg.sonar.arrays):
        raise _Bad(
            rec,
            f"{rec}: array {array} not in the configuration "
            f"(it has {len(cfg.sonar.arrays)} sonar arrays)",
        )
    pan = _float(f[3], "pan", rec)
    n = _int(f[4], "n", rec, minimum=0)
    if len(f) - 5 != 3 * n:
        raise _Bad(rec, f"{rec}: expected {3 * n} echo fields after n={n}, got {len(f) - 5}")
    echoes = []
    for i in range(n):
        letter, r, b = f[5 + 3 * i : 8 + 3 * i]
        if letter not in LETTER_KINDS:
            raise _Bad(
                rec, f"{rec}: echo {i + 1}: unknown kind {_clip(letter)} (expected P, C or E)"
            )
        echoes.append(
            SonarEcho(
                LETTER_KINDS[letter],
                _float(r, f"echo {i + 1} range", rec),
                _float(b, f"echo {i + 1} bearing", rec),
            )
        )
    return SonarReading(t, array, pan, tuple(echoes))


def _truth(f: list[str], cfg: RobotConfig) -> TruthPose:
    rec = "truth record"
    _count(f, 5, "T t x y theta", rec)
    t = _stamp(f[1], rec)
    return TruthPose(t, _float(f[2], "x", rec), _float(f[3], "y", rec), _float(f[4], "theta", rec))


_PARSERS = {"O": _odometry, "L": _laser, "S": _sonar, "T": _truth}
_STREAMS = {"O": "odometry", "L": "laser", "S": "sonar", "T": "truth"}


def _strip_eol(raw: bytes) -> bytes:
    if raw.endswith(b"\n"):
        raw = raw[:-1]
    return raw[:-1] if raw.endswith(b"\r") else raw


class LogReader:
    """Reads a log: the header on construction, then events by iteration (single pass, in
    constant memory). Gzip is detected by its magic bytes.

    Strict mode raises :class:`LogFormatError` at the first bad line. With ``tolerant=True``
    bad records are skipped and counted in ``skipped`` and ``skipped_by_reason``, the first
    ``MAX_PROBLEMS`` messages kept in ``problems``; header and gzip errors are always fatal.
    Records stamped earlier than the record of the same type before them are passed on as
    they are (the SLAM pipeline puts them back in order or drops them) and counted in
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
        self.skipped = 0
        self.skipped_by_reason: dict[str, int] = {}
        self.problems: list[str] = []
        self.backwards: Counter[str] = Counter()
        self._last_t: dict[str, float] = {}
        self.clock: str | None = None  # the clock used, when checked
        self.clock_record: dict[str, Any] | None = None
        self._index: tuple[np.ndarray, np.ndarray] | None = None  # lines, stamps (index)
        self._bad_lines: set[int] = set()  # records with sporadic bad stamps
        self._carry = (0, 0)  # ticks of dropped odometry records, for the next one
        self._lineno = 0  # the line of the record last read
        self.findings: Any = None  # the plausibility findings (checks)
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
            from fgslam.io.readers.plausibility import Findings, Rules, check_events

            rules = Rules.of(self.config, limits, clock=self.clock != "index")
            order = {"order": "passed on as stamped (the pipeline puts them back in order)"}
            self.findings = Findings(self.name, strict, self._skip, rules, order)
            self._events = check_events(self._events, rules, self.findings, lambda: self._lineno)

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

    def summary(self) -> dict[str, Any]:
        """What was skipped or found out of order so far (the keys of the foreign readers'
        ``problems.summary()``)."""
        out = {
            "skipped": self.skipped,
            "skipped_by_reason": dict(self.skipped_by_reason),
            "timestamps_backwards": dict(self.backwards),
            "problems": list(self.problems),
        }
        if self.clock_record is not None:
            out["timestamps"] = self.clock_record
        if self.findings is not None:
            from fgslam.io.readers.common import clock_warnings

            out["plausibility"] = self.findings.summary()
            out["warnings"] = clock_warnings(self.clock_record) + self.findings.warnings()
        return out

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
                if self.findings is not None:
                    what = f"{stream} record stamped {event.t:.6g} s (junk or far back)"
                    self.findings.note("order", what, line=lineno)
                self.backwards[stream] += 1
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
        self.skipped += 1
        self.skipped_by_reason[reason] = self.skipped_by_reason.get(reason, 0) + 1
        if len(self.problems) < MAX_PROBLEMS:
            self.problems.append(message)

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
