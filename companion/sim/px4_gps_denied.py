"""PX4 SITL without GPS, flying on the companion's SLAM pose; the camera rendered from SIH's truth.

GPS off, EKF2 fed only by our external vision (:data:`GPS_DENIED_PX4_PARAMS`). The simulated
RealSense must not see the room from PX4's estimate: that estimate is built from the SLAM
pose, which is built from the camera, and the test would only check itself. SIH sends its
true state as HIL_STATE_QUATERNION on its display link (UDP 19450+i -> 19410+i);
:class:`SihTruth` follows it there, renders the camera from it and records it, so PX4's
estimate and the SLAM pose can be judged against it.

Frames: the truth's map frame is x east, y north of where the vehicle stood when the truth was
first seen, z above the floor (SIH's ground is its home altitude; the body stands
:data:`STANDING_HEIGHT_M` above it when landed). The companion's map frame
is PX4's local frame at its first scan, which without GPS is that same spot give or take the
estimator's start (:func:`frame_alignment` measures the difference on the ground).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from companion.config import CompanionConfig
from companion.errors import LinkError
from companion.geo import GeoOrigin
from companion.mavlink.link import MavlinkLink
from companion.mavlink.state import LinkLike
from companion.sim.flow_sensor import FlowSensorModel, flow_rad_fields, integration_dt
from companion.sim.odometry import OdometryDriftModel
from companion.sim.px4_sitl import READY_LINE, Px4Sitl
from companion.sim.sim_world import (
    SharedSimState,
    SimCameraSource,
    SimPlacement,
    start_point_room_m,
)
from companion.sources.sim import room_from_config
from semmap.frames import (
    R_FLU_FRD,
    R_NED_ENU,
    make_transform,
    ned_to_enu,
    pose_from_xyz_rpy,
    rpy_from_rotation,
    wrap_angle_rad,
    yaw_ned_to_enu,
)

log = logging.getLogger(__name__)

#: PX4 parameters for indoor flight on the companion's pose (docs/mavlink.md explains each).
GPS_DENIED_PX4_PARAMS: dict[str, float | int] = {
    "SYS_HAS_GPS": 0,          # no GPS receiver: no GNSS pre-flight checks
    "EKF2_GPS_CTRL": 0,        # and EKF2 fuses no GNSS
    "EKF2_EV_CTRL": 9,         # external vision: horizontal position (1) + yaw (8), not height
    "EKF2_HGT_REF": 2,         # height from the downward range finder (vision gives none; baro drifts by decimetres)
    "EKF2_RNG_CTRL": 2,        # the range finder always fused
    "EKF2_MIN_RNG": 0.01,      # what the range finder reads landed (SIH's sits on the floor: 0; 0.01 is PX4's least)
    "EKF2_GND_EFF_DZ": 0.0,    # baro fused through take-off (SIH's baro has no ground effect): see docs/mavlink.md
    "EKF2_BARO_NOISE": 0.5,    # SIH's baro (0.08 m s.d. at rest) holds the height while it is the only aid
    "EKF2_EV_DELAY": 0.0,      # our stamps are capture times, mapped onto PX4's clock by TIMESYNC
    "EKF2_DELAY_MAX": 200.0,   # fusion horizon (ms, PX4's default): see docs/mavlink.md before raising it
    "EKF2_EVP_NOISE": 0.02,    # the least noise EKF2 fuses our poses with; above it, our covariance
    "EKF2_EVA_NOISE": 0.02,
}
#: PX4's start-up script has run: its links and shell answer.
STARTED_LINE = "Startup script returned successfully"
#: SIH's display link: PX4 sends HIL_STATE_QUATERNION from 19450+i to 19410+i.
DISPLAY_PORT_BASE = 19410
DISPLAY_LOCAL_PORT_BASE = 19450
#: SIH's body rests with its origin on the ground; the Hummingbird's body (and its D455) stands
#: this high above the floor on its landing gear (a camera at floor level sees nothing).
STANDING_HEIGHT_M = 0.1
#: A truth sample's PX4 time mapped onto ours must land this close to its arrival (loopback).
MAX_MAPPING_ERROR_S = 0.25
#: The truth's rate on the display link (PX4 starts it at 25 Hz).
TRUTH_RATE_HZ = 50.0


class GpsDeniedSitl(Px4Sitl):
    """:class:`Px4Sitl` with :data:`GPS_DENIED_PX4_PARAMS` (``params`` add to or override
    them). Starting does not wait for "Ready for takeoff!": without GPS PX4 is ready only once
    our external vision reaches it, so call :meth:`wait_ready` after the companion runs."""

    def __init__(self, *, params: dict[str, float | int] | None = None, **kw: object) -> None:
        super().__init__(params={**GPS_DENIED_PX4_PARAMS, **(params or {})}, **kw)  # type: ignore[arg-type]

    def _wait_ready(self) -> None:
        """Start-up returns once PX4's start-up script has run (its MAVLink links and shell
        are up); readiness for take-off is :meth:`wait_ready`'s."""
        self._wait_for_line(STARTED_LINE, poll_s=0.1)

    def wait_ready(self) -> None:
        """Block until PX4 says it is ready for take-off (raises :class:`Px4SitlError` when it
        exits or is not ready within ``ready_timeout_s``)."""
        self._wait_for_line(READY_LINE, poll_s=0.1)

    @property
    def display_url(self) -> str:
        """Where SIH's true state arrives (the display link's remote port)."""
        return f"udpin://127.0.0.1:{DISPLAY_PORT_BASE + self._need_instance()}"

    def stream_truth(self, rate_hz: float = TRUTH_RATE_HZ) -> None:
        """HIL_STATE_QUATERNION at ``rate_hz`` on the display link."""
        self.mavlink_stream(DISPLAY_LOCAL_PORT_BASE + self._need_instance(), "HIL_STATE_QUATERNION", rate_hz)


