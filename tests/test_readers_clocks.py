"""The clock checks of native fgslam logs and ROS bags (docs/readers.md, "Timestamps: never
silently wrong"): every defect on a small synthetic log or bag written here, with the same
rules as CARMEN's (fgslam.io.readers.sanity; CARMEN's cases are in test_readers_sanity.py)."""

from __future__ import annotations

import gzip
import math
import os
import threading

import numpy as np
import pytest
from readers_helpers import write_native

from fgslam.cli import main
from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.formats import open_log
from fgslam.io.logfile import LogReader
from fgslam.io.logrecords import LogFormatError
from fgslam.io.readers.sanity import INDEX_PERIOD, common_clock

UNIX = 1.7e9  # a UNIX-time clock (an online recording, a converted CARMEN log)


def native(tmp_path, name="x.log", **kw):
    path = tmp_path / name
    write_native(path, **kw)
    return path


def record_lines(path, letter: str) -> list[int]:
    """Line numbers (from 1) of the records of one tag."""
    text = path.read_text().splitlines()
    return [i + 1 for i, ln in enumerate(text) if ln.startswith(letter + " ")]


def by_type(events):
    out: dict[type, list] = {OdometryEvent: [], LaserScan: [], SonarReading: [], TruthPose: []}
    for e in events:
        out[type(e)].append(e)
    return out


def ticks(events) -> tuple[int, int]:
    odo = [e for e in events if isinstance(e, OdometryEvent)]
    return sum(e.ticks_right for e in odo), sum(e.ticks_left for e in odo)


# -- native logs ------------------------------------------------------------------------------


def test_native_sound_log_from_zero_is_read_unchanged(tmp_path):
    """A simulator-like log whose clock starts at exactly 0: sound (a 0 is junk only on a
    UNIX clock), every record delivered as the unchecked reader delivers it, the check
    recorded in the summary (report.json's "reader")."""
    path = native(tmp_path)
    log = open_log(path)
    events = list(log)
    with LogReader(path) as plain:  # the format-level reader: no check
        assert plain.clock_record is None and "timestamps" not in plain.summary()
        assert [(type(e), e.t) for e in plain] == [(type(e), e.t) for e in events]
    assert events[0].t == 0.0
    rec = log.summary()["timestamps"]
    assert rec == {
        "requested": "auto",
        "defects": {},
        "used": "log",
        "clock": "log (stamps, sound)",
        "sporadic_bad_stamps": {},
        "unix_time": False,
    }


def test_native_quantised_stamps_are_refused_and_index_runs_them(tmp_path):
    """Every stamp written with 6 significant digits (1.13486e+09): refused naming the
    defect and the first scan sharing its predecessor's stamp; --timestamps index stamps
    scan k at k * 0.2 s, spreads the other records between the scans, and says so."""
    six = lambda kind, k, t: float(f"{1.13486e9 + t:.6g}")
    path = native(tmp_path, stamp=six)
    second_scan = record_lines(path, "L")[1]
    with pytest.raises(
        LogFormatError,
        match=rf"x\.log: no usable timestamps \(stamps: laser stamps quantised \(30 of 30 "
        rf"scans share a stamp, 1 distinct values; first at line {second_scan}: "
        r"1\.13486e\+09\)\); choose with --timestamps index\|log",
    ):
        open_log(path, strict=True)
    log = open_log(path, timestamps="index")
    events = list(log)
    ev = by_type(events)
    assert [e.t for e in ev[LaserScan]] == pytest.approx(INDEX_PERIOD * np.arange(1, 31))
    assert [e.t for e in events] == sorted(e.t for e in events)
    assert len(ev[OdometryEvent]) == 120 and len(ev[TruthPose]) == 30
    assert ev[OdometryEvent][0].t == pytest.approx(INDEX_PERIOD / 7)  # 6 records before scan 1
    rec = log.summary()["timestamps"]
    assert rec["used"] == "index" and rec["index_period_s"] == INDEX_PERIOD
    assert "quantised" in rec["defects"]["log"][0]


def test_native_odometry_stamped_zero(tmp_path):
    """Odometry all stamped 0 (a simulator clock: 0 itself is a time there, but not for
    every record): refused naming the stream and its first line."""
    path = native(tmp_path, stamp=lambda kind, k, t: 0.0 if kind == "odometry" else t)
    first = record_lines(path, "O")[0]
    with pytest.raises(
        LogFormatError, match=rf"odometry stamped 0 \(120 of 120, first at line {first}\)"
    ):
        open_log(path, strict=True)
    assert ticks(open_log(path, timestamps="index")) == (360, 240)


