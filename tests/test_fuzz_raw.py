"""Bad raw recordings never escape: every mutated recording is either decoded or refused with
a UserError naming the file (``fgslam replay`` exits 2 with one line), never a traceback; and
the device receivers take any bytes, also frames whose CRC holds around hostile payloads.

The recording is built here with the recorder and the devices' encoders (as
tests/test_devices_raw.py does); experiments/fuzzlib.py holds the mutators of the fuzz
experiment (tests import nothing from experiments)."""

from __future__ import annotations

import json
import math
import struct
import tempfile
import zlib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from devices import frames as fr
from devices import sick
from devices.odometry import OdometryReceiver, encode_sample
from devices.raw import MAGIC, RawFormatError, RawReader, RawRecorder
from devices.replay import ReplayFile
from devices.sonar import SonarReceiver, encode_reading
from fgslam.cli import main
from fgslam.errors import UserError
from fgslam.online.ports import replay, replay_to_log

FUZZ = settings(deadline=None, max_examples=200, suppress_health_check=[HealthCheck.too_slow])
NAMES = ("laser", "sonar0", "odometry")
HOSTILE = (
    '"x"',
    "null",
    "1e400",
    "-1e400",
    "NaN",
    "Infinity",
    "-1",
    "0",
    "1.5",
    "true",
    "[]",
    "{}",
    "99999999999999999999999999",
    "1" + "0" * 5000,  # beyond Python's int digit limit
    "[" * 3000,  # nesting beyond the recursion limit
    '"toaster"',
    '"sonar"',
    '"sick-pls"',
)
_HEAD = struct.Struct("<cdI")


def write_recording(raw: Path) -> Path:
    """A small valid raw directory: laser (open at 9600, baud 38400, two scans), sonar array
    0 and odometry (framed, some frames split over two reads)."""
    raw.mkdir(parents=True, exist_ok=True)
    with RawRecorder(raw / "laser.raw", {"device": "sick-pls", "port": "/dev/a"}) as rec:
        rec.marker(0.0, "open", baud=9600, port="/dev/a")
        rec.sent(0.01, sick.build_telegram(sick.HOST_ADDRESS, bytes([sick.CMD_STATUS])))
        rec.received(0.02, bytes([sick.ACK]))
        rec.marker(0.1, "baud", baud=38400)
        for k in range(2):
            tel = sick.build_telegram(sick.DEVICE_ADDRESS, sick.encode_b0([100 + k] * 361))
            rec.received(0.3 + 0.2 * k, tel[:100])
            rec.received(0.35 + 0.2 * k, tel[100:])
        rec.marker(1.0, "close", reason="end")
    header = {"device": "sonar", "port": "/dev/b", "array": 0, "device_clock": True}
    with RawRecorder(raw / "sonar0.raw", header) as rec:
        rec.marker(0.0, "open", baud=fr.DEFAULT_BAUD)
        for k in range(4):
            echoes = [("plane", 1.0 + k, 0.1), ("corner", 2.0, -0.2)]
            payload = encode_reading(100_000 * k, 0.05 * k, echoes)
            rec.received(0.1 * k + 0.01, fr.build_frame(fr.SONAR_SYNC, fr.DATA_SONAR, k, payload))
    header = {"device": "odometry", "port": "/dev/c", "device_clock": True}
    with RawRecorder(raw / "odometry.raw", header) as rec:
        rec.marker(0.0, "open", baud=fr.DEFAULT_BAUD)
        for k in range(6):
            frame = fr.build_frame(
                fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, k, encode_sample(50_000 * k, k, -k)
            )
            rec.received(0.05 * k + 0.01, frame[:5])
            rec.received(0.05 * k + 0.02, frame[5:])
    return raw


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict[str, bytes]:
    raw = write_recording(tmp_path_factory.mktemp("valid") / "raw")
    return {name: (raw / f"{name}.raw").read_bytes() for name in NAMES}


def build_record(tag: bytes, t: float, data: bytes) -> bytes:
    head = _HEAD.pack(tag, t, len(data))
    return head + data + struct.pack("<I", zlib.crc32(data, zlib.crc32(head)))


def header_end(data: bytes) -> int:
    return data.index(b"\n", len(MAGIC)) + 1


def records(data: bytes) -> list[tuple[int, bytes, float, bytes]]:
    """(offset, tag, t, payload) of each record of a valid file."""
    out, i = [], header_end(data)
    while i < len(data):
        tag, t, n = _HEAD.unpack_from(data, i)
        out.append((i, tag, t, data[i + _HEAD.size : i + _HEAD.size + n]))
        i += _HEAD.size + n + 4
    return out


