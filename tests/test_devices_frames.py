"""The framed sonar and odometry protocols: framing, payloads, receivers (sequence gaps,
device time), time registration of laser frames, and property tests of the decoders."""

from __future__ import annotations

import math

import pytest
from devices_helpers import chunked
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from devices import frames as fr
from devices import sick
from devices.clock import DeviceTime
from devices.frames import Frame, FrameDecoder, build_frame, crc16_ccitt
from devices.odometry import OdometryFrame, OdometryReceiver, decode_sample, encode_sample
from devices.sonar import Echo, SonarFrame, SonarReceiver, decode_reading, encode_reading

PROPS = settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])
SYNCS = [fr.SONAR_SYNC, fr.ODOMETRY_SYNC]


def test_crc_and_frame_layout():
    assert crc16_ccitt(b"123456789") == 0x29B1
    f = build_frame(fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, 0x1234, b"\x01\x02")
    assert f[:6] == bytes.fromhex("AA 4F 02 40 34 12") and len(f) == 6 + 2 + 2
    assert crc16_ccitt(f[:-2]) == int.from_bytes(f[-2:], "little")
    assert FrameDecoder(fr.ODOMETRY_SYNC).feed(f) == [Frame(fr.DATA_ODOMETRY, 0x1234, b"\x01\x02")]
    # a sonar decoder does not accept odometry frames (swapped cables are noticed)
    assert FrameDecoder(fr.SONAR_SYNC).feed(f) == []
    with pytest.raises(ValueError):
        build_frame(fr.SONAR_SYNC, 1, 0, bytes(256))


def test_sonar_payload_round_trip_and_quantisation():
    echoes = [("plane", 2.3456, -0.51234), ("corner", 0.0004, 3.14159), ("edge", 70.0, 0.0)]
    t_us, pan, got = decode_reading(encode_reading(123456789, -1.5707963, echoes))
    assert t_us == 123456789 and pan == -1.5708
    assert got == (
        Echo("plane", 2.346, -0.5123),
        Echo("corner", 0.0, 3.1416),
        Echo("edge", 65.535, 0.0),  # saturates
    )
    assert decode_reading(encode_reading(2**32 + 5, 0.0, []))[0] == 5  # wraps
    for bad in (b"", encode_reading(0, 0, echoes)[:-1], encode_reading(0, 0, [])[:-1] + b"\x01"):
        with pytest.raises(ValueError):
            decode_reading(bad)
    with pytest.raises(ValueError):
        decode_reading(encode_reading(0, 0, [])[:-1] + b"\x01" + bytes([7, 0, 0, 0, 0]))
    with pytest.raises(ValueError):
        encode_reading(0, 0, [("edge", 1.0, 0.0)] * 50)


def test_odometry_payload_round_trip_and_saturation():
    assert decode_sample(encode_sample(10_000, 21, -20)) == (10_000, 21, -20, 0)
    assert decode_sample(encode_sample(0, 40_000, -40_000)) == (0, 32767, -32768, 0x04)
    with pytest.raises(ValueError):
        decode_sample(b"\x00" * 8)


def test_info_round_trip():
    info = fr.DeviceInfo(1, fr.KIND_SONAR, 1, 0.04)
    assert fr.DeviceInfo.decode(info.encode()) == info
    with pytest.raises(ValueError):
        fr.DeviceInfo.decode(b"\x01")


def odo_frame(seq: int, t_us: int, r: int = 1, l: int = 2) -> bytes:
    return build_frame(fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, seq, encode_sample(t_us, r, l))


