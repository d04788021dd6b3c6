"""Telemetry logs (``.tlog``): record what the autopilot sent, replay it through the same link.

The format is the one QGroundControl and MAVProxy write: for each message, an 8-byte
big-endian timestamp (microseconds since the UNIX epoch) followed by the raw MAVLink 1 or 2
packet. :class:`TlogWriter` appends received packets as they arrive;
:func:`iter_tlog` reads them back, and the ``tlog://`` URL (see
:class:`~companion.mavlink.replay.ReplayTransport`) feeds a recording into a
:class:`~companion.mavlink.link.MavlinkLink` as if it came from the wire, so a recorded flight
replays through exactly the code that handled it live.
"""

from __future__ import annotations

import logging
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

from companion.errors import DataError

log = logging.getLogger(__name__)

_STAMP = struct.Struct(">Q")
_MAGIC_V1 = 0xFE
_MAGIC_V2 = 0xFD
_V1_OVERHEAD = 6 + 2  # header + checksum
_V2_OVERHEAD = 10 + 2
_V2_SIGNATURE = 13
_V2_SIGNED_FLAG = 0x01


@dataclass(frozen=True)
class TlogRecord:
    """One logged packet: receive time (UNIX seconds) and the raw bytes."""

    stamp_s: float
    packet: bytes


def packet_length(header: bytes) -> int:
    """Total length of the MAVLink packet whose first 3 bytes are ``header``; 0 if not one."""
    if len(header) < 3:
        return 0
    if header[0] == _MAGIC_V2:
        return _V2_OVERHEAD + header[1] + (_V2_SIGNATURE if header[2] & _V2_SIGNED_FLAG else 0)
    if header[0] == _MAGIC_V1:
        return _V1_OVERHEAD + header[1]
    return 0


def iter_tlog(path: str | Path) -> Iterator[TlogRecord]:
    """Yield the records of a ``.tlog`` file in order. Raises :class:`DataError` naming the
    file and byte offset when it is not a telemetry log; a truncated last record (a log cut
    off by a power loss) ends the iteration with a warning."""
    p = Path(path)
    try:
        f = p.open("rb")
    except OSError as exc:
        raise DataError(f"{p}: cannot read telemetry log: {exc.strerror or exc}") from exc
    with f:
        offset = 0
        while True:
            head = f.read(_STAMP.size + 3)
            if not head:
                return
            if len(head) < _STAMP.size + 3:
                log.warning("%s: truncated record at byte %d ignored", p, offset)
                return
            (stamp_us,) = _STAMP.unpack(head[:_STAMP.size])
            n = packet_length(head[_STAMP.size:])
            if n == 0:
                raise DataError(f"{p}: not a MAVLink telemetry log (no packet start at byte "
                                f"{offset + _STAMP.size})")
            rest = f.read(n - 3)
            if len(rest) < n - 3:
                log.warning("%s: truncated record at byte %d ignored", p, offset)
                return
            yield TlogRecord(stamp_us / 1e6, head[_STAMP.size:] + rest)
            offset += _STAMP.size + n


class TlogWriter:
    """Appends packets to a ``.tlog`` file (context manager; flushes on close).

    Writes go to a buffered file: a few hundred bytes per message, cheap enough for the
    event loop; the buffer is flushed at least every ``flush_interval_s``.
    """

    def __init__(self, path: str | Path, flush_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.flush_interval_s = flush_interval_s
        self.records = 0
        self._f: BinaryIO | None = None
        self._last_flush_s = 0.0

    def __enter__(self) -> "TlogWriter":
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._f = self.path.open("ab")
        except OSError as exc:
            raise DataError(f"{self.path}: cannot write telemetry log: {exc.strerror or exc}") from exc
        self._last_flush_s = time.monotonic()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def write(self, packet: bytes, stamp_s: float | None = None) -> None:
        """Append one packet stamped ``stamp_s`` (UNIX seconds; now if None)."""
        if self._f is None:
            raise DataError(f"{self.path}: telemetry log is not open")
        stamp = time.time() if stamp_s is None else stamp_s
        self._f.write(_STAMP.pack(int(stamp * 1e6)) + packet)
        self.records += 1
        now = time.monotonic()
        if now - self._last_flush_s >= self.flush_interval_s:
            self._f.flush()
            self._last_flush_s = now

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None
            log.info("telemetry log %s: %d records", self.path, self.records)
