"""SICK PLS telegrams: the reference file's test vectors, B0 parsing, and property tests of
the streaming decoder (random bytes, truncation, bit flips, arbitrary chunking)."""

from __future__ import annotations

import numpy as np
import pytest
from devices_helpers import chunked
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from devices import sick
from devices.sick import (
    Control,
    Telegram,
    TelegramDecoder,
    build_telegram,
    crc16,
    encode_b0,
    parse_b0,
)

PROPS = settings(deadline=None, max_examples=150, suppress_health_check=[HealthCheck.too_slow])

# gathered from the public open-source drivers of the LMS2xx/PLS family
VECTORS = {
    "request one scan": ("02 00 02 00 30 01 31 18", 0x00, "30 01"),
    "start streaming": ("02 00 02 00 20 24 34 08", 0x00, "20 24"),
    "set 38400 baud": ("02 00 02 00 20 40 50 08", 0x00, "20 40"),
    "status request": ("02 00 01 00 31 15 12", 0x00, "31"),
    "installation mode, LMS password": (
        "02 00 0A 00 20 00 53 49 43 4B 5F 4C 4D 53 BE C5",
        0x00,
        "20 00 53 49 43 4B 5F 4C 4D 53",
    ),
    "mode-switch reply": ("02 80 03 00 A0 00 10 16 0A", 0x80, "A0 00 10"),
}


def test_crc_check_values():
    assert crc16(b"123456789") == 0xA656
    assert crc16(b"") == 0x0000


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_reference_vectors_build_and_decode(name):
    wire, address, payload = VECTORS[name]
    wire_b, payload_b = bytes.fromhex(wire), bytes.fromhex(payload)
    assert build_telegram(address, payload_b) == wire_b
    assert crc16(wire_b[:-2]) == wire_b[-2] | wire_b[-1] << 8
    dec = TelegramDecoder(address)
    assert dec.feed(wire_b) == [Telegram(address, payload_b)]
    assert dec.stats.crc_errors == dec.stats.discarded == 0


def test_builders_match_vectors():
    assert sick.mode_payload(sick.MODE_STREAM) == bytes.fromhex("20 24")
    assert sick.baud_payload(38400) == bytes.fromhex("20 40")
    lms = sick.mode_payload(sick.MODE_INSTALLATION, sick.LMS_PASSWORD)
    assert build_telegram(0, lms) == bytes.fromhex(VECTORS["installation mode, LMS password"][0])
    with pytest.raises(ValueError):
        sick.baud_payload(57600)
    with pytest.raises(ValueError):
        build_telegram(0, b"")
    with pytest.raises(ValueError):
        build_telegram(0, bytes(813))


def test_reply_with_leading_ack():
    dec = TelegramDecoder(sick.DEVICE_ADDRESS, controls=True)
    out = dec.feed(bytes.fromhex("06 02 80 03 00 A0 00 10 16 0A"))
    assert out == [Control(sick.ACK), Telegram(0x80, bytes.fromhex("A0 00 10"))]
    assert out[1].command == sick.REPLY_MODE and out[1].data == b"\x00\x10"
    # a NAK, and without controls the lone byte is discarded instead
    assert dec.feed(b"\x15") == [Control(sick.NAK)]
    plain = TelegramDecoder()
    assert plain.feed(b"\x06") == [] and plain.stats.discarded == 1


def test_361_value_b0_frame():
    payload = encode_b0(np.full(361, 250))
    wire = build_telegram(sick.DEVICE_ADDRESS, payload)
    assert wire.startswith(bytes.fromhex("02 80 D6 02 B0 69 01"))
    assert len(wire) == 732  # LEN 726
    mv = parse_b0(payload)
    assert mv.divisor == 100 and not mv.partial and mv.status == 0x10 and mv.severity == 0
    np.testing.assert_array_equal(mv.ranges(), np.full(361, 2.5))


def test_b0_units_flags_specials_status():
    d = [0, 1, 8182, 8183, 8187, 8189, 8190, 8191, 1234]
    flags = [0, 1, 2, 3, 4, 5, 6, 7, 7]
    payload = encode_b0(d, mm=True, status=0xE3, flags=flags)
    mv = parse_b0(payload)
    assert mv.divisor == 1000
    np.testing.assert_array_equal(mv.distances, d)  # flags do not leak into distances
    np.testing.assert_array_equal(mv.flags, flags)
    r = mv.ranges()
    assert np.isnan(r[[0, 3, 4, 5, 6, 7]]).all()  # 0 and every special value: no return
    assert r[1] == 0.001 and r[2] == 8.182 and r[8] == 1.234
    assert mv.severity == 3 and mv.restart and mv.implausible and mv.pollution
    cm = parse_b0(encode_b0([235, 3000]))
    assert cm.ranges().tolist() == [2.35, 30.0]  # exact: cm / 100
    part = parse_b0(encode_b0([1, 2], partial_index=2))
    assert part.partial and part.partial_index == 2


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\xb0",
        b"\xa0\x00\x10",  # not B0
        bytes.fromhex("b0 02 00 01 00 10"),  # 2 values announced, 1 present
        bytes.fromhex("b0 01 80 01 00 10"),  # unit code 2
    ],
)
def test_b0_malformed(payload):
    with pytest.raises(ValueError):
        parse_b0(payload)


