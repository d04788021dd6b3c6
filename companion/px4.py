"""PX4's flight modes and the MAVLink conventions PX4 uses, written once.

PX4 puts its flight mode into ``HEARTBEAT.custom_mode`` as two bytes of a 32-bit word::

    custom_mode = main_mode << 16 | sub_mode << 24

with ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` set in ``base_mode`` (PX4
``src/modules/commander/px4_custom_mode.h``). The same encoding is used by
``MAV_CMD_DO_SET_MODE`` (param1 = base mode, param2 = main mode, param3 = sub mode).

PX4 packs parameter values into the ``float param_value`` field of ``PARAM_VALUE`` and
``PARAM_SET`` *byte-wise* (``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE``, PX4
``src/modules/mavlink/mavlink_parameters.cpp``): an integer parameter's bytes are the float's
low bytes, so the INT32 value 5000000 travels as a tiny denormal float, not as 5000000.0
(ArduPilot's C cast). :func:`encode_param_value` / :func:`decode_param_value` are that encoding.

Both our link (:mod:`companion.mavlink`) and the mock autopilot (:mod:`companion.sim.autopilot`)
decode and encode modes and parameters through this module, so the two cannot disagree. It depends on nothing
but the standard library so either side can import it cheaply.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass


class MainMode(enum.IntEnum):
    """PX4 ``PX4_CUSTOM_MAIN_MODE_*``."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class PosctlSubMode(enum.IntEnum):
    """PX4 ``PX4_CUSTOM_SUB_MODE_POSCTL_*`` (only meaningful with :attr:`MainMode.POSCTL`)."""

    POSCTL = 0
    ORBIT = 1


class AutoSubMode(enum.IntEnum):
    """PX4 ``PX4_CUSTOM_SUB_MODE_AUTO_*`` (only meaningful with :attr:`MainMode.AUTO`)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    RTGS = 7
    FOLLOW_TARGET = 8
    PRECLAND = 9


class FlightMode(enum.Enum):
    """A named PX4 flight mode, its value being the ``(main, sub)`` pair.

    ``HOLD`` is what QGroundControl and MAVSDK call ``AUTO.LOITER``.
    """

    MANUAL = (MainMode.MANUAL, 0)
    ALTCTL = (MainMode.ALTCTL, 0)
    POSCTL = (MainMode.POSCTL, 0)
    ORBIT = (MainMode.POSCTL, PosctlSubMode.ORBIT)  # MAV_CMD_DO_ORBIT
    ACRO = (MainMode.ACRO, 0)
    OFFBOARD = (MainMode.OFFBOARD, 0)
    STABILIZED = (MainMode.STABILIZED, 0)
    RATTITUDE = (MainMode.RATTITUDE, 0)
    READY = (MainMode.AUTO, AutoSubMode.READY)
    TAKEOFF = (MainMode.AUTO, AutoSubMode.TAKEOFF)
    HOLD = (MainMode.AUTO, AutoSubMode.LOITER)
    MISSION = (MainMode.AUTO, AutoSubMode.MISSION)
    RTL = (MainMode.AUTO, AutoSubMode.RTL)
    LAND = (MainMode.AUTO, AutoSubMode.LAND)
    FOLLOW_TARGET = (MainMode.AUTO, AutoSubMode.FOLLOW_TARGET)
    PRECLAND = (MainMode.AUTO, AutoSubMode.PRECLAND)

    @property
    def main_mode(self) -> int:
        return int(self.value[0])

    @property
    def sub_mode(self) -> int:
        return int(self.value[1])

    @property
    def custom_mode(self) -> int:
        """The 32-bit ``HEARTBEAT.custom_mode`` word for this mode."""
        return encode_custom_mode(self.main_mode, self.sub_mode)

    @property
    def is_auto(self) -> bool:
        """True for the modes in which PX4's navigator flies (takeoff, hold, mission, RTL, land)."""
        return self.main_mode == MainMode.AUTO


