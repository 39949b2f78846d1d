"""The native log format: exact round trips, deterministic output, streaming, one-line errors
naming file and line, tolerant mode, gzip, and fuzzing (only LogFormatError may escape)."""

from __future__ import annotations

import gzip
import itertools
import math
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fgslam.config import from_dict, load_config
from fgslam.errors import UserError
from fgslam.events import LaserScan, OdometryEvent, SonarEcho, SonarReading, TruthPose
from fgslam.io import logfile, logrecords
from fgslam.io.logfile import LogReader, read_log
from fgslam.io.logrecords import LogFormatError, format_record, open_text
from fgslam.io.logwriter import LogWriter
from fgslam.io.readers.source import MAX_PROBLEMS

CFG = load_config()
N = CFG.laser.n_beams
_small = CFG.to_dict()
_small["laser"]["n_beams"] = 3
SMALL = from_dict(_small, "<small>")  # 3 beams, 2 sonar arrays: fast fuzzing
FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def events(rng: np.random.Generator | None = None) -> list:
    rng = rng or np.random.default_rng(1)
    ranges = np.round(rng.uniform(0.0, 40.0, N) / 0.05) * 0.05
    ranges[ranges > 30.0] = np.nan
    return [
        OdometryEvent(0.01, 12, -3),
        TruthPose(0.0, -1.5, 2.25, -math.pi),
        LaserScan(0.2133333333333333, ranges),
        LaserScan(0.4, np.full(N, np.nan)),
        SonarReading(0.04, 1, -1.2345678901234567, (SonarEcho("plane", 2.5, -0.1),)),
        SonarReading(0.08, 0, 0.0, ()),
        SonarReading(
            1e-7,
            1,
            -0.0,
            tuple(SonarEcho(k, 1 / 3, -(2**-1074)) for k in ("plane", "corner", "edge")),
        ),
        OdometryEvent(1.7e9 + 0.123456789, -(2**62), 2**62),
        TruthPose(123456.78901234567, 1e-300, -1.7976931348623157e308, 5e-324),
    ]


def write(path: Path, evs, cfg=CFG, world="box world", meta=None) -> Path:
    with LogWriter(path, cfg, world, meta) as w:
        for e in evs:
            w.write(e)
    return path


def log_text(tmp_path: Path, records: list[str], cfg=CFG, name="run.log") -> Path:
    """A log with a valid header (lines 1-3) followed by ``records`` as raw text lines."""
    path = write(tmp_path / name, [], cfg)
    with open(path, "a") as f:
        f.write("".join(r + "\n" for r in records))
    return path


def error_of(path: Path, tolerant: bool = False) -> str:
    with pytest.raises(LogFormatError) as exc:
        read_log(path, tolerant=tolerant)
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("name", ["run.log", "run.log.gz"])
def test_round_trip_every_event_type(tmp_path, name):
    evs = events()
    path = write(tmp_path / name, evs, meta={"seed": 7, "simulator": "fgslam-sim 0.1"})
    header, out = read_log(path)
    assert out == evs
    assert [type(e) for e in out] == [type(e) for e in evs]
    assert header.version == 2 and header.world == "box world"
    assert header.meta == {"seed": 7, "simulator": "fgslam-sim 0.1"}
    assert header.config == CFG and header.config.source == f"{path} (CONFIG header)"
    assert isinstance(out[6], SonarReading) and isinstance(out[6].echoes, tuple)
    assert math.copysign(1.0, out[6].pan) == -1.0  # -0.0 survives