@dataclass(frozen=True)
class TruthSample:
    """SIH's true state: PX4's time (s), our time (s, ``time.monotonic``), map-frame x/y/z (m,
    z above the floor), yaw (rad, ENU: from east, counter-clockwise), roll and pitch (rad, FLU)
    (what the camera was rendered with, so a flight can be replayed offline)."""

    px4_s: float
    local_s: float
    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float
    roll_rad: float
    pitch_rad: float


def truth_pose(msg: mavlink.MAVLink_message, origin: GeoOrigin) -> tuple[NDArray[np.float64], float]:
    """(4, 4) map-frame FLU body pose and its ENU yaw from a HIL_STATE_QUATERNION, positions
    relative to ``origin`` (z above its altitude)."""
    n, e, d = origin.to_ned(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
    w, x, y, z = (float(v) for v in msg.attitude_quaternion)
    R_ned_frd = Rotation.from_quat([x, y, z, w]).as_matrix()
    R_map_flu = R_NED_ENU @ R_ned_frd @ R_FLU_FRD  # both swaps are their own inverse
    T = make_transform(R_map_flu, R_NED_ENU @ np.array([n, e, d]))
    return T, math.atan2(float(R_map_flu[1, 0]), float(R_map_flu[0, 0]))


class SihTruth:
    """Follows SIH's true state on the display link (``async with``), publishes it to the
    simulated camera and records it. ``to_local``: PX4 time (s) -> our time (s), once known
    (the service's :class:`~companion.mavlink.timesync.AutopilotClock`); until then samples
    are stamped on arrival."""

    def __init__(self, url: str, placement: SimPlacement, shared: SharedSimState,
                 odometry: OdometryDriftModel | None = None, flow: FlowSensorModel | None = None) -> None:
        self.url = url
        #: A downward flow sensor wired to PX4 (see :mod:`companion.sim.flow_sensor`): each
        #: truth sample goes back to PX4 as OPTICAL_FLOW_RAD on the display link. None: none.
        self.flow = flow
        self._flow_prev_s: float | None = None
        #: OPTICAL_FLOW_RAD sent to PX4.
        self.flow_sent = 0
        #: An odometry sensor of its own (optical flow, VIO): the truth through this drift,
        #: handed to the camera's frames with PX4's estimate as their pose (see
        #: :meth:`follow_estimate`); None: frames carry no pose, the service poses them from
        #: PX4's telemetry and dead-reckons its odometry from PX4's velocity.
        self.odometry = odometry
        self._estimate: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
        self._floor_down_m: float | None = None
        self.link = MavlinkLink(url)
        self.placement = placement
        self.shared = shared
        self.to_local: Callable[[float], float | None] | None = None
        self.origin: GeoOrigin | None = None
        self.samples: list[TruthSample] = []
        #: The latest (our time s, (4, 4) map-frame body pose), None before the first.
        self.latest: tuple[float, NDArray[np.float64]] | None = None
        self._detach: Callable[[], None] | None = None
        self._mapping_warned = False

    async def __aenter__(self) -> SihTruth:
        await self.link.__aenter__()
        self._detach = self.link.add_listener(self.handle, ("HIL_STATE_QUATERNION",))
        return self

    async def __aexit__(self, *exc: object) -> None:
        if self._detach is not None:
            self._detach()
        await self.link.__aexit__(None, None, None)

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if self.origin is None:
            self.origin = GeoOrigin(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
            log.info("SIH truth: the vehicle starts at %.7f, %.7f, %.2f m AMSL", self.origin.lat_deg,
                     self.origin.lon_deg, self.origin.alt_m)
        T, yaw = truth_pose(msg, self.origin)
        T[2, 3] += STANDING_HEIGHT_M
        px4_s = msg.time_usec * 1e-6
        local_s = time.monotonic()
        # PX4 v1.16's HIL_STATE_QUATERNION stream leaves time_usec 0: then it is stamped on arrival.
        mapped = self.to_local(px4_s) if self.to_local is not None and msg.time_usec > 0 else None
        if mapped is not None and abs(mapped - local_s) <= MAX_MAPPING_ERROR_S:
            local_s = mapped  # when it was true, not when this loop got to it
        elif mapped is not None and not self._mapping_warned:
            self._mapping_warned = True
            log.warning("SIH truth: PX4 time %.3f s maps to %.3f s, %.3f s from its arrival: stamped on arrival",
                        px4_s, mapped, mapped - local_s)
        self.latest = (local_s, T)
        if self.flow is not None:
            # The body's attitude back in NED/FRD (both swaps are their own inverse).
            self._send_flow(msg, R_NED_ENU @ T[:3, :3] @ R_FLU_FRD, float(T[2, 3]) - STANDING_HEIGHT_M)
        if self.odometry is None:
            self.shared.set_pose(local_s, T)
        elif self._estimate is not None and self._floor_down_m is not None:
            self.shared.set_pose(local_s, T, self._estimate_pose(T), self._odometry_pose(local_s, T, yaw))
        x, y, z = (float(v) for v in T[:3, 3])
        roll, pitch, _ = rpy_from_rotation(T[:3, :3])
        self.samples.append(TruthSample(px4_s, local_s, x, y, z, yaw, roll, pitch))

    def _send_flow(self, msg: mavlink.MAVLink_message, R_ned_frd: NDArray[np.float64],  # noqa: N803
                   height_m: float) -> None:
        """The flow over the time since the previous truth sample, on arrival times: the
        sensor integrates between its own messages, and PX4 stamps each on arrival."""
        assert self.flow is not None
        now = time.monotonic()
        dt, self._flow_prev_s = integration_dt(self._flow_prev_s, now), now
        if dt is None:
            return
        v_ned = 0.01 * np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)  # cm/s
        rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=np.float64)
        sample = self.flow.sample(dt, v_ned, R_ned_frd, rates, height_m)
        try:
            self.link.send(self.link.mav.optical_flow_rad_encode(int(now * 1e6), 0, **flow_rad_fields(sample)))
        except LinkError as exc:
            log.warning("optical flow not sent: %s", exc)
            return
        self.flow_sent += 1

    def follow_estimate(self, link: LinkLike, target_system: int = 1) -> Callable[[], None]:
        """Keep PX4's estimate (LOCAL_POSITION_NED, ATTITUDE) from ``link`` as the frames' pose."""
        rpy = [0.0, 0.0, 0.0]

        def handle(msg: mavlink.MAVLink_message) -> None:
            if msg.get_srcSystem() != target_system or msg.get_srcComponent() != 1:
                return
            if msg.get_type() == "ATTITUDE":
                rpy[:] = [float(msg.roll), float(msg.pitch), float(msg.yaw)]
            elif all(math.isfinite(v) for v in (msg.x, msg.y, msg.z)):
                if self._floor_down_m is None:
                    self._floor_down_m = float(msg.z)  # it stands on the floor when the service starts
                self._estimate = ((float(msg.x), float(msg.y), float(msg.z)), (rpy[0], rpy[1], rpy[2]))

        return link.add_listener(handle, ("LOCAL_POSITION_NED", "ATTITUDE"))

    def _estimate_pose(self, T_true: NDArray[np.float64]) -> NDArray[np.float64]:  # noqa: N803
        """PX4's position and heading for a frame rendered at ``T_true``, with the true roll and
        pitch: PX4 levels its attitude on its IMU, not on our vision, to a fraction of a degree;
        its latest ATTITUDE message lags the render by up to a telemetry period, in which a
        vehicle starting a leg tilts by degrees, and a scan levelled with that lag is not level."""
        assert self._estimate is not None and self._floor_down_m is not None
        (n, e, d), (_, _, yaw_ned) = self._estimate
        roll, pitch, _ = rpy_from_rotation(T_true[:3, :3])
        x, y, _ = ned_to_enu(n, e, d)
        z = self._floor_down_m - d + STANDING_HEIGHT_M  # above the floor, as the truth's z
        return pose_from_xyz_rpy(x, y, z, roll, pitch, yaw_ned_to_enu(yaw_ned))

    def _odometry_pose(self, local_s: float, T: NDArray[np.float64], yaw: float) -> NDArray[np.float64]:
        assert self.odometry is not None
        x, y, odo_yaw = self.odometry.update(local_s, (float(T[0, 3]), float(T[1, 3]), yaw))
        roll, pitch, _ = rpy_from_rotation(T[:3, :3])
        return pose_from_xyz_rpy(float(x), float(y), float(T[2, 3]), roll, pitch, float(odo_yaw))

    async def wait_first(self, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not self.samples:
            if time.monotonic() > deadline:
                raise LinkError(f"no HIL_STATE_QUATERNION from SIH on {self.url} within {timeout_s:.0f} s")
            await asyncio.sleep(0.05)

    def frame_source(self, cfg: CompanionConfig) -> SimCameraSource:
        """The simulated camera rendering the room from the truth (picklable)."""
        return SimCameraSource(cfg, self.placement, self.shared)

    def path_map_m(self) -> NDArray[np.float64]:
        """(N, 3) the true path, map frame, oldest first."""
        return np.array([(s.x_m, s.y_m, s.z_m) for s in self.samples], dtype=np.float64).reshape(-1, 3)

    def at(self, t_s: NDArray[np.float64], clock: str = "px4") -> NDArray[np.float64]:
        """(N, 4) x, y, z, yaw interpolated at times ``t_s`` on PX4's (``px4``) or our clock."""
        arr = np.array([(s.px4_s if clock == "px4" else s.local_s, s.x_m, s.y_m, s.z_m, s.yaw_rad)
                        for s in self.samples], dtype=np.float64)
        yaw = np.unwrap(arr[:, 4])
        cols = [np.interp(t_s, arr[:, 0], arr[:, k]) for k in (1, 2, 3)]
        return np.column_stack([*cols, np.interp(t_s, arr[:, 0], yaw)])


def placement_around_start(cfg: CompanionConfig) -> SimPlacement:
    """The seeded room with the truth's origin (where the vehicle stands) just inside its first doorway."""
    room = room_from_config(cfg)
    return SimPlacement(room, start_point_room_m(room))


class EstimateRecorder:
    """PX4's estimate (LOCAL_POSITION_NED with ATTITUDE's yaw) on a link, stamped on arrival
    (``time.monotonic``: loopback, as the truth's samples)."""

    def __init__(self, target_system: int = 1) -> None:
        self.target_system = target_system
        self.rows: list[tuple[float, float, float, float, float]] = []  # our s, x east, y north, -down, yaw ENU
        self._yaw_enu = math.nan

    def attach(self, link: LinkLike) -> Callable[[], None]:
        return link.add_listener(self.handle, ("LOCAL_POSITION_NED", "ATTITUDE"))

    def handle(self, msg: mavlink.MAVLink_message) -> None:
        if msg.get_srcSystem() != self.target_system or msg.get_srcComponent() != 1:
            return
        if msg.get_type() == "ATTITUDE":
            self._yaw_enu = wrap_angle_rad(math.pi / 2 - float(msg.yaw))
        elif all(math.isfinite(v) for v in (msg.x, msg.y, msg.z)):
            self.rows.append((time.monotonic(), float(msg.y), float(msg.x), -float(msg.z), self._yaw_enu))


@dataclass
class Alignment:
    """The companion's map frame on the truth's: ``p_truth = R(yaw) p_map + t``."""

    yaw_rad: float = 0.0
    t_xy_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros(2))

    def apply(self, xy_m: NDArray[np.float64]) -> NDArray[np.float64]:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.asarray(xy_m, dtype=np.float64) @ np.array([[c, s], [-s, c]]) + self.t_xy_m


def frame_alignment(est: NDArray[np.float64], truth: NDArray[np.float64]) -> Alignment:
    """The rigid 2D transform from the estimate's frame to the truth's, from (N, 4) x, y, z, yaw
    pairs taken while the vehicle stood still on the ground (the frames' difference there is
    where each started, not an error of the flight)."""
    dyaw = float(np.angle(np.mean(np.exp(1j * (truth[:, 3] - est[:, 3])))))
    c, s = math.cos(dyaw), math.sin(dyaw)
    rotated = est[:, :2] @ np.array([[c, s], [-s, c]])
    return Alignment(dyaw, np.mean(truth[:, :2] - rotated, axis=0))


def p95(values: NDArray[np.float64] | list[float]) -> float | None:
    arr = np.asarray(values, dtype=np.float64)
    return round(float(np.percentile(arr, 95)), 3) if arr.size else None

