"""The plausibility rules every input format shares (fgslam.io.readers.plausibility;
docs/readers.md, "Plausibility"): laser ranges outside the laser's range, scans with no valid
beam, odometry beyond the robot's limits, implausible truth, stamps out of order. Each case of
the fuzz campaign on the native log (negative ranges, scans without a valid beam, an odometry
record of 1e25 ticks, truth headings of 1e9 rad) on small synthetic logs written with the
project's log writer, the same rules on CARMEN logs; by default counted, warned once with the
count and the first record, listed in report.json; with --strict an error (exit status 2)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from readers_helpers import carmen_text

from fgslam.cli import main
from fgslam.config import load_config
from fgslam.errors import ReaderError
from fgslam.events import LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.formats import open_log
from fgslam.io.logwriter import LogWriter

N_BEAMS = 5
MAX_RANGE = 8.0


def write_native(path, n=30, scan=None, odometry=None, truth=None, stamp=None):
    """A native log of ``n`` scan periods of 0.2 s (four odometry records, a sonar and a truth
    record, then a 5-beam scan at 2 m; laser max_range 8 m); ``scan(k, ranges)``,
    ``odometry(k, ticks)``, ``truth(k, pose)`` change the k-th record of their kind (from 0),
    ``stamp(kind, k, t)`` its stamp."""
    cfg = load_config()
    cfg = dataclasses.replace(
        cfg, laser=dataclasses.replace(cfg.laser, n_beams=N_BEAMS, max_range=MAX_RANGE)
    )
    count = {"odometry": 0, "laser": 0, "truth": 0, "sonar": 0}

    def at(kind, t):
        k = count[kind]
        count[kind] += 1
        return k, float(stamp(kind, k, t)) if stamp else t

    with LogWriter(path, cfg, "synthetic") as w:
        for p in range(n):
            base = 0.2 * p
            for j in range(4):
                k, t = at("odometry", base + 0.05 * j)
                w.write(OdometryEvent(t, *(odometry(k, (3, 2)) if odometry else (3, 2))))
                if j == 1:
                    w.write(SonarReading(at("sonar", base + 0.07)[1], 0, 0.0, ()))
                if j == 2:
                    k, t = at("truth", base + 0.1)
                    pose = (0.01 * p, 0.0, 0.1)
                    w.write(TruthPose(t, *(truth(k, pose) if truth else pose)))
            k, t = at("laser", base + 0.15)
            r = np.full(N_BEAMS, 2.0)
            w.write(LaserScan(t, scan(k, r) if scan else r))
    return path


def lines_of(path, letter):
    """Line numbers (from 1) of the records of one tag."""
    text = path.read_text().splitlines()
    return [i + 1 for i, ln in enumerate(text) if ln.startswith(letter + " ")]


def read(path, **kw):
    log = open_log(path, **kw)
    events = list(log)
    summary = log.summary() if isinstance(log.problems, list) else log.problems.summary()
    return log, events, summary


def one_warning(summary, words):
    """The one warning line containing ``words`` (and no other mentioning them)."""
    found = [w for w in summary.get("warnings", []) if words in w]
    assert len(found) == 1, summary.get("warnings")
    return found[0]


def half_negative(k, r):
    return np.full_like(r, -1.5) if k % 2 else r


# -- native logs: the fuzz campaign's cases ----------------------------------------------------


def test_native_negative_ranges_are_no_return_counted_and_warned(tmp_path):
    """Half the scans at -1.5 m: those beams read as no return (NaN), 15 scans counted with
    their 75 beams and the first scan's line, one warning naming count and first record."""
    path = write_native(tmp_path / "x.log", scan=half_negative)
    _, events, summary = read(path)
    scans = [e for e in events if isinstance(e, LaserScan)]
    assert len(scans) == 30
    assert all(np.isnan(s.ranges).all() for s in scans[1::2])
    assert all((s.ranges == 2.0).all() for s in scans[0::2])
    first = lines_of(path, "L")[1]
    w = one_warning(summary, "ranges out of range")
    assert w.startswith("15 laser scans with ranges out of range (75 beams; first: ")
    assert f"x.log:{first}: " in w and "-1.5 m" in w and "(0, 8] m" in w
    assert "--strict" in w


def test_native_scans_without_a_valid_beam_are_counted_and_warned(tmp_path):
    """Scans whose every range is NaN: passed on, counted, one warning with the first line."""
    path = write_native(tmp_path / "x.log", scan=lambda k, r: r * np.nan if k >= 20 else r)
    _, events, summary = read(path)
    assert sum(isinstance(e, LaserScan) for e in events) == 30
    w = one_warning(summary, "no valid beam")
    assert w.startswith("10 laser scans with no valid beam (first: ")
    assert f"x.log:{lines_of(path, 'L')[20]}: " in w


