"""One reader interface for every format (issue 32, item 3; docs/readers.md, "One interface for
every format"): a native log, a CARMEN log and a ROS bag opened with ``open_log`` are each a
``LogSource`` with one ``Problems`` type; the same planted problem is reported through it with
the same counts and the same warning, and ``--strict`` refuses it the same way. The commands
that read logs print the reader's warnings alike (plot-log and export-reference too), and no
caller asks a reader for its format."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from readers_helpers import carmen_text

from fgslam.cli import main
from fgslam.config import load_config
from fgslam.events import Event, LaserScan, OdometryEvent, SonarReading, TruthPose
from fgslam.io.formats import open_log
from fgslam.io.logfile import LogReader
from fgslam.io.logwriter import LogWriter
from fgslam.io.readers.carmen import CarmenLog
from fgslam.io.readers.plausibility import ImplausibleInput
from fgslam.io.readers.source import LogSource, Problems

ROOT = Path(__file__).resolve().parents[1]
SENSOR_EVENTS = (OdometryEvent, LaserScan, SonarReading, TruthPose)
KEYS = (
    "laser_ranges_out_of_range",
    "scans_without_valid_beam",
    "implausible_odometry",
    "implausible_truth",
    "stamps_out_of_order",
)


def native(path: Path, jump: int | None = None, back: int | None = None) -> Path:
    """A native log of 30 scan periods of 0.2 s (four odometry records, a truth pose and a
    5-beam scan each); ``jump``: odometry record ``jump`` drives 1e6 m; ``back``: scan
    ``back`` stamped 0.1 s before the scan before it."""
    import dataclasses

    cfg = load_config()
    cfg = dataclasses.replace(cfg, laser=dataclasses.replace(cfg.laser, n_beams=5))
    n_odo = 0
    with LogWriter(path, cfg, "synthetic") as w:
        for p in range(30):
            base = 0.2 * p
            for j in range(4):
                ticks = 10**10 if n_odo == jump else 3
                w.write(OdometryEvent(base + 0.05 * j, ticks, ticks))
                n_odo += 1
            w.write(TruthPose(base + 0.1, 0.01 * p, 0.0, 0.0))
            t = base - 0.1 if p == back else base + 0.15
            w.write(LaserScan(t, np.full(5, 2.0)))
    return path


def carmen(path: Path, jump: int | None = None, back: int | None = None) -> Path:
    """The room run as a raw CARMEN log (readers_helpers.carmen_text); ``jump``: ODOM line
    ``jump`` 1e6 m off; ``back``: FLASER ``back`` stamped 1.5 s before its ODOM line."""
    lines, n_odom, n_scan = [], 0, 0
    for ln in carmen_text(corrected=False).splitlines():
        f = ln.split()
        if f and f[0] == "ODOM":
            if n_odom == jump:
                f[1] = "1000000.0"
            n_odom += 1
        elif f and f[0] == "FLASER":
            if n_scan == back:
                f[-3] = f[-1] = repr(float(f[-3]) - 1.5)
            n_scan += 1
        lines.append(" ".join(f))
    path.write_text("\n".join(lines) + "\n")
    return path


def bag(path: Path, jump: int | None = None, back: int | None = None) -> Path:
    """A ROS 1 bag (readers_helpers.write_bag); ``jump``: odometry message ``jump`` 1e6 m off;
    ``back``: the scan after odometry message ``back`` stamped 0.5 s back."""
    pytest.importorskip("rosbags")
    from readers_helpers import write_bag

    write_bag(path, True, jump=jump, backwards_scan=back)
    return path


FORMATS = {
    "fgslam": (native, "n.log", {"jump": 41, "back": 12}),
    "carmen": (carmen, "c.log", {"jump": 12, "back": 9}),
    "ros": (bag, "b.bag", {"jump": 7, "back": 5}),
}


def read(path: Path, **options) -> tuple[LogSource, list[Event]]:
    log = open_log(path, **options)
    with log:
        return log, list(log)


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_is_one_log_source(tmp_path, fmt):
    """Events, config, world, meta, reference kind, the clock record and one Problems type,
    with the same summary keys, warnings and report section on a sound input."""
    write, name, _ = FORMATS[fmt]
    log, events = read(write(tmp_path / name))
    assert isinstance(log, LogSource) and log.format == fmt
    assert type(log.problems) is Problems
    assert events and all(isinstance(e, SENSOR_EVENTS) for e in events)
    assert log.config.laser.n_beams > 0 and isinstance(log.world, str) and log.world
    assert isinstance(log.meta, dict)
    assert log.reference_kind in (None, "ground truth", "reference")
    assert log.clock_record is not None and log.clock_record["used"] == log.clock
    summary = log.summary()
    assert summary == log.problems.summary()
    assert {"skipped", "skipped_by_reason", "timestamps_backwards", "problems"} <= set(summary)
    assert {"timestamps", "plausibility", "warnings"} <= set(summary)
    assert log.problems.counts() == dict.fromkeys(KEYS, 0)
    assert log.problems.warnings() == summary["warnings"]
    report = log.problems.report()
    assert report is not None and report["plausibility"] == summary["plausibility"]
    assert not log.problems.strict


@pytest.mark.parametrize("fmt", FORMATS)
def test_an_implausible_odometry_jump_is_reported_alike(tmp_path, fmt):
    """One odometry record 1e6 m off: every format counts one implausible odometry record,
    skipped, in the same place, with the same warning; --strict refuses it as the same
    ImplausibleInput (one line naming the file)."""
    write, name, planted = FORMATS[fmt]
    path = write(tmp_path / name, jump=planted["jump"])
    log, _ = read(path)
    counts = log.problems.counts()
    assert counts == dict(dict.fromkeys(KEYS, 0), implausible_odometry=1), counts
    assert log.problems.skipped_by_reason["implausible odometry"] == 1
    warning = [w for w in log.problems.warnings() if "implausible odometry" in w]
    assert len(warning) == 1 and warning[0].startswith(
        f"1 implausible odometry record (first: {path}"
    )
    assert warning[0].endswith("skipped, the jump dropped; --strict refuses such a log")
    assert log.problems.report()["plausibility"]["implausible_odometry"]["count"] == 1
    with pytest.raises(ImplausibleInput, match=r"implausible odometry.*refused with --strict"):
        read(path, strict=True)


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_scan_stamped_out_of_order_is_reported_alike(tmp_path, fmt):
    """One scan stamped before the record before it: one stamp out of order, counted with
    the stream's backward stamps, warned once; --strict refuses it the same way."""
    write, name, planted = FORMATS[fmt]
    path = write(tmp_path / name, back=planted["back"])
    log, _ = read(path)
    counts = log.problems.counts()
    assert counts == dict(dict.fromkeys(KEYS, 0), stamps_out_of_order=1), counts
    assert sum(log.problems.backwards.values()) == 1
    warning = [w for w in log.problems.warnings() if "out of order" in w]
    assert len(warning) == 1 and warning[0].startswith("1 record stamped out of order (first: ")
    with pytest.raises(ImplausibleInput, match=r"stamp out of order.*refused with --strict"):
        read(path, strict=True)


