"""Odometry given as poses, and what an odometry stream is (docs/readers.md, "Odometry
streams").

fgslam's odometry stream is one type whatever the input: :class:`fgslam.events.OdometryEvent`,
the encoder ticks of each wheel over a sample ending at its stamp, in the order delivered
(stamps never going backwards in the foreign readers). Formats that give odometry as poses
(CARMEN, ROS) turn each pose increment into such samples through :class:`VirtualDrive`;
:class:`OdometryJumps` drops implausible jumps of a pose stream and :class:`StaleOdometryHold`
spreads a pose stream that froze and caught up. Integrated, the stream is a path (times and
cumulative poses: :func:`fgslam.evaluation.dense.odometry_path`).

:class:`OdometryChain` is the one other view, kept apart on purpose: a log's odometry
*records* as the file holds them (file order, each record's own stamp, the scans among
them), which the relations benchmark composes along; the event stream cannot give it,
because it carries records stamped backwards into the next sample and cuts increments into
samples.

Poses are (x m, y m, theta rad); headings wrapped with :func:`factors.geometry.wrap_angle`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from factors.geometry import wrap_angle
from fgslam.config import RobotConfig
from fgslam.errors import ReaderError
from fgslam.events import Event, OdometryEvent
from fgslam.io.readers.sanity import OdometryLimits, implausible, usage

Increment = tuple[float, float, float] | np.ndarray  # (dx m, dy m, dtheta rad)

# The virtual differential drive of logs that give odometry as poses (CARMEN, ROS):
# 0.1 mm per tick on a 2 m wheelbase; every increment is cut into samples of at most 5 cm of
# travel and 2 deg of turn, so that the eq 5 noise (per sample) depends on the path, not on
# the log's odometry rate. k = 0.5 per sample gives sigma 11 cm per wheel, 8 cm along track
# and 4.5 deg of heading per metre driven straight, and about 5 cm of travel for a 30 deg turn
# on the spot (the wide virtual wheelbase makes turns on the spot uncertain in position too,
# as real ones are; with 0.5 m, iSAM2 met near-singular between factors on the Intel log).
VIRTUAL_METRES_PER_TICK = 1e-4
VIRTUAL_WHEELBASE = 2.0
VIRTUAL_ENCODER_STEPS = 10000
VIRTUAL_K = 0.5  # sigma(L) = k L per sample, each wheel (k_r, k_l)
VIRTUAL_K_D = 0.1  # sigma(D) = k_d D per sample (acts on the turn of the sample)
VIRTUAL_STEP = 0.05  # m of travel per sample at most
VIRTUAL_TURN = math.radians(2.0)  # rad of turn per sample at most
MAX_SAMPLES = 200000  # samples of one increment at most (10 km, 400 turns)


def relative(a: tuple[float, float, float], b: tuple[float, float, float]) -> np.ndarray:
    """inverse(a) * b for poses (x, y, theta): b in the frame of a, heading wrapped."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    dth = wrap_angle(b[2] - a[2])
    return np.array([c * dx + s * dy, -s * dx + c * dy, dth])


