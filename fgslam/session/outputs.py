"""The outputs of a localization (``fgslam localize``, ``fgslam online --map``):
trajectory.tum (every localized scan), trajectory_bridged.tum (every scan, the rest placed by
the odometry between localized ones), report.json and map.png (the saved map's occupancy
grid with the localized path, where it was localized and where it was lost)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fgslam.io import safeio


def plot_localization(session, res, path: str | Path) -> None:
    """Draw ``res`` (:class:`~fgslam.session.localize.LocalizationResult`) on ``session``'s
    grid into ``path`` (PNG, written atomically)."""
    grid = session.grid()
    rows, cols = grid.pixels.shape
    x0, y0 = grid.origin
    ext = (x0, x0 + cols * grid.resolution, y0, y0 + rows * grid.resolution)
    w = max(6.0, min(16.0, (ext[1] - ext[0]) / 4))
    h = max(4.0, min(12.0, w * (ext[3] - ext[2]) / max(ext[1] - ext[0], 1e-9)))
    fig, ax = plt.subplots(figsize=(w, h))
    try:
        ax.imshow(grid.pixels, cmap="gray", vmin=0, vmax=255, extent=ext, origin="upper")
        ax.plot(*session.poses[:, :2].T, color="0.6", lw=0.6, label="map's path")
        if len(res.truth):
            ax.plot(*res.truth[:, :2].T, color="tab:green", lw=0.8, label="true path")
        ok = np.isfinite(res.poses).all(axis=1)
        p = np.where(ok[:, None], res.poses, np.nan)
        ax.plot(p[:, 0], p[:, 1], color="tab:blue", lw=1.0, label="localized")
        for e in res.events:
            i = int(np.searchsorted(res.times, e["t"]))
            if e["event"] == "localized" and i < len(p) and ok[min(i, len(p) - 1)]:
                ax.plot(*e["pose"][:2], "o", color="tab:blue", ms=7, mfc="none")
            elif e["event"] == "lost" and 0 < i <= len(p):
                j = i - 1
                while j > 0 and not ok[j]:
                    j -= 1
                if ok[j]:
                    ax.plot(*p[j, :2], "x", color="tab:red", ms=8)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title("localization on the saved map (o: localized, x: lost)")
        ax.legend(loc="best", fontsize=8)
        with safeio.atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    finally:
        plt.close(fig)


def write_localization(
    session, res, out: str | Path, extra: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write trajectory.tum, trajectory_bridged.tum, map.png and report.json (its content,
    with ``extra``, returned) into the folder ``out``, each atomically."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rep = res.report()
    rep.update(extra or {})
    res.write_trajectory(out / "trajectory.tum")
    res.write_trajectory(out / "trajectory_bridged.tum", bridged=True)
    plot_localization(session, res, out / "map.png")
    safeio.write_text(out / "report.json", json.dumps(rep, indent=1))
    return rep


def summary(rep: dict[str, Any]) -> str:
    """The localization in one line."""
    loc_at = rep["localized_at"]
    if loc_at is None:
        return f"not localized: {rep['scans']} scans, no answer of the global search confirmed"
    msg = (
        f"localized at t = {loc_at:.2f} s ({rep['first_localization']['how']}); "
        f"{rep['scans_localized']} of {rep['scans']} scans localized (the rest bridged by "
        "the odometry in trajectory_bridged.tum), "
        f"{rep['relocalizations']} relocalizations, {len(rep['lost'])} times lost; "
        f"{rep['real_time_factor']}x real time"
    )
    err = rep.get("error_vs_truth")
    if err:
        msg += (
            f"; against the truth: {err['position_rmse_m']:.3f} m, "
            f"{err['heading_rmse_deg']:.2f} deg RMSE"
        )
    return msg
