"""Putting events from several sources into one time order (log time, s).

Two jobs, two tools:

- :class:`SourceMerger` / :func:`merge_sources`: a k-way merge of per-device streams by
  device timestamp. Each device delivers its own events in time order, but the devices
  interleave on the host in an order that depends on its speed and load (a starved driver
  thread delivers seconds of events at once). The merge releases an event only when every
  device it waits for has delivered one at least as late, so its output is a function of
  the per-device sequences alone - the same online, under any load, as in a replay of the
  recording. Only a device declared *silent* (disconnected, or nothing for a while although
  its driver kept reading) is not waited for; what it delivers later than the merge has
  gone is passed on at once and counted as ``late``.
- :class:`ReorderBuffer`: a bounded-delay reorder of one stream (a log written in arrival
  order), used by the SLAM pipeline over logs and behind the merge.

The merge key of an event is its time, made non-decreasing per source
(``max(t, previous key)``): a device clock filter that lowers its offset may stamp an event
a little before its predecessor, and the key keeps the source's order without changing the
event. Ties: source name order, then arrival order within the source.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence

from fgslam.events import Event

# s of log time: the one reorder window of the SLAM pipeline, over logs and online. Online it
# puts back a device's first events after a silence and the steps back of a device clock
# filter that finds a smaller delay (large at the start of a fast emulation); a replayed
# recording goes through the same window, so that both give the same map.
REORDER_WINDOW = 2.0


def _keyed(events: Iterable[Event], rank: int) -> Iterator[tuple[float, int, int, Event]]:
    key = -math.inf
    for k, ev in enumerate(events):
        key = max(key, ev.t)
        yield key, rank, k, ev


def merge_sources(streams: Mapping[str, Iterable[Event]]) -> Iterator[Event]:
    """The events of per-source ``streams`` (name -> events in that source's order) in
    merge order, lazily: what :class:`SourceMerger` gives when no source is ever silent."""
    ranks = {name: i for i, name in enumerate(sorted(streams))}
    keyed = [_keyed(streams[name], ranks[name]) for name in streams]
    for _key, _rank, _k, ev in heapq.merge(*keyed):
        yield ev


class SourceMerger:
    """Incremental k-way merge of the event streams of ``sources`` (device names).

    :meth:`push` takes an event of one source in that source's order and returns the events
    now due, in merge order; :meth:`set_silent` stops or resumes waiting for a source (a
    source that delivers is waited for again); :meth:`flush` returns the rest. Without
    silences the output equals :func:`merge_sources` of the same per-source sequences,
    whatever the interleaving of the pushes.
    """

    def __init__(self, sources: Sequence[str]) -> None:
        if not sources:
            raise ValueError("a merge needs at least one source")
        self._rank = {name: i for i, name in enumerate(sorted(sources))}
        self._key = dict.fromkeys(self._rank, -math.inf)  # key of each source's last event
        self._seq = dict.fromkeys(self._rank, 0)
        self.silent: set[str] = set()
        self._heap: list[tuple[float, int, int, Event]] = []
        self.released = (-math.inf, -1)  # (key, rank) of the last event released
        self.late = 0  # events of a silent-declared source older than the merge had gone

    @property
    def sources(self) -> list[str]:
        return sorted(self._rank)

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, source: str, ev: Event) -> list[Event]:
        """Take ``ev`` of ``source``; returns the events now due."""
        rank = self._rank[source]  # KeyError: not a source of this merge
        key = max(ev.t, self._key[source])
        self._key[source] = key
        self.silent.discard(source)
        k = self._seq[source]
        self._seq[source] = k + 1
        if (key, rank) < self.released:
            self.late += 1
            return [ev]
        heapq.heappush(self._heap, (key, rank, k, ev))
        return self._release()

    def set_silent(self, source: str, silent: bool = True) -> list[Event]:
        """Stop (``silent``) or resume waiting for ``source``; returns the events now due."""
        if source not in self._rank:
            raise KeyError(source)
        if silent:
            self.silent.add(source)
        else:
            self.silent.discard(source)
        return self._release()

    def waiting_for(self) -> str | None:
        """The source the next event waits for (None: nothing held, or none to wait for)."""
        live = [(self._key[s], r, s) for s, r in self._rank.items() if s not in self.silent]
        return min(live)[2] if live and self._heap else None

    def flush(self) -> list[Event]:
        """Every event still held, in merge order (the end of the streams)."""
        return self._pop((math.inf, math.inf))

    def _release(self) -> list[Event]:
        live = [(self._key[s], r) for s, r in self._rank.items() if s not in self.silent]
        return self._pop(min(live) if live else (math.inf, math.inf))

    def _pop(self, until: tuple[float, float]) -> list[Event]:
        out = []
        heap = self._heap
        while heap and heap[0][:2] <= until:
            key, rank, _, ev = heapq.heappop(heap)
            self.released = (key, rank)
            out.append(ev)
        return out


class ReorderBuffer:
    """Puts events back into time order within a bounded delay.

    Sources interleave in a log written in arrival order: a laser scan is stamped when its
    first byte left the scanner, so it reaches the host after the sonar readings and
    odometry samples of its transmission time (0.21 s at 38400 baud, 0.84 s at 9600). An
    event is held until one ``window`` s (log time) newer has been seen, and events leave
    in order of time (ties: arrival order), so an input already in order leaves unchanged.
    An event older than one already released cannot be put back: it is dropped
    (``dropped``). ``window`` 0 releases every event at once (late events are dropped).
    """

    def __init__(self, window: float = 1.0) -> None:
        if not window >= 0:
            raise ValueError(f"reorder window must be >= 0, got {window}")
        self.window = float(window)
        self.newest = -math.inf  # latest time seen
        self.released = -math.inf  # time of the last event released
        self.dropped = 0  # events too late to put back
        self.reordered = 0  # events that came after a later one and were put back
        self._heap: list[tuple[float, int, Event]] = []
        self._n = 0

    def __len__(self) -> int:
        return len(self._heap)

    def push(self, ev: Event) -> list[Event]:
        """Take one event; returns the events now due, in time order."""
        if ev.t < self.released:
            self.dropped += 1
            return []
        if ev.t < self.newest:
            self.reordered += 1
        else:
            self.newest = ev.t
        self._n += 1
        heapq.heappush(self._heap, (ev.t, self._n, ev))
        return self._pop(self.newest - self.window)

    def flush(self) -> list[Event]:
        """Every event still held, in time order (the end of the stream)."""
        return self._pop(math.inf)

    def _pop(self, until: float) -> list[Event]:
        out = []
        heap = self._heap
        while heap and heap[0][0] <= until:
            out.append(heapq.heappop(heap)[2])
        if out:
            self.released = out[-1].t
        return out
