"""Sanity of foreign logs' clocks and odometry (docs/readers.md, "Timestamps and odometry").

**Clocks.** :func:`stream_defects` examines one clock over the streams of a log, each in file
order (CARMEN, :func:`stamp_defects`: the ``timestamp`` field, the ``ipc`` clock, or
``logger_timestamp``, over the scans and the odometry records; native fgslam logs: the
records' stamps over the laser, odometry, sonar and truth records; ROS bags: the header
stamps or the record times, per topic), and names what makes it unusable:

- ``stamped 0``: more than half of a stream's stamps are 0;
- ``wrapped at 2^32``: a stamp drops by more than 2^31 s from a predecessor above 2^31 s;
- ``quantised``: more than :data:`MAX_SHARED_SCANS` of the scans share the stamp of the scan
  before them (stamps written with too few digits);
- ``junk``/``backwards``: more than :data:`MAX_BAD_FRACTION` of a stream's stamps are junk
  (negative or ``0 < |t| < 1e-9``, like 3e-86; or, in a stream that is not mostly 0, a 0)
  or earlier than the latest sound stamp before them by more than ``tolerance`` s.

Fewer junk or far-backward stamps than that are *sporadic*: counted (``bad_stamps``), and
the reader treats those records as going backwards (a scan is dropped, an odometry record's
motion is carried into the next sample). :func:`choose_clock` then takes the first sound
clock in the reader's order of preference (CARMEN: the ``ipc`` field, else the ``logger``
field; ROS: header stamps, else record times; native: its one clock), else refuses with one
line naming each clock's first defect and its line (message, topic), unless the reader allows
a ``fallback`` (CARMEN and native logs, unless strict: ``index``, the records' order, with
the reason recorded); ``--timestamps`` forces a choice (``index``, CARMEN and native logs:
scan k at ``k * INDEX_PERIOD`` s, the other records between two scans spread evenly between
them). The record of the choice names the clock in words (``"clock"``, for report.json).
:func:`common_clock` tells whether several streams' stamps run on one clock, against a
second clock (a bag's record times).

**Odometry.** :func:`implausible` tells whether a pose increment over ``dt`` s exceeds a speed
or turn-rate bound (with ``MIN_DT`` s of slack, so that stamps too close together are no
excuse), or, without a clock (``dt`` None: index stamps), a bound on one step's distance
alone; :func:`usage` is the fraction of the bound an increment takes; :class:`OdometryLimits`
holds the bounds and the hole tolerance. A *hole* is a gap
between two odometry records longer than ``hole`` s with scans in it: counted, and its
samples are stamped at its end, so that the preintegration sees the gap
(:func:`factors.odometry.preintegrate` adds the hole covariance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fgslam.errors import ReaderError

CLOCKS = ("auto", "ipc", "logger", "index")
INDEX_PERIOD = 0.2  # s between scans with --timestamps index
MAX_STAMP = 1e10  # s: a stamp beyond is not a time (CARMEN stamps are UNIX seconds, 2^32 = 4.3e9)
MAX_SHARED_SCANS = 0.05  # fraction of scans sharing the previous scan's stamp: "quantised"
MAX_BAD_FRACTION = 0.02  # fraction of junk or far-backward stamps tolerated as sporadic
BACKWARDS_TOLERANCE = 2.0  # s
WRAP = 2.0**32
MIN_DT = 0.25  # s of slack in the plausibility test


class NoUsableClock(ReaderError):
    """No clock of the log is sound and no fallback was allowed (strict)
    (:func:`choose_clock`)."""


@dataclass(frozen=True)
class OdometryLimits:
    """Plausible odometry: at most ``max_speed`` m/s and ``max_turn_rate`` rad/s between two
    records (with :data:`MIN_DT` s of slack), or, where the log has no clock (index stamps),
    at most ``max_step`` m between two records (any turn: a heading is known only modulo a
    full turn); odometry that repeats its last pose is held as possibly stale for up to
    ``stale`` s, and a gap of a pose stream of up to ``spread`` s is interpolated: its motion,
    which the record after it measures, is spread over it
    (:class:`fgslam.io.readers.odometry.StaleOdometryHold`). A longer gap with scans in it is
    an odometry hole (longer than ``hole`` s where the odometry is no pose stream: corrected
    CARMEN logs)."""

    max_speed: float = 3.0
    max_turn_rate: float = 6.0
    hole: float = 1.0
    stale: float = 2.0  # s; MIT CSAIL's freezes last up to 1.07 s
    spread: float = 5.0  # s; intel.orig.bag's /odom pauses for up to 3.1 s (258 gaps of 1-3 s)
    max_step: float = 10.0  # m between two odometry records, without a clock

    def notes(self) -> dict[str, float]:
        """The bounds as the readers report them (``summary()["odometry"]["limits"]``)."""
        return {
            "max_speed_m_s": self.max_speed,
            "max_turn_rate_rad_s": self.max_turn_rate,
            "hole_s": self.hole,
            "stale_s": self.stale,
            "spread_s": self.spread,
            "max_step_m": self.max_step,
        }


def usage(inc: Any, dt: float | None, limits: OdometryLimits) -> float:
    """The fraction of the plausible motion that the increment (dx m, dy m, dtheta rad) over
    ``dt`` s takes (above 1: implausible; NaN counts as infinite): the larger of distance
    over ``max_speed * (dt + MIN_DT)`` and turn over ``max_turn_rate * (dt + MIN_DT)``; a
    non-finite ``dt`` (a junk stamp) gets ``MIN_DT`` alone; ``dt`` None (no clock): distance
    over ``max_step``."""
    dist = math.hypot(float(inc[0]), float(inc[1]))
    turn = abs(float(inc[2]))
    if dt is None:
        out = dist / limits.max_step
    else:
        span = max(dt, 0.0) + MIN_DT if math.isfinite(dt) else MIN_DT
        out = max(dist / (limits.max_speed * span), turn / (limits.max_turn_rate * span))
    return out if math.isfinite(out) and math.isfinite(turn) else math.inf


def implausible(inc: Any, dt: float | None, limits: OdometryLimits) -> str | None:
    """Why the increment (dx m, dy m, dtheta rad) over ``dt`` s is implausible, or None;
    ``dt`` None: the log has no clock, only the distance of one step is bounded."""
    dist = math.hypot(float(inc[0]), float(inc[1]))
    turn = abs(float(inc[2]))
    if dt is None:
        if not (dist <= limits.max_step and math.isfinite(turn)):
            return f"{dist:.3g} m in one step (more than {limits.max_step:g} m; no clock)"
        return None
    span = max(dt, 0.0) + MIN_DT if math.isfinite(dt) else MIN_DT
    if not (dist <= limits.max_speed * span):
        return f"{dist:.3g} m in {max(dt, 0.0):.3g} s (more than {limits.max_speed:g} m/s)"
    if not (turn <= limits.max_turn_rate * span):
        return (
            f"{math.degrees(turn):.3g} deg in {max(dt, 0.0):.3g} s "
            f"(more than {limits.max_turn_rate:g} rad/s)"
        )
    return None


@dataclass
class StampReport:
    """What :func:`stamp_defects` found in one field: defects (one line each, with the first
    bad line) and the line numbers of sporadic bad stamps."""

    defects: list[str] = field(default_factory=list)
    sporadic: dict[str, set[int]] = field(default_factory=dict)

    @property
    def sound(self) -> bool:
        return not self.defects


def _stream(
    name: str,
    lines: np.ndarray,
    t: np.ndarray,
    tolerance: float,
    rep: StampReport,
    unit: str = "line",
    zero_is_junk: bool = True,
) -> None:
    if not len(t):
        return
    zero = t == 0
    mostly_zero = zero.mean() > 0.5
    if mostly_zero:
        rep.defects.append(
            f"{name} stamped 0 ({int(zero.sum())} of {len(t)}, first at {unit} {lines[zero][0]})"
        )
        return
    junk = ~np.isfinite(t)
    if zero_is_junk:
        junk |= (t < 0) | (np.abs(t) < 1e-9)
    bad = junk.copy()
    latest = -math.inf
    wrapped = None
    for i in range(len(t)):
        if junk[i]:
            continue
        if latest > WRAP / 2 and latest - t[i] > WRAP / 2 and wrapped is None:
            wrapped = i
        if t[i] < latest - tolerance:
            bad[i] = True
        else:
            latest = max(latest, t[i])
    if wrapped is not None:
        rep.defects.append(f"{name} stamps wrapped at 2^32 ({unit} {lines[wrapped]})")
        return
    if bad.sum() > MAX_BAD_FRACTION * len(t):
        i = int(np.argmax(bad))
        what = "junk" if junk[i] else f"backwards by more than {tolerance:g} s"
        rep.defects.append(
            f"{name} stamps {what} ({int(bad.sum())} of {len(t)} bad, first at {unit} "
            f"{lines[i]}: {t[i]:.6g})"
        )
        return
    if bad.any():
        rep.sporadic[name] = set(lines[bad].tolist())


def stream_defects(
    streams: dict[str, tuple[Any, Any]],
    tolerance: float = BACKWARDS_TOLERANCE,
    scans: str | None = "scan",
    unit: str = "line",
    zero_is_junk: bool = True,
) -> StampReport:
    """The defects of one clock over any number of streams: ``streams`` maps a stream's name
    (``"scan"``, ``"odometry"``, a ROS topic) to its records' positions (line numbers, or
    message numbers: ``unit`` names them in the messages) and stamps, each in file order.
    The stream named ``scans`` is also checked for quantised stamps. ``zero_is_junk``:
    stamps 0, negative or below 1e-9 s are junk (a UNIX clock, as CARMEN's); False for a
    clock that may start at 0 (the simulator's), where only non-finite stamps are junk
    (a stray 0 later in the log still goes backwards)."""
    rep = StampReport()
    arrays = {
        k: (np.asarray(ln, dtype=int), np.asarray(t, dtype=float)) for k, (ln, t) in streams.items()
    }
    for name, (ln, t) in arrays.items():
        _stream(name, ln, t, tolerance, rep, unit, zero_is_junk)
    if scans in arrays:
        sl, st = arrays[scans]
        if len(st) > 1 and not (st == 0).mean() > 0.5:
            same = np.diff(st) == 0
            if same.mean() > MAX_SHARED_SCANS:
                i = int(np.argmax(same)) + 1
                rep.defects.append(
                    f"{scans} stamps quantised ({int(same.sum()) + 1} of {len(st)} scans share "
                    f"a stamp, {len(np.unique(st))} distinct values; first at {unit} {sl[i]}: "
                    f"{st[i]:.6g})"
                )
    return rep


def stamp_defects(
    scan_lines: Any,
    scan_t: Any,
    odo_lines: Any,
    odo_t: Any,
    tolerance: float = BACKWARDS_TOLERANCE,
) -> StampReport:
    """The defects of one stamp field over the scans and the odometry records (file order)."""
    return stream_defects({"scan": (scan_lines, scan_t), "odometry": (odo_lines, odo_t)}, tolerance)


def common_clock(offsets: dict[str, Any], tolerance: float = BACKWARDS_TOLERANCE) -> str | None:
    """Whether the stamps of several streams run on one clock, judged against a second clock
    that does (a bag's record times): ``offsets`` maps a stream to (second clock - stamp)
    per record. None when the streams' median offsets agree within ``tolerance`` s; else the
    defect, naming the two streams furthest apart."""
    med = {k: float(np.median(v)) for k, v in offsets.items() if len(v)}
    finite = {k: v for k, v in med.items() if math.isfinite(v)}
    if len(finite) < 2:
        return None
    lo, hi = min(finite, key=finite.get), max(finite, key=finite.get)
    gap = finite[hi] - finite[lo]
    if gap <= tolerance:
        return None
    return (
        f"{lo} and {hi} {gap:.6g} s apart against the record times (not one clock; "
        f"median record time - stamp {finite[lo]:.6g} s and {finite[hi]:.6g} s)"
    )


def choose_clock(
    name: str,
    reports: dict[str, StampReport],
    requested: str = "auto",
    choices: tuple[str, ...] = CLOCKS,
    labels: dict[str, str] | None = None,
    hint: str = "index|ipc|logger",
    fallback: str | None = None,
) -> tuple[str, dict[str, Any]]:
    """The clock to use and the record of the choice (for the reader's metadata).
    ``reports`` maps each clock that can be checked to its defects, in the order of
    preference (CARMEN: ``ipc``, ``logger``; ROS: ``header``, ``bag``; native: ``log``);
    ``choices`` are the values ``requested`` may take (``auto`` among them); ``labels`` name
    the clocks in the error (default ``"<clock> field"``), ``hint`` the ``--timestamps``
    values it suggests. When ``requested`` is ``auto`` and no clock is sound, ``fallback``
    is used (``index``: the records' order; the record's ``fallback`` says why), or without
    one :class:`NoUsableClock` (a ``ReaderError``) is raised. The
    record's ``clock`` names the clock used and why, in words (for report.json)."""
    if requested not in choices:
        raise ReaderError(f"unknown --timestamps {requested!r}; expected one of {choices}")
    labels = labels or {}
    record: dict[str, Any] = {
        "requested": requested,
        "defects": {k: list(r.defects) for k, r in reports.items() if r.defects},
    }

    def label(k: str) -> str:
        return labels.get(k, f"{k} field")

    if requested == "auto":
        for clock, rep in reports.items():
            if rep.sound:
                chosen = clock
                why = [f"{label(clock)}, sound"]
                why += [f"{label(k)}: {r.defects[0]}" for k, r in reports.items() if r.defects]
                break
        else:
            what = "; ".join(f"{label(k)}: {r.defects[0]}" for k, r in reports.items())
            if fallback is None:
                raise NoUsableClock(
                    f"{name}: no usable timestamps ({what}); choose with --timestamps {hint}"
                )
            chosen = fallback
            record["fallback"] = f"no usable timestamps ({what})"
            why = [f"no usable stamps: {what}"]
    else:
        chosen = requested
        why = [f"--timestamps {chosen}"]
    if chosen == "index":
        why.append(f"record order, scans {INDEX_PERIOD:g} s apart")
    record["used"] = chosen
    record["clock"] = f"{chosen} ({'; '.join(why)})"
    if chosen == "index":
        record["index_period_s"] = INDEX_PERIOD
    elif chosen in reports:
        record["sporadic_bad_stamps"] = {k: len(v) for k, v in reports[chosen].sporadic.items()}
    return chosen, record


def index_stamps(kinds: list[str]) -> list[float]:
    """Stamps by record order (``kinds``: ``"scan"`` or another kind per timed record): scan
    k (from 1) at ``k * INDEX_PERIOD``, the other records before it (odometry, sonar, truth)
    spread evenly over the period before it (and after the last scan, over the period after
    it)."""
    out = [0.0] * len(kinds)
    scan_k = 0
    pending: list[int] = []

    def spread(start: float) -> None:
        for j, i in enumerate(pending):
            out[i] = start + INDEX_PERIOD * (j + 1) / (len(pending) + 1)
        pending.clear()

    for i, kind in enumerate(kinds):
        if kind == "scan":
            spread(scan_k * INDEX_PERIOD)
            scan_k += 1
            out[i] = scan_k * INDEX_PERIOD
        else:
            pending.append(i)
    spread(scan_k * INDEX_PERIOD)
    return out
