"""The playback thread that feeds emulators (:mod:`devices.emulators`) their measurements at
their times: a time-ordered schedule of actions, each called at its due log time."""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

from devices.clock import Clock


class Playback:
    """Runs a time-ordered ``schedule`` of (run time, action) pairs in a thread: each action
    is called with the log time it is due at, ``offset + run time``.

    ``offset`` is the log time at which the run starts: with ``wait_for`` the playback first
    waits (up to ``wait_timeout`` wall s) until ``wait_for()`` is true - e.g. until every
    emulator's host is streaming - so that nothing of the run is sent before the drivers
    listen. Actions that fall behind run at once (the run then lags real time rather than
    skipping data).

    The schedule is computed ahead (a simulation is costly: ray casting, sonar echoes): its
    first ``lead`` s of run time (inf: all of it) in :meth:`start`, before any host can be
    waiting for data, the rest by a thread of its own, so that a busy host delays the start
    rather than the data: emulated devices keep their time as real ones do.
    """

    def __init__(
        self,
        clock: Clock,
        schedule: Iterable[tuple[float, Callable[[float], Any]]],
        *,
        wait_for: Callable[[], bool] | None = None,
        wait_timeout: float = 30.0,
        lead: float = 0.0,
        name: str = "emulator-playback",
    ) -> None:
        self.clock = clock
        self.schedule = schedule
        self.wait_for = wait_for
        self.wait_timeout = wait_timeout
        self.lead = lead
        self.offset = math.nan
        self.done = threading.Event()
        self.started = threading.Event()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._ahead: queue.Queue[tuple[float, Callable[[float], Any]] | None] = queue.Queue()
        self._computed = -math.inf  # run time of the last action computed
        self._all_computed = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._producer = threading.Thread(target=self._produce, name=f"{name}-ahead", daemon=True)

    def _fill(self, until: float) -> bool:
        """Compute the schedule up to run time ``until``; False once it is exhausted."""
        for item in self._items:
            self._ahead.put(item)
            self._computed = item[0]
            if self._computed >= until or self._stop.is_set():
                return True
        self._ahead.put(None)
        self._all_computed.set()
        return False

    def _produce(self) -> None:
        try:
            if not self._all_computed.is_set():
                self._fill(math.inf)
        except BaseException as exc:
            self.error = exc
            self._ahead.put(None)
            self._all_computed.set()

    def start(self) -> Playback:
        self._items = iter(self.schedule)
        self._fill(self.lead)
        self._producer.start()
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        try:
            if self.wait_for is not None:
                deadline = time.monotonic() + self.wait_timeout
                while not self.wait_for() and time.monotonic() < deadline:
                    if self._stop.wait(0.02):
                        return
            self.offset = self.clock.now()
            self.started.set()
            while (item := self._ahead.get()) is not None:
                t, action = item
                due = self.offset + t
                if not self.clock.sleep_until(due, self._stop):
                    return
                action(due)
        except BaseException as exc:
            self.error = exc
        finally:
            self.done.set()
