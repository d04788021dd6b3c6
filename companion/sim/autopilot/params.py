"""The mock autopilot's parameters, with PX4's byte-wise MAVLink encoding.

PX4 sends every parameter in the ``float param_value`` field of ``PARAM_VALUE`` *byte-wise*
(``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE``); MAVSDK knows this from the autopilot type.
The mock encodes and decodes with :mod:`companion.px4`, as our link does.

Only the parameters the mock itself uses and the ones clients (MAVSDK, QGroundControl, our
link) read are defined; their defaults are PX4's except where noted for indoor flight.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from companion.px4 import MAV_PARAM_TYPE_INT32, MAV_PARAM_TYPE_REAL32

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParamSpec:
    """One parameter's name, MAVLink type and default value."""

    name: str
    param_type: int  # MAV_PARAM_TYPE_INT32 or MAV_PARAM_TYPE_REAL32
    default: float


#: The parameter table, in PARAM_REQUEST_LIST order.
PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("SYS_AUTOSTART", MAV_PARAM_TYPE_INT32, 4001),
    ParamSpec("MAV_SYS_ID", MAV_PARAM_TYPE_INT32, 1),
    ParamSpec("MAV_COMP_ID", MAV_PARAM_TYPE_INT32, 1),
    ParamSpec("MAV_TYPE", MAV_PARAM_TYPE_INT32, 2),
    ParamSpec("MIS_TAKEOFF_ALT", MAV_PARAM_TYPE_REAL32, 2.5),
    ParamSpec("MIS_DIST_1WP", MAV_PARAM_TYPE_REAL32, 900.0),
    ParamSpec("NAV_ACC_RAD", MAV_PARAM_TYPE_REAL32, 2.0),
    ParamSpec("MPC_XY_CRUISE", MAV_PARAM_TYPE_REAL32, 5.0),
    ParamSpec("MPC_XY_VEL_MAX", MAV_PARAM_TYPE_REAL32, 12.0),
    ParamSpec("MPC_Z_VEL_MAX_UP", MAV_PARAM_TYPE_REAL32, 3.0),
    ParamSpec("MPC_Z_VEL_MAX_DN", MAV_PARAM_TYPE_REAL32, 1.5),
    ParamSpec("MPC_ACC_HOR", MAV_PARAM_TYPE_REAL32, 3.0),
    ParamSpec("MPC_XY_VEL_P_ACC", MAV_PARAM_TYPE_REAL32, 1.8),
    ParamSpec("MPC_ACC_UP_MAX", MAV_PARAM_TYPE_REAL32, 4.0),
    ParamSpec("MPC_YAWRAUTO_MAX", MAV_PARAM_TYPE_REAL32, 45.0),
    ParamSpec("MPC_LAND_SPEED", MAV_PARAM_TYPE_REAL32, 0.7),
    ParamSpec("MPC_TKO_SPEED", MAV_PARAM_TYPE_REAL32, 1.5),
    # PX4's default RTL altitude is 60 m; an indoor vehicle returns at 2 m.
    ParamSpec("RTL_RETURN_ALT", MAV_PARAM_TYPE_REAL32, 2.0),
    ParamSpec("RTL_DESCEND_ALT", MAV_PARAM_TYPE_REAL32, 2.0),
    ParamSpec("RTL_LAND_DELAY", MAV_PARAM_TYPE_REAL32, 0.0),
    ParamSpec("COM_OF_LOSS_T", MAV_PARAM_TYPE_REAL32, 1.0),
    ParamSpec("COM_OBL_RC_ACT", MAV_PARAM_TYPE_INT32, 0),
    ParamSpec("COM_DISARM_LAND", MAV_PARAM_TYPE_REAL32, 2.0),
    ParamSpec("COM_DISARM_PRFLT", MAV_PARAM_TYPE_REAL32, 10.0),
    ParamSpec("COM_RC_IN_MODE", MAV_PARAM_TYPE_INT32, 4),
    ParamSpec("COM_RCL_EXCEPT", MAV_PARAM_TYPE_INT32, 4),
    ParamSpec("NAV_DLL_ACT", MAV_PARAM_TYPE_INT32, 0),
    ParamSpec("EKF2_EV_CTRL", MAV_PARAM_TYPE_INT32, 0),
    ParamSpec("EKF2_HGT_REF", MAV_PARAM_TYPE_INT32, 1),
    ParamSpec("EKF2_EV_DELAY", MAV_PARAM_TYPE_REAL32, 0.0),
    ParamSpec("EKF2_GPS_CTRL", MAV_PARAM_TYPE_INT32, 7),
    ParamSpec("EKF2_NOAID_TOUT", MAV_PARAM_TYPE_INT32, 5000000),
    ParamSpec("EKF2_OF_CTRL", MAV_PARAM_TYPE_INT32, 0),
    ParamSpec("SYS_HAS_GPS", MAV_PARAM_TYPE_INT32, 1),
    ParamSpec("SYS_FAILURE_EN", MAV_PARAM_TYPE_INT32, 0),
    ParamSpec("FLW_TGT_HT", MAV_PARAM_TYPE_REAL32, 8.0),
    ParamSpec("FLW_TGT_DST", MAV_PARAM_TYPE_REAL32, 8.0),
    ParamSpec("FLW_TGT_FA", MAV_PARAM_TYPE_REAL32, 180.0),
    ParamSpec("FLW_TGT_RS", MAV_PARAM_TYPE_REAL32, 0.1),
    ParamSpec("FLW_TGT_ALT_M", MAV_PARAM_TYPE_INT32, 0),
    ParamSpec("FLW_TGT_MAX_VEL", MAV_PARAM_TYPE_REAL32, 5.0),
    ParamSpec("MC_ORBIT_RAD_MAX", MAV_PARAM_TYPE_REAL32, 1000.0),
    ParamSpec("CAL_ACC0_ID", MAV_PARAM_TYPE_INT32, 1310988),
    ParamSpec("CAL_GYRO0_ID", MAV_PARAM_TYPE_INT32, 1310988),
    ParamSpec("CAL_MAG0_ID", MAV_PARAM_TYPE_INT32, 197388),
)


class ParamStore:
    """Current parameter values by name, typed as in :data:`PARAM_SPECS`."""

    def __init__(self, overrides: dict[str, float] | None = None) -> None:
        self._specs = {s.name: s for s in PARAM_SPECS}
        self._order = [s.name for s in PARAM_SPECS]
        self._values: dict[str, float] = {s.name: float(s.default) for s in PARAM_SPECS}
        for name, value in (overrides or {}).items():
            self.set(name, value)

    def __len__(self) -> int:
        return len(self._order)

    def __contains__(self, name: object) -> bool:
        return name in self._values

    def get(self, name: str) -> float:
        """The value of ``name``. Raises KeyError for an unknown parameter."""
        return self._values[name]

    def set(self, name: str, value: float) -> float:
        """Set ``name`` (rounded for integer parameters); returns the stored value."""
        spec = self._specs.get(name)
        if spec is None:
            raise KeyError(f"unknown parameter {name!r}")
        stored = float(int(round(value))) if spec.param_type == MAV_PARAM_TYPE_INT32 else float(value)
        self._values[name] = stored
        log.debug("param %s = %s", name, stored)
        return stored

    def spec(self, name: str) -> ParamSpec:
        return self._specs[name]

    def index_of(self, name: str) -> int:
        return self._order.index(name)

    def name_at(self, index: int) -> str | None:
        return self._order[index] if 0 <= index < len(self._order) else None

    def names(self) -> list[str]:
        return list(self._order)
