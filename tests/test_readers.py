"""Readers of foreign logs: CARMEN (synthetic and the shared real logs), Victoria Park, ROS 1
and ROS 2 bags written here with rosbags; bad input; the virtual drive."""

from __future__ import annotations

import gzip
import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from readers_helpers import DATA, carmen_text, path, rel, write_bag

from factors.odometry import integrate_poses
from fgslam.errors import ReaderError
from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.formats import open_log, sniff_format
from fgslam.io.readers.carmen import CarmenLog
from fgslam.io.readers.carmen_records import odometry_check
from fgslam.io.readers.common import derived_config
from fgslam.io.readers.odometry import VirtualDrive, relative
from fgslam.io.readers.victoria import read_victoria, to_bearing_range

INTEL = DATA / "intel-corrected.log.gz"
FREIBURG = DATA / "freiburg-079-corrected.log.gz"
VICTORIA = DATA / "victoria_park.txt"
needs = {
    p: pytest.mark.skipif(not p.exists(), reason=f"{p.name} not in ../shared/data")
    for p in (INTEL, FREIBURG, VICTORIA)
}


def odometry_between_scans(events, cfg):
    """Odometry-only relative pose (x, y, th) from the previous scan to each scan."""
    o = cfg.odometry
    lr, ll, out = [], [], []
    for e in events:
        if isinstance(e, OdometryEvent):
            lr.append(e.ticks_right * o.metres_per_tick_right)
            ll.append(e.ticks_left * o.metres_per_tick_left)
        elif isinstance(e, LaserScan):
            out.append(integrate_poses(lr, ll, o.wheelbase)[-1] if lr else np.zeros(3))
            lr, ll = [], []
    return np.array(out)


def assert_increment(got, expected):
    """Odometry through the virtual drive against the increment it was given: heading and
    distance exact (to the 0.1 mm ticks), position within the documented chord bound
    |d| |atan2(dy, dx) - dtheta/2|."""
    got, expected = np.asarray(got), np.asarray(expected)
    dist = math.hypot(expected[0], expected[1])
    assert got[2] == pytest.approx(expected[2], abs=2e-4)
    assert math.hypot(got[0], got[1]) == pytest.approx(dist, abs=1e-3)
    beta = math.atan2(expected[1], expected[0]) if dist > 1e-9 else 0.0
    bound = dist * abs(math.remainder(beta - expected[2] / 2, 2 * math.pi)) + 1e-3
    assert math.hypot(*(got[:2] - expected[:2])) <= bound


# ------------------------------------------------------------------ the virtual drive


@pytest.mark.parametrize(
    "inc",
    [(0.3, 0.0, 0.0), (0.0, 0.0, 1.0), (0.5, 0.1, 0.4), (-0.2, 0.0, -0.3), (1e-5, 0.0, 0.0)],
)
def test_virtual_drive_reproduces_chord_increments(inc):
    """An increment along the chord of its turn (dy = dx tan(dth/2)) comes back exactly, to
    the 0.1 mm quantisation; others keep their heading change and distance."""
    cfg = derived_config(181)
    drive = VirtualDrive(cfg)
    dx, _, dth = inc
    chord = (dx, dx * math.tan(dth / 2), dth)
    evs = drive.ticks(1.0, chord)
    o = cfg.odometry
    p = integrate_poses(
        [e.ticks_right * o.metres_per_tick_right for e in evs],
        [e.ticks_left * o.metres_per_tick_left for e in evs],
        o.wheelbase,
    )[-1]
    assert np.allclose(p[:2], chord[:2], atol=2e-4)
    assert p[2] == pytest.approx(dth, abs=2e-4)
    # samples of at most 5 cm / 2 deg, stamped at the end time for the first increment
    assert len(evs) >= max(1, math.ceil(abs(dth) / math.radians(2.0) - 1e-9))
    assert all(e.t == 1.0 for e in evs)