@pytest.mark.parametrize("ticks", [10**25, 10**400], ids=["1e25", "1e400"])
def test_native_odometry_record_of_1e25_ticks_is_skipped(tmp_path, ticks):
    """One odometry record of 1e25 ticks (the EKF's "odometry alone 5.9e20 m"), or of more
    than a float holds: skipped and counted as implausible odometry (the jump dropped, every
    other record's ticks kept)."""
    path = write_native(tmp_path / "x.log", odometry=lambda k, t: (ticks, ticks) if k == 40 else t)
    _, events, summary = read(path)
    odo = [e for e in events if isinstance(e, OdometryEvent)]
    assert len(odo) == 119
    assert sum(e.ticks_right for e in odo) == 3 * 119
    assert summary["skipped_by_reason"] == {"implausible odometry": 1}
    w = one_warning(summary, "implausible odometry")
    assert w.startswith("1 implausible odometry record (first: ")
    assert f"x.log:{lines_of(path, 'O')[40]}: " in w


def test_native_odometry_turn_without_travel_is_implausible(tmp_path):
    """The rule holds the turn too: wheels 1e6 ticks apart in opposite directions (no
    travel, 1500 rad in 0.05 s) are skipped; a sharp but possible turn is not."""
    turn = {10: (10**6, -(10**6)), 20: (60, -60)}  # 1500 rad; 0.09 rad in 0.05 s
    path = write_native(tmp_path / "x.log", odometry=lambda k, t: turn.get(k, t))
    _, events, summary = read(path)
    assert summary["skipped_by_reason"] == {"implausible odometry": 1}
    assert (60, -60) in [
        (e.ticks_right, e.ticks_left) for e in events if isinstance(e, OdometryEvent)
    ]


def test_native_truth_heading_of_1e9_rad_is_skipped(tmp_path):
    """Truth poses with a heading of 1e9 rad (or 1e8 m away): skipped and counted."""

    def bad(k, pose):
        return {3: (pose[0], pose[1], 1e9), 7: (1e8, 0.0, 0.0)}.get(k, pose)

    path = write_native(tmp_path / "x.log", truth=bad)
    _, events, summary = read(path)
    truth = [e for e in events if isinstance(e, TruthPose)]
    assert len(truth) == 28 and max(abs(e.theta) for e in truth) == pytest.approx(0.1)
    assert summary["skipped_by_reason"] == {"implausible truth pose": 2}
    w = one_warning(summary, "truth pose")
    assert w.startswith("2 implausible truth poses (first: ")
    assert "heading 1e+09 rad" in w and f"x.log:{lines_of(path, 'T')[3]}: " in w


def test_native_stamps_out_of_order_are_passed_on_counted_and_warned(tmp_path):
    """A scan stamped 0.3 s before the scan before it (within the clock's tolerance): passed
    on as stamped (the pipeline's reorder buffer), counted, warned with its line."""
    path = write_native(
        tmp_path / "x.log", stamp=lambda kind, k, t: t - 0.5 if (kind, k) == ("laser", 12) else t
    )
    _, events, summary = read(path)
    assert sum(isinstance(e, LaserScan) for e in events) == 30
    w = one_warning(summary, "stamped out of order")
    assert w.startswith("1 record stamped out of order (first: ")
    assert f"x.log:{lines_of(path, 'L')[12]}: " in w and "passed on as stamped" in w


def test_native_sound_log_has_no_finding(tmp_path):
    """A log with nothing implausible: no warning, every record delivered; the report's
    section lists the rules' limits, from the configuration (max_range 8 m)."""
    path = write_native(tmp_path / "x.log")
    _, events, summary = read(path)
    assert len(events) == 30 * 7 and summary.get("warnings", []) == []
    section = summary["plausibility"]
    assert section["rules"]["laser_range_m"] == [0.0, MAX_RANGE]
    assert all(v["count"] == 0 for k, v in section.items() if k != "rules")


def test_the_range_limit_is_the_configured_lasers(tmp_path):
    """Ranges just inside and just beyond the configured 8 m (not a constant sized for one
    laser): 8 m is a return, 8.5 m is out of range."""
    path = write_native(tmp_path / "x.log", scan=lambda k, r: np.array([8.0, 8.5, 2, 2, 2]))
    _, events, summary = read(path)
    scan = next(e for e in events if isinstance(e, LaserScan))
    assert scan.ranges[0] == 8.0 and np.isnan(scan.ranges[1])
    assert summary["plausibility"]["laser_ranges_out_of_range"]["beams"] == 30


