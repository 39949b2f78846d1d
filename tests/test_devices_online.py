"""The simulator's run through the emulators, over ptys, into the drivers and back out as
fgslam events; raw recording and replay (identical logs, the same events as live); faults;
``fgslam replay``. Accelerated 4x; every wait generous, assertions on content."""

from __future__ import annotations

import shutil
from collections import defaultdict

import numpy as np
import pytest
from devices_helpers import wait_until

from devices.odometry import OdometryFrame
from devices.pty_emulator import Faults
from devices.sick import LaserFrame, encode_b0, parse_b0
from devices.sonar import SonarFrame
from fgslam.cli import main
from fgslam.config import load_config
from fgslam.errors import UserError
from fgslam.events import LaserScan, OdometryEvent, SonarReading
from fgslam.io.logfile import read_log
from fgslam.online.ports import DevicePorts, replay, replay_to_log, start_emulators, to_event
from fgslam.sim.world import load_world

CFG = load_config()
SPEED = 4.0


def by_source(events) -> dict:
    out = defaultdict(list)
    for e in events:
        key = ("sonar", e.array) if isinstance(e, SonarReading) else type(e).__name__
        out[key].append(e)
    return dict(out)


def run_emulated(raw_dir, duration=2.5, faults=None, **ports_kw):
    """Emulate ``duration`` s of the corridor run; drivers record into ``raw_dir``."""
    emu = start_emulators(
        CFG,
        load_world("corridor"),
        seed=3,
        speed=SPEED,
        duration=duration,
        faults=faults,
        keep_sent=True,
    )
    try:
        ports = DevicePorts.for_emulation(
            CFG,
            emu,
            record_dir=raw_dir,
            world="corridor",
            meta={"seed": 3},
            **ports_kw,
        )
        with ports:
            assert emu.wait(60), "the emulated run did not finish"
            assert emu.playback.error is None
            got: list = []
            n_sent = len(emu.sent)

            def settled() -> bool:  # everything arrived, or nothing more for a while
                while (ev := ports.get(0.3)) is not None:
                    got.append(ev)
                    if len(got) >= n_sent:
                        return True
                return True

            wait_until(settled)
            status = ports.status()
            assert not ports.errors()
        return emu, got, status
    finally:
        emu.stop()


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    raw = tmp_path_factory.mktemp("online") / "raw"
    emu, got, status = run_emulated(raw)
    return raw, emu, got, status


def test_emulated_run_arrives_intact(clean_run):
    _, emu, got, status = clean_run
    sent, live = by_source(emu.sent), by_source(got)
    assert {k: len(v) for k, v in live.items()} == {k: len(v) for k, v in sent.items()}
    for name, s in status.items():
        assert s["crc_errors"] == s.get("dropped_frames", 0) == s["rejected"] == 0, name
        assert s["opens"] == 1 and s["disconnects"] == 0, name
    # odometry: exact ticks; device time mapped to log time, in order
    odo_s, odo_l = sent["OdometryEvent"], live["OdometryEvent"]
    assert [(e.ticks_right, e.ticks_left) for e in odo_l] == [
        (e.ticks_right, e.ticks_left) for e in odo_s
    ]
    assert np.all(np.diff([e.t for e in odo_l]) >= 0)
    t0 = emu.start_time
    # the device-time filter settles at the least latency seen: most samples are mapped
    # within that of their true time (the first ones carry the first reads' latency)
    err = np.array([a.t - t0 - b.t for a, b in zip(odo_l, odo_s, strict=True)])
    assert np.median(np.abs(err)) < 1.0
    # laser: ranges exact (5 cm quanta in cm), stamped at the first byte: never before it
    # left (how much later is the host's read latency: its load, not asserted here; the
    # stamping arithmetic is tested on chunks in test_devices_sick.py)
    for a, b in zip(live["LaserScan"], sent["LaserScan"], strict=True):
        np.testing.assert_array_equal(a.ranges, b.ranges)
        assert a.t - t0 - b.t > -1e-3
    # sonar: quantised to 1 mm and 1e-4 rad
    for i in range(len(CFG.sonar.arrays)):
        for a, b in zip(live[("sonar", i)], sent[("sonar", i)], strict=True):
            assert a.array == i and abs(a.pan - b.pan) <= 5e-5 + 1e-12
            assert [e.kind for e in a.echoes] == [e.kind for e in b.echoes]
            for ea, eb in zip(a.echoes, b.echoes, strict=True):
                assert abs(ea.range - eb.range) <= 5e-4 + 1e-12
                assert abs(ea.bearing - eb.bearing) <= 5e-5 + 1e-12
    assert len(emu.truth) > 0 and emu.truth[0].t >= t0