def test_virtual_drive_quantisation_does_not_accumulate():
    """10 000 increments of 0.123 45 mm: the rounded ticks sum to the true distance."""
    cfg = derived_config(181)
    drive = VirtualDrive(cfg)
    ticks = [drive.ticks(float(k), (1.2345e-4, 0.0, 0.0))[0] for k in range(1, 10001)]
    total = sum(e.ticks_right for e in ticks) * cfg.odometry.metres_per_tick_right
    assert total == pytest.approx(1.2345, abs=1e-4)
    assert {e.ticks_right for e in ticks} == {1, 2}  # each sample rounded on its own
    # 4 samples of 5 cm, stamped evenly over (10000, 10002]
    assert [e.t for e in drive.ticks(10002.0, (0.2, 0.0, 0.0))] == [
        10000.5,
        10001.0,
        10001.5,
        10002.0,
    ]


# ------------------------------------------------------------------ CARMEN, synthetic


def test_carmen_corrected_log(tmp_path):
    """Detected as corrected; odometry between scans k-1 and k equals inverse(P_{k-1}) *
    ODOM_before_k (here: the true increment composed with the odometry error); the corrected
    poses come as truth events marked as a reference; NEFF counted; no-return is NaN."""
    f = tmp_path / "room.log"
    f.write_text(carmen_text(corrected=True))
    assert sniff_format(f) == "carmen"
    log = open_log(f)
    assert isinstance(log, CarmenLog) and log.mode == "corrected"
    assert log.reference_kind == "reference"
    assert log.config.laser.n_beams == 180 and log.config.laser.fov_deg == 180.0
    events = list(log)
    scans = [e for e in events if isinstance(e, LaserScan)]
    truth = [e for e in events if isinstance(e, TruthPose)]
    assert len(scans) == len(truth) == 30
    assert np.isnan(scans[0].ranges[5]) and np.isfinite(scans[0].ranges[6])
    assert log.problems.skipped_by_reason == Counter({"unknown record NEFF": 30})
    odo = odometry_between_scans(events, log.config)
    truth_path = path(30)
    for k in range(1, 30):
        # the true increment composed with the odometry error (0.02, 0, 0.01)
        inc = rel(truth_path[k - 1], truth_path[k])
        c, s = math.cos(inc[2]), math.sin(inc[2])
        assert_increment(odo[k], [inc[0] + 0.02 * c, inc[1] + 0.02 * s, inc[2] + 0.01])
    for e, p in zip(truth, truth_path, strict=True):
        assert (e.x, e.y, e.theta) == pytest.approx(p)


def test_flaser_scans_reads_the_raw_scans(tmp_path):
    """The scans of a log as arrays (for experiments): every FLASER in order, its stamp and
    both pose fields; no-return (80 m and beyond) is NaN; ``limit`` stops early."""
    from fgslam.io.readers.carmen_records import flaser_scans

    f = tmp_path / "room.log"
    f.write_text(carmen_text(corrected=True))
    sc = flaser_scans(f)
    assert sc["ranges"].shape == (30, 180) and sc["pose"].shape == sc["odom"].shape == (30, 3)
    np.testing.assert_allclose(sc["t"], 1.0 + np.arange(30))
    np.testing.assert_allclose(sc["pose"], path(30), atol=1e-5)
    events = [e for e in open_log(f) if isinstance(e, LaserScan)]
    np.testing.assert_array_equal(np.isnan(sc["ranges"][0]), np.isnan(events[0].ranges))
    assert flaser_scans(f, limit=4)["t"].shape == (4,)


def test_carmen_raw_log(tmp_path):
    """A raw log: ODOM lines are cumulative odometry; no reference; increments recovered."""
    f = tmp_path / "raw.log.gz"
    with gzip.open(f, "wt") as g:
        g.write(carmen_text(corrected=False))
    log = open_log(f)
    assert log.mode == "raw" and log.reference_kind is None
    events = list(log)
    assert not any(isinstance(e, TruthPose) for e in events)
    odo = odometry_between_scans(events, log.config)
    truth_path = path(30)
    inc = rel(truth_path[3], truth_path[4])
    c, s = math.cos(inc[2]), math.sin(inc[2])
    assert_increment(odo[4], [inc[0] + 0.02 * c, inc[1] + 0.02 * s, inc[2] + 0.01])


