"""Raw recordings: format, crash safety (a truncated last record), damage, and replay
through the receivers giving the same measurements as the live decode."""

from __future__ import annotations

import struct
import zlib

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from devices import frames as fr
from devices import sick
from devices.odometry import OdometryReceiver, encode_sample
from devices.raw import MAGIC, RawFormatError, RawReader, RawRecorder
from devices.replay import ReplayFile, make_receiver, replay_dir

PROPS = settings(deadline=None, max_examples=60, suppress_health_check=[HealthCheck.too_slow])


def write_sample(path):
    with RawRecorder(path, {"device": "odometry", "port": "/dev/x"}) as rec:
        rec.marker(0.0, "open", baud=115200)
        rec.sent(0.01, b"\xaaO\x00\x01\x01\x00")
        for k in range(5):
            frame = fr.build_frame(
                fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, k, encode_sample(10_000 * k, k, -k)
            )
            rec.received(0.1 * k, frame[:7])
            rec.received(0.1 * k + 0.05, frame[7:])
        rec.marker(1.0, "close", reason="test")


def test_round_trip_and_header(tmp_path):
    p = tmp_path / "odometry.raw"
    write_sample(p)
    r = RawReader(p)
    assert r.header == {"device": "odometry", "port": "/dev/x"}
    recs = list(r)
    assert [x.tag for x in recs] == ["M", "T"] + ["D"] * 10 + ["M"]
    assert recs[0].marker == {"baud": 115200, "event": "open"} and recs[2].t == 0.0
    assert not r.truncated and r.skipped_bytes == 0
    ms = list(ReplayFile(p))
    assert [(m.seq, m.ticks_right, m.ticks_left) for m in ms] == [(k, k, -k) for k in range(5)]
    assert [m.t_host for m in ms] == [0.1 * k + 0.05 for k in range(5)]


def test_truncated_last_record_is_tolerated(tmp_path):
    p = tmp_path / "odometry.raw"
    write_sample(p)
    data = p.read_bytes()
    full = list(RawReader(p))
    for cut in range(len(data) - 40, len(data)):  # inside the last records
        p.write_bytes(data[:cut])
        r = RawReader(p)
        recs = list(r)
        assert recs == full[: len(recs)] and r.truncated


def test_damaged_record_is_skipped(tmp_path):
    p = tmp_path / "odometry.raw"
    write_sample(p)
    data = bytearray(p.read_bytes())
    start = data.index(b"\n", len(MAGIC)) + 1
    data[start + 60] ^= 0xFF  # inside the second record
    p.write_bytes(bytes(data))
    r = RawReader(p)
    recs = list(r)
    assert len(recs) == 12 and r.skipped_bytes > 0 and not r.truncated


@pytest.mark.parametrize(
    "content, msg",
    [
        (b"", "not an fgslam raw"),
        (MAGIC + b"{bad\n", "bad header"),
        (MAGIC + b"[1]\n", "bad header"),
    ],
)
def test_bad_files(tmp_path, content, msg):
    p = tmp_path / "x.raw"
    p.write_bytes(content)
    with pytest.raises(RawFormatError, match=msg):
        RawReader(p)
    with pytest.raises(ValueError, match="unknown device"):
        make_receiver({"device": "toaster"})


def test_replay_dir_merges_by_read_time(tmp_path):
    with RawRecorder(tmp_path / "laser.raw", {"device": "sick-pls"}) as rec:
        rec.marker(0.0, "open", baud=9600)
        rec.marker(0.1, "baud", baud=38400)
        tel = sick.build_telegram(0x80, sick.encode_b0([100] * 361))
        rec.received(0.25, tel)
        rec.received(0.45, b"\x00garbage" + tel)
    write_sample(tmp_path / "odometry.raw")
    got = [(n, m.t_host) for n, m in replay_dir(tmp_path)]
    assert got == sorted(got, key=lambda x: x[1])
    assert [n for n, _ in got].count("laser") == 2
    (scan, _) = [m for n, m in replay_dir(tmp_path) if n == "laser"]
    assert scan.t == pytest.approx(0.25 - 732 * 11 / 38400)  # the recorded baud is used


@PROPS
@given(chunks=st.lists(st.binary(max_size=50), max_size=8), cut=st.integers(0, 10_000))
def test_reader_never_raises_on_truncation_or_garbage(tmp_path_factory, chunks, cut):
    p = tmp_path_factory.mktemp("raw") / "odometry.raw"
    with RawRecorder(p, {"device": "odometry"}) as rec:
        for k, c in enumerate(chunks):
            rec.received(float(k), c)
    data = p.read_bytes()
    head = data.index(b"\n", len(MAGIC)) + 1
    k = head + cut % (len(data) - head + 1)
    p.write_bytes(data[:k] + bytes(reversed(data[k:])))  # truncated, then garbage
    intact, end = 0, head
    for c in chunks:
        end += 17 + len(c)
        intact += end <= k
    recs = list(RawReader(p))
    assert len(recs) >= intact
    assert [r.data for r in recs[:intact]] == chunks[:intact]
    list(ReplayFile(p))


def test_record_layout_is_documented(tmp_path):
    p = tmp_path / "x.raw"
    with RawRecorder(p, {"device": "odometry"}) as rec:
        rec.received(1.5, b"ab")
    data = p.read_bytes()
    body = data[data.index(b"\n", len(MAGIC)) + 1 :]
    tag, t, n = struct.unpack_from("<cdI", body)
    assert (tag, t, n, body[13:15]) == (b"D", 1.5, 2, b"ab")
    assert struct.unpack_from("<I", body, 15)[0] == zlib.crc32(body[:15])
    assert OdometryReceiver().counters()["frames"] == 0
