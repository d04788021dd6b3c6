"""Ask Linux for a short scheduler slice so the setpoint task wakes on time under CPU load.

Linux 6.6+ schedules normal tasks with EEVDF; since 6.12 a task may request its own time
slice through ``sched_setattr(2)`` (``sched_attr.sched_runtime`` with ``SCHED_OTHER``; see
the kernel's ``Documentation/scheduler/sched-eevdf.rst``). A short slice gives the task an
earlier virtual deadline, so when its timer fires it preempts a CPU-bound task instead of
waiting for that task's slice to end. No privilege is needed and the task's share of CPU
time is unchanged: it only runs in shorter, timelier pieces, which suits an event loop that
sleeps between 20 ms setpoint ticks.

Older kernels (CFS) accept the call and ignore the slice; other systems are told no. Call
:func:`request_short_slice` from the thread that runs the event loop (it applies to the
calling thread only).
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform
import sys

log = logging.getLogger(__name__)

#: ``__NR_sched_setattr`` per machine (asm-generic numbering on the 64-bit ARM/RISC-V ports).
_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "arm64": 274, "riscv64": 274, "armv7l": 380,
                      "i686": 351}
_SCHED_OTHER = 0
#: The kernel clamps custom slices to 0.1..100 ms.
MIN_SLICE_S = 0.0001
MAX_SLICE_S = 0.1


class _SchedAttr(ctypes.Structure):
    _fields_ = [  # the kernel's struct sched_attr, SCHED_ATTR_SIZE_VER1
        ("size", ctypes.c_uint32),
        ("sched_policy", ctypes.c_uint32),
        ("sched_flags", ctypes.c_uint64),
        ("sched_nice", ctypes.c_int32),
        ("sched_priority", ctypes.c_uint32),
        ("sched_runtime", ctypes.c_uint64),
        ("sched_deadline", ctypes.c_uint64),
        ("sched_period", ctypes.c_uint64),
        ("sched_util_min", ctypes.c_uint32),
        ("sched_util_max", ctypes.c_uint32),
    ]


def request_short_slice(slice_s: float) -> bool:
    """Request a ``slice_s`` scheduler slice for the calling thread (keeps its nice value).

    Returns True if the kernel accepted the request, False (logged) where it cannot be made:
    not Linux, an unknown machine, a real-time policy in use, or the syscall refused.
    """
    if not MIN_SLICE_S <= slice_s <= MAX_SLICE_S:
        raise ValueError(f"scheduler slice must be {MIN_SLICE_S * 1e3:.1f}..{MAX_SLICE_S * 1e3:.0f} ms "
                         f"(got {slice_s * 1e3:.3f} ms)")
    nr = _SYS_SCHED_SETATTR.get(platform.machine())
    if not sys.platform.startswith("linux") or nr is None:
        log.info("short scheduler slice not available on %s/%s", sys.platform, platform.machine())
        return False
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        log.info("thread already runs under a real-time policy; scheduler slice left alone")
        return False
    attr = _SchedAttr(
        size=ctypes.sizeof(_SchedAttr), sched_policy=_SCHED_OTHER,
        sched_nice=os.getpriority(os.PRIO_PROCESS, 0), sched_runtime=int(slice_s * 1e9),
    )
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(nr, 0, ctypes.byref(attr), 0) != 0:
        err = ctypes.get_errno()
        log.warning("sched_setattr(slice %.2f ms) refused: %s", slice_s * 1e3, os.strerror(err))
        return False
    log.info("scheduler slice of %.2f ms requested for the event-loop thread", slice_s * 1e3)
    return True