def test_carmen_backwards_scan_is_dropped_and_its_motion_carried(tmp_path):
    """Scan 10 stamped 0.5 s before scan 9 (within the tolerance): counted, skipped, never
    reordered; the odometry to the next scan covers both intervals, so the odometry path is
    not broken."""
    f = tmp_path / "back.log"
    f.write_text(carmen_text(stamp=lambda k: 1.0 + k if k != 10 else 9.5))
    log = open_log(f)
    events = list(log)
    assert log.problems.backwards == Counter({"FLASER": 1})
    times = [e.t for e in events]
    assert times == sorted(times)
    scans = [e for e in events if isinstance(e, LaserScan)]
    assert len(scans) == 29 and 9.5 not in [s.t for s in scans]
    odo = odometry_between_scans(events, log.config)
    tp = path(30)
    # scan index 9 in the events is log scan 11: motion from scan 9 to 11 (two errors)
    two = relative(tp[9], tp[11])
    assert np.hypot(*(odo[10][:2] - two[:2])) < 0.06
    assert odo[10][2] == pytest.approx(two[2] + 0.02, abs=2e-3)


def test_carmen_bad_records(tmp_path):
    """An unknown record is counted; a malformed FLASER stops a strict read with the file
    and line, and is skipped and counted in tolerant mode."""
    f = tmp_path / "bad.log"
    f.write_text(carmen_text(extra={3: "RAWLASER1 1 2 3", 7: "FLASER 180 1.0 2.0"}))
    with pytest.raises(ReaderError, match=r"bad\.log:\d+: FLASER: expected 191 fields"):
        list(open_log(f))
    log = open_log(f, tolerant=True)
    scans = sum(isinstance(e, LaserScan) for e in log)
    assert scans == 30
    assert log.problems.skipped_by_reason["bad FLASER record"] == 1
    assert log.problems.skipped_by_reason["unknown record RAWLASER1"] == 1
    assert "bad.log" in log.problems.messages[0]


@pytest.mark.parametrize("damage", ["truncate", "corrupt"])
def test_carmen_damaged_gzip(tmp_path, damage):
    data = gzip.compress(carmen_text().encode())
    if damage == "truncate":
        data = data[: len(data) * 2 // 3]
    else:
        data = data[:200] + bytes(b ^ 0x55 for b in data[200:400]) + data[400:]
    f = tmp_path / "damaged.log.gz"
    f.write_bytes(data)
    with pytest.raises(ReaderError, match="corrupt or truncated gzip data"):
        list(open_log(f, format="carmen"))


def test_unknown_format(tmp_path):
    f = tmp_path / "x.txt"
    f.write_text("hello world\n")
    with pytest.raises(ReaderError, match="unknown log format"):
        open_log(f)
    with pytest.raises(ReaderError, match="no such file"):
        open_log(tmp_path / "missing.log")


@settings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.sampled_from(
                [
                    "FLASER",
                    "FLASER 2 1 2",
                    "FLASER 2 1 2 0 0 0 0 0 0 1.0 h 1.0",
                    "FLASER -1",
                    "FLASER 2 1 nan 0 0 0 0 0 0 1.0 h 1.0",
                    "ODOM 0 0 0 0 0 0 1.0 h 1.0",
                    "ODOM 1 2",
                    "ROBOTLASER1 0 -1.5 3.1 0.01 80 0.01 0 2 1 1 0",
                    "PARAM",
                    "TRUEPOS 1 2 3 4 5 6 7 h 7",
                    "#",
                ]
            ),
            st.text(max_size=40),
        ),
        max_size=12,
    ),
    st.booleans(),
)
def test_carmen_parser_fuzz(tmp_path_factory, lines, tolerant):
    """Whatever the text, the CARMEN reader raises nothing but ReaderError."""
    f = tmp_path_factory.mktemp("fuzz") / "f.log"
    f.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
    try:
        for _ in CarmenLog(f, tolerant=tolerant):
            pass
    except ReaderError:
        pass


# ------------------------------------------------------------------ CARMEN, real data


@needs[INTEL]
def test_intel_odometry_rule_holds_on_the_data():
    """The ODOM lines between two scans restart from the corrected pose of the first scan:
    the first of them lies within a few mm of P_{k-1} (median), not of the ODOM line before
    scan k-1 (median 5 cm away: the correction), so inverse(P_{k-1}) * ODOM_before_k is the
    raw odometry increment."""
    d = odometry_check(INTEL)
    norm = lambda v: np.hypot(v[:, 0], v[:, 1])
    assert len(d["increment"]) == 909
    assert np.median(norm(d["first_step"])) < 0.01
    assert np.median(norm(d["jump"])) > 0.03
    assert np.median(norm(d["increment"])) > 0.5  # scans are ~0.66 m apart
    # and the increments agree with the corrected motion better than the other reading
    e = norm(d["increment"] - d["corrected"])
    g = norm(d["global"] - d["corrected"])
    assert np.median(e) < 0.06 and np.median(e) < np.median(g)


