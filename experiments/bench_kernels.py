"""The compiled kernels (fgslam.scanmatch.kernels, fgslam.frontend.kernels) side by side with
their numpy references, and numba's compilation cost: a cold start (an empty cache: the kernel
compiles on its first call) against a warm one (compiled code loaded from the cache), each in
a fresh process.

Run: python experiments/bench_kernels.py [--repeat 200]
Prints a markdown table, a row per kernel: per-call time of the numpy reference and of the
compiled kernel, their ratio, and the first call's time in a cold and in a warm process. The
inputs: gather_sums a correlative search's level (361 beams, 41 rotations, 500 candidates);
the front end's a 361-beam scan of walls (segment_scan, with the line growing compiled,
against segment_scan_reference) and a 60-beam wall (fit_line's single fit with its
covariances and source Jacobians, against _fit_line_once_numpy; the end trimming, against
_trim_bounds_numpy).
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
from fgslam.scanmatch.kernels import gather_sums
from fgslam.frontend import fits, segmentation
from fgslam.config import SegmentParams
t1 = time.perf_counter()
kernel = sys.argv[1]
if kernel == "gather_sums":
    flat = np.zeros(100, dtype=np.uint8); base = np.zeros((1, 3), dtype=np.int64)
    gather_sums(flat, base, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))
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


def inputs(seed: int = 0):
    """A correlative search's level: a 400 x 400 grid, 361 points at 41 rotations, 500
    candidate translations within 10 cells."""
    rng = np.random.default_rng(seed)
    ny = 400
    flat = rng.integers(0, 256, 400 * ny, dtype=np.uint8)
    base = rng.integers(20 * ny, 380 * ny, (41, 361), dtype=np.int64)
    r = rng.integers(0, 41, 500, dtype=np.int64)
    off = rng.integers(-10, 11, 500) * ny + rng.integers(-10, 11, 500)
    return flat, base, r, off


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
        (
            "grow_lines (segment_scan)",
            per_call(segmentation.segment_scan_reference, seg, repeat),
            per_call(segmentation.segment_scan, seg, repeat),
        ),
        (
            "line_fit (one line fit)",
            per_call(fits._fit_line_once_numpy, args, repeat),
            per_call(fits._fit_line_once, args, repeat),
        ),
        (
            "trim_bounds",
            per_call(fits._trim_bounds_numpy, targs, repeat),
            per_call(kernels.trim_bounds, targs, repeat),
        ),
    ]


def start(cache_dir: str, kernel: str = "gather_sums") -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    cmd = [sys.executable, "-c", CHILD, kernel]
    out = subprocess.run(cmd, env=env, check=True, capture_output=True)
    return json.loads(out.stdout.decode().strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=200, help="calls timed per kernel")
    args = ap.parse_args()
    from fgslam.scanmatch.kernels import gather_sums, gather_sums_numpy

    flat, base, r, off = inputs()
    assert np.array_equal(gather_sums(flat, base, r, off), gather_sums_numpy(flat, base, r, off))
    t_np = per_call(gather_sums_numpy, (flat, base, r, off), args.repeat)
    t_nb = per_call(gather_sums, (flat, base, r, off), args.repeat)
    rows = [("gather_sums", t_np, t_nb), *frontend_rows(args.repeat)]
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
