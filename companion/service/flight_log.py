"""The flight log: one CSV row per tick with the vehicle's pose, mode and the setpoint flown."""

from __future__ import annotations

import asyncio
import csv
import logging
import math
import time
from pathlib import Path
from types import TracebackType
from typing import TextIO

from companion.background import end_task
from companion.mavlink.vehicle import Vehicle
from semmap.frames import ned_to_enu, yaw_ned_to_enu

log = logging.getLogger(__name__)

COLUMNS = ("t_s", "x_m", "y_m", "z_m", "yaw_deg", "vx_m_s", "vy_m_s", "armed", "mode", "offboard",
           "sp_x_m", "sp_y_m", "sp_z_m", "setpoints_sent")


def _r(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.3f}"


class FlightLog:
    """Writes ``path`` (CSV, map frame ENU) at ``rate_hz`` while open (async context manager)."""

    def __init__(self, path: str | Path, vehicle: Vehicle, rate_hz: float = 10.0) -> None:
        self.path = Path(path)
        self.vehicle = vehicle
        self.period_s = 1.0 / rate_hz
        self.rows = 0
        self._file: TextIO | None = None
        self._task: asyncio.Task[None] | None = None
        self._t0 = time.monotonic()

    async def __aenter__(self) -> FlightLog:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("w", newline="", encoding="utf-8")
        self._writer = csv.writer(self._file)
        self._writer.writerow(COLUMNS)
        self._task = asyncio.create_task(self._run(), name="flight-log")
        return self

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        task, self._task = self._task, None
        try:
            await end_task(task, "the flight log's writer")
        finally:
            if self._file is not None:
                self._file.close()
                self._file = None
        log.info("flight log: %d rows in %s", self.rows, self.path)

    def write_row(self) -> None:
        """Append the vehicle's current state (skipped before the first position)."""
        s = self.vehicle.snapshot()
        frame = s.map_frame
        if s.position_ned_m is None or frame is None or self._file is None:
            return
        x, y, z = frame.from_ned(*s.position_ned_m)
        vx, vy, _vz = ned_to_enu(*(s.velocity_ned_m_s or (math.nan, math.nan, math.nan)))
        yaw = math.degrees(yaw_ned_to_enu(s.yaw_ned_rad)) if s.yaw_ned_rad is not None else math.nan
        st = self.vehicle.offboard.status()
        sp = (math.nan,) * 3
        if st.setpoint is not None and st.state.streams:
            sp = frame.from_ned(*st.setpoint.position_ned_m)
        self._writer.writerow([
            f"{time.monotonic() - self._t0:.3f}", _r(x), _r(y), _r(z), _r(yaw), _r(vx), _r(vy), int(s.armed),
            s.flight_mode.name if s.flight_mode else "", st.state.value, _r(sp[0]), _r(sp[1]), _r(sp[2]),
            st.setpoints_sent,
        ])
        self.rows += 1

    async def _run(self) -> None:
        while True:
            self.write_row()
            await asyncio.sleep(self.period_s)
