"""Physical plausibility of an input's events: one set of rules for every format (native fgslam
logs, CARMEN logs, ROS bags; docs/readers.md, "Plausibility").

:class:`Rules` states them, with limits from the robot's configuration and the reader's
:class:`~fgslam.io.readers.sanity.OdometryLimits`; :func:`check_events` applies them to a
reader's event stream (:mod:`fgslam.events`) as it leaves the reader; :class:`Findings`
counts each kind, keeps its first record, words one warning per kind and the ``report.json``
section, and under ``strict`` (``--strict``) raises :class:`ImplausibleInput` (a
``ReaderError``) at the first finding, naming the file and the record. A reader that already
applies a rule at reading, where it knows more (a CARMEN log's odometry poses, its records
going backwards), notes what it finds in the same :class:`Findings`.

The rules:

- ``ranges``: a laser range is NaN (no return) or lies in ``(range_min, range_max]``:
  ``range_min`` 0 (the configuration has no minimum range: a range is positive),
  ``range_max`` the configured laser's ``max_range`` (the simulator and the device drivers
  turn ranges beyond it into NaN; the foreign readers turn their formats' no-return codes
  into NaN at reading, CARMEN's 81.91, ROS's ``range_max``). Beams outside (negative, 0,
  infinite, beyond) are read as no return; the scan is counted (and its beams).
- ``empty_scan``: a scan with no valid beam (every range NaN or out of range, or no beam):
  counted and passed on (no feature comes of it; a keyframe still may).
- ``odometry``: an odometry record's wheel motion (its ticks times the configuration's metres
  per tick: travel and turn of the differential drive) over the time since the odometry record
  before it is held to :func:`fgslam.io.readers.sanity.implausible` (speed and turn rate, with
  :data:`~fgslam.io.readers.sanity.MIN_DT` s of slack); the first record over the configured
  ``odometry.sample_period``; without a clock (index stamps), no wheel may travel more than
  ``max_step`` in one record. Such a record is skipped (the jump dropped: its ticks are not
  carried) and counted.
- ``truth``: a truth pose is finite, within :data:`MAX_COORD` m of the origin in x and y and
  its heading within :data:`MAX_HEADING` rad. Others are skipped and counted.
- ``order``: a record stamped earlier than the record of its kind before it (streams:
  odometry, laser, sonar, truth). A native log passes it on (the pipeline's reorder buffer
  puts it back in order or drops it); the foreign readers drop it or carry its motion at
  reading and note it (:meth:`fgslam.io.readers.source.Problems.backward`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from fgslam.errors import ReaderError
from fgslam.events import Event, LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.readers.sanity import OdometryLimits, implausible

MAX_COORD = 1e7  # m: a truth (or pose) coordinate beyond is not a position
MAX_HEADING = 1e4  # rad: sources write headings within a turn; 1600 turns unwrapped at most
RANGE_MIN = 0.0  # m, exclusive: the configuration has no minimum range
STREAMS = {OdometryEvent: "odometry", LaserScan: "laser", SonarReading: "sonar", TruthPose: "truth"}


@dataclass(frozen=True)
class Kind:
    """One kind of finding: its key in ``report.json``, its label in messages, the records it
    counts (one, several), what is done with them without ``--strict``, and the
    ``skipped_by_reason`` of a record dropped for it (None: not dropped)."""

    key: str
    label: str
    one: str
    many: str
    default: str
    reason: str | None = None


KINDS = {
    "ranges": Kind(
        "laser_ranges_out_of_range",
        "laser ranges out of range",
        "laser scan with ranges out of range",
        "laser scans with ranges out of range",
        "those beams read as no return",
    ),
    "empty_scan": Kind(
        "scans_without_valid_beam",
        "laser scan with no valid beam",
        "laser scan with no valid beam",
        "laser scans with no valid beam",
        "passed on, nothing extracted from them",
    ),
    "odometry": Kind(
        "implausible_odometry",
        "implausible odometry",
        "implausible odometry record",
        "implausible odometry records",
        "skipped, the jump dropped",
        "implausible odometry",
    ),
    "truth": Kind(
        "implausible_truth",
        "implausible truth pose",
        "implausible truth pose",
        "implausible truth poses",
        "skipped",
        "implausible truth pose",
    ),
    "order": Kind(
        "stamps_out_of_order",
        "stamp out of order",
        "record stamped out of order",
        "records stamped out of order",
        "dropped, their motion carried into the next record",
    ),
}


class ImplausibleInput(ReaderError):
    """An implausible record refused with ``--strict``: one line naming file and record."""


@dataclass(frozen=True)
class Rules:
    """The plausibility rules with their limits (see the module documentation)."""

    range_min: float  # m, exclusive
    range_max: float  # m, inclusive
    limits: OdometryLimits
    metres_per_tick: tuple[float, float]  # right, left wheel
    wheelbase: float  # m
    sample_period: float  # s: the time a first odometry record covers
    clock: bool = True  # False: index stamps, only a step's length is bounded
    max_coord: float = MAX_COORD
    max_heading: float = MAX_HEADING

    @classmethod
    def of(cls, cfg: Any, limits: OdometryLimits | None = None, clock: bool = True) -> Rules:
        """The rules for a robot configuration (laser range, wheel geometry) and odometry
        limits (default :class:`~fgslam.io.readers.sanity.OdometryLimits`)."""
        o = cfg.odometry
        return cls(
            range_min=RANGE_MIN,
            range_max=float(cfg.laser.max_range),
            limits=limits or OdometryLimits(),
            metres_per_tick=(o.metres_per_tick_right, o.metres_per_tick_left),
            wheelbase=float(o.wheelbase),
            sample_period=float(o.sample_period),
            clock=clock,
        )

    def notes(self) -> dict[str, Any]:
        """The limits as ``report.json`` lists them."""
        return {
            "laser_range_m": [self.range_min, self.range_max],
            "odometry": self.limits.notes(),
            "odometry_clock": self.clock,
            "truth_max_coordinate_m": self.max_coord,
            "truth_max_heading_rad": self.max_heading,
        }

    def out_of_range(self, ranges: np.ndarray) -> np.ndarray:
        """The beams (bool per range) that are neither NaN (no return) nor within
        ``(range_min, range_max]``."""
        with np.errstate(invalid="ignore"):
            inside = (ranges > self.range_min) & (ranges <= self.range_max)
        return ~(inside | np.isnan(ranges))

    def odometry(self, ev: OdometryEvent, dt: float | None) -> str | None:
        """Why an odometry record (``dt`` s after the odometry record before it; None: the
        first record) is implausible, or None."""
        right = _metres(ev.ticks_right, self.metres_per_tick[0])
        left = _metres(ev.ticks_left, self.metres_per_tick[1])
        if not self.clock:
            wheel = max(abs(right), abs(left))
            if not wheel <= self.limits.max_step:
                return (
                    f"a wheel travelled {wheel:.3g} m in one record "
                    f"(more than {self.limits.max_step:g} m; no clock)"
                )
            return None
        inc = (0.5 * (right + left), 0.0, (right - left) / self.wheelbase)
        return implausible(inc, self.sample_period if dt is None else dt, self.limits)

    def truth(self, ev: TruthPose) -> str | None:
        """Why a truth pose is implausible, or None."""
        x, y, th = float(ev.x), float(ev.y), float(ev.theta)
        if not all(map(math.isfinite, (x, y, th))):
            return f"pose {x:.6g} {y:.6g} {th:.6g} not finite"
        if not (abs(x) <= self.max_coord and abs(y) <= self.max_coord):
            return f"position {x:.6g} {y:.6g} m (beyond {self.max_coord:g} m)"
        if not abs(th) <= self.max_heading:
            return f"heading {th:.6g} rad (beyond {self.max_heading:g} rad)"
        return None


def _metres(ticks: int, per_tick: float) -> float:
    """A wheel's travel (m) of ``ticks`` (an integer of any size: infinite beyond floats)."""
    try:
        return ticks * per_tick
    except OverflowError:
        return math.inf if ticks > 0 else -math.inf