def test_native_wrapped_stamps(tmp_path):
    """UNIX stamps wrapping at 2^32: refused naming the line where the clock wraps; run as
    they are when asked (--timestamps log), the choice and the defect recorded."""
    wrap = lambda kind, k, t: (2.0**32 - 3.01 + t) % 2.0**32
    path = native(tmp_path, stamp=wrap)
    lines = path.read_text().splitlines()
    first_wrapped = next(
        i + 1 for i, ln in enumerate(lines) if ln[:2] == "O " and float(ln.split()[1]) < 1e9
    )
    with pytest.raises(
        LogFormatError, match=rf"odometry stamps wrapped at 2\^32 \(line {first_wrapped}\)"
    ):
        open_log(path, strict=True)
    log = open_log(path, timestamps="log")
    assert len(by_type(log)[LaserScan]) == 30
    rec = log.summary()["timestamps"]
    assert rec["used"] == "log" and rec["requested"] == "log" and rec["unix_time"]
    assert "wrapped" in rec["defects"]["log"][0]


def test_native_junk_stamps_on_a_unix_clock(tmp_path):
    """On a UNIX clock, stamps like 3e-86 on 10 % of the sonar records: refused as junk,
    naming the first."""
    junk = lambda kind, k, t: 3e-86 if kind == "sonar" and k % 10 == 3 else UNIX + t
    path = native(tmp_path, stamp=junk)
    line = record_lines(path, "S")[3]
    with pytest.raises(
        LogFormatError, match=rf"sonar stamps junk \(3 of 30 bad, first at line {line}: 3e-86\)"
    ):
        open_log(path, strict=True)


def test_native_scan_back_beyond_the_tolerance(tmp_path):
    """One scan of 30 stamped 5.5 s before its predecessor (3 %, above the 2 % of sporadic
    stamps): refused naming its line; within a wider tolerance it is passed on as the
    format passes any record going backwards (and counted)."""
    back = lambda kind, k, t: t - 5.5 if (kind, k) == ("laser", 29) else t
    path = native(tmp_path, stamp=back)
    line = record_lines(path, "L")[29]
    with pytest.raises(
        LogFormatError,
        match=rf"laser stamps backwards by more than 2 s \(1 of 30 bad, first at line {line}",
    ):
        open_log(path, strict=True)
    log = open_log(path, backwards_tolerance=10.0)
    assert len(by_type(log)[LaserScan]) == 30 and log.backwards == {"laser": 1}


def test_native_sporadic_bad_stamps_are_dropped_and_odometry_carried(tmp_path):
    """A UNIX-clock log whose first odometry record is stamped 0 and one later odometry
    record 8 s back (2 of 240: sporadic): both dropped and counted, their ticks added to
    the next odometry record (the odometry path stays whole), the events in time order."""

    def stamp(kind, k, t):
        if kind == "odometry" and k == 0:
            return 0.0
        if kind == "odometry" and k == 150:
            return UNIX + t - 8.0
        return UNIX + t

    path = native(tmp_path, n=60, stamp=stamp)
    log = open_log(path)
    events = list(log)
    assert ticks(events) == (720, 480)  # as the clean log
    assert len(by_type(events)[OdometryEvent]) == 238
    assert [e.t for e in events] == sorted(e.t for e in events)
    rec = log.summary()["timestamps"]
    assert rec["used"] == "log" and rec["sporadic_bad_stamps"] == {"odometry": 2}
    assert rec["unix_time"] and log.backwards == {"odometry": 2}


