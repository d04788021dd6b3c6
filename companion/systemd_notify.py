"""systemd integration: the ``sd_notify`` protocol and a watchdog that only pings while healthy.

The protocol is one datagram of newline-separated ``KEY=VALUE`` assignments sent to the unix
socket named by ``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace), see
``sd_notify(3)``. It is small enough to speak directly, so there is no dependency. Outside
systemd (``NOTIFY_SOCKET`` unset) every call is a cheap no-op that returns False.

::

    notifier = SystemdNotifier.from_env()
    async with Watchdog(notifier) as watchdog:          # WatchdogSec= from $WATCHDOG_USEC
        watchdog.register("perception", max_silence_s=5.0)
        notifier.ready("mapping")                        # Type=notify: start-up is done
        ...
        watchdog.alive("perception")                     # each turn of the perception loop

The watchdog task pings ``WATCHDOG=1`` at half the timeout. It runs on the event loop, so a
blocked loop stops the pings; and it skips the ping while any registered loop has been
silent longer than its ``max_silence_s``, so a hung coroutine is also restarted by systemd
(``WatchdogSec=`` with ``Restart=on-failure``).
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import time
from collections.abc import Callable, Mapping
from types import TracebackType

from companion.background import end_task


def _address(notify_socket: str) -> str | None:
    """The ``sendto`` address for ``$NOTIFY_SOCKET``; None if it is not a unix socket name."""
    if notify_socket.startswith("@"):
        return "\0" + notify_socket[1:]
    if notify_socket.startswith("/"):
        return notify_socket
    return None


def watchdog_timeout_s(environ: Mapping[str, str] | None = None) -> float | None:
    """The watchdog timeout systemd set for this process (``WatchdogSec=``), in seconds.

    None when there is none: ``$WATCHDOG_USEC`` unset or invalid, or ``$WATCHDOG_PID`` names
    another process (the variables were inherited from a parent).
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC", "")
    pid = env.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


