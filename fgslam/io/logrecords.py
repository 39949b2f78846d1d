"""The records of the native fgslam log (docs/log-format.md): the format's constants, opening
its (possibly gzipped) files, one event as one line (:func:`format_record`) and one line as one
event (the parsers of :class:`fgslam.io.logfile.LogReader`, each raising ``_Bad`` with a
one-line message). The writer is :mod:`fgslam.io.logwriter`, the reader :mod:`fgslam.io.logfile`.
"""

from __future__ import annotations

import gzip
import io
import json
import math
import operator
from dataclasses import dataclass
from os import PathLike
from typing import IO, Any

import numpy as np

from fgslam.config import RobotConfig
from fgslam.errors import UserError
from fgslam.events import (
    SONAR_KINDS,
    Event,
    LaserScan,
    OdometryEvent,
    SonarEcho,
    SonarReading,
    TruthPose,
)

FORMAT_NAME = "FGSLAM-LOG"
FORMAT_VERSION = 2  # written; 2 added a scan's own bearings to the laser record
READ_VERSIONS = (1, 2)  # read
BEARINGS_TAG = "B"  # in a laser record: the scan's own bearings follow
GZIP_MAGIC = b"\x1f\x8b"
MAX_LINE_BYTES = 1 << 23  # longer lines are bad records (bounds memory on corrupt input)
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