def test_replay_gives_the_live_events_and_identical_logs(clean_run, tmp_path):
    raw, _, got, _ = clean_run
    replayed = list(replay(raw))
    assert by_source(replayed) == by_source(got)  # same events, same stamps, per source
    a, b = tmp_path / "a.log.gz", tmp_path / "b.log.gz"
    res = replay_to_log(raw, a)
    replay_to_log(raw, b)
    assert a.read_bytes() == b.read_bytes()
    header, events = read_log(a)
    assert events == replayed and header.world == "corridor" and header.meta["seed"] == 3
    assert header.config == CFG and res.events == len(events)
    assert set(res.files) == {"laser", "sonar0", "sonar1", "odometry"}
    assert not any(f["truncated"] for f in res.files.values())


def test_cli_replay(clean_run, tmp_path, capsys):
    raw = clean_run[0]
    out = tmp_path / "r.log"
    assert main(["replay", str(raw), "--out", str(out)]) == 0
    assert "events" in capsys.readouterr().out
    assert read_log(out)[1] == list(replay(raw))
    # a crash cut the last record of one file: the rest is still decoded
    cut = tmp_path / "cut"
    shutil.copytree(raw, cut)
    data = (cut / "odometry.raw").read_bytes()
    (cut / "odometry.raw").write_bytes(data[:-7])
    assert main(["replay", str(cut), "--out", str(tmp_path / "c.log")]) == 0
    assert "truncated" in capsys.readouterr().out
    n_cut = len(read_log(tmp_path / "c.log")[1])
    assert len(read_log(out)[1]) - 2 <= n_cut <= len(read_log(out)[1])


@pytest.mark.parametrize(
    "argv, msg",
    [
        (["replay", "nowhere", "--out", "x.log"], "not a directory"),
        (["replay", ".", "--out", "x.log"], "no raw recordings"),
    ],
)
def test_cli_replay_bad_input_is_one_line(one_line_error, argv, msg):
    one_line_error(argv, msg)


def test_faults_and_disconnect_lose_nothing_received(tmp_path):
    faults = {
        "laser": Faults(seed=1, noise=0.3, drop=0.1),
        "sonar0": Faults(seed=2, noise=0.3, flip=0.1),
        "odometry": Faults(seed=3, disconnects=((1.0, 0.3),)),
    }
    raw = tmp_path / "raw"
    emu, got, status = run_emulated(raw, faults=faults, reopen_interval=0.05)
    sent, live = by_source(emu.sent), by_source(got)
    assert status["odometry"]["disconnects"] >= 1 and status["odometry"]["opens"] >= 2
    assert status["sonar0"]["crc_errors"] > 0 and status["laser"]["discarded"] > 0
    assert status["sonar0"]["dropped_frames"] > 0
    assert 0 < len(live["OdometryEvent"]) < len(sent["OdometryEvent"])  # lost while unplugged
    assert len(live[("sonar", 1)]) == len(sent[("sonar", 1)])  # no faults there

    def subsequence(small, big, same) -> bool:
        it = iter(big)
        return all(any(same(a, b) for b in it) for a in small)

    ticks = lambda a, b: (a.ticks_right, a.ticks_left) == (b.ticks_right, b.ticks_left)
    assert subsequence(live["OdometryEvent"], sent["OdometryEvent"], ticks)
    ranges = lambda a, b: np.array_equal(a.ranges, b.ranges, equal_nan=True)
    assert subsequence(live["LaserScan"], sent["LaserScan"], ranges)
    # everything the drivers decoded live is in the recording
    assert by_source(replay(raw)) == live


def test_to_event_rejects_what_the_front_end_cannot_use():
    mv = parse_b0(encode_b0([100] * CFG.laser.n_beams))
    r = mv.ranges()
    r[0] = CFG.laser.max_range + 1.0
    ev = to_event(LaserFrame(1.0, 1.2, r, mv), CFG)
    assert isinstance(ev, LaserScan) and np.isnan(ev.ranges[0]) and ev.ranges[1] == 1.0
    bad = parse_b0(encode_b0([100] * CFG.laser.n_beams, status=0x03))
    assert to_event(LaserFrame(1.0, 1.2, bad.ranges(), bad), CFG) is None
    short = parse_b0(encode_b0([100] * 10))
    assert to_event(LaserFrame(1.0, 1.2, short.ranges(), short), CFG) is None
    assert to_event(SonarFrame(1.0, 1.0, 0, 0, 5, 0.0, ()), CFG) is None
    assert to_event(OdometryFrame(1.0, 1.0, 0, 0, 3, 4, 0x01), CFG) is None
    assert to_event(OdometryFrame(1.0, 1.0, 0, 0, 3, 4, 0), CFG) == OdometryEvent(1.0, 3, 4)


def test_device_ports_bad_arguments():
    with pytest.raises(UserError, match="no device port"):
        DevicePorts(CFG)
    with pytest.raises(UserError, match="sonar ports"):
        DevicePorts(CFG, sonar=["a", "b", "c"])
    with pytest.raises(UserError, match="baud"):
        DevicePorts(CFG, laser="x", laser_baud=1234)
