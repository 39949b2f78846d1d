"""Sweeps on Dask (issue 36): the specification, a small sweep on a local cluster, resuming
without running a finished cell again, a killed worker's cell run again, the report."""

from __future__ import annotations

import json
import os
import shutil
import threading
from pathlib import Path

import cloudpickle
import numpy as np
import pytest

from fgslam.sweep import SweepError, load_spec, run_sweep, spec_from_dict, write_report
from fgslam.sweep.cell import RESULT, finished
from fgslam.sweep.engine import cell_folder

# -- the specification -----------------------------------------------------------------------


def test_a_grid_is_every_combination_with_stable_names():
    spec = spec_from_dict(
        {
            "run": {"duration": 10.0, "sensors": "laser"},
            "grid": {
                "seed": [1, 2, 3],
                "backend": ["ekf", "isam2"],
                "scanmatch.odometry": ["both", "wheels"],
            },
        }
    )
    assert len(spec.cells) == 12
    ids = [c.id for c in spec.cells]
    assert len(set(ids)) == 12
    again = spec_from_dict(
        {
            "grid": {
                "scanmatch.odometry": ["both", "wheels"],
                "backend": ["ekf", "isam2"],
                "seed": [1, 2, 3],
            },
            "run": {"sensors": "laser", "duration": 10.0},
        }
    )
    assert sorted(c.id for c in again.cells) == sorted(ids)  # order of keys does not matter
    c = spec.cells[0]
    assert c.overrides() == {"scanmatch": {"odometry": c.settings["scanmatch.odometry"]}}
    assert "seed" not in c.group and "backend" in c.group
    # listed cells beside the grid
    listed = spec_from_dict(
        {"run": {"seed": 1}, "cells": [{"backend": "ekf"}, {"backend": "batch"}]}
    )
    assert [c.settings["backend"] for c in listed.cells] == ["ekf", "batch"]


@pytest.mark.parametrize(
    ("data", "says"),
    [
        ({"grid": {"seed": 3}}, "non-empty list"),
        ({"run": {"seed": 1, "colour": "red"}}, "unknown setting"),
        ({"run": {"seed": 1, "backend": "kalman"}}, "backend"),
        ({"run": {"seed": 1, "sensors": "radar"}}, "sensors"),
        ({"run": {"seed": "one"}}, "integer"),
        ({"run": {"seed": True}}, "integer"),
        ({"run": {"backend": "ekf"}}, "a log or a seed"),
        ({"run": {"seed": 1, "log": "x.log"}}, "a log or a seed"),
        ({"run": {"log": "/no/such.log"}}, "no such file"),
        ({"run": {"seed": 1, "duration": -1.0}}, "> 0"),
        ({"run": {"seed": 1, "scanmatch.odometry": "telepathy"}}, "configuration"),
        ({"run": {"seed": 1, "nosection.key": 1}}, "configuration"),
        ({"grid": {"seed": [1, 1]}}, "more than once"),
        ({"runs": {}}, "unknown top-level"),
    ],
)
def test_a_bad_specification_is_refused_saying_why(data, says):
    with pytest.raises(SweepError, match=says) as e:
        spec_from_dict(data)
    assert "\n" not in str(e.value)


def test_a_bad_specification_file_is_one_line(tmp_path, one_line_error):
    (tmp_path / "bad.toml").write_text("[grid\nseed = [1")
    one_line_error(["sweep", str(tmp_path / "bad.toml"), "--out", "o"], "not a TOML")
    one_line_error(["sweep", str(tmp_path / "none.toml"), "--out", "o"], "no such sweep")
    one_line_error(["sweep", "--report", str(tmp_path)], "not a sweep folder")


# -- running ------------------------------------------------------------------------------------

SMALL = {
    "name": "small",
    "run": {"duration": 12.0, "sensors": "laser"},
    "grid": {"seed": [1, 2], "backend": ["isam2", "ekf"]},
}


@pytest.fixture(scope="module")
def small_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    spec = spec_from_dict(SMALL)
    run = run_sweep(spec, out, workers=2, processes=False)
    return spec, out, run


