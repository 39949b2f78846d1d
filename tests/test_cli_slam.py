"""`fgslam run` and `fgslam compare` from the command line, on a short simulated log."""

from __future__ import annotations

import json

import pytest

from fgslam.cli import main


@pytest.fixture(scope="module")
def short_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("log")
    log = d / "short.log.gz"
    assert main(["simulate", "--seed", "2", "--duration", "25", "--out", str(log)]) == 0
    return log


def test_run_writes_outputs(short_log, tmp_path, capsys):
    out = tmp_path / "run"
    assert (
        main(["run", str(short_log), "--backend", "ekf", "--sensors", "fused", "--out", str(out)])
        == 0
    )
    for name in ("trajectory.tum", "map.json", "report.json", "map.png"):
        assert (out / name).stat().st_size > 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["backend"] == "ekf" and rep["sensors"] == "fused" and "ate" in rep
    assert rep["ate"]["rmse"] < rep["ate_odometry"]["rmse"] + 0.02
    assert "ATE RMSE" in capsys.readouterr().out


def test_compare_writes_table_and_figure(short_log, tmp_path, capsys):
    out = tmp_path / "cmp"
    assert main(["compare", str(short_log), "--out", str(out)]) == 0
    rows = json.loads((out / "comparison.json").read_text())
    assert {(r["backend"], r["sensors"]) for r in rows} == {
        (b, s) for b in ("ekf", "isam2", "batch") for s in ("fused", "laser", "sonar")
    }
    md = (out / "comparison.md").read_text()
    assert md.startswith("# fgslam compare: short.log.gz") and "Columns: ATE RMSE" in md
    assert md.count("\n| ") >= 9 and (out / "comparison.png").stat().st_size > 20000
    assert (out / "isam2-sonar" / "map.png").exists()
    assert "| batch | fused |" in capsys.readouterr().out


def test_run_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.log"
    bad.write_text("FGSLAM-LOG 1\nnot a header\n")
    assert main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "bad.log" in err and "Traceback" not in err


def test_run_scan_matching_options(short_log, tmp_path, capsys):
    """--odometry/--keyframes/--loops: the paper's scheme has a keyframe at every scan; the
    default (scan matching, keyframes by motion) fewer keyframes and a pose at every scan;
    report.json says which; an unknown choice is a usage error."""
    paper, default = tmp_path / "paper", tmp_path / "default"
    args = ["run", str(short_log), "--backend", "isam2", "--sensors", "laser"]
    assert (
        main(
            [
                *args,
                "--odometry",
                "wheels",
                "--keyframes",
                "every-scan",
                "--loops",
                "off",
                "--out",
                str(paper),
            ]
        )
        == 0
    )
    assert main([*args, "--out", str(default)]) == 0
    a = json.loads((paper / "report.json").read_text())
    b = json.loads((default / "report.json").read_text())
    assert a["poses"] == a["scans_placed"] == b["scans_placed"]
    assert b["poses"] < a["poses"] / 2
    sa, sb = a["statistics"], b["statistics"]
    assert "scan_matches" not in sa and sa["keyframes_wheels_only"] == a["poses"] - 1
    assert sb["scan_matches"] == b["scans_placed"] - 1 and sb["keyframes_scan_linked"] > 0
    assert b["ate"]["rmse"] < 0.1 and a["ate"]["rmse"] < 0.1
    dense = (default / "trajectory_dense.tum").read_text().splitlines()
    assert len(dense) >= b["scans_placed"]
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main([*args, "--odometry", "sonar", "--out", str(tmp_path / "x")])
    assert "--odometry" in capsys.readouterr().err


