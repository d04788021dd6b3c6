"""A record of float64 values in shared memory that neither side ever waits on.

The service and the perception process share a few small records (the telemetry pose
history, the latest SLAM pose, the simulated vehicle's pose). A lock around them would let a
process killed while holding it (SIGKILL, the OOM killer, a segfault in a native library)
block the other side for good, and with it the setpoint stream. So a record has one writer
at a time and is read optimistically, as a seqlock: the writer makes a sequence number odd,
writes, stores a CRC of the payload and makes the number even again; a reader copies the
record and keeps the copy only if the number was even and unchanged around the copy and the
CRC matches (the CRC also catches a torn copy on CPUs that reorder stores). A reader that
cannot get a whole copy within ``READ_TIMEOUT_S`` (a writer preempted or killed mid-write)
gets None and tries again next time; a later writer starts from whatever state it finds.
"""

from __future__ import annotations

import multiprocessing as mp
import time
import zlib
from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: How long a reader retries before giving up on one read.
READ_TIMEOUT_S = 0.005

_SEQ, _CRC, _HEAD = 0, 1, 2


def _crc(payload: NDArray[np.float64]) -> float:
    return float(zlib.crc32(payload.tobytes()))


class SharedRecord:
    """``size`` float64 values in shared memory (all 0.0 at first); one writer at a time.

    Picklable into a ``spawn``ed child while it starts, like ``multiprocessing.Array``.
    """

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"a shared record needs at least one value (got {size})")
        self.size = size
        self._raw = mp.get_context("spawn").RawArray("d", _HEAD + size)
        self._view = np.frombuffer(self._raw, dtype=np.float64)
        self._view[_CRC] = _crc(self._view[_HEAD:])

    def __getstate__(self) -> dict[str, Any]:
        return {"size": self.size, "_raw": self._raw}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.size = state["size"]
        self._raw = state["_raw"]
        self._view = np.frombuffer(self._raw, dtype=np.float64)

    def write(self, values: ArrayLike, start: int = 0) -> None:
        """Write ``values`` at ``start`` (the rest of the record stays as it is)."""
        self.write_segments(((start, values),))

    def write_segments(self, segments: Iterable[tuple[int, ArrayLike]]) -> None:
        """Write each ``(start, values)`` as one update: a reader sees all of them or none."""
        parts = [(start, np.asarray(values, dtype=np.float64).reshape(-1)) for start, values in segments]
        for start, vals in parts:
            if start < 0 or start + len(vals) > self.size:
                raise ValueError(f"{len(vals)} values at {start} do not fit a shared record of {self.size}")
        v = self._view
        seq = v[_SEQ]
        # Odd while writing; a writer killed mid-write left it odd already, and it stays so.
        odd = seq if seq % 2 == 1 else seq + 1
        v[_SEQ] = odd
        for start, vals in parts:
            v[_HEAD + start:_HEAD + start + len(vals)] = vals
        v[_CRC] = _crc(v[_HEAD:])
        v[_SEQ] = odd + 1

    def writer_view(self) -> NDArray[np.float64]:
        """The payload as the writer sees it (read-only; only the writer may read it this way)."""
        out = self._view[_HEAD:]
        out.flags.writeable = False
        return out

    def read(self, timeout_s: float = READ_TIMEOUT_S) -> NDArray[np.float64] | None:
        """A whole copy of the payload, or None when none could be taken within ``timeout_s``."""
        v = self._view
        deadline = time.monotonic() + timeout_s
        while True:
            seq = v[_SEQ]
            if seq % 2 == 0:
                copy = v.copy()
                if copy[_SEQ] == seq and v[_SEQ] == seq and _crc(copy[_HEAD:]) == copy[_CRC]:
                    return copy[_HEAD:]
            if time.monotonic() >= deadline:
                return None
            time.sleep(0)
