"""Fuzz every input path of fgslam: bad input must be read or refused, never escape (issue
"Bad input never escapes", item 5).

Each path starts from a small valid input, generates mutants from ``--seed`` (the same seed
gives the same inputs) and runs each one in this process through the entry point the command
line uses:

- ``carmen``, ``native``, ``ros1``, ``ros2``: ``fgslam convert LOG --out /dev/null``
  (``fgslam.cli.main``: ``fgslam.io.formats.open_log``, every event read and written, the
  reader's summary), with the reader options a user may give (``--tolerant``, ``--strict``,
  ``--timestamps``, ``--carmen-mode``). CARMEN and native logs: text mutants (a field
  replaced by a hostile token, dropped or added; lines repeated, removed, swapped, cut;
  hostile header JSON) and byte mutants (flips, cuts, garbage; some gzipped, some gzip
  streams damaged). Bags (written here with ``rosbags``): byte flips, cuts, overwrites.
- ``victoria``: ``fgslam.io.readers.victoria.read_victoria`` and ``to_bearing_range`` of every
  sighting (what ``experiments/real_victoria_park.py`` does; there is no command).
- ``evaluate``: ``fgslam evaluate`` on mutated TUM and relations files
  (``fuzzlib.mutated_eval_inputs``, ``fuzzlib.evaluate_outcome``).
- ``config``: ``fgslam.config.load_config`` on a mutated robot TOML file (values replaced by
  hostile ones, keys and sections dropped, types changed, arrays emptied, damaged bytes, deep
  nesting; or a small override file), then what ``fgslam config`` prints (``to_dict``, TOML)
  and the parameters a run derives from it (front end, scan matcher, keyframes, loops, map,
  odometry, calibration priors).
- ``devices``: the receivers ``fgslam online`` and ``fgslam replay`` decode with
  (``devices.sick.SickReceiver``, ``devices.odometry.OdometryReceiver``,
  ``devices.sonar.SonarReceiver``: ``TelegramDecoder``/``FrameDecoder``, ``parse_b0``,
  ``decode_sample``, ``decode_reading``, ``DeviceTime``) fed random and mutated byte streams
  in random chunks, with valid-CRC frames around hostile payloads, hostile sequence numbers
  and device times, line-rate changes and resets; every measurement through
  ``fgslam.online.ports.to_event`` and its event through ``fgslam.io.logfile.format_record`` (as
  ``fgslam replay`` writes it).
- ``raw``: ``fgslam replay`` on mutated raw recordings (``fuzzlib.simulated_recording``,
  ``fuzzlib.mutated_recordings``, ``fuzzlib.replay_outcome``).

Outcomes: *accepted* (read or decoded to the end, exit 0), *clean error* (the project's one
error for bad input, a ``fgslam.errors.UserError``: exit status 2 with one error line),
*escape* (any other exception, or another exit), *hang* (longer than ``--timeout`` s,
``signal.setitimer``); *raw warnings* counts the inputs that raised a warning other than the
project's own (``OutputWarning``, ``RunWarning``), e.g. numpy's RuntimeWarnings. Prints one
markdown table, then each kind of escape, hang and raw warning with a count and one example
(exception, file:line, the mutation). The first examples of each kind are saved under
``--save`` (default ``fgslam_fuzz_escapes`` in the system's temporary folder);
``--reproduce DIR`` runs a saved input again without catching anything.

Run: python experiments/fuzz_inputs.py [--seed 0] [--scale 1] [--paths carmen,native,...]
       [--timeout 20] [--save DIR]
     python experiments/fuzz_inputs.py --reproduce <save dir>/<case>
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import gzip
import io
import json
import math
import os
import random
import re
import shutil
import signal
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import fuzzlib
import numpy as np

from fgslam.errors import OutputWarning, RunWarning, UserError

ROOT = Path(__file__).resolve().parents[1]
SAVE_DIR = Path(tempfile.gettempdir()) / "fgslam_fuzz_escapes"
EXAMPLES_SAVED = 2  # inputs saved per kind of escape, hang or warning

# path -> inputs at --scale 1 (total 100 000)
COUNTS = {
    "carmen": 15_000,
    "native": 15_000,
    "victoria": 10_000,
    "evaluate": 15_000,
    "config": 15_000,
    "devices": 20_000,
    "raw": 5_000,
    "ros1": 2_500,
    "ros2": 2_500,
}

# Numbers and words a damaged or hostile file could hold where a number belongs
TOKENS = (
    "nan", "NaN", "-nan", "inf", "-inf", "+inf", "Infinity", "infinity", "1e308", "-1e308",
    "1.7976931348623157e308", "1e309", "1e400", "-1e400", "1e-320", "5e-324", "-5e-324", "0",
    "-0", "-0.0", "0.0", "1", "-1", "2", "3", "1e5", "100000", "100001", "65536",
    "4294967296", "-2147483649", "9223372036854775808", "99999999999999999999999999",
    "1" + "0" * 5000, "1e10", "1e12", "1e20", "1e100", "3.14159", "1e-9", "0x10", "1_0",
    "x", "-", ".", "e", "#", "\x00", "\u0661\u0662", "1,5", "O", "L", "S", "T", "FLASER",
    "ODOM",
)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Outcomes


class Hang(BaseException):
    """An input that ran past the time bound (raised by the interval timer)."""


@dataclass
class Result:
    """One input's outcome: ``kind`` accepted, clean, escape or hang; ``key`` names the kind
    of escape (exception type and place); ``detail`` its message; ``warnings`` the raw
    warnings it raised, each (kind key, message)."""

    kind: str
    key: str = ""
    detail: str = ""
    warnings: list[tuple[str, str]] = field(default_factory=list)


def _rel(filename: str) -> str:
    try:
        return str(Path(filename).resolve().relative_to(ROOT))
    except ValueError:
        parts = Path(filename).parts
        lib = [i for i, x in enumerate(parts) if x == "site-packages" or x.startswith("python3")]
        return "/".join(parts[lib[-1] + 1 :]) if lib else filename


def _in_project(filename: str) -> bool:
    rel = _rel(filename)
    return rel.startswith(("fgslam/", "devices/", "factors/"))


def describe(exc: BaseException) -> tuple[str, str]:
    """(kind key, message) of an exception: its type, the deepest frame of the project
    (fgslam/, devices/, factors/) and, if elsewhere, the frame that raised it."""
    tb = traceback.extract_tb(exc.__traceback__)
    own = [f for f in tb if _in_project(f.filename)]
    where = f"{_rel(own[-1].filename)}:{own[-1].lineno}" if own else "?"
    if tb and (not own or tb[-1] is not own[-1]):
        where += f" (raised in {_rel(tb[-1].filename)}:{tb[-1].lineno})"
    return f"{type(exc).__name__} at {where}", str(exc)[:240]


def _warning_key(w: warnings.WarningMessage) -> str:
    if issubclass(w.category, ResourceWarning):  # raised where the object was collected
        text = re.sub(r"name=\S+", "name=...", str(w.message))[:70]
        return f"ResourceWarning: {text}"
    text = re.sub(r"\d+", "#", str(w.message))[:70]
    return f"{w.category.__name__} at {_rel(w.filename)}:{w.lineno}: {text}"


def _on_alarm(signum: int, frame: Any) -> None:
    raise Hang()


def run_input(runner: Callable[[Path, dict], Result], folder: Path, opts: dict, timeout: float):
    """Run one input with the time bound, recording its warnings; never raises (but a
    KeyboardInterrupt)."""
    with warnings.catch_warnings(record=True) as log:
        warnings.simplefilter("always")
        signal.setitimer(signal.ITIMER_REAL, timeout)
        try:
            res = runner(folder, opts)
        except Hang:
            res = Result("hang", f"longer than {timeout:g} s")
        except UserError as exc:
            res = Result("clean", detail=str(exc)[:240])
        except Exception as exc:  # what the campaign counts: any other exception
            key, msg = describe(exc)
            res = Result("escape", key, msg)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        gc.collect(1)  # objects the input left in cycles: their ResourceWarnings are its own
    for w in log:
        if not issubclass(w.category, (OutputWarning, RunWarning)):
            res.warnings.append((_warning_key(w), str(w.message)[:200]))
    return res


def cli(argv: list[str]) -> Result:
    """``fgslam ARGV`` (``fgslam.cli.main``) in this process: accepted (0), clean (2 and one
    error line), else an escape named by the exit status."""
    from fgslam.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(argv)
    lines = err.getvalue().strip().splitlines()
    if status == 0:
        return Result("accepted")
    prefix = f"fgslam {argv[0]}: error: "
    if status == 2 and lines and lines[-1].startswith(prefix):
        return Result("clean", detail=lines[-1][len(prefix) :][:240])
    errors = [k for k, ln in enumerate(lines) if ln.startswith(prefix)]
    if status == 2 and errors:  # the error line broken by a line break in its message
        key = f"exit status 2, the error message spanning {len(lines) - errors[-1]} lines"
        return Result("escape", key, " | ".join(lines[errors[-1] :])[:240])
    return Result("escape", f"exit status {status}", err.getvalue()[-240:])


def from_outcome(o: fuzzlib.Outcome) -> Result:
    """A :class:`fuzzlib.Outcome` (replay_outcome, evaluate_outcome) as a Result."""
    if o.kind in ("decoded", "evaluated"):
        return Result("accepted")
    if o.kind == "refused":
        return Result("clean", detail=o.detail)
    if o.kind == "traceback":  # "Type at file:line: message"
        key, _, msg = o.detail.partition(": ")
        return Result("escape", key, msg)
    return Result("escape", f"exit status {o.status}", o.detail)


# ---------------------------------------------------------------------------------------------
# Generic mutators: each returns (new data, what was done)


def mutate_bytes(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """One byte-level damage: bits flipped, a cut, garbage inserted, a region overwritten,
    zeroed or repeated."""
    if not data:
        return rng.randbytes(rng.randint(1, 32)), "random bytes"
    b = bytearray(data)
    op = rng.choice(("flip", "flip", "cut", "insert", "overwrite", "zero", "repeat"))
    if op == "flip":
        where = sorted(rng.randrange(len(b)) for _ in range(rng.randint(1, 8)))
        for i in where:
            b[i] ^= 1 << rng.randrange(8) if rng.random() < 0.7 else rng.randint(1, 255)
        return bytes(b), f"bytes flipped at {where}"
    i = rng.randrange(len(b) + 1)
    if op == "cut":
        return bytes(b[:i]), f"cut to {i} bytes"
    if op == "insert":
        junk = rng.randbytes(rng.randint(1, 64))
        return bytes(b[:i] + junk + b[i:]), f"{len(junk)} random bytes inserted at {i}"
    n = rng.randint(1, 64)
    if op == "overwrite":
        b[i : i + n] = rng.randbytes(n)
        return bytes(b[: len(data)]), f"{n} bytes overwritten at {i}"
    if op == "zero":
        b[i : i + n] = bytes(n)
        return bytes(b[: len(data)]), f"{n} bytes zeroed at {i}"
    j = min(len(b), i + rng.randint(1, 300))
    return bytes(b[:j] + b[i:j] + b[j:]), f"bytes {i}..{j} repeated"


def mutate_fields(
    text: str, rng: random.Random, tokens: tuple[str, ...] = TOKENS, skip: int = 0
) -> tuple[str, str]:
    """One line-level damage of a text of whitespace-separated fields (lines before
    ``skip`` left alone): a field replaced by a token, dropped or added; a line repeated,
    removed, swapped, cut or added."""
    lines = text.split("\n")
    if len(lines) <= skip + 1:
        return mutate_bytes(text.encode(), rng)[0].decode("utf-8", "replace"), "bytes"
    k = rng.randrange(skip, len(lines) - 1)
    f = lines[k].split(" ")
    op = rng.choice(("token",) * 6 + ("drop", "add", "dup", "del", "swap", "cut", "count"))
    if op == "token" or (op == "count" and len(f) < 2):
        i = rng.randrange(len(f))
        tok = rng.choice(tokens)
        f[i] = tok
        what = f"line {k + 1} field {i + 1} = {tok[:20]!r}"
    elif op == "count":  # a count field (beam, echo numbers) off by a little or a lot
        i = rng.randrange(1, min(len(f), 10))
        try:
            v = int(float(f[i])) + rng.choice((-2, -1, 1, 2, 100, -1000))
        except (ValueError, OverflowError):
            v = rng.randint(-5, 500)
        f[i] = str(v)
        what = f"line {k + 1} field {i + 1} = {v}"
    elif op == "drop":
        i = rng.randrange(len(f))
        del f[i]
        what = f"line {k + 1} field {i + 1} dropped"
    elif op == "add":
        i = rng.randint(0, len(f))
        f.insert(i, rng.choice(tokens))
        what = f"line {k + 1} a field inserted at {i + 1}"
    else:
        if op == "dup":
            lines.insert(k, lines[k])
        elif op == "del":
            del lines[k]
        elif op == "swap":
            j = rng.randrange(skip, len(lines) - 1)
            lines[k], lines[j] = lines[j], lines[k]
            op = f"swapped with line {j + 1}"
        elif op == "cut":
            lines[k] = lines[k][: rng.randrange(len(lines[k]) + 1)]
        return "\n".join(lines), f"line {k + 1} {op}"
    lines[k] = " ".join(f)
    return "\n".join(lines), what


def rounds(rng: random.Random) -> int:
    return rng.choice((1, 1, 1, 2, 3))


def text_mutant(
    text: str,
    rng: random.Random,
    field_ops: Callable[[str, random.Random], tuple[str, str]],
    gzip_ok: bool = True,
) -> tuple[bytes, str]:
    """A mutant of a text file: ``field_ops`` rounds (75 %) or byte damage; sometimes
    gzipped, sometimes with the gzip stream itself damaged."""
    whats = []
    if rng.random() < 0.75:
        for _ in range(rounds(rng)):
            text, what = field_ops(text, rng)
            whats.append(what)
        data = text.encode("utf-8", "surrogateescape")
    else:
        data = text.encode()
        for _ in range(rounds(rng)):
            data, what = mutate_bytes(data, rng)
            whats.append(what)
    if gzip_ok and rng.random() < 0.12:
        data = gzip.compress(data, mtime=0)
        whats.append("gzipped")
        if rng.random() < 0.4:
            data, what = mutate_bytes(data, rng)
            whats.append(f"gzip stream {what}")
    return data, "; ".join(whats)


def reader_flags(rng: random.Random, carmen: bool = False, bag: bool = False) -> list[str]:
    """Reader options a user may give (mostly none)."""
    flags: list[str] = []
    u = rng.random()
    if u < 0.15:
        flags.append("--tolerant")
    elif u < 0.3:
        flags.append("--strict")
    if rng.random() < 0.2:
        clocks = ("header", "bag") if bag else ("ipc", "logger", "index") if carmen else ("log",)
        flags += ["--timestamps", rng.choice(("auto", "index", *clocks) if not bag else clocks)]
    if carmen and rng.random() < 0.2:
        flags += ["--carmen-mode", rng.choice(("auto", "corrected", "raw"))]
    return flags


# ---------------------------------------------------------------------------------------------
# Cases


@dataclass
class Case:
    """One generated input: ``files`` (name -> bytes) written into a fresh folder, ``opts``
    (JSON) for the path's runner, ``what`` the mutation."""

    what: str
    files: dict[str, bytes]
    opts: dict[str, Any]


