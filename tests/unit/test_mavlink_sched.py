"""The scheduler-slice request for the event-loop thread."""

from __future__ import annotations

import re
import sys
import threading
from pathlib import Path

import pytest

from companion.config import LinkConfig
from companion.errors import ConfigError
from companion.mavlink.sched import request_short_slice


def test_slice_range_is_checked() -> None:
    with pytest.raises(ValueError, match="0.1..100 ms"):
        request_short_slice(0.00001)
    with pytest.raises(ValueError, match="0.1..100 ms"):
        request_short_slice(1.0)


def test_config_allows_off_or_the_kernel_range() -> None:
    assert LinkConfig(scheduler_slice_ms=0.0).scheduler_slice_ms == 0.0
    from companion.config import config_from_dict

    with pytest.raises(ConfigError, match=r"link.scheduler_slice_ms: must be 0 \(off\) or 0.1..100 ms"):
        config_from_dict({"link": {"scheduler_slice_ms": 0.05}}, "drone.yaml")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sched_setattr is Linux-only")
def test_slice_applies_to_the_calling_thread_only() -> None:
    """Run in a helper thread so the test runner's own thread keeps its scheduling."""
    result: dict[str, object] = {}

    def worker() -> None:
        result["ok"] = request_short_slice(0.0005)
        sched = Path("/proc/thread-self/sched")
        result["text"] = sched.read_text() if sched.exists() else ""

    # Other tests may already have shortened this (the event-loop) thread's slice; what
    # matters is that the helper thread's request leaves it as it was.
    main_before = Path("/proc/thread-self/sched").read_text()
    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert result["ok"] is True
    m = re.search(r"^se\.slice\s*:\s*(\d+)", str(result["text"]), re.M)
    if m is None:
        pytest.skip("kernel does not report per-task slices (pre-EEVDF); request accepted")
    assert int(m.group(1)) == 500_000
    main_after = Path("/proc/thread-self/sched").read_text()
    before = re.search(r"^se\.slice\s*:\s*(\d+)", main_before, re.M)
    after = re.search(r"^se\.slice\s*:\s*(\d+)", main_after, re.M)
    assert before is not None and after is not None
    assert int(after.group(1)) == int(before.group(1))
