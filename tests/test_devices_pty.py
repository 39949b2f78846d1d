"""Drivers against emulators over real pseudo-terminals: SICK login, baud change and
detection, streaming, single scans, NAK/retry, timeouts, faults, disconnect and reconnect.
Every wait is generous and every assertion is on content, not on time."""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import pytest
from devices_helpers import wait_until

from devices.clock import Clock
from devices.driver import DeviceError, DeviceRunner
from devices.emulators import OdometryEmulator, SickEmulator, SonarEmulator
from devices.odometry import OdometryBoard
from devices.pty_emulator import Faults
from devices.raw import RawRecorder
from devices.replay import ReplayFile
from devices.sick import NAK, Control, SickPLS, build_telegram
from devices.sonar import SonarArray


@pytest.fixture
def stack():
    with contextlib.ExitStack() as s:
        yield s


@pytest.fixture
def clock():
    return Clock()


def scan(k: int) -> np.ndarray:
    """Distinct content per k: cm values, with a few special ones."""
    d = (np.arange(361) * 7 + 100 * k) % 3000 + 10
    d[k % 361] = 8190
    return d


def expected(k: int) -> np.ndarray:
    r = scan(k) / 100.0
    r[scan(k) >= 8183] = np.nan
    return r


def read_n(dev, n: int, timeout: float = 20.0) -> list:
    """Read until ``n`` measurements came (or the generous timeout passed)."""
    out: list = []

    def enough() -> bool:
        out.extend(dev.read(0.05))
        return len(out) >= n

    wait_until(enough, timeout, 0)
    return out


def read_idle(dev, done) -> list:
    """Read until ``done()`` holds and a read brings nothing more."""
    out: list = []

    def idle() -> bool:
        new = dev.read(0.2)
        out.extend(new)
        return done() and not new

    wait_until(idle, 20.0, 0)
    return out


def sick_pair(stack, clock, tmp_path=None, faults=None, **kw):
    emu = SickEmulator(clock=clock, faults=faults)
    stack.callback(emu.stop)
    emu.start()
    rec = None
    if tmp_path is not None:
        rec = stack.enter_context(RawRecorder(tmp_path / "laser.raw", {"device": "sick-pls"}))
    drv = SickPLS(emu.port, clock=clock, recorder=rec, **kw)
    stack.callback(drv.close)
    return emu, drv


def test_sick_login_baud_change_streaming_and_recording(stack, clock, tmp_path):
    emu, drv = sick_pair(stack, clock, tmp_path)
    assert emu.baud == 9600 and not emu.streaming  # power-up state
    drv.open()
    assert drv.port_baud == emu.baud == 38400 and drv.known_baud == 38400
    assert emu.streaming and not emu.installation
    assert drv.link.opens == 1 and drv.link.naks == drv.link.timeouts == 0
    for k in range(4):
        emu.offer_scan(clock.now() + 0.3 * k, scan(k))
    frames = read_n(drv, 4)
    assert len(frames) == 4
    for k, f in enumerate(frames):
        np.testing.assert_array_equal(f.ranges, expected(k))
        assert f.ok and f.t < f.t_host and f.values.status == 0x10
    drv.close()
    replayed = list(ReplayFile(tmp_path / "laser.raw"))
    assert [(f.t, f.t_host) for f in replayed] == [(f.t, f.t_host) for f in frames]
    assert all(
        np.array_equal(a.ranges, b.ranges, equal_nan=True)
        for a, b in zip(replayed, frames, strict=True)
    )


def test_sick_single_scans_on_request(stack):
    clock = Clock(speed=4.0)  # 4x accelerated: a 9600-baud frame takes 0.21 s
    emu, drv = sick_pair(stack, clock, mode="request", baud=9600)
    drv.open()
    assert emu.baud == 9600 and not emu.streaming and not emu.installation  # no login needed
    stop = threading.Event()

    def feeder():
        k = 0
        while not stop.wait(0.02):
            emu.offer_scan(clock.now(), scan(k))
            k += 1

    t = threading.Thread(target=feeder, daemon=True)
    t.start()
    stack.callback(t.join)
    stack.callback(stop.set)
    got = [drv.read(0.1)[0] for _ in range(3)]
    ks = []
    for f in got:  # each is one offered scan, in order, never a repeat
        k = next(k for k in range(500) if np.array_equal(f.ranges, expected(k), equal_nan=True))
        ks.append(k)
    assert ks == sorted(set(ks))
    assert emu.stats.commands >= 3 + 2  # status probe, mode, 3 requests


