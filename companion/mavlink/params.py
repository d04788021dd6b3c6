"""Reading the autopilot's parameters (PARAM_REQUEST_READ -> PARAM_VALUE).

PX4 sends every parameter in PARAM_VALUE's ``float param_value`` field *byte-wise*
(:func:`companion.px4.decode_param_value` reads it). PX4 also sends PARAM_VALUE
unasked when a parameter changes (a ground station's PARAM_SET), so :class:`ParamWatch`
keeps listening after the first answer.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Iterable

from pymavlink.dialects.v20 import common as mavlink

from companion.errors import LinkError
from companion.mavlink.link import MavlinkLink
from companion.px4 import decode_param_value, param_id_str

log = logging.getLogger(__name__)

class ParamWatch:
    """The latest values of ``names`` on the autopilot ``target_system``/``target_component``,
    from every PARAM_VALUE it sends (answers and unasked updates). :meth:`read` asks for the
    missing ones; ``on_change(name, value)`` is called for each new value."""

    def __init__(self, link: MavlinkLink, target_system: int, target_component: int, names: Iterable[str],
                 on_change: Callable[[str, float], None] | None = None) -> None:
        self.link = link
        self.target_system = target_system
        self.target_component = target_component
        self.names = tuple(names)
        self.on_change = on_change
        self.values: dict[str, float] = {}
        self._changed = asyncio.Event()
        self._detach: Callable[[], None] | None = None

    def attach(self) -> Callable[[], None]:
        """Start listening; returns the detacher."""
        self._detach = self.link.add_listener(self._on_param, ("PARAM_VALUE",))
        return self._detach

    def _on_param(self, msg: mavlink.MAVLink_param_value_message) -> None:
        if msg.get_srcSystem() != self.target_system:
            return
        name = param_id_str(msg.param_id)
        if name not in self.names:
            return
        value = decode_param_value(msg.param_value, msg.param_type)
        if not math.isfinite(value) or self.values.get(name) == value:
            return
        self.values[name] = value
        self._changed.set()
        if self.on_change is not None:
            self.on_change(name, value)

    @property
    def complete(self) -> bool:
        return all(n in self.values for n in self.names)

    def request_missing(self) -> None:
        """Send a PARAM_REQUEST_READ for every parameter not yet known."""
        for name in self.names:
            if name not in self.values:
                try:
                    self.link.send(self.link.mav.param_request_read_encode(
                        self.target_system, self.target_component, name.encode("ascii"), -1))
                except LinkError as exc:
                    log.warning("PARAM_REQUEST_READ %s not sent: %s", name, exc)

    async def read(self, timeout_s: float = 1.0, attempts: int = 5) -> dict[str, float]:
        """Ask for every parameter not yet known, up to ``attempts`` times ``timeout_s`` apart;
        returns all values, or raises :class:`LinkError` naming the unanswered ones."""
        for _ in range(max(1, attempts)):
            if self.complete:
                break
            self.request_missing()
            deadline = asyncio.get_running_loop().time() + timeout_s
            while not self.complete:
                remaining = deadline - asyncio.get_running_loop().time()
                if remaining <= 0:
                    break
                self._changed.clear()
                try:
                    await asyncio.wait_for(self._changed.wait(), remaining)
                except TimeoutError:
                    break
        missing = [n for n in self.names if n not in self.values]
        if missing:
            raise LinkError(f"the autopilot (system {self.target_system}) did not answer PARAM_REQUEST_READ for "
                            f"{', '.join(missing)} ({attempts} tries, {timeout_s:g} s apart)")
        return dict(self.values)