def test_sequence_gaps_duplicates_and_reset():
    rcv = OdometryReceiver(device_clock=False)
    rcv.reset(115200)
    data = b"".join(odo_frame(s, 10_000 * s) for s in [65534, 65535, 0, 3, 3, 4])
    out = rcv.feed(1.0, data)
    assert [m.seq for m in out] == [65534, 65535, 0, 3, 4]
    assert rcv.dropped_frames == 2 and rcv.duplicates == 1
    assert all(isinstance(m, OdometryFrame) and m.t == m.t_host == 1.0 for m in out)
    rcv.reset(115200)  # reopened: frames lost meanwhile are not gaps
    rcv.feed(2.0, odo_frame(100, 0))
    assert rcv.dropped_frames == 2
    # replies pass through; a data frame with a bad payload is counted, not raised
    reply = build_frame(fr.ODOMETRY_SYNC, fr.CMD_INFO | fr.REPLY_BIT, 7, b"x")
    bad = build_frame(fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, 101, b"short")
    assert rcv.feed(3.0, reply + bad) == [Frame(0x81, 7, b"x")] and rcv.bad_frames == 1


def test_sonar_receiver_labels_array():
    rcv = SonarReceiver(array=1)
    rcv.reset(115200)
    payload = encode_reading(40_000, 0.25, [("edge", 1.5, 0.1)])
    (m,) = rcv.feed(5.0, build_frame(fr.SONAR_SYNC, fr.DATA_SONAR, 0, payload))
    assert isinstance(m, SonarFrame) and m.array == 1 and m.pan == 0.25
    assert m.echoes == (Echo("edge", 1.5, 0.1),) and m.t_device == 40_000 and m.t == 5.0


def test_device_time_min_delay_filter():
    dt = DeviceTime(drift=1e-3)
    # device clock = host clock - 100 s; transport delays 30, 10, 50, 10 ms
    assert dt.map(0, 100.03) == pytest.approx(100.03)
    assert dt.map(1_000_000, 101.01) == pytest.approx(101.01)  # a smaller delay: snap
    assert dt.map(2_000_000, 102.05) == pytest.approx(102.01 + 1e-3)  # crept by the drift
    assert dt.map(3_000_000, 103.01) == pytest.approx(103.01)
    # wrap of the 32-bit microsecond counter
    dt2 = DeviceTime()
    dt2.map(2**32 - 500_000, 10.0)
    assert dt2.map(500_000, 11.0) == pytest.approx(11.0)
    assert dt2.restarts == 0
    # a device restart (clock jumps back) resets the filter
    dt2.map(100, 20.0)
    assert dt2.restarts == 1 and dt2.map(1_000_100, 21.0) == pytest.approx(21.0)


def test_laser_frame_time_registration():
    rcv = sick.SickReceiver()
    rcv.reset(38400)
    wire = sick.build_telegram(0x80, sick.encode_b0([100] * 361))
    (m,) = rcv.feed(10.0, wire)
    assert m.t_host == 10.0 and m.t == pytest.approx(10.0 - 732 * 11 / 38400)
    rcv.set_baud(9600)
    (m,) = rcv.feed(20.0, b"\x06" + wire)[1:]
    assert m.t == pytest.approx(20.0 - 732 * 11 / 9600) and m.ok


# -- property tests


@PROPS
@given(st.sampled_from(SYNCS), st.binary(max_size=700), st.lists(st.integers(0, 700), max_size=12))
def test_random_bytes_never_raise(sync, data, cuts):
    dec = FrameDecoder(sync)
    out = []
    for c in chunked(data, cuts):
        out += dec.feed(c)
    assert all(f.encode(sync) in data for f in out)
    assert dec.stats.discarded + dec.pending + sum(len(f.payload) + 8 for f in out) == len(data)


@PROPS
@given(
    st.sampled_from(SYNCS),
    st.binary(max_size=300),
    st.integers(0, 255),
    st.integers(0, 0xFFFF),
    st.binary(max_size=255),
    st.binary(max_size=300),
    st.lists(st.integers(0, 900), max_size=10),
)
def test_valid_frame_in_garbage_is_never_lost(sync, before, ftype, seq, payload, after, cuts):
    data = before + build_frame(sync, ftype, seq, payload) + after
    dec = FrameDecoder(sync)
    out = []
    for c in chunked(data, cuts):
        out += dec.feed(c)
    assert Frame(ftype, seq, payload) in out


