"""The worker-process helper both worker processes use: start, typed messages, deadlines,
stopping, and naming how a child ended."""

from __future__ import annotations

import os
import signal
import time
from multiprocessing.connection import Connection

import pytest

from planner.process import Ready, Stop, WorkerProcess


def _echo(conn: Connection) -> None:
    conn.send(Ready())
    while True:
        msg = conn.recv()
        if isinstance(msg, Stop):
            return
        conn.send(msg)


def _until_stopped(conn: Connection, stop: Connection) -> None:
    conn.send(Ready())
    try:
        stop.recv()
    except EOFError:
        conn.send("stopping")


def test_typed_messages_round_trip_and_stop_ends_the_child() -> None:
    worker = WorkerProcess(_echo, (), "echo")
    worker.start()
    try:
        assert isinstance(worker.recv(time.monotonic() + 30.0), Ready)
        worker.send(Ready())
        assert worker.recv(time.monotonic() + 10.0) == Ready()
        with pytest.raises(TimeoutError):
            worker.recv(time.monotonic() + 0.05)
    finally:
        worker.stop(10.0)
    assert worker.exitcode == 0
    assert worker.exit_reason() == "exited with code 0"


def test_a_killed_child_ends_the_parents_read_and_is_named() -> None:
    worker = WorkerProcess(_echo, (), "echo")
    worker.start()
    try:
        assert isinstance(worker.recv(time.monotonic() + 30.0), Ready)
        assert worker.pid is not None
        os.kill(worker.pid, signal.SIGKILL)
        with pytest.raises(EOFError):
            worker.recv(time.monotonic() + 10.0)
        worker.join(5.0)
        assert worker.killed_by_signal()
        assert worker.exit_reason() == f"killed by signal {int(signal.SIGKILL)}"
    finally:
        worker.stop(1.0)


def test_closing_the_stop_pipe_asks_a_one_way_child_to_stop() -> None:
    worker = WorkerProcess(_until_stopped, (), "stoppable", duplex=False, stop_pipe=True)
    worker.start()
    try:
        assert isinstance(worker.recv(time.monotonic() + 30.0), Ready)
        worker.request_stop()
        assert worker.recv(time.monotonic() + 10.0) == "stopping"
        worker.join(10.0)
        assert worker.exitcode == 0
    finally:
        worker.stop(1.0)
