"""Helpers shared by the device tests."""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable


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
