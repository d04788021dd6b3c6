"""Connection URL parsing: every MAVSDK form, and errors that name the bad URL."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.errors import LinkError
from companion.mavlink.urls import DEFAULT_SERIAL_BAUD, EndpointKind, parse_url


@pytest.mark.parametrize(
    ("url", "kind", "host", "port"),
    [
        ("udpin://0.0.0.0:14540", EndpointKind.UDP_IN, "0.0.0.0", 14540),
        ("udp://:14540", EndpointKind.UDP_IN, "0.0.0.0", 14540),
        ("udpout://192.168.1.10:14580", EndpointKind.UDP_OUT, "192.168.1.10", 14580),
        ("tcp://127.0.0.1:5760", EndpointKind.TCP_CLIENT, "127.0.0.1", 5760),
        ("tcpin://0.0.0.0:5760", EndpointKind.TCP_SERVER, "0.0.0.0", 5760),
        ("udpin://[::1]:14540", EndpointKind.UDP_IN, "::1", 14540),
        ("udpin://127.0.0.1:0", EndpointKind.UDP_IN, "127.0.0.1", 0),
        ("UDPOUT://localhost:1", EndpointKind.UDP_OUT, "localhost", 1),
    ],
)
def test_network_urls(url: str, kind: EndpointKind, host: str, port: int) -> None:
    ep = parse_url(url)
    assert (ep.kind, ep.host, ep.port, ep.is_network) == (kind, host, port, True)
    assert str(ep) == url


def test_serial_with_and_without_baud() -> None:
    ep = parse_url("serial:///dev/ttyTHS1:921600")
    assert (ep.kind, ep.device, ep.baud, ep.is_network) == (EndpointKind.SERIAL, "/dev/ttyTHS1", 921600, False)
    ep = parse_url("serial:///dev/ttyUSB0")
    assert (ep.device, ep.baud) == ("/dev/ttyUSB0", DEFAULT_SERIAL_BAUD)


def test_tlog_replay_urls() -> None:
    ep = parse_url("tlog:///runs/flight.tlog")
    assert (ep.kind, ep.device, ep.speed, ep.is_network) == (EndpointKind.REPLAY, "/runs/flight.tlog", 1.0, False)
    assert parse_url("tlog:///runs/flight.tlog?speed=0").speed == 0.0
    assert parse_url("tlog:///runs/flight.tlog?speed=2.5").speed == 2.5


@pytest.mark.parametrize(
    ("url", "fragment"),
    [
        ("0.0.0.0:14540", "expected scheme://"),
        ("udpx://0.0.0.0:14540", "unknown scheme 'udpx'"),
        ("udpin://0.0.0.0", "missing ':port'"),
        ("udpin://0.0.0.0:port", "port must be a number"),
        ("udpin://0.0.0.0:70000", "port must be 0..65535"),
        ("udpout://host:0", "port must be 1..65535"),
        ("udpout://:14540", "needs a host"),
        ("tcp://:5760", "needs a host"),
        ("udpin://0.0.0.0:14540/x", "unexpected path"),
        ("serial://", "needs a device"),
        ("serial:///dev/ttyS0:fast", "baud rate must be a positive number"),
        ("serial://ttyS0:57600", "absolute path"),
        ("udpin://[::1]14540", "IPv6"),
        ("tlog://runs/flight.tlog", "absolute file path"),
        ("tlog:///f.tlog?speed=-1", "?speed=N with N >= 0"),
        ("tlog:///f.tlog?rate=2", "the only option"),
        ("tlog:///f.tlog?speed=fast", "the only option"),
    ],
)
def test_bad_urls_name_the_url(url: str, fragment: str) -> None:
    with pytest.raises(LinkError) as info:
        parse_url(url)
    assert repr(url) in str(info.value)
    assert fragment in str(info.value)


@given(port=st.integers(1, 65535), host=st.from_regex(r"[a-z][a-z0-9.-]{0,20}", fullmatch=True))
def test_udpout_round_trip(port: int, host: str) -> None:
    ep = parse_url(f"udpout://{host}:{port}")
    assert (ep.host, ep.port) == (host, port)
