"""Connection URLs in the MAVSDK style, parsed into a typed endpoint.

Accepted forms (the same as MAVSDK's ``System.connect``)::

    udpin://0.0.0.0:14540        listen on a UDP port; reply to whoever sent last
    udp://:14540                 legacy MAVSDK spelling of udpin (empty host = 0.0.0.0)
    udpout://192.168.1.10:14580  send to a fixed UDP address from an ephemeral port
    tcp://127.0.0.1:5760         connect to a TCP server (reconnects when it drops)
    tcpin://0.0.0.0:5760         accept one TCP client at a time
    serial:///dev/ttyTHS1:921600 a serial device at a baud rate (default 57600)
    tlog:///runs/flight.tlog     replay a telemetry log at recorded speed (read-only link);
    tlog:///runs/f.tlog?speed=0  ... as fast as possible (?speed=4: four times faster)

Every error is a :class:`~companion.errors.LinkError` whose message repeats the bad URL.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from companion.errors import LinkError

#: MAVSDK's default baud rate when a serial URL gives none.
DEFAULT_SERIAL_BAUD = 57600


class EndpointKind(enum.Enum):
    """The transport an endpoint needs."""

    UDP_IN = "udpin"
    UDP_OUT = "udpout"
    TCP_CLIENT = "tcp"
    TCP_SERVER = "tcpin"
    SERIAL = "serial"
    REPLAY = "tlog"


_SCHEMES: dict[str, EndpointKind] = {
    "udpin": EndpointKind.UDP_IN,
    "udp": EndpointKind.UDP_IN,
    "udpout": EndpointKind.UDP_OUT,
    "tcp": EndpointKind.TCP_CLIENT,
    "tcpin": EndpointKind.TCP_SERVER,
    "serial": EndpointKind.SERIAL,
    "tlog": EndpointKind.REPLAY,
}


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection URL.

    Network kinds fill ``host``/``port``; ``SERIAL`` fills ``device``/``baud``; ``REPLAY``
    fills ``device`` (the log file) and ``speed`` (0 = as fast as possible).
    """

    kind: EndpointKind
    url: str
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0
    speed: float = 1.0

    @property
    def is_network(self) -> bool:
        return self.kind not in (EndpointKind.SERIAL, EndpointKind.REPLAY)

    def __str__(self) -> str:
        return self.url


def _port(text: str, url: str, *, listening: bool) -> int:
    if not text.isdigit():
        raise LinkError(f"connection URL {url!r}: port must be a number (got {text!r})")
    port = int(text)
    # Port 0 on a listening endpoint asks the OS for a free port (tests, tools).
    lowest = 0 if listening else 1
    if not lowest <= port <= 65535:
        raise LinkError(f"connection URL {url!r}: port must be {lowest}..65535 (got {port})")
    return port


def parse_url(url: str) -> Endpoint:
    """Parse a MAVSDK-style connection URL; raises :class:`LinkError` naming the URL."""
    if not isinstance(url, str) or "://" not in url:
        raise LinkError(
            f"connection URL {url!r}: expected scheme://address, e.g. udpin://0.0.0.0:14540"
        )
    scheme, rest = url.split("://", 1)
    kind = _SCHEMES.get(scheme.lower())
    if kind is None:
        allowed = ", ".join(f"{s}://" for s in _SCHEMES)
        raise LinkError(f"connection URL {url!r}: unknown scheme {scheme!r} (allowed: {allowed})")
    if kind is EndpointKind.SERIAL:
        return _parse_serial(rest, url)
    if kind is EndpointKind.REPLAY:
        return _parse_replay(rest, url)
    if rest.startswith("["):  # IPv6 literal: [::1]:14540
        host, sep, port_text = rest[1:].partition("]:")
        if not sep:
            raise LinkError(f"connection URL {url!r}: IPv6 address needs the form [addr]:port")
    else:
        host, sep, port_text = rest.rpartition(":")
        if not sep:
            raise LinkError(f"connection URL {url!r}: missing ':port'")
    if "/" in port_text:
        raise LinkError(f"connection URL {url!r}: unexpected path after the port")
    listening = kind in (EndpointKind.UDP_IN, EndpointKind.TCP_SERVER)
    port = _port(port_text, url, listening=listening)
    if not host:
        if not listening:
            raise LinkError(f"connection URL {url!r}: {scheme}:// needs a host to connect to")
        host = "0.0.0.0"
    return Endpoint(kind=kind, url=url, host=host, port=port)


def _parse_serial(rest: str, url: str) -> Endpoint:
    if not rest:
        raise LinkError(f"connection URL {url!r}: serial:// needs a device, e.g. serial:///dev/ttyUSB0:57600")
    device, sep, baud_text = rest.rpartition(":")
    if not sep or not device:
        device, baud = rest, DEFAULT_SERIAL_BAUD
    else:
        if not baud_text.isdigit() or int(baud_text) <= 0:
            raise LinkError(f"connection URL {url!r}: baud rate must be a positive number (got {baud_text!r})")
        baud = int(baud_text)
    if not device.startswith("/") and not device.upper().startswith("COM"):
        raise LinkError(f"connection URL {url!r}: serial device must be an absolute path (got {device!r})")
    return Endpoint(kind=EndpointKind.SERIAL, url=url, device=device, baud=baud)


def _parse_replay(rest: str, url: str) -> Endpoint:
    path, _, query = rest.partition("?")
    if not path.startswith("/"):
        raise LinkError(f"connection URL {url!r}: tlog:// needs an absolute file path, e.g. tlog:///runs/flight.tlog")
    speed = 1.0
    if query:
        key, _, value = query.partition("=")
        try:
            speed = float(value)
        except ValueError:
            speed = -1.0
        if key != "speed" or not speed >= 0.0:
            raise LinkError(f"connection URL {url!r}: the only option is ?speed=N with N >= 0 (got {query!r})")
    return Endpoint(kind=EndpointKind.REPLAY, url=url, device=path, speed=speed)