def test_record_syntax():
    assert format_record(OdometryEvent(0.01, 3, -4)) == "O 0.01 3 -4"
    assert format_record(TruthPose(0.1, 1e-300, -2.5, 0.0)) == "T 0.1 1e-300 -2.5 0.0"
    s = SonarReading(0.3, 1, -0.5, (SonarEcho("corner", 1.25, 0.1), SonarEcho("edge", 2.0, 0)))
    assert format_record(s) == "S 0.3 1 -0.5 2 C 1.25 0.1 E 2.0 0.0"
    assert format_record(SonarReading(0.3, 0, 0.5, ())) == "S 0.3 0 0.5 0"
    assert format_record(LaserScan(2.0, np.array([0.15, np.nan, 3]))) == "L 2.0 3 0.15 nan 3.0"


def test_header_and_comments(tmp_path):
    path = write(tmp_path / "a.log", [OdometryEvent(1.0, 1, 2)], world="  lab: 2nd floor ")
    lines = path.read_text().splitlines()
    assert lines[0] == "FGSLAM-LOG 2" and lines[1].startswith("CONFIG {")
    assert lines[2] == "WORLD   lab: 2nd floor "
    path.write_text(
        "\n".join([lines[0], "# a comment", "", lines[1], 'META {"a": 1}', lines[2]])
        + '\nMETA {"b":[1,2]}\n\n  # indented comment\r\n'
        + lines[3]
        + "\r\n"
    )
    header, out = read_log(path)
    assert header.world == "  lab: 2nd floor " and header.meta == {"a": 1, "b": [1, 2]}
    assert out == [OdometryEvent(1.0, 1, 2)]


@given(
    t=st.floats(-1e10, 1e10),
    ticks=st.tuples(st.integers(-(2**63), 2**63), st.integers(-(2**63), 2**63)),
    ranges=st.lists(st.floats(allow_infinity=False), min_size=3, max_size=3),
    pose=st.tuples(*[st.floats(allow_nan=False, allow_infinity=False)] * 3),
    echoes=st.lists(
        st.tuples(
            st.sampled_from(["plane", "corner", "edge"]),
            st.floats(allow_nan=False, allow_infinity=False),
            st.floats(allow_nan=False, allow_infinity=False),
        ),
        max_size=5,
    ),
    array=st.integers(0, 1),
)
@settings(max_examples=100, deadline=None)
def test_round_trip_property(t, ticks, ranges, pose, echoes, array):
    evs = [
        OdometryEvent(t, *ticks),
        LaserScan(t, np.array(ranges)),
        SonarReading(t, array, pose[2], tuple(SonarEcho(*e) for e in echoes)),
        TruthPose(t, *pose),
    ]
    with tempfile.TemporaryDirectory() as d:
        assert read_log(write(Path(d) / "p.log", evs, SMALL))[1] == evs


def test_writer_rejects_what_it_cannot_write(tmp_path):
    with pytest.raises(ValueError, match="line break"):
        LogWriter(tmp_path / "a.log", CFG, "two\nlines")
    with LogWriter(tmp_path / "a.log", CFG, "w") as w:
        with pytest.raises(ValueError, match="n_beams=361"):
            w.write(LaserScan(0.0, np.zeros(360)))
        with pytest.raises(ValueError, match="finite"):
            w.write(LaserScan(0.0, np.full(N, np.inf)))
        with pytest.raises(ValueError, match="finite"):
            w.write(OdometryEvent(math.nan, 1, 1))
        with pytest.raises(ValueError, match="array 2"):
            w.write(SonarReading(0.0, 2, 0.0, ()))
        with pytest.raises(ValueError, match="kind"):
            w.write(SonarReading(0.0, 0, 0.0, (SonarEcho("wall", 1.0, 0.0),)))
        with pytest.raises(TypeError):
            w.write(OdometryEvent(0.0, 1.5, 1))  # type: ignore[arg-type]
    assert read_log(tmp_path / "a.log")[1] == []  # nothing half-written


# ------------------------------------------------------------------- determinism and gzip