@needs[INTEL]
def test_intel_reader():
    log = open_log(INTEL)
    assert log.mode == "corrected" and log.config.laser.n_beams == 180
    events = list(log)
    kinds = Counter(type(e).__name__ for e in events)
    assert kinds["LaserScan"] == kinds["TruthPose"] == 906  # 910 scans, 4 stamped backwards
    # 4 scans and 1249 of 13 700 ODOM lines stamped before the last delivered event, 150
    # ODOM lines stamped after the scan that follows them: counted, their motion carried
    # (the 910 repeats of the corrected pose after each scan are not odometry, whatever
    # their stamp: 68 of them carry junk stamps like 1e-42 instead of 0)
    assert log.problems.backwards == Counter(
        {"FLASER": 4, "ODOM": 1249, "ODOM after its scan": 150}
    )
    assert len(log._repeats) == 910
    assert log.meta["timestamps"]["used"] == "ipc" and not log.meta["timestamps"]["defects"]
    assert log.problems.summary()["odometry"]["implausible"] == 0
    assert log.problems.skipped_by_reason == Counter({"unknown record NEFF": 910})
    times = [e.t for e in events]
    assert times == sorted(times)
    # the odometry integrated between scans (the ODOM lines' path, sample by sample) ends
    # where the rule's increment does: heading exactly, position to ~1 mm (median; up to
    # ~1 cm where an ODOM line's own chord is bent), over the scans before the first dropped one
    d = odometry_check(INTEL)["increment"]
    odo = odometry_between_scans(events, log.config)
    dth = np.remainder(odo[1:251, 2] - d[:250, 2] + math.pi, 2 * math.pi) - math.pi
    assert np.abs(dth).max() < 2e-4
    e = np.hypot(*(odo[1:251, :2] - d[:250, :2]).T)
    assert np.median(e) < 0.003 and e.max() < 0.02


@needs[FREIBURG]
def test_freiburg_reader():
    log = open_log(FREIBURG)
    assert log.config.laser.n_beams == 360
    n = sum(isinstance(e, LaserScan) for e in log)
    # the ODOM lines stamped outside the surrounding scans are repeats of the corrected pose
    # (not odometry): counted in the metadata, no odometry goes backwards
    assert n == 4791 and log.problems.backwards == Counter()
    ts = log.meta["timestamps"]
    assert ts["used"] == "ipc" and ts["repeat_lines"] == 4791
    assert ts["repeat_lines_not_stamped_0"] > 0
    d = odometry_check(FREIBURG)
    e = np.hypot(*(d["increment"] - d["corrected"])[:, :2].T)
    g = np.hypot(*(d["global"] - d["corrected"])[:, :2].T)
    assert np.median(e) < np.median(g)


# ------------------------------------------------------------------ Victoria Park


@needs[VICTORIA]
def test_victoria_park_file():
    vp = read_victoria(VICTORIA)
    assert len(vp.steps) == 6968 and vp.n_sightings == 3640 and len(vp.landmarks) == 151
    assert vp.steps[-1].j == 7119 and not vp.problems.skipped
    assert sniff_format(VICTORIA) == "victoria"
    with pytest.raises(ReaderError, match="Victoria Park"):
        open_log(VICTORIA)


def test_victoria_bad_input(tmp_path):
    f = tmp_path / "vp.txt"
    f.write_text(
        "ODOMETRY 0 1 0.1 0 0 0.01 0 0 0.01 0 0.01\n"
        "LANDMARK 1 2 3.0 4.0 0.4 0 0.4\n"
        "ODOMETRY 5 6 0.1 0 0 0.01 0 0 0.01 0 0.01\n"
        "FOO 1 2\n"
        "ODOMETRY 1 3 0.1 0 0 0.01 0 0 0.01 0 -0.01\n"
    )
    with pytest.raises(ReaderError, match=r"vp\.txt:5: ODOMETRY: covariance not positive"):
        read_victoria(f)
    vp = read_victoria(f, tolerant=True)
    assert len(vp.steps) == 1 and vp.n_sightings == 1
    assert vp.problems.backwards["ODOMETRY chain broken"] == 1
    assert vp.problems.skipped_by_reason["unknown record FOO"] == 1
    assert vp.problems.skipped_by_reason["bad ODOMETRY record"] == 1