def test_problems_say_how_they_are_reported(tmp_path):
    """What differs between formats is a property of their Problems, not a question the
    caller asks: a native log passes records out of order on (its counts are report.json's
    "input" section: the reader section holds its checks), a CARMEN log drops or carries
    them and counts record types it does not use as ignored."""
    nat, _ = read(native(tmp_path / "n.log"))
    path = tmp_path / "c.log"
    path.write_text(carmen_text(corrected=True))
    car, _ = read(path)
    assert isinstance(car, CarmenLog)
    assert nat.problems.passes_out_of_order and not car.problems.passes_out_of_order
    assert set(nat.problems.report()) == {"timestamps", "plausibility", "warnings"}
    assert car.problems.report() == car.problems.summary()
    assert car.problems.ignored == {"unknown record NEFF": 30}
    assert car.problems.skipped_by_reason == {"unknown record NEFF": 30}
    assert not nat.problems.ignored
    # a native log read without checks gives no reader section (nothing was checked)
    with LogReader(tmp_path / "n.log") as plain:
        list(plain)
    assert plain.problems.report() is None and plain.clock_record is None


def _clockless_carmen(path: Path) -> Path:
    """A CARMEN log whose every stamp is 0: read in record order, with a warning."""
    lines = []
    for ln in carmen_text(corrected=False).splitlines():
        f = ln.split()
        if f and f[0] in ("ODOM", "FLASER"):
            f[-3] = f[-1] = "0.0"
        lines.append(" ".join(f))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("command", ["plot-log", "export-reference", "convert"])
