"""Mutated raw device recordings (``devices/raw.py``) for fuzz experiments.

- :func:`simulated_recording` writes a valid raw directory (laser, sonar arrays, odometry and
  ``session.json``) from a short simulated run, byte for byte as the drivers record one.
- :func:`mutate` damages a recording's bytes in one of several ways (:data:`MUTATIONS`): byte
  flips, truncation, inserted garbage, hostile values in the header's or a marker's JSON, and
  records re-signed (valid CRC) with hostile times or payloads.
- :func:`mutated_recordings` yields ``(file name, description, bytes)`` from a seed: the same
  seed gives the same mutants.
- :func:`replay_outcome` runs ``fgslam replay`` (``fgslam.cli.main``) on a directory and
  classifies the result.

Use from a script in this folder (``import fuzzlib``), as ``fuzz_raw.py`` does.
"""

from __future__ import annotations

import contextlib
import io
import json
import random
import re
import struct
import traceback
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from devices import frames as fr
from devices import sick
from devices.odometry import encode_sample
from devices.raw import MAGIC, RawRecorder
from devices.sonar import encode_reading
from fgslam.config import load_config
from fgslam.events import LaserScan, OdometryEvent, SonarReading
from fgslam.online.ports import SESSION_FILE, SESSION_FORMAT, SESSION_VERSION, laser_distances_cm
from fgslam.sim.simulate import events, plan_run
from fgslam.sim.world import load_world

_HEAD = struct.Struct("<cdI")
_CRC = struct.Struct("<I")

# JSON texts a hostile or broken writer could put where a value belongs
HOSTILE_JSON = (
    '"x"',
    '""',
    "null",
    "true",
    "false",
    "1e400",
    "-1e400",
    "NaN",
    "Infinity",
    "-Infinity",
    "-1",
    "0",
    "1.5",
    "1e-300",
    "99999999999999999999999999999",
    "1" + "0" * 5000,  # beyond Python's int digit limit
    "[]",
    "{}",
    '"sick-pls"',
    '"sonar"',
    '"odometry"',
    "[" * 50_000,  # nesting beyond the recursion limit
)
HOSTILE_TIMES = (
    float("nan"),
    float("inf"),
    -float("inf"),
    1e300,
    -1e300,
    -1.0,
    0.0,
    1e12,
)


@dataclass(frozen=True)
class Record:
    """One record of a raw file as it lies in the bytes: offset, tag, time, payload."""

    offset: int
    tag: bytes
    t: float
    data: bytes


def build_record(tag: bytes, t: float, data: bytes) -> bytes:
    """A record's bytes with a valid CRC (``devices/raw.py`` layout)."""
    head = _HEAD.pack(tag, t, len(data))
    return head + data + _CRC.pack(zlib.crc32(data, zlib.crc32(head)))


def split_header(data: bytes) -> tuple[bytes, int]:
    """The header line's JSON bytes and the offset of the first record (the whole file if
    there is no header line)."""
    end = data.find(b"\n", len(MAGIC))
    if not data.startswith(MAGIC) or end < 0:
        return b"", len(data)
    return data[len(MAGIC) : end], end + 1


def records(data: bytes) -> list[Record]:
    """The intact records of a raw file in order (stops at the first one that does not
    check)."""
    _, i = split_header(data)
    out = []
    while len(data) - i >= _HEAD.size + _CRC.size:
        tag, t, n = _HEAD.unpack_from(data, i)
        j = i + _HEAD.size + n
        if len(data) < j + _CRC.size or zlib.crc32(data[i:j]) != _CRC.unpack_from(data, j)[0]:
            break
        out.append(Record(i, tag, t, data[i + _HEAD.size : j]))
        i = j + _CRC.size
    return out


def _replace_json_field(text: str, key: str, value: str) -> str:
    """``text`` (one JSON object) with ``key``'s value replaced by the JSON text ``value``
    (added if the key is absent)."""
    obj = json.loads(text)
    if key in obj:
        pattern = re.compile(r'("' + re.escape(key) + r'"\s*:\s*)(' + _JSON_SCALAR + ")")
        new, k = pattern.subn(lambda m: m.group(1) + value, text, count=1)
        if k:
            return new
    body = text.rstrip()[:-1].rstrip()
    sep = "" if body.endswith("{") else ", "
    return f'{body}{sep}"{key}": {value}}}'


