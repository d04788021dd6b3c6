"""The shared records between the service and the perception process never block either side."""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
import time
from typing import Any

import numpy as np
import pytest

from companion.service.localization import SharedLocalization
from companion.shared_record import SharedRecord
from companion.sim.sim_world import SharedSimState
from companion.sources.poses import SharedPoseHistory

CTX = mp.get_context("spawn")


def _pose(x_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x_m
    return T


def _within(fn: Any, timeout_s: float) -> Any:
    """``fn()`` in a thread; fails the test if it does not return within ``timeout_s``."""
    out: list[Any] = []
    t = threading.Thread(target=lambda: out.append(fn()), daemon=True)
    t.start()
    t.join(timeout_s)
    assert not t.is_alive(), f"blocked for more than {timeout_s} s"
    return out[0]


# --- children (module level: spawn imports them) ----------------------------------------

def _write_uniform_forever(rec: SharedRecord, started: Any) -> None:
    k = 0
    while True:
        k += 1
        rec.write(np.full(rec.size, float(k)))
        started.value = 1


def _read_poses_forever(history: SharedPoseHistory, started: Any) -> None:
    while True:
        history.pose_at(0.5, max_gap_s=10.0)
        started.value = 1


def _publish_localization_forever(shared: SharedLocalization, started: Any) -> None:
    k = 0
    while True:
        k += 1
        shared.publish({"x_m": float(k), "stamp_s": float(k)})
        started.value = 1


def _read_sim_poses_forever(state: SharedSimState, started: Any) -> None:
    while True:
        state.poses()
        started.value = 1


def _run_then_kill(target: Any, arg: Any, busy_s: float = 0.05) -> None:
    """Start ``target(arg, started)`` in a spawned child, let it work, SIGKILL it."""
    started = CTX.Value("b", 0, lock=False)
    proc = CTX.Process(target=target, args=(arg, started), daemon=True)
    proc.start()
    deadline = time.monotonic() + 60.0
    while not started.value and time.monotonic() < deadline:
        time.sleep(0.01)
    assert started.value, "the child never started working"
    time.sleep(busy_s)
    os.kill(proc.pid, signal.SIGKILL)
    proc.join(10.0)


# --- the record itself ------------------------------------------------------------------

def test_a_record_reads_back_what_was_written() -> None:
    rec = SharedRecord(4)
    assert np.array_equal(rec.read(), np.zeros(4))
    rec.write([1.0, 2.0], start=1)
    rec.write_segments(((0, [5.0]), (3, [7.0])))
    assert rec.read().tolist() == [5.0, 1.0, 2.0, 7.0]


def test_a_write_that_does_not_fit_names_the_sizes() -> None:
    rec = SharedRecord(3)
    with pytest.raises(ValueError, match="2 values at 2 do not fit a shared record of 3"):
        rec.write([1.0, 2.0], start=2)


def test_a_reader_never_gets_a_torn_record() -> None:
    rec = SharedRecord(2048)
    started = CTX.Value("b", 0, lock=False)
    proc = CTX.Process(target=_write_uniform_forever, args=(rec, started), daemon=True)
    proc.start()
    try:
        while not started.value:
            time.sleep(0.01)
        whole = 0
        for _ in range(3000):
            r = rec.read()
            if r is not None:
                assert np.all(r == r[0]), "a copy mixed two writes"
                whole += 1
        assert whole > 0
    finally:
        proc.kill()
        proc.join(10.0)


def test_a_writer_killed_mid_write_leaves_readers_and_the_next_writer_free() -> None:
    rec = SharedRecord(16)
    rec.write(np.full(16, 3.0))
    rec._view[0] += 1  # noqa: SLF001 - the sequence number a writer killed mid-write leaves odd
    t0 = time.monotonic()
    assert rec.read() is None
    assert time.monotonic() - t0 < 0.5
    rec.write(np.full(16, 4.0))
    assert rec.read().tolist() == [4.0] * 16


# --- the records the service shares with the perception process -------------------------

def test_perception_killed_while_reading_telemetry_poses_never_blocks_the_service() -> None:
    history = SharedPoseHistory(capacity=256)
    for i in range(256):
        history.push(i * 0.01, _pose(i * 0.01))
    stamp = [2.56]
    for _ in range(3):
        _run_then_kill(_read_poses_forever, history)

        def push() -> bool:
            stamp[0] += 0.01
            return history.push(stamp[0], _pose(stamp[0]))

        assert _within(push, 2.0)
    assert history.latest_stamp_s() == pytest.approx(stamp[0])


def test_perception_killed_while_publishing_its_slam_pose_never_blocks_the_service() -> None:
    shared = SharedLocalization()
    for _ in range(3):
        _run_then_kill(_publish_localization_forever, shared)
        latest = _within(shared.latest, 2.0)
        assert latest is None or latest.seq > 0
    # The next perception process publishes as before.
    shared.publish({"x_m": 1.5})
    state = shared.latest()
    assert state is not None and state.T_map_body[0, 3] == pytest.approx(1.5)


def test_perception_killed_while_reading_the_sim_pose_never_blocks_the_world() -> None:
    state = SharedSimState()
    state.set_pose(1.0, _pose(0.0))
    for k in range(3):
        _run_then_kill(_read_sim_poses_forever, state)
        _within(lambda k=k: state.set_pose(2.0 + k, _pose(float(k))), 2.0)
    poses = state.poses()
    assert poses is not None and poses.T_map_body[0, 3] == pytest.approx(2.0)