def convert_runner(folder: Path, opts: dict) -> Result:
    return cli(["convert", str(folder / opts["log"]), "--out", os.devnull, *opts["flags"]])


# -- CARMEN


def _fmt(*v: float) -> str:
    return " ".join(repr(round(float(x), 6)) for x in v)


def carmen_text(corrected: bool, n: int = 20, beams: int = 37) -> str:
    """A small CARMEN log of a robot driving an arc in a room: raw (cumulative ODOM,
    TRUEPOS, FLASER and ROBOTLASER1 lines) or corrected (GMapping style: ODOM before each
    scan, the scan, ODOM repeated with stamp 0, NEFF)."""
    rng = random.Random(7)
    lines = ["# CARMEN Logfile", "# message formats defined: PARAM ODOM FLASER ROBOTLASER1"]
    lines += ["PARAM robot_frontlaser_offset 0.0 h 0", "PARAM laser_front_laser_fov 180 h 0"]
    pose = (0.0, 0.0, 0.0)
    for k in range(n):
        t = 1.0 + 0.2 * k
        prev = pose
        pose = (0.1 * k * math.cos(0.02 * k), 0.1 * k * math.sin(0.02 * k), 0.02 * k)
        ranges = [rng.uniform(0.4, 7.5) for _ in range(beams)]
        ranges[rng.randrange(beams)] = 81.91
        r = _fmt(*ranges)
        if corrected:
            lines.append(f"ODOM {_fmt(*pose)} 0.1 0.0 0.0 {t - 0.05!r} h {t - 0.05!r}")
            lines.append(f"FLASER {beams} {r} {_fmt(*pose)} {_fmt(*pose)} {t!r} h {t!r}")
            lines.append(f"ODOM {_fmt(*pose)} 0 0 0 0 h 0")
            lines.append(f"NEFF {rng.uniform(5, 30):.3f}")
            continue
        mid = tuple((a + b) / 2 for a, b in zip(prev, pose, strict=True))
        lines.append(f"ODOM {_fmt(*mid)} 0.1 0.0 0.0 {t - 0.1!r} h {t - 0.1!r}")
        lines.append(f"ODOM {_fmt(*pose)} 0.1 0.0 0.0 {t - 0.01!r} h {t - 0.01!r}")
        lines.append(f"TRUEPOS {_fmt(*pose)} {_fmt(*pose)} {t!r} h {t!r}")
        if k % 4 == 3:
            head = f"ROBOTLASER1 0 {-math.pi / 2!r} {math.pi!r} {math.pi / (beams - 1)!r} 20.0"
            lines.append(
                f"{head} 0.01 0 {beams} {r} 0 0.12 0.0 0.0 {_fmt(*pose)} 0.1 0.0 0.5 0.3 "
                f"0.0 {t!r} h {t!r}"
            )
        else:
            lines.append(f"FLASER {beams} {r} {_fmt(*pose)} {_fmt(*pose)} {t!r} h {t!r}")
    return "\n".join(lines) + "\n"


