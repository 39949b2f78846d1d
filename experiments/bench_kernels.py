"""The compiled kernels (fgslam.scanmatch.kernels, fgslam.frontend.kernels) side by side with
their numpy references, and numba's compilation cost: a cold start (an empty cache: the kernel
compiles on its first call) against a warm one (compiled code loaded from the cache), each in
a fresh process.

Run: python experiments/bench_kernels.py [--repeat 200]
Prints a markdown table, a row per kernel: per-call time of the numpy reference and of the
compiled kernel, their ratio, and the first call's time (on a tiny input) in a cold and in a
warm process. Every compiled result is checked against its reference before it is timed.

The scan matcher's inputs: a simulated scan (361 beams, 1 cm noise, fgslam.sim.raycast) of an
8 x 5 m box room with a pillar, prepared as a Reference with the configured MatchParams
(361 points, a 73 x 147 grid of 4 cm cells), and a second scan from up to 0.3 m / 0.1 rad away.
branch_and_bound: the whole correlative search (search._search against search._search_numpy:
the same window and pyramid, the branch and bound compiled or in numpy; the same candidates and
scores) from a guess off the truth, 39 rotations x 17 x 17 translations; icp_loop: the whole
ICP (icp._icp against icp._icp_numpy, the inliers' Jacobians included) from a start off the
truth; local_lines and polyline_cells: the Reference's local lines and polyline cells over its
binned points (kernels.cells, built once) against reference._normals_numpy and
reference._polyline_cells_numpy over a cKDTree (built once); splat: the likelihood kernel
stamped around the polyline's cells (the Reference's grid). (A compiled max-pooling of the
search's crop, 28 124 cells, 4 levels, ran 0.7x numpy's: it stays numpy, search._pool.) The
front end's: a
361-beam scan of walls (segment_scan, with the line growing compiled, against
segment_scan_reference) and a 60-beam wall (fit_line's single fit with its covariances and
source Jacobians, against _fit_line_once_numpy; the end trimming, against _trim_bounds_numpy).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

CHILD = """
import sys, time, json
t0 = time.perf_counter()
import numpy as np
from fgslam.scanmatch import kernels as sk
from fgslam.frontend import fits, segmentation
from fgslam.config import SegmentParams
t1 = time.perf_counter()
kernel = sys.argv[1]
p = np.column_stack([np.linspace(0.0, 1.0, 20), np.zeros(20)])
if kernel == "branch_and_bound":
    levels = np.zeros((2, 200), dtype=np.uint8); base = np.full((1, 3), 100, dtype=np.int64)
    sk.branch_and_bound(levels, base, 1, 2, 2, 10, 3, 0.1, 10)
elif kernel == "icp_loop":
    nrm = np.tile([0.0, 1.0], (20, 1))
    sk.icp_loop(sk.cells(p, 0.2), nrm, p.copy(), p + 0.01, np.zeros(3), 0.02, 3.0, 0.2, 5)
elif kernel == "local_lines":
    sk.local_lines(sk.cells(p, 0.2), 10, 0.25, 4e-4)
elif kernel == "polyline_cells":
    sk.polyline_cells(sk.cells(p, 0.2), 0.2, np.array([-0.1, -0.1]), 0.04, (32, 6))
elif kernel == "splat":
    off = np.array([-1, 0, 1], dtype=np.int64)
    sk.splat(np.array([5], dtype=np.int64), off, np.array([1, 2, 1], dtype=np.uint8), 10)
elif kernel == "grow_lines":
    segmentation.segment_scan(np.linspace(-1, 1, 20), np.full(20, 2.0), SegmentParams())
else:
    p = np.linspace(0.0, 0.5, 10); r = 2.0 / np.cos(0.2 - p); ok = np.ones(10, dtype=bool)
    if kernel == "line_fit":
        fits._fit_line_once(p, r, ok, 0.01, [0.01], 10, None, [np.ones(10), r])
    else:
        fits.kernels.trim_bounds(p, r, ok, 0.2, 2.0, 3.0)
