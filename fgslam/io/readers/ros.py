"""ROS 1 and ROS 2 bags through the ``rosbags`` package (``pip install fgslam[ros]``).

- ``sensor_msgs/LaserScan`` (``scan_topic``) -> :class:`~fgslam.events.LaserScan`: the
  configured laser's beam count, field of view (``angle_max - angle_min``) and the mount's
  yaw (the middle of the scan) come from the first scan; the mount's pose is the transform
  from the robot's base frame to the scan's frame in ``/tf_static`` or ``/tf``
  (:func:`tf_mount`), else the robot origin; ``laser_mount`` (x, y, yaw in rad) replaces
  it. Beam k of a message lies at ``angle_min + k angle_increment``; a scan whose beams lie
  elsewhere than the configured laser's (another beam count, another start: a scanner that
  interlaces its scans) carries its own bearings (:func:`fgslam.events.own_bearings`).
  Ranges not finite, outside ``[range_min, range_max)`` (a reading at ``range_max`` is no
  return) or <= 0 are NaN.
- ``nav_msgs/Odometry`` (``odom_topic``) -> encoder ticks of the virtual differential drive
  (:class:`~fgslam.io.readers.common.VirtualDrive`): each message's pose relative to the
  previous message's pose.
- ``sensor_msgs/Range`` (``range_topics``, optional) -> :class:`~fgslam.events.SonarReading`
  of sonar array i (the i-th topic, mounted at ``range_mounts[i]``, x, y, yaw in rad, default
  the robot origin facing forward) with one ``plane`` echo at bearing 0 when the range lies
  in ``[min_range, max_range]``, none otherwise. A plain ultrasonic ranger neither classifies
  its echoes nor measures their bearing: this mapping treats every echo as a plane seen at
  normal incidence, which is often wrong; use ``--sensors laser`` unless that holds.

Times are the messages' header stamps, or the bag's record times where the header stamps are
unsound (``timestamps``: ``auto``, ``header``, ``bag``; recorded in ``meta["timestamps"]``):
before reading, both clocks are checked per topic with the rules of
:mod:`fgslam.io.readers.sanity` (stamped 0, wrapped, quantised scans, junk, backwards beyond
``backwards_tolerance``), and the header stamps also for being one clock across the topics
(:func:`~fgslam.io.readers.sanity.common_clock`); with neither sound, a one-line
:class:`ReaderError` names each clock's first defect and its topic. Messages with sporadic
bad stamps are handled as going backwards (below). Odometry messages moving faster than the
reader's :class:`~fgslam.io.readers.sanity.OdometryLimits` are skipped and counted, the jump
dropped (:class:`~fgslam.io.readers.odometry.OdometryJumps`), or with ``strict`` an error. Scans
and range readings wait for the odometry message after them, which is spread over the span
(:class:`~fgslam.io.readers.odometry.StaleOdometryHold`, as in raw CARMEN logs): a frozen
stream that catches up (``stale_spans``, ``stale_seconds`` in the odometry notes) and a pause
of up to ``spread`` s (``gap_spans``, ``gap_seconds``) are interpolated; longer gaps while
scans come are counted as holes. Topic names are
chosen by option; left out, the only topic of the right type is taken. A bag without such a
topic is a :class:`ReaderError` listing the topics it has. Header stamps that go backwards
are counted: a scan or range reading is then skipped, an odometry message's motion is carried
into the next one; nothing is reordered.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fgslam.config import Mount
from fgslam.errors import ReaderError
from fgslam.events import (
    BEARING_TOLERANCE,
    Event,
    LaserScan,
    SonarEcho,
    SonarReading,
    own_bearings,
)
from fgslam.io.readers.common import derived_config, input_warnings
from fgslam.io.readers.odometry import OdometryJumps, StaleOdometryHold, VirtualDrive, compose
from fgslam.io.readers.sanity import (
    BACKWARDS_TOLERANCE,
    MAX_STAMP,
    OdometryLimits,
    StampReport,
    choose_clock,
    common_clock,
    stream_defects,
)
from fgslam.io.readers.source import Source, StrPath

ROS_CLOCKS = ("auto", "header", "bag")
SCAN = "sensor_msgs/msg/LaserScan"
ODOM = "nav_msgs/msg/Odometry"
RANGE = "sensor_msgs/msg/Range"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
BASE_FRAMES = ("base_link", "base_footprint")  # the robot's frame, after odometry's child
TF_MESSAGES = 2000  # messages of a dynamic tf topic searched for the laser's mount at most
UPRIGHT = math.cos(math.radians(10.0))  # a laser tilted more is not a 2-D mount


def _import():
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:  # pragma: no cover - depends on the installation
        raise ReaderError(
            "reading ROS bags needs the 'rosbags' package: pip install 'fgslam[ros]'"
        ) from None
    return AnyReader, Stores, get_typestore


def is_bag(path: StrPath) -> bool:
    """A ROS 2 bag directory (metadata.yaml) or a ROS 1 bag file (``#ROSBAG V2.0``)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").exists()
    try:
        with open(p, "rb") as f:
            return f.read(13) == b"#ROSBAG V2.0\n"
    except OSError:
        return False


def _stamp(msg: Any) -> float:
    s = msg.header.stamp
    return float(s.sec) + 1e-9 * float(s.nanosec)


def bag_messages(reader: Any, conns: Sequence[Any], name: str) -> Iterator[tuple[Any, int, bytes]]:
    """``reader.messages(connections=conns)`` with the library's failures on a damaged bag
    (a chunk, index or record it cannot read: rosbags' own errors, but also AssertionError,
    KeyError, UnicodeDecodeError, sqlite and decompression errors from deep inside it) turned
    into a :class:`ReaderError` naming the file and the message (counted from 1 in the bag's
    order over ``conns``). Only the library's iteration is guarded: the caller's code runs
    outside it."""
    if not conns:
        return
    count = 0
    try:
        it = reader.messages(connections=conns)
    except Exception as exc:  # the library, on the file's bytes
        raise ReaderError(f"{name}: cannot read the bag's messages ({_cause(exc)})") from None
    while True:
        try:
            item = next(it)
        except StopIteration:
            return
        except Exception as exc:  # the library, on the file's bytes
            raise ReaderError(
                f"{name}: cannot read message {count + 1} of the bag ({_cause(exc)}); "
                "a damaged or truncated bag (a ROS 1 bag cut off while recording may read "
                "after `rosbag reindex`)"
            ) from None
        count += 1
        yield item


def _printable(text: str) -> str:
    """A name from the bag as one line (control characters escaped)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _cause(exc: BaseException) -> str:
    """One line: the exception's type and the first line of its message."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0][:200]}" if text else type(exc).__name__


def _yaw(q: Any) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def beam_angles(msg: Any) -> np.ndarray:
    """The beam angles of a ``sensor_msgs/LaserScan`` (rad, its header frame, beam order):
    ``angle_min + k angle_increment`` (REP-117), or spread evenly over ``[angle_min,
    angle_max]`` when the increment is 0 or not a number."""
    n = len(msg.ranges)
    a0, inc = float(msg.angle_min), float(msg.angle_increment)
    if inc != 0 and math.isfinite(inc):
        return a0 + inc * np.arange(n)
    return np.linspace(a0, float(msg.angle_max), n)


def _span(msg: Any) -> tuple[float, float]:
    """The first scan's smallest and largest beam angle (rad): ``angle_min`` and ``angle_max``
    themselves where they agree with the increment (as the configuration had them before
    per-scan geometry), else the ends of :func:`beam_angles`."""
    a = beam_angles(msg)
    lo, hi = float(msg.angle_min), float(msg.angle_max)
    if len(a) and not (
        abs(a[0] - lo) <= BEARING_TOLERANCE and abs(a[-1] - hi) <= BEARING_TOLERANCE
    ):
        lo, hi = float(a[0]), float(a[-1])
    return min(lo, hi), max(lo, hi)


def _rotation(q: Any) -> np.ndarray:
    """The 3x3 rotation of a quaternion (normalised)."""
    x, y, z, w = (float(v) for v in (q.x, q.y, q.z, q.w))
    s = x * x + y * y + z * z + w * w
    if not (math.isfinite(s) and s > 0):
        raise ValueError("not a rotation")
    x, y, z, w = (v / math.sqrt(s) for v in (x, y, z, w))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


class TfTree:
    """The first transform seen of every frame (``child -> parent``) of tf messages."""

    def __init__(self) -> None:
        self.parent: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}

    def add(self, msg: Any) -> bool:
        """Take the transforms of a ``tf2_msgs/TFMessage`` of frames not yet known; returns
        whether there were any."""
        new = False
        for tr in msg.transforms:
            child, parent = tr.child_frame_id.strip("/ "), tr.header.frame_id.strip("/ ")
            if not child or not parent or child == parent or child in self.parent:
                continue
            v = tr.transform.translation
            try:
                rot = _rotation(tr.transform.rotation)
            except ValueError:
                continue
            t = np.array([float(v.x), float(v.y), float(v.z)])
            if np.isfinite(t).all():
                self.parent[child] = (parent, rot, t)
                new = True
        return new

    def _to_root(self, frame: str) -> tuple[str, np.ndarray, np.ndarray]:
        """The root of ``frame`` and frame's pose in it (rotation, translation)."""
        rot, t = np.eye(3), np.zeros(3)
        for _ in range(len(self.parent) + 1):  # a cycle ends the walk
            if frame not in self.parent:
                break
            frame, r, v = self.parent[frame]
            rot, t = r @ rot, r @ t + v
        return frame, rot, t

    def pose(self, base: str, frame: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The pose of ``frame`` in ``base`` (rotation, translation in m), or None when the
        two are not connected."""
        rb, rot_b, t_b = self._to_root(base)
        rf, rot_f, t_f = self._to_root(frame)
        if rb != rf:
            return None
        return rot_b.T @ rot_f, rot_b.T @ (t_f - t_b)


def tf_mount(
    reader: Any, scan_frame: str, bases: Sequence[str], name: str = "bag"
) -> tuple[tuple[float, float, float] | None, str]:
    """The pose (x m, y m, yaw rad) of the laser frame ``scan_frame`` in the robot's frame,
    the first of ``bases`` that the bag's tf topics connect to it (static topics whole, then
    the first ``TF_MESSAGES`` messages of the dynamic ones: a transform's first message is
    taken), and what was found (frames, or why not). None when no tf connects them or when
    the laser is tilted more than 10 deg from upright (upside down: a 2-D mount cannot hold
    it)."""
    scan_frame = scan_frame.strip("/ ")
    topics = [c for c in reader.connections if c.msgtype in TF_TYPES]
    if not topics:
        return None, "no tf topic"
    if not scan_frame:
        return None, "the scans have no frame_id"
    tree = TfTree()

    def search() -> tuple[str, tuple[np.ndarray, np.ndarray]] | None:
        for b in bases:
            p = tree.pose(b, scan_frame) if b != scan_frame else (np.eye(3), np.zeros(3))
            if p is not None:
                return b, p
        return None

    found = None
    static = [c for c in topics if "static" in c.topic]
    dynamic = [c for c in topics if "static" not in c.topic]
    for conns, limit in ((static, math.inf), (dynamic, TF_MESSAGES)):
        for count, (conn, _, raw) in enumerate(bag_messages(reader, conns, name)):
            if count >= limit:
                break
            try:
                new = tree.add(reader.deserialize(raw, conn.msgtype))
            except Exception:  # a damaged tf message: the mount comes from the others
                continue
            if new and conns is dynamic and (found := search()) is not None:
                break
        if (found := found or search()) is not None:
            break
    if found is None:
        return None, f"tf connects none of {', '.join(bases)} to {scan_frame}"
    base, (rot, t) = found
    if rot[2, 2] < UPRIGHT:
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(rot[2, 2])))))
        return None, f"{scan_frame} is tilted {tilt:.0f} deg from upright in {base}"
    return (float(t[0]), float(t[1]), math.atan2(rot[1, 0], rot[0, 0])), f"{base} -> {scan_frame}"


class RosBag(Source):
    """A ROS 1 or ROS 2 bag as fgslam events; see the module documentation."""

    format = "ros"

    def __init__(
        self,
        path: StrPath,
        scan_topic: str | None = None,
        odom_topic: str | None = None,
        range_topics: Sequence[str] = (),
        laser_mount: tuple[float, float, float] | None = None,
        range_mounts: Sequence[tuple[float, float, float]] = (),
        tolerant: bool = False,
        timestamps: str = "auto",
        limits: OdometryLimits | None = None,
        backwards_tolerance: float = BACKWARDS_TOLERANCE,
        strict: bool = False,
    ) -> None:
        super().__init__(path)
        self.strict = strict  # refuse implausible odometry
        if timestamps not in ROS_CLOCKS:
            raise ReaderError(
                f"unknown --timestamps {timestamps!r} for a bag; expected one of {ROS_CLOCKS}"
            )
        self.limits = limits or OdometryLimits()
        AnyReader, Stores, get_typestore = _import()
        self._AnyReader = AnyReader
        self._typestore = get_typestore(Stores.ROS2_HUMBLE)
        self.tolerant = tolerant
        with self._open() as reader:
            topics = self._topics
            self.scan_topic = self._pick(topics, scan_topic, SCAN, "--scan-topic")
            self.odom_topic = self._pick(topics, odom_topic, ODOM, "--odom-topic")
            self.range_topics = [
                self._pick(topics, t, RANGE, "--range-topic") for t in range_topics
            ]
            first = self._clock_pass(reader)
            mount_note: dict[str, Any] = {"source": "laser_mount option"}
            if first is not None and laser_mount is None:
                tf, why = tf_mount(reader, first.header.frame_id, self._bases(reader), self.name)
                laser_mount = tf or (0.0, 0.0, 0.0)
                mount_note = {"source": "tf" if tf else "robot origin", "tf": why}
        if first is None:
            raise ReaderError(f"{self.name}: topic {self.scan_topic} has no messages")
        clock_record = self._choose_clock(timestamps, backwards_tolerance)
        n = len(first.ranges)
        lo, hi = _span(first)
        fov = round(math.degrees(hi - lo), 4)  # float32 angles
        if n < 2 or not 0 < fov <= 360:
            raise ReaderError(f"{self.name}: first scan has {n} beams over {fov:g} deg")
        self._middle = 0.5 * (lo + hi)  # rad: the laser frame's x axis in the scans' frame
        yaw = self._middle + laser_mount[2]
        cfg = derived_config(
            n,
            fov,
            max_range=float(first.range_max) if first.range_max > 0 else 80.0,
            mount=(laser_mount[0], laser_mount[1], yaw),
        )
        if self.range_topics:
            mounts = list(range_mounts) + [(0.0, 0.0, 0.0)] * len(self.range_topics)
            base = cfg.sonar.arrays[0]
            arrays = tuple(
                dataclasses.replace(
                    base,
                    name=t,
                    mount=Mount(m[0], m[1], math.degrees(m[2])),
                    pan_min_deg=0.0,
                    pan_max_deg=0.0,
                )
                for t, m in zip(self.range_topics, mounts, strict=False)
            )
            cfg = dataclasses.replace(cfg, sonar=dataclasses.replace(cfg.sonar, arrays=arrays))
        self.config = cfg
        self.n_beams = n
        self._geometry: dict[tuple[int, float, float, float], Any] = {}
        mount_note["mount"] = [round(float(v), 6) for v in laser_mount]
        self.world = f"ROS bag {Path(self.name).name}"
        self.meta = {
            "source_format": "ros",
            "source": self.name,
            "scan_topic": self.scan_topic,
            "odom_topic": self.odom_topic,
            "range_topics": list(self.range_topics),
            "laser": f"{n} beams over {fov:g} deg",
            "laser_mount": mount_note,
            "timestamps": clock_record,
        }
        self.problems.notes["timestamps"] = clock_record
        self._new_pass()

    def _new_pass(self) -> None:
        """Fresh counts for a pass over the events (the odometry notes and the problems)."""
        self.problems.new_pass()
        self._odo_notes: dict[str, Any] = {
            "holes": 0,
            "implausible": 0,
            "rebased": 0,
            "stale_spans": 0,
            "stale_seconds": 0.0,
            "limits": self.limits.notes(),
        }
        self.problems.notes["odometry"] = self._odo_notes

    def _clock_pass(self, reader: Any) -> Any:
        """One pass over the messages of the topics read: each one's header stamp and record
        time, by topic and message number (from 1, every message counted, undecodable ones
        left out of the stamps); returns the first scan."""
        wanted = {self.scan_topic, self.odom_topic, *self.range_topics}
        self._stamps: dict[str, tuple[list[int], list[float], list[float]]] = {
            t: ([], [], []) for t in (self.scan_topic, self.odom_topic, *self.range_topics)
        }
        count = dict.fromkeys(wanted, 0)
        first = None
        conns = [c for c in reader.connections if c.topic in wanted]
        for conn, bag_ns, raw in bag_messages(reader, conns, self.name):
            count[conn.topic] += 1
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                header = _stamp(msg)
                record = 1e-9 * float(bag_ns)
            except Exception:  # the reading pass reports it
                continue
            if first is None and conn.topic == self.scan_topic:
                first = msg
            k, h, b = self._stamps[conn.topic]
            k.append(count[conn.topic])
            h.append(header)
            b.append(record)
        return first

    def _bases(self, reader: Any) -> list[str]:
        """The robot's frame candidates: the odometry's child frame, then ``BASE_FRAMES``."""
        out = []
        conns = [c for c in reader.connections if c.topic == self.odom_topic]
        for conn, _, raw in bag_messages(reader, conns, self.name):
            try:
                child = reader.deserialize(raw, conn.msgtype).child_frame_id.strip("/ ")
            except Exception:  # the reading pass reports it
                continue
            out = [child] if child else []
            break
        return out + [b for b in BASE_FRAMES if b not in out]

    def scan_geometry(self, msg: Any) -> tuple[np.ndarray | None, bool] | None:
        """A scan message's bearings in the laser frame as a :class:`LaserScan` takes them
        (None: the configured laser's) and whether its ranges run backwards (a negative
        increment: reversed so that the bearings increase); None when its beams have no
        usable geometry (no beams, angles not numbers, two beams at one angle)."""
        key = (
            len(msg.ranges),
            float(msg.angle_min),
            float(msg.angle_max),
            float(msg.angle_increment),
        )
        if key in self._geometry:
            return self._geometry[key]
        a = beam_angles(msg) - self._middle
        back = len(a) > 1 and a[-1] < a[0]
        if back:
            a = a[::-1]
        geo = None
        if len(a) and np.isfinite(a).all() and (np.diff(a) > 0).all():
            geo = (own_bearings(a, self.config.laser), bool(back))
        if len(self._geometry) < 256:  # a few geometries (interlaced scans); bounded
            self._geometry[key] = geo
        return geo

    def _choose_clock(self, requested: str, tolerance: float) -> dict[str, Any]:
        """The defects of the header stamps (per topic, and whether the topics share one
        clock) and of the record times (per topic), the clock chosen
        (:func:`fgslam.io.readers.sanity.choose_clock`) and the messages with sporadic bad
        stamps; returns the record of the choice."""
        reports: dict[str, StampReport] = {}
        for clock, col in (("header", 1), ("bag", 2)):
            streams = {t: (v[0], v[col]) for t, v in self._stamps.items()}
            rep = stream_defects(streams, tolerance, scans=self.scan_topic, unit="message")
            if clock == "header" and rep.sound:
                offsets = {t: np.subtract(v[2], v[1]) for t, v in self._stamps.items()}
                split = common_clock(offsets, tolerance)
                if split:
                    rep.defects.append(f"header stamps of {split}")
            reports[clock] = rep
        self.clock, record = choose_clock(
            self.name,
            reports,
            requested,
            choices=ROS_CLOCKS,
            labels={"header": "header stamps", "bag": "record times"},
            hint="header|bag",
        )
        self._bad: set[tuple[str, int]] = {
            (topic, k) for topic, ks in reports[self.clock].sporadic.items() for k in ks
        }
        del self._stamps
        return record

    def _open(self):
        try:
            reader = self._AnyReader([Path(self.path)], default_typestore=self._typestore)
            reader.open()
            self._topics = {
                _printable(str(name)): _printable(str(info.msgtype))
                for name, info in reader.topics.items()
            }
            reader.close()
        except Exception as exc:  # the library, on the file's bytes (any of its failures)
            raise ReaderError(f"{self.name}: cannot read the bag ({_cause(exc)})") from None
        return reader

    def _pick(self, topics: dict[str, str], name: str | None, msgtype: str, option: str) -> str:
        have = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
        if name is not None:
            if name not in topics:
                raise ReaderError(f"{self.name}: no topic {name}; the bag has: {have}")
            if topics[name] != msgtype:
                raise ReaderError(
                    f"{self.name}: topic {name} is {topics[name]}, expected {msgtype}"
                )
            return name
        found = [t for t, m in topics.items() if m == msgtype]
        if len(found) != 1:
            what = "no" if not found else "more than one"
            raise ReaderError(
                f"{self.name}: {what} {msgtype} topic (choose one with {option}); "
                f"the bag has: {have}"
            )
        return found[0]

    def events(self) -> Iterator[Event]:
        """The bag's events of one pass (checked by the shared plausibility rules in
        :meth:`Source.__iter__`)."""
        self._new_pass()
        drive = VirtualDrive(self.config)
        hold = StaleOdometryHold(drive, self.limits, self._odo_notes)
        pr = self.problems
        last = -math.inf
        jumps = OdometryJumps(self.limits)  # the odometry poses, implausible ones skipped
        first_odom = True
        last_odo_in = -math.inf  # s: the last odometry message used
        in_hole = False
        n_scans = 0
        carried = np.zeros(3)
        array_of = {t: i for i, t in enumerate(self.range_topics)}
        wanted = {self.scan_topic, self.odom_topic, *self.range_topics}

        def late(topic: str, number: int, t: float, last: float) -> None:
            what = "a bad stamp" if math.isnan(t) else f"stamped {t:.6f} s"
            pr.backward(topic, f"{topic} message {number}: {what}, before {last:.6f} s")

        with self._open() as reader:
            conns = [c for c in reader.connections if c.topic in wanted]
            count = dict.fromkeys(wanted, 0)
            for conn, bag_ns, raw in bag_messages(reader, conns, self.name):
                count[conn.topic] += 1
                bad = (conn.topic, count[conn.topic]) in self._bad  # a sporadic bad stamp
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    t = _stamp(msg) if self.clock == "header" else 1e-9 * float(bag_ns)
                    if bad:
                        t = math.nan
                    elif not (math.isfinite(t) and abs(t) < MAX_STAMP):
                        raise ValueError(f"stamp {t:.6g} is not a time")
                    if conn.topic == self.odom_topic:
                        p = msg.pose.pose
                        pose = (float(p.position.x), float(p.position.y), _yaw(p.orientation))
                        if not all(abs(v) < 1e7 for v in pose):
                            raise ValueError(f"pose {pose} out of range")
                except Exception as exc:
                    msg_text = f"{self.name}: {conn.topic}: cannot decode a message ({exc})"
                    if not self.tolerant:
                        raise ReaderError(msg_text) from None
                    pr.skip(f"undecodable {conn.topic}", msg_text)
                    continue
                if conn.topic == self.odom_topic:
                    inc, why = jumps.step(pose, t)
                    self._odo_notes["rebased"] = jumps.rebased
                    if first_odom:
                        first_odom = False
                        if bad:
                            late(conn.topic, count[conn.topic], t, last)
                        else:
                            last = max(last, t)
                            last_odo_in = t  # a gap after the first record is a hole too
                        continue
                    if inc is None:  # a jump: dropped (OdometryJumps)
                        pr.note("odometry", f"{conn.topic} at t={t:.6f}: {why}", skipped=True)
                        self._odo_notes["implausible"] += 1
                        continue
                    carried = compose(carried, inc)
                    if bad:  # carried into the next message, as one going backwards
                        late(conn.topic, count[conn.topic], t, last)
                        continue
                    if t < last:
                        late(conn.topic, count[conn.topic], t, last)
                        continue
                    last = t
                    yield from hold.odometry(t, carried)
                    carried = np.zeros(3)
                    last_odo_in, in_hole = t, False
                    continue
                if bad or t < last:
                    late(conn.topic, count[conn.topic], t, last)
                    continue
                last = t
                if conn.topic == self.scan_topic and t - last_odo_in > max(
                    self.limits.hole, self.limits.spread
                ):
                    if not in_hole and last_odo_in > -math.inf:
                        self._odo_notes["holes"] += 1
                        in_hole = True
                if conn.topic == self.scan_topic:
                    geo = self.scan_geometry(msg)
                    if geo is None:
                        pr.skip(
                            "scan without beam geometry",
                            f"{self.name}: {conn.topic} at t={t:.6f}: {len(msg.ranges)} beams "
                            f"from {msg.angle_min:g} rad by {msg.angle_increment:g} rad",
                        )
                        continue
                    with np.errstate(invalid="ignore"):  # a signalling NaN among float32s
                        r = np.array(msg.ranges, dtype=float)
                    with np.errstate(invalid="ignore"):
                        bad = ~np.isfinite(r) | (r < msg.range_min) | (r >= msg.range_max)
                    r[bad | (r <= 0)] = np.nan
                    if geo[1]:
                        r = r[::-1].copy()
                    n_scans += 1
                    yield from hold.event(LaserScan(t, r, geo[0]))
                else:
                    r = float(msg.range)
                    echoes = ()
                    if math.isfinite(r) and msg.min_range <= r <= msg.max_range and r > 0:
                        echoes = (SonarEcho("plane", r, 0.0),)
                    yield from hold.event(SonarReading(t, array_of[conn.topic], 0.0, echoes))
        yield from hold.flush()
        self.problems.notes["warnings"] = input_warnings(
            n_scans, drive.travel, self._odo_notes, self.meta.get("timestamps"), implausible=False
        )
