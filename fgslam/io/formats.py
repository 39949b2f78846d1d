"""Which reader reads a file: :func:`sniff_format` and :func:`open_log`, which returns a
:class:`~fgslam.io.readers.source.LogSource` whatever the format (events by iteration,
``config``, ``world``, ``meta``, ``reference_kind``, ``clock_record`` and ``problems``, one
:class:`~fgslam.io.readers.source.Problems` type for all):

- native fgslam logs (:class:`fgslam.io.logfile.LogReader`);
- CARMEN logs (:class:`fgslam.io.readers.carmen.CarmenLog`);
- ROS 1 / ROS 2 bags (:class:`fgslam.io.readers.ros.RosBag`, needs ``rosbags``).

The Victoria Park text format is not a sensor log: :func:`fgslam.io.readers.victoria.read_victoria`
and :mod:`fgslam.slam.pointslam`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fgslam.errors import ReaderError
from fgslam.io.readers.common import head_text
from fgslam.io.readers.sanity import BACKWARDS_TOLERANCE, INDEX_PERIOD, NoUsableClock
from fgslam.io.readers.source import LogSource, StrPath

FORMATS = ("fgslam", "carmen", "ros", "victoria")

CARMEN_TAGS = ("FLASER", "ROBOTLASER1", "ODOM", "PARAM", "RLASER", "TRUEPOS", "SYNC", "NEFF")


def sniff_format(path: StrPath) -> str:
    """One of :data:`FORMATS`, from the file's first bytes (gzip looked through)."""
    from fgslam.io.readers.ros import is_bag

    p = Path(path)
    if not p.exists():
        raise ReaderError(f"{path}: no such file or directory")
    if is_bag(p):
        return "ros"
    if p.is_dir():
        raise ReaderError(f"{path}: a directory, but not a ROS 2 bag (no metadata.yaml)")
    head = head_text(p)
    if head.startswith("FGSLAM-LOG"):
        return "fgslam"
    tags = {ln.split()[0] for ln in head.splitlines()[:-1] if ln.split()}
    if tags & {"ODOMETRY", "LANDMARK"} and not tags & {"FLASER", "ODOM"}:
        return "victoria"
    if tags & set(CARMEN_TAGS) or (any(t.startswith("#") for t in tags) and "ODOM" in head):
        return "carmen"
    raise ReaderError(
        f"{path}: unknown log format (expected an fgslam log, a CARMEN log, a ROS bag or a "
        "Victoria Park file)"
    )


def open_log(path: StrPath, format: str | None = None, **options: Any) -> LogSource:
    """Open a log of any supported sensor-log format; ``options`` go to the reader
    (``tolerant``, ``strict``, ``timestamps``, ``limits`` and ``backwards_tolerance`` for
    all; ``timestamps``: fgslam ``auto``/``log``/``index``, CARMEN ``auto``/``ipc``/``logger``/
    ``index``, ROS ``auto``/``header``/``bag``; CARMEN: ``mode``, ``no_return``; ROS:
    ``scan_topic``, ``odom_topic``, ``range_topics``, ``laser_mount``, ``range_mounts``).
    Every format's clock is checked (docs/readers.md, "Timestamps"): a CARMEN or native log
    without a usable clock is read in record order (``index``) with a warning, refused with
    ``strict``. The events of native and CARMEN logs go through the same plausibility rules
    (:mod:`fgslam.io.readers.plausibility`: laser ranges out of range, scans without a valid
    beam, implausible odometry, implausible truth, stamps out of order), each kind counted
    and warned once, an error with ``strict``."""
    fmt = format or sniff_format(path)
    if fmt == "fgslam":
        return _open_native(path, options)
    if fmt == "carmen":
        from fgslam.io.readers.carmen import CarmenLog

        keys = (
            "mode",
            "no_return",
            "tolerant",
            "reference",
            "timestamps",
            "limits",
            "backwards_tolerance",
            "strict",
        )
        return CarmenLog(path, **{k: v for k, v in options.items() if k in keys})
    if fmt == "ros":
        from fgslam.io.readers.ros import RosBag

        keys = (
            "scan_topic",
            "odom_topic",
            "range_topics",
            "laser_mount",
            "range_mounts",
            "tolerant",
            "timestamps",
            "limits",
            "backwards_tolerance",
            "strict",
        )
        return RosBag(path, **{k: v for k, v in options.items() if k in keys})
    if fmt == "victoria":
        raise ReaderError(
            f"{path}: a Victoria Park file holds odometry steps and landmark sightings, not "
            "sensor data: run it with experiments/real_victoria_park.py "
            "(fgslam.slam.pointslam)"
        )
    raise ReaderError(f"unknown format {fmt!r}; expected one of {FORMATS}")


def _open_native(path: StrPath, options: dict[str, Any]) -> LogSource:
    """A native log (:class:`fgslam.io.logfile.LogReader`) with its clock checked and its events
    through the plausibility rules; without a usable clock (``timestamps`` auto) it is read
    in record order (``index``) unless ``strict``, the reason in ``clock_record["fallback"]``
    and ``["clock"]``."""
    from fgslam.io.logfile import LogReader
    from fgslam.io.logrecords import LogFormatError

    timestamps = options.get("timestamps") or "auto"
    kw = {
        "tolerant": bool(options.get("tolerant", False)),
        "backwards_tolerance": options.get("backwards_tolerance", BACKWARDS_TOLERANCE),
        "checks": True,  # the plausibility rules (fgslam.io.readers.plausibility)
        "strict": bool(options.get("strict", False)),
        "limits": options.get("limits"),
    }
    try:
        return LogReader(path, timestamps=timestamps, **kw)
    except LogFormatError as exc:
        cause = exc.__context__  # LogReader words the clock check's NoUsableClock as its own
        if options.get("strict") or timestamps != "auto" or not isinstance(cause, NoUsableClock):
            raise
    reader = LogReader(path, timestamps="index", **kw)
    record = reader.clock_record
    if record is not None:  # a regular file: the clock was checked
        what = "; ".join(f"stamps: {d[0]}" for d in record["defects"].values() if d)
        record["requested"] = "auto"
        record["fallback"] = f"no usable timestamps ({what})"
        record["clock"] = (
            f"index (no usable stamps: {what}; record order, scans {INDEX_PERIOD:g} s apart)"
        )
    return reader