t2 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1}))
"""


def box_scans(seed: int = 0):
    """A Reference of the box room's first scan (fgslam.sim.scenes.box_room_scans), the
    query scan, the query's true pose in the reference's frame, the MatchParams and the
    random generator."""
    from fgslam.config import load_config
    from fgslam.scanmatch import MatchParams, Reference
    from fgslam.sim.scenes import box_room_scans

    ref_points, query, truth, rng = box_room_scans(seed)
    params = MatchParams.from_config(load_config())
    return Reference.build(ref_points, params), query, truth, params, rng


def frontend_inputs(seed: int = 0):
    """A 361-beam scan of four walls (1 cm noise, a few invalid beams), and one wall of 60
    beams with the front end's systematic errors and sources."""
    rng = np.random.default_rng(seed)
    phi = np.radians(np.arange(-90, 90.5, 0.5))
    r = np.empty(phi.size)
    for a, b, alpha, d in [(0, 90, -1.2, 3.0), (90, 200, 0.1, 4.0), (200, 300, 0.9, 2.5)]:
        r[a:b] = d / np.cos(alpha - phi[a:b])
    r[300:] = 5.0
    r += rng.normal(0.0, 0.01, phi.size)
    r[rng.random(phi.size) < 0.02] = np.nan
    p = np.radians(np.linspace(-20, 20, 60))
    rr = 3.0 / np.cos(0.1 - p) + rng.normal(0.0, 0.01, p.size)
    return phi, r, p, rr


def per_call(fn, args, repeat: int) -> float:
    fn(*args)
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn(*args)
    return (time.perf_counter() - t0) / repeat


def row(name: str, reference, compiled, args, repeat: int, compiled_args=None):
    """(name, numpy s/call, compiled s/call): ``reference`` and ``compiled`` timed on
    ``args`` (the compiled one on ``compiled_args`` where its signature differs)."""
    fast = args if compiled_args is None else compiled_args
    return name, per_call(reference, args, repeat), per_call(compiled, fast, repeat)


def scanmatch_rows(repeat: int) -> list[tuple[str, float, float]]:
    """(kernel, numpy s/call, compiled s/call) of the scan matcher's kernels on a box room's
    scans, each checked against its reference first."""
    import math

    from fgslam.scanmatch import icp, kernels, search
    from fgslam.scanmatch.reference import _normals_numpy, _polyline_cells_numpy

    ref, q, truth, params, rng = box_scans()
    tree = ref.tree
    # the search from a guess off the truth
    guess = truth + np.array([*rng.uniform(-0.1, 0.1, 2), rng.uniform(-0.05, 0.05)])
    got, want = search._search(ref, q, guess, params), search._search_numpy(ref, q, guess, params)
    assert np.array_equal(got.poses, want.poses) and np.array_equal(got.scores, want.scores)
    s_args = (ref, q, guess, params)
    # ICP from a start off the truth
    start = truth + np.array([*rng.uniform(-0.06, 0.06, 2), rng.uniform(-0.02, 0.02)])
    got, want = icp._icp(ref, q, start, params), icp._icp_numpy(ref, q, start, params)
    np.testing.assert_allclose(got.pose, want.pose, rtol=0, atol=1e-9)
    assert got.iterations == want.iterations
    i_args = (ref, q, start, params)
    # the Reference's local lines and polyline cells, as Reference.build makes them
    p, c = ref.points, ref.cells
    l_args = (c, params.normal_k, params.normal_radius, params.sigma_range**2)
    ln_args = (p, tree, params)
    got, want = kernels.local_lines(*l_args), _normals_numpy(*ln_args)
    for x, y in zip(got, want, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9)
    res = ref.resolution
    reach = math.ceil(3.0 * ref._blur / res) + 1
    shape = tuple(np.floor((p.max(axis=0) - p.min(axis=0)) / res).astype(int) + 2 * reach + 1)
    pc = (params.link_distance, ref.origin, res, shape)
    occ = kernels.polyline_cells(c, *pc)
    assert np.array_equal(occ, _polyline_cells_numpy(p, tree, *pc))
    # the likelihood kernel splatted around them (the Reference's grid)
    k = np.arange(-reach, reach + 1)
    kx, ky = np.meshgrid(k, k, indexing="ij")
    kd = np.hypot(kx, ky).ravel() * res
    use = kd <= 3.0 * ref._blur
    off = (kx.ravel() * shape[1] + ky.ravel())[use]
    val = np.round(255.0 * np.exp(-0.5 * (kd[use] / ref._blur) ** 2)).astype(np.uint8)
    sp_args = (occ, off, val, shape[0] * shape[1])
    assert np.array_equal(kernels.splat(*sp_args).reshape(shape), ref.grid)
    assert np.array_equal(kernels.splat(*sp_args), kernels.splat_numpy(*sp_args))
    return [
        row(
            "branch_and_bound (search._search)",
            search._search_numpy,
            search._search,
            s_args,
            repeat,
        ),
        row("icp_loop (icp._icp)", icp._icp_numpy, icp._icp, i_args, repeat),
        row("local_lines", _normals_numpy, kernels.local_lines, ln_args, repeat, l_args),
        row(
            "polyline_cells",
            _polyline_cells_numpy,
            kernels.polyline_cells,
            (p, tree, *pc),
            repeat,
            (c, *pc),
        ),
        row("splat", kernels.splat_numpy, kernels.splat, sp_args, repeat),
    ]