_BY_PAIR: dict[tuple[int, int], FlightMode] = {
    (m.main_mode, m.sub_mode): m for m in FlightMode
}

# --- MAVLink constants PX4 uses (values from the common dialect, named here so call sites
# never carry bare numbers and neither side needs pymavlink just to read a heartbeat) ---------

MAV_AUTOPILOT_PX4 = 12
MAV_TYPE_QUADROTOR = 2
MAV_TYPE_GCS = 6
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_COMP_ID_AUTOPILOT1 = 1
MAV_COMP_ID_ONBOARD_COMPUTER = 191

MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_TEST_ENABLED = 2
MAV_MODE_FLAG_AUTO_ENABLED = 4
MAV_MODE_FLAG_GUIDED_ENABLED = 8
MAV_MODE_FLAG_STABILIZE_ENABLED = 16
MAV_MODE_FLAG_HIL_ENABLED = 32
MAV_MODE_FLAG_MANUAL_INPUT_ENABLED = 64
MAV_MODE_FLAG_SAFETY_ARMED = 128

MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5

MAV_LANDED_STATE_UNDEFINED = 0
MAV_LANDED_STATE_ON_GROUND = 1
MAV_LANDED_STATE_IN_AIR = 2
MAV_LANDED_STATE_TAKEOFF = 3
MAV_LANDED_STATE_LANDING = 4

#: ``MAV_PARAM_TYPE``: PX4's parameters are INT32 or REAL32; the other integer types are
#: decoded too, from the low bytes of the field as the MAVLink parameter union lays them.
MAV_PARAM_TYPE_UINT8 = 1
MAV_PARAM_TYPE_INT8 = 2
MAV_PARAM_TYPE_UINT16 = 3
MAV_PARAM_TYPE_INT16 = 4
MAV_PARAM_TYPE_UINT32 = 5
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9

#: ``struct`` format of each integer parameter type inside the 4-byte field (little endian).
_PARAM_INT_FORMATS = {
    MAV_PARAM_TYPE_UINT8: "<B", MAV_PARAM_TYPE_INT8: "<b", MAV_PARAM_TYPE_UINT16: "<H",
    MAV_PARAM_TYPE_INT16: "<h", MAV_PARAM_TYPE_UINT32: "<I", MAV_PARAM_TYPE_INT32: "<i",
}

#: ``MAV_CMD_COMPONENT_ARM_DISARM`` param2 value that forces a disarm in flight.
PX4_FORCE_DISARM_MAGIC = 21196.0

#: PX4's default UDP ports for the onboard (API/offboard) link: PX4 sends from
#: ``local`` to ``remote`` (``mavlink start -u 14580 -o 14540`` in SITL).
PX4_ONBOARD_LOCAL_PORT = 14580
PX4_ONBOARD_REMOTE_PORT = 14540
PX4_GCS_REMOTE_PORT = 14550


@dataclass(frozen=True)
class DecodedMode:
    """A heartbeat's mode fields, decoded."""

    armed: bool
    mode: FlightMode | None  # None when the custom mode is not a known PX4 mode
    main_mode: int
    sub_mode: int


def encode_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """``custom_mode`` word from PX4 main and sub mode numbers (each 0..255)."""
    if not (0 <= main_mode <= 255 and 0 <= sub_mode <= 255):
        raise ValueError(f"PX4 main/sub mode out of range: {main_mode}, {sub_mode}")
    return (main_mode << 16) | (sub_mode << 24)