def carmen_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    bases = {True: carmen_text(True), False: carmen_text(False)}
    for _ in range(n):
        corrected = rng.random() < 0.5
        data, what = text_mutant(bases[corrected], rng, lambda t, r: mutate_fields(t, r, skip=1))
        kind = "corrected" if corrected else "raw"
        flags = reader_flags(rng, carmen=True)
        yield Case(f"{kind} log: {what}", {"log.clf": data}, {"log": "log.clf", "flags": flags})


# -- native logs


def native_log(path: Path) -> None:
    """A small native log: 19-beam laser, 20 scan periods of odometry, sonar (both arrays),
    truth and scans, one scan with its own bearings; META present."""
    from fgslam.config import load_config
    from fgslam.events import LaserScan, OdometryEvent, SonarEcho, SonarReading, TruthPose
    from fgslam.io.logwriter import LogWriter

    cfg = load_config()
    cfg = dataclasses.replace(cfg, laser=dataclasses.replace(cfg.laser, n_beams=19))
    rng = np.random.default_rng(3)
    with LogWriter(path, cfg, "synthetic", {"source": "fuzz", "duration": 4.0}) as w:
        for p in range(20):
            b = 0.2 * p
            for j in range(4):
                w.write(OdometryEvent(b + 0.05 * j, 30 + j, 28 - j))
            echoes = (SonarEcho("plane", 1.5, 0.01), SonarEcho("corner", 2.25, -0.2))
            w.write(SonarReading(b + 0.06, p % 2, 0.3 - 0.05 * p, echoes[: p % 3]))
            w.write(TruthPose(b + 0.07, 0.01 * p, 0.002 * p, 0.001 * p))
            ranges = rng.uniform(0.5, 8.0, 19)
            ranges[p % 19] = np.nan
            bearings = np.linspace(-1.2, 1.2, 19) if p == 7 else None
            w.write(LaserScan(b + 0.15, ranges, bearings))