def test_bearing_range_covariance_by_jacobian():
    """(3, 4) with an isotropic 0.25 m^2: range variance 0.25, bearing variance 0.25 / 25."""
    z, c = to_bearing_range(np.array([3.0, 4.0]), np.eye(2) * 0.25)
    assert z == pytest.approx([math.atan2(4, 3), 5.0])
    assert c == pytest.approx(np.diag([0.01, 0.25]))
    # anisotropic: variance only along x at (0, 2) is all bearing: (dphi/dx)^2 = 1/4
    z, c = to_bearing_range(np.array([0.0, 2.0]), np.diag([1.0, 0.0]))
    assert c == pytest.approx(np.diag([0.25, 0.0]))


@settings(max_examples=150, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.sampled_from(
                [
                    "ODOMETRY 0 1 0.1 0 0 0.01 0 0 0.01 0 0.01",
                    "ODOMETRY 1 2 0.1 0 0 1 2 3 4 5 6",
                    "ODOMETRY 1 x",
                    "LANDMARK 1 5 0 0 1 0 1",
                    "LANDMARK 0 5 1 1 1 0 1",
                    "LANDMARK 0 5 1 1 inf 0 1",
                ]
            ),
            st.text(max_size=40),
        ),
        max_size=10,
    ),
    st.booleans(),
)
def test_victoria_parser_fuzz(tmp_path_factory, lines, tolerant):
    f = tmp_path_factory.mktemp("fuzz") / "vp.txt"
    f.write_text("\n".join(lines), encoding="utf-8", errors="surrogatepass")
    try:
        read_victoria(f, tolerant=tolerant)
    except ReaderError:
        pass


# ------------------------------------------------------------------ ROS bags


@pytest.fixture(params=["ros1", "ros2"])
def bag(request, tmp_path):
    pytest.importorskip("rosbags")
    p = tmp_path / ("run.bag" if request.param == "ros1" else "run_ros2")
    write_bag(p, ros1=request.param == "ros1", backwards_scan=5)
    return p


def test_ros_bag_round_trip(bag):
    assert sniff_format(bag) == "ros"
    log = open_log(bag, range_topics=["/sonar"])
    cfg = log.config
    assert cfg.laser.n_beams == 181 and cfg.laser.fov_deg == pytest.approx(180.0)
    assert [a.name for a in cfg.sonar.arrays] == ["/sonar"]
    events = list(log)
    kinds = Counter(type(e).__name__ for e in events)
    assert kinds["LaserScan"] == 9 and kinds["SonarReading"] == 10  # scan 5 went backwards
    assert log.problems.backwards == Counter({"/scan": 1})
    times = [e.t for e in events]
    assert times == sorted(times)
    scan = next(e for e in events if isinstance(e, LaserScan))
    assert np.isnan(scan.ranges[:3]).all() and scan.ranges[3] == pytest.approx(2.0)
    sonar = [e for e in events if isinstance(e, SonarReading)]
    assert sonar[0].echoes[0].kind == "plane" and sonar[0].echoes[0].range == pytest.approx(1.5)
    assert sonar[1].echoes == ()  # 9 m: beyond max_range
    # odometry: 19 increments of a 5 cm chord turning 0.02 rad
    o = cfg.odometry
    odo = [e for e in events if isinstance(e, OdometryEvent)]
    p = integrate_poses(
        [e.ticks_right * o.metres_per_tick_right for e in odo],
        [e.ticks_left * o.metres_per_tick_left for e in odo],
        o.wheelbase,
    )[-1]
    x = sum(0.05 * math.cos(0.02 * j + 0.01) for j in range(19))
    y = sum(0.05 * math.sin(0.02 * j + 0.01) for j in range(19))
    assert p == pytest.approx([x, y, 0.38], abs=5e-4)


