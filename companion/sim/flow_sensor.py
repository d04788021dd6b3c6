"""A downward optical-flow sensor on SIH's truth, for PX4 as OPTICAL_FLOW_RAD.

Indoor vehicles carry one beside the range finder (ARK Flow, a PMW3901 board), wired to the
flight controller: EKF2 then keeps a velocity of its own (``EKF2_OF_CTRL``) when the
companion's pose stops, where its IMU alone lets the vehicle drift decimetres in seconds.
SIH simulates none, so the GPS-denied bench makes one from the true state SIH sends on its
display link and sends it back to PX4 there, as the sensor's own MAVLink port would.

Conventions are MAVLink's (PX4 takes them unchanged into ``sensor_optical_flow``): the
sensor looks down with its axes on the body's FRD axes (``SENS_FLOW_ROT`` 0); a right-handed
rotation about an axis reads as positive flow about it, so moving forward (+x) reads +y and
moving right (+y) reads -x, and the sensor's gyro is integrated alongside for EKF2 to take
the rotation out again.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

#: PX4 parameters for EKF2 to fuse the flow next to the external vision (docs/mavlink.md).
FLOW_PX4_PARAMS: dict[str, float | int] = {
    "EKF2_OF_CTRL": 1,         # fuse optical flow
    "SENS_FLOW_ROT": 0,        # the sensor's axes are the body's
    "SENS_FLOW_MINHGT": 0.08,  # below this the sensor reads nothing (FlowSensorModel.min_height_m)
    "SENS_FLOW_MAXHGT": 4.0,   # indoors the floor is never farther
}

#: What a flow sensor's quality field means by a clean image (MAVLink: 0 none, 255 best).
FULL_QUALITY = 255
#: Gaps between truth messages outside this (s) are no integration interval: the first one,
#: or a stall of the loop, whose flow would be the rate of one instant stretched over it.
MIN_DT_S, MAX_DT_S = 0.002, 0.1


@dataclass(frozen=True)
class FlowSample:
    """One OPTICAL_FLOW_RAD's content: flow and gyro integrated over ``integration_s``
    (rad, about the sensor's x and y / x, y and z), ``quality`` 0-255, ``distance_m`` along
    the sensor's axis to the floor."""

    integration_s: float
    flow_xy_rad: tuple[float, float]
    gyro_xyz_rad: tuple[float, float, float]
    quality: int
    distance_m: float


@dataclass
class FlowSensorModel:
    """The flow a downward sensor reads over ``dt_s`` for a true motion: the body velocity
    over the distance to the floor plus the body rates, with white noise of
    ``noise_rad_s`` (1-sigma, on the rate). Below ``min_height_m`` (on the ground) it reads
    nothing, with quality 0, as a real sensor does out of focus."""

    noise_rad_s: float = 0.02
    min_height_m: float = 0.08
    seed: int = 0
    _rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def sample(self, dt_s: float, v_ned_m_s: NDArray[np.float64], R_ned_frd: NDArray[np.float64],  # noqa: N803
               rates_frd_rad_s: NDArray[np.float64], height_m: float) -> FlowSample:
        """The flow over ``dt_s`` for velocity ``v_ned_m_s`` (3,), attitude ``R_ned_frd``
        (3, 3), body rates ``rates_frd_rad_s`` (3,) and ``height_m`` of the sensor above
        the floor."""
        rates = np.asarray(rates_frd_rad_s, dtype=np.float64).reshape(3)
        gyro = (float(rates[0] * dt_s), float(rates[1] * dt_s), float(rates[2] * dt_s))
        cos_tilt = float(R_ned_frd[2, 2])  # body z against down
        if height_m < self.min_height_m or cos_tilt < 0.5:
            return FlowSample(dt_s, (0.0, 0.0), gyro, 0, max(height_m, 0.0))
        distance_m = height_m / cos_tilt
        v_frd = R_ned_frd.T @ np.asarray(v_ned_m_s, dtype=np.float64).reshape(3)
        rate_x = -v_frd[1] / distance_m + rates[0] + self._rng.normal(0.0, self.noise_rad_s)
        rate_y = v_frd[0] / distance_m + rates[1] + self._rng.normal(0.0, self.noise_rad_s)
        return FlowSample(dt_s, (float(rate_x * dt_s), float(rate_y * dt_s)), gyro, FULL_QUALITY, distance_m)


def flow_rad_fields(s: FlowSample) -> dict[str, float | int]:
    """OPTICAL_FLOW_RAD's fields for ``s`` (its time and sensor id aside). The distance is
    sent as unknown (-1): PX4 then takes its own range finder's, which is what EKF2 fuses
    the flow with anyway, and does not publish the flow's as a second range finder."""
    return {"integration_time_us": max(1, int(round(s.integration_s * 1e6))),
            "integrated_x": s.flow_xy_rad[0], "integrated_y": s.flow_xy_rad[1],
            "integrated_xgyro": s.gyro_xyz_rad[0], "integrated_ygyro": s.gyro_xyz_rad[1],
            "integrated_zgyro": s.gyro_xyz_rad[2], "temperature": 2500, "quality": s.quality,
            "time_delta_distance_us": 0, "distance": -1.0}


def integration_dt(prev_s: float | None, now_s: float) -> float | None:
    """The interval to integrate over since ``prev_s`` (None: skip this sample)."""
    if prev_s is None:
        return None
    dt = now_s - prev_s
    return dt if MIN_DT_S <= dt <= MAX_DT_S else None