class Findings:
    """What the rules found in one pass over an input: per kind the count and the first
    record's message; under ``strict`` the first finding is an :class:`ImplausibleInput`.
    ``skip(reason, message)`` counts a dropped record where the reader counts its skipped
    records (``Problems.skip``); ``defaults`` words what the reader does with a kind where it
    differs from :data:`KINDS` (a native log passes records out of order on)."""

    def __init__(
        self,
        name: str,
        strict: bool = False,
        skip: Callable[[str, str], None] | None = None,
        rules: Rules | None = None,
        defaults: dict[str, str] | None = None,
    ) -> None:
        self.name = name
        self.strict = strict
        self.skip = skip
        self.rules = rules
        self.defaults = {k: v.default for k, v in KINDS.items()} | (defaults or {})
        self.counts = dict.fromkeys(KINDS, 0)
        self.first: dict[str, str] = {}
        self.beams = 0  # out-of-range beams (kind "ranges" counts scans)

    def note(
        self, kind: str, detail: str, *, line: int | None = None, skipped: bool = False
    ) -> None:
        """One finding of ``kind``: ``detail`` names the record and what is wrong with it,
        ``line`` its line in the file when known; ``skipped``: the record is dropped (counted
        with the reader's skipped records)."""
        k = KINDS[kind]
        where = f"{self.name}:{line}" if line is not None else self.name
        message = f"{where}: {k.label}: {detail}"
        if self.strict:
            raise ImplausibleInput(
                f"{message} (refused with --strict; without it, {self.defaults[kind]}, counted "
                "and warned)"
            )
        self.counts[kind] += 1
        self.first.setdefault(kind, message)
        if skipped and self.skip is not None and k.reason is not None:
            self.skip(k.reason, message)

    def warnings(self) -> list[str]:
        """One line per kind found: the count, the first record, what was done."""
        out = []
        for kind, n in self.counts.items():
            if not n:
                continue
            k = KINDS[kind]
            extra = f"{self.beams} beams; " if kind == "ranges" else ""
            out.append(
                f"{n} {k.many if n > 1 else k.one} ({extra}first: {self.first[kind]}): "
                f"{self.defaults[kind]}; --strict refuses such a log"
            )
        return out

    def summary(self) -> dict[str, Any]:
        """The ``report.json`` section (``"plausibility"`` in the reader's summary): the
        rules' limits and per kind the count and the first record."""
        out: dict[str, Any] = {"rules": self.rules.notes()} if self.rules else {}
        for kind, k in KINDS.items():
            entry: dict[str, Any] = {"count": self.counts[kind]}
            if kind == "ranges":
                entry["beams"] = self.beams
            if kind in self.first:
                entry["first"] = self.first[kind]
            out[k.key] = entry
        return out