HOSTILE_JSON = (*fuzzlib.HOSTILE_JSON, "[" * 3000 + "]" * 3000)


def _json_paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append((*prefix, k))
            out += _json_paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append((*prefix, i))
            out += _json_paths(v, (*prefix, i))
    return out


def mutate_json(text: str, rng: random.Random) -> tuple[str, str]:
    """A JSON object's text with one value (at any depth) replaced by a hostile JSON text,
    or one key removed."""
    obj = json.loads(text)
    paths = _json_paths(obj)
    if not paths:
        return '{"x": ' + rng.choice(HOSTILE_JSON) + "}", "hostile object"
    path = rng.choice(paths)
    parent = obj
    for p in path[:-1]:
        parent = parent[p]
    name = ".".join(map(str, path))
    if rng.random() < 0.2:
        del parent[path[-1]]
        return json.dumps(obj, separators=(",", ":")), f"{name} removed"
    value = rng.choice(HOSTILE_JSON)
    parent[path[-1]] = "\x00HOSTILE\x00"
    text = json.dumps(obj, separators=(",", ":")).replace('"\\u0000HOSTILE\\u0000"', value)
    return text, f"{name} = {value[:20]}"


def mutate_native(text: str, rng: random.Random) -> tuple[str, str]:
    """A native log's header (version line, CONFIG, WORLD or META) or a record damaged."""
    lines = text.split("\n")
    u = rng.random()
    tag = "CONFIG" if u < 0.3 else "META" if u < 0.36 else None
    k = next((i for i, ln in enumerate(lines) if tag and ln.startswith(f"{tag} {{")), None)
    if tag and k is not None:
        try:
            new, what = mutate_json(lines[k][len(tag) + 1 :], rng)
        except (ValueError, RecursionError):  # mutated before: not JSON any more
            return mutate_fields(text, rng, skip=4)
        lines[k] = f"{tag} {new}"
        return "\n".join(lines), f"{tag} {what}"
    if u < 0.36:
        return mutate_fields(text, rng, skip=4)
    if u < 0.4:
        k = rng.randrange(4)
        new = rng.choice(
            ("FGSLAM-LOG 1", "FGSLAM-LOG 3", "FGSLAM-LOG", "FGSLAM-LOG x", "WORLD", "WORLD \x00",
             "WORLD " + "w" * 10_000, "META {}", "META []", "CONFIG {}", "CONFIG []", "")
        )  # fmt: skip
        lines[k] = new
        return "\n".join(lines), f"header line {k + 1} = {new[:20]!r}"
    return mutate_fields(text, rng, skip=4)


def native_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    native_log(work / "base.log")
    base = (work / "base.log").read_text()
    for _ in range(n):
        data, what = text_mutant(base, rng, mutate_native)
        flags = reader_flags(rng)
        yield Case(what, {"log.log": data}, {"log": "log.log", "flags": flags})


# -- Victoria Park


def victoria_text(n: int = 30) -> str:
    """A small Victoria Park file: a chain of odometry steps, landmarks seen along it."""
    rng = random.Random(5)
    lines = []
    for i in range(n):
        lines.append(
            f"ODOMETRY {i} {i + 1} {0.5 + rng.uniform(-0.01, 0.01):.6f} 0.0 "
            f"{rng.uniform(-0.05, 0.05):.6f} 0.01 0 0 0.01 0 0.001"
        )
        for _ in range(rng.randint(0, 2)):
            lm = 1000 + rng.randrange(12)
            x, y = rng.uniform(1, 20), rng.uniform(-10, 10)
            lines.append(f"LANDMARK {i + 1} {lm} {x:.4f} {y:.4f} 0.04 0.001 0.04")
    return "\n".join(lines) + "\n"


def victoria_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    base = victoria_text()
    tokens = (*TOKENS, "ODOMETRY", "LANDMARK", "-0.01", "1e-300", "1e-20", "1e200")
    for _ in range(n):
        data, what = text_mutant(base, rng, lambda t, r: mutate_fields(t, r, tokens), False)
        yield Case(what, {"victoria.txt": data}, {"tolerant": rng.random() < 0.3})


def victoria_runner(folder: Path, opts: dict) -> Result:
    from fgslam.io.readers.victoria import read_victoria, to_bearing_range

    data = read_victoria(folder / "victoria.txt", tolerant=opts["tolerant"])
    for sightings in data.sightings.values():
        for s in sightings:
            to_bearing_range(s.xy, s.cov)
    return Result("accepted")


# -- evaluation inputs (TUM, relations)


def evaluate_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    good = {"good.tum": fuzzlib.tum_text().encode(), "good.rel": fuzzlib.relations_text().encode()}
    seed = rng.randrange(1 << 30)
    for kind, what, text in fuzzlib.mutated_eval_inputs(seed, n):
        if kind == "relations":
            files, args = {"fuzz.rel": text.encode()}, ["good.tum", "--relations", "fuzz.rel"]
        elif rng.random() < 0.5:
            files, args = {"fuzz.tum": text.encode()}, ["good.tum", "--reference", "fuzz.tum"]
        else:
            files = {"fuzz.tum": text.encode()}
            args = ["fuzz.tum", "--reference", "good.tum", "--relations", "good.rel"]
        yield Case(f"{kind}: {what}", {**good, **files}, {"args": [*args, "--out", "r.json"]})


def evaluate_runner(folder: Path, opts: dict) -> Result:
    args = [a if a.startswith("--") else str(folder / a) for a in opts["args"]]
    return from_outcome(fuzzlib.evaluate_outcome(args))


# -- robot configuration (TOML)

TOML_VALUES = (
    "nan", "+nan", "-nan", "inf", "+inf", "-inf", "1e400", "-1e400", "5e-324", "1e-320",
    "1e-300", "0", "0.0", "-0.0", "-1", "-1.0", "1", "2", "1e308", "-1e308", "1e9", "1e10",
    "100000", "100001", "360.0000001", "9223372036854775807", "-9223372036854775808",
    "0x7FFFFFFF", "0o777", "0b1", "1_000", "true", "false", '"x"', '""', '"nan"', "'inf'",
    '"\\u0000"', "[]", "[1, 2]", "[nan, nan, nan]", "[0.0, 0.0, 0.0]", "[1e400, 1, 1]",
    "[-1.0, 0.01, 0.01]", "[0.01, 0.01]", "[[1]]", '["a"]', "{}", "{ x = 1 }",
    "{ x = nan, y = 0, yaw_deg = 0 }", "{ x = 0, y = 0, yaw_deg = 1e400 }",
    "{ x = 0, y = 0 }", "1979-05-27T07:32:00Z", "1979-05-27", "07:32:00",
    "[" * 4000 + "]" * 4000, "{ a = " * 2000 + "1" + " }" * 2000,
)  # fmt: skip
_TOML_LINE = re.compile(r"^(\s*)([A-Za-z_][\w]*)(\s*=\s*)(.*?)(\s*#.*)?$")
_NUMBER = re.compile(r"-?\d+(?:\.\d+)?(?:e-?\d+)?")


