"""`fgslam simulate` and `fgslam plot-log` from the command line."""

from __future__ import annotations

import json

import pytest

from fgslam.cli import main
from fgslam.events import LaserScan, TruthPose
from fgslam.io.logfile import LogReader


def test_simulate_is_deterministic_and_plot_log_draws(tmp_path, capsys):
    a, b, c = tmp_path / "a.log.gz", tmp_path / "b.log.gz", tmp_path / "c.log"
    assert main(["simulate", "--seed", "4", "--duration", "8", "--out", str(a)]) == 0
    assert main(["simulate", "--seed", "4", "--duration", "8", "--out", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()  # byte-identical for the same seed
    assert main(["simulate", "--seed", "5", "--duration", "8", "--out", str(c)]) == 0
    out = capsys.readouterr().out
    assert "world 'corridor', seed 4" in out and "real time" in out
    with LogReader(a) as r:
        assert r.world == "corridor" and r.meta["seed"] == 4
        evs = list(r)
    assert any(isinstance(e, LaserScan) for e in evs)
    assert any(isinstance(e, TruthPose) for e in evs)
    png = tmp_path / "a.png"
    assert main(["plot-log", str(a), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20000
    assert "laser scans" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, msg",
    [
        (["simulate", "--world", "atlantis", "--out", "x.log"], "cannot read"),
        (["simulate", "--duration", "-3", "--out", "x.log"], "--duration"),
        (["plot-log", "missing.log", "--out", "x.png"], "missing.log"),
    ],
)
def test_bad_input_is_one_line(one_line_error, argv, msg):
    one_line_error(argv, msg)


def test_simulate_custom_world_without_route(tmp_path, capsys):
    w = tmp_path / "w.json"
    w.write_text(json.dumps({"name": "box", "walls": [{"id": "a", "points": [[0, 0], [1, 0]]}]}))
    assert main(["simulate", "--world", str(w), "--out", str(tmp_path / "x.log")]) == 2
    assert "no route" in capsys.readouterr().err


def test_world_help_names_every_built_in_world():
    from fgslam.cli import WORLD_HELP
    from fgslam.sim.world import BUILTIN_WORLDS

    assert all(name in WORLD_HELP for name in BUILTIN_WORLDS)


@pytest.mark.parametrize("value", [1e308, -1e20, 1e7])
def test_world_with_a_coordinate_beyond_any_building(tmp_path, capsys, value):
    """A wall point at 1e308 m: refused naming the element (it once simulated on with numpy
    overflow warnings and infinite segments)."""
    import warnings
    from importlib.resources import files

    world = json.loads((files("fgslam") / "data" / "world_corridor.json").read_text())
    world["walls"][0]["points"][1][0] = value
    w = tmp_path / "w.json"
    w.write_text(json.dumps(world))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc = main(["simulate", "--world", str(w), "--duration", "1", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "walls[0]" in err and "\n" not in err, err
