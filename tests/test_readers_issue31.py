"""Every real log runs to the end (issue 31, "Odometry and clocks"): implausible odometry is
skipped and counted by default (refused with ``strict``), a log without usable stamps runs
in record order with a warning (refused with ``strict``) and says which clock it used, and
the preintegrated odometry covariance has a physical floor (one encoder tick per wheel).
Small synthetic logs and bags (tests/readers_helpers.py); docs/readers.md."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from readers_helpers import bag_drive, carmen_text, write_bag, write_native

from factors.odometry import COVARIANCE_FLOOR, OdometryIntegrator, integrate_poses, preintegrate
from fgslam.cli import build_parser, main
from fgslam.config import load_config
from fgslam.errors import ReaderError
from fgslam.events import LaserScan, OdometryEvent
from fgslam.io.formats import open_log
from fgslam.io.logrecords import LogFormatError
from fgslam.io.readers.common import derived_config
from fgslam.io.readers.sanity import INDEX_PERIOD, OdometryLimits, implausible


def zero_stamps(text: str) -> str:
    """Every FLASER and ODOM line of a CARMEN log stamped 0 in both stamp fields."""
    out = []
    for line in text.splitlines():
        f = line.split()
        if f and f[0] in ("FLASER", "ODOM"):
            f[-3] = f[-1] = "0"
            line = " ".join(f)
        out.append(line)
    return "\n".join(out) + "\n"


def odometry_end(log, events) -> np.ndarray:
    """The pose (x, y, theta) the odometry events of a reader reach from the origin."""
    o = log.config.odometry
    odo = [e for e in events if isinstance(e, OdometryEvent)]
    lr = np.array([e.ticks_right for e in odo]) * o.metres_per_tick_right
    ll = np.array([e.ticks_left for e in odo]) * o.metres_per_tick_left
    return integrate_poses(lr, ll, o.wheelbase)[-1]


# -- clocks -----------------------------------------------------------------------------------


def test_carmen_log_stamped_zero_runs_in_record_order_with_a_warning(tmp_path):
    """A CARMEN log whose every stamp is 0 (as orebro-corrected's scans): read by default in
    record order (scans 0.2 s apart) with a warning, the clock named in the record that goes
    into report.json; ``strict`` refuses it as before."""
    f = tmp_path / "z.log"
    f.write_text(zero_stamps(carmen_text(corrected=True, n=10)))
    with pytest.raises(ReaderError, match="no usable timestamps"):
        open_log(f, strict=True)
    log = open_log(f)
    events = list(log)
    scans = [e for e in events if isinstance(e, LaserScan)]
    assert [s.t for s in scans] == pytest.approx(INDEX_PERIOD * np.arange(1, 11))
    rec = log.problems.summary()["timestamps"]
    assert rec["used"] == "index" and rec["requested"] == "auto"
    assert rec["clock"].startswith("index (no usable stamps: ipc field: scan stamped 0")
    warnings = log.problems.summary()["warnings"]
    assert any("no usable timestamps" in w and "record order" in w for w in warnings)


def test_cli_run_names_the_clock_in_the_report_and_strict_refuses(tmp_path, capsys):
    """``fgslam run`` on the log stamped 0: runs, warns, and report.json's reader record
    names the clock; ``--strict`` is the old one-line refusal (exit 2)."""
    f = tmp_path / "z.log"
    f.write_text(zero_stamps(carmen_text(corrected=False, n=10)))
    base = ["run", str(f), "--backend", "ekf", "--sensors", "laser"]
    assert main([*base, "--strict", "--out", str(tmp_path / "s")]) == 2
    assert "no usable timestamps" in capsys.readouterr().err
    assert main([*base, "--out", str(tmp_path / "o")]) == 0
    assert "warning: no usable timestamps" in capsys.readouterr().out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["reader"]["timestamps"]["clock"].startswith("index (no usable stamps")


def test_without_a_clock_speeds_are_not_checked_but_jumps_are(tmp_path):
    """With index stamps the odometry's speed is not measured against the invented 0.2 s:
    records 1.5 m apart pass (they would be 5 m/s), a 50 m jump is still skipped."""
    text = carmen_text(corrected=False, n=10, odo_error=(0.0, 0.0, 0.0))
    lines = []
    for line in text.splitlines():  # stretch the drive: about 1.5 m between records
        f = line.split()
        if f and f[0] == "ODOM":
            f[1], f[2] = repr(5 * float(f[1])), repr(5 * float(f[2]))
        lines.append(" ".join(f))
    f = tmp_path / "z.log"
    f.write_text(zero_stamps("\n".join(lines)))
    log = open_log(f, mode="raw")
    list(log)
    assert log.problems.notes["odometry"]["implausible"] == 0
    lim = OdometryLimits()
    assert implausible((1.5, 0.0, 3.0), None, lim) is None  # no clock: no speed, no turn rate
    assert "m in one step" in implausible((50.0, 0.0, 0.0), None, lim)


def test_native_log_stamped_zero_falls_back_to_record_order(tmp_path):
    """A native log stamped 0 throughout: open_log reads it in record order and says so;
    ``strict`` refuses it as before."""
    path = tmp_path / "x.log"
    write_native(path, n=10, stamp=lambda kind, k, t: 0.0)
    with pytest.raises(LogFormatError, match="no usable timestamps"):
        open_log(path, strict=True)
    log = open_log(path)
    scans = [e for e in log if isinstance(e, LaserScan)]
    assert [s.t for s in scans] == pytest.approx(INDEX_PERIOD * np.arange(1, 11))
    rec = log.summary()["timestamps"]
    assert rec["used"] == "index" and rec["clock"].startswith("index (no usable stamps")


# -- implausible odometry ---------------------------------------------------------------------


@pytest.mark.parametrize("ros1", [True, False])
def test_bag_odometry_spike_is_skipped_and_counted_by_default(tmp_path, ros1):
    """One odometry message 1e6 m off: by default skipped and counted with a warning, the
    odometry continuing from the last good message (the same path as without the spike);
    ``strict`` refuses the bag."""
    path = tmp_path / ("j.bag" if ros1 else "j")
    write_bag(path, ros1, with_range=False, jump=7)
    with pytest.raises(ReaderError, match=r"implausible odometry.*--strict"):
        list(open_log(path, strict=True))
    log = open_log(path)
    events = list(log)
    assert sum(isinstance(e, LaserScan) for e in events) == 10
    notes = log.problems.summary()
    assert notes["odometry"]["implausible"] == 1
    assert notes["skipped_by_reason"]["implausible odometry"] == 1
    assert any("implausible odometry" in w for w in notes["warnings"])
    np.testing.assert_allclose(odometry_end(log, events), bag_drive(19), atol=1e-3)


def test_bag_odometry_jump_that_stays_is_dropped(tmp_path):
    """Odometry that jumps 1.2 m between two messages 0.1 s apart and continues from there
    (as intel.orig.bag's /odom does twice): the jump is dropped and the odometry continues
    from the jumped message (counted as rebased), not carried into the next message, whose
    offset from the last good one (1.3 m in 0.2 s) is within the speed bound's slack."""
    path = tmp_path / "s.bag"
    write_bag(path, True, with_range=False, shift=(7, 1.2))
    log = open_log(path)
    events = list(log)
    odo = log.problems.notes["odometry"]
    assert odo["implausible"] == 1 and odo["rebased"] == 1
    # the drive without message 6 -> 7 (the jump) ...
    end = odometry_end(log, events)
    np.testing.assert_allclose(end[2], bag_drive(19)[2] - 0.02, atol=1e-3)
    assert np.hypot(*(end[:2] - bag_drive(19)[:2])) < 0.06  # ... not 1.2 m off


def test_cli_strict_flag(tmp_path, capsys):
    """--strict on every command that reads logs; ``fgslam convert`` of the bag with a
    spike: written by default (the skip reported), refused with --strict."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for cmd in ("run", "convert", "compare", "export-reference", "plot-log"):
        assert "--strict" in sub.choices[cmd].format_help(), cmd
    path = tmp_path / "j.bag"
    write_bag(path, True, with_range=False, jump=7)
    out = tmp_path / "o.log"
    assert main(["convert", str(path), "--strict", "--out", str(out)]) == 2
    assert "implausible odometry" in capsys.readouterr().err
    assert main(["convert", str(path), "--out", str(out)]) == 0
    assert "implausible odometry" in capsys.readouterr().out


# -- the odometry covariance floor ------------------------------------------------------------


def test_standing_robot_covariance_is_floored_by_the_encoder():
    """A robot standing still (zero wheel distances, or no sample at all) gets a positive
    definite covariance of the size of one encoder tick per wheel: each wheel's distance over
    the interval is off by the difference of two quantisation errors, uniform over one tick
    (variance tick^2 / 6, checked by Monte Carlo), i.e. along track tick^2 / 12, heading
    tick^2 / (3 D^2), lateral as along track; plus the numerical floor."""
    cfg = load_config()
    o = cfg.odometry
    tick = o.metres_per_tick_right
    rng = np.random.default_rng(1)
    start = rng.uniform(0, 1, 200000)  # encoder phases (in ticks) at the interval's ends
    moved = rng.uniform(0, 50, 200000)
    err = (np.round(start + moved) - np.round(start) - moved) * tick
    assert np.var(err) == pytest.approx(tick**2 / 6, rel=0.02)
    want = np.diag([tick**2 / 12, tick**2 / 12, tick**2 / (3 * o.wheelbase**2)])
    want += COVARIANCE_FLOOR * np.eye(3)
    p = o.params()
    for pre in (preintegrate(np.zeros(20), np.zeros(20), p), preintegrate([], [], p)):
        assert np.all(np.linalg.eigvalsh(pre.covariance) > 0)
        np.testing.assert_allclose(pre.covariance, want, rtol=1e-9, atol=1e-15)
    integ = OdometryIntegrator(p)
    integ.add(0.01, 0.0, 0.0)
    np.testing.assert_allclose(integ.keyframe().covariance, want, rtol=1e-9, atol=1e-15)
    # the virtual drive of the readers: its own tick (0.1 mm) on a 2 m wheelbase
    v = derived_config(181).odometry
    pv = preintegrate(np.zeros(5), np.zeros(5), v.params())
    assert np.all(np.linalg.eigvalsh(pv.covariance) > 0)
    assert pv.covariance[0, 0] == pytest.approx(1e-8 / 12 + COVARIANCE_FLOOR)


def test_resolution_is_a_configuration_key(tmp_path):
    """``[odometry] resolution`` (m per wheel) overrides the encoder tick; its floor is the
    same in both covariance conventions when the wheels are alike, and a moving robot's
    covariance grows by exactly the floor."""
    from factors.odometry import resolution_floor

    toml = tmp_path / "r.toml"
    toml.write_text("[odometry]\nresolution = 0.002\n")
    cfg = load_config(toml)
    p = cfg.odometry.params()
    assert (p.resolution_right, p.resolution_left) == (0.002, 0.002)
    D = cfg.odometry.wheelbase
    np.testing.assert_allclose(
        resolution_floor(p), np.diag([4e-6 / 12, 4e-6 / 12, 4e-6 / (3 * D * D)])
    )
    lr, ll = np.full(10, 0.01), np.full(10, 0.012)
    bare = dataclasses.replace(p, resolution_right=0.0, resolution_left=0.0)
    a, b = preintegrate(lr, ll, p), preintegrate(lr, ll, bare)
    np.testing.assert_allclose(a.covariance - b.covariance, resolution_floor(p), atol=1e-15)
    np.testing.assert_allclose(
        a.covariance_start - b.covariance_start, resolution_floor(p), atol=1e-15
    )


def saturated(text: str, rng, share: float = 0.05, code: float = 51.15, pad: float = 50.0):
    """A CARMEN log whose laser reports no return as ``code`` (a share of the readings) and
    whose last beam is a padding field reading ``pad`` in every scan."""
    out = []
    for line in text.splitlines():
        f = line.split()
        if f and f[0] == "FLASER":
            n = int(f[1])
            r = [float(v) for v in f[2 : 2 + n]]
            for i in range(n):
                if rng.random() < share or r[i] > 80:
                    r[i] = code
            r[-1] = pad
            f[2 : 2 + n] = [repr(v) for v in r]
            line = " ".join(f)
        out.append(line)
    return "\n".join(out) + "\n"


def test_carmen_laser_with_its_own_no_return_value_and_a_padding_beam(tmp_path):
    """A laser that reports no return as 51.15 m (acapulco-corrected: 7.9 % of its readings)
    and fills its 181st beam with 50.0: both read as no return (NaN), the value found from
    the first scans and recorded, the configured laser's range lowered to it; the room's
    own readings (below 10 m) stay. The same log with the LMS's 81.91 is unchanged."""
    rng = np.random.default_rng(5)
    base = carmen_text(corrected=True, n=40, beams=181)
    f = tmp_path / "s.log"
    f.write_text(saturated(base, rng))
    log = open_log(f)
    scans = [e for e in log if isinstance(e, LaserScan)]
    r = np.vstack([s.ranges for s in scans])
    assert np.isnan(r[:, -1]).all()
    assert not (r > 50).any()  # nothing left at the no-return code
    assert 0.03 < np.isnan(r[:, :-1]).mean() < 0.08
    assert 50.0 < log.meta["no_return_m"] < 51.15 and log.meta["dead_beams"] == [180]
    assert log.config.laser.max_range == pytest.approx(log.meta["no_return_m"], abs=1e-3)
    plain = tmp_path / "p.log"
    plain.write_text(base)
    log = open_log(plain)
    r = np.vstack([s.ranges for s in log if isinstance(s, LaserScan)])
    assert "dead_beams" not in log.meta and log.meta.get("no_return_m", 80.0) == 80.0
    assert np.isnan(r[:, 5]).all() and np.isfinite(r[:, :5]).all()