def toml_schema() -> list[tuple[str, str, str]]:
    """(section, key, value text) of every key of the default configuration."""
    from fgslam.config import default_config_text

    out, section = [], ""
    for ln in default_config_text().splitlines():
        if ln.startswith("["):
            section = ln.strip("[] ")
        elif m := _TOML_LINE.match(ln):
            if not ln.lstrip().startswith("#"):
                out.append((section, m.group(2), m.group(4)))
    return out


def mutate_toml(text: str, rng: random.Random) -> tuple[str, str]:
    """One damage of a robot TOML file: a value replaced by a hostile one (or a number
    inside an inline table or array), a key or a section header dropped, a key repeated,
    an unknown key, ``[[sonar.arrays]]`` blocks removed or repeated, sonar arrays emptied."""
    lines = text.split("\n")
    keyed = [i for i, ln in enumerate(lines) if _TOML_LINE.match(ln) and not ln.startswith("#")]
    op = rng.choice(("value",) * 8 + ("number", "number", "drop", "header", "dup", "unknown",
                                      "arrays", "arrays"))  # fmt: skip
    if op in ("value", "number") and keyed:
        k = rng.choice(keyed)
        m = _TOML_LINE.match(lines[k])
        assert m is not None
        value = m.group(4)
        nums = list(_NUMBER.finditer(value))
        if op == "number" and nums and (value.startswith(("{", "["))):
            n = rng.choice(nums)
            new = value[: n.start()] + rng.choice(TOML_VALUES[:34]) + value[n.end() :]
        else:
            new = rng.choice(TOML_VALUES)
        lines[k] = f"{m.group(1)}{m.group(2)}{m.group(3)}{new}"
        return "\n".join(lines), f"{m.group(2)} = {new[:30]}"
    if op == "drop" and keyed:
        k = rng.choice(keyed)
        name = lines[k].split("=")[0].strip()
        del lines[k]
        return "\n".join(lines), f"key {name} dropped"
    if op == "dup" and keyed:
        k = rng.choice(keyed)
        lines.insert(k, lines[k])
        return "\n".join(lines), f"line {k + 1} repeated"
    headers = [i for i, ln in enumerate(lines) if ln.startswith("[")]
    if op == "header" and headers:
        k = rng.choice(headers)
        name = lines[k]
        del lines[k]
        return "\n".join(lines), f"header {name} dropped"
    if op == "unknown":
        k = rng.randrange(len(lines))
        key = rng.choice(("extra", "n_beams", "mount", "arrays", "robot", "laser"))
        lines.insert(k, f"{key} = {rng.choice(TOML_VALUES[:40])}")
        return "\n".join(lines), f"line {k + 1} = {lines[k][:40]}"
    arrays = [i for i, ln in enumerate(lines) if ln.strip() == "[[sonar.arrays]]"]
    if arrays:
        u = rng.random()
        if u < 0.35:
            k = rng.choice(arrays)
            end = next((j for j in range(k + 1, len(lines)) if lines[j].startswith("[")), None)
            end = len(lines) if end is None else end
            del lines[k:end]
            return "\n".join(lines), "a [[sonar.arrays]] block removed"
        if u < 0.7:
            k = arrays[0]
            end = next(j for j in range(k + 1, len(lines)) if lines[j].startswith("["))
            block = lines[k:end]
            lines[k:k] = block * rng.randint(1, 300)
            return "\n".join(lines), "a [[sonar.arrays]] block repeated"
        new = [ln for ln in lines if ln.strip() != "[[sonar.arrays]]"]
        return "\n".join(new), "the [[sonar.arrays]] headers removed"
    return mutate_fields(text, rng)


def override_toml(schema: list[tuple[str, str, str]], rng: random.Random) -> tuple[str, str]:
    """A small user file: one to four keys of the schema with hostile values."""
    picks = sorted(rng.sample(schema, rng.randint(1, 4)))
    parts, done, last = [], [], None
    for section, key, _ in picks:
        value = rng.choice(TOML_VALUES)
        if section == "sonar.arrays":
            parts.append("[[sonar.arrays]]")
            last = None
        elif section != last:
            parts.append(f"[{section}]")
            last = section
        parts.append(f"{key} = {value}")
        done.append(f"{section}.{key} = {value[:20]}")
    return "\n".join(parts) + "\n", "override file: " + ", ".join(done)


def config_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    from fgslam.config import default_config_text

    base = default_config_text()
    schema = toml_schema()
    for _ in range(n):
        if rng.random() < 0.2:
            text, what = override_toml(schema, rng)
            yield Case(what, {"robot.toml": text.encode()}, {})
            continue
        data, what = text_mutant(base, rng, mutate_toml, gzip_ok=False)
        yield Case(what, {"robot.toml": data}, {})


def config_runner(folder: Path, opts: dict) -> Result:
    """``load_config`` (every ``--config``), what ``fgslam config`` prints, and the
    parameters a run derives from the configuration."""
    import tomli_w

    from fgslam import config as c
    from fgslam.config.robot import KeyframeParams, LoopParams, MapParams
    from fgslam.scanmatch import MatchParams

    cfg = c.load_config(folder / "robot.toml")
    data = cfg.to_dict()
    tomli_w.dumps(data)
    json.dumps(data, allow_nan=False)
    c.frontend_thresholds(cfg)
    MatchParams.from_config(cfg)
    KeyframeParams.from_config(cfg)
    LoopParams.from_config(cfg)
    MapParams.from_config(cfg)
    cfg.odometry.params()
    cfg.odometry.calibration_prior()
    cfg.laser.calibration_prior()
    cfg.sonar.calibration_prior()
    cfg.laser.bearings  # noqa: B018 - computed as a run does
    cfg.laser.scan_period  # noqa: B018
    cfg.laser.mount.pose  # noqa: B018
    for arr in cfg.sonar.arrays:
        arr.mount.pose  # noqa: B018
    return Result("accepted")


# -- device byte streams


def _sick_values(rng: random.Random, n: int = 361) -> bytes:
    from devices import sick

    u = rng.random()
    if u < 0.6:
        d = [rng.randint(30, 3000) for _ in range(n)]
        for _ in range(rng.randint(0, 5)):
            d[rng.randrange(n)] = rng.choice((0, 8183, 8187, 8189, 8190, 8191))
    elif u < 0.8:
        d = [rng.choice((0, 1, 8182, 8183, 8191)) for _ in range(n)]
    else:
        d = [rng.randint(0, 8191) for _ in range(n)]
    flags = [rng.randrange(8) for _ in range(n)] if rng.random() < 0.2 else None
    partial = rng.randrange(4) if rng.random() < 0.1 else None
    status = 0x10 if rng.random() < 0.7 else rng.randrange(256)
    mm = rng.random() < 0.2
    return sick.encode_b0(d, mm=mm, status=status, flags=flags, partial_index=partial)


