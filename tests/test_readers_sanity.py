"""Timestamps and odometry of foreign logs: every defect of docs/readers.md on a small
synthetic CARMEN log written here (fgslam.io.readers.sanity, fgslam.io.readers.carmen)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from readers_helpers import carmen_text, odometry_at

from fgslam.cli import main
from fgslam.errors import ReaderError
from fgslam.events import LaserScan, OdometryEvent, TruthPose
from fgslam.io.formats import open_log
from fgslam.io.readers.carmen import CarmenLog
from fgslam.io.readers.odometry import MAX_SAMPLES
from fgslam.io.readers.sanity import INDEX_PERIOD, OdometryLimits, implausible, index_stamps
from fgslam.sim.scenes import PAPER

TIMED = ("FLASER", "ODOM")


def restamp(text: str, ipc=None, logger=None, repeat=None, corrected: bool = False) -> str:
    """Rewrite the stamps of the timed records (k-th scan or ODOM line, repeats of corrected
    logs excluded): ``ipc(kind, k, t)`` / ``logger(kind, k, t)`` give the new value (a
    string or a float); ``repeat(k)`` the stamp of the k-th repeat line."""
    out = []
    counts = {"FLASER": 0, "ODOM": 0, "repeat": 0}
    prev = None
    for line in text.splitlines():
        f = line.split()
        if f and f[0] in TIMED:
            kind = f[0]
            if kind == "ODOM" and prev == "FLASER" and corrected:
                kind = "repeat"
            k = counts[kind]
            counts[kind] += 1
            t = float(f[-3])
            if kind == "repeat":
                if repeat is not None:
                    f[-3] = f[-1] = str(repeat(k))
            else:
                if ipc is not None:
                    f[-3] = str(ipc(kind, k, t))
                if logger is not None:
                    f[-1] = str(logger(kind, k, t))
            line = " ".join(f)
        if f and f[0] in TIMED:
            prev = f[0]
        out.append(line)
    return "\n".join(out) + "\n"


def write(tmp_path, text: str, name: str = "x.log"):
    f = tmp_path / name
    f.write_text(text)
    return f


def scans_and_odometry(log):
    ev = list(log)
    return (
        [e for e in ev if isinstance(e, LaserScan)],
        [e for e in ev if isinstance(e, OdometryEvent)],
        ev,
    )


def test_index_stamps():
    assert index_stamps(["odometry", "scan", "odometry", "odometry", "scan"]) == pytest.approx(
        [0.1, 0.2, 0.2 + 0.2 / 3, 0.2 + 0.4 / 3, 0.4]
    )
    assert INDEX_PERIOD == 0.2


def test_coarse_stamps_are_refused_naming_the_line(tmp_path):
    """Scan and odometry stamps with 6 significant digits (1.13486e+09: two values over the
    run) in both fields: a one-line error naming the defect and its line; --timestamps
    index runs it with scans 0.2 s apart, and the metadata says so."""
    six = lambda kind, k, t: f"{1.13486e9 + 0.4 * t:.6g}"
    f = write(tmp_path, restamp(carmen_text(corrected=False), ipc=six, logger=six))
    with pytest.raises(
        ReaderError,
        match=r"x\.log: no usable timestamps \(ipc field: scan "
        r"stamps quantised .* first at line \d+",
    ):
        open_log(f, strict=True)
    log = open_log(f, timestamps="index")
    scans, _odo, ev = scans_and_odometry(log)
    assert len(scans) == 30
    assert [s.t for s in scans] == pytest.approx(INDEX_PERIOD * np.arange(1, 31))
    assert [e.t for e in ev] == sorted(e.t for e in ev)
    assert log.meta["timestamps"]["used"] == "index"
    assert "quantised" in log.meta["timestamps"]["defects"]["ipc"][0]


def test_odometry_stamped_zero_uses_the_logger_field(tmp_path):
    """ODOM lines stamped 0 in the ipc field but sound in the logger field: the logger field
    is used, the odometry covers the whole run and the metadata records why."""
    f = write(
        tmp_path,
        restamp(carmen_text(corrected=False), ipc=lambda kind, k, t: 0 if kind == "ODOM" else t),
    )
    log = open_log(f)
    scans, odo, _ = scans_and_odometry(log)
    assert log.clock == "logger" and len(scans) == 30
    assert odo[-1].t == pytest.approx(30.0) and len(odo) > 29
    rec = log.meta["timestamps"]
    assert rec["used"] == "logger" and "odometry stamped 0" in rec["defects"]["ipc"][0]
    assert log.problems.summary()["timestamps"] == rec  # into report.json's "reader"


def test_scans_stamped_zero_with_junk_repeats(tmp_path):
    """A corrected log whose scans are all stamped 0 in both fields and whose repeat lines
    carry junk stamps (3e-86): refused naming the scan defect; the repeats are still
    recognised (by repeating the scan's pose) and not taken for odometry."""
    text = restamp(
        carmen_text(corrected=True),
        ipc=lambda kind, k, t: 0 if kind == "FLASER" else t,
        logger=lambda kind, k, t: 0 if kind == "FLASER" else t,
        repeat=lambda k: 3e-86,
        corrected=True,
    )
    f = write(tmp_path, text)
    with pytest.raises(ReaderError, match=r"scan stamped 0 \(30 of 30, first at line \d+\)"):
        open_log(f, strict=True)
    log = open_log(f, timestamps="index")
    scans, _, ev = scans_and_odometry(log)
    assert len(scans) == 30 and len(log._repeats) == 30
    assert sum(isinstance(e, TruthPose) for e in ev) == 30
    assert log.meta["timestamps"]["repeat_lines_not_stamped_0"] == 30


def test_wrapped_stamps_use_the_other_field(tmp_path):
    """ipc stamps wrapping at 2^32: named; the sound logger field is used instead; when
    both wrap, refused naming the line where it wraps."""
    wrap = lambda kind, k, t: (4294967280.0 + t) % 2.0**32
    f = write(tmp_path, restamp(carmen_text(corrected=False), ipc=wrap))
    log = open_log(f)
    assert log.clock == "logger"
    assert "wrapped at 2^32" in log.meta["timestamps"]["defects"]["ipc"][0]
    assert len(scans_and_odometry(log)[0]) == 30
    f2 = write(tmp_path, restamp(carmen_text(corrected=False), ipc=wrap, logger=wrap), "w.log")
    with pytest.raises(ReaderError, match=r"wrapped at 2\^32 \(line \d+\)"):
        open_log(f2, strict=True)
    # forced: the user's choice is run, and recorded
    log = open_log(f2, timestamps="ipc")
    assert log.meta["timestamps"]["used"] == "ipc" and log.meta["timestamps"]["requested"]


def test_scan_going_back_beyond_the_tolerance(tmp_path):
    """A scan stamped 5.5 s before its predecessor (tolerance 2 s) in both fields: refused
    naming its line; within the tolerance it is dropped and counted (test_readers)."""
    f = write(tmp_path, carmen_text(stamp=lambda k: 1.0 + k if k != 10 else 4.5))
    lines = f.read_text().splitlines()
    bad = 1 + next(i for i, ln in enumerate(lines) if ln.startswith("FLASER") and " 4.5 h" in ln)
    with pytest.raises(ReaderError, match=rf"backwards by more than 2 s .* line {bad}: 4\.5\)"):
        open_log(f, strict=True)
    assert len(scans_and_odometry(open_log(f, backwards_tolerance=10.0))[0]) == 29


def test_sporadic_junk_stamps_are_counted_and_carried(tmp_path):
    """One ODOM line of 120 with a junk stamp (1e-42): sporadic, counted in the metadata,
    its motion carried into the next sample (the odometry path stays whole)."""
    n = 120
    text = restamp(
        carmen_text(corrected=False, n=n),
        ipc=lambda kind, k, t: 1e-42 if (kind, k) == ("ODOM", 50) else t,
        logger=lambda kind, k, t: 1e-42 if (kind, k) == ("ODOM", 50) else t,
    )
    log = open_log(write(tmp_path, text))
    scans, odo, ev = scans_and_odometry(log)
    assert len(scans) == n
    assert log.meta["timestamps"]["sporadic_bad_stamps"] == {"odometry": 1}
    assert log.problems.backwards["ODOM"] == 1
    assert [e.t for e in ev] == sorted(e.t for e in ev)
    clean = open_log(write(tmp_path, carmen_text(corrected=False, n=n), "clean.log"))
    o2 = [e for e in clean if isinstance(e, OdometryEvent)]
    total = lambda o: (sum(e.ticks_right for e in o), sum(e.ticks_left for e in o))
    assert total(odo) == total(o2)


@pytest.mark.parametrize("field", ["ipc", "pose"])
def test_huge_values_are_a_one_line_error(tmp_path, field):
    """A stamp of 1e308 (or a pose coordinate of 1e300): file, line and field named; in
    tolerant mode the record is skipped and counted."""
    text = carmen_text(corrected=False)
    lines = text.splitlines()
    i = next(i for i, ln in enumerate(lines) if ln.startswith("FLASER"))
    f = lines[i].split()
    if field == "ipc":
        f[-3] = "1e308"
        pattern = rf"x\.log:{i + 1}: FLASER: timestamp 1e\+308 out of range"
    else:
        f[-9] = "1e300"
        pattern = rf"x\.log:{i + 1}: FLASER: pose .* out of range"
    lines[i] = " ".join(f)
    path = write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(ReaderError, match=pattern):
        list(open_log(path))
    log = open_log(path, tolerant=True)
    assert len(scans_and_odometry(log)[0]) == 29
    assert log.problems.skipped_by_reason["bad FLASER record"] == 1


@pytest.mark.parametrize("jump", [1e10, 1e6])
def test_odometry_jump(tmp_path, jump):
    """A corrupt ODOM line 1e10 m away (the known hang: billions of virtual ticks) is out of
    any pose's range; one 1e6 m away is implausible motion: strict, an error naming the
    line; tolerant (the bad record), skipped and counted, the rest of the odometry intact
    (the same ticks as the clean log)."""
    text = carmen_text(corrected=False)
    lines = text.splitlines()
    i = [k for k, ln in enumerate(lines) if ln.startswith("ODOM")][12]
    f = lines[i].split()
    f[1] = repr(jump)
    lines[i] = " ".join(f)
    path = write(tmp_path, "\n".join(lines) + "\n")
    what = "ODOM: pose 1e\\+10 .* out of range" if jump > 1e7 else "implausible odometry: 1e\\+06 m"
    with pytest.raises(ReaderError, match=rf"x\.log:{i + 1}: {what}"):
        list(open_log(path, strict=True))
    log = open_log(path, tolerant=True)
    scans, odo, _ = scans_and_odometry(log)
    assert len(scans) == 30
    assert log.problems.skipped == 1  # the bad record (bad ODOM or implausible odometry)
    clean = [e for e in open_log(write(tmp_path, text, "c.log")) if isinstance(e, OdometryEvent)]
    assert sum(e.ticks_right for e in odo) == sum(e.ticks_right for e in clean)


def test_odometry_that_jumps_and_stays_is_rebased(tmp_path):
    """Odometry that jumps 100 m and continues from there (a reset): the first record is
    skipped, the following ones continue from the new origin (counted as rebased)."""
    text = carmen_text(corrected=False)
    lines = text.splitlines()
    idx = [k for k, ln in enumerate(lines) if ln.startswith("ODOM")]
    for k in idx[15:]:
        f = lines[k].split()
        f[1] = repr(float(f[1]) + 100.0)
        lines[k] = " ".join(f)
    log = open_log(write(tmp_path, "\n".join(lines) + "\n"), tolerant=True)
    scans, _odo, _ = scans_and_odometry(log)
    notes = log.problems.notes["odometry"]
    assert len(scans) == 30 and notes["implausible"] == 1 and notes["rebased"] == 1


def test_implausible_bounds():
    lim = OdometryLimits(max_speed=2.0, max_turn_rate=1.0)
    assert implausible((0.5, 0.0, 0.0), 0.2, lim) is None  # 0.5 m in 0.45 s of allowance
    assert "m/s" in implausible((1.0, 0.0, 0.0), 0.2, lim)
    assert "rad/s" in implausible((0.0, 0.0, 1.0), 0.2, lim)
    assert implausible((math.nan, 0.0, 0.0), 1.0, lim) is not None
    assert implausible((0.1, 0.0, 0.0), math.nan, lim) is None  # no dt: MIN_DT slack


def test_odometry_hole_is_counted_and_its_motion_stamped_at_its_end(tmp_path):
    """No ODOM line for scans 10..15 (6 s) while the scans keep coming: one hole, 6 s, and
    the motion over it comes in samples stamped after the hole (not spread back over scans
    already delivered: the events stay in time order)."""
    text = carmen_text(corrected=False)
    lines = text.splitlines()
    odom = [k for k, ln in enumerate(lines) if ln.startswith("ODOM")]
    keep = [ln for k, ln in enumerate(lines) if k not in odom[10:16]]
    log = open_log(write(tmp_path, "\n".join(keep) + "\n"))
    _scans, odo, ev = scans_and_odometry(log)
    notes = log.problems.notes["odometry"]
    assert notes["holes"] == 1 and notes["hole_seconds"] == pytest.approx(7.0)
    assert [e.t for e in ev] == sorted(e.t for e in ev)
    assert not [e for e in odo if 10.0 < e.t < 17.0]
    assert sum(e.t == 17.0 for e in odo) > 1  # the hole's motion, at its end


def test_cli_timestamps_option(tmp_path, capsys):
    """fgslam convert --timestamps index runs a log refused without it with --strict."""
    six = lambda kind, k, t: f"{1.13486e9 + 0.4 * t:.6g}"
    f = write(tmp_path, restamp(carmen_text(corrected=False), ipc=six, logger=six))
    assert main(["convert", str(f), "--strict", "--out", str(tmp_path / "o.log")]) == 2
    assert "no usable timestamps" in capsys.readouterr().err
    assert main(["convert", str(f), "--timestamps", "index", "--out", str(tmp_path / "o.log")]) == 0


FIELD = st.one_of(
    st.sampled_from(["1e308", "-1e308", "inf", "-inf", "nan", "1e10", "-1e10", "0", "3e-86"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-50, 50).map(repr),
)


@settings(max_examples=120, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.sampled_from(["ODOM", "FLASER", "TRUEPOS"]), st.lists(FIELD, min_size=9, max_size=9)
        ),
        min_size=1,
        max_size=10,
    ),
    st.booleans(),
)
def test_reader_fuzz_huge_infinite_nan_fields(tmp_path_factory, records, tolerant):
    """Records of the right shape with huge, infinite, NaN or junk fields: the reader raises
    nothing but ReaderError, and the number of events it produces is bounded (what made it
    hang was a jump of 1e10 m driven as billions of virtual ticks)."""
    lines = ["FLASER 3 1 1 1 0 0 0 0 0 0 1.0 h 1.0"]
    for tag, v in records:
        if tag == "ODOM":
            lines.append(f"ODOM {v[0]} {v[1]} {v[2]} 0 0 0 {v[3]} h {v[4]}")
        elif tag == "FLASER":
            lines.append(
                f"FLASER 3 {v[0]} {v[1]} 1 {v[2]} {v[3]} {v[4]} {v[5]} {v[6]} {v[7]} "
                f"{v[8]} h {v[8]}"
            )
        else:
            lines.append(f"TRUEPOS {v[0]} {v[1]} {v[2]} {v[3]} {v[4]} {v[5]} {v[6]} h {v[7]}")
    f = tmp_path_factory.mktemp("fuzz") / "f.log"
    f.write_text("\n".join(lines) + "\n")
    n = 0
    for timestamps in ("auto", "index"):
        try:
            for _ in CarmenLog(f, tolerant=tolerant, timestamps=timestamps):
                n += 1
                assert n < 4 * MAX_SAMPLES
        except ReaderError:
            pass


