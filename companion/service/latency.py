"""Recent latencies with percentiles, for status messages and reports."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field


@dataclass
class LatencyStats:
    """Recent latencies (ms) with percentiles for status messages and reports."""

    values_ms: deque[float] = field(default_factory=lambda: deque(maxlen=2000))

    def add(self, ms: float) -> None:
        self.values_ms.append(ms)

    def summary(self) -> dict[str, float | int]:
        """``{"count", "p50_ms", "p95_ms", "max_ms"}`` (empty values -> count 0 only)."""
        v = sorted(self.values_ms)
        if not v:
            return {"count": 0}

        def pct(q: float) -> float:
            return round(v[min(len(v) - 1, int(round(q * (len(v) - 1))))], 1)

        return {"count": len(v), "p50_ms": pct(0.5), "p95_ms": pct(0.95), "max_ms": round(v[-1], 1)}