def with_field(obj: dict, key: str, value_text: str) -> bytes:
    """``obj`` as JSON with ``key``'s value the raw JSON text ``value_text``."""
    return json.dumps({**obj, key: "@@"}).replace('"@@"', value_text).encode()


def with_header_field(data: bytes, key: str, value_text: str) -> bytes:
    end = header_end(data)
    header = json.loads(data[len(MAGIC) : end])
    return MAGIC + with_field(header, key, value_text) + b"\n" + data[end:]


def with_record(data: bytes, index: int, tag: bytes, t: float, payload: bytes) -> bytes:
    """``data`` with its record ``index`` replaced by a re-signed (CRC-valid) one."""
    off, _, _, old = records(data)[index]
    end = off + _HEAD.size + len(old) + 4
    return data[:off] + build_record(tag, t, payload) + data[end:]


def markers(data: bytes) -> list[int]:
    return [k for k, r in enumerate(records(data)) if r[1] == b"M"]


def check_replay(raw: Path, mutated: Path) -> None:
    """Decoded, or refused with a UserError naming the mutated file."""
    try:
        for ev in replay(raw):
            assert math.isfinite(ev.t)
    except UserError as exc:
        assert str(mutated) in str(exc)
        assert "\n" not in str(exc)


def replay_mutant(valid: dict[str, bytes], name: str, data: bytes) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp)
        for n, d in valid.items():
            (raw / f"{n}.raw").write_bytes(data if n == name else d)
        check_replay(raw, raw / f"{name}.raw")


# ---------------------------------------------------------------------------------------------
# mutated recordings


@FUZZ
@given(
    name=st.sampled_from(NAMES),
    flips=st.lists(st.tuples(st.integers(0, 1 << 20), st.integers(1, 255)), min_size=1, max_size=8),
    cut=st.one_of(st.none(), st.integers(0, 1 << 20)),
)
def test_byte_flips_and_truncation_are_decoded_or_refused(valid, name, flips, cut):
    data = bytearray(valid[name])
    for pos, xor in flips:
        data[pos % len(data)] ^= xor
    if cut is not None:
        data = data[: cut % (len(data) + 1)]
    replay_mutant(valid, name, bytes(data))


@FUZZ
@given(
    name=st.sampled_from(NAMES),
    key=st.sampled_from(["device", "array", "device_clock", "port"]),
    value=st.sampled_from(HOSTILE),
)
def test_hostile_header_fields_are_decoded_or_refused(valid, name, key, value):
    replay_mutant(valid, name, with_header_field(valid[name], key, value))


@FUZZ
@given(
    name=st.sampled_from(NAMES),
    which=st.integers(0, 10),
    key=st.sampled_from(["baud", "baud", "event", "reason"]),
    value=st.one_of(st.sampled_from(HOSTILE), st.integers(-(10**30), 10**30).map(str)),
)
def test_hostile_marker_fields_are_decoded_or_refused(valid, name, which, key, value):
    data = valid[name]
    k = markers(data)[which % len(markers(data))]
    _, tag, t, payload = records(data)[k]
    mutated = with_record(data, k, tag, t, with_field(json.loads(payload), key, value))
    replay_mutant(valid, name, mutated)


@FUZZ
@given(
    name=st.sampled_from(NAMES),
    which=st.integers(0, 100),
    tag=st.sampled_from([None, b"D", b"T", b"M"]),
    t=st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)),
    payload=st.one_of(st.none(), st.binary(max_size=80)),
)
def test_resigned_records_are_decoded_or_refused(valid, name, which, tag, t, payload):
    """Records whose CRC holds around a hostile time, tag or content (a bad writer)."""
    data = valid[name]
    k = which % len(records(data))
    _, old_tag, old_t, old_payload = records(data)[k]
    mutated = with_record(
        data,
        k,
        old_tag if tag is None else tag,
        old_t if t is None else t,
        old_payload if payload is None else payload,
    )
    replay_mutant(valid, name, mutated)


# ---------------------------------------------------------------------------------------------
# the cases of the issue, and the CLI


def _one(tmp_path: Path, valid: dict[str, bytes], name: str, data: bytes) -> Path:
    raw = tmp_path / "raw"
    raw.mkdir()
    for n, d in valid.items():
        (raw / f"{n}.raw").write_bytes(data if n == name else d)
    return raw


