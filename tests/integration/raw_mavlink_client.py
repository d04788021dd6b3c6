"""A minimal raw MAVLink client for the mock-autopilot tests (no MAVSDK, no link code)."""

from __future__ import annotations

import asyncio
import socket
import time
from typing import Any

from pymavlink.dialects.v20 import common as mavlink


class RawClient:
    """A minimal MAVLink endpoint: one UDP socket, a parser, a message log."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        self.mav.robust_parsing = True
        self.ap_addr: tuple[str, int] = ("127.0.0.1", 0)
        self.log: list[Any] = []
        self._since: int | None = None

    def close(self) -> None:
        self.sock.close()

    def send(self, msg: Any) -> None:
        if self._since is None:
            self._since = self.mark()  # replies may arrive before recv() is called
        self.sock.sendto(msg.pack(self.mav), self.ap_addr)
        self.mav.seq = (self.mav.seq + 1) % 256

    def send_raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.ap_addr)

    def _drain(self) -> None:
        while True:
            try:
                data = self.sock.recv(65535)
            except BlockingIOError:
                return
            parser = mavlink.MAVLink(None)  # per datagram: garbage cannot eat the next one
            parser.robust_parsing = True
            for msg in parser.parse_buffer(data) or []:
                if msg.get_type() != "BAD_DATA":
                    self.log.append(msg)

    def mark(self) -> int:
        """Index into :attr:`log` from which :meth:`recv` should look."""
        self._drain()
        return len(self.log)

    async def recv(self, mtype: str, timeout_s: float = 3.0, pred: Any = None,
                   since: int | None = None) -> Any:
        """Wait for the next ``mtype`` message matching ``pred`` (received after this call,
        or after ``since`` from :meth:`mark`, or after the last :meth:`send`)."""
        from_send, self._since = self._since, None
        if since is None:
            since = from_send
        start = self.mark() if since is None else since
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._drain()
            for msg in self.log[start:]:
                if msg.get_type() == mtype and (pred is None or pred(msg)):
                    return msg
            start = len(self.log)
            await asyncio.sleep(0.005)
        raise AssertionError(f"no {mtype} within {timeout_s} s")

    async def command(self, cmd: int, *params: float, timeout_s: float = 2.0) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        since = self.mark()
        self.send(self.mav.command_long_encode(1, 1, cmd, 0, *p))
        ack = await self.recv("COMMAND_ACK", timeout_s, lambda m: m.command == cmd, since)
        return int(ack.result)

    def count(self, mtype: str) -> int:
        self._drain()
        return sum(1 for m in self.log if m.get_type() == mtype)

    async def wait_ready(self, timeout_s: float = 10.0) -> None:
        """Wait, as a client of real PX4 must, until SYS_STATUS reports the pre-arm checks
        passing (PX4 says "Ready for takeoff!" then)."""
        await self.recv("SYS_STATUS", timeout_s, since=0, pred=lambda m: bool(
            m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK))

    def status_texts(self) -> list[str]:
        """Every STATUSTEXT received so far, chunked ones (MAVLink 2 ``id``) joined."""
        self._drain()
        texts: list[str] = []
        open_chunks: dict[int, int] = {}  # id -> index in texts
        for m in self.log:
            if m.get_type() != "STATUSTEXT":
                continue
            if m.id == 0:
                texts.append(m.text)
            elif m.id in open_chunks:
                texts[open_chunks[m.id]] += m.text
            else:
                open_chunks[m.id] = len(texts)
                texts.append(m.text)
        return texts