def test_sick_nak_retry_and_timeouts(stack, clock):
    emu, drv = sick_pair(stack, clock, retries=2, ack_timeout=0.5)
    drv.open()
    emu.refuse_next(1)
    assert drv.status().command == 0xB1
    assert drv.link.naks == 1 and drv.link.retries == 1
    emu.ignore_next(1)
    assert drv.status().command == 0xB1
    assert drv.link.timeouts == 1 and drv.link.retries == 2
    emu.ignore_next(10)
    with pytest.raises(DeviceError, match="no reply"):
        drv.request(b"\x31", retries=1)
    assert drv.link.timeouts == 1 + 2 and drv.link.retries == 2 + 1


def test_sick_refusals(stack, clock):
    emu, drv = sick_pair(stack, clock, password=b"WRONG_PW")
    with pytest.raises(DeviceError, match="installation password"):
        drv.open()  # 9600 -> 38400 needs the login
    assert not drv.is_open and emu.baud == 9600
    drv = SickPLS(emu.port, clock=clock, baud=9600)
    stack.callback(drv.close)
    drv.open()
    with pytest.raises(DeviceError, match="refused"):
        drv.request(b"\x77")  # unknown command: ACK + 92
    with pytest.raises(DeviceError, match="refused"):
        drv.set_baud(19200)  # not in installation mode: A0 01
    # a request with a bad CRC is answered with a NAK
    bad = bytearray(build_telegram(0, b"\x31"))
    bad[-1] ^= 1
    drv._write(bytes(bad))
    got: list = []
    assert wait_until(lambda: Control(NAK) in got or bool(got.extend(drv._read_items(0.05))))


def test_sick_baud_detection_on_a_scanner_left_at_38400(stack, clock):
    emu, drv = sick_pair(stack, clock)
    drv.open()
    drv.close()
    fresh = SickPLS(emu.port, clock=clock, ack_timeout=0.5)  # knows nothing: tries 9600 first
    stack.callback(fresh.close)
    fresh.open()
    assert fresh.port_baud == 38400 and fresh.link.timeouts >= 1
    assert emu.stats.garbled >= 1  # the 9600-baud probe was noise to the scanner


def test_sick_faults_noise_and_stalls_lose_nothing(stack):
    clock = Clock(speed=4.0)
    faults = Faults(seed=5, noise=0.7, delay=0.3, delay_s=0.05)
    emu, drv = sick_pair(stack, clock, faults=faults)
    drv.open()
    for k in range(12):
        emu.offer_scan(clock.now() + 0.25 * k, scan(k))
    frames = read_n(drv, 12)
    for k, f in enumerate(frames):
        np.testing.assert_array_equal(f.ranges, expected(k))
    assert emu.stats.noise_bytes > 0 and emu.stats.stalls > 0
    assert drv.counters()["discarded"] > 0


def test_sick_reconnect_after_power_cycle(stack, clock, tmp_path):
    emu, drv = sick_pair(stack, clock, tmp_path, faults=Faults(power_cycle=True), ack_timeout=0.2)
    got: list = []
    runner = DeviceRunner(drv, got.append, reopen_interval=0.1, silence_timeout=60)
    stack.callback(runner.stop)
    runner.start()
    assert runner.connected.wait(20)
    emu.offer_scan(clock.now(), scan(0))
    assert wait_until(lambda: len(got) == 1)
    emu.disconnect(0.3)  # cable out, scanner restarts at 9600, values on request
    assert wait_until(lambda: drv.link.opens == 2 and runner.connected.is_set())
    assert drv.link.disconnects == 1 and emu.baud == 38400 and emu.streaming
    emu.offer_scan(clock.now(), scan(1))
    assert wait_until(lambda: len(got) == 2)
    np.testing.assert_array_equal(got[1].ranges, expected(1))
    runner.stop()
    assert runner.error is None
    replayed = list(ReplayFile(tmp_path / "laser.raw"))
    assert [f.t for f in replayed] == [f.t for f in got]


def framed_pair(stack, clock, emu_cls, drv_cls, faults=None, **kw):
    emu = emu_cls("dev", clock=clock, faults=faults)
    stack.callback(emu.stop)
    emu.start()
    drv = drv_cls(emu.port, clock=clock, **kw)
    stack.callback(drv.close)
    return emu, drv