def _json_object_text(data: bytes) -> str | None:
    """``data`` as text if it is one JSON object, else None."""
    try:
        text = data.decode()
        return text if isinstance(json.loads(text), dict) else None
    except (ValueError, RecursionError):
        return None


_JSON_SCALAR = r'"(?:[^"\\]|\\.)*"|-?[0-9][0-9.eE+-]*|true|false|null|NaN|-?Infinity'


# -- mutations: each takes (file bytes, rng) and returns (new bytes, description)


def flip_bytes(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """One to eight bytes anywhere in the file XOR-ed with random values."""
    b = bytearray(data)
    where = sorted(rng.randrange(len(b)) for _ in range(rng.randint(1, 8)))
    for i in where:
        b[i] ^= rng.randint(1, 255)
    return bytes(b), f"bytes flipped at {where}"


def flip_header_bytes(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A byte of the magic or header line replaced (no CRC protects them)."""
    _, start = split_header(data)
    b = bytearray(data)
    i = rng.randrange(max(1, min(start, len(b))))
    b[i] = rng.randrange(256)
    return bytes(b), f"header byte {i} set to {b[i]}"


def truncate(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """The file cut anywhere (a crash, a partial copy)."""
    k = rng.randrange(len(data) + 1)
    return data[:k], f"truncated to {k} bytes"


def insert_garbage(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """Random bytes inserted, or a region duplicated, somewhere after the header."""
    _, start = split_header(data)
    i = rng.randint(min(start, len(data)), len(data))
    if rng.random() < 0.5:
        junk = rng.randbytes(rng.randint(1, 64))
        return data[:i] + junk + data[i:], f"{len(junk)} random bytes inserted at {i}"
    j = rng.randint(i, min(len(data), i + 200))
    return data[:i] + data[i:j] + data[i:], f"bytes {i}..{j} duplicated"


def header_field(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A header field (device, array, device_clock, port or a new one) given a hostile
    JSON value."""
    head, start = split_header(data)
    text = _json_object_text(head)
    if text is None:
        return flip_header_bytes(data, rng)
    key = rng.choice(("device", "array", "device_clock", "port", "extra"))
    value = rng.choice(HOSTILE_JSON)
    new = _replace_json_field(text, key, value).encode()
    return MAGIC + new + b"\n" + data[start:], f"header {key} = {value[:20]}"


def marker_field(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A marker's field (event, baud, reason) given a hostile JSON value, or the marker's
    bytes replaced by non-JSON; the record re-signed so that its CRC holds."""
    marks = [r for r in records(data) if r.tag == b"M" and _json_object_text(r.data)]
    if not marks:
        return truncate(data, rng)
    r = rng.choice(marks)
    if rng.random() < 0.15:
        payload = rng.choice((b"", b"not json", b"[1, 2]", b"\xff\xfe", b"[" * 50_000))
        what = f"marker at {r.offset} replaced by {payload[:10]!r}"
    else:
        key = rng.choice(("baud", "baud", "event", "reason"))
        value = rng.choice(HOSTILE_JSON)
        payload = _replace_json_field(r.data.decode(), key, value).encode()
        what = f"marker at {r.offset}: {key} = {value[:20]}"
    rec = build_record(r.tag, r.t, payload)
    end = r.offset + _HEAD.size + len(r.data) + _CRC.size
    return data[: r.offset] + rec + data[end:], what


def record_time(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A record's time set to a hostile value (NaN, inf, huge, negative), re-signed."""
    recs = records(data)
    if not recs:
        return truncate(data, rng)
    r = rng.choice(recs)
    t = rng.choice(HOSTILE_TIMES)
    rec = build_record(r.tag, t, r.data)
    end = r.offset + len(rec)
    return data[: r.offset] + rec + data[end:], f"record at {r.offset}: t = {t}"


def record_payload(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A record's bytes (or its tag) changed and the record re-signed: the device stream
    gets damage that the file's CRC does not catch."""
    recs = records(data)
    if not recs:
        return truncate(data, rng)
    r = rng.choice(recs)
    payload = bytearray(r.data)
    tag = r.tag
    if rng.random() < 0.2:
        tag = rng.choice((b"D", b"T", b"M"))
    elif payload and rng.random() < 0.7:
        for _ in range(rng.randint(1, 4)):
            payload[rng.randrange(len(payload))] = rng.randrange(256)
    else:
        payload = bytearray(rng.randbytes(rng.randint(0, 300)))
    end = r.offset + _HEAD.size + len(r.data) + _CRC.size
    rec = build_record(tag, r.t, bytes(payload))
    return data[: r.offset] + rec + data[end:], f"record at {r.offset} re-signed ({tag!r})"


def session_field(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    """A field of ``session.json`` (format, world, clock_speed, meta, config) given a hostile
    JSON value."""
    text = _json_object_text(data)
    if text is None:
        return truncate(data, rng)
    key = rng.choice(("format", "world", "clock_speed", "clock_speed", "meta", "config"))
    value = rng.choice((*HOSTILE_JSON, '"a\\nb"', '{"k": NaN}'))
    return _replace_json_field(text, key, value).encode(), f"session {key} = {value[:20]}"


SESSION_MUTATIONS = (session_field, session_field, flip_bytes, truncate)
MUTATIONS = (
    flip_bytes,
    flip_header_bytes,
    truncate,
    insert_garbage,
    header_field,
    marker_field,
    record_time,
    record_payload,
)


def mutate(
    data: bytes, rng: random.Random, rounds: int = 1, mutations: tuple = MUTATIONS
) -> tuple[bytes, str]:
    """``data`` after ``rounds`` mutations drawn from ``mutations``, and what they did."""
    whats = []
    for _ in range(rounds):
        if not data:
            break
        fn = rng.choice(mutations)
        data, what = fn(data, rng)
        whats.append(f"{fn.__name__}: {what}")
    return data, "; ".join(whats)


def mutated_recordings(
    raw_dir: str | Path, n: int, seed: int = 0
) -> Iterator[tuple[str, str, bytes]]:
    """``n`` mutants of the ``*.raw`` files (and ``session.json``) of ``raw_dir``: (file name,
    what was done, bytes), one file mutated each time (one to three mutations).
    Deterministic for a seed."""
    files = {p.name: p.read_bytes() for p in sorted(Path(raw_dir).glob("*.raw"))}
    if not files:
        raise ValueError(f"{raw_dir}: no *.raw files")
    session = Path(raw_dir) / SESSION_FILE
    if session.exists():
        files[SESSION_FILE] = session.read_bytes()
    rng = random.Random(seed)
    names = sorted(files)
    for _ in range(n):
        name = rng.choice(names)
        kinds = SESSION_MUTATIONS if name == SESSION_FILE else MUTATIONS
        data, what = mutate(files[name], rng, rng.choice((1, 1, 1, 2, 3)), kinds)
        yield name, what, data


# -- a valid recording


def simulated_recording(
    raw_dir: str | Path, duration: float = 3.0, seed: int = 0, world: str = "corridor"
) -> Path:
    """Write a raw directory of ``duration`` s of a simulated run of ``world``, as the drivers
    record one: ``laser.raw`` (opened at 9600 baud, switched to 38400), ``sonar<i>.raw``,
    ``odometry.raw`` (115200 baud; frames in one or two reads) and ``session.json``."""
    raw = Path(raw_dir)
    raw.mkdir(parents=True, exist_ok=True)
    cfg = load_config()
    w = load_world(world)
    run = plan_run(w, cfg, seed, None, duration)
    rng = random.Random(seed)
    names = ["laser", *(f"sonar{i}" for i in range(len(cfg.sonar.arrays))), "odometry"]
    headers = {
        "laser": {"device": "sick-pls", "port": "/dev/ttyS0"},
        "odometry": {"device": "odometry", "port": "/dev/ttyS9", "device_clock": True},
    }
    for i in range(len(cfg.sonar.arrays)):
        port = f"/dev/ttyS{i + 1}"
        headers[f"sonar{i}"] = {"device": "sonar", "port": port, "array": i, "device_clock": True}
    session = {
        "format": SESSION_FORMAT,
        "version": SESSION_VERSION,
        "world": world,
        "clock_speed": 1.0,
        "config": cfg.to_dict(),
        "devices": headers,
        "meta": {"fuzz_seed": seed},
    }
    (raw / SESSION_FILE).write_text(json.dumps(session, indent=1) + "\n")
    recs = {n: RawRecorder(raw / f"{n}.raw", headers[n]) for n in names}
    try:
        laser = recs["laser"]
        laser.marker(0.0, "open", baud=9600)
        laser.sent(0.001, sick.build_telegram(sick.HOST_ADDRESS, bytes([sick.CMD_STATUS])))
        laser.received(0.02, bytes([sick.ACK]))
        laser.marker(0.03, "baud", baud=38400)
        for n in names[1:]:
            recs[n].marker(0.0, "open", baud=fr.DEFAULT_BAUD)
        seqs = dict.fromkeys(names, 0)

        def framed(name: str, sync: bytes, ftype: int, t: float, payload: bytes) -> None:
            frame = fr.build_frame(sync, ftype, seqs[name], payload)
            seqs[name] += 1
            _received(recs[name], t + 0.0005, frame, rng)

        for ev in events(w, cfg, run):
            if ev.t < 0.05:
                continue
            if isinstance(ev, LaserScan):
                payload = sick.encode_b0(laser_distances_cm(ev.ranges))
                tel = sick.build_telegram(sick.DEVICE_ADDRESS, payload)
                _received(laser, ev.t + sick.transmission_time(len(tel), 38400), tel, rng)
            elif isinstance(ev, SonarReading):
                echoes = [(e.kind, e.range, e.bearing) for e in ev.echoes]
                payload = encode_reading(round(ev.t * 1e6), ev.pan, echoes)
                framed(f"sonar{ev.array}", fr.SONAR_SYNC, fr.DATA_SONAR, ev.t, payload)
            elif isinstance(ev, OdometryEvent):
                payload = encode_sample(round(ev.t * 1e6), ev.ticks_right, ev.ticks_left)
                framed("odometry", fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, ev.t, payload)
        for rec in recs.values():
            rec.marker(duration + 0.1, "close", reason="end of run")
    finally:
        for rec in recs.values():
            rec.close()
    return raw


def _received(rec: RawRecorder, t: float, frame: bytes, rng: random.Random) -> None:
    """``frame`` read in one chunk at ``t`` or in two (the first a little earlier)."""
    if len(frame) > 2 and rng.random() < 0.3:
        k = rng.randrange(1, len(frame))
        rec.received(t - 1e-4, frame[:k])
        rec.received(t, frame[k:])
    else:
        rec.received(t, frame)


# -- running the replay


@dataclass(frozen=True)
class Outcome:
    """What ``fgslam replay`` did: ``kind`` is "decoded" (status 0), "refused" (status 2,
    one error line), "traceback" (an exception escaped) or "odd" (anything else);
    ``detail`` the error line or the exception."""

    kind: str
    status: int | None
    detail: str


def cli_outcome(command: str, args: list[str], done: str) -> Outcome:
    """Run ``fgslam COMMAND ARGS`` in this process and classify what it did (``done``: the
    kind of status 0)."""
    from fgslam.cli import main

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            status = main([command, *args])
    except Exception as exc:  # what the experiment counts: any exception that escaped
        last = traceback.extract_tb(exc.__traceback__)[-1]
        where = f"{Path(last.filename).name}:{last.lineno}"
        return Outcome("traceback", None, f"{type(exc).__name__} at {where}: {exc}"[:300])
    lines = err.getvalue().strip().splitlines()
    if status == 0:
        return Outcome(done, 0, "")
    if status == 2 and len(lines) == 1 and lines[0].startswith(f"fgslam {command}: error: "):
        return Outcome("refused", 2, lines[0])
    return Outcome("odd", status, err.getvalue()[:300])


def replay_outcome(raw_dir: str | Path, out: str | Path) -> Outcome:
    """Run ``fgslam replay RAW_DIR --out OUT`` in this process and classify what it did."""
    return cli_outcome("replay", [str(raw_dir), "--out", str(out)], "decoded")


# -- evaluation inputs: TUM trajectories and relations files (fgslam evaluate)

EVAL_TOKENS = (
    "nan", "inf", "-inf", "1e308", "-1e308", "1e300", "1e200", "1e155", "1e10", "1e7", "0",
    "-0.0", "1e-300", "x", "#", "", "1_0", "\x00",
)  # fmt: skip


def tum_text(n: int = 20) -> str:
    """A valid TUM trajectory of ``n`` poses 0.5 s apart (a curve, yaw quaternions)."""
    import math

    rows = []
    for k in range(n):
        x, y, th = 0.3 * k, 0.02 * k * k, 0.05 * k
        rows.append(f"{0.5 * k!r} {x!r} {y!r} 0 0 0 {math.sin(th / 2)!r} {math.cos(th / 2)!r}")
    return "\n".join(rows) + "\n"


def relations_text(n: int = 20) -> str:
    """Valid relations (``t1 t2 x y z roll pitch yaw``) between poses k and k + 2 of
    :func:`tum_text`'s trajectory."""
    import math

    rows = []
    for k in range(n - 2):
        a = (0.3 * k, 0.02 * k * k, 0.05 * k)
        b = (0.3 * (k + 2), 0.02 * (k + 2) ** 2, 0.05 * (k + 2))
        c, s = math.cos(a[2]), math.sin(a[2])
        dx, dy = b[0] - a[0], b[1] - a[1]
        rows.append(
            f"{0.5 * k!r} {0.5 * (k + 2)!r} {c * dx + s * dy!r} {-s * dx + c * dy!r} 0 0 0 "
            f"{b[2] - a[2]!r}"
        )
    return "\n".join(rows) + "\n"


def mutate_lines(text: str, rng: random.Random, count: int = 3) -> tuple[str, str]:
    """A text file of whitespace-separated fields with ``count`` mutations (a field replaced
    by one of :data:`EVAL_TOKENS`, a field dropped or added, a line repeated, removed or
    swapped with another): (description, mutated text)."""
    lines = [ln.split() for ln in text.splitlines()]
    done = []
    for _ in range(count):
        if not lines:
            break
        k = rng.randrange(len(lines))
        op = rng.choice(["token", "token", "token", "drop", "add", "dup", "del", "swap"])
        if op == "token" and lines[k]:
            i, tok = rng.randrange(len(lines[k])), rng.choice(EVAL_TOKENS)
            lines[k][i] = tok
            done.append(f"line {k + 1} field {i + 1} = {tok!r}")
        elif op == "drop" and lines[k]:
            del lines[k][rng.randrange(len(lines[k]))]
            done.append(f"line {k + 1} a field dropped")
        elif op == "add":
            lines[k].append(rng.choice(EVAL_TOKENS))
            done.append(f"line {k + 1} a field added")
        elif op == "dup":
            lines.insert(k, list(lines[k]))
            done.append(f"line {k + 1} repeated")
        elif op == "del":
            del lines[k]
            done.append(f"line {k + 1} removed")
        elif op == "swap":
            j = rng.randrange(len(lines))
            lines[k], lines[j] = lines[j], lines[k]
            done.append(f"lines {k + 1} and {j + 1} swapped")
    return "; ".join(done), "\n".join(" ".join(ln) for ln in lines) + "\n"


def mutated_eval_inputs(seed: int, count: int) -> Iterator[tuple[str, str, str]]:
    """``count`` mutants ``(kind, description, text)`` of :func:`tum_text` (kind "tum") and
    :func:`relations_text` (kind "relations"); the same seed gives the same mutants."""
    rng = random.Random(seed)
    for _ in range(count):
        kind = rng.choice(["tum", "relations"])
        base = tum_text() if kind == "tum" else relations_text()
        desc, text = mutate_lines(base, rng, rng.randint(1, 4))
        yield kind, desc, text


def evaluate_outcome(args: list[str]) -> Outcome:
    """Run ``fgslam evaluate ARGS`` in this process and classify it as :func:`replay_outcome`
    does ("evaluated" for status 0)."""
    return cli_outcome("evaluate", args, "evaluated")