def split_custom_mode(custom_mode: int) -> tuple[int, int]:
    """``(main_mode, sub_mode)`` from a ``custom_mode`` word."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_from_main_sub(main_mode: int, sub_mode: int) -> FlightMode | None:
    """The named mode for a ``(main, sub)`` pair, or None if PX4 has no such mode.

    Main modes other than AUTO and POSCTL ignore the sub mode, as PX4 does.
    """
    if main_mode != MainMode.AUTO and (int(main_mode), int(sub_mode)) not in _BY_PAIR:
        sub_mode = 0  # e.g. Position's "slow" sub mode is Position
    return _BY_PAIR.get((int(main_mode), int(sub_mode)))


def decode_custom_mode(custom_mode: int) -> FlightMode | None:
    """The named mode in a ``HEARTBEAT.custom_mode`` word, or None if unknown."""
    return mode_from_main_sub(*split_custom_mode(custom_mode))


def decode_heartbeat(base_mode: int, custom_mode: int) -> DecodedMode:
    """Decode a PX4 heartbeat's ``base_mode`` and ``custom_mode`` fields.

    If ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` is not set the custom mode is meaningless and
    ``mode`` is None.
    """
    main, sub = split_custom_mode(custom_mode)
    mode = (
        mode_from_main_sub(main, sub)
        if base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        else None
    )
    return DecodedMode(
        armed=bool(base_mode & MAV_MODE_FLAG_SAFETY_ARMED), mode=mode, main_mode=main, sub_mode=sub
    )


def encode_heartbeat_base_mode(mode: FlightMode, armed: bool) -> int:
    """``HEARTBEAT.base_mode`` as PX4 fills it for ``mode`` (custom flag, armed, auto/guided)."""
    base = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if armed:
        base |= MAV_MODE_FLAG_SAFETY_ARMED
    if mode not in (FlightMode.MANUAL, FlightMode.ACRO):
        base |= MAV_MODE_FLAG_STABILIZE_ENABLED
    if mode.is_auto:
        base |= MAV_MODE_FLAG_AUTO_ENABLED | MAV_MODE_FLAG_GUIDED_ENABLED
    elif mode in (FlightMode.POSCTL, FlightMode.ORBIT, FlightMode.OFFBOARD):
        base |= MAV_MODE_FLAG_GUIDED_ENABLED
    if mode in (FlightMode.MANUAL, FlightMode.ALTCTL, FlightMode.POSCTL, FlightMode.STABILIZED,
                FlightMode.ACRO, FlightMode.RATTITUDE):
        base |= MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
    return base


def set_mode_params(mode: FlightMode) -> tuple[float, float, float]:
    """``MAV_CMD_DO_SET_MODE`` params 1-3 (base mode, main mode, sub mode) for ``mode``."""
    return float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(mode.main_mode), float(mode.sub_mode)


def mode_from_set_mode_params(param1: float, param2: float, param3: float) -> FlightMode | None:
    """The mode a ``MAV_CMD_DO_SET_MODE`` asks for, or None if it is not a PX4 custom mode."""
    if not int(param1) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return None
    return mode_from_main_sub(int(param2), int(param3))


def encode_param_value(value: float, param_type: int) -> float:
    """The ``param_value`` float PX4 sends (and expects in PARAM_SET) for ``value`` of
    ``param_type``: an integer's bytes in the field's low bytes, REAL32 as itself.
    Raises ValueError for an integer out of its type's range."""
    fmt = _PARAM_INT_FORMATS.get(int(param_type))
    if fmt is None:
        return float(value)
    try:
        raw = struct.pack(fmt, int(value)).ljust(4, b"\x00")
    except struct.error as exc:
        raise ValueError(f"parameter value {value!r} does not fit MAV_PARAM_TYPE {param_type}: {exc}") from exc
    return float(struct.unpack("<f", raw)[0])


def decode_param_value(value: float, param_type: int) -> float:
    """The parameter's value from a PARAM_VALUE's or PARAM_SET's ``param_value`` float
    (inverse of :func:`encode_param_value`)."""
    fmt = _PARAM_INT_FORMATS.get(int(param_type))
    if fmt is None:
        return float(value)
    return float(struct.unpack_from(fmt, struct.pack("<f", float(value)))[0])


def param_id_str(param_id: bytes | str) -> str:
    """A MAVLink ``param_id`` (up to 16 chars, NUL padded) as a plain string."""
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", errors="replace")
    return str(param_id).split("\x00", 1)[0]