def test_odometry_hole_through_the_pipeline(tmp_path):
    """The 7 s hole of the synthetic log, run through SLAM (laser, EKF): the keyframes in it
    get the hole covariance (counted in the statistics, each second once), not zero motion
    with full confidence."""
    from fgslam.config import with_scanmatch
    from fgslam.slam.runner import run_slam

    text = carmen_text(corrected=False)
    lines = text.splitlines()
    odom = [k for k, ln in enumerate(lines) if ln.startswith("ODOM")]
    keep = [ln for k, ln in enumerate(lines) if k not in odom[10:16]]
    log = open_log(write(tmp_path, "\n".join(keep) + "\n"))
    res = run_slam(log, with_scanmatch(log.config, PAPER), "ekf", "laser")
    assert res.stats["odometry_hole_seconds"] == pytest.approx(7.0)
    assert res.stats["odometry_hole_intervals"] == 6


def test_warnings_for_inputs_with_almost_nothing(tmp_path, capsys):
    """A log whose odometry never moves, or with 3 scans: one-line warnings in the reader's
    summary (report.json's "reader") and on the console of fgslam run."""
    text = carmen_text(corrected=False, n=3, odo_error=(0.0, 0.0, 0.0))
    lines = []
    for ln in text.splitlines():  # freeze the odometry at the origin
        f = ln.split()
        if f and f[0] == "ODOM":
            f[1:4] = ["0", "0", "0"]
        lines.append(" ".join(f))
    f = write(tmp_path, "\n".join(lines) + "\n")
    log = open_log(f, mode="raw")
    list(log)
    w = log.problems.summary()["warnings"]
    assert any("only 3 laser scans" in x for x in w)
    assert any("never moves" in x for x in w)
    assert (
        main(
            [
                "run",
                str(f),
                "--carmen-mode",
                "raw",
                "--sensors",
                "laser",
                "--backend",
                "ekf",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    assert "warning: only 3 laser scans" in capsys.readouterr().out
    import json

    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert any("never moves" in x for x in rep["reader"]["warnings"])


@pytest.mark.parametrize("ros1", [True, False])
def test_ros_bag_unset_header_stamps_and_a_jump(tmp_path, ros1):
    """A bag whose header stamps are all 0: the record times are used (metadata says so);
    an odometry message 1e6 m off: strict, an error; tolerant, skipped and counted (as by
    default)."""
    from readers_helpers import write_bag

    path = tmp_path / ("z.bag" if ros1 else "z")
    write_bag(path, ros1, zero_stamps=True, with_range=False)
    log = open_log(path)
    scans, _, _ = scans_and_odometry(log)
    assert log.meta["timestamps"]["used"] == "bag" and len(scans) == 10
    assert [e.t for e in scans] == pytest.approx(1.0 + 0.1 * np.arange(1, 20, 2))
    path2 = tmp_path / ("j.bag" if ros1 else "j")
    write_bag(path2, ros1, with_range=False, jump=7)
    with pytest.raises(ReaderError, match="implausible odometry"):
        list(open_log(path2, strict=True))
    log = open_log(path2, tolerant=True)
    list(log)
    assert log.problems.notes["odometry"]["implausible"] >= 1


def _stale_log(tmp_path, odom_lines: bool, frozen: range, n: int = 30):
    """The room run as a raw log, scans 0.2 s apart, whose odometry repeats scan
    ``frozen.start - 1``'s pose over the scans ``frozen`` and catches up after them (in the
    ODOM lines and the FLASER odometry fields, or in the FLASER fields alone)."""
    from readers_helpers import path

    text = carmen_text(corrected=False, n=n, odo_error=(0.0, 0.0, 0.0), stamp=lambda k: 1 + 0.2 * k)
    out, k_scan, k_odom, held = [], 0, 0, None
    for ln in text.splitlines():
        f = ln.split()
        if f and f[0] == "ODOM":
            if not odom_lines:
                continue
            if k_odom == frozen.start - 1:
                held = f[1:4]
            if k_odom in frozen:
                f[1:4] = held
            k_odom += 1
        elif f and f[0] == "FLASER":
            nb = int(f[1])
            if k_scan == frozen.start - 1:
                held = f[2 + nb + 3 : 2 + nb + 6]
            if k_scan in frozen:
                f[2 + nb : 2 + nb + 6] = held + held
            k_scan += 1
        out.append(" ".join(f))
    return write(tmp_path, "\n".join(out) + "\n"), path(n)


def _odometry_at_scans(log):
    """The odometry pose (integrated from the delivered samples) at each delivered scan."""
    return odometry_at(log, log.config.odometry)


@pytest.mark.parametrize("odom_lines", [True, False])
def test_stale_odometry_is_spread_over_its_span(tmp_path, odom_lines):
    """Odometry that repeats its pose for 0.8 s while the robot drives and turns, then
    catches up (MIT CSAIL's FLASER fields do): the held scans come out among the catch-up's
    samples spread over the span, so the odometry at each scan of the span is near the
    truth (the old reading: no motion, then the whole of it in one scan interval, 0.4 m and
    9 deg off in the middle), the events stay in time order, and the span is counted."""
    f, truth = _stale_log(tmp_path, odom_lines, range(10, 14))
    (tmp_path / "clean").mkdir()
    log = open_log(f, mode="raw")
    ev = list(log)
    assert [e.t for e in ev] == sorted(e.t for e in ev)
    assert sum(isinstance(e, LaserScan) for e in ev) == len(truth)
    notes = log.problems.notes["odometry"]
    assert notes["stale_spans"] == 1 and notes["stale_seconds"] == pytest.approx(1.0)
    odo = _odometry_at_scans(open_log(f, mode="raw"))
    clean, _ = _stale_log(tmp_path / "clean", odom_lines, range(0))
    ref = _odometry_at_scans(open_log(clean, mode="raw"))  # the same drive, never frozen
    err = np.hypot(*(odo[:, :2] - ref[:, :2]).T)
    assert err.max() < 0.05, err.round(3)
    assert np.abs(odo[:, 2] - ref[:, 2]).max() < math.radians(1.0)
    assert np.allclose(odo[14:], ref[14:], atol=1e-3)  # caught up: the same from then on
    # not holding (stale = 0) is the old reading: far off in the span
    old = _odometry_at_scans(open_log(f, mode="raw", limits=OdometryLimits(stale=0.0)))
    assert np.hypot(*(old[:, :2] - ref[:, :2]).T).max() > 0.3


def test_a_stop_longer_than_the_stale_bound_is_not_spread(tmp_path):
    """Odometry that repeats for the last 4 s of the log (longer than OdometryLimits.stale)
    is a stop (or a hole), not stale: the held scans come out as they were (no motion over
    them), in order."""
    f, truth = _stale_log(tmp_path, True, range(10, 30))
    log = open_log(f, mode="raw")
    ev = list(log)
    assert [e.t for e in ev] == sorted(e.t for e in ev)
    assert log.problems.notes["odometry"]["stale_spans"] == 0
    assert OdometryLimits().stale < 4.0
    odo = _odometry_at_scans(open_log(f, mode="raw"))
    assert len(odo) == len(truth) and np.allclose(odo[10:], odo[9], atol=1e-4)