def test_resync_after_garbage_and_false_sync():
    tel = build_telegram(0x80, bytes.fromhex("B1 41 42 10"))
    # a false "02 80" claiming 0x0100 bytes runs past the real telegram: not held hostage
    garbage = bytes.fromhex("FF 02 80 00 01 02 02 80")
    dec = TelegramDecoder()
    assert dec.feed(garbage + tel) == [Telegram(0x80, bytes.fromhex("B1 41 42 10"))]
    assert dec.stats.crc_errors >= 1 and dec.stats.discarded == len(garbage)
    assert dec.pending == 0
    # LEN above 812 is rejected at once
    dec = TelegramDecoder()
    assert dec.feed(bytes.fromhex("02 80 2D 03") + tel) == [Telegram(0x80, tel[4:-2])]


# -- property tests


payloads = st.binary(min_size=1, max_size=60)
garbage = st.binary(max_size=80)


def feed_all(dec, chunks):
    out = []
    for c in chunks:
        out += dec.feed(c)
    return out


@PROPS
@given(st.binary(max_size=600), st.lists(st.integers(0, 600), max_size=12))
def test_random_bytes_never_raise(data, cuts):
    dec = TelegramDecoder(controls=True)
    out = feed_all(dec, chunked(data, cuts))
    for item in out:
        if isinstance(item, Telegram):
            assert build_telegram(item.address, item.payload) in data
    s = dec.stats
    assert s.bytes_in == len(data)
    assert s.discarded + dec.pending + sum(
        len(i.payload) + 6 if isinstance(i, Telegram) else 1 for i in out
    ) == len(data)


@PROPS
@given(garbage, payloads, garbage, st.lists(st.integers(0, 300), max_size=10))
def test_valid_telegram_in_garbage_is_never_lost(before, payload, after, cuts):
    tel = build_telegram(0x80, payload)
    data = before + tel + after
    out = feed_all(TelegramDecoder(), chunked(data, cuts))
    assert Telegram(0x80, payload) in out


@PROPS
@given(payloads, st.integers(0, 10_000))
def test_truncated_telegram_waits_then_completes(payload, cut):
    tel = build_telegram(0x80, payload)
    k = cut % len(tel)
    dec = TelegramDecoder()
    assert dec.feed(tel[:k]) == []
    assert dec.feed(tel[k:]) == [Telegram(0x80, payload)]


@PROPS
@given(payloads, st.integers(0, 10_000), garbage)
@example(b"\xfd\x90", 18, b"\xfd\x90")  # a CRC-accepted longer frame: left out
@example(b"\xfd\x90", 3, b"\xfd\x90")
def test_bit_flip_is_caught(payload, bit, after):
    tel = bytearray(build_telegram(0x80, payload))
    i = bit % (len(tel) * 8)
    tel[i // 8] ^= 1 << (i % 8)
    good = build_telegram(0x80, b"\xb1\x10")
    # A flip in LEN makes the frame swallow what follows; the SICK CRC (weak: a shift and an
    # XOR of byte pairs) may accept that longer frame, which no decoder could tell from a
    # real one (e.g. payload fd 90, bit 18, followed by fd 90): such cases are left out.
    n = tel[2] | tel[3] << 8
    frame = (bytes(tel) + after + good)[: n + 6]
    assume(not (len(frame) == n + 6 and crc16(frame[:-2]) == frame[-2] | frame[-1] << 8))
    out = feed_all(TelegramDecoder(), [bytes(tel), after, good])
    # the damaged telegram never comes out (in any form); the next good one does
    assert Telegram(0x80, payload) not in out
    assert out[-1] == Telegram(0x80, b"\xb1\x10")
    assert all(t.payload in (b"\xb1\x10",) or build_telegram(0x80, t.payload) in after for t in out)


@PROPS
@given(st.binary(max_size=900), st.lists(st.integers(0, 900), max_size=8))
def test_receiver_never_raises(data, cuts):
    rcv = sick.SickReceiver()
    rcv.reset(38400)
    for k, c in enumerate(chunked(data, cuts)):
        for item in rcv.feed(float(k), c):
            if isinstance(item, sick.LaserFrame):
                assert item.t <= item.t_host


def test_scans_read_in_one_chunk_get_their_own_stamps():
    """A host that read late finds two scans (and a few bytes of a third) in one chunk read
    at time t: the first ended two frames' plus the tail's transmission before t, the
    second one frame plus the tail before, each stamped at its first byte."""
    from devices.sick import (
        DEVICE_ADDRESS,
        SickReceiver,
        build_telegram,
        encode_b0,
        transmission_time,
    )

    baud = 38400
    tel = build_telegram(DEVICE_ADDRESS, encode_b0(np.full(361, 250)))
    tail = tel[:7]
    rcv = SickReceiver()
    rcv.reset(baud)
    t = 100.0
    scans = [x for x in rcv.feed(t, tel + tel + tail) if hasattr(x, "ranges")]
    frame = transmission_time(len(tel), baud)
    rest = transmission_time(len(tail), baud)
    assert [s.t for s in scans] == pytest.approx([t - rest - 2 * frame, t - rest - frame])
    assert all(s.t_host == t for s in scans)
    # the same bytes one chunk each: each frame stamped by its own read
    rcv.reset(baud)
    a = [x for x in rcv.feed(50.0, tel) if hasattr(x, "ranges")]
    assert [s.t for s in a] == pytest.approx([50.0 - frame])
