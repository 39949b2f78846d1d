"""Helpers shared by the device tests."""

from __future__ import annotations

import contextlib
import itertools
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    """``data`` split at the positions ``cuts`` (taken modulo its length + 1)."""
    points = sorted({c % (len(data) + 1) for c in cuts})
    return [data[a:b] for a, b in itertools.pairwise([0, *points, len(data)])]


def wait_until(cond: Callable[[], bool], timeout: float = 20.0, step: float = 0.01) -> bool:
    """Poll ``cond`` until it holds or ``timeout`` wall seconds pass (generous: the
    machine may be loaded; tests assert on content, not on time)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(step)
    return True


@contextlib.contextmanager
def cpu_hogs(per_core: int = 2) -> Iterator[int]:
    """Busy processes loading every core (``per_core`` each) while the block runs: a loaded
    machine, started and stopped by the test. Yields their number."""
    n = per_core * (os.cpu_count() or 1)
    procs = [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], stdin=subprocess.DEVNULL)
        for _ in range(n)
    ]
    try:
        yield n
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()
