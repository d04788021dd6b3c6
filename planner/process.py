"""One worker process and the pipe to it: the helper both worker processes share.

The planner's worker (:mod:`planner.worker`, synchronous requests) and companion's
perception process (asynchronous updates read by a thread) each run one ``spawn`` child
(no inherited threads or sockets) that talks over a pipe in typed message dataclasses. What
they share lives here: starting the child with its ends of the pipes closed in the parent
(so the parent's reads end in EOF when the child exits, however it exits), reading with a
deadline, naming how a child ended, and stopping it (asked first, killed when it does not
go). It lives in ``planner`` because ``companion`` may import ``planner``, never the reverse.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any


@dataclass(frozen=True)
class Ready:
    """A worker's first message: it is set up and serving."""


@dataclass(frozen=True)
class Stop:
    """Asks a worker that reads requests to finish and exit."""


class WorkerProcess:
    """A ``spawn`` child running ``target(conn, [stop,] *args)``, seen from the parent.

    ``duplex``: ``conn`` carries requests and replies both ways; otherwise the child only
    sends on it. ``stop_pipe``: the child also gets the reading end of a pipe that the parent
    closes to ask it to stop (:meth:`request_stop`); the parent's death closes it too.
    """

    def __init__(self, target: Callable[..., None], args: tuple[Any, ...], name: str, *,
                 duplex: bool = True, stop_pipe: bool = False) -> None:
        ctx = mp.get_context("spawn")
        self.conn: Connection
        child_conn: Connection
        if duplex:
            self.conn, child_conn = ctx.Pipe(duplex=True)
        else:
            self.conn, child_conn = ctx.Pipe(duplex=False)  # (reading end, sending end)
        self._child_ends: tuple[Connection, ...] = (child_conn,)
        self._stop: Connection | None = None
        if stop_pipe:
            stop_recv, self._stop = ctx.Pipe(duplex=False)
            self._child_ends += (stop_recv,)
        self.name = name
        self.proc = ctx.Process(target=target, args=self._child_ends + tuple(args), name=name, daemon=True)

    def start(self) -> None:
        """Start the child; the parent keeps only its own ends of the pipes."""
        self.proc.start()
        for end in self._child_ends:
            end.close()

    @property
    def pid(self) -> int | None:
        """The child's pid (None before it started)."""
        return self.proc.pid

    @property
    def exitcode(self) -> int | None:
        return self.proc.exitcode

    def is_alive(self) -> bool:
        return self.proc.is_alive()

    def killed_by_signal(self) -> bool:
        code = self.proc.exitcode
        return code is not None and code < 0

    def exit_reason(self) -> str:
        """How the child ended, for a log line or an error ("killed by signal 9")."""
        code = self.proc.exitcode
        if code is None:
            return "still running"
        return f"killed by signal {-code}" if code < 0 else f"exited with code {code}"

    def send(self, msg: object) -> None:
        self.conn.send(msg)

    def recv(self, deadline_mono_s: float) -> object:
        """The next message; :class:`TimeoutError` past the ``time.monotonic()`` deadline,
        :class:`EOFError` when the child has gone."""
        remaining = deadline_mono_s - time.monotonic()
        if remaining <= 0.0 or not self.conn.poll(remaining):
            raise TimeoutError(f"{self.name} sent nothing in time")
        return self.conn.recv()

    def request_stop(self) -> None:
        """Ask the child to stop: close the stop pipe, or send :class:`Stop`. Never blocks and
        never raises, whether the child lives or not."""
        if self._stop is not None:
            self._stop.close()
            return
        try:
            self.conn.send(Stop())
        except (OSError, ValueError):
            pass

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()

    def join(self, timeout_s: float) -> None:
        self.proc.join(timeout_s)

    def stop(self, timeout_s: float) -> None:
        """Ask the child to stop, wait ``timeout_s``, then kill it; closes the pipes."""
        self.request_stop()
        self.proc.join(timeout_s)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(1.0)
        self.close()

    def close(self) -> None:
        """Close the parent's ends of the pipes (the child's process is left as it is)."""
        self.conn.close()
        if self._stop is not None:
            self._stop.close()