def test_clockless_native_log_bounds_odometry_by_step(tmp_path):
    """A native log stamped 0 throughout runs in record order (no clock: no speeds); the
    1e25-tick record is still skipped (no wheel travels more than max_step in one record)."""
    path = write_native(
        tmp_path / "x.log",
        stamp=lambda kind, k, t: 0.0,
        odometry=lambda k, t: (10**25, 10**25) if k == 40 else t,
    )
    log, _, summary = read(path)
    assert log.clock == "index"
    assert summary["skipped_by_reason"] == {"implausible odometry": 1}
    assert "a wheel travelled" in one_warning(summary, "implausible odometry")


# -- the same rules on CARMEN logs -------------------------------------------------------------


def carmen(tmp_path, edit, corrected=True, name="c.log", **kw):
    """The room run as a CARMEN log (readers_helpers.carmen_text) with ``edit(k, fields)``
    changing the fields of the k-th FLASER line."""
    out, k = [], 0
    for ln in carmen_text(corrected=corrected, **kw).splitlines():
        f = ln.split()
        if f and f[0] == "FLASER":
            f = edit(k, f)
            k += 1
        out.append(" ".join(f))
    path = tmp_path / name
    path.write_text("\n".join(out) + "\n")
    return path


def negative_flaser(k, f):
    if k % 2:
        n = int(f[1])
        f[2 : 2 + n] = ["-1.5"] * n
    return f


def test_carmen_negative_ranges_follow_the_same_rule(tmp_path):
    """Half the FLASER scans at -1.5 m: as in a native log, read as no return, counted (15
    scans, 180 beams each) and warned once with the first line; 81.91 (the LMS's no return)
    is a code of the format, not a finding."""
    path = carmen(tmp_path, negative_flaser)
    _, events, summary = read(path)
    scans = [e for e in events if isinstance(e, LaserScan)]
    assert all(np.isnan(s.ranges).all() for s in scans[1::2])
    assert np.isnan(scans[0].ranges).sum() == 1  # beam 5: 81.91
    w = one_warning(summary, "ranges out of range")
    assert w.startswith("15 laser scans with ranges out of range (2700 beams; first: ")
    # named by its stamp: the rules see the stream, where the scan's line is not known
    assert "c.log: laser ranges out of range: laser scan at t=2.000000 s" in w
    assert one_warning(summary, "no valid beam").startswith("15 laser scans with no valid beam")


def test_carmen_truth_heading_and_backwards_scan(tmp_path):
    """A raw log's TRUEPOS with a heading of 1e6 rad (within the format's 1e7 bound) is
    skipped as implausible truth; a scan stamped back is dropped (as before) and now also
    warned about as a stamp out of order, naming its line."""
    truepos = "TRUEPOS 0.5 0.2 1000000.0 0 0 0 {t} h {t}"
    extra = {k: truepos.format(t=repr(0.5 + k)) for k in (4, 6)}
    extra[6] = "TRUEPOS 0.5 0.2 0.3 0 0 0 6.5 h 6.5"
    path = tmp_path / "c.log"
    path.write_text(
        carmen_text(corrected=False, extra=extra, stamp=lambda k: 8.5 if k == 9 else 1.0 + k)
    )
    _, events, summary = read(path)
    truth = [e for e in events if isinstance(e, TruthPose)]
    assert [e.theta for e in truth] == [0.3]
    assert summary["skipped_by_reason"]["implausible truth pose"] == 1
    assert "heading 1e+06 rad" in one_warning(summary, "truth pose")
    # the ODOM line before scan 9 comes first: both are stamped 8.5 s, after scan 8's 9 s
    back = [i + 1 for i, ln in enumerate(path.read_text().splitlines()) if " 8.5 h 8.5" in ln]
    w = one_warning(summary, "stamped out of order")
    assert w.startswith(f"2 records stamped out of order (first: {path}:{back[0]}: ")
    assert summary["timestamps_backwards"] == {"ODOM": 1, "FLASER": 1}


def test_carmen_implausible_odometry_is_a_plausibility_finding(tmp_path):
    """The CARMEN reader judges odometry on its poses (where it knows more than the ticks),
    and notes what it finds with the other kinds: one warning, listed in the summary."""
    text = carmen_text(corrected=False).splitlines()
    i = [k for k, ln in enumerate(text) if ln.startswith("ODOM")][12]
    f = text[i].split()
    f[1] = "1000000.0"
    text[i] = " ".join(f)
    path = tmp_path / "c.log"
    path.write_text("\n".join(text) + "\n")
    _, _, summary = read(path)
    w = one_warning(summary, "implausible odometry")
    assert w.startswith(f"1 implausible odometry record (first: {path}:{i + 1}: ")
    assert summary["plausibility"]["implausible_odometry"]["count"] == 1