def _hostile_b0(rng: random.Random) -> bytes:
    """A B0 payload that lies: any info word (count, unit code), any body length."""
    u = rng.random()
    if u < 0.3:
        return bytes([0xB0]) + rng.randbytes(rng.randint(0, 811))
    n = rng.choice((0, 1, 2, 180, 361, 404, 405, 1023, rng.randrange(1024)))
    unit = rng.choice((0, 1, 2, 3))
    info = n | unit << 14 | (rng.randrange(8) << 11 if rng.random() < 0.3 else 0)
    body_n = n if rng.random() < 0.6 else max(0, n + rng.choice((-1, 1, -n, 3)))
    body = rng.randbytes(2 * min(body_n, 404))
    return bytes([0xB0, info & 0xFF, info >> 8]) + body + bytes([rng.randrange(256)])


def sick_stream(rng: random.Random) -> bytes:
    """Telegrams as a PLS sends them (ACK, status and mode replies, B0 scans), some with a
    valid CRC around a hostile payload, or a raw header that lies about its length."""
    from devices import sick

    parts = []
    for _ in range(rng.randint(1, 6)):
        u = rng.random()
        if u < 0.45:
            payload = _sick_values(rng)
        elif u < 0.75:
            payload = _hostile_b0(rng)
        elif u < 0.85:
            payload = rng.choice((bytes([0xB1]) + rng.randbytes(rng.randint(0, 40)),
                                  bytes([0xA0, rng.randrange(3)]), bytes([0x92]),
                                  rng.randbytes(rng.randint(1, 812))))  # fmt: skip
        else:
            n = rng.choice((0, 813, 0xFFFF, rng.randrange(0x10000)))
            head = bytes([0x02, 0x80, n & 0xFF, n >> 8]) + rng.randbytes(rng.randint(0, 100))
            parts.append(head + sick.crc16(head).to_bytes(2, "little"))
            continue
        parts.append(sick.build_telegram(sick.DEVICE_ADDRESS, payload))
        if rng.random() < 0.2:
            parts.append(bytes([rng.choice((sick.ACK, sick.NAK))]))
    return b"".join(parts)


def _framed_payload(rng: random.Random, sonar: bool, t_us: int) -> bytes:
    from devices.odometry import encode_sample
    from devices.sonar import KINDS, MAX_ECHOES, encode_reading

    u = rng.random()
    if u < 0.5:
        if sonar:
            echoes = [
                (rng.choice(KINDS), rng.uniform(0, 70), rng.uniform(-4, 4))
                for _ in range(rng.randint(0, 4 if rng.random() < 0.8 else MAX_ECHOES))
            ]
            return encode_reading(t_us, rng.uniform(-4, 4), echoes)
        r, l = (rng.randint(-40000, 40000) for _ in range(2))
        return encode_sample(t_us, r, l, rng.choice((0, 0, 0, 1, 2, 4, 255)))
    if u < 0.75:
        return rng.randbytes(rng.choice((0, 1, 5, 8, 9, 10, 13, rng.randint(0, 255))))
    if sonar:  # count and body that disagree, unknown kinds, extreme fields
        n = rng.choice((0, 1, 2, 50, 255))
        echoes = b"".join(
            bytes([rng.choice((0, 1, 2, 3, 255))]) + rng.randbytes(4)
            for _ in range(min(n + rng.choice((0, 0, -1, 1)), 49) if n else 0)
        )
        return t_us.to_bytes(4, "little") + rng.randbytes(2) + bytes([n]) + echoes
    return (
        rng.choice((0, 0xFFFFFFFF, t_us)).to_bytes(4, "little")
        + rng.choice((b"\x00\x80\xff\x7f", b"\xff\x7f\x00\x80", rng.randbytes(4)))
        + bytes([rng.randrange(256)])
    )


def framed_stream(rng: random.Random, sonar: bool) -> bytes:
    """Frames of a sonar array or the odometry board: data frames (hostile payloads, SEQ and
    device times that jump, repeat or wrap), replies, error frames, the other device's
    frames, headers that lie about their length."""
    from devices import frames as fr

    sync = fr.SONAR_SYNC if sonar else fr.ODOMETRY_SYNC
    dtype = fr.DATA_SONAR if sonar else fr.DATA_ODOMETRY
    seq = rng.randrange(0x10000)
    t_us = rng.choice((0, 1000, 0xFFFFFFFF - 50_000, rng.randrange(1 << 32)))
    parts = []
    for _ in range(rng.randint(1, 12)):
        u = rng.random()
        seq = (seq + rng.choice((1, 1, 1, 1, 0, 2, -1, 0x8000, 0xFFFF))) & 0xFFFF
        t_us = (t_us + rng.choice((10_000, 10_000, 40_000, 0, -5_000, 1 << 31))) & 0xFFFFFFFF
        if u < 0.7:
            parts.append(fr.build_frame(sync, dtype, seq, _framed_payload(rng, sonar, t_us)))
        elif u < 0.8:
            ftype = rng.choice((fr.CMD_INFO | 0x80, fr.TYPE_ERROR, 0x42, rng.randrange(256)))
            parts.append(fr.build_frame(sync, ftype, seq, rng.randbytes(rng.randint(0, 12))))
        elif u < 0.9:
            other = fr.ODOMETRY_SYNC if sonar else fr.SONAR_SYNC
            parts.append(fr.build_frame(other, rng.choice((0x40, 0x41)), seq, rng.randbytes(9)))
        else:
            head = sync + bytes([rng.choice((0, 255, rng.randrange(256))), dtype]) + b"\0\0"
            parts.append(head + rng.randbytes(rng.randint(0, 40)))
    return b"".join(parts)


def device_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    for _ in range(n):
        device = rng.choice(("sick", "sick", "odometry", "sonar"))
        u = rng.random()
        if u < 0.08:
            data, what = rng.randbytes(rng.randint(0, 3000)), "random bytes"
        elif u < 0.15:  # random bytes sprinkled with sync sequences
            syncs = (b"\x02\x80", b"\x06", b"\x15") if device == "sick" else (b"\xaaS", b"\xaaO")
            data = b"".join(
                rng.choice(syncs) + rng.randbytes(rng.randint(0, 30)) for _ in range(50)
            )
            what = "random bytes and sync sequences"
        else:
            data = sick_stream(rng) if device == "sick" else framed_stream(rng, device == "sonar")
            what = "frames"
            for _ in range(rng.choice((0, 0, 1, 1, 2, 3))):
                data, w = mutate_bytes(data, rng)
                what += f"; {w}"
        ops: list[list] = []
        t = rng.choice((0.0, 0.5, 1e6, 1e9))
        i = 0
        while i < len(data) or not ops:
            k = min(len(data), i + rng.choice((1, 7, 64, 500, 4000)))
            t += rng.choice((0.0, 1e-4, 0.01, 0.2))
            ops.append(["feed", t, data[i:k].hex()])
            i = k
            if rng.random() < 0.08:
                ops.append([rng.choice(("baud", "reset")), rng.choice((9600, 38400, 500000, 50))])
        opts = {
            "device": device,
            "device_clock": rng.random() < 0.8,
            "array": rng.choice((0, 1, 2, 255)),
            "ops": ops,
        }
        yield Case(f"{device}: {what}; {len(ops)} ops", {"stream.bin": data}, opts)


