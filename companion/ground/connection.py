"""The MQTT broker connection: credentials, TLS, the client, and what a failure means.

Everything here names the config key at fault (``mqtt.password_file``, ``mqtt.tls_ca_file``,
``mqtt.username``) so that a refused or unreadable credential is fixed from the message alone.
"""

from __future__ import annotations

import logging
import socket
import ssl
from pathlib import Path

import aiomqtt
from aiomqtt.exceptions import MqttConnectError

from companion.config import MqttConfig
from companion.errors import GroundLinkError
from companion.ground.messages import encode, online_message

#: CONNACK codes that mean the credentials were refused (MQTT 3.1.1: 4 and 5).
_AUTH_REFUSED = {4, 5, 134, 135}


def read_password_file(path: str | Path) -> str:
    """The first line of ``mqtt.password_file`` (trailing whitespace removed)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise GroundLinkError(f"mqtt.password_file: cannot read {p}: {exc.strerror or exc}") from exc
    lines = text.splitlines()
    password = lines[0].rstrip() if lines else ""
    if not password:
        raise GroundLinkError(f"mqtt.password_file: {p} is empty")
    return password


def make_tls_context(cfg: MqttConfig) -> ssl.SSLContext | None:
    """The TLS context for ``cfg`` (None when TLS is off). The broker's name is verified."""
    if not cfg.use_tls:
        return None
    try:
        ctx = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=cfg.tls_ca_file)
    except (OSError, ssl.SSLError) as exc:
        raise GroundLinkError(f"mqtt.tls_ca_file: cannot load {cfg.tls_ca_file}: {exc}") from exc
    if cfg.tls_cert_file is not None and cfg.tls_key_file is not None:
        try:
            ctx.load_cert_chain(cfg.tls_cert_file, cfg.tls_key_file)
        except (OSError, ssl.SSLError) as exc:
            raise GroundLinkError(
                f"mqtt.tls_cert_file/tls_key_file: cannot load {cfg.tls_cert_file}, "
                f"{cfg.tls_key_file}: {exc}"
            ) from exc
    return ctx


def make_client(cfg: MqttConfig, *, client_id: str, password: str | None, tls: ssl.SSLContext | None,
                online_topic: str, logger: logging.Logger) -> aiomqtt.Client:
    """The broker client for ``cfg``, with the retained ``online: false`` last will on
    ``online_topic``."""
    will = aiomqtt.Will(
        online_topic, encode(online_message(cfg.vehicle_id, False)),
        qos=1, retain=True,
    )
    return aiomqtt.Client(
        cfg.host,
        cfg.port,
        username=cfg.username,
        password=password,
        logger=logger.getChild("paho"),
        identifier=client_id,
        will=will,
        # MQTT 5: only its "retain as published" shows a live-delivered retained command.
        protocol=aiomqtt.ProtocolVersion.V5,
        clean_start=True,
        keepalive=cfg.keepalive_s,
        timeout=cfg.timeout_s,
        tls_context=tls,
        max_queued_incoming_messages=1000,
        # Small messages (replies, telemetry) must not wait for Nagle's algorithm.
        socket_options=((socket.IPPROTO_TCP, socket.TCP_NODELAY, 1),),
    )


def describe_failure(cfg: MqttConfig, exc: BaseException) -> GroundLinkError:
    """The connection failure ``exc`` as a :class:`GroundLinkError` naming the broker, and
    the config keys to check when the broker refused the credentials."""
    where = f"MQTT broker {cfg.host}:{cfg.port}"
    rc = getattr(exc, "rc", None)
    code = getattr(rc, "value", rc)
    if isinstance(exc, MqttConnectError) and code in _AUTH_REFUSED:
        who = f"user {cfg.username!r}" if cfg.username else "anonymous access"
        return GroundLinkError(
            f"{where} refused {who}: {exc} (check mqtt.username and mqtt.password_file)"
        )
    text = str(exc) or type(exc).__name__
    if exc.__cause__ is not None:  # aiomqtt wraps the socket error that ended the session
        text = f"{text}: {exc.__cause__}"
    return GroundLinkError(f"{where}: {text}")
