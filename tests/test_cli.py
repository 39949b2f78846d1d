"""The command line: help on every subcommand, config round trip, one-line errors."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from fgslam.cli import build_parser, main
from fgslam.config import load_config


def test_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "config" in out and "factor graph" in out


def test_every_subcommand_has_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert sub.choices
    for name in sub.choices:
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        assert len(capsys.readouterr().out) > 200, name


def test_config_round_trip(tmp_path, capsys):
    assert main(["config"]) == 0
    text = capsys.readouterr().out
    p = tmp_path / "robot.toml"
    p.write_text(text)
    assert load_config(p) == load_config()


def test_config_error_is_one_line(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text("[odometry]\nwheelbase = 'x'\n")
    assert main(["config", "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "odometry.wheelbase" in err and "Traceback" not in err


def test_module_entry_point():
    out = subprocess.run(
        [sys.executable, "-m", "fgslam.cli", "config", "--json"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert '"wheelbase"' in out


def test_console_script_installed():
    exe = shutil.which("fgslam")
    if exe is None:
        pytest.skip("fgslam console script not on PATH (package not installed)")
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, check=True).stdout
    assert "usage: fgslam" in out