class SystemdNotifier:
    """Sends ``sd_notify`` messages. Never raises: a failed send is logged and returns False.

    ``notify_socket``: the value of ``$NOTIFY_SOCKET`` (None: not under systemd).
    """

    def __init__(self, notify_socket: str | None, *, logger: logging.Logger | None = None) -> None:
        self._log = logger or logging.getLogger(__name__)
        self._address = _address(notify_socket) if notify_socket else None
        if notify_socket and self._address is None:
            self._log.warning("ignoring NOTIFY_SOCKET=%r: not a unix socket path or @name",
                              notify_socket)
        self._sock: socket.socket | None = None
        self._failed = False

    @classmethod
    def from_env(
        cls, environ: Mapping[str, str] | None = None, *, logger: logging.Logger | None = None
    ) -> "SystemdNotifier":
        """The notifier for ``$NOTIFY_SOCKET`` (a disabled one when unset)."""
        env = os.environ if environ is None else environ
        return cls(env.get("NOTIFY_SOCKET") or None, logger=logger)

    @property
    def enabled(self) -> bool:
        """True when running under systemd with a notification socket."""
        return self._address is not None

    def notify(self, **fields: str | int) -> bool:
        """Send one message of ``KEY=VALUE`` lines (``notify(READY=1, STATUS="...")``).

        Newlines in values are replaced by spaces (they would end the assignment). Returns
        True if the datagram was sent.
        """
        if self._address is None:
            return False
        lines = [f"{k}={str(v).replace(chr(10), ' ')}" for k, v in fields.items()]
        data = "\n".join(lines).encode("utf-8")
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(data, socket.MSG_DONTWAIT, self._address)
        except OSError as exc:
            if not self._failed:  # once: a missing socket would otherwise log every ping
                self._log.warning("sd_notify to %r failed: %s", self._printable, exc)
            self._failed = True
            return False
        if self._failed:
            self._log.info("sd_notify to %r works again", self._printable)
            self._failed = False
        return True

    @property
    def _printable(self) -> str:
        addr = self._address or ""
        return "@" + addr[1:] if addr.startswith("\0") else addr

    def ready(self, status: str | None = None) -> bool:
        """Start-up is complete (``READY=1``), optionally with a status line."""
        return self.notify(READY=1, **({"STATUS": status} if status else {}))

    def status(self, text: str) -> bool:
        """One line shown by ``systemctl status``."""
        return self.notify(STATUS=text)

    def stopping(self, status: str | None = None) -> bool:
        """The service is shutting down (``STOPPING=1``)."""
        return self.notify(STOPPING=1, **({"STATUS": status} if status else {}))

    def watchdog(self) -> bool:
        """Keep-alive ping (``WATCHDOG=1``)."""
        return self.notify(WATCHDOG=1)

    def extend_timeout(self, seconds: float) -> bool:
        """Ask for ``seconds`` more before start-up (or stop) counts as failed."""
        return self.notify(EXTEND_TIMEOUT_USEC=int(seconds * 1e6))

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class Watchdog:
    """Async context manager pinging systemd's watchdog while the service is healthy.

    ``timeout_s``: the watchdog timeout (default: from ``$WATCHDOG_USEC``; None or a
    disabled notifier means no pinging, but :meth:`register`/:meth:`alive` still work).
    Pings go out every ``timeout_s / 2``. ``clock``: monotonic seconds.
    """

    def __init__(
        self,
        notifier: SystemdNotifier,
        *,
        timeout_s: float | None = None,
        logger: logging.Logger | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.notifier = notifier
        self.timeout_s = timeout_s if timeout_s is not None else watchdog_timeout_s()
        self._log = logger or logging.getLogger(__name__)
        self._clock = clock
        self._max_silence_s: dict[str, float] = {}
        self._last_alive_s: dict[str, float] = {}
        self._task: asyncio.Task[None] | None = None
        self._unhealthy: list[str] = []
        #: Pings sent so far.
        self.pings = 0

    @property
    def interval_s(self) -> float | None:
        """Time between pings: half the timeout (None when there is no watchdog)."""
        return self.timeout_s / 2.0 if self.timeout_s else None

    def register(self, name: str, max_silence_s: float) -> None:
        """Watch a loop: it must call :meth:`alive` at least every ``max_silence_s``."""
        if max_silence_s <= 0.0:
            raise ValueError(f"max_silence_s must be > 0 (got {max_silence_s})")
        self._max_silence_s[name] = max_silence_s
        self._last_alive_s[name] = self._clock()

    def unregister(self, name: str) -> None:
        """Stop watching a loop (e.g. a stage that was shut down on purpose)."""
        self._max_silence_s.pop(name, None)
        self._last_alive_s.pop(name, None)

    def alive(self, name: str) -> None:
        """Heartbeat of the loop ``name``."""
        if name in self._max_silence_s:
            self._last_alive_s[name] = self._clock()

    def stale(self) -> list[str]:
        """Registered loops silent for longer than allowed, sorted by name."""
        now = self._clock()
        return sorted(n for n, limit in self._max_silence_s.items()
                      if now - self._last_alive_s[n] > limit)

    def check(self) -> bool:
        """One watchdog tick: ping if healthy, else report which loops are silent.

        Returns True if a ping was sent.
        """
        stale = self.stale()
        if stale:
            if stale != self._unhealthy:
                now = self._clock()
                ages = ", ".join(f"{n} silent {now - self._last_alive_s[n]:.1f} s" for n in stale)
                self._log.error("watchdog: not pinging systemd: %s", ages)
                self.notifier.status(f"unhealthy: {ages}")
            self._unhealthy = stale
            return False
        if self._unhealthy:
            self._log.warning("watchdog: all loops alive again, pinging systemd")
            self._unhealthy = []
        if self.notifier.watchdog():
            self.pings += 1
            return True
        return False

    async def _run(self, interval_s: float) -> None:
        loop = asyncio.get_running_loop()
        while True:
            due = loop.time() + interval_s
            await asyncio.sleep(interval_s)
            lag_s = loop.time() - due
            if lag_s > interval_s / 2.0:
                self._log.warning("watchdog: event loop was blocked for %.2f s", lag_s)
            self.check()

    async def __aenter__(self) -> "Watchdog":
        interval = self.interval_s
        if interval is not None and self.notifier.enabled:
            self.check()  # first ping right away: start-up may have taken a while
            self._task = asyncio.create_task(self._run(interval), name="systemd-watchdog")
            self._log.info("watchdog: pinging systemd every %.2f s (timeout %.2f s)",
                           interval, self.timeout_s)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        task, self._task = self._task, None
        await end_task(task, "the systemd watchdog's pinger")