@pytest.mark.parametrize("value", ['"x"', "null", "1e400", "-1", "256", "1.0", "true"])
def test_bad_sonar_array_is_refused(tmp_path, valid, value):
    data = with_header_field(valid["sonar0"], "array", value)
    raw = _one(tmp_path, valid, "sonar0", data)
    with pytest.raises(RawFormatError, match=r"sonar0\.raw, line 2 \(header\): array must be"):
        ReplayFile(raw / "sonar0.raw")
    with pytest.raises(UserError, match=r"sonar0\.raw"):
        list(replay(raw))


@pytest.mark.parametrize("value", ['"toaster"', "null", "[]", '"Sonar"'])
def test_unknown_device_kind_is_the_raw_format_error(tmp_path, valid, value):
    raw = _one(tmp_path, valid, "odometry", with_header_field(valid["odometry"], "device", value))
    with pytest.raises(RawFormatError, match=r"odometry\.raw, line 2.*unknown device kind"):
        ReplayFile(raw / "odometry.raw")
    with pytest.raises(UserError, match=r"odometry\.raw"):
        list(replay(raw))


@pytest.mark.parametrize("value", ['"false"', "0", "null"])
def test_device_clock_must_be_a_boolean(tmp_path, valid, value):
    data = with_header_field(valid["odometry"], "device_clock", value)
    raw = _one(tmp_path, valid, "odometry", data)
    with pytest.raises(RawFormatError, match="device_clock must be true or false"):
        ReplayFile(raw / "odometry.raw")


@pytest.mark.parametrize("event", ["open", "baud"])
@pytest.mark.parametrize("value", ["1e400", "-1e400", "NaN", '"x"', "null", "0", "-9600", "1e-300"])
def test_bad_baud_marker_is_refused_naming_the_record(tmp_path, valid, event, value):
    data = valid["laser"]
    k = next(k for k in markers(data) if json.loads(records(data)[k][3])["event"] == event)
    off, tag, t, payload = records(data)[k]
    data = with_record(data, k, tag, t, with_field(json.loads(payload), "baud", value))
    raw = _one(tmp_path, valid, "laser", data)
    msg = rf"laser\.raw, record at byte {off}: {event} marker's baud must be an integer"
    with pytest.raises(RawFormatError, match=msg):
        list(ReplayFile(raw / "laser.raw"))
    with pytest.raises(UserError, match=msg):
        list(replay(raw))


@pytest.mark.parametrize("t", [math.nan, math.inf, -math.inf, 1e300, -2e9])
def test_record_time_that_is_not_a_time_is_refused(tmp_path, valid, t):
    data = valid["odometry"]
    off, tag, _, payload = records(data)[3]
    raw = _one(tmp_path, valid, "odometry", with_record(data, 3, tag, t, payload))
    with pytest.raises(UserError, match=rf"odometry\.raw, record at byte {off}: time"):
        replay_to_log(raw, tmp_path / "out.log")
    assert not (tmp_path / "out.log").exists()


@pytest.mark.parametrize("payload", [b"not json", b"[1, 2]", b"[" * 3000, b'{"event": "dance"}'])
def test_marker_that_is_not_a_known_event_is_refused(tmp_path, valid, payload):
    data = valid["sonar0"]
    off, tag, t, _ = records(data)[markers(data)[0]]
    raw = _one(tmp_path, valid, "sonar0", with_record(data, markers(data)[0], tag, t, payload))
    with pytest.raises(UserError, match=rf"sonar0\.raw, record at byte {off}: marker"):
        list(replay(raw))


def test_header_nested_too_deeply_is_refused(tmp_path, valid):
    data = valid["laser"]
    raw = _one(tmp_path, valid, "laser", MAGIC + b"[" * 3000 + data[header_end(data) - 1 :])
    with pytest.raises(RawFormatError, match=r"laser\.raw, line 2: bad header"):
        RawReader(raw / "laser.raw")


def test_unreadable_raw_file_is_refused(tmp_path, valid):
    raw = _one(tmp_path, valid, "laser", valid["laser"])
    (raw / "odometry.raw").unlink()
    (raw / "odometry.raw").mkdir()  # a directory where a file is expected
    with pytest.raises(UserError, match=r"odometry\.raw: cannot read"):
        list(replay(raw))


@pytest.mark.parametrize(
    "key, value, msg",
    [
        ("world", '"a\\nb"', "world must be one line"),
        ("clock_speed", "NaN", "clock_speed must be a positive number"),
        ("clock_speed", '"x"', "clock_speed must be a positive number"),
        ("meta", '{"k": NaN}', "meta must be an object of finite values"),
        ("meta", "[1]", "meta must be an object"),
        ("config", "[1]", "expected a table"),
    ],
)
def test_bad_session_fields_are_refused(tmp_path, valid, key, value, msg):
    raw = _one(tmp_path, valid, "laser", valid["laser"])
    session = {"format": "fgslam-raw-session", "version": 1, "world": "w"}
    (raw / "session.json").write_bytes(with_field(session, key, value))
    with pytest.raises(UserError, match=msg):
        replay_to_log(raw, tmp_path / "out.log")