def test_run_calibration_option(short_log, tmp_path, capsys):
    """--calibration wheels (the default robot's default, with its laser offset): report.json
    holds the wheel calibration errors with sigmas below the configuration's prior (learned
    from 25 s of data), and the simulator's bias (0.6 %, 0.5 %, 0.5 %) within 3 sigma; with
    both off, no calibration entry."""
    out, plain = tmp_path / "cal", tmp_path / "plain"
    args = ["run", str(short_log), "--backend", "isam2", "--sensors", "fused"]
    capsys.readouterr()
    assert main([*args, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    off = ["--calibration", "off", "--laser-calibration", "off"]
    assert main([*args, *off, "--out", str(plain)]) == 0
    assert "calibration (" not in capsys.readouterr().out
    cal = json.loads((out / "report.json").read_text())["calibration"]
    e_r = f"e_r {1e3 * cal['estimate'][0]:+.2f} +- {1e3 * cal['sigma'][0]:.2f}"
    assert f"calibration (1e-3; laser_offset in mm): {e_r}, e_l" in printed
    assert cal["parameters"] == ["e_r", "e_l", "e_b", "laser_offset"]
    est, sig = cal["estimate"][:3], cal["sigma"][:3]
    assert all(s < 0.01 for s in sig[:2]) and all(s <= 0.01 for s in sig)
    for e, s, truth in zip(est, sig, (0.006, 0.005, 0.005), strict=True):
        assert abs(e - truth) < 3 * s, (est, sig)
    # the simulated log's truth beside them (the simulator's defaults), and the error in sigmas
    assert cal["truth"] == pytest.approx([0.006, 0.005, 0.005, 0.008])
    assert cal["error_sigmas"][:3] == pytest.approx(
        [(e - t) / s for e, t, s in zip(est, (0.006, 0.005, 0.005), sig, strict=True)]
    )
    assert "calibration" not in json.loads((plain / "report.json").read_text())
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main([*args, "--calibration", "yes", "--out", str(tmp_path / "x")])
    assert "invalid choice" in capsys.readouterr().err


def test_run_laser_calibration_option(short_log, tmp_path):
    """--laser-calibration offset: report.json holds the wheels' errors and the laser's
    range offset, its sigma learned from 25 s of data (below the 1 cm prior) and the
    simulator's 8 mm within 3 sigma of it (range: also the scale)."""
    args = ["run", str(short_log), "--backend", "isam2", "--sensors", "laser"]
    for mode, names in (
        ("offset", ["e_r", "e_l", "e_b", "laser_offset"]),
        ("range", ["e_r", "e_l", "e_b", "laser_offset", "laser_scale"]),
    ):
        out = tmp_path / mode
        assert main([*args, "--laser-calibration", mode, "--out", str(out)]) == 0
        cal = json.loads((out / "report.json").read_text())["calibration"]
        assert cal["parameters"] == names
        est, sig = cal["estimate"][3], cal["sigma"][3]
        assert sig < 0.005 and abs(est - 0.008) < 3 * sig, (est, sig)


def test_run_sonar_calibration_option(short_log, tmp_path):
    """--sonar-calibration sound (sonar only, each reading at its own time): report.json holds
    the speed of sound's relative error after the others, its sigma learned from 25 s of data
    (below 0.8 %, the prior 1 %; measured 0.6 %) and the simulator's draw for the log within
    3 sigma of it."""
    from fgslam.io.logfile import LogReader

    truth = LogReader(short_log).meta["sound_speed_bias"]
    out = tmp_path / "sound"
    args = ["run", str(short_log), "--backend", "isam2", "--sensors", "sonar"]
    assert (
        main(
            [*args, "--sonar-calibration", "sound", "--sonar-timing", "own-time", "--out", str(out)]
        )
        == 0
    )
    rep = json.loads((out / "report.json").read_text())
    cal = rep["calibration"]
    assert cal["parameters"] == ["e_r", "e_l", "e_b", "laser_offset", "sound"]
    est, sig = cal["estimate"][-1], cal["sigma"][-1]
    assert sig < 0.008 and abs(est - truth) < 3 * sig, (est, sig, truth)


def test_run_sonar_timing_option(short_log, tmp_path):
    """--sonar-timing own-time: the graph attaches sonar features at their own time
    (report.json statistics count them); the default (scan-frame) attaches none."""
    args = ["run", str(short_log), "--backend", "isam2", "--sensors", "sonar"]
    assert main([*args, "--sonar-timing", "own-time", "--out", str(tmp_path / "own")]) == 0
    assert main([*args, "--out", str(tmp_path / "scan")]) == 0
    own = json.loads((tmp_path / "own" / "report.json").read_text())["statistics"]
    scan = json.loads((tmp_path / "scan" / "report.json").read_text())["statistics"]
    assert own["sonar_own_time"] > 50 and "sonar_own_time" not in scan
