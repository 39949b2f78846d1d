"""What every foreign-log reader shares: the error type, reading text files (gzip looked
through), the robot configuration derived from the data and the one-line warnings about an
input. The reader interface and its problems are in :mod:`fgslam.io.readers.source`; the
odometry of logs that give it as poses (the virtual differential drive, the hold of stale
odometry, implausible jumps, the file-order chain of the relations benchmark) in
:mod:`fgslam.io.readers.odometry`. Both are imported here too, where readers and tests have
always found them.

Readers yield the project's own events (:mod:`fgslam.events`), so everything downstream (front
end, runner, backends, ``fgslam convert``) works on them unchanged. Units SI, REP-103 frames.
"""

from __future__ import annotations

import dataclasses
import gzip
import io
import math
import zlib
from collections.abc import Iterator
from typing import IO, Any

from fgslam.config import SICK_LMS_SIGMA_RANGE, Mount, RobotConfig, load_config
from fgslam.errors import ReaderError
from fgslam.frontend.fits import RESIDUAL_TEST
from fgslam.io.readers.odometry import (
    VIRTUAL_ENCODER_STEPS,
    VIRTUAL_K,
    VIRTUAL_K_D,
    VIRTUAL_METRES_PER_TICK,
    VIRTUAL_WHEELBASE,
)
from fgslam.io.readers.sanity import OdometryLimits
from fgslam.io.readers.source import (
    StrPath,
    clock_warnings,
)

RESIDUAL_LEVEL = RESIDUAL_TEST  # real logs: fit covariances scaled by their residual


def open_lines(path: StrPath) -> Iterator[tuple[int, str]]:
    """(line number, text without EOL) of a text file, gzip detected by its magic bytes.
    Corrupt or truncated gzip data and undecodable bytes raise :class:`ReaderError`."""
    name = str(path)
    try:
        raw = open(path, "rb")
    except OSError as exc:
        raise ReaderError(f"{name}: cannot open: {exc.strerror or exc}") from None
    gz = raw.peek(2)[:2] == b"\x1f\x8b"
    f: IO[bytes] = gzip.GzipFile(fileobj=raw, mode="rb") if gz else raw
    n = 0
    try:
        while True:
            try:
                line = f.readline(1 << 23)
            except (EOFError, zlib.error, OSError) as exc:
                what = "corrupt or truncated gzip data" if gz else "read error"
                where = f"after line {n}" if n else "at the start"
                raise ReaderError(f"{name}: {what} {where} ({exc})") from None
            if not line:
                return
            n += 1
            yield n, line.decode("utf-8", errors="replace").rstrip("\r\n")
    finally:
        f.close()
        raw.close()


def head_text(path: StrPath, nbytes: int = 4096) -> str:
    """The first bytes of a (possibly gzipped) file as text, for format sniffing."""
    with open(path, "rb") as raw:
        data = raw.read(2)
        raw.seek(0)
        if data == b"\x1f\x8b":
            try:
                with gzip.GzipFile(fileobj=raw) as g:
                    data = g.read(nbytes)
            except (EOFError, zlib.error, OSError):
                data = b""
        else:
            data = raw.read(nbytes)
    return io.BytesIO(data).read().decode("utf-8", errors="replace")


def derived_config(
    n_beams: int,
    fov_deg: float = 180.0,
    *,
    max_range: float = 80.0,
    sigma_range: float = SICK_LMS_SIGMA_RANGE,
    range_resolution: float = 0.01,
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
    name: str = "log robot",
) -> RobotConfig:
    """The default configuration with the laser of the log (``n_beams`` over ``fov_deg``,
    first beam at -fov/2, mounted at ``mount`` (x, y, yaw rad), stamps without a known
    transmission delay) and the virtual differential drive of the reader's odometry (0.1 mm
    per tick, wheelbase 2 m, k_r = k_l = 0.5 and k_d = 0.1 per sample of at most 5 cm / 2
    deg; no wheel calibration estimated). The sonar section stays the default; these logs
    have no advanced sonar."""
    cfg = load_config()
    laser = dataclasses.replace(
        cfg.laser,
        mount=Mount(float(mount[0]), float(mount[1]), math.degrees(mount[2])),
        n_beams=int(n_beams),
        fov_deg=float(fov_deg),
        range_resolution=range_resolution,
        sigma_range=sigma_range,
        max_range=max_range,
        delay_min=0.0,
        delay_max=0.0,
        baud_rate=500000,
    )
    odo = dataclasses.replace(
        cfg.odometry,
        wheelbase=VIRTUAL_WHEELBASE,
        wheel_radius_right=VIRTUAL_METRES_PER_TICK * VIRTUAL_ENCODER_STEPS / (2 * math.pi),
        wheel_radius_left=VIRTUAL_METRES_PER_TICK * VIRTUAL_ENCODER_STEPS / (2 * math.pi),
        encoder_steps_per_rev=VIRTUAL_ENCODER_STEPS,
        k_r=VIRTUAL_K,
        k_l=VIRTUAL_K,
        k_d=VIRTUAL_K_D,
        hole_tolerance=OdometryLimits().hole,
        # the virtual drive's "wheels" replay the log's odometry poses, which already hold
        # the robot's own calibration: no physical radii to estimate (and on Freiburg 079
        # estimating them took the relations from 0.037 to 0.129 m: experiments/README.md,
        # real_relations.py)
        calibration="off",
    )
    return dataclasses.replace(
        cfg,
        robot=dataclasses.replace(cfg.robot, name=name),
        laser=laser,
        odometry=odo,
        frontend=dataclasses.replace(cfg.frontend, residual_level=RESIDUAL_LEVEL),
        source="<derived from the log>",
    )


MIN_SCANS = 10  # fewer scans than this: "almost nothing to process"


def input_warnings(
    scans: int,
    travel: float,
    odometry: dict[str, Any] | None = None,
    clock: dict[str, Any] | None = None,
    implausible: bool = True,
) -> list[str]:
    """One-line warnings about an input that gives almost nothing to process, no motion,
    mostly holes, implausible odometry skipped (``odometry``: the reader's odometry notes;
    ``implausible`` False: the reader notes those in the plausibility findings, which word
    the warning), or no usable clock (``clock``: the record of
    :func:`fgslam.io.readers.sanity.choose_clock`), for the console and ``report.json``."""
    out = clock_warnings(clock)
    if scans < MIN_SCANS:
        out.append(f"only {scans} laser scans: almost nothing to process")
    if scans >= 2 and travel < 1e-3:
        out.append("the odometry never moves: the robot stood still, or the log has no odometry")
    if odometry and odometry.get("holes"):
        out.append(
            f"{odometry['holes']} odometry holes ({odometry.get('hole_seconds', 0):g} s without "
            "odometry while scans came): their motion is uncertain"
        )
    if implausible and odometry and odometry.get("implausible"):
        rebased = odometry.get("rebased", 0)
        out.append(
            f"{odometry['implausible']} implausible odometry records skipped (jumps, dropped: "
            "the odometry continues from the last good record"
            + (f", or from the jump where it stayed: {rebased} times" if rebased else "")
            + "; --strict refuses such a log)"
        )
    return out