def _record(ev: Event) -> str:
    name = {"odometry": "odometry record", "laser": "laser scan", "truth": "truth pose"}
    return f"{name.get(STREAMS[type(ev)], 'sonar reading')} at t={ev.t:.6f} s"


def check_events(
    events: Iterable[Event],
    rules: Rules,
    findings: Findings,
    line: Callable[[], int | None] | None = None,
) -> Iterator[Event]:
    """The events of a reader's stream through the rules (module documentation), each
    finding noted in ``findings``; ``line()`` gives the line of the record just read where
    the reader knows it (native logs)."""
    findings.rules = rules
    last: dict[str, float] = {}  # per stream, the latest stamp
    last_odometry: float | None = None  # the stamp of the last odometry record used
    for ev in events:
        stream = STREAMS.get(type(ev))
        if stream is None:  # not a sensor event: not ours to judge
            yield ev
            continue
        at = line() if line is not None else None
        if ev.t < last.get(stream, -math.inf):
            findings.note(
                "order",
                f"{_record(ev)}, earlier than the {stream} record before it "
                f"(t={last[stream]:.6f} s)",
                line=at,
            )
        else:
            last[stream] = ev.t
        if isinstance(ev, LaserScan):
            r = np.asarray(ev.ranges, dtype=float)
            bad = rules.out_of_range(r)
            if bad.any():
                n = int(bad.sum())
                findings.note(
                    "ranges",
                    f"{_record(ev)}: {n} of {r.size} ranges outside "
                    f"({rules.range_min:g}, {rules.range_max:g}] m (e.g. {r[bad][0]:.6g} m)",
                    line=at,
                )
                findings.beams += n
                r = r.copy()
                r[bad] = np.nan
                ev = LaserScan(ev.t, r, ev.bearings)
            if not (~np.isnan(r)).any():
                findings.note(
                    "empty_scan",
                    f"{_record(ev)}: none of its {r.size} ranges is a return in "
                    f"({rules.range_min:g}, {rules.range_max:g}] m",
                    line=at,
                )
        elif isinstance(ev, OdometryEvent):
            dt = None if last_odometry is None else ev.t - last_odometry
            why = rules.odometry(ev, dt)
            if why is not None:
                findings.note("odometry", f"{_record(ev)}: {why}", line=at, skipped=True)
                continue
            last_odometry = ev.t if last_odometry is None else max(last_odometry, ev.t)
        elif isinstance(ev, TruthPose):
            why = rules.truth(ev)
            if why is not None:
                findings.note("truth", f"{_record(ev)}: {why}", line=at, skipped=True)
                continue
        yield ev