def test_every_command_prints_the_readers_warnings(tmp_path, capsys, command):
    """plot-log and export-reference print the reader's warnings as convert and run do."""
    pytest.importorskip("matplotlib")
    path = carmen(tmp_path / "c.log", jump=12)
    suffix = {"plot-log": ".png", "export-reference": ".tum", "convert": ".log"}[command]
    argv = [command, str(path), "--out", str(tmp_path / f"out{suffix}")]
    if command == "export-reference":  # a raw log has no reference: use a corrected one
        text = carmen_text(corrected=True).splitlines()
        i = [k for k, ln in enumerate(text) if ln.startswith("FLASER")][3]
        f = text[i].split()
        f[2:12] = ["-1.5"] * 10  # ten negative ranges
        text[i] = " ".join(f)
        path.write_text("\n".join(text) + "\n")
        argv[1] = str(path)
    assert main(argv) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("warning: ")]
    assert len(lines) == 1, out
    word = "ranges out of range" if command == "export-reference" else "implausible odometry"
    assert word in lines[0]


def test_a_clockless_log_warns_on_plot_log(tmp_path, capsys):
    """The clock warning too (a log read in record order) reaches plot-log's output."""
    pytest.importorskip("matplotlib")
    path = _clockless_carmen(tmp_path / "z.log")
    assert main(["plot-log", str(path), "--out", str(tmp_path / "z.png")]) == 0
    out = capsys.readouterr().out
    assert "warning: no usable timestamps" in out, out


PROBE = re.compile(
    r"getattr\(\s*(reader|log|source)\s*,\s*[\"'](problems|world|reference_kind|summary|"
    r"clock_record|meta|config)[\"']|hasattr\(\s*(reader|log|source)\s*,|"
    r"isinstance\(\s*(reader|log|source|problems)(\.problems)?\s*,\s*(list|LogReader|CarmenLog|"
    r"RosBag)\b"
)


def probes(text: str) -> list[str]:
    """The lines of ``text`` that ask a reader what it is instead of using the interface."""
    return [ln.strip() for ln in text.splitlines() if PROBE.search(ln)]


def test_a_planted_probe_is_found():
    planted = (
        "problems = getattr(reader, 'problems', None)\n"
        "if isinstance(problems, list): pass\n"
        "if hasattr(reader, 'summary'): pass\n"
        "kind = reader.reference_kind\n"
    )
    assert probes(planted) == [
        "problems = getattr(reader, 'problems', None)",
        "if isinstance(problems, list): pass",
        "if hasattr(reader, 'summary'): pass",
    ]


def test_no_caller_probes_a_reader():
    """fgslam and the experiments use the interface only: no getattr/hasattr/isinstance on a
    reader to find out which format it is."""
    found = {
        str(p.relative_to(ROOT)): probes(p.read_text())
        for folder in ("fgslam", "experiments")
        for p in sorted((ROOT / folder).rglob("*.py"))
    }
    assert not {k: v for k, v in found.items() if v}
