"""The ground link's close ends its session's loops, even when Python 3.11's ``wait_for`` (which
aiomqtt's publish awaits its acknowledgement with) swallows the send loop's cancellation: it
returns the publication's result when the acknowledgement has arrived by the time the
cancellation is delivered, instead of raising."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest

from companion.config import CompanionConfig
from companion.ground import MqttBridge
from companion.ground import connection as ground_connection


class _Client:
    """A broker client whose acknowledgement of a state publication arrives together with the
    publisher's cancellation (what aiomqtt's publish then does on Python 3.11)."""

    def __init__(self, online_topic: str) -> None:
        self.online_topic = online_topic
        self.waiting = asyncio.Event()
        self._incoming: asyncio.Queue[Any] = asyncio.Queue()

    async def __aenter__(self) -> _Client:
        return self

    async def __aexit__(self, *exc: object) -> None:
        return None

    async def subscribe(self, *args: object, **kwargs: object) -> list[int]:
        return [1]

    async def publish(self, topic: str, payload: object, qos: int = 0, retain: bool = False) -> None:
        if topic == self.online_topic:  # the announcement and the goodbye: acknowledged at once
            return
        self.waiting.set()
        try:
            await asyncio.sleep(3600)  # waiting for the PUBACK
        except asyncio.CancelledError:
            return  # it was read in the same loop iteration: wait_for returns, the cancellation is lost

    @property
    def messages(self) -> AsyncIterator[Any]:
        return self._messages()

    async def _messages(self) -> AsyncIterator[Any]:
        while True:
            yield await self._incoming.get()


def test_bridge_close_ends_the_send_loop_whose_cancellation_wait_for_swallowed_with_its_puback(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The send loop, its cancellation lost, waits for more to send; the session's end used to
    wait for it for good, and the service's stop with it (its perception process mapping on)."""
    bridge = MqttBridge.from_config(CompanionConfig())
    client = _Client(bridge.topics.online)
    monkeypatch.setattr(ground_connection, "make_client", lambda *a, **k: client)

    async def main() -> tuple[bool, list[str]]:
        await bridge.__aenter__()
        assert await bridge.wait_connected(5.0)
        bridge.publish_status("active", 1.0)
        await asyncio.wait_for(client.waiting.wait(), 5.0)
        closed = asyncio.create_task(bridge.__aexit__(None, None, None))
        done, _ = await asyncio.wait({closed}, timeout=8.0)
        await asyncio.sleep(0.1)
        left = [t.get_name() for t in asyncio.all_tasks() if t.get_name() in ("mqtt-send", "mqtt-receive")]
        for t in asyncio.all_tasks():
            if t is not asyncio.current_task():
                t.cancel()
        return closed in done, left

    closed_in_time, loops_left = asyncio.run(main())
    assert closed_in_time, "the bridge's close did not end"
    assert loops_left == [], f"the session's loops outlived the close: {loops_left}"