_CFG: list = []


def device_runner(folder: Path, opts: dict) -> Result:
    """A fresh receiver fed the chunks (with line-rate changes and resets between them);
    every measurement turned into an event as the online run and the replay do, and the
    event into the record the replay writes."""
    from devices.driver import Measurement
    from devices.odometry import OdometryReceiver
    from devices.sick import SickReceiver
    from devices.sonar import SonarReceiver
    from fgslam.config import load_config
    from fgslam.io.logrecords import format_record
    from fgslam.online.ports import to_event

    if not _CFG:
        _CFG.append(load_config())
    cfg = _CFG[0]
    rcv: Any
    if opts["device"] == "sick":
        rcv = SickReceiver()
    elif opts["device"] == "odometry":
        rcv = OdometryReceiver(opts["device_clock"])
    else:
        rcv = SonarReceiver(opts["array"], opts["device_clock"])
    for op in opts["ops"]:
        if op[0] == "feed":
            for item in rcv.feed(op[1], bytes.fromhex(op[2])):
                ev = to_event(item, cfg) if isinstance(item, Measurement) else None
                if ev is not None:
                    format_record(ev)  # as fgslam replay writes it
        elif op[0] == "baud":
            rcv.set_baud(op[1])
        else:
            rcv.reset(op[1])
    rcv.counters()
    return Result("accepted")


# -- raw recordings


def raw_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    seed = rng.randrange(1 << 30)
    raw = fuzzlib.simulated_recording(work / "raw", 1.0, seed)
    base = {f"raw/{p.name}": p.read_bytes() for p in sorted(raw.iterdir())}
    for name, what, data in fuzzlib.mutated_recordings(raw, n, seed):
        yield Case(f"{name}: {what}", {**base, f"raw/{name}": data}, {})


def raw_runner(folder: Path, opts: dict) -> Result:
    return from_outcome(fuzzlib.replay_outcome(folder / "raw", folder / "out.log"))


# -- ROS bags