def test_a_small_sweep_runs_every_cell_into_its_folder(small_sweep):
    """Four cells (two seeds, two backends) on an in-process local cluster: each folder
    holds the run's outputs and result.json; every cell's ATE against the simulated truth
    is a few centimetres."""
    spec, out, run = small_sweep
    assert run.skipped == 0 and sorted(run.ran) == sorted(c.id for c in spec.cells)
    assert not run.failed
    for c in spec.cells:
        folder = cell_folder(out, c.id)
        assert {"report.json", "trajectory.tum", RESULT} <= {p.name for p in folder.iterdir()}
        r = finished(folder)
        assert r["settings"] == c.settings
        assert 0 < r["metrics"]["ate_m"] < 0.05
        assert r["metrics"]["keyframes"] > 10
    assert not list(Path(out, "cells").glob(".*"))  # no temporary folder left


def test_the_report_summarizes_per_setting(small_sweep, tmp_path):
    spec, out, _ = small_sweep
    done = write_report(out, tmp_path / "rep")
    assert done == {"cells": 4, "settings": 2, "folder": str(tmp_path / "rep")}
    rows = (tmp_path / "rep" / "summary.csv").read_text().splitlines()
    assert rows[0].startswith("setting,cells,ate_m_mean")
    by = {r.split(",")[0]: r.split(",") for r in rows[1:]}
    assert set(by) == {"backend=isam2", "backend=ekf"}
    ates = [finished(cell_folder(out, c.id))["metrics"]["ate_m"] for c in spec.cells]
    isam2 = [a for a, c in zip(ates, spec.cells, strict=True) if c.settings["backend"] == "isam2"]
    assert float(by["backend=isam2"][2]) == pytest.approx(np.mean(isam2))
    assert (tmp_path / "rep" / "boxplots.png").stat().st_size > 1000
    assert "| backend=ekf | 2 |" in (tmp_path / "rep" / "summary.md").read_text()
    assert len((tmp_path / "rep" / "cells.csv").read_text().splitlines()) == 5


_calls: list[str] = []
_lock = threading.Lock()


def _write_result(settings, folder, name=""):
    """What a cell's run leaves (a stand-in for run_cell): result.json, the folder renamed
    into place."""
    tmp = Path(folder + ".tmp")
    tmp.mkdir(parents=True, exist_ok=True)
    result = {"cell": name, "settings": settings, "metrics": {"ate_m": 0.01}, "wall_s": 0.0}
    (tmp / RESULT).write_text(json.dumps(result))
    if Path(folder).exists():
        shutil.rmtree(folder)
    os.replace(tmp, folder)
    return result


def _counting_cell(settings, folder, name=""):
    """The stand-in, recording the call (threads of this process)."""
    with _lock:
        _calls.append(name)
    return _write_result(settings, folder, name)


def test_a_resumed_sweep_runs_only_what_is_missing(small_sweep, tmp_path):
    """The small sweep copied; one cell deleted, one left half written by an interrupted run
    (a folder without result.json): started again, those two run, no finished one."""
    spec, out, _ = small_sweep
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    gone, half = spec.cells[0].id, spec.cells[1].id
    shutil.rmtree(cell_folder(copy, gone))
    (cell_folder(copy, half) / RESULT).unlink()
    _calls.clear()
    run = run_sweep(spec, copy, workers=2, processes=False, cell_fn=_counting_cell)
    assert sorted(_calls) == sorted([gone, half])
    assert run.skipped == 2 and sorted(run.ran) == sorted([gone, half])
    _calls.clear()
    again = run_sweep(spec, copy, workers=2, processes=False, cell_fn=_counting_cell)
    assert _calls == [] and again.skipped == 4


def _dies_once(settings, folder, name=""):
    """Kills its worker process on the first attempt (a marker file beside the cell's folder
    says it was made), then runs; seed 3 kills it every time."""
    marker = Path(folder + ".attempted")
    marker.parent.mkdir(parents=True, exist_ok=True)
    if settings["seed"] == 3 or not marker.exists():
        marker.write_text("x")
        os._exit(1)
    return _write_result(settings, folder, name)


