"""CARMEN logs (``FLASER``, ``ROBOTLASER1``, ``ODOM``, ``TRUEPOS``; gzipped or not).

Records (whitespace separated; ``#`` lines are comments)::

    FLASER n r_1 .. r_n x y theta odom_x odom_y odom_theta timestamp host logger_timestamp
    ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode
        n r_1 .. r_n m e_1 .. e_m laser_x laser_y laser_theta x y theta tv rv
        forward_safety side_safety turn_axis timestamp host logger_timestamp
    ODOM x y theta tv rv accel timestamp host logger_timestamp
    TRUEPOS true_x true_y true_theta odom_x odom_y odom_theta timestamp host logger_timestamp
    PARAM name value host timestamp

Two kinds of log (``mode``, detected by default):

- **corrected** (written by a SLAM run, e.g. GMapping's, like the public Intel log): both
  FLASER pose fields hold the corrected pose P_k, the ``ODOM`` lines between scans hold
  P_{k-1} composed with the raw odometry since scan k-1, and an ``ODOM`` line stamped 0 after
  each scan repeats P_k. The raw odometry increment between scans k-1 and k is therefore
  ``inverse(P_{k-1}) * ODOM_before_k`` (``ODOM_before_k``: the last ODOM line before scan k).
  Each ODOM line between the scans, taken relative to P_{k-1}, gives the odometry path
  sample by sample up to that increment; P_k becomes a ``TruthPose`` (the *reference*
  trajectory, not ground truth).
- **raw**: ``ODOM`` lines are cumulative wheel odometry; each one's increment over the
  previous one becomes an odometry sample. ``TRUEPOS`` lines (simulated logs) are ground
  truth.

Odometry increments become encoder ticks of the virtual differential drive of
:func:`fgslam.io.readers.common.derived_config` (:class:`~fgslam.io.readers.common.VirtualDrive`).
Ranges at or beyond ``no_return`` (m, the LMS reports no return as 81.91; a laser whose
readings pile up just below a lower largest value, e.g. 32.767 or 51.15 m, reports it there:
probed from the first scans, ``meta["no_return_m"]``), at or beyond a ``ROBOTLASER1``'s
maximum range, ``inf`` or ``nan`` are no return (NaN), as are the readings of a beam that
reads one value in every probed scan (a padding field, ``meta["dead_beams"]``). Negative, zero or
``-inf`` ranges are no code of the format: they are left to the plausibility rules that
every format shares (:mod:`fgslam.io.readers.plausibility`: read as no return, counted, warned,
refused with ``strict``), as are implausible odometry (judged here on the poses) and records
stamped out of order (dropped or carried here, noted there).

Laser geometry: a ``FLASER`` line's n beams lie evenly over 180 deg from -90 deg; a
``ROBOTLASER1``'s at ``start_angle + k resolution`` (CARMEN's rule; spread over ``fov``
instead where the two agree to 0.1 % of a beam, the resolution field being rounded). The first
scan gives the configured laser; a scan whose beams lie elsewhere (another beam count, start
or resolution) carries its own bearings (:func:`fgslam.events.own_bearings`), in the laser
frame of the first scan.
Records of other types (``NEFF``, ``RLASER``, ``SYNC``, ...) are skipped and counted. A scan
stamped earlier than the last delivered event is skipped and counted (its odometry carried to
the next sample); an ODOM line stamped before the last delivered event, or (corrected logs)
after the scan that follows it, is counted and its motion carried into the next sample:
events are never reordered and their stamps never go backwards.

**Stale odometry** (raw logs; MIT CSAIL's FLASER odometry fields freeze for 0.6-1.1 s while
the robot turns): an ``ODOM`` line that repeats the last pose, or a scan whose odometry field
does (logs without ``ODOM`` lines; such a scan gives no zero sample), and the events after it
are held and spread by :class:`~fgslam.io.readers.odometry.StaleOdometryHold` (``stale_spans``,
``stale_seconds`` in the odometry notes); so is a pause of the ``ODOM`` lines of up to
``spread`` s (``gap_spans``, ``gap_seconds``), longer ones counted as holes.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator

import numpy as np

from fgslam.errors import ReaderError
from fgslam.events import Event, LaserScan, TruthPose, own_bearings
from fgslam.io.readers.carmen_records import (
    LASER_TAGS,
    USED_TAGS,
    _Bad,
    parse_record,
)
from fgslam.io.readers.common import derived_config, input_warnings, open_lines
from fgslam.io.readers.odometry import (
    OdometryChain,
    OdometryJumps,
    StaleOdometryHold,
    VirtualDrive,
    compose,
    relative,
)
from fgslam.io.readers.sanity import (
    BACKWARDS_TOLERANCE,
    OdometryLimits,
    choose_clock,
    implausible,
    index_stamps,
    stamp_defects,
)
from fgslam.io.readers.source import Source, StrPath

MODES = ("auto", "corrected", "raw")
NO_RETURN = 80.0
MAX_LASER_OFFSET = 10.0  # m: a robot_frontlaser_offset beyond is not a mount
# the no-return probe (CarmenLog._probe_no_return): scans read, fewest to decide on, the band
# below the log's largest reading taken as the saturation value, and the share of readings
# in it that makes it one (real returns within 1 % of the largest are far rarer)
PROBE_SCANS = 300
MIN_PROBE_SCANS = 20
SATURATION_BAND = 0.01
SATURATION_SHARE = 0.002
DEAD_SHARE = 0.02  # more constant beams than this share: the robot stood, no beam is dead


class CarmenLog(Source):
    """A CARMEN log as fgslam events; see the module documentation."""

    format = "carmen"

    def __init__(
        self,
        path: StrPath,
        mode: str = "auto",
        no_return: float = NO_RETURN,
        tolerant: bool = False,
        reference: bool = True,
        timestamps: str = "auto",
        limits: OdometryLimits | None = None,
        backwards_tolerance: float = BACKWARDS_TOLERANCE,
        strict: bool = False,
    ) -> None:
        super().__init__(path)
        self.strict = strict  # refuse implausible odometry and a log without a usable clock
        if mode not in MODES:
            raise ReaderError(f"unknown CARMEN mode {mode!r}; expected one of {MODES}")
        self.no_return = float(no_return)
        self.tolerant = tolerant
        self.reference = reference
        self.limits = limits or OdometryLimits()
        self._probe(mode)
        self._probe_no_return()
        self._clock_pass(timestamps, backwards_tolerance)

    def _clock_pass(self, requested: str, tolerance: float) -> None:
        """One pass over the stamps: the repeats of corrected logs (the ODOM line after a
        scan, stamped 0 or repeating its pose), the defects of both stamp fields, the clock
        chosen (:func:`fgslam.io.readers.sanity.choose_clock`) and, unless it is ``ipc``, the
        stamp of every timed record."""
        lines: list[int] = []
        kinds: list[str] = []
        ipc: list[float] = []
        logger: list[float] = []
        self._repeats: set[int] = set()
        after_scan: tuple | None = None  # pose of the scan just read (corrected logs)
        odd_repeats = 0
        for lineno, rec in self._records(strict=False):
            tag = rec["tag"]
            if tag not in ("ODOM", *LASER_TAGS):
                continue
            if tag == "ODOM" and self.mode == "corrected" and after_scan is not None:
                if rec["t"] == 0.0 or rec["pose"] == after_scan:
                    self._repeats.add(lineno)
                    odd_repeats += rec["t"] != 0.0
                    after_scan = None
                    continue
            after_scan = rec["pose"] if tag in LASER_TAGS else None
            lines.append(lineno)
            kinds.append("odometry" if tag == "ODOM" else "scan")
            ipc.append(rec["t"])
            logger.append(rec["t_logger"])
        ln, kd = np.array(lines, dtype=int), np.array(kinds)
        reports = {}
        for name, vals in (("ipc", ipc), ("logger", logger)):
            v = np.array(vals, dtype=float)
            sc, od = kd == "scan", kd == "odometry"
            reports[name] = stamp_defects(ln[sc], v[sc], ln[od], v[od], tolerance)
        fallback = None if self.strict else "index"
        clock, record = choose_clock(self.name, reports, requested, fallback=fallback)
        self.clock = clock
        self._stamps: dict[int, float] | None = None
        if clock == "index":
            self._stamps = dict(zip(lines, index_stamps(kinds), strict=True))
        elif clock == "logger":
            self._stamps = dict(zip(lines, logger, strict=True))
        self._bad_stamps: set[int] = set()
        if clock in reports:
            for v in reports[clock].sporadic.values():
                self._bad_stamps |= v
        if self.mode == "corrected":
            record["repeat_lines"] = len(self._repeats)
            record["repeat_lines_not_stamped_0"] = int(odd_repeats)
        self.meta["timestamps"] = record
        self.problems.notes["timestamps"] = record
        self._new_pass()

    def _new_pass(self) -> None:
        """Fresh counts for a pass over the events (the odometry notes and the problems)."""
        self.problems.new_pass()
        self._odo_notes: dict = {
            "holes": 0,
            "hole_seconds": 0.0,
            "holes_first": [],
            "implausible": 0,
            "rebased": 0,
            "stale_spans": 0,
            "stale_seconds": 0.0,
            "limits": self.limits.notes(),
        }
        self.problems.notes["odometry"] = self._odo_notes

    # ------------------------------------------------------------------ header

    def _records(self, strict: bool | None = None) -> Iterator[tuple[int, dict]]:
        strict = not self.tolerant if strict is None else strict
        for lineno, text in open_lines(self.path):
            f = text.split()
            if not f or f[0].startswith("#"):
                continue
            try:
                rec = parse_record(f)
            except _Bad as exc:
                msg = f"{self.name}:{lineno}: {exc}"
                if strict:
                    raise ReaderError(msg) from None
                yield lineno, {"tag": "bad", "reason": f"bad {f[0]} record", "message": msg}
                continue
            yield lineno, rec

    def _probe_no_return(self, scans: int = PROBE_SCANS) -> None:
        """The laser's own "no return" value and dead beams, from the first ``scans`` laser
        records. A laser reports no return as its saturation value (the LMS 81.91 m, others
        32.767 m or ~51 m): readings within ``SATURATION_BAND`` of the largest reading of the
        log, seen in more than ``SATURATION_SHARE`` of the readings, are that value, so
        ``no_return`` (and the configured laser's maximum range) is lowered to the band's
        bottom. A beam that reads one value in every probed scan (a padding field) measures
        nothing: its readings are NaN. Both are recorded in ``meta``."""
        rows: list[np.ndarray] = []
        for _, rec in self._records(strict=False):
            if rec["tag"] in LASER_TAGS and len(rec["ranges"]) == self.n_beams:
                rows.append(np.asarray(rec["ranges"], dtype=float))
                if len(rows) >= scans:
                    break
        self.dead_beams = np.zeros(self.n_beams, dtype=bool)
        if len(rows) < MIN_PROBE_SCANS:
            return
        r = np.vstack(rows)
        ok = np.isfinite(r) & (r > 0)
        if not ok.any():
            return
        top = float(r[ok].max())
        band = top * (1.0 - SATURATION_BAND)
        if top < self.no_return and np.mean(r[ok] >= band) > SATURATION_SHARE:
            self.no_return = band
            laser = dataclasses.replace(self.config.laser, max_range=band)
            self.config = dataclasses.replace(self.config, laser=laser)
        self.dead_beams = np.all(r == r[0], axis=0) & (r[0] < self.no_return)
        if self.dead_beams.sum() > max(1, DEAD_SHARE * self.n_beams):
            self.dead_beams[:] = False  # many: a standing robot in a static world, not padding
        self.meta["no_return_m"] = round(self.no_return, 3)
        if self.dead_beams.any():
            self.meta["dead_beams"] = np.flatnonzero(self.dead_beams).tolist()

    def _probe(self, mode: str) -> None:
        """Laser geometry, laser offset and the kind of log, from the records up to the
        first scan (and the record after it)."""
        first = None
        offset = 0.0
        after_first: dict | None = None
        for _, rec in self._records(strict=False):
            if rec["tag"] == "PARAM" and rec["name"] == "robot_frontlaser_offset":
                try:
                    offset = float(rec["value"])
                except ValueError:
                    pass
                if not abs(offset) <= MAX_LASER_OFFSET:
                    raise ReaderError(
                        f"{self.name}: PARAM robot_frontlaser_offset {rec['value']}: not a "
                        f"laser mount (beyond {MAX_LASER_OFFSET:g} m)"
                    )
            if first is not None and rec["tag"] in ("ODOM", *LASER_TAGS):
                after_first = rec
                break
            if rec["tag"] in LASER_TAGS:
                first = rec
        if first is None:
            raise ReaderError(
                f"{self.name}: no FLASER or ROBOTLASER1 record: not a CARMEN laser log"
            )
        n = len(first["ranges"])
        mount = (offset, 0.0, 0.0)
        if first["laser_pose"] is not None:
            lp, rp = first["laser_pose"], first["pose"]
            mount = tuple(relative(rp, lp))
        yaw = first["start"] + math.radians(first["fov"]) / 2
        mount = (mount[0], mount[1], mount[2] + yaw)
        self._middle = yaw  # rad: the laser frame's x axis in the records' angles
        self._geometry: dict[tuple[int, float, float], np.ndarray | None] = {}
        self.n_beams = n
        self.config = derived_config(n, first["fov"], max_range=self.no_return, mount=mount)
        if mode == "auto":
            corrected = (
                first["tag"] == "FLASER"
                and first["pose"] == first["odom"]
                and after_first is not None
                and after_first["tag"] == "ODOM"
                and after_first["pose"] == first["pose"]
            )
            mode = "corrected" if corrected else "raw"
        self.mode = mode
        if mode == "corrected" and self.reference:
            self.reference_kind = "reference"
        self.world = f"CARMEN log {self.name.rsplit('/', 1)[-1]}"
        self.meta = {
            "source_format": "carmen",
            "source": self.name,
            "carmen_mode": mode,
            "laser": f"{n} beams over {first['fov']:g} deg",
        }
        if self.reference_kind:
            self.meta["reference"] = "corrected poses of the log (a SLAM result, not ground truth)"

    # ------------------------------------------------------------------ events

    def events(self) -> Iterator[Event]:
        """The log's events (unchecked: iterating the log applies the plausibility rules,
        :class:`~fgslam.io.readers.common.Source`)."""
        self._new_pass()
        if self.problems.findings is None:  # read directly: the reader's own rules still note
            from fgslam.io.readers.plausibility import Findings

            self.problems.findings = Findings(self.name, self.strict, self.problems.skip)
        drive = VirtualDrive(self.config)
        pr = self.problems
        notes = self._odo_notes
        limits = self.limits
        last_scan_t = -math.inf
        last_odo_t = -math.inf
        in_hole = False
        hole_from = 0.0

        def end_hole(now: float) -> bool:
            if in_hole:
                notes["hole_seconds"] = round(notes["hole_seconds"] + now - hole_from, 3)
            return False

        base = (0.0, 0.0, 0.0)  # corrected: P_{k-1}; raw: the last scan odometry field
        jumps = OdometryJumps(limits, clock=self.clock != "index")  # raw: the ODOM lines
        pending: list[tuple[float, np.ndarray, int]] = []  # corrected: ODOMs rel. to P_{k-1}
        carried = np.zeros(3)  # motion not yet delivered (an increment)
        have_odom = False
        n_scans = 0
        # raw logs: events held while the odometry repeats its last pose (stale odometry)
        hold = StaleOdometryHold(drive, limits, notes)
        # a gap in a pose stream is spread by the hold up to `spread` s; corrected logs' ODOM
        # lines restart at every scan and are not held
        hole = limits.hole if self.mode == "corrected" else max(limits.hole, limits.spread)

        for lineno, rec in self._records():
            tag = rec["tag"]
            if tag == "bad":
                pr.skip(rec["reason"], rec["message"])
                continue
            if tag not in USED_TAGS:
                pr.ignore(f"unknown record {tag[:20]}")
                continue
            if tag == "PARAM" or lineno in self._repeats:
                continue
            t = rec["t"] if self._stamps is None else self._stamps.get(lineno, rec["t"])
            if lineno in self._bad_stamps:
                t = math.nan  # a sporadic junk stamp: handled as going backwards
            if tag == "ODOM":
                if self.mode == "corrected":
                    prev_t, prev, _ = pending[-1] if pending else (last_scan_t, np.zeros(3), 0)
                    rel = relative(base, rec["pose"])
                    if self._implausible(lineno, relative(prev, rel), t - prev_t):
                        continue
                    pending.append((t, rel, lineno))
                    continue
                if not have_odom:
                    jumps.step(rec["pose"], t)
                    have_odom = True
                    last_odo_t = t if math.isfinite(t) else last_odo_t
                    continue
                inc, why = jumps.step(rec["pose"], t)
                notes["rebased"] = jumps.rebased
                if inc is None:  # a jump: dropped (OdometryJumps)
                    self._skip_implausible(lineno, why)
                    continue
                carried = compose(carried, inc)
                if not (t >= last_odo_t and t >= last_scan_t):
                    self._backward("ODOM", lineno, t, max(last_odo_t, last_scan_t))
                    continue
                last_odo_t, in_hole = t, end_hole(t)
                yield from hold.odometry(t, carried)
                carried = np.zeros(3)
                continue
            if tag == "TRUEPOS":
                if self.reference and self.mode == "raw":
                    self.reference_kind = "ground truth"
                    if t >= last_odo_t:
                        yield from hold.event(TruthPose(t, *rec["pose"]), needs_odometry=False)
                    else:
                        self._backward("TRUEPOS", lineno, t, last_odo_t)
                continue
            # a scan
            ranges = np.asarray(rec["ranges"], dtype=float)
            if ranges.size == 0:
                pr.skip("scan without beams", f"{self.name}:{lineno}: no ranges")
                continue
            bearings = self.scan_bearings(rec)
            backwards = not (t >= last_scan_t and t >= last_odo_t)
            if self.mode == "corrected":
                # the ODOM lines since scan k-1, relative to P_{k-1}: one sample each when
                # stamped in order up to this scan, else carried into the next sample
                emitted = np.zeros(3)
                for ti, rel, ln in pending if not backwards else ():
                    if last_odo_t <= ti <= t:
                        yield from drive.ticks(
                            ti,
                            compose(carried, relative(emitted, rel)),
                            after=last_scan_t,
                            hole=limits.hole,
                        )
                        carried, emitted, last_odo_t = np.zeros(3), rel, ti
                        in_hole = end_hole(ti)
                    elif not ti >= last_odo_t:
                        self._backward("ODOM", ln, ti, last_odo_t)
                    else:
                        after = f"ODOM stamped {ti:.6f} s, after the scan that follows it"
                        self._backward("ODOM after its scan", ln, ti, t, after)
                final = pending[-1][1] if pending else emitted
                carried = compose(carried, relative(emitted, final))
                base, pending = rec["pose"], []
            elif not have_odom:  # raw log without ODOM lines: the scan's odometry field
                if last_scan_t > -math.inf:
                    inc = relative(base, rec["odom"])
                    if self._implausible(lineno, inc, t - last_scan_t):
                        inc = np.zeros(3)
                    carried = compose(carried, inc)
                base = rec["odom"]
            if backwards:
                self._backward(tag, lineno, t, max(last_scan_t, last_odo_t))
                continue  # the scan is dropped; its motion stays in `carried`
            if self.mode == "corrected" and np.any(carried != 0):
                yield from drive.ticks(t, carried, after=last_scan_t, hole=limits.hole)
                carried = np.zeros(3)
                last_odo_t, in_hole = t, end_hole(t)
            elif not have_odom and self.mode == "raw":  # the scan's odometry field
                yield from hold.odometry(t, carried, sample=False)
                carried = np.zeros(3)
                last_odo_t, in_hole = t, end_hole(t)
            if last_odo_t > -math.inf and t - last_odo_t > hole:
                if not in_hole:  # a hole: no odometry for too long while scans come
                    notes["holes"] += 1
                    if len(notes["holes_first"]) < 10:
                        notes["holes_first"].append({"line": lineno, "from_s": last_odo_t})
                    in_hole, hole_from = True, last_odo_t
            if self.mode == "corrected" and self.reference:
                yield TruthPose(t, *rec["pose"])
            last_scan_t = t
            ranges = ranges.copy()
            with np.errstate(invalid="ignore"):  # no return; other ranges out of range are
                ranges[ranges >= min(self.no_return, rec["max_range"])] = np.nan  # plausibility's
            if len(ranges) == len(self.dead_beams):
                ranges[self.dead_beams] = np.nan
            n_scans += 1
            yield from hold.event(LaserScan(t, ranges, bearings))
        yield from hold.flush()
        self.problems.notes["warnings"] = input_warnings(
            n_scans, drive.travel, notes, self.meta.get("timestamps"), implausible=False
        )

    def scan_bearings(self, rec: dict) -> np.ndarray | None:
        """A laser record's bearings (rad, the laser frame of the configuration: the first
        scan's) as a :class:`LaserScan` takes them: None where they are the configured
        laser's."""
        key = (len(rec["ranges"]), rec["start"], rec["fov"])
        if key not in self._geometry:
            a = rec["start"] - self._middle + np.linspace(0.0, math.radians(rec["fov"]), key[0])
            b = own_bearings(a, self.config.laser)
            if len(self._geometry) >= 256:  # a few geometries (interlaced scans); bounded
                return b
            self._geometry[key] = b
        return self._geometry[key]

    def _implausible(self, lineno: int, inc: np.ndarray, dt: float) -> bool:
        """Check an odometry increment (dx m, dy m, dtheta rad) over ``dt`` s (not used with
        index stamps: no clock, only the step's distance is bounded): False when plausible;
        else :meth:`_skip_implausible` and True."""
        why = implausible(inc, None if self.clock == "index" else dt, self.limits)
        if why is None:
            return False
        self._skip_implausible(lineno, why)
        return True

    def _skip_implausible(self, lineno: int, why: str) -> None:
        """An implausible odometry record: skipped and counted, or (strict) a
        :class:`ReaderError` naming the line (the plausibility findings:
        :mod:`fgslam.io.readers.plausibility`)."""
        self.problems.note("odometry", why, line=lineno, skipped=True)
        self._odo_notes["implausible"] += 1

    def _backward(
        self, stream: str, lineno: int, t: float, last: float, detail: str | None = None
    ) -> None:
        """A record stamped before the last event delivered (at ``last`` s), or with a
        sporadic junk stamp (``t`` NaN): dropped or its motion carried, counted, noted as a
        stamp out of order (:meth:`~fgslam.io.readers.source.Problems.backward`)."""
        if detail is None and math.isfinite(t):
            detail = f"{stream} stamped {t:.6f} s, before the last event delivered ({last:.6f} s)"
        self.problems.backward(stream, detail or f"{stream} with a junk stamp", lineno)