def frontend_rows(repeat: int) -> list[tuple[str, float, float]]:
    """(kernel, numpy s/call, compiled s/call) of the front end's kernels, each checked
    against its reference first."""
    from fgslam.config import SegmentParams
    from fgslam.frontend import fits, kernels, segmentation

    phi, r, p, rr = frontend_inputs()
    sp = SegmentParams()
    assert segmentation.segment_scan(phi, r, sp) == segmentation.segment_scan_reference(phi, r, sp)
    ok = np.ones(p.size, dtype=bool)
    args = (p, rr, ok, 0.01, [0.01, 0.01 * rr], 10, fits.RESIDUAL_TEST, [np.ones(p.size), rr])
    got, want = fits._fit_line_once(*args), fits._fit_line_once_numpy(*args)
    np.testing.assert_allclose(got.cov, want.cov, rtol=1e-9)
    a, d = want.params
    targs = (p, rr, ok, float(a), float(d), 3.0)
    assert tuple(kernels.trim_bounds(*targs)) == fits._trim_bounds_numpy(*targs)
    seg = (phi, r, sp)
    return [
        row(
            "grow_lines (segment_scan)",
            segmentation.segment_scan_reference,
            segmentation.segment_scan,
            seg,
            repeat,
        ),
        row(
            "line_fit (one line fit)", fits._fit_line_once_numpy, fits._fit_line_once, args, repeat
        ),
        row("trim_bounds", fits._trim_bounds_numpy, kernels.trim_bounds, targs, repeat),
    ]


def start(cache_dir: str, kernel: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    cmd = [sys.executable, "-c", CHILD, kernel]
    out = subprocess.run(cmd, env=env, check=True, capture_output=True)
    return json.loads(out.stdout.decode().strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=200, help="calls timed per kernel")
    args = ap.parse_args()
    rows = [*scanmatch_rows(args.repeat), *frontend_rows(args.repeat)]
    print(
        "| kernel | numpy (ms/call) | compiled (ms/call) | ratio | first call cold (s) | "
        "first call warm (s) |"
    )
    print("|---|---|---|---|---|---|")
    for name, t_np, t_nb in rows:
        with tempfile.TemporaryDirectory() as cache:
            kernel = name.split()[0]
            cold = start(cache, kernel)  # compiles, writes the cache
            warm = start(cache, kernel)  # loads it
        print(
            f"| {name} | {1e3 * t_np:.3f} | {1e3 * t_nb:.3f} | {t_np / t_nb:.1f}x | "
            f"{cold['first_call_s']:.2f} | {warm['first_call_s']:.3f} |"
        )


if __name__ == "__main__":
    main()
