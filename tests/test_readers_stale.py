"""Stale odometry (fgslam.io.readers.common.StaleOdometryHold): the hold on its own, in ROS bags,
and the same events and notes from a raw CARMEN log and a bag of the same drive (the CARMEN
cases on the room log are in test_readers_sanity.py)."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from readers_helpers import bag_drive, fmt, odometry_at, write_bag

from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.formats import open_log
from fgslam.io.readers.common import derived_config
from fgslam.io.readers.odometry import StaleOdometryHold, VirtualDrive
from fgslam.io.readers.sanity import OdometryLimits

CFG = derived_config(5)
MOVE = (0.15, 0.0, 0.0)  # m, m, rad: three samples of 5 cm
NO_GAP = {"gap_spans": 0, "gap_seconds": 0.0}


def _hold(stale: float = 1.0) -> tuple[StaleOdometryHold, dict]:
    notes: dict = {}
    return StaleOdometryHold(VirtualDrive(CFG), OdometryLimits(stale=stale), notes), notes


def _scan(t: float) -> LaserScan:
    return LaserScan(t, np.full(5, 2.0))


def _kinds(events) -> list[tuple[str, float]]:
    return [(type(e).__name__[0], round(e.t, 6)) for e in events]


def test_a_short_freeze_is_held_and_spread():
    """Repeats at 1.1 and 1.2 s (the last change at 1.0 s, within ``stale``): the repeats and
    the scans after them are held (so is the scan of 1.05 s: every event waits for the record
    after it); the catch-up at 1.3 s is spread over the span since the last change with the
    held scans among its samples; one span of 0.3 s."""
    hold, notes = _hold()
    assert notes == {"stale_spans": 0, "stale_seconds": 0.0, **NO_GAP}
    assert _kinds(hold.odometry(1.0, (0.05, 0.0, 0.0))) == [("O", 1.0)]
    assert hold.event(_scan(1.05)) == []
    for t in (1.1, 1.2):
        assert hold.odometry(t, np.zeros(3)) == []
        assert hold.event(_scan(t + 0.05)) == []
    out = hold.odometry(1.3, MOVE)
    assert _kinds(out) == [
        ("L", 1.05),
        ("O", 1.1),
        ("L", 1.15),
        ("O", 1.2),
        ("L", 1.25),
        ("O", 1.3),
    ]
    odo = [e for e in out if isinstance(e, OdometryEvent)]
    assert [(e.ticks_right, e.ticks_left) for e in odo] == [(500, 500)] * 3  # 0.1 mm/tick
    assert notes == {"stale_spans": 1, "stale_seconds": pytest.approx(0.3), **NO_GAP}
    assert hold.held == [] and hold.repeat_t is None


def test_a_freeze_longer_than_stale_is_a_stop():
    """Repeats from 1.4 s after the last change at 1.0 s: held while within ``stale`` (1 s);
    the repeat at 2.6 s shows a stop: zero samples up to each held repeat (1.4 and 1.8 s) and
    to the repeat itself, at most ``hole / 2`` s apart (2.2 s fills in), among the held scans
    (the standing robot's odometry keeps its samples: no gap); no span is counted. Events held
    at the end of the log are flushed as they were."""
    hold, notes = _hold(stale=1.0)
    hold.odometry(1.0, MOVE)
    assert hold.odometry(1.4, np.zeros(3)) == [] and hold.event(_scan(1.45)) == []
    assert hold.odometry(1.8, np.zeros(3)) == [] and hold.event(_scan(1.85)) == []
    out = hold.odometry(2.6, np.zeros(3))
    assert _kinds(out) == [("O", 1.4), ("L", 1.45), ("O", 1.8), ("L", 1.85), ("O", 2.2), ("O", 2.6)]
    assert all(e.ticks_right == e.ticks_left == 0 for e in out if isinstance(e, OdometryEvent))
    assert notes["stale_spans"] == 0
    # the stop goes on: held again (the last sample is recent), flushed at the end
    assert hold.odometry(3.0, np.zeros(3)) == [] and hold.event(_scan(3.05)) == []
    assert _kinds(hold.flush()) == [("L", 3.05)]
    assert notes == {"stale_spans": 0, "stale_seconds": 0.0, **NO_GAP}


def test_an_event_ends_a_hold_and_scan_fields_give_no_zero_samples():
    """A scan beyond ``stale`` after a repeat shows the stop itself (the repeat's zero sample,
    the held); the scan then waits for the next record. A repeat in a scan's odometry field
    (``sample=False``) that is a stop releases the held events without zero samples. An event
    placed without the odometry (a truth pose) waits behind held events but does not start a
    hold."""
    hold, notes = _hold(stale=1.0)
    hold.odometry(1.0, MOVE)
    assert hold.odometry(1.5, np.zeros(3)) == [] and hold.event(_scan(1.55)) == []
    assert _kinds(hold.event(_scan(2.2))) == [("O", 1.5), ("L", 1.55)]
    assert _kinds(hold.flush()) == [("L", 2.2)]

    hold, notes = _hold(stale=1.0)
    hold.odometry(1.0, MOVE, sample=False)
    assert hold.odometry(1.5, np.zeros(3), sample=False) == [] and hold.event(_scan(1.5)) == []
    assert _kinds(hold.odometry(2.2, np.zeros(3), sample=False)) == [("L", 1.5)]
    assert hold.event(_scan(2.2)) == [] and _kinds(hold.flush()) == [("L", 2.2)]

    hold, notes = _hold(stale=1.0)
    hold.odometry(1.0, MOVE)
    assert hold.odometry(1.5, np.zeros(3)) == []
    truth = TruthPose(1.52, 0.0, 0.0, 0.0)
    assert hold.event(truth, needs_odometry=False) == [truth]  # nothing held before it
    assert hold.event(_scan(1.55)) == []
    assert hold.event(TruthPose(1.57, 0.0, 0.0, 0.0), needs_odometry=False) == []
    assert _kinds(hold.odometry(1.6, MOVE)) == [
        ("O", 1.546667),
        ("L", 1.55),
        ("T", 1.57),
        ("O", 1.573333),
        ("O", 1.6),
    ]
    assert notes["stale_spans"] == 1 and notes["stale_seconds"] == pytest.approx(0.6)


# ------------------------------------------------------------------ ROS bags


LAG = 0.05  # s: scans and range readings after the odometry message of their step


def _later(topic: str, k: int, t: float) -> float:
    return t if topic == "/odom" else t + LAG


def _bag(tmp_path, ros1: bool, name: str, **kw):
    """A bag of :func:`write_bag` whose scans and range readings come ``LAG`` s after the
    odometry (header stamps and record times): no event shares a stamp with a sample."""
    pytest.importorskip("rosbags")
    p = tmp_path / (f"{name}.bag" if ros1 else name)
    write_bag(p, ros1, header=_later, record=_later, **kw)
    return p


def _odometry_at(events, kind=LaserScan) -> np.ndarray:
    """The odometry pose integrated from the delivered samples at each event of ``kind``."""
    return odometry_at(events, CFG.odometry, kind)


@pytest.mark.parametrize("ros1", [True, False])
def test_ros_frozen_odometry_is_held_and_spread(tmp_path, ros1):
    """/odom repeats its pose of 1.5 s at 1.6-1.9 s while the robot drives on, then catches up
    at 2.0 s (25 cm, 0.1 rad): the scans and range readings of 1.75 and 1.95 s are held and
    come out among the catch-up's samples, so the odometry at every scan is the clean bag's;
    one span of 0.5 s is counted, with the bound in the notes. Without the stale hold (stale
    = 0) the scans of the freeze see the robot standing, 10 cm behind at 1.75 s."""
    frozen = _bag(tmp_path, ros1, "frozen", frozen=range(6, 10))
    log = open_log(frozen, range_topics=["/sonar"])
    events = list(log)
    assert [e.t for e in events] == sorted(e.t for e in events)
    assert sum(isinstance(e, LaserScan) for e in events) == 10
    assert sum(isinstance(e, SonarReading) for e in events) == 10
    notes = log.problems.notes["odometry"]
    assert notes["stale_spans"] == 1 and notes["stale_seconds"] == pytest.approx(0.5)
    assert notes["limits"]["stale_s"] == OdometryLimits().stale and notes["holes"] == 0
    clean = list(open_log(_bag(tmp_path, ros1, "clean"), range_topics=["/sonar"]))
    for kind in (LaserScan, SonarReading):
        assert np.allclose(_odometry_at(events, kind), _odometry_at(clean, kind), atol=1e-3)
    old = list(open_log(frozen, range_topics=["/sonar"], limits=OdometryLimits(stale=0.0)))
    err = np.hypot(*(_odometry_at(old)[:, :2] - _odometry_at(clean)[:, :2]).T)
    assert err.max() > 0.08


@pytest.mark.parametrize("ros1", [True, False])
def test_ros_odometry_frozen_beyond_stale_is_a_stop(tmp_path, ros1):
    """/odom repeats its pose for the last 3 s of the bag (longer than ``stale``): a stop, not
    stale; every scan comes out, in order, with no motion over the stop; no span counted."""
    path = _bag(tmp_path, ros1, "stop", n=40, frozen=range(50, 80), with_range=False)
    log = open_log(path)
    events = list(log)
    assert [e.t for e in events] == sorted(e.t for e in events)
    assert sum(isinstance(e, LaserScan) for e in events) == 40
    assert log.problems.notes["odometry"]["stale_spans"] == 0
    assert OdometryLimits().stale < 3.0
    odo = _odometry_at(events)
    assert np.allclose(odo[25:], odo[24], atol=1e-4)  # scan 24 at 5.95 s, the last change 5.9 s
    assert not np.allclose(odo[24], odo[23], atol=1e-2)


def _sample_gaps(events) -> list[float]:
    """The gaps (s) between consecutive odometry samples with an event between them: what the
    factors would read as odometry holes when longer than the hole tolerance."""
    gaps, last, between = [], None, False
    for e in events:
        if isinstance(e, OdometryEvent):
            if last is not None and between:
                gaps.append(e.t - last)
            last, between = e.t, False
        else:
            between = True
    return gaps


def test_a_gap_is_spread_and_leaves_no_hole():
    """A pose stream quiet from 1.0 to 3.0 s while scans come every 0.2 s: the scans wait for
    the record of 3.0 s, whose 15 cm are spread over the gap in samples at most ``hole / 2`` s
    apart (zero samples filling in), the scans among them; one gap span of 2 s, no sample gap
    longer than 0.5 s. A scan more than ``spread`` s after the last record ends the hold as it
    was: the record after it is stamped at its end (a hole the factors see)."""
    hold, notes = _hold()
    hold.odometry(1.0, MOVE)
    for k in range(1, 10):
        assert hold.event(_scan(1.0 + 0.2 * k)) == []
    out = hold.odometry(3.0, MOVE)
    assert [e.t for e in out] == sorted(e.t for e in out)
    assert sum(isinstance(e, LaserScan) for e in out) == 9
    odo = [e for e in out if isinstance(e, OdometryEvent)]
    assert [round(e.t, 6) for e in odo] == [1.5, 2.0, 2.5, 3.0]
    assert sum(e.ticks_right for e in odo) == 1500  # the 15 cm, 0.1 mm per tick
    assert max(_sample_gaps(out)) <= 0.5 + 1e-9
    assert notes["gap_spans"] == 1 and notes["gap_seconds"] == pytest.approx(2.0)

    hold, notes = _hold()
    hold.odometry(1.0, MOVE)
    assert hold.event(_scan(1.5)) == []
    assert _kinds(hold.event(_scan(1.0 + OdometryLimits().spread + 0.5))) == [
        ("L", 1.5),
        ("L", 6.5),
    ]
    assert _kinds(hold.odometry(7.0, MOVE)) == [("O", 7.0)] * 3
    assert notes["gap_spans"] == 0


@pytest.mark.parametrize("ros1", [True, False])
def test_ros_paused_odometry_is_spread(tmp_path, ros1):
    """/odom pauses for 1.2 s (messages 6-17 left out) while the robot drives on: the scans of
    the pause wait for the message after it and come out among its samples, so the odometry
    at every scan is the clean bag's (interpolated: the drive is steady) and no sample gap is
    left for a hole; one gap span counted, no hole. With ``spread`` 0 (the hold off), the
    scans of the pause see the robot standing and a hole is counted."""
    paused = _bag(tmp_path, ros1, "paused", paused=range(6, 18))
    events = list(log := open_log(paused, range_topics=["/sonar"]))
    notes = log.problems.notes["odometry"]
    assert notes["gap_spans"] == 1 and notes["holes"] == 0
    assert notes["gap_seconds"] == pytest.approx(1.3)
    assert max(_sample_gaps(events)) < OdometryLimits().hole
    clean = list(open_log(_bag(tmp_path, ros1, "clean"), range_topics=["/sonar"]))
    assert np.allclose(_odometry_at(events), _odometry_at(clean), atol=0.03)
    off = OdometryLimits(spread=0.0, stale=0.0)
    old = list(log := open_log(paused, range_topics=["/sonar"], limits=off))
    assert log.problems.notes["odometry"]["holes"] == 1
    err = np.hypot(*(_odometry_at(old)[:, :2] - _odometry_at(clean)[:, :2]).T)
    assert err.max() > 0.4


def _carmen_twin(path, n: int, frozen: range) -> None:
    """A raw CARMEN log of the drive of :func:`_bag`: an ``ODOM`` line per odometry message
    (same stamps and poses, frozen alike), a 181-beam FLASER at each scan's stamp."""
    lines = []
    for k in range(2 * n):
        t = 1.0 + 0.1 * k
        pose = bag_drive(frozen.start - 1 if k in frozen else k)
        lines.append(f"ODOM {fmt(pose)} 0 0 0 {t!r} h {t!r}")
        if k % 2:
            r, ts = fmt(np.full(181, 2.0)), t + LAG
            lines.append(f"FLASER 181 {r} {fmt(pose)} {fmt(pose)} {ts!r} h {ts!r}")
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("frozen", [range(6, 10), range(3, 6), range(12, 19)])
def test_carmen_and_ros_hold_alike(tmp_path, frozen):
    """The same drive, odometry freeze and scan timing as a raw CARMEN log and a ROS 2 bag:
    the same odometry samples and scan stamps, and the same stale notes."""
    n = 12
    bag = _bag(tmp_path, False, "bag", n=n, frozen=frozen, with_range=False)
    carmen = tmp_path / "twin.log"
    _carmen_twin(carmen, n, frozen)
    logs = open_log(bag), open_log(carmen, mode="raw")
    streams = [list(log) for log in logs]
    for a, b in zip(*streams, strict=True):
        assert type(a) is type(b) and a.t == pytest.approx(b.t, abs=1e-6)
        if isinstance(a, OdometryEvent):
            assert (a.ticks_right, a.ticks_left) == (b.ticks_right, b.ticks_left)
    ros, car = (log.problems.notes["odometry"] for log in logs)
    assert ros["stale_spans"] == car["stale_spans"] == 1
    assert ros["stale_seconds"] == car["stale_seconds"] == pytest.approx(0.1 * (len(frozen) + 1))
    assert ros["limits"] == car["limits"]


def test_a_second_read_counts_each_record_once(tmp_path):
    """Reading a CARMEN log or a bag again gives the same events and the same problems and
    notes: the counts of a pass start from zero (they used to add up)."""
    frozen = range(4, 7)
    bag = _bag(tmp_path, False, "bag", n=12, frozen=frozen, with_range=False)
    carmen = tmp_path / "twin.log"
    _carmen_twin(carmen, 12, frozen)
    with open(carmen, "a") as f:
        f.write("NEFF 1 2 3\n")  # an unknown record: skipped and counted
    for log in (open_log(bag), open_log(carmen, mode="raw")):
        first, notes = _kinds(log), copy.deepcopy(log.problems.summary())
        assert _kinds(log) == first and log.problems.summary() == notes
        assert notes["odometry"]["stale_spans"] == 1
    assert notes["skipped_by_reason"] == {"unknown record NEFF": 1}


@pytest.mark.parametrize("ros1", [True, False])
def test_a_standing_robots_odometry_keeps_its_samples(tmp_path, ros1):
    """The robot stands for the last 3 s of the bag while /odom keeps reporting every 0.1 s:
    each of those records gives its zero sample (they were once swallowed by the stale hold
    but for one every ``stale`` s, which read as odometry holes of up to ``stale`` s between
    the scans of a standing robot): every scan lies within 0.1 s of a sample, but those of
    the last ``stale`` s, still held when the log ends and flushed as they were."""
    path = _bag(tmp_path, ros1, "stand", n=40, frozen=range(50, 80), with_range=False)
    events = list(open_log(path))
    end = max(e.t for e in events)
    last, worst = None, 0.0
    for e in events:
        if isinstance(e, OdometryEvent):
            last = e.t
        elif isinstance(e, LaserScan) and last is not None and e.t < end - OdometryLimits().stale:
            worst = max(worst, e.t - last)
    assert worst <= 0.1 + 1e-6
    zero = [e for e in events if isinstance(e, OdometryEvent) and e.t > 6.0]
    assert len(zero) >= 15 and all(e.ticks_right == e.ticks_left == 0 for e in zero)