@pytest.mark.parametrize("suffix", [".log", ".log.gz"])
def test_byte_identical_output(tmp_path, suffix):
    a = write(tmp_path / f"a{suffix}", events(np.random.default_rng(3)), meta={"seed": 3})
    b = write(tmp_path / f"other_name{suffix}", events(np.random.default_rng(3)), meta={"seed": 3})
    assert a.read_bytes() == b.read_bytes()
    if suffix.endswith(".gz"):
        assert a.read_bytes()[:2] == b"\x1f\x8b"
        assert a.read_bytes()[4:8] == b"\0\0\0\0"  # mtime 0
        assert gzip.decompress(a.read_bytes()).startswith(b"FGSLAM-LOG 2\nCONFIG {")


def test_gzip_detected_by_magic_not_suffix(tmp_path):
    evs = events()
    gz = write(tmp_path / "a.log.gz", evs)
    renamed = gz.rename(tmp_path / "a.log")
    assert read_log(renamed)[1] == evs
    plain = write(tmp_path / "b.log", evs).rename(tmp_path / "b.log.gz")
    assert read_log(plain)[1] == evs


def test_open_text(tmp_path):
    with open_text(tmp_path / "x.txt.gz", "w") as f:
        f.write("héllo\n")
    assert gzip.decompress((tmp_path / "x.txt.gz").read_bytes()) == "héllo\n".encode()
    with open_text(tmp_path / "x.txt.gz", "r") as f:
        assert f.read() == "héllo\n"


