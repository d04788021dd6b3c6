"""Wire format of the MQTT ground link: the outbound messages and their builders.

Every payload is a JSON object with ``"schema_version": 1``
(:data:`~companion.ground.schema.SCHEMA_VERSION`); ``docs/mqtt.md`` documents each one with an
example. Positions are in the map frame (ENU: x
east, y north, z up, metres; see :mod:`semmap.frames`); times are Unix seconds (``stamp_s``).
A builder refuses a non-finite value with a :class:`ValueError` naming the field.
"""

from __future__ import annotations

import base64
import math
import time
from collections.abc import Iterable, Mapping
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from semmap.costmap import Costmap, ObjectFootprint

#: Coordinates in outbound messages are rounded to this many decimals (1 mm) so that equal
#: states compare equal and payloads stay small.
_DECIMALS = 3

Xyz = tuple[float, float, float]
Xy = tuple[float, float]


class _Message(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    schema_version: Literal[1] = 1
    vehicle_id: str
    #: Unix time the message was built, seconds.
    stamp_s: float


class StatusMessage(_Message):
    """``status``, 1 Hz: what the service is doing and how long each stage takes."""

    state: str
    uptime_s: float = Field(ge=0.0)
    #: Latest duration of each pipeline stage, e.g. {"perception": 41.2, "planner": 120.0}.
    stage_timings_ms: dict[str, float] = Field(default_factory=dict)
    #: Health of each part, e.g. {"mavlink": true, "camera": true, "map_fresh": false}.
    health: dict[str, bool] = Field(default_factory=dict)
    detail: str | None = None


class TelemetryMessage(_Message):
    """``telemetry``, 5 Hz: the vehicle's pose and state in the map frame."""

    xyz_map_m: Xyz
    velocity_map_m_s: Xyz
    #: Heading, degrees counter-clockwise from east (map frame ENU).
    yaw_deg: float
    armed: bool
    in_air: bool
    flight_mode: str
    battery_remaining_pct: float | None = Field(default=None, ge=0.0, le=100.0)


class ObjectItem(BaseModel):
    """One mapped object: its footprint polygon (legs and the space between included)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    object_id: int
    class_name: str
    #: Probability the object is real.
    existence: float = Field(ge=0.0, le=1.0)
    #: Vertical extent above the floor.
    z_min_m: float
    z_max_m: float
    #: Clearance the planner keeps from it.
    margin_m: float = Field(ge=0.0)
    polygon_xy_m: list[Xy]


class ObjectsMessage(_Message):
    """``objects``, retained, published when the list changes."""

    objects: list[ObjectItem]


class MapMessage(_Message):
    """``map``, retained, low rate: the costmap as a lossless grayscale PNG.

    Pixel values are the cost constants of :mod:`semmap.costmap` (0 free .. 252 soft cost,
    253 inscribed, 254 lethal, 255 unknown). The picture is north-up: grid cell (row r,
    col c) is pixel (height_px - 1 - r, c). ``origin_xy_m`` is the map-frame position of the
    lower-left corner of the lower-left pixel.
    """

    encoding: Literal["png"] = "png"
    content: Literal["cost"] = "cost"
    resolution_m: float = Field(gt=0.0)
    origin_xy_m: Xy
    width_px: int = Field(ge=1)
    height_px: int = Field(ge=1)
    #: The altitude band the costmap was made for.
    band_z_m: tuple[float, float]
    #: When the map was last updated (Unix seconds; 0 = unknown).
    map_stamp_s: float
    png_base64: str


class PathMessage(_Message):
    """``path``, retained: the path being flown; an empty list means none."""

    #: The goal command this path serves, when it came from the ground.
    request_id: str | None = None
    waypoints_xyz_map_m: list[Xyz]
    length_m: float = Field(ge=0.0)


class ReplyMessage(_Message):
    """``reply``: the answer to every command received."""

    request_id: str | None
    command: str
    ok: bool
    reason: str | None = None


class OnlineMessage(_Message):
    """``online``, retained: true while connected; the broker publishes false (last will)."""

    online: bool


OUTBOUND_MODELS: dict[str, type[_Message]] = {
    "status": StatusMessage,
    "telemetry": TelemetryMessage,
    "objects": ObjectsMessage,
    "map": MapMessage,
    "path": PathMessage,
    "reply": ReplyMessage,
    "online": OnlineMessage,
}


def encode(msg: BaseModel) -> bytes:
    """The JSON payload of an outbound message (UTF-8, compact)."""
    return msg.model_dump_json().encode("utf-8")


def _r(v: float) -> float:
    return round(float(v), _DECIMALS)


def _finite(name: str, values: Iterable[float]) -> None:
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite (got {v})")


def status_message(
    vehicle_id: str,
    state: str,
    uptime_s: float,
    stage_timings_ms: Mapping[str, float] | None = None,
    health: Mapping[str, bool] | None = None,
    detail: str | None = None,
    stamp_s: float | None = None,
) -> StatusMessage:
    """Build a ``status`` message; timings in milliseconds, rounded to 0.1 ms."""
    return StatusMessage(
        vehicle_id=vehicle_id,
        stamp_s=time.time() if stamp_s is None else stamp_s,
        state=state,
        uptime_s=round(uptime_s, 3),
        stage_timings_ms={k: round(float(v), 1) for k, v in (stage_timings_ms or {}).items()},
        health={k: bool(v) for k, v in (health or {}).items()},
        detail=detail,
    )


def telemetry_message(
    vehicle_id: str,
    xyz_map_m: NDArray[np.floating] | Iterable[float],
    velocity_map_m_s: NDArray[np.floating] | Iterable[float],
    yaw_rad: float,
    armed: bool,
    in_air: bool,
    flight_mode: str,
    battery_remaining_pct: float | None = None,
    stamp_s: float | None = None,
) -> TelemetryMessage:
    """Build a ``telemetry`` message from a map-frame (ENU) position (3,) and velocity (3,).

    ``yaw_rad`` is the ENU heading (counter-clockwise from east); it is sent in degrees.
    """
    p = [float(v) for v in np.asarray(xyz_map_m, dtype=np.float64).reshape(3)]
    v = [float(x) for x in np.asarray(velocity_map_m_s, dtype=np.float64).reshape(3)]
    return TelemetryMessage(
        vehicle_id=vehicle_id,
        stamp_s=time.time() if stamp_s is None else stamp_s,
        xyz_map_m=(_r(p[0]), _r(p[1]), _r(p[2])),
        velocity_map_m_s=(_r(v[0]), _r(v[1]), _r(v[2])),
        yaw_deg=round(math.degrees(yaw_rad), 2),
        armed=armed,
        in_air=in_air,
        flight_mode=flight_mode,
        battery_remaining_pct=battery_remaining_pct,
    )


def object_items(objects: Iterable[ObjectFootprint]) -> list[ObjectItem]:
    """Footprints as wire items, sorted by id, coordinates rounded to 1 mm."""
    items = []
    for ob in sorted(objects, key=lambda o: o.object_id):
        poly = np.asarray(ob.polygon_xy_m, dtype=np.float64).reshape(-1, 2)  # (M, 2)
        items.append(ObjectItem(
            object_id=int(ob.object_id),
            class_name=ob.class_name,
            existence=round(float(ob.existence), 3),
            z_min_m=_r(ob.z_min_m),
            z_max_m=_r(ob.z_max_m),
            margin_m=_r(ob.resolved_margin_m),
            polygon_xy_m=[(_r(x), _r(y)) for x, y in poly],
        ))
    return items


def objects_message(
    vehicle_id: str, objects: Iterable[ObjectFootprint], stamp_s: float | None = None
) -> ObjectsMessage:
    """Build an ``objects`` message from map-frame footprints."""
    return ObjectsMessage(
        vehicle_id=vehicle_id,
        stamp_s=time.time() if stamp_s is None else stamp_s,
        objects=object_items(objects),
    )


def encode_cost_png(cost: NDArray[np.uint8]) -> bytes:
    """(rows, cols) uint8 costs -> a north-up lossless grayscale PNG (row 0 at the bottom)."""
    grid = np.ascontiguousarray(np.flipud(np.asarray(cost, dtype=np.uint8)))
    ok, buf = cv2.imencode(".png", grid, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise ValueError(f"could not encode a {grid.shape} costmap as PNG")
    return buf.tobytes()


def decode_cost_png(png: bytes) -> NDArray[np.uint8]:
    """Inverse of :func:`encode_cost_png`: (rows, cols) uint8 with row 0 the southern row."""
    img = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ValueError("not a grayscale PNG")
    return np.ascontiguousarray(np.flipud(img))


def map_message(vehicle_id: str, costmap: Costmap, stamp_s: float | None = None) -> MapMessage:
    """Build a ``map`` message: the costmap's cost layer as a PNG picture."""
    spec = costmap.spec
    png = encode_cost_png(costmap.cost)
    return MapMessage(
        vehicle_id=vehicle_id,
        stamp_s=time.time() if stamp_s is None else stamp_s,
        resolution_m=spec.resolution_m,
        origin_xy_m=(_r(spec.origin_xy_m[0]), _r(spec.origin_xy_m[1])),
        width_px=spec.cols,
        height_px=spec.rows,
        band_z_m=(_r(costmap.band.z_min_m), _r(costmap.band.z_max_m)),
        map_stamp_s=float(costmap.stamp_s),
        png_base64=base64.b64encode(png).decode("ascii"),
    )


def path_message(
    vehicle_id: str,
    waypoints_xyz_map_m: NDArray[np.floating] | Iterable[Iterable[float]],
    request_id: str | None = None,
    stamp_s: float | None = None,
) -> PathMessage:
    """Build a ``path`` message from (N, 3) map-frame waypoints (N may be 0: no path)."""
    pts = np.asarray(waypoints_xyz_map_m, dtype=np.float64).reshape(-1, 3)  # (N, 3)
    _finite("waypoints_xyz_map_m", pts.ravel())
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
    return PathMessage(
        vehicle_id=vehicle_id,
        stamp_s=time.time() if stamp_s is None else stamp_s,
        request_id=request_id,
        waypoints_xyz_map_m=[(_r(x), _r(y), _r(z)) for x, y, z in pts],
        length_m=_r(length),
    )


def reply_message(
    vehicle_id: str,
    kind: str,
    ok: bool,
    request_id: str | None,
    reason: str | None = None,
    stamp_s: float | None = None,
) -> ReplyMessage:
    """Build a ``reply`` to a command of ``kind``; ``reason`` says why it was refused."""
    return ReplyMessage(
        vehicle_id=vehicle_id,
        stamp_s=time.time() if stamp_s is None else stamp_s,
        request_id=request_id,
        command=kind,
        ok=ok,
        reason=reason,
    )


def online_message(vehicle_id: str, online: bool, stamp_s: float | None = None) -> OnlineMessage:
    """Build an ``online`` message (also used, with ``online=False``, as the last will)."""
    return OnlineMessage(
        vehicle_id=vehicle_id, stamp_s=time.time() if stamp_s is None else stamp_s, online=online
    )