@PROPS
@given(st.sampled_from(SYNCS), st.binary(max_size=255), st.integers(0, 10_000))
def test_truncated_frame_waits_then_completes(sync, payload, cut):
    f = build_frame(sync, 0x41, 9, payload)
    k = cut % len(f)
    dec = FrameDecoder(sync)
    assert dec.feed(f[:k]) == []
    assert dec.feed(f[k:]) == [Frame(0x41, 9, payload)]


@PROPS
@given(st.binary(max_size=60), st.integers(0, 10_000))
def test_bit_flip_is_caught(payload, bit):
    f = bytearray(build_frame(fr.SONAR_SYNC, 0x41, 3, payload))
    i = bit % (len(f) * 8)
    f[i // 8] ^= 1 << (i % 8)
    good = build_frame(fr.SONAR_SYNC, 0x41, 4, b"ok")
    out = FrameDecoder(fr.SONAR_SYNC).feed(bytes(f) + good)
    assert out == [Frame(0x41, 4, b"ok")]


@PROPS
@given(
    st.binary(max_size=400),
    st.binary(max_size=40),
    st.integers(0, 0xFFFF),
    st.lists(st.integers(0, 400), max_size=8),
    st.booleans(),
)
def test_receivers_never_raise(data, payload, seq, cuts, sonar):
    """Random bytes, and data frames with random payloads, in random chunks."""
    rcv = SonarReceiver(0) if sonar else OdometryReceiver()
    rcv.reset(115200)
    sync, dtype = (fr.SONAR_SYNC, fr.DATA_SONAR) if sonar else (fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY)
    data = data + build_frame(sync, dtype, seq, payload) + data
    for k, c in enumerate(chunked(data, cuts)):
        for m in rcv.feed(float(k), c):
            assert not isinstance(m, SonarFrame | OdometryFrame) or m.t <= m.t_host
    assert rcv.dropped_frames >= 0 and math.isfinite(rcv.time.drift)


DOC_EXAMPLES = [  # docs/devices.md
    (
        build_frame(fr.ODOMETRY_SYNC, fr.DATA_ODOMETRY, 7, encode_sample(1_230_000, 21, -20)),
        "AA 4F 09 40 07 00 B0 C4 12 00 15 00 EC FF 00 F9 0E",
    ),
    (
        build_frame(
            fr.SONAR_SYNC,
            fr.DATA_SONAR,
            258,
            encode_reading(40_000, 0.5, [("plane", 2.35, -0.1), ("edge", 1.2, 0.25)]),
        ),
        "AA 53 11 41 02 01 40 9C 00 00 88 13 02 00 2E 09 18 FC 02 B0 04 C4 09 37 C9",
    ),
    (build_frame(fr.SONAR_SYNC, fr.CMD_INFO, 1), "AA 53 00 01 01 00 DB 96"),
    (
        build_frame(fr.SONAR_SYNC, 0x81, 1, fr.DeviceInfo(1, fr.KIND_SONAR, 1, 0.04).encode()),
        "AA 53 07 81 01 00 01 02 01 40 9C 00 00 8C 6D",
    ),
    (build_frame(fr.ODOMETRY_SYNC, fr.CMD_START, 2), "AA 4F 00 02 02 00 A9 15"),
    (build_frame(fr.ODOMETRY_SYNC, 0x82, 2, b"\x00"), "AA 4F 01 82 02 00 00 FD 9C"),
    (build_frame(fr.ODOMETRY_SYNC, fr.TYPE_ERROR, 3, b"\x09\x01"), "AA 4F 02 FF 03 00 09 01 24 91"),
]


@pytest.mark.parametrize("frame, wire", DOC_EXAMPLES)
def test_documented_examples(frame, wire):
    assert frame == bytes.fromhex(wire)
