"""Event ordering (issue 17): the merge of per-device streams by device time gives the same
order whatever the interleaving in which the devices' events reach the host; silences;
the reorder buffer; the drivers' attentive time (a host too busy to read is not a silent
device)."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import devices.driver as driver
from devices.driver import AttentiveTimer, SerialDevice
from fgslam.events import OdometryEvent
from fgslam.io.ordering import ReorderBuffer, SourceMerger, merge_sources

NAMES = ["laser", "odometry", "sonar0", "sonar1"]


def _stream(name: str, times: list[float]) -> list[OdometryEvent]:
    # the tick fields carry the source and the index, so events are told apart
    return [OdometryEvent(t, NAMES.index(name), k) for k, t in enumerate(times)]


streams_st = st.dictionaries(
    st.sampled_from(NAMES),
    st.lists(st.floats(0.0, 50.0, allow_nan=False), max_size=40),
    min_size=1,
)


@settings(max_examples=200, deadline=None)
@given(streams_st, st.randoms(use_true_random=False), st.booleans())
def test_the_merge_does_not_depend_on_the_interleaving(raw, rnd, sort_each):
    """Any interleaving of the pushes that keeps each source's own order gives the output
    of merge_sources; with sources in time order that output is in time order; a device
    clock filter's small steps back within a source keep the source's order."""
    streams = {n: _stream(n, sorted(ts) if sort_each else ts) for n, ts in raw.items()}
    expected = list(merge_sources(streams))
    assert sorted(map(id, expected)) == sorted(id(e) for s in streams.values() for e in s)
    if sort_each:
        assert [e.t for e in expected] == sorted(e.t for e in expected)
    for n, s in streams.items():  # each source's order is kept
        assert [e for e in expected if e.ticks_right == NAMES.index(n)] == s
    merger = SourceMerger(list(streams))
    pos = dict.fromkeys(streams, 0)
    out = []
    while any(pos[n] < len(s) for n, s in streams.items()):
        n = rnd.choice([n for n, s in streams.items() if pos[n] < len(s)])
        out += merger.push(n, streams[n][pos[n]])
        pos[n] += 1
    out += merger.flush()
    assert out == expected and merger.late == 0


def test_merge_waits_for_every_source_until_one_is_silent():
    m = SourceMerger(["laser", "odometry"])
    assert m.push("odometry", OdometryEvent(1.0, 0, 0)) == []  # the laser may still be earlier
    assert m.push("odometry", OdometryEvent(2.0, 0, 1)) == []
    assert m.waiting_for() == "laser"
    # odometry 1.0 and the laser's own 1.5 are due; odometry 2.0 waits for the laser's next
    assert [e.t for e in m.push("laser", OdometryEvent(1.5, 1, 0))] == [1.0, 1.5]
    assert [e.t for e in m.set_silent("laser")] == [2.0]  # the laser is gone
    late = OdometryEvent(1.8, 1, 1)  # ... and comes back with something older
    assert m.push("laser", late) == [late] and m.late == 1
    assert "laser" not in m.silent  # a source that delivers is waited for again
    assert m.push("odometry", OdometryEvent(3.0, 0, 2)) == []
    assert [e.t for e in m.push("laser", OdometryEvent(3.5, 1, 2))] == [3.0]
    assert [e.t for e in m.flush()] == [3.5]
    with pytest.raises(KeyError):
        m.push("wheel", OdometryEvent(4.0, 0, 0))
    with pytest.raises(ValueError):
        SourceMerger([])


def test_ties_go_by_source_name_then_arrival():
    evs = {
        "odometry": [OdometryEvent(1.0, 1, 0), OdometryEvent(1.0, 1, 1)],
        "laser": [OdometryEvent(1.0, 0, 0)],
    }
    got = [(e.ticks_right, e.ticks_left) for e in merge_sources(evs)]
    assert got == [(0, 0), (1, 0), (1, 1)]


def test_reorder_buffer_puts_late_events_back_within_its_window():
    buf = ReorderBuffer(1.0)
    out = []
    for t in (0.0, 0.5, 0.2, 1.3, 0.4, 3.0, 0.3):
        out += buf.push(OdometryEvent(t, 0, 0))
    out += buf.flush()
    assert [e.t for e in out] == [0.0, 0.2, 0.4, 0.5, 1.3, 3.0]  # 0.3 came after 1.3 left
    assert buf.dropped == 1 and buf.reordered == 2
    with pytest.raises(ValueError):
        ReorderBuffer(-1.0)


class _FakeClock:
    """time.monotonic for devices.driver: advances ``step`` s at every call (a host that
    runs the thread rarely)."""

    def __init__(self, step: float) -> None:
        self.t, self.step = 0.0, step

    def __call__(self) -> float:
        self.t += self.step
        return self.t


def test_attentive_timer_counts_each_wait_at_most_its_cap(monkeypatch):
    fake = _FakeClock(5.0)
    monkeypatch.setattr(driver.time, "monotonic", fake)
    timer = AttentiveTimer(cap=0.2)
    for _ in range(10):
        timer.tick()
    assert timer.elapsed == pytest.approx(2.0)  # 50 s passed, 2 s of attention
    timer.reset()
    assert timer.elapsed == 0.0


class _SilentPort:
    in_waiting = 0

    def read(self, n: int) -> bytes:
        return b""


class _NoReceiver:
    def feed(self, t, data):
        return []


def test_a_host_that_reads_rarely_does_not_make_a_device_silent(monkeypatch):
    """The driver's silence is its attentive waiting: reads that took the host 2 s each
    (it was busy) add at most the timer's cap, so 3 s of silence takes many reads."""
    fake = _FakeClock(2.0)
    monkeypatch.setattr(driver.time, "monotonic", fake)
    dev = SerialDevice("/dev/null", _NoReceiver())
    dev._ser = _SilentPort()
    reads = 0
    while dev.seconds_since_data() <= 3.0:
        assert dev.read(0.1) == []
        reads += 1
    assert reads >= 3.0 / AttentiveTimer().cap
    assert fake.t > 10 * 3.0  # the wall clock ran far beyond the silence timeout meanwhile
    dev.data_arrived()
    assert dev.seconds_since_data() == 0.0


def test_reorder_of_a_shuffled_stream_within_the_window_is_sorted():
    rng = random.Random(4)
    times = sorted(rng.uniform(0, 100) for _ in range(500))
    jittered = sorted(times, key=lambda t: t + rng.uniform(0, 0.9))
    buf = ReorderBuffer(1.0)
    out = [e.t for t in jittered for e in buf.push(OdometryEvent(t, 0, 0))]
    out += [e.t for e in buf.flush()]
    assert out == times and buf.dropped == 0