CLI_CASES = [
    ("sonar0", lambda d: with_header_field(d, "array", '"x"'), "array must be"),
    ("sonar0", lambda d: with_header_field(d, "array", "null"), "array must be"),
    ("sonar0", lambda d: with_header_field(d, "array", "1e400"), "array must be"),
    ("odometry", lambda d: with_header_field(d, "device", '"toaster"'), "unknown device kind"),
    (
        "laser",
        lambda d: with_record(
            d, 0, b"M", 0.0, b'{"baud": 1e400, "event": "open", "port": "/dev/a"}'
        ),
        "open marker's baud",
    ),
    ("laser", lambda d: d[: len(MAGIC) + 5], "bad header"),
    ("odometry", lambda d: with_record(d, 2, b"D", math.nan, records(d)[2][3]), "time nan"),
]


@pytest.mark.parametrize("name, mutate, msg", CLI_CASES)
def test_cli_replay_exits_2_with_one_line(tmp_path, valid, capsys, name, mutate, msg):
    raw = _one(tmp_path, valid, name, mutate(valid[name]))
    out = tmp_path / "out.log"
    assert main(["replay", str(raw), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fgslam replay: error: ")
    assert f"{name}.raw" in err and msg in err
    assert not out.exists()


def test_cli_replay_decodes_the_valid_recording(tmp_path, valid, capsys):
    raw = _one(tmp_path, valid, "laser", valid["laser"])
    assert main(["replay", str(raw), "--out", str(tmp_path / "out.log")]) == 0
    assert "2 LaserScan, 6 OdometryEvent, 4 SonarReading" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------
# the receivers under the file: any bytes, and frames whose CRC holds around any payload

FEED = settings(deadline=None, max_examples=200, suppress_health_check=[HealthCheck.too_slow])
times = st.floats(-1e9, 1e9)
bauds = st.integers(50, 20_000_000)


def framed(sync: bytes, data_type: int):
    frame = st.builds(
        lambda ftype, seq, payload: fr.build_frame(sync, ftype, seq, payload),
        st.sampled_from([data_type, data_type, 0x81, 0xFF, 0x00]),
        st.integers(0, 0xFFFF),
        st.binary(max_size=255),
    )
    return st.lists(st.one_of(frame, st.binary(max_size=40)), max_size=12)


def b0_payloads():
    raw_b0 = st.builds(
        lambda info, body: bytes([sick.REPLY_VALUES]) + struct.pack("<H", info) + body,
        st.integers(0, 0xFFFF),
        st.binary(max_size=120),
    )
    return st.one_of(raw_b0, st.binary(min_size=1, max_size=120))


def telegrams():
    tel = st.builds(lambda p: sick.build_telegram(sick.DEVICE_ADDRESS, p), b0_payloads())
    return st.lists(st.one_of(tel, st.binary(max_size=40)), max_size=10)


def feed_all(rcv, chunks, ts, baud) -> None:
    rcv.reset(baud)
    for k, chunk in enumerate(chunks):
        if k == len(chunks) // 2:
            rcv.set_baud(baud)
        for item in rcv.feed(ts[k % len(ts)], chunk):
            t = getattr(item, "t", None)
            assert t is None or math.isfinite(t)
    assert all(v >= 0 for v in rcv.counters().values())


@FEED
@given(chunks=framed(fr.SONAR_SYNC, fr.DATA_SONAR), ts=st.lists(times, min_size=1), baud=bauds)
def test_sonar_receiver_takes_any_frames(chunks, ts, baud):
    feed_all(SonarReceiver(3), chunks, ts, baud)


@FEED
@given(
    chunks=framed(fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY),
    ts=st.lists(times, min_size=1),
    baud=bauds,
    clock=st.booleans(),
)
def test_odometry_receiver_takes_any_frames(chunks, ts, baud, clock):
    feed_all(OdometryReceiver(clock), chunks, ts, baud)


@FEED
@given(chunks=telegrams(), ts=st.lists(times, min_size=1), baud=bauds)
def test_sick_receiver_takes_any_telegrams(chunks, ts, baud):
    feed_all(sick.SickReceiver(), chunks, ts, baud)