def test_ros_bag_missing_topics(bag):
    with pytest.raises(ReaderError, match=r"no topic /laser; the bag has: /odom \(nav_msgs"):
        open_log(bag, scan_topic="/laser")
    with pytest.raises(ReaderError, match="is sensor_msgs/msg/Range, expected"):
        open_log(bag, scan_topic="/sonar")


def test_ros_bag_without_odometry(tmp_path):
    pytest.importorskip("rosbags")
    p = tmp_path / "noodom"
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(p, version=8) as w:
        w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
    with pytest.raises(ReaderError, match=r"no sensor_msgs/msg/LaserScan topic.*/chatter"):
        open_log(p)


def test_ros_bag_convert_command(bag, tmp_path, capsys):
    from fgslam.cli import main
    from fgslam.io.logfile import read_log

    out = tmp_path / "bag.log.gz"
    assert main(["convert", str(bag), "--range-topic", "/sonar", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "9 LaserScan" in text and "10 SonarReading" in text and "'/scan': 1" in text
    header, events = read_log(out)
    assert header.meta["scan_topic"] == "/scan" and len(header.config.sonar.arrays) == 1
    assert sum(isinstance(e, LaserScan) for e in events) == 9
    assert main(["convert", str(bag), "--odom-topic", "/nope", "--out", str(out)]) == 2
    assert "the bag has: /odom" in capsys.readouterr().err


def test_carmen_robotlaser1(tmp_path):
    """ROBOTLASER1: field of view, start angle and the laser's mount (laser pose relative to
    the robot pose) from the record; a raw log, odometry from ODOM lines."""
    n = 91
    lines = []
    for k in range(3):
        t = 1.0 + k
        x = 0.1 * k
        ranges = " ".join(["2.5"] * n)
        lines.append(f"ODOM {x} 0 0 0 0 0 {t} h {t}")
        lines.append(
            f"ROBOTLASER1 0 -0.785398 1.570796 0.017453 30 0.01 0 {n} {ranges} 2 7 8 "
            f"{x + 0.2} 0.05 0.1 {x} 0 0 0.1 0 0.5 0.3 1e6 {t} h {t}"
        )
    f = tmp_path / "rl.log"
    f.write_text("\n".join(lines) + "\n")
    log = open_log(f)
    assert log.mode == "raw"
    laser = log.config.laser
    assert laser.n_beams == n and laser.fov_deg == pytest.approx(90.0, abs=1e-4)
    assert (laser.mount.x, laser.mount.y) == pytest.approx((0.2, 0.05))
    assert laser.mount.yaw_deg == pytest.approx(math.degrees(0.1), abs=1e-4)
    events = list(log)
    scans = [e for e in events if isinstance(e, LaserScan)]
    assert [s.t for s in scans] == [1.0, 2.0, 3.0]
    assert odometry_between_scans(events, log.config)[2] == pytest.approx([0.1, 0, 0], abs=2e-4)
    f.write_text(lines[1][:-20] + "\n")
    with pytest.raises(ReaderError, match="ROBOTLASER1"):
        list(open_log(f, format="carmen"))


@needs[INTEL]
def test_intel_scans_overlap_when_placed_with_the_reference_poses():
    """The derived laser geometry is right: consecutive scans placed with the corrected poses
    fall on each other (median nearest-point distance ~4 cm), mirrored bearings do not."""
    from scipy.spatial import cKDTree

    log = open_log(INTEL)
    scans, poses = [], []
    for e in log:
        if isinstance(e, TruthPose):
            poses.append((e.x, e.y, e.theta))
        elif isinstance(e, LaserScan):
            scans.append(e.ranges)
    phi = log.config.laser.bearings

    def points(k, sign):
        r, (x, y, th) = scans[k], poses[k]
        ok = np.isfinite(r) & (r < 20)
        a = th + sign * phi[ok]
        return np.column_stack([x + r[ok] * np.cos(a), y + r[ok] * np.sin(a)])

    def spread(sign):
        d = [
            np.median(cKDTree(points(k + 1, sign)).query(points(k, sign))[0])
            for k in range(100, 880, 37)
        ]
        return float(np.median(d))

    assert spread(1) < 0.08 and spread(-1) > 3 * spread(1)