def test_odometry_faults_are_counted_and_never_corrupt(stack, clock):
    faults = Faults(seed=3, noise=0.3, drop=0.1, flip=0.1)
    emu, drv = framed_pair(stack, clock, OdometryEmulator, OdometryBoard, faults)
    drv.open()
    assert drv.info.kind == 1 and drv.info.period == 0.01
    t0 = clock.now()
    for k in range(300):
        emu.offer_sample(t0 + 0.002 * k, k, -k)
    got = read_idle(drv, lambda: emu.stats.frames_sent == 300)
    assert emu.stats.frames_sent == 300
    assert all((m.ticks_right, m.ticks_left) == (m.seq, -m.seq) for m in got)  # no corruption
    c = drv.counters()
    assert c["crc_errors"] > 0 and c["discarded"] > 0 and c["dropped_frames"] > 0
    assert len(got) + c["dropped_frames"] == got[-1].seq - got[0].seq + 1
    assert [m.seq for m in got] == sorted(m.seq for m in got)


def test_sonar_noise_loses_nothing_and_device_time_is_mapped(stack, clock):
    emu, drv = framed_pair(
        stack, clock, SonarEmulator, SonarArray, Faults(seed=1, noise=0.8), array=1
    )
    drv.open()
    t0 = clock.now()
    for k in range(100):
        echoes = [("plane", 1.0 + k / 100, 0.1), ("edge", 2.0, -0.2)][: k % 3]
        emu.offer_reading(t0 + 0.004 * k, 0.01 * k, echoes, device_time=1000.0 + 0.004 * k)
    got = read_n(drv, 100)
    assert [m.seq for m in got] == list(range(100)) and drv.counters()["dropped_frames"] == 0
    assert all(m.array == 1 and m.pan == round(0.01 * k, 4) for k, m in enumerate(got))
    assert got[5].echoes[:1] == (("plane", 1.05, 0.1),)
    # device time 1000 s + k * 4 ms mapped onto the host clock: never later than the read
    assert all(m.t <= m.t_host for m in got)
    assert np.diff([m.t for m in got]).min() >= 0


def test_framed_device_checks(stack, clock):
    emu, drv = framed_pair(stack, clock, OdometryEmulator, SonarArray, reply_timeout=0.1)
    with pytest.raises(DeviceError, match="no reply"):
        drv.open()  # a sonar driver on the odometry board's port
    drv = OdometryBoard(emu.port, clock=clock, baud=57600, reply_timeout=0.1)
    stack.callback(drv.close)
    with pytest.raises(DeviceError, match="no reply"):
        drv.open()  # wrong line rate
    assert emu.stats.garbled > 0
    # a reply takes the emulator a few ms; 2 s (attentive) leave room for a loaded machine
    drv = OdometryBoard(emu.port, clock=clock, reply_timeout=2.0, retries=1)
    stack.callback(drv.close)
    emu.refuse_next(1)
    with pytest.raises(DeviceError, match="refused"):
        drv.open()
    emu.ignore_next(1)
    drv.open()  # one timeout, then the retry gets through
    assert drv.link.timeouts == 1 and drv.link.retries == 1 and emu.started


def test_disconnect_and_silence_reconnect(stack, clock, tmp_path):
    emu, drv = framed_pair(stack, clock, OdometryEmulator, OdometryBoard, reply_timeout=0.2)
    drv.recorder = stack.enter_context(RawRecorder(tmp_path / "o.raw", drv.recording_header()))
    got: list = []
    runner = DeviceRunner(drv, got.append, reopen_interval=0.05, silence_timeout=0.5)
    stack.callback(runner.stop)
    runner.start()
    stop = threading.Event()

    def feeder():
        k = 0
        while not stop.wait(0.01):
            emu.offer_sample(clock.now(), k, k)
            k += 1

    t = threading.Thread(target=feeder, daemon=True)
    t.start()
    stack.callback(t.join)
    stack.callback(stop.set)
    assert wait_until(lambda: len(got) > 20)
    emu.disconnect(0.2)  # the cable: the port errors, the link disappears, then comes back
    assert wait_until(lambda: drv.link.opens >= 2 and len(got) > 60)
    n = drv.link.opens
    emu.stall(1.0)  # the board stops answering: silence, reopen once it answers again
    assert wait_until(lambda: drv.link.opens > n and runner.connected.is_set())
    k = len(got)
    assert wait_until(lambda: len(got) > k + 20)
    stop.set()
    runner.stop()
    assert runner.error is None and drv.link.disconnects >= 2
    assert emu.stats.disconnects == 1
    # seq restarts are not gaps, frames lost while away are not counted as dropped
    assert drv.counters()["dropped_frames"] == 0
    assert all(m.ticks_right == m.ticks_left for m in got)
    assert [m.t for m in ReplayFile(tmp_path / "o.raw")] == [m.t for m in got]