# -- --strict: each kind an error, exit status 2 -----------------------------------------------


def native_cases(tmp_path):
    return {
        "ranges": write_native(tmp_path / "r.log", scan=half_negative),
        "empty": write_native(tmp_path / "e.log", scan=lambda k, r: r * np.nan if k == 3 else r),
        "odometry": write_native(
            tmp_path / "o.log", odometry=lambda k, t: (10**25, 10**25) if k == 40 else t
        ),
        "truth": write_native(
            tmp_path / "t.log", truth=lambda k, p: (p[0], p[1], 1e9) if k == 3 else p
        ),
        "order": write_native(
            tmp_path / "s.log",
            stamp=lambda kind, k, t: t - 0.5 if (kind, k) == ("laser", 12) else t,
        ),
    }


WORDS = {
    "ranges": ("r.log", "L", 1, "laser ranges out of range"),
    "empty": ("e.log", "L", 3, "laser scan with no valid beam"),
    "odometry": ("o.log", "O", 40, "implausible odometry"),
    "truth": ("t.log", "T", 3, "implausible truth pose"),
    "order": ("s.log", "L", 12, "stamp out of order"),
}


def test_strict_refuses_each_kind_naming_file_and_line(tmp_path, capsys):
    """With --strict each kind is a one-line error naming the file and the record's line,
    exit status 2 (fgslam convert and fgslam run); without it, converted with the warning."""
    for kind, path in native_cases(tmp_path).items():
        name, letter, k, label = WORDS[kind]
        line = lines_of(path, letter)[k]
        with pytest.raises(ReaderError, match=rf"{name}:{line}: {label}: .*--strict"):
            list(open_log(path, strict=True))
        out = tmp_path / f"{kind}.out.log"
        assert main(["convert", str(path), "--strict", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{name}:{line}: {label}" in err, err
        assert not out.exists()
        assert main(["convert", str(path), "--out", str(out)]) == 0
        assert f"warning: {15 if kind == 'ranges' else 1} " in capsys.readouterr().out


def test_strict_refuses_carmen_negative_ranges(tmp_path, capsys):
    path = carmen(tmp_path, negative_flaser)
    with pytest.raises(ReaderError, match=r"c\.log: laser ranges out of range: .*--strict"):
        list(open_log(path, strict=True))
    assert main(["convert", str(path), "--strict", "--out", str(tmp_path / "o.log")]) == 2
    assert "laser ranges out of range" in capsys.readouterr().err


def test_run_lists_the_findings_in_report_json(tmp_path, capsys):
    """fgslam run on a native log with negative ranges: exit 0, one console warning per kind,
    the kinds listed in report.json's "reader"; --strict: exit status 2, one line."""
    path = write_native(tmp_path / "x.log", scan=half_negative)
    argv = ["run", str(path), "--backend", "ekf", "--sensors", "laser"]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert out.count("warning: 15 laser scans with ranges out of range") == 1
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    section = rep["reader"]["plausibility"]
    assert section["laser_ranges_out_of_range"]["count"] == 15
    assert section["laser_ranges_out_of_range"]["beams"] == 75
    assert section["scans_without_valid_beam"]["count"] == 15
    assert "x.log:" in section["laser_ranges_out_of_range"]["first"]
    assert any("ranges out of range" in w for w in rep["reader"]["warnings"])
    assert main([*argv, "--strict", "--out", str(tmp_path / "s")]) == 2
    assert "laser ranges out of range" in capsys.readouterr().err


def test_bag_shares_the_rules(tmp_path):
    """A ROS bag goes through the same rules: a scan stamped before the last event is noted
    as a stamp out of order with its message, listed with the rules' limits; ``strict``
    refuses it naming the topic and message."""
    pytest.importorskip("rosbags")
    from readers_helpers import write_bag

    path = tmp_path / "b.bag"
    write_bag(path, True, backwards_scan=5)
    log = open_log(path)
    list(log)
    summary = log.problems.summary()["plausibility"]
    assert summary["stamps_out_of_order"]["count"] == 1, summary
    assert "/scan message 3" in summary["stamps_out_of_order"]["first"]
    assert summary["rules"]["laser_range_m"] == [0.0, 30.0]  # the bag's own range_max
    with pytest.raises(ReaderError, match=r"/scan message 3.*--strict"):
        list(open_log(path, strict=True))