def test_truncated_gzip(tmp_path):
    data = write(tmp_path / "a.log.gz", events() * 20).read_bytes()
    for cut in (len(data) - 4, len(data) // 2, 12):
        p = tmp_path / f"cut{cut}.log.gz"
        p.write_bytes(data[:cut])
        for tolerant in (False, True):
            msg = error_of(p, tolerant)
            assert msg.startswith(f"{p}: corrupt or truncated gzip data"), msg


def test_corrupt_gzip(tmp_path):
    good = write(tmp_path / "a.log.gz", events() * 20).read_bytes()
    zeroed = bytearray(good)
    zeroed[len(good) // 2 : len(good) // 2 + 16] = bytes(16)
    (tmp_path / "b.log.gz").write_bytes(bytes(zeroed))
    # tolerant: the damaged deflate stream may first decode to garbage records
    assert "corrupt or truncated gzip data" in error_of(tmp_path / "b.log.gz", tolerant=True)
    (tmp_path / "c.log.gz").write_bytes(b"\x1f\x8b" + b"not really gzip" * 10)
    assert "corrupt or truncated gzip data at the start" in error_of(tmp_path / "c.log.gz")
    (tmp_path / "d.log.gz").write_bytes(good[:-8] + b"garbage!")  # bad CRC and size
    assert "corrupt or truncated gzip data after line" in error_of(tmp_path / "d.log.gz")
    (tmp_path / "e.log.gz").write_bytes(good + b"trailing junk")
    assert "corrupt or truncated gzip data after line" in error_of(tmp_path / "e.log.gz")


# ------------------------------------------------------------------------------ streaming


def test_streaming_returns_events_before_a_bad_tail(tmp_path):
    """The reader is a generator over lines: the start is returned long before the tail."""
    odo = [OdometryEvent(0.01 * i, i, -i) for i in range(20000)]
    path = write(tmp_path / "big.log", odo)
    with open(path, "ab") as f:
        f.write(b"O 1 2\n\xff\xfe\x00 garbage")
    with LogReader(path) as reader:
        assert list(itertools.islice(reader, 3)) == odo[:3]
    reader = LogReader(path)
    got = []
    with pytest.raises(LogFormatError, match=rf"big.log:{20000 + 4}: odometry record"):
        for e in reader:
            got.append(e)
    assert got == odo


def test_streaming_gzip_before_truncation(tmp_path):
    odo = [OdometryEvent(0.01 * i, i, -i) for i in range(20000)]
    data = write(tmp_path / "big.log.gz", odo).read_bytes()
    (tmp_path / "cut.log.gz").write_bytes(data[: len(data) // 2])
    with LogReader(tmp_path / "cut.log.gz") as reader:
        assert next(iter(reader)) == odo[0]
        got = []
        with pytest.raises(LogFormatError, match="truncated gzip"):
            for e in reader:
                got.append(e)
        assert got == odo[1 : len(got) + 1] and len(got) > 100


# ------------------------------------------------------------------------------ errors


def _valid_laser(n=N):
    return "L 1.0 " + f"{n} " + " ".join(["1.5"] * n)


@pytest.mark.parametrize(
    ("records", "expected"),
    [
        (["X 1 2"], "run.log:4: unknown record tag 'X' (expected O, L, S or T)"),
        (["O 1 2 3", "O inf 1 2"], "run.log:5: odometry record: timestamp: expected a finite"),
        (["T nan 1 2 3"], "run.log:4: truth record: timestamp: expected a finite number"),
        (["L -inf 361"], "run.log:4: laser record: timestamp: expected a finite number"),
        (["O 1 2"], "run.log:4: odometry record: expected 4 fields 'O t ticks_right ticks_left'"),
        (["O 1 2 3 4"], "run.log:4: odometry record: expected 4 fields"),
        (["T 1 2 3"], "run.log:4: truth record: expected 5 fields 'T t x y theta', got 4"),
        (["O 1 2.5 3"], "run.log:4: odometry record: ticks_right: expected an integer, got '2.5'"),
        (["O 1 2 1_0"], "run.log:4: odometry record: ticks_left: expected an integer"),
        (["T 1 x 0 0"], "run.log:4: truth record: x: expected a number, got 'x'"),
        (["T 1 0 0 1e999"], "run.log:4: truth record: theta: expected a finite number"),
        (["O 1 2 3", "O 1e308 1 2"], "run.log:5: odometry record: timestamp: '1e308' is not a"),
        (["S -2e10 0 0 0"], "run.log:4: sonar record: timestamp: '-2e10' is not a plausible"),
        (["", "# c", "L 1.0"], "run.log:6: laser record: expected 'L t n r_1 ... r_n', got 2"),
        (
            [_valid_laser(360)],
            "run.log:4: laser record: n=360 but the configuration has n_beams=361",
        ),
        (
            [_valid_laser()[:-4]],
            "run.log:4: laser record: expected 361 ranges after n=361, got 360",
        ),
        ([_valid_laser() + " 2.0"], "laser record: expected 361 ranges after n=361, got 362"),
        ([_valid_laser()[:-3] + "inf"], "run.log:4: laser record: range 361: expected a finite"),
        ([_valid_laser()[:-3] + "abc"], "run.log:4: laser record: range 361: expected a number"),
        (["L 1.0 -1"], "run.log:4: laser record: n: expected an integer >= 0, got -1"),
        (["S 1 0 0.5 1 X 1.0 0.0"], "run.log:4: sonar record: echo 1: unknown kind 'X'"),
        (["S 1 0 0.5 1 p 1.0 0.0"], "run.log:4: sonar record: echo 1: unknown kind 'p'"),
        (["S 1 0 0.5 2 P 1.0 0.0"], "run.log:4: sonar record: expected 6 echo fields after n=2"),
        (["S 1 0 0.5"], "run.log:4: sonar record: expected 'S t array pan n"),
        (["S 1 2 0.5 0"], "run.log:4: sonar record: array 2 not in the configuration"),
        (["S 1 0 nan 0"], "run.log:4: sonar record: pan: expected a finite number"),
        (["S 1 0 0 1 E 1 inf"], "run.log:4: sonar record: echo 1 bearing: expected a finite"),
        (["O 1 2 3", "WORLD again"], "run.log:5: WORLD header line after a record"),
        (["O 1 2 3", "META {}"], "run.log:5: META header line after a record"),
    ],
)
def test_bad_records(tmp_path, records, expected):
    path = log_text(tmp_path, records)
    msg = error_of(path)
    assert msg.startswith(str(tmp_path)) and expected in msg, msg
    # tolerant mode skips exactly the one bad record
    with LogReader(path, tolerant=True) as reader:
        out = list(reader)
    messages = reader.problems.messages
    assert reader.skipped == 1 and len(messages) == 1 and expected in messages[0]
    assert sum(reader.skipped_by_reason.values()) == 1
    assert len(out) == sum(1 for r in records if r and not r.startswith("#")) - 1


def test_not_utf8_record(tmp_path):
    path = log_text(tmp_path, ["O 1 2 3"])
    with open(path, "ab") as f:
        f.write(b"O 1 \xff 3\n")
    assert error_of(path).endswith("run.log:5: not UTF-8 text")


def test_line_too_long(tmp_path, monkeypatch):
    monkeypatch.setattr(logfile, "MAX_LINE_BYTES", 20000)
    path = log_text(tmp_path, ["O 1 2 3", "T " + "1" * 50000, "O 2 3 4"])
    assert error_of(path).endswith("run.log:5: line longer than 20000 bytes")
    with LogReader(path, tolerant=True) as reader:
        assert list(reader) == [OdometryEvent(1.0, 2, 3), OdometryEvent(2.0, 3, 4)]
    assert reader.skipped_by_reason == {"line too long": 1}


def _header_lines():
    return ["FGSLAM-LOG 1", f"CONFIG {logrecords._json(CFG.to_dict())}", "WORLD w"]


def _cfg_with(**laser):
    d = CFG.to_dict()
    d["laser"].update(laser)
    return f"CONFIG {logrecords._json(d)}"


@pytest.mark.parametrize(
    ("lines", "expected"),
    [
        ([], "run.log: empty file, not an fgslam log (expected first line 'FGSLAM-LOG 2')"),
        (["hello world"], "run.log:1: not an fgslam log (expected first line 'FGSLAM-LOG 2'"),
        (["", "FGSLAM-LOG 1"], "run.log:1: not an fgslam log"),
        (["FGSLAM-LOG"], "run.log:1: not an fgslam log"),
        (["FGSLAM-LOG 3"], "run.log:1: unsupported log format version 3 (this fgslam reads"),
        (["FGSLAM-LOG one"], "run.log:1: bad format version 'one' (expected an integer)"),
        (["FGSLAM-LOG 1", "WORLD w"], "run.log: missing CONFIG header line"),
        (["FGSLAM-LOG 1", "WORLD w", "O 1 2 3"], "run.log:3: missing CONFIG header line"),
        ([*_header_lines()[:2], "O 1 2 3"], "run.log:3: missing WORLD header line"),
        ([*_header_lines()[:2], "CONFIG {"], "run.log:3: CONFIG header: expected a JSON object"),
        (["FGSLAM-LOG 1", "CONFIG {", "WORLD w"], "run.log:2: CONFIG header: expected a JSON obj"),
        (["FGSLAM-LOG 1", "CONFIG [1]"], "run.log:2: CONFIG header: expected a JSON object, got"),
        (["FGSLAM-LOG 1", "CONFIG " + "[" * 100000], "run.log:2: CONFIG header: expected a JSON"),
        (
            ["FGSLAM-LOG 1", _cfg_with(n_beams=-1), "WORLD w"],
            "run.log:2: CONFIG header: key 'laser.n_beams': expected a positive number, got -1",
        ),
        (
            ["FGSLAM-LOG 1", _cfg_with(fov_deg=10**400), "WORLD w"],
            "run.log:2: CONFIG header: invalid value (int too large to convert to float)",
        ),
        (["FGSLAM-LOG 1", "CONFIG {}", "WORLD w"], "run.log:2: CONFIG header: missing required"),
        ([*_header_lines(), "WORLD x"], "run.log:4: second WORLD header line"),
        ([*_header_lines(), _header_lines()[1]], "run.log:4: second CONFIG header line"),
        ([*_header_lines(), "META [1]"], "run.log:4: META header: expected a JSON object"),
        ([*_header_lines(), "META nope"], "run.log:4: META header: expected a JSON object"),
        ([*_header_lines(), 'META {"a":1}', 'META {"a":2}'], "run.log:5: META header: key 'a'"),
    ],
)
def test_header_errors_are_fatal_even_when_tolerant(tmp_path, lines, expected):
    path = tmp_path / "run.log"
    path.write_text("".join(line + "\n" for line in lines))
    for tolerant in (False, True):
        msg = error_of(path, tolerant)
        assert msg.startswith(str(path)) and expected in msg, msg


def test_cannot_open(tmp_path):
    msg = error_of(tmp_path / "missing.log")
    assert "missing.log: cannot open log" in msg
    assert issubclass(LogFormatError, UserError)


def test_tolerant_counts(tmp_path):
    path = log_text(
        tmp_path,
        ["O 1 2 3", "X", "O 1 2", "L 1 2", "O 2 3 4", "Q 1", "S 1 0 0 1 Z 1 1", "T 5 1 2 3"]
        + ["O x 1 1"] * 30,
    )
    with LogReader(path, tolerant=True) as reader:
        out = list(reader)
    assert out == [OdometryEvent(1.0, 2, 3), OdometryEvent(2.0, 3, 4), TruthPose(5.0, 1, 2, 3)]
    assert reader.skipped == 35
    assert reader.skipped_by_reason == {
        "unknown record tag": 2,
        "odometry record": 31,
        "laser record": 1,
        "sonar record": 1,
    }
    messages = reader.problems.messages
    assert len(messages) == MAX_PROBLEMS
    assert messages[0] == f"{path}:5: unknown record tag 'X' (expected O, L, S or T)"


# ------------------------------------------------------------------------------ fuzzing


def _read_all(path: Path, tolerant: bool):
    try:
        return read_log(path, tolerant=tolerant)[1]
    except LogFormatError as exc:
        assert "\n" not in str(exc)
        return None


def _header_bytes() -> bytes:
    with tempfile.TemporaryDirectory() as d:
        return write(Path(d) / "h.log", [], SMALL).read_bytes()


HEADER = _header_bytes()


@given(tail=st.binary(max_size=1000))
@FUZZ
def test_fuzz_random_bytes_after_header(tail):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.log"
        p.write_bytes(HEADER + tail)
        for tolerant in (False, True):
            _read_all(p, tolerant)  # only LogFormatError may escape
        g = Path(d) / "f.log.gz"
        g.write_bytes(gzip.compress(HEADER + tail, mtime=0))
        _read_all(g, False)


@given(lines=st.lists(st.text(max_size=80), max_size=20))
@FUZZ
def test_fuzz_random_text_lines_after_header(lines):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.log"
        p.write_bytes(HEADER + "\n".join(lines).encode("utf-8", "surrogatepass"))
        for tolerant in (False, True):
            _read_all(p, tolerant)


@given(data=st.binary(min_size=1, max_size=200), pos=st.integers(0, 10**6))
@FUZZ
def test_fuzz_corrupted_gzip(data, pos):
    gz = bytearray(gzip.compress(HEADER + b"O 1 2 3\n" * 50, mtime=0))
    pos %= len(gz)
    gz[pos : pos + len(data)] = data
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.log.gz"
        p.write_bytes(bytes(gz))
        for tolerant in (False, True):
            _read_all(p, tolerant)


_finite = st.floats(allow_nan=False, allow_infinity=False)
_stamp = st.floats(-1e10, 1e10)
_events = st.one_of(
    st.builds(OdometryEvent, _stamp, st.integers(-(10**12), 10**12), st.integers(-5, 5)),
    st.builds(TruthPose, _stamp, _finite, _finite, _finite),
    st.builds(
        LaserScan,
        _stamp,
        st.lists(st.floats(allow_infinity=False), min_size=3, max_size=3).map(np.array),
    ),
    st.builds(
        SonarReading,
        _stamp,
        st.integers(0, 1),
        _finite,
        st.lists(
            st.builds(SonarEcho, st.sampled_from(["plane", "corner", "edge"]), _finite, _finite),
            max_size=3,
        ).map(tuple),
    ),
)
# Lines that are certainly bad records: an unknown tag, a record missing its last field,
# bytes that are not UTF-8.
_garbage = st.one_of(
    st.text(max_size=40).map(lambda s: ("X" + s.replace("\n", " ")).encode()),
    _events.map(lambda e: format_record(e).rsplit(" ", 1)[0].encode()),
    st.binary(max_size=40).map(lambda b: b"\xff" + b.replace(b"\n", b"")),
)


@given(
    items=st.lists(
        st.one_of(_events.map(lambda e: (True, e)), _garbage.map(lambda g: (False, g))),
        max_size=25,
    )
)
@FUZZ
def test_fuzz_tolerant_keeps_every_valid_record(items):
    body = b"".join((format_record(x).encode() if ok else x) + b"\n" for ok, x in items)
    valid = [x for ok, x in items if ok]
    n_bad = sum(1 for ok, _ in items if not ok)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "f.log"
        p.write_bytes(HEADER + body)
        with LogReader(p, tolerant=True) as reader:
            assert list(reader) == valid
        assert reader.skipped == n_bad
        if n_bad:
            first_bad = next(i for i, (ok, _) in enumerate(items) if not ok)
            with pytest.raises(LogFormatError, match=rf"^{re.escape(str(p))}:{4 + first_bad}: "):
                read_log(p)
        else:
            assert read_log(p)[1] == valid


# ---------------------------------------------------------------------------------------------
# Nothing half-written, nothing reordered silently (issue 16)


@pytest.mark.parametrize("name", ["run.log", "run.log.gz"])
def test_writer_is_atomic(tmp_path, name):
    """A log appears at its path only when complete; a failed write leaves the old file (or
    none) and no temporary file behind."""
    path = tmp_path / name
    with LogWriter(path, CFG, "w") as w:
        w.write(OdometryEvent(0.0, 1, 1))
        assert not path.exists()  # still being written
    old = path.read_bytes()
    with pytest.raises(ValueError, match="n_beams"):
        with LogWriter(path, CFG, "w") as w:
            w.write(OdometryEvent(0.0, 2, 2))
            w.write(LaserScan(0.1, np.zeros(3)))
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]
    w = LogWriter(tmp_path / "b.log", CFG, "w")
    w.abort()
    assert list(tmp_path.iterdir()) == [path]


def test_reader_counts_stamps_going_backwards(tmp_path):
    recs = ["O 1.0 0 0", "O 2.0 0 0", "O 1.5 0 0", "T 0.5 0 0 0", "T 0.4 0 0 0", "O 2.5 0 0"]
    with LogReader(log_text(tmp_path, recs)) as r:
        evs = list(r)
        assert [e.t for e in evs] == [1.0, 2.0, 1.5, 0.5, 0.4, 2.5]  # passed on as they are
        assert dict(r.backwards) == {"odometry": 1, "truth": 1}
        assert r.summary()["timestamps_backwards"] == {"odometry": 1, "truth": 1}


def test_absurd_stamp_is_skipped_and_counted_in_tolerant_mode(tmp_path):
    with LogReader(log_text(tmp_path, ["O 1 0 0", "L 1e308 361", "O 2 0 0"]), tolerant=True) as r:
        assert [e.t for e in r] == [1.0, 2.0]
        assert r.skipped_by_reason == {"absurd timestamp": 1}
    with pytest.raises(ValueError, match="plausible"):
        format_record(OdometryEvent(1e308, 0, 0))