def test_a_killed_workers_cell_is_run_again_then_reported_failed(tmp_path):
    """On a local cluster of a worker process (restarted by its nanny when it dies; one
    worker, so that a death is counted against the cell that caused it only: Dask blames
    every cell a dying worker held): a cell whose worker dies once is run again and
    finishes; one whose worker dies every time is reported failed after the retries
    (KilledWorker), and the other cells finish."""
    import sys

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        spec = spec_from_dict(
            {"run": {"duration": 1.0}, "cells": [{"seed": 1}, {"seed": 2}, {"seed": 3}]}
        )
        run = run_sweep(spec, tmp_path, workers=1, retries=1, cell_fn=_dies_once)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    ids = [c.id for c in spec.cells]
    assert sorted(run.ran) == sorted(ids[:2])
    assert list(run.failed) == [ids[2]]
    assert "KilledWorker" in run.failed[ids[2]]
    assert json.loads((tmp_path / "failed.json").read_text()) == run.failed
    for i in ids[:2]:
        assert Path(str(cell_folder(tmp_path, i)) + ".attempted").exists()  # it died once
        assert finished(cell_folder(tmp_path, i)) is not None
    assert finished(cell_folder(tmp_path, ids[2])) is None


def test_the_cli_runs_and_reports(tmp_path, capsys):
    from fgslam.cli import main

    (tmp_path / "s.toml").write_text(
        'name = "cli"\n[run]\nduration = 8.0\nsensors = "laser"\nbackend = "ekf"\n'
        "[grid]\nseed = [1, 2]\n"
    )
    out = tmp_path / "out"
    assert main(["sweep", str(tmp_path / "s.toml"), "--out", str(out), "--workers", "1"]) == 0
    assert "0 cells finished before, 2 run now, 0 failed" in capsys.readouterr().out
    assert main(["sweep", str(tmp_path / "s.toml"), "--out", str(out), "--workers", "1"]) == 0
    assert "2 cells finished before, 0 run now" in capsys.readouterr().out
    assert main(["sweep", "--report", str(out)]) == 0
    assert "| all | 2 |" in capsys.readouterr().out
    assert load_spec(tmp_path / "s.toml").name == "cli"


def test_a_sweep_on_an_existing_scheduler(tmp_path):
    """--scheduler's path: the cells go to a cluster started elsewhere (here one in this
    process, reached by its address) and finish there; the cluster is left running."""
    from distributed import LocalCluster

    spec = spec_from_dict({"run": {"duration": 1.0}, "grid": {"seed": [1, 2, 3]}})
    with LocalCluster(n_workers=2, processes=False, dashboard_address=":0") as cluster:
        _calls.clear()
        run = run_sweep(spec, tmp_path, scheduler=cluster.scheduler_address, cell_fn=_counting_cell)
        assert sorted(run.ran) == sorted(c.id for c in spec.cells) and not run.failed
        assert cluster.scheduler_address  # still up
    with pytest.raises(SweepError, match="cannot reach"):
        run_sweep(
            spec_from_dict({"run": {"seed": 9}}), tmp_path / "x", scheduler="tcp://127.0.0.1:9"
        )


def _square(settings):
    with _lock:
        _calls.append(f"{settings['case']}{settings['seed']}")
    return {"case": settings["case"], "value": settings["seed"] ** 2}


def test_an_experiments_own_sweep_keeps_the_grids_order_and_resumes(tmp_path):
    """sweep_function (the experiments' loops over seeds): an experiment's own setting
    (``case``) beside the seed, the results in the grid's order, and a second call runs
    nothing."""
    from fgslam.sweep import sweep_function

    grid = {"case": ["b", "a"], "seed": [3, 1, 2]}
    _calls.clear()
    got = sweep_function(_square, grid, tmp_path, workers=2, extra=("case",), processes=False)
    assert [(g["case"], g["value"]) for g in got] == [
        ("b", 9), ("b", 1), ("b", 4), ("a", 9), ("a", 1), ("a", 4)
    ]  # fmt: skip
    assert sorted(_calls) == sorted(["b3", "b1", "b2", "a3", "a1", "a2"])
    _calls.clear()
    assert sweep_function(_square, grid, tmp_path, extra=("case",), processes=False) == got
    assert _calls == []
    with pytest.raises(SweepError, match="unknown setting"):
        sweep_function(_square, grid, tmp_path, processes=False)  # "case" not declared