def test_native_timestamps_option_values(tmp_path, capsys):
    """A CARMEN or ROS clock name for a native log is a one-line error; --timestamps index
    converts a log refused without it (with --strict), and the converted log keeps its
    META."""
    path = native(tmp_path, stamp=lambda kind, k, t: 0.0)
    with pytest.raises(LogFormatError, match="unknown --timestamps 'ipc' for an fgslam log"):
        open_log(path, timestamps="ipc")
    out = tmp_path / "o.log"
    assert main(["convert", str(path), "--strict", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "odometry stamped 0 (120 of 120" in err and err.count("\n") == 1
    assert main(["convert", str(path), "--timestamps", "index", "--out", str(out)]) == 0
    scans = [e for e in LogReader(out) if isinstance(e, LaserScan)]
    assert [e.t for e in scans] == pytest.approx(INDEX_PERIOD * np.arange(1, 31))


def test_native_damaged_gzip_still_streams_up_to_the_damage(tmp_path):
    """The clock check reads what it can of a truncated gzip log; the reading pass delivers
    the events before the damage and then raises, as without the check."""
    path = native(tmp_path, name="x.log.gz", t0=1.0)
    data = gzip.decompress(path.read_bytes())
    packed = gzip.compress(data, mtime=0)
    path.write_bytes(packed[: 3 * len(packed) // 4])  # past the header (the configuration)
    log = open_log(path, format="fgslam")
    got = []
    with pytest.raises(LogFormatError, match="corrupt or truncated gzip data"):
        for e in log:
            got.append(e)
    assert got and log.summary()["timestamps"]["used"] == "log"


def test_native_log_from_a_fifo_is_not_checked(tmp_path):
    """A log read from a FIFO cannot be read twice: read unchecked, and recorded so."""
    src = native(tmp_path, t0=1.0)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    feeder = threading.Thread(target=lambda: fifo.write_bytes(src.read_bytes()))
    feeder.start()
    try:
        log = open_log(fifo, format="fgslam")
        assert len(list(log)) == 30 * 7
    finally:
        feeder.join()
    rec = log.summary()["timestamps"]
    assert rec["checked"] is False and rec["used"] == "log"


def test_common_clock():
    assert common_clock({"/scan": [0.01, 0.02], "/odom": [0.0, 0.03]}) is None
    msg = common_clock({"/scan": [0.01, 0.02], "/odom": [1.7e9, 1.7e9], "/x": []})
    assert msg.startswith("/scan and /odom 1.7e+09 s apart against the record times")


# -- ROS bags ---------------------------------------------------------------------------------


@pytest.fixture(params=["ros1", "ros2"])
def ros1(request) -> bool:
    return request.param == "ros1"


def bag(tmp_path, ros1: bool, name: str = "b", **kw):
    from readers_helpers import write_bag

    path = tmp_path / (f"{name}.bag" if ros1 else name)
    write_bag(path, ros1, **kw)
    return path


def test_bag_sound_clocks_use_the_header_stamps(tmp_path, ros1):
    """Header stamps 0.01 s before the record times on every topic: header stamps used, no
    defect, nothing dropped."""
    path = bag(tmp_path, ros1, header=lambda topic, k, t: t - 0.01)
    log = open_log(path)
    ev = by_type(list(log))
    rec = log.meta["timestamps"]
    assert rec == {
        "requested": "auto",
        "defects": {},
        "used": "header",
        "clock": "header (header stamps, sound)",
        "sporadic_bad_stamps": {},
    }
    assert len(ev[LaserScan]) == 10 and ev[LaserScan][0].t == pytest.approx(1.09)


def test_bag_unset_header_stamps_use_the_record_times(tmp_path, ros1):
    """Header stamps all 0 (unset): named per topic, the record times used."""
    log = open_log(bag(tmp_path, ros1, zero_stamps=True))
    rec = log.meta["timestamps"]
    assert rec["used"] == "bag"
    assert rec["defects"]["header"][0] == "/scan stamped 0 (10 of 10, first at message 1)"
    assert len(by_type(log)[LaserScan]) == 10


def test_bag_quantised_header_stamps(tmp_path, ros1):
    """Scan header stamps written in whole seconds (scans share them): the record times are
    used, and the defect names the topic and the first message sharing its predecessor's
    stamp."""
    path = bag(tmp_path, ros1, header=lambda topic, k, t: math.floor(t) if topic == "/scan" else t)
    log = open_log(path)
    rec = log.meta["timestamps"]
    assert rec["used"] == "bag"
    assert rec["defects"]["header"][0].startswith(
        "/scan stamps quantised (9 of 10 scans share a stamp, 2 distinct values; first at "
        "message 2: 1)"
    )
    scans = by_type(log)[LaserScan]
    assert [e.t for e in scans] == pytest.approx(1.0 + 0.1 * np.arange(1, 20, 2))


def test_bag_negative_header_stamps_are_junk(tmp_path, ros1):
    """Header stamps 2 s early on /odom, so that its first ten are negative (an int32
    second overflowing, a clock offset gone wrong): junk (half of them), named with the
    topic and the first message; the record times are used."""
    early = lambda topic, k, t: t - 2.0 if topic == "/odom" else t
    log = open_log(bag(tmp_path, ros1, header=early, with_range=False))
    rec = log.meta["timestamps"]
    assert rec["used"] == "bag"
    assert rec["defects"]["header"] == ["/odom stamps junk (11 of 20 bad, first at message 1: -1)"]


def test_bag_topics_on_different_header_clocks(tmp_path, ros1):
    """/scan stamped in simulated time (from 1 s), /odom and /sonar in UNIX time: each
    topic's header stamps look sound alone, but they are not one clock (every scan would
    be 1.7e9 s "late" against the odometry and dropped); the record times are used."""
    path = bag(
        tmp_path,
        ros1,
        header=lambda topic, k, t: t if topic == "/scan" else UNIX + t,
        record=lambda topic, k, t: UNIX + t,
    )
    log = open_log(path)
    rec = log.meta["timestamps"]
    assert rec["used"] == "bag"
    (defect,) = rec["defects"]["header"]
    assert defect.startswith("header stamps of /odom and /scan 1.7e+09 s apart against the record")
    ev = by_type(list(log))
    assert len(ev[LaserScan]) == 10 and not log.problems.backwards


def test_bag_without_a_usable_clock_is_refused_naming_topic_and_defect(tmp_path, ros1, capsys):
    """Header stamps unset and record times in whole seconds: a one-line error naming each
    clock's first defect and its topic; --timestamps bag runs it as asked."""
    path = bag(tmp_path, ros1, zero_stamps=True, record=lambda topic, k, t: float(math.floor(t)))
    name = path.name
    with pytest.raises(Exception) as err:
        open_log(path)
    msg = str(err.value)
    assert msg.endswith(
        f"{name}: no usable timestamps (header stamps: /scan stamped 0 (10 of 10, first at "
        "message 1); record times: /scan stamps quantised (9 of 10 scans share a stamp, 2 "
        "distinct values; first at message 2: 1)); choose with --timestamps header|bag"
    )
    out = tmp_path / "o.log"
    assert main(["convert", str(path), "--out", str(out)]) == 2
    err_text = capsys.readouterr().err
    assert err_text.count("\n") == 1 and "no usable timestamps" in err_text
    assert main(["convert", str(path), "--timestamps", "bag", "--out", str(out)]) == 0
    log = open_log(path, timestamps="bag")
    assert log.meta["timestamps"]["used"] == "bag" and log.meta["timestamps"]["requested"] == "bag"
    with pytest.raises(Exception, match="unknown --timestamps 'index' for a bag"):
        open_log(path, timestamps="index")


def test_bag_header_stamps_going_back_beyond_the_tolerance(tmp_path, ros1):
    """Every fourth odometry header stamp 5 s back (25 %): named with the topic and the
    first message; the record times are used."""
    back = lambda topic, k, t: UNIX + t - (5.0 if topic == "/odom" and k % 4 == 3 else 0.0)
    path = bag(tmp_path, ros1, header=back, record=lambda topic, k, t: UNIX + t)
    log = open_log(path)
    rec = log.meta["timestamps"]
    assert rec["used"] == "bag"
    assert rec["defects"]["header"][0].startswith(
        "/odom stamps backwards by more than 2 s (5 of 20 bad, first at message 4: 1.7e+09)"
    )
    assert len(by_type(log)[LaserScan]) == 10


def test_bag_sporadic_bad_header_stamps_are_dropped_and_odometry_carried(tmp_path, ros1):
    """In a bag of 60 scans, one odometry header stamp 0 and one scan 5 s back (under 2 % of
    each topic): the header stamps stay in use; the scan is dropped, the odometry message's
    motion carried into the next one (the same ticks as the clean bag), both counted."""

    def header(topic, k, t):
        if (topic, k) == ("/odom", 40):
            return 0.0
        if (topic, k) == ("/scan", 30):
            return t - 5.0
        return t

    log = open_log(bag(tmp_path, ros1, n=60, header=header, with_range=False))
    events = list(log)
    clean = list(open_log(bag(tmp_path, ros1, name="c", n=60, with_range=False)))
    assert ticks(events) == ticks(clean)
    assert len(by_type(events)[LaserScan]) == 59
    assert [e.t for e in events] == sorted(e.t for e in events)
    rec = log.meta["timestamps"]
    assert rec["used"] == "header"
    assert rec["sporadic_bad_stamps"] == {"/scan": 1, "/odom": 1}
    assert log.problems.backwards == {"/scan": 1, "/odom": 1}