def odometry_chain(path: StrPath, mode: str = "auto") -> OdometryChain:
    """The log's odometry record by record in file order, for the relations benchmark
    (:class:`fgslam.io.readers.odometry.OdometryChain`): every scan and ``ODOM`` line with its
    own stamp and
    the cumulative raw odometry at it (corrected logs: each ``ODOM`` line's increment over
    the line before it within its scan interval, the lines restarting from the scan's
    corrected pose; raw logs: the ``ODOM`` poses, or without them the scans' odometry
    fields), and the scans' corrected (reference) poses. File order, not stamps, orders the
    chain: the stamps of some records go backwards (Intel), their order in the file does
    not."""
    log = CarmenLog(path, mode=mode, tolerant=True)
    corrected = log.mode == "corrected"
    rec_t: list[float] = []
    rec_scan: list[int] = []  # index of the scan at or before the record in file order
    is_scan: list[bool] = []
    chain: list[np.ndarray] = []
    scan_t: list[float] = []
    scan_pose: list[tuple] = []
    odo = np.zeros(3)
    base: tuple | None = None  # corrected: P_{k-1}; raw: the last odometry pose
    last = np.zeros(3)
    have_odom = False
    for lineno, rec in log._records(strict=False):
        tag = rec["tag"]
        if tag not in ("ODOM", *LASER_TAGS) or lineno in log._repeats:
            continue
        if tag == "ODOM":
            have_odom = True
            if corrected:
                if base is None:
                    continue
                rel = relative(base, rec["pose"])
                odo = compose(odo, relative(last, rel))
                last = rel
            else:
                if base is not None:
                    odo = compose(odo, relative(base, rec["pose"]))
                base = rec["pose"]
            rec_t.append(rec["t"])
            rec_scan.append(len(scan_t) - 1)
            is_scan.append(False)
            chain.append(odo.copy())
            continue
        if corrected:
            base, last = rec["pose"], np.zeros(3)
        elif not have_odom:
            if base is not None:
                odo = compose(odo, relative(base, rec["odom"]))
            base = rec["odom"]
        scan_t.append(rec["t"])
        scan_pose.append(rec["pose"])
        rec_t.append(rec["t"])
        rec_scan.append(len(scan_t) - 1)
        is_scan.append(True)
        chain.append(odo.copy())
    c = np.array(chain).reshape(-1, 3)
    c[:, 2] = np.unwrap(c[:, 2])
    return OdometryChain(
        np.array(rec_t),
        np.array(rec_scan, dtype=int),
        np.array(is_scan, dtype=bool),
        c,
        np.array(scan_t),
        np.array(scan_pose).reshape(-1, 3),
    )
