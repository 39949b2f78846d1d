"""A sweep's report (``fgslam sweep --report DIR``; docs/sweeps.md): every finished cell's
figures, and per setting (the varied settings but the seed) their count, mean, median and
spread (standard deviation, min, max), as CSV, a Markdown table and box plots."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from fgslam.io import safeio
from fgslam.sweep.cell import finished
from fgslam.sweep.engine import cell_folder
from fgslam.sweep.spec import SweepError

# the figures summarized and drawn, in order, with their labels
SHOWN = {
    "ate_m": "ATE RMSE (m)",
    "relations_m": "relations error (m)",
    "relations_deg": "relations error (deg)",
    "nees_mean": "pose NEES (mean)",
    "realtime_factor": "real-time factor",
}


def collect(out: str | Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The sweep's index (``sweep.json``) and the results of its finished cells."""
    out = Path(out)
    try:
        index = json.loads((out / "sweep.json").read_text())
    except FileNotFoundError:
        raise SweepError(f"{out}: not a sweep folder (no sweep.json)") from None
    except (OSError, ValueError) as e:
        raise SweepError(f"{out}/sweep.json: unreadable ({e})") from None
    results = []
    for c in index.get("cells", []):
        r = finished(cell_folder(out, c["id"]))
        if r is not None:
            results.append({**r, "cell": c["id"]})
    return index, results


def group_key(settings: dict[str, Any], varying: list[str]) -> str:
    """A setting's name: its varied settings but the seed, ``k=v`` joined."""
    parts = [f"{k}={settings[k]}" for k in varying if k != "seed" and k in settings]
    return ", ".join(parts) or "all"


def summarize(index: dict[str, Any], results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per setting: n, and per figure of :data:`SHOWN` mean, median, std, min, max
    over the cells that have it (NaN where none has)."""
    varying = index.get("varying", [])
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in results:
        groups.setdefault(group_key(r["settings"], varying), []).append(r)
    rows = []
    for name, rs in groups.items():
        row: dict[str, Any] = {"setting": name, "cells": len(rs)}
        for m in SHOWN:
            v = np.array([x["metrics"].get(m) for x in rs if x["metrics"].get(m) is not None])
            v = v[np.isfinite(v.astype(float))] if len(v) else v
            stats = (
                (v.mean(), np.median(v), v.std(), v.min(), v.max()) if len(v) else (math.nan,) * 5
            )
            for s, x in zip(("mean", "median", "std", "min", "max"), stats, strict=True):
                row[f"{m}_{s}"] = float(x)
        row["failed_or_partial"] = int(sum(x["metrics"].get("partial", 0) for x in rs))
        rows.append(row)
    return rows


def write_report(out: str | Path, to: str | Path | None = None) -> dict[str, Any]:
    """Write ``cells.csv`` (every finished cell), ``summary.csv``, ``summary.md`` and
    ``boxplots.png`` into ``to`` (default: ``out``); returns what it wrote."""
    index, results = collect(out)
    if not results:
        raise SweepError(f"{out}: no finished cell to report on")
    to = Path(to or out)
    to.mkdir(parents=True, exist_ok=True)
    rows = summarize(index, results)
    varying = index.get("varying", [])
    cells = []
    for r in results:
        cells.append(
            {
                "cell": r["cell"],
                **{k: r["settings"].get(k) for k in varying},
                **r["metrics"],
                "wall_s": r.get("wall_s"),
            }
        )
    _write_csv(to / "cells.csv", cells)
    _write_csv(to / "summary.csv", rows)
    safeio.write_text(to / "summary.md", markdown(index, rows))
    boxplots(index, results, to / "boxplots.png")
    return {"cells": len(results), "settings": len(rows), "folder": str(to)}


def markdown(index: dict[str, Any], rows: list[dict[str, Any]]) -> str:
    """The summary as a Markdown table: per setting, the cells and mean / median (std) of
    each figure."""
    head = ["setting", "cells", *SHOWN.values()]
    lines = [f"# {index.get('name', 'sweep')}", "", "| " + " | ".join(head) + " |"]
    lines.append("|" + "---|" * len(head))
    for r in rows:
        vals = []
        for m in SHOWN:
            mean = r[f"{m}_mean"]
            vals.append(
                "-"
                if math.isnan(mean)
                else f"{mean:.4g} / {r[f'{m}_median']:.4g} ({r[f'{m}_std']:.2g})"
            )
        lines.append(f"| {r['setting']} | {r['cells']} | " + " | ".join(vals) + " |")
    lines += ["", "mean / median (standard deviation) over the cells of each setting", ""]
    return "\n".join(lines)


def boxplots(index: dict[str, Any], results: list[dict[str, Any]], path: Path) -> None:
    """One box plot per figure that any cell has, a box per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    varying = index.get("varying", [])
    names = sorted({group_key(r["settings"], varying) for r in results})
    shown = [m for m in SHOWN if any(r["metrics"].get(m) is not None for r in results)]
    fig, axes = plt.subplots(
        len(shown), 1, figsize=(max(6, 1.2 * len(names) + 2), 2.6 * len(shown)), squeeze=False
    )
    for ax, m in zip(axes[:, 0], shown, strict=True):
        data = [
            [
                r["metrics"][m]
                for r in results
                if group_key(r["settings"], varying) == n and r["metrics"].get(m) is not None
            ]
            for n in names
        ]
        ax.boxplot([d if d else [math.nan] for d in data], showmeans=True)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(SHOWN[m], fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].set_title(str(index.get("name", "sweep")))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=110)
    plt.close(fig)
    with safeio.atomic_path(path) as tmp:
        tmp.write_bytes(buf.getvalue())


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    for r in rows:
        w.writerow(r)
    safeio.write_text(path, buf.getvalue())
