"""An occupancy grid from scans at known poses, written and read in the ROS map_server
format (``map.pgm``: 8-bit greyscale, row 0 the top of the map; ``map.yaml``: the image,
the resolution, the origin of the lower-left pixel and the thresholds).

Every beam marks the cells it crossed as seen free and its end cell as seen occupied; a
cell is occupied when at least ``OCCUPIED`` of its observations were hits, free when at
most ``FREE``, unknown (never seen, or in between) otherwise. Frames: world (m, rad)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from factors.geometry import transform_points
from fgslam.io import safeio

OCCUPIED = 0.65  # map_server's occupied_thresh
FREE = 0.196  # map_server's free_thresh
PIXEL_OCCUPIED, PIXEL_FREE, PIXEL_UNKNOWN = 0, 254, 205  # map_saver's values
MAX_CELLS = 25_000_000  # a wider map gets coarser cells


@dataclass
class OccupancyGrid:
    """``pixels`` (rows, cols) uint8 as in map.pgm (row 0 the top, i.e. the largest y);
    ``origin`` (x, y) of the lower-left pixel's corner, m; ``resolution`` m per cell."""

    pixels: NDArray[np.uint8]
    origin: tuple[float, float]
    resolution: float

    def occupied(self) -> NDArray[np.bool_]:
        return self.pixels == PIXEL_OCCUPIED

    def free(self) -> NDArray[np.bool_]:
        return self.pixels == PIXEL_FREE

    def cell_of(self, xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """(row, col) of world points (N, 2), m; they may lie outside the grid."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        col = np.floor((xy[:, 0] - self.origin[0]) / self.resolution).astype(np.int64)
        up = np.floor((xy[:, 1] - self.origin[1]) / self.resolution).astype(np.int64)
        return self.pixels.shape[0] - 1 - up, col


def occupancy_grid(
    poses: NDArray[np.float64],
    scans: list[NDArray[np.float64] | None],
    laser_xy: tuple[float, float],
    resolution: float = 0.05,
) -> OccupancyGrid:
    """The grid of ``scans`` (robot-frame points, m; None: none) seen from the laser at
    ``laser_xy`` on the robot (m) at ``poses`` ((N, 3) world)."""
    origins, ends = [], []
    for pose, pts in zip(np.asarray(poses, dtype=float).reshape(-1, 3), scans, strict=True):
        if pts is None or len(pts) == 0 or not np.isfinite(pose).all():
            continue
        p = np.asarray(pts, dtype=float)
        p = p[np.isfinite(p).all(axis=1)]
        ends.append(transform_points(pose, p))
        origins.append(np.repeat(transform_points(pose, np.array([laser_xy])), len(p), axis=0))
    if not ends:
        return OccupancyGrid(np.full((1, 1), PIXEL_UNKNOWN, np.uint8), (0.0, 0.0), resolution)
    end, org = np.vstack(ends), np.vstack(origins)
    lo = np.minimum(end.min(axis=0), org.min(axis=0)) - 2 * resolution
    hi = np.maximum(end.max(axis=0), org.max(axis=0)) + 2 * resolution
    res = max(resolution, math.sqrt(float(np.prod(hi - lo)) / MAX_CELLS))
    nx, ny = (np.ceil((hi - lo) / res).astype(int) + 1).tolist()
    hits = np.zeros(nx * ny, np.int64)
    seen = np.zeros(nx * ny, np.int64)

    def flat(xy: NDArray[np.float64]) -> NDArray[np.int64]:
        ij = np.floor((xy - lo) / res).astype(np.int64)
        return ij[:, 0] * ny + ij[:, 1]

    hit_cells = flat(end)
    hits += np.bincount(hit_cells, minlength=nx * ny)
    seen += np.bincount(hit_cells, minlength=nx * ny)
    # the free cells: a sample every resolution along each beam, short of its end cell
    d = end - org
    length = np.hypot(d[:, 0], d[:, 1])
    n = max(int(np.ceil(length.max() / res)), 1)
    chunk = max(1, 4_000_000 // n)
    s = np.arange(n) * res
    for a in range(0, len(end), chunk):
        b = min(a + chunk, len(end))
        ln = length[a:b, None]
        keep = s[None, :] < ln - res
        frac = s[None, :] / np.maximum(ln, 1e-9)
        x = org[a:b, 0:1] + frac * d[a:b, 0:1]
        y = org[a:b, 1:2] + frac * d[a:b, 1:2]
        seen += np.bincount(flat(np.column_stack([x[keep], y[keep]])), minlength=nx * ny)
    p_occ = np.divide(hits, seen, out=np.zeros(nx * ny), where=seen > 0)
    pix = np.full(nx * ny, PIXEL_UNKNOWN, np.uint8)
    pix[(seen > 0) & (p_occ <= FREE)] = PIXEL_FREE
    pix[(seen > 0) & (p_occ >= OCCUPIED)] = PIXEL_OCCUPIED
    # (nx, ny) with y up -> image rows top to bottom
    img = pix.reshape(nx, ny).T[::-1].copy()
    return OccupancyGrid(img, (float(lo[0]), float(lo[1])), float(res))


def write_map(grid: OccupancyGrid, folder: str | Path, name: str = "map") -> None:
    """``name``.pgm (binary P5) and ``name``.yaml in ``folder``, each written atomically."""
    folder = Path(folder)
    rows, cols = grid.pixels.shape
    header = f"P5\n# fgslam occupancy grid, {grid.resolution:g} m/cell\n{cols} {rows}\n255\n"
    with safeio.atomic_path(folder / f"{name}.pgm") as tmp:
        tmp.write_bytes(header.encode("ascii") + grid.pixels.astype(np.uint8).tobytes())
    yaml = (
        f"image: {name}.pgm\n"
        f"resolution: {grid.resolution:.6g}\n"
        f"origin: [{grid.origin[0]:.6f}, {grid.origin[1]:.6f}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED}\n"
        f"free_thresh: {FREE}\n"
        "mode: trinary\n"
    )
    safeio.write_text(folder / f"{name}.yaml", yaml)
