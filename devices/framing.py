"""The streaming frame decoder shared by every serial protocol here (SICK telegrams, the framed
sonar and odometry protocols).

A decoder accepts byte chunks of any size and returns every complete frame whose check sum
holds, in stream order. It searches for the protocol's sync bytes, reads the length from the
header, and checks the CRC; after a failure it advances one byte (never a whole length, which
would skip a real frame hidden behind a false sync). When the candidate at the head of the
buffer is still incomplete it looks ahead for a later complete, valid frame: so a false sync in
garbage whose claimed length runs past a real frame can never hold that frame hostage.
The buffer never grows beyond one maximal frame plus the last chunk.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any


@dataclass
class DecoderStats:
    """Counters of a decoder: bytes fed, valid frames, rejected candidates, discarded bytes."""

    bytes_in: int = 0
    frames: int = 0
    # candidate frames (sync + plausible header) that failed the CRC, or were abandoned
    # because a complete valid frame started inside them
    crc_errors: int = 0
    discarded: int = 0  # bytes outside every valid frame (garbage, rejected candidates)

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


class StreamDecoder:
    """Base class: ``sync`` bytes start every frame; ``header_len`` bytes (sync included) give
    the frame's total length through :meth:`_length`; :meth:`_valid` checks the CRC and
    :meth:`_item` turns the frame's bytes into the object returned by :meth:`feed`."""

    def __init__(self, sync: bytes, header_len: int) -> None:
        if len(sync) < 1 or header_len < len(sync):
            raise ValueError("bad sync or header length")
        self._sync = bytes(sync)
        self._hlen = header_len
        self._buf = bytearray()
        self.stats = DecoderStats()
        # after feed(): (index in its output, bytes of the chunk after the frame's last
        # byte) per frame, so that a frame can be stamped with the time its end arrived
        self.frame_tails: list[tuple[int, int]] = []

    # -- protocol hooks

    def _length(self, buf: bytearray, i: int) -> int:
        """Total frame length from the header at ``buf[i:]`` (``header_len`` bytes are
        available), or 0 when the header is impossible."""
        raise NotImplementedError

    def _valid(self, buf: bytearray, i: int, n: int) -> bool:
        """Whether ``buf[i:i + n]`` passes the check sum."""
        raise NotImplementedError

    def _item(self, frame: bytes) -> Any:
        return frame

    def _skip(self, buf: bytearray, a: int, b: int, out: list[Any]) -> None:
        """Bytes ``buf[a:b]`` are outside any frame (subclasses may pick out control bytes)."""
        self.stats.discarded += b - a

    # -- engine

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a possible frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (counted as discarded), e.g. after a reconnect."""
        self.stats.discarded += len(self._buf)
        self._buf.clear()

    def _probe(self, buf: bytearray, i: int) -> int:
        """> 0: a valid frame of that length at i; 0: not a frame; -1: not complete yet."""
        if len(buf) - i < self._hlen:
            return -1
        n = self._length(buf, i)
        if n <= 0:
            return 0
        if len(buf) - i < n:
            return -1
        return n if self._valid(buf, i, n) else 0

    def feed(self, data: bytes | bytearray | memoryview) -> list[Any]:
        """Add a chunk; return the frames it completed, in stream order (and set
        :attr:`frame_tails`). Never raises on any byte content."""
        buf = self._buf
        buf += data
        self.stats.bytes_in += len(data)
        out: list[Any] = []
        self.frame_tails = []
        sync = self._sync
        pos = 0
        while True:
            i = buf.find(sync, pos)
            if i < 0:
                # keep a tail that may be the beginning of the sync sequence
                end = len(buf)
                for k in range(min(len(sync) - 1, end - pos), 0, -1):
                    if buf[end - k : end] == sync[:k]:
                        end -= k
                        break
                if end > pos:
                    self._skip(buf, pos, end, out)
                pos = end
                break
            if i > pos:
                self._skip(buf, pos, i, out)
            pos = i
            n = self._probe(buf, i)
            if n > 0:
                out.append(self._item(bytes(buf[i : i + n])))
                self.frame_tails.append((len(out) - 1, len(buf) - (i + n)))
                self.stats.frames += 1
                pos = i + n
                continue
            if n == 0:
                if len(buf) - i >= self._hlen and self._length(buf, i) > 0:
                    self.stats.crc_errors += 1
                self._skip(buf, i, i + 1, out)
                pos = i + 1
                continue
            # incomplete at the head: does a complete valid frame start further on?
            j = buf.find(sync, i + 1)
            while j >= 0 and self._probe(buf, j) <= 0:
                j = buf.find(sync, j + 1)
            if j < 0:
                break  # wait for more bytes
            self.stats.crc_errors += 1  # the head candidate was not a frame
            self._skip(buf, i, j, out)
            pos = j
        del buf[:pos]
        return out