def write_bag(path: Path, ros1: bool, n: int = 12) -> None:
    """A small bag: /scan (31 beams over 180 deg), /odom (two messages per scan, driving an
    arc), /sonar (sensor_msgs/Range)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = ts.types
    g = {k.split("/")[-1]: T[k] for k in T if k.startswith("geometry_msgs/msg/")}
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr

    def header(t: float, frame: str) -> Any:
        sec = math.floor(t)
        kw = {"stamp": T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9))}
        return T["std_msgs/msg/Header"](frame_id=frame, **kw, **({"seq": 0} if ros1 else {}))

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        writer = Writer(path, version=8)
    zero = g["Vector3"](x=0.0, y=0.0, z=0.0)
    with writer:
        cs = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=ts)
        co = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        cr = writer.add_connection("/sonar", "sensor_msgs/msg/Range", typestore=ts)
        for k in range(2 * n):
            t = 1.0 + 0.1 * k
            x, y, th = 0.05 * k * math.cos(0.01 * k), 0.05 * k * math.sin(0.01 * k), 0.02 * k
            q = g["Quaternion"](x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2))
            pose = g["Pose"](position=g["Point"](x=x, y=y, z=0.0), orientation=q)
            odom = T["nav_msgs/msg/Odometry"](
                header=header(t, "odom"),
                child_frame_id="base_link",
                pose=g["PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=g["TwistWithCovariance"](
                    twist=g["Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
                ),
            )
            writer.write(co, round(t * 1e9), ser(odom, "nav_msgs/msg/Odometry"))
            if k % 2 == 0:
                continue
            r = np.linspace(1.0, 4.0, 31, dtype=np.float32)
            r[0], r[1] = np.inf, 0.01
            scan = T["sensor_msgs/msg/LaserScan"](
                header=header(t, "laser"),
                angle_min=-math.pi / 2,
                angle_max=math.pi / 2,
                angle_increment=math.pi / 30,
                time_increment=0.0,
                scan_time=0.1,
                range_min=0.05,
                range_max=30.0,
                ranges=r,
                intensities=np.zeros(0, dtype=np.float32),
            )
            writer.write(cs, round(t * 1e9), ser(scan, "sensor_msgs/msg/LaserScan"))
            rng_msg = T["sensor_msgs/msg/Range"](
                header=header(t, "sonar"),
                radiation_type=0,
                field_of_view=0.3,
                min_range=0.1,
                max_range=5.0,
                range=9.0 if k == 3 else 1.5,
            )
            writer.write(cr, round(t * 1e9), ser(rng_msg, "sensor_msgs/msg/Range"))


def bag_mutant(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    whats = []
    for _ in range(rounds(rng)):
        data, what = mutate_bytes(data, rng)
        whats.append(what)
    return data, "; ".join(whats)


def ros1_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    write_bag(work / "base.bag", True)
    base = (work / "base.bag").read_bytes()
    for _ in range(n):
        data, what = bag_mutant(base, rng)
        flags = reader_flags(rng, bag=True)
        yield Case(what, {"m.bag": data}, {"log": "m.bag", "flags": flags})


def ros2_cases(rng: random.Random, n: int, work: Path) -> Iterator[Case]:
    write_bag(work / "bag2", False)
    db = (work / "bag2" / "bag2.db3").read_bytes()
    meta = (work / "bag2" / "metadata.yaml").read_text()
    for _ in range(n):
        files = {"bag2/metadata.yaml": meta.encode(), "bag2/bag2.db3": db}
        if rng.random() < 0.12:
            text, what = mutate_fields(meta, rng, (*TOKENS, "null", "[]", "{}", "'", "-"))
            files["bag2/metadata.yaml"] = text.encode()
            what = f"metadata.yaml {what}"
        else:
            files["bag2/bag2.db3"], what = bag_mutant(db, rng)
        flags = reader_flags(rng, bag=True)
        yield Case(what, files, {"log": "bag2", "flags": flags})


# ---------------------------------------------------------------------------------------------
# The campaign

PATHS: dict[str, tuple[Callable, Callable[[Path, dict], Result]]] = {
    "carmen": (carmen_cases, convert_runner),
    "native": (native_cases, convert_runner),
    "victoria": (victoria_cases, victoria_runner),
    "evaluate": (evaluate_cases, evaluate_runner),
    "config": (config_cases, config_runner),
    "devices": (device_cases, device_runner),
    "raw": (raw_cases, raw_runner),
    "ros1": (ros1_cases, convert_runner),
    "ros2": (ros2_cases, convert_runner),
}


def write_files(folder: Path, files: dict[str, bytes]) -> None:
    for name, data in files.items():
        p = folder / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)


@dataclass
class Tally:
    """Counts of one path, and per kind of escape, hang and warning: count and first
    example."""

    inputs: int = 0
    counts: Counter = field(default_factory=Counter)
    warned: int = 0
    kinds: Counter = field(default_factory=Counter)  # (outcome, key) -> inputs
    examples: dict = field(default_factory=dict)  # (outcome, key) -> (what, detail, saved)
    seconds: float = 0.0


def save_case(path: str, case: Case, key: str, detail: str, save: Path, n: int) -> str:
    slug = re.sub(r"[^A-Za-z0-9]+", "-", key)[:60].strip("-")
    folder = save / f"{path}-{slug}-{n}"
    shutil.rmtree(folder, ignore_errors=True)
    write_files(folder / "input", case.files)
    meta = {"path": path, "what": case.what, "opts": case.opts, "kind": key, "detail": detail}
    (folder / "case.json").write_text(json.dumps(meta, indent=1) + "\n")
    return str(folder)


def campaign(path: str, n: int, seed: int, timeout: float, save: Path | None) -> Tally:
    gen, runner = PATHS[path]
    tally = Tally()
    rng = random.Random(f"{seed}:{path}")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=f"fuzz-{path}-") as tmp:
        work = Path(tmp)
        (work / "base").mkdir()
        for i, case in enumerate(gen(rng, n, work / "base")):
            folder = work / f"in{i}"
            folder.mkdir()
            write_files(folder, case.files)
            res = run_input(runner, folder, case.opts, timeout)
            shutil.rmtree(folder, ignore_errors=True)
            tally.inputs += 1
            tally.counts[res.kind] += 1
            tally.warned += bool(res.warnings)
            found = [(res.kind, res.key, res.detail)] if res.kind in ("escape", "hang") else []
            found += [("warning", k, m) for k, m in dict(res.warnings).items()]
            for kind, key, detail in found:
                tally.kinds[(kind, key)] += 1
                seen = tally.kinds[(kind, key)]
                if save is not None and seen <= EXAMPLES_SAVED:
                    where = save_case(path, case, f"{kind}-{key}", detail, save, seen)
                else:
                    where = ""
                if seen == 1:
                    tally.examples[(kind, key)] = (case.what, detail, where)
    tally.seconds = time.perf_counter() - t0
    return tally


def report(tallies: dict[str, Tally], seed: int, scale: float, wall: float) -> str:
    out = [
        f"fuzz campaign: seed {seed}, scale {scale:g}, "
        f"{sum(t.inputs for t in tallies.values())} inputs, {wall:.0f} s",
        "",
        "| path | inputs | accepted | clean errors | escapes | hangs | raw warnings |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    total = Tally()
    for path, t in tallies.items():
        c = t.counts
        out.append(
            f"| {path} | {t.inputs} | {c['accepted']} | {c['clean']} | {c['escape']} | "
            f"{c['hang']} | {t.warned} |"
        )
        total.inputs += t.inputs
        total.counts.update(c)
        total.warned += t.warned
    c = total.counts
    out.append(
        f"| **all** | {total.inputs} | {c['accepted']} | {c['clean']} | {c['escape']} | "
        f"{c['hang']} | {total.warned} |"
    )
    out.append("")
    out.append("seconds per path: " + ", ".join(f"{p} {t.seconds:.0f}" for p, t in tallies.items()))
    for label, kind in (("escapes", "escape"), ("hangs", "hang"), ("raw warnings", "warning")):
        rows = [(p, k, n, t.examples[(kind, k)]) for p, t in tallies.items()
                for (o, k), n in t.kinds.items() if o == kind]  # fmt: skip
        if not rows:
            continue
        out += ["", f"{label} by kind (inputs, path, kind; one example):"]
        for p, k, n, (what, detail, where) in sorted(rows, key=lambda r: (r[0], -r[2])):
            out.append(f"- {n} x {p}: {k}")
            out.append(f"  - input: {what[:300]}")
            if detail:
                out.append(f"  - message: {detail[:200]}")
            if where:
                out.append(f"  - saved: {where}")
    return "\n".join(out)


def reproduce(folder: Path) -> None:
    """Run a saved input again, letting any exception and warning through."""
    meta = json.loads((folder / "case.json").read_text())
    print(f"{meta['path']}: {meta['what']}\nrecorded: {meta['kind']}: {meta['detail']}")
    _, runner = PATHS[meta["path"]]
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(folder / "input", Path(tmp), dirs_exist_ok=True)
        if meta["path"] in ("carmen", "native", "ros1", "ros2"):  # the traceback, not a Result
            from fgslam.cli import main

            argv = ["convert", str(Path(tmp) / meta["opts"]["log"]), "--out", os.devnull]
            print("fgslam " + " ".join([*argv, *meta["opts"]["flags"]]))
            print("exit status", main([*argv, *meta["opts"]["flags"]]))
            return
        print(runner(Path(tmp), meta["opts"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="generation seed (default 0)")
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every count (default 1)")
    ap.add_argument("--paths", default=",".join(PATHS), help=f"comma-separated of {list(PATHS)}")
    ap.add_argument("--timeout", type=float, default=20.0, help="s per input (default 20)")
    ap.add_argument("--save", default=str(SAVE_DIR), help="where examples are saved ('' none)")
    ap.add_argument("--reproduce", metavar="DIR", help="run one saved input again")
    args = ap.parse_args()
    if args.reproduce:
        reproduce(Path(args.reproduce))
        return
    paths = [p.strip() for p in args.paths.split(",") if p.strip()]
    unknown = [p for p in paths if p not in PATHS]
    if unknown:
        ap.error(f"unknown paths {unknown}; known: {', '.join(PATHS)}")
    save = Path(args.save) if args.save else None
    if save is not None:
        save.mkdir(parents=True, exist_ok=True)
    signal.signal(signal.SIGALRM, _on_alarm)
    t0 = time.perf_counter()
    tallies = {}
    for p in paths:
        n = max(1, round(COUNTS[p] * args.scale))
        tallies[p] = campaign(p, n, args.seed, args.timeout, save)
        print(f"{p}: {n} inputs in {tallies[p].seconds:.0f} s", file=sys.stderr, flush=True)
    print(report(tallies, args.seed, args.scale, time.perf_counter() - t0))


if __name__ == "__main__":
    main()
