"""Writing the native fgslam log (docs/log-format.md): :class:`LogWriter`, incremental,
deterministic (the same events give byte-identical files, gzip included) and atomic (the log
appears at its path only when complete)."""

from __future__ import annotations

import contextlib
import os
from typing import Any

import numpy as np

from fgslam.config import RobotConfig
from fgslam.events import Event, LaserScan, SonarReading
from fgslam.io.logrecords import (
    FORMAT_NAME,
    FORMAT_VERSION,
    StrPath,
    _json,
    format_record,
    open_text,
)
from fgslam.io.safeio import is_special, temp_path


class LogWriter:
    """Writes a log incrementally: the header on construction, one line per :meth:`write`.

    A ``.gz`` name gives a gzip file; output is deterministic (byte-identical for the same
    arguments and events). The log is written to a temporary file in the same folder and
    renamed to ``path`` by :meth:`close`, so ``path`` never holds a partial log; leaving the
    context manager by an exception (or :meth:`abort`) deletes the temporary file instead.
    """

    def __init__(
        self, path: StrPath, config: RobotConfig, world: str, meta: dict[str, Any] | None = None
    ) -> None:
        if "\n" in world or "\r" in world:
            raise ValueError("world name must not contain a line break")
        lines = [f"{FORMAT_NAME} {FORMAT_VERSION}", f"CONFIG {_json(config.to_dict())}"]
        lines.append(f"WORLD {world}")
        if meta:
            lines.append(f"META {_json(meta, sort_keys=True)}")
        self.path = path
        self.config = config
        self._n_beams = config.laser.n_beams
        self._n_arrays = len(config.sonar.arrays)
        self._tmp = path if is_special(path) else temp_path(path)
        self._f = open_text(self._tmp, "w")
        self._done = False
        self._f.write("\n".join(lines) + "\n")

    def write(self, event: Event) -> None:
        """Append one event; ValueError if it does not fit the configuration or the format (a
        scan without its own bearings must have the configured beam count)."""
        if (
            isinstance(event, LaserScan)
            and event.bearings is None
            and np.size(event.ranges) != self._n_beams
        ):
            raise ValueError(
                f"laser scan has {np.size(event.ranges)} ranges, configuration has "
                f"n_beams={self._n_beams}"
            )
        if isinstance(event, SonarReading) and not 0 <= event.array < self._n_arrays:
            raise ValueError(f"sonar array {event.array} not in the configuration")
        self._f.write(format_record(event) + "\n")

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        """Finish the log: flush, close and rename it into place."""
        if self._done:
            return
        self._done = True
        try:
            self._f.close()
            if self._tmp != self.path:
                os.replace(self._tmp, self.path)
        except BaseException:
            self._discard()
            raise

    def abort(self) -> None:
        """Give up: delete the temporary file, leave ``path`` as it was."""
        if self._done:
            return
        self._done = True
        try:
            self._f.close()
        finally:
            self._discard()

    def _discard(self) -> None:
        if self._tmp != self.path:
            with contextlib.suppress(OSError):
                os.unlink(self._tmp)

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
