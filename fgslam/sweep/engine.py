"""Running a sweep on Dask (``fgslam sweep``; docs/sweeps.md).

The cells go to a ``dask.distributed`` cluster: a :class:`~distributed.LocalCluster` of
``workers`` processes (one thread each; default one per core) with a memory limit each, or
an existing cluster's scheduler (``scheduler``, e.g. ``tcp://host:8786``, whose workers the
user started with ``dask worker``) — the same code either way. Dask does the scheduling, the
retries and the bookkeeping of workers; this module only decides what to run and reports.

Resuming: a cell whose folder holds a ``result.json`` is finished
(:mod:`fgslam.sweep.cell`) and is never run again; a sweep started again runs what is
missing. A worker that dies during a cell (killed, out of memory) has its cell run again
elsewhere, up to ``retries`` times (Dask's ``distributed.scheduler.allowed-failures``), then
the cell is reported failed and the others go on. A cell whose run raises is reported failed
at once (the same settings would fail the same way). The failed cells, with why, are in
``failed.json``; a later start tries them again.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fgslam.io import safeio
from fgslam.sweep.cell import finished, run_cell
from fgslam.sweep.spec import SweepError, SweepSpec

CELLS = "cells"
# the local workers' settings: no stack sampling (every 10 ms by default, holding the GIL the
# pipeline's Python needs) and no malloc trimming at every 64 kB (Dask's default for its
# workers); each cell single-threaded in its numerical libraries. On the 40-cell benchmark
# (experiments/bench_sweep.py) Dask's defaults made a cell 1.6x as long as in a process pool.
WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.nanny.pre-spawn-environ": {
        "OMP_NUM_THREADS": 1,
        "MKL_NUM_THREADS": 1,
        "OPENBLAS_NUM_THREADS": 1,
    },
}


@dataclass
class SweepRun:
    """What a start of a sweep did: cells finished before (skipped), run now, failed (with
    why), and the wall time."""

    total: int
    skipped: int = 0
    ran: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0
    dashboard: str | None = None


def cell_folder(out: str | Path, cell_id: str) -> Path:
    return Path(out) / CELLS / cell_id


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    memory_limit: str | float = "auto",
    retries: int = 2,
    processes: bool = True,
    progress: Callable[[dict[str, Any]], None] | None = None,
    cell_fn: Callable[..., dict[str, Any]] = run_cell,
) -> SweepRun:
    """Run the cells of ``spec`` that are not finished in ``out`` (module doc); returns what
    happened. ``progress`` is called at the start (with ``dashboard``, the Dask dashboard's
    address) and after each cell with the counts (done, failed, running, to_do, total,
    eta_s). ``processes`` False: a LocalCluster of threads in this process
    (tests). ``cell_fn``: what runs a cell (:func:`fgslam.sweep.cell.run_cell`)."""
    import dask
    from distributed import Client, LocalCluster, as_completed

    if retries < 0:
        raise SweepError(f"retries must be >= 0, got {retries}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _write_index(spec, out)
    todo = [c for c in spec.cells if finished(cell_folder(out, c.id)) is None]
    run = SweepRun(total=len(spec.cells), skipped=len(spec.cells) - len(todo))
    if not todo:
        return run
    t0 = time.perf_counter()
    n_workers = workers or os.cpu_count() or 1
    with dask.config.set({**WORKER_CONFIG, "distributed.scheduler.allowed-failures": retries}):
        if scheduler:
            try:
                client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError) as e:
                raise SweepError(f"cannot reach the Dask scheduler {scheduler} ({e})") from None
            cluster = None
            workers_info = client.scheduler_info().get("workers", {}).values()
            n_workers = max(sum(w.get("nthreads", 1) for w in workers_info), 1)
        else:
            cluster = LocalCluster(
                n_workers=n_workers,
                threads_per_worker=1,
                processes=processes,
                memory_limit=memory_limit,
                dashboard_address=":0",
            )
            client = Client(cluster)
        run.dashboard = client.dashboard_link
        if progress is not None:
            progress(
                {
                    "done": run.skipped,
                    "failed": 0,
                    "running": min(len(todo), n_workers),
                    "to_do": len(todo),
                    "total": run.total,
                    "eta_s": None,
                    "dashboard": run.dashboard,
                }
            )
        # at most one cell per worker thread in flight: a worker that dies is blamed only
        # for the cell it was running (Dask counts a death against every task it held)
        queue = list(todo)
        futures: dict = {}

        def submit() -> None:
            c = queue.pop(0)
            folder = str(cell_folder(out, c.id))
            f = client.submit(cell_fn, c.settings, folder, c.id, key=f"cell-{c.id}", pure=False)
            futures[f] = c
            pending.add(f)

        pending = as_completed()
        for _ in range(min(n_workers, len(queue))):
            submit()
        try:
            durations: list[float] = []
            for fut in pending:
                c = futures[fut]
                try:
                    res = fut.result()
                    run.ran.append(c.id)
                    durations.append(float(res.get("wall_s", 0.0)))
                except Exception as e:  # the run's error, or KilledWorker after the retries
                    run.failed[c.id] = f"{type(e).__name__}: {e}".splitlines()[0][:500]
                if queue:
                    submit()
                if progress is not None:
                    left = len(todo) - len(run.ran) - len(run.failed)
                    mean = sum(durations) / len(durations) if durations else math.nan
                    progress(
                        {
                            "done": run.skipped + len(run.ran),
                            "failed": len(run.failed),
                            "running": min(left, n_workers),
                            "to_do": left,
                            "total": run.total,
                            "eta_s": mean * left / n_workers if durations else None,
                        }
                    )
        except BaseException:  # Ctrl-C: the finished cells stay; nothing half written
            for f in futures:
                f.cancel()
            raise
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    run.wall_s = time.perf_counter() - t0
    _write_failed(out, run.failed)
    return run


def _write_index(spec: SweepSpec, out: Path) -> None:
    """``sweep.json``: the sweep's name, source and every cell's id and settings (the
    report's table of contents; rewritten at each start)."""
    index = {
        "name": spec.name,
        "source": str(spec.source) if spec.source else None,
        "varying": list(spec.varying),
        "cells": [{"id": c.id, "settings": c.settings} for c in spec.cells],
    }
    safeio.write_text(out / "sweep.json", json.dumps(index, indent=1))


def _write_failed(out: Path, failed: dict[str, str]) -> None:
    path = out / "failed.json"
    if not failed:
        path.unlink(missing_ok=True)
        return
    safeio.write_text(path, json.dumps(failed, indent=1))


def sweep_function(
    fn: Callable[[dict[str, Any]], Any],
    grid: dict[str, list],
    out: str | Path,
    *,
    workers: int | None = None,
    name: str = "",
    extra: tuple[str, ...] = (),
    progress: Callable[[dict[str, Any]], None] | None = None,
    processes: bool = True,
) -> list[Any]:
    """An experiment's sweep: ``fn(settings)`` (a JSON-able result) for every combination
    of ``grid`` (settings as in a specification, ``extra`` names its own), as cells under
    ``out`` on a local cluster (resumable: :class:`fgslam.sweep.cell.FunctionCell`); returns
    the results in the grid's order. :class:`SweepError` when a cell failed."""
    from fgslam.sweep.cell import FunctionCell
    from fgslam.sweep.spec import spec_from_dict

    spec = spec_from_dict({"name": name or "sweep", "grid": grid}, extra=extra)
    run = run_sweep(
        spec,
        out,
        workers=workers,
        progress=progress,
        cell_fn=FunctionCell(fn),
        processes=processes,
    )
    if run.failed:
        raise SweepError(f"{len(run.failed)} cells failed: {run.failed}")
    return [finished(cell_folder(out, c.id))["result"] for c in spec.cells]
