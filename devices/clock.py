"""Time: the host's log clock, and the mapping of a device's own clock onto it.

Log time is what every frame and event is stamped with: seconds since the clock's origin on
the host's monotonic clock, multiplied by ``speed`` (1 for a real robot; K when the emulators
run K times faster than real time, so that log time keeps the simulated run's time scale).
"""

from __future__ import annotations

import threading
import time


class Clock:
    """Log time in s: ``(time.monotonic() - origin) * speed``. Thread safe.

    Drivers stamp every read with :meth:`now`; emulators schedule their output with it. The
    drivers and the emulators of one process may share a clock, so that their times agree.
    """

    def __init__(self, speed: float = 1.0, origin: float | None = None) -> None:
        if not speed > 0:
            raise ValueError(f"clock speed must be positive, got {speed}")
        self.speed = float(speed)
        # origin on time.monotonic(), which all processes of the machine share: a clock
        # made with another clock's origin and speed reads the same in another process
        self.origin = time.monotonic() if origin is None else float(origin)

    def now(self) -> float:
        """Current log time, s."""
        return (time.monotonic() - self.origin) * self.speed

    def wall(self, dt: float) -> float:
        """Wall-clock seconds that ``dt`` s of log time take."""
        return dt / self.speed

    def sleep_until(self, t: float, stop: threading.Event | None = None) -> bool:
        """Sleep until log time ``t``; False if ``stop`` was set meanwhile."""
        while True:
            dt = self.wall(t - self.now())
            if dt <= 0:
                return True
            if stop is not None:
                if stop.wait(min(dt, 0.5)):
                    return False
            else:
                time.sleep(min(dt, 0.5))


class DeviceTime:
    """Maps a device's free-running clock (an unsigned counter of microseconds that wraps at
    ``2**bits``) to log time.

    Each frame gives one observation ``t_host - t_device`` = clock offset + transport delay,
    and the delay is never negative: the least observation is the best offset estimate (a
    one-way minimum-delay filter). The estimate may creep up by ``drift`` s per s of host
    time, so that a device clock running slow is followed; a faster one is followed by new
    minima. A device clock that jumps backwards (a device restart) resets the filter. The
    mapped time is never later than the host stamp.
    """

    def __init__(self, drift: float = 2e-4, bits: int = 32) -> None:
        self.drift = drift
        self._wrap = 1 << bits
        self.restarts = 0  # backward jumps of the device clock seen
        self.reset()

    def reset(self) -> None:
        """Forget the device clock (a new device, or one that may have restarted)."""
        self._raw: int | None = None
        self._us = 0  # unwrapped device time, us
        self._offset: float | None = None
        self._t_ref = 0.0

    def map(self, device_us: int, t_host: float) -> float:
        """Log time of device time ``device_us`` observed in a frame read at ``t_host``."""
        if self._raw is not None:
            step = (device_us - self._raw) % self._wrap
            if step > self._wrap // 2:  # went backwards: the device restarted
                self.reset()
                self.restarts += 1
            else:
                self._us += step
        if self._raw is None:
            self._us = device_us
        self._raw = device_us
        t_dev = self._us * 1e-6
        obs = t_host - t_dev
        if self._offset is not None:
            predicted = self._offset + self.drift * (t_host - self._t_ref)
            if predicted <= obs:
                return t_dev + predicted
        self._offset, self._t_ref = obs, t_host
        return t_host
