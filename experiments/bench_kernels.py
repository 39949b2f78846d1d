"""The compiled kernels (fgslam.scanmatch.kernels) side by side with their numpy references,
and numba's compilation cost: a cold start (an empty cache: the kernel compiles on its first
call) against a warm one (compiled code loaded from the cache), each in a fresh process.

Run: python experiments/bench_kernels.py [--repeat 200]
Prints a markdown table: per-call time of the numpy reference and of the compiled kernel on
inputs the size of a correlative search's level (361 beams, 41 rotations, 500 candidates),
their ratio, and the first call's time in a cold and in a warm process.
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
import time, json
t0 = time.perf_counter()
import numpy as np
from fgslam.scanmatch.kernels import gather_sums
t1 = time.perf_counter()
flat = np.zeros(100, dtype=np.uint8); base = np.zeros((1, 3), dtype=np.int64)
gather_sums(flat, base, np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))
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


def per_call(fn, args, repeat: int) -> float:
    fn(*args)
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn(*args)
    return (time.perf_counter() - t0) / repeat


def start(cache_dir: str) -> dict:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, check=True, capture_output=True)
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
    with tempfile.TemporaryDirectory() as cache:
        cold = start(cache)  # compiles, writes the cache
        warm = start(cache)  # loads it
    print(
        "| kernel | numpy (ms/call) | compiled (ms/call) | ratio | first call cold (s) | "
        "first call warm (s) |"
    )
    print("|---|---|---|---|---|---|")
    print(
        f"| gather_sums | {1e3 * t_np:.3f} | {1e3 * t_nb:.3f} | {t_np / t_nb:.1f}x | "
        f"{cold['first_call_s']:.2f} | {warm['first_call_s']:.3f} |"
    )


if __name__ == "__main__":
    main()