def compose(a: tuple[float, float, float], d: tuple[float, float, float]) -> np.ndarray:
    """a * d for poses (x, y, theta)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array(
        [
            a[0] + c * d[0] - s * d[1],
            a[1] + s * d[0] + c * d[1],
            wrap_angle(a[2] + d[2]),
        ]
    )


class VirtualDrive:
    """Pose increments -> encoder ticks of a virtual differential drive.

    An increment (dx, dy, dtheta) in the frame of the previous pose is driven as ``n`` equal
    samples (``n`` the least with at most ``VIRTUAL_STEP`` of travel and ``VIRTUAL_TURN`` of
    turn each), each of heading change ``dtheta / n`` and a chord length chosen so that the
    ``n`` samples (eqs 1-3) end at distance ``hypot(dx, dy)`` (backwards when ``dx < 0``),
    wheel distances ``L_r = c + dtheta D / 2n``, ``L_l = c - dtheta D / 2n``. The heading change
    is exact; the position is exact when the robot moved along the chord of its turn (no
    sideways slip), otherwise off by ``hypot(dx, dy) |atan2(dy, dx) - dtheta/2|``. Ticks are
    rounded with the remainder carried to the next sample, so the quantisation (0.1 mm per
    tick) never accumulates. The samples are stamped evenly over (previous stamp, t].
    """

    def __init__(self, cfg: RobotConfig) -> None:
        o = cfg.odometry
        self.D = o.wheelbase
        self.mr, self.ml = o.metres_per_tick_right, o.metres_per_tick_left
        self.cum_r = self.cum_l = 0.0
        self.tick_r = self.tick_l = 0
        self.t: float | None = None
        self.travel = 0.0  # m of wheel travel driven (distance plus turning), for warnings

    def _tick(self, t: float, lr: float, ll: float) -> OdometryEvent:
        self.travel += abs(lr + ll) / 2 + abs(lr - ll) / 2
        self.cum_r += lr
        self.cum_l += ll
        tr, tl = round(self.cum_r / self.mr), round(self.cum_l / self.ml)
        ev = OdometryEvent(t, tr - self.tick_r, tl - self.tick_l)
        self.tick_r, self.tick_l = tr, tl
        return ev

    def ticks(
        self,
        t: float,
        inc: tuple[float, float, float],
        after: float = -math.inf,
        hole: float = math.inf,
        spacing: float = math.inf,
    ) -> list[OdometryEvent]:
        """The odometry samples of one increment ending at time ``t``, stamped no earlier
        than ``after`` (the last event delivered); after a gap longer than ``hole`` s they
        are all stamped ``t`` (the motion's time is unknown: the gap stays visible). Spread
        samples lie at most ``spacing`` s apart: zero samples fill the span where the motion
        takes fewer samples, its own samples evenly among them. An increment that would take
        more than :data:`MAX_SAMPLES` samples is a :class:`ReaderError` (readers bound motion
        before they get here)."""
        dx, dy, dth = (float(v) for v in inc)
        dist = math.hypot(dx, dy)
        if not (dist <= MAX_SAMPLES * VIRTUAL_STEP and abs(dth) <= MAX_SAMPLES * VIRTUAL_TURN):
            raise ReaderError(f"odometry increment of {dist:.3g} m, {dth:.3g} rad: too large")
        n = max(1, math.ceil(dist / VIRTUAL_STEP - 1e-9), math.ceil(abs(dth) / VIRTUAL_TURN - 1e-9))
        h = dth / n
        # n chords of length c turning by h each span 2 c sin(n h/2) / (2 sin(h/2))
        ratio = math.sin(h / 2) / math.sin(dth / 2) if abs(dth) > 1e-12 else 1.0 / n
        c = math.copysign(dist * ratio, dx) if dx < 0 else dist * ratio
        gap = t - self.t if self.t is not None else 0.0
        t = max(t, after)
        t0 = max(self.t, after) if self.t is not None and self.t < t else t
        if gap > hole:
            t0 = t
        self.t = t
        m = n
        if t > t0 and math.isfinite(spacing):
            m = max(n, min(MAX_SAMPLES, math.ceil((t - t0) / spacing - 1e-9)))
        # slot j (of m) carries a motion sample where floor(j n / m) steps up
        moving = [(j + 1) * n // m > j * n // m for j in range(m)]
        return [
            self._tick(
                t0 + (t - t0) * (j + 1) / m if j < m - 1 else t,
                (c + 0.5 * h * self.D) if moving[j] else 0.0,
                (c - 0.5 * h * self.D) if moving[j] else 0.0,
            )
            for j in range(m)
        ]


class StaleOdometryHold:
    """Stale odometry: a pose stream that freezes and then catches up, spread over its span.

    Odometry given as poses sometimes repeats its last pose while the robot moves and then
    jumps (MIT CSAIL's FLASER fields repeat for 0.6-1.1 s while the robot turns, then jump by
    up to 85 deg in one record). Read as it is, that is "no motion" with full confidence and
    then the whole motion in one scan interval. So an odometry record that repeats the last
    pose (a zero increment) is held while the last change lies at most ``stale`` s back
    (:class:`~fgslam.io.readers.sanity.OdometryLimits`), and so are the events after it (scans,
    sonar readings):

    - when the odometry moves again, its increment is spread evenly over the span since the
      last change (samples of the :class:`VirtualDrive`) and the held events are delivered
      among its samples, in time order; counted in ``notes`` as ``stale_spans`` and
      ``stale_seconds`` (s, the span from the last change to the catch-up);
    - when it repeats for longer than ``stale`` s, the robot stood still (or it is a hole):
      zero samples up to each held repeat record (at most ``hole / 2`` s apart) and the held
      events are delivered in time order (a standing robot's odometry keeps coming: no gap in
      its samples, no hole).

    A robot that stops and starts again within ``stale`` s is thus seen creeping over the
    stop; its first increment is small.

    Gaps: every other event waits for the odometry record after it (up to ``spread`` s after
    the last record), and that record's samples are spread over the span since the last event
    delivered, the held events among them: a scan's odometry is interpolated between the
    records around it. A pose stream that pauses (``intel.orig.bag``'s /odom is quiet for 1-3
    s at a time, its scans stamped in bursts) still measures the motion over the pause, so
    the pause is spread like a catch-up, its samples at most ``hole / 2`` s apart (zero
    samples filling in), and no sample gap is left for the factors to read as an odometry
    hole; spans longer than ``hole`` s are counted as ``gap_spans`` and ``gap_seconds``. An
    event more than ``spread`` s after the last record ends the hold as it was: a hole.

    Events leave in the order of their stamps, which never go below the last one delivered.
    Feed every odometry record to :meth:`odometry`, every other event to :meth:`event`, and
    call :meth:`flush` at the end of the log.
    """

    def __init__(self, drive: VirtualDrive, limits: OdometryLimits, notes: dict[str, Any]) -> None:
        self.drive = drive
        self.stale = limits.stale  # s
        self.hole = limits.hole  # s
        self.spacing = limits.hole / 2  # s between the samples of a span spread, at most
        self.spread = max(limits.spread, limits.stale)  # s: the longest span spread
        self.notes = notes
        for key in ("stale", "gap"):
            notes.setdefault(f"{key}_spans", 0)
            notes.setdefault(f"{key}_seconds", 0.0)
        self.held: list[Event] = []
        self.repeat_t: float | None = None  # s, stamp of the last repeat held
        self.repeats: list[float] = []  # s, stamps of the held repeats that are records
        self.last_out = -math.inf  # s, stamp of the last event delivered
        self.last_record: float | None = None  # s, stamp of the last odometry record

    def holding(self, t: float) -> bool:
        """Whether a repeat (or an event after one) at ``t`` s is held: the last change of the
        odometry lies at most ``stale`` s back."""
        return self.drive.t is not None and t - self.drive.t <= self.stale

    def odometry(self, t: float, inc: Increment, *, sample: bool = True) -> list[Event]:
        """The events an odometry record at ``t`` s with increment ``inc`` (dx m, dy m, dtheta
        rad, over the last record) releases. ``sample`` False: the record is no odometry
        record of its own (a scan's odometry field): a repeat that is a stop gives no zero
        samples, only the held events."""
        self.last_record = t
        if np.any(np.asarray(inc) != 0):
            return self._motion(t, inc)
        if self.holding(t):
            self.repeat_t = t
            if sample:
                self.repeats.append(t)
            return []
        if not sample:
            return self._release()
        self.repeats.append(t)  # a stop, this record its last repeat
        return self._stood_still()

    def event(self, ev: Event, *, needs_odometry: bool = True) -> list[Event]:
        """The events a non-odometry event releases: none while it is held (it waits for the
        odometry record after it, up to ``spread`` s after the last record), else the event
        itself (after the held ones when the hold ended as a stop or a hole).
        ``needs_odometry`` False: an event placed without the odometry (a ground-truth pose)
        waits only behind held events, to keep the time order, and never ends a hold."""
        out: list[Event] = []
        if not needs_odometry:
            if self.held:
                self.held.append(ev)
                return []
        else:
            if self.repeat_t is not None and not self.holding(ev.t):
                out = self._stood_still()
            if self.last_record is not None:
                if ev.t - self.last_record <= self.spread:
                    self.held.append(ev)
                    return out
                out += self._release()  # a hole: the held events as they were
        self.last_out = max(self.last_out, ev.t)
        return [*out, ev]

    def flush(self) -> list[Event]:
        """The events still held at the end of the log, as they were."""
        return self._release()

    def _stood_still(self) -> list[Event]:
        """The pending repeats were a stop: zero samples up to each held repeat record (at
        most ``hole / 2`` s apart) among the held events, in time order (a sample before an
        event of the same stamp)."""
        zeros = [
            ev
            for t in self.repeats
            for ev in self.drive.ticks(t, np.zeros(3), after=self.last_out, spacing=self.spacing)
        ]
        return self._deliver(zeros)

    def _motion(self, t: float, inc: Increment) -> list[Event]:
        """The samples of ``inc`` ending at ``t`` s (spread back over the held span) and the
        held events, in time order (a sample before an event of the same stamp)."""
        start = self.drive.t
        if self.held:  # a held span is spread, not a hole
            ticks = self.drive.ticks(t, inc, self.last_out, self.spread, self.spacing)
            stale = self.repeat_t is not None and np.any(np.asarray(inc) != 0)
            kind = "stale" if stale else "gap"
            if start is not None and (stale or t - start > self.hole):
                self.notes[f"{kind}_spans"] += 1
                secs = self.notes[f"{kind}_seconds"] + t - start
                self.notes[f"{kind}_seconds"] = round(secs, 3)
        else:
            ticks = self.drive.ticks(t, inc, after=self.last_out, hole=self.hole)
        return self._deliver(ticks)

    def _deliver(self, samples: list[OdometryEvent]) -> list[Event]:
        """``samples`` and the held events in time order (a sample before an event of the same
        stamp; held events of one stamp in their held order); the hold emptied."""
        out = sorted([*samples, *self.held], key=lambda e: (e.t, not isinstance(e, OdometryEvent)))
        self.held, self.repeat_t, self.repeats = [], None, []
        if out:
            self.last_out = max(self.last_out, out[-1].t)
        return out

    def _release(self) -> list[Event]:
        out, self.held, self.repeat_t, self.repeats = self.held, [], None, []
        if out:
            self.last_out = max(self.last_out, out[-1].t)
        return out


class OdometryJumps:
    """Implausible odometry in a stream of poses (x m, y m, theta rad) with stamps (s): what
    :meth:`step` returns is the increment to deliver, in the frame of the last pose used, or
    None for a pose skipped as implausible (:func:`fgslam.io.readers.sanity.implausible`).

    A jump is dropped, never carried into the motion: the pose after a skipped one is taken
    relative to whichever of the last good pose and the skipped pose it lies nearer to, by
    the fraction of the plausible motion it takes (:func:`fgslam.io.readers.sanity.usage`).
    Nearer the last good pose (a spike), the odometry continues from it; nearer the skipped
    pose (the odometry jumped and stayed, as ``intel.orig.bag``'s /odom does twice), it
    continues from the skipped pose (counted as ``rebased``): in both cases the jump itself
    is not motion, and the motion before and after it is kept. ``clock`` False (index
    stamps): only the distance of a step is checked. A pose with a stamp that is not finite
    (a sporadic junk stamp) keeps the stamp of the pose before it."""

    def __init__(self, limits: OdometryLimits, clock: bool = True) -> None:
        self.limits = limits
        self.clock = clock
        self.base: tuple[float, float, float] | None = None  # the last pose used
        self.base_t = -math.inf  # s, its stamp
        self.jumped: tuple[float, float, float] | None = None  # the last pose skipped
        self.jumped_t = -math.inf
        self.rebased = 0

    def _dt(self, t: float, since: float) -> float | None:
        return t - since if self.clock else None

    def step(self, pose: tuple[float, float, float], t: float) -> tuple[np.ndarray | None, str]:
        """(increment or None, why the pose is implausible: "" when it is not) for the next
        pose at ``t`` s; the first pose gives a zero increment."""
        t_known = t if math.isfinite(t) else None
        if self.base is None:
            self.base, self.base_t = pose, t_known if t_known is not None else self.base_t
            return np.zeros(3), ""
        inc = relative(self.base, pose)
        why = implausible(inc, self._dt(t, self.base_t), self.limits)
        if self.jumped is not None:
            from_jump = relative(self.jumped, pose)
            dt_jump = self._dt(t, self.jumped_t)
            if implausible(from_jump, dt_jump, self.limits) is None and (
                why is not None
                or usage(from_jump, dt_jump, self.limits)
                < usage(inc, self._dt(t, self.base_t), self.limits)
            ):
                self.rebased += 1  # the odometry jumped and stayed: continue from there
                self._use(pose, t_known)
                return from_jump, ""
        if why is not None:
            self.jumped = pose
            self.jumped_t = t_known if t_known is not None else self.base_t
            return None, why
        self._use(pose, t_known)
        return inc, ""

    def _use(self, pose: tuple[float, float, float], t: float | None) -> None:
        self.base, self.jumped = pose, None
        if t is not None:
            self.base_t = t


@dataclasses.dataclass
class OdometryChain:
    """A log's odometry records in file order (:func:`fgslam.io.readers.carmen.odometry_chain`):
    each record's stamp ``t`` (s), the index of the scan at or before it in the file
    (``scan``, -1 before the first), whether it is a scan (``is_scan``), the cumulative
    odometry at it (``poses``, heading unwrapped), and the scans' stamps and reference
    poses (``scan_t``, ``scan_poses``)."""

    t: NDArray[np.float64]
    scan: NDArray[np.int64]
    is_scan: NDArray[np.bool_]
    poses: NDArray[np.float64]
    scan_t: NDArray[np.float64]
    scan_poses: NDArray[np.float64]

    def scan_records(self) -> NDArray[np.int64]:
        """Record index of each scan."""
        return np.flatnonzero(self.is_scan)
