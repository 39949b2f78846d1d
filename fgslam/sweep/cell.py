"""One cell of a sweep, run where a Dask worker runs it (docs/sweeps.md).

A cell is a run of the SLAM pipeline (:func:`fgslam.slam.runner.run_slam`) over a log or a
simulated run, with the outputs of ``fgslam run`` (report.json, trajectory.tum, map.png) and
``result.json``: the cell's settings and the figures a sweep compares (:func:`metrics`). The
cell's folder is written as a whole into a sibling temporary folder and then renamed into
place, ``result.json`` last inside it: a folder with a ``result.json`` is a finished cell,
anything else is not, whatever stopped the run (Ctrl-C, a killed worker, a power cut).
"""

from __future__ import annotations

import json
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

RESULT = "result.json"


def finished(folder: str | Path) -> dict[str, Any] | None:
    """The result of the finished cell in ``folder``, None if it is not finished (no or an
    unreadable ``result.json``)."""
    try:
        return json.loads((Path(folder) / RESULT).read_text())
    except (OSError, ValueError):
        return None


def run_cell(settings: dict[str, Any], folder: str, name: str = "") -> dict[str, Any]:
    """Run the cell of ``settings`` (:class:`fgslam.sweep.spec.Cell`) into ``folder``, unless
    it is finished already; returns its result (``result.json``'s content). Raises what the
    run raises (the sweep reports the cell failed); nothing is left in ``folder`` then."""
    return in_cell(folder, lambda tmp: _run(settings, tmp, name))


def _run(settings: dict[str, Any], tmp: Path, name: str) -> dict[str, Any]:
    from fgslam.config import load_config, with_options
    from fgslam.io.formats import open_log
    from fgslam.sim import simulate_to_log, true_calibration
    from fgslam.sim.world import BUILTIN_WORLDS, load_world
    from fgslam.slam.outputs import write_outputs
    from fgslam.slam.runner import run_slam
    from fgslam.sweep.spec import Cell

    t0 = time.perf_counter()
    world = None
    if "log" in settings:
        reader = open_log(settings["log"])
    else:
        world = load_world(settings["world"])
        sim = tmp / "simulated.log.gz"
        simulate_to_log(world, load_config(None), sim, settings["seed"], settings.get("duration"))
        reader = open_log(sim)
    cfg = with_options(reader.config, Cell(settings).overrides())
    res = run_slam(
        reader, cfg, settings["backend"], settings["sensors"],
        association=settings.get("association"),
    )  # fmt: skip
    rep = write_outputs(
        res,
        tmp,
        reader.meta.get("true_map"),
        true_calibration=true_calibration(reader.meta),
        world=world if settings.get("world") in BUILTIN_WORLDS else None,
        cfg=cfg,
    )
    if "seed" in settings:
        (tmp / "simulated.log.gz").unlink(missing_ok=True)
    return {
        "cell": name,
        "settings": settings,
        "metrics": metrics(rep, res, settings),
        "wall_s": round(time.perf_counter() - t0, 3),
        "host": os.uname().nodename,
    }


def in_cell(folder: str | Path, work) -> dict[str, Any]:
    """A cell's protocol: ``folder``'s result if it is finished; else ``work(tmp)`` (its
    outputs into ``tmp``, a new folder beside ``folder``; returns the result), the result
    written as ``tmp``'s result.json and ``tmp`` renamed to ``folder`` (whatever an earlier,
    unfinished attempt left there removed first). On an error nothing is left."""
    folder = Path(folder)
    done = finished(folder)
    if done is not None:
        return done
    tmp = folder.parent / f".{folder.name}.running-{uuid.uuid4().hex[:8]}"
    tmp.mkdir(parents=True)
    try:
        result = work(tmp)
        (tmp / RESULT).write_text(json.dumps(result, indent=1, default=_json_default))
        if folder.exists():  # a failed attempt's leftovers (never a finished cell)
            shutil.rmtree(folder)
        os.replace(tmp, folder)
        return result
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


class FunctionCell:
    """A cell function (for :func:`fgslam.sweep.run_sweep`'s ``cell_fn``) of ``fn``, which
    maps a cell's settings to a JSON-able result (an experiment's own run): the result is
    kept in the cell's ``result.json`` (:func:`in_cell`)."""

    def __init__(self, fn) -> None:
        self.fn = fn

    def __call__(self, settings: dict[str, Any], folder: str, name: str = "") -> dict[str, Any]:
        def work(_tmp: Path) -> dict[str, Any]:
            t0 = time.perf_counter()
            out = self.fn(settings)
            return {"cell": name, "settings": settings, "result": out,
                    "wall_s": round(time.perf_counter() - t0, 3)}  # fmt: skip

        return in_cell(folder, work)


def metrics(rep: dict[str, Any], res, settings: dict[str, Any]) -> dict[str, float | None]:
    """The figures a sweep compares (None where the run has none): ATE RMSE (m) and heading
    RMSE (deg) against the log's truth, the pose NEES (mean; its share inside the 95 % band),
    the relations error (mean translation m, rotation deg) when the log has a relations
    file, the real-time factor, keyframes, landmarks, accepted loop closures, and 1 for a
    run its backend did not finish (partial)."""
    ate = rep.get("ate") or {}
    nees = rep.get("nees") or {}
    out: dict[str, float | None] = {
        "ate_m": ate.get("rmse"),
        "ate_heading_deg": ate.get("heading_rmse_deg"),
        "nees_mean": nees.get("mean"),
        "nees_within_95": nees.get("within_95"),
        "realtime_factor": rep.get("realtime_factor"),
        "keyframes": len(res.times),
        "landmarks": rep.get("landmarks_total"),
        "loops_accepted": (rep.get("loop_closures") or {}).get("accepted", 0),
        "partial": 1.0 if rep.get("partial") else 0.0,
        "relations_m": None,
        "relations_deg": None,
    }
    rel = relations_file(settings)
    if rel is not None:
        r = relations_error(settings["log"], rel, *res.every_scan)
        out["relations_m"], out["relations_deg"] = r["trans_mean"], r["rot_mean_deg"]
    return out


def relations_file(settings: dict[str, Any]) -> Path | None:
    """The relations file of a cell: ``relations``, else the log's sibling ``X.relations``."""
    if "relations" in settings:
        return Path(settings["relations"])
    if "log" not in settings:
        return None
    log = Path(settings["log"])
    stem = log.name.split(".")[0]
    cand = log.with_name(f"{stem}.relations")
    return cand if cand.is_file() else None


def relations_error(log, relations, t, poses) -> dict[str, Any]:
    """The relations benchmark's error of the poses at every scan: with a CARMEN log's
    odometry between the scans (the benchmark's method), else interpolated."""
    from fgslam.evaluation import dense
    from fgslam.io.formats import sniff_format

    rel = dense.read_relations(relations)
    if sniff_format(log) == "carmen":
        from fgslam.io.readers.carmen import odometry_chain

        chain = odometry_chain(log)
        est, has = dense.estimate_at_scans(chain, t, poses)
        return dense.relations_error_chain(rel, chain, est, has)
    return dense.relations_error(rel, np.asarray(t), np.asarray(poses))


def _json_default(o: object) -> object:
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"{type(o).__name__} is not JSON")
