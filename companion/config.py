"""The root configuration: every stage's model composed into one, read from YAML.

``CompanionConfig()`` *is* the embedded default; ``config/default.yaml`` spells it out and a
test keeps the two equal. A file may give only the keys it changes. Errors name the file, the
key path and what is allowed, e.g.::

    config/drone.yaml: map.resolution_m: must be > 0 (got -0.05)
"""

from __future__ import annotations

import ipaddress
import logging
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from companion.errors import LinkError
from planner.config import PlannerConfig
from semmap.config import (
    CameraConfig,
    ClassConfig,
    DetectorConfig,
    GeometryConfig,
    MapConfig,
    SlamConfig,
    StageConfig,
    TrackerConfig,
    default_classes,
)
from semmap.errors import ConfigError

log = logging.getLogger(__name__)


class LinkConfig(StageConfig):
    """The MAVLink link to the autopilot."""

    #: MAVSDK-style URL: udpin://host:port, udpout://host:port, tcp://host:port,
    #: tcpin://host:port, serial:///dev/ttyX:baud; tlog:///path.tlog replays a recording.
    url: str = "udpin://0.0.0.0:14540"
    #: Our identity: the vehicle's system id and MAV_COMP_ID_ONBOARD_COMPUTER.
    system_id: int = Field(default=1, ge=1, le=255)
    component_id: int = Field(default=191, ge=1, le=255)
    target_system: int = Field(default=1, ge=1, le=255)
    target_component: int = Field(default=1, ge=0, le=255)
    heartbeat_rate_hz: float = Field(default=1.0, gt=0.0, le=10.0)
    setpoint_rate_hz: float = Field(default=30.0, ge=20.0, le=50.0)
    #: Setpoints are streamed at least this long before OFFBOARD is requested.
    offboard_warmup_s: float = Field(default=1.0, ge=1.0)
    heartbeat_timeout_s: float = Field(default=3.0, gt=0.0)
    pose_timeout_s: float = Field(default=0.5, gt=0.0)
    command_timeout_s: float = Field(default=1.0, gt=0.0)
    command_retries: int = Field(default=3, ge=0, le=10)
    #: 32-byte MAVLink 2 signing key file; None = signing off.
    signing_key_path: str | None = None
    obstacle_distance_rate_hz: float = Field(default=10.0, ge=0.0, le=50.0)
    #: OBSTACLE_DISTANCE range (metres): nearer obstacles are reported at the minimum;
    #: a sector clear out to the maximum is reported as "no obstacle".
    obstacle_distance_min_m: float = Field(default=0.2, ge=0.0)
    obstacle_distance_max_m: float = Field(default=8.0, gt=0.0, le=600.0)
    #: Seconds to wait for the vehicle to report OFFBOARD after requesting it.
    offboard_engage_timeout_s: float = Field(default=3.0, gt=0.0)
    #: Tracking monitor: the vehicle farther than this from the setpoint we send, for longer
    #: than ``tracking_timeout_s``, is held where it is and the path re-planned from there.
    tracking_error_m: float = Field(default=1.0, gt=0.0)
    tracking_timeout_s: float = Field(default=2.0, gt=0.0)
    #: Arming waits up to this long for PX4's readiness (pre-arm checks, home, estimator:
    #: 15-70 s after boot), then retries a refused arm ``arm_retries`` times.
    ready_timeout_s: float = Field(default=120.0, gt=0.0)
    arm_retries: int = Field(default=3, ge=0, le=20)
    #: Scheduler slice (ms) the event-loop thread asks Linux for, so the setpoint task wakes
    #: on time under CPU load (EEVDF, Linux >= 6.12; ignored before); 0 = leave it alone.
    scheduler_slice_ms: float = Field(default=0.5, ge=0.0, le=100.0)
    #: Send the SLAM pose to PX4 as external vision.
    external_vision: bool = False
    #: The SLAM pose's 1-sigma errors sent with it as ODOMETRY's covariance (EKF2 weighs it by
    #: them with ``EKF2_EV_NOISE_MD`` 0): bench/slam.py's ATE and the live error in flight in
    #: the SLAM's own frame (PX4 SITL: 0.04-0.08 m p95 after a best-fit alignment).
    vision_position_std_m: float = Field(default=0.03, gt=0.0, le=5.0)
    vision_yaw_std_deg: float = Field(default=2.0, gt=0.0, le=90.0)
    #: A SLAM pose that moves farther than this from where the previous one and the odometry
    #: since put it (a loop closure, a relocalisation) bumps ODOMETRY's ``reset_counter``, so
    #: EKF2 resets to it instead of rejecting it at its innovation gate.
    vision_reset_jump_m: float = Field(default=0.10, gt=0.0)
    vision_reset_jump_deg: float = Field(default=3.0, gt=0.0)
    #: The frames' odometry (``Frame.T_odom_body``) is a sensor of the vehicle's own that PX4's
    #: estimate does not contain (optical flow, VIO): a partly matched SLAM pose, which takes
    #: the direction its scan cannot see (a bare wall) from that odometry, is then a
    #: measurement and goes to PX4 too, as does a scan that matched nothing (the last match
    #: moved by the odometry), its position 1-sigma grown by
    #: ``vision_odometry_drift_per_m`` for every metre flown since the last full match. Off
    #: (default) the odometry may be PX4's own velocity, and only full matches are sent.
    vision_odometry_independent: bool = False
    vision_odometry_drift_per_m: float = Field(default=0.05, gt=0.0, le=1.0)
    #: PX4 has no horizontal position but our pose (no GPS; docs/mavlink.md "PX4 without GPS"):
    #: when the pose stops the vehicle holds and then lands (the two settings below). Off,
    #: PX4 coasts on its other sources while the SLAM has no match.
    vision_is_position_source: bool = False
    #: No SLAM pose sent for this long while flying on it: hold on PX4's last estimate ...
    vision_lost_hold_s: float = Field(default=1.0, gt=0.0)
    #: ... and land when it has not come back after this long. None (default): as late as
    #: PX4's estimate allows, so that the descent at ``MPC_LAND_SPEED`` touches down before
    #: ``EKF2_NOAID_TOUT`` ends it (both read from PX4). A value is refused when that
    #: descent from ``planner.flight_altitude_m`` cannot end in time, and capped at any height.
    vision_lost_land_s: float | None = Field(default=None, gt=0.0)

    @model_validator(mode="after")
    def _vision_lost_order(self) -> "LinkConfig":
        if self.vision_lost_land_s is not None and self.vision_lost_land_s <= self.vision_lost_hold_s:
            raise ValueError(f"link.vision_lost_land_s ({self.vision_lost_land_s}) must be longer than "
                             f"link.vision_lost_hold_s ({self.vision_lost_hold_s})")
        return self

    @field_validator("url")
    @classmethod
    def _url_scheme(cls, v: str) -> str:
        from companion.mavlink.urls import parse_url  # local: config stays cheap to import

        try:
            parse_url(v)
        except LinkError as exc:
            raise ValueError(str(exc)) from exc
        return v

    @field_validator("scheduler_slice_ms")
    @classmethod
    def _slice(cls, v: float) -> float:
        if 0.0 < v < 0.1:
            raise ValueError(f"must be 0 (off) or 0.1..100 ms (got {v})")
        return v

    @model_validator(mode="after")
    def _obstacle_range(self) -> "LinkConfig":
        if self.obstacle_distance_min_m >= self.obstacle_distance_max_m:
            raise ValueError(
                f"obstacle_distance_min_m ({self.obstacle_distance_min_m}) must be below "
                f"obstacle_distance_max_m ({self.obstacle_distance_max_m})"
            )
        return self


def _is_loopback(host: str) -> bool:
    """True for a host name or address that never leaves this machine."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class MqttConfig(StageConfig):
    """The MQTT ground link."""

    enabled: bool = True
    host: str = "127.0.0.1"
    port: int = Field(default=1883, ge=1, le=65535)
    vehicle_id: str = Field(default="drone1", pattern=r"^[A-Za-z0-9_-]+$")
    #: Topics live under ``<topic_prefix>/<vehicle_id>/``.
    topic_prefix: str = Field(default="companion", pattern=r"^[A-Za-z0-9_/-]+$")
    username: str | None = None
    #: File holding the password (first line); keeps the secret out of the config.
    password_file: str | None = None
    #: Connect with TLS using the system's CA store. Setting ``tls_ca_file`` (the CA that
    #: signed the broker's certificate) or a client certificate/key also turns TLS on.
    tls: bool = False
    tls_ca_file: str | None = None
    tls_cert_file: str | None = None
    tls_key_file: str | None = None
    keepalive_s: int = Field(default=10, ge=1)
    #: Broker round-trip timeout (CONNACK, SUBACK, PUBACK).
    timeout_s: float = Field(default=5.0, gt=0.0)
    reconnect_min_s: float = Field(default=0.5, gt=0.0)
    reconnect_max_s: float = Field(default=10.0, gt=0.0)
    #: Events (command replies) kept while the broker is unreachable; the oldest is dropped.
    outbox_size: int = Field(default=100, ge=1)
    #: Commands accepted per second (token bucket) and the burst allowed above that rate.
    command_rate_limit_hz: float = Field(default=5.0, gt=0.0)
    command_burst: int = Field(default=5, ge=1)
    #: Validated commands waiting for the service; further ones are refused while full.
    command_queue_size: int = Field(default=16, ge=1)
    #: The map picture is the largest payload: published at most this often.
    map_rate_hz: float = Field(default=0.2, gt=0.0, le=10.0)

    @model_validator(mode="after")
    def _tls_and_backoff(self) -> "MqttConfig":
        if (self.tls_cert_file is None) != (self.tls_key_file is None):
            raise ValueError("tls_cert_file and tls_key_file must be given together")
        if self.password_file is not None and self.username is None:
            raise ValueError("password_file set but username is missing")
        if self.reconnect_min_s > self.reconnect_max_s:
            raise ValueError(
                f"reconnect_min_s ({self.reconnect_min_s}) must be <= reconnect_max_s "
                f"({self.reconnect_max_s})"
            )
        return self

    @model_validator(mode="after")
    def _no_cleartext_password(self) -> "MqttConfig":
        # A password sent without TLS can be read by anyone on the network path to the broker.
        if self.password_file is not None and not self.use_tls and not _is_loopback(self.host):
            raise ValueError(
                f"password_file set for the remote broker {self.host!r} without TLS: the "
                "password would cross the network in clear text (set tls: true or "
                "tls_ca_file)"
            )
        return self

    @property
    def use_tls(self) -> bool:
        """True if the connection to the broker is made with TLS."""
        return self.tls or any(
            f is not None for f in (self.tls_ca_file, self.tls_cert_file, self.tls_key_file)
        )


class ServiceConfig(StageConfig):
    """The asyncio service as a whole."""

    output_dir: str = "out"
    map_dir: str = "out/map"
    checkpoint_interval_s: float = Field(default=10.0, gt=0.0)
    on_sigterm: Literal["hold", "land"] = "hold"
    #: Where the map's poses come from: ``odometry``, the autopilot's estimate as it is;
    #: ``slam``, the 2D SLAM on the camera's scans (:mod:`companion.service.localization`).
    #: The one switch for that choice (``slam`` holds the SLAM's own parameters).
    localization: Literal["odometry", "slam"] = "odometry"
    #: Frames waiting for perception; the oldest is dropped when full.
    frame_queue_size: int = Field(default=1, ge=1, le=16)
    status_rate_hz: float = Field(default=1.0, gt=0.0)
    telemetry_rate_hz: float = Field(default=5.0, gt=0.0)


class SimConfig(StageConfig):
    """The simulated indoor world (the embedded default's camera and ground truth)."""

    seed: int = 0
    room_width_m: float = Field(default=8.0, ge=3.0, le=50.0)
    room_depth_m: float = Field(default=6.0, ge=3.0, le=50.0)
    wall_height_m: float = Field(default=2.6, ge=2.0, le=6.0)
    n_objects: int = Field(default=8, ge=0, le=60)
    n_doorways: int = Field(default=2, ge=1, le=4)
    #: Room generator: ``realistic`` (furniture in groups as people arrange it: chairs pushed
    #: under tables, desks against walls, clutter; :mod:`companion.sim.layouts`) or
    #: ``scattered`` (each piece alone at a random spot, 0.25 m from the next).
    layout: Literal["realistic", "scattered"] = "realistic"
    #: The simulated D455 (:mod:`companion.sim.d455`, docs/simulation.md); each effect off at 0.
    #: Depth noise: sigma = depth_noise_coeff * z^2 (metres; 0.005 = Intel's 2 % RMS at 4 m).
    depth_noise_coeff: float = Field(default=0.005, ge=0.0)
    #: Fraction of pixels at depth edges invalidated.
    depth_edge_dropout: float = Field(default=0.5, ge=0.0, le=1.0)
    #: Fraction of the remaining edge pixels given a depth between their two surfaces.
    depth_flying_pixels: float = Field(default=0.3, ge=0.0, le=1.0)
    #: Hole probability on black surfaces (falling to 0 at albedo 0.15).
    depth_dark_holes: float = Field(default=0.8, ge=0.0, le=1.0)
    #: Hole probability on shiny surfaces (screens, whiteboards) seen nearly head-on.
    depth_shiny_holes: float = Field(default=0.7, ge=0.0, le=1.0)
    #: Hole probability reached at camera.depth_max_m (growing from 3/4 of it).
    depth_far_dropout: float = Field(default=0.4, ge=0.0, le=1.0)
    #: Disparity in 1/32-pixel steps (depth steps growing with z^2), before z16 millimetres.
    depth_disparity_quantisation: bool = True
    #: Minimum range at an 848-pixel-wide depth image, scaled by the configured width (0: off;
    #: camera.depth_min_m applies either way).
    depth_min_z_m: float = Field(default=0.5, ge=0.0, le=3.0)
    #: Colour auto-exposure (gain follows the view's brightness) and motion blur in fast turns.
    rgb_auto_exposure: bool = True
    rgb_motion_blur: bool = True
    #: Who flies the vehicle the simulated camera rides on: ``mock``, the in-process mock PX4
    #: on the ports below; ``external``, the autopilot on ``link.url`` (PX4 SITL, a real
    #: vehicle on the bench): the camera renders the room from the pose it reports.
    autopilot: Literal["mock", "external"] = "mock"
    #: Mock autopilot UDP ports (PX4 layout).
    autopilot_local_port: int = Field(default=14580, ge=1, le=65535)
    autopilot_offboard_port: int = Field(default=14540, ge=1, le=65535)
    autopilot_gcs_port: int = Field(default=14550, ge=1, le=65535)
    #: The mock autopilot has no GPS: its horizontal position comes only from the companion's
    #: external vision, late and noisy like EKF2's (needs ``service.localization: slam`` and
    #: ``link.external_vision``; :mod:`companion.sim.autopilot.gps_denied`).
    gps_denied: bool = False
    #: The mock autopilot's reported pose drifts (:class:`companion.sim.odometry.OdometryDriftModel`):
    #: what an indoor EKF without GPS reports. Off = it reports the truth.
    odometry_drift: bool = False
    #: Travelled distances read this fraction long.
    odometry_scale_error: float = Field(default=0.03, ge=-0.5, le=0.5)
    #: Reported minus true heading grows at this rate (deg/s).
    odometry_heading_drift_deg_s: float = Field(default=0.5, ge=-10.0, le=10.0)
    #: Random-walk noise per unit of motion (m/sqrt(m), rad/sqrt(rad)).
    odometry_noise_m_per_sqrt_m: float = Field(default=0.005, ge=0.0)
    odometry_noise_rad_per_sqrt_rad: float = Field(default=0.005, ge=0.0)
    #: Fraction of each external-vision innovation the mock's estimator applies (EKF2 fusing
    #: VISION_POSITION_ESTIMATE / ODOMETRY); 0 = vision is recorded, not fused.
    vision_fusion_gain: float = Field(default=0.5, ge=0.0, le=1.0)
    #: How the simulated camera's frames (stamped with ``time.monotonic`` at capture, as a
    #: RealSense stamps them) get their pose: ``telemetry``, they come without one, as a
    #: RealSense delivers them, and the service poses them from the autopilot's MAVLink
    #: telemetry (:mod:`companion.sources.poses`), the drone's own path; ``autopilot``, each
    #: carries the autopilot's estimate at its capture (no link needed: offline tools).
    camera_pose: Literal["autopilot", "telemetry"] = "telemetry"
    #: Mock autopilot home (the local NED / map origin); default = PX4 SITL's home.
    home_lat_deg: float = Field(default=47.397742, ge=-90.0, le=90.0)
    home_lon_deg: float = Field(default=8.545594, ge=-180.0, le=180.0)
    home_alt_m: float = 488.0


class CompanionConfig(StageConfig):
    """Root of the configuration."""

    #: Bumped when a key is renamed or removed, so old files fail with a clear message.
    version: Literal[1] = 1
    classes: list[ClassConfig] = Field(default_factory=default_classes)
    camera: CameraConfig = CameraConfig()
    detector: DetectorConfig = DetectorConfig()
    tracker: TrackerConfig = TrackerConfig()
    geometry: GeometryConfig = GeometryConfig()
    map: MapConfig = MapConfig()
    slam: SlamConfig = SlamConfig()
    planner: PlannerConfig = PlannerConfig()
    link: LinkConfig = LinkConfig()
    mqtt: MqttConfig = MqttConfig()
    service: ServiceConfig = ServiceConfig()
    sim: SimConfig = SimConfig()

    @model_validator(mode="after")
    def _cross_checks(self) -> "CompanionConfig":
        names = [c.name for c in self.classes]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"classes: duplicate class names {dupes}")
        if not names:
            raise ValueError("classes: at least one class is needed")
        for key, value in self.detector.class_map.items():
            for target in [value] if isinstance(value, str) else value:
                if target not in names:
                    raise ValueError(
                        f"detector.class_map[{key!r}] maps to unknown class {target!r} (classes: {names})"
                    )
            if not value:
                raise ValueError(f"detector.class_map[{key!r}] is an empty list")
        for key in self.detector.class_score_thresholds:
            if key not in names:
                raise ValueError(
                    f"detector.class_score_thresholds has unknown class {key!r} (classes: {names})"
                )
        return self

    def class_by_name(self, name: str) -> ClassConfig:
        for c in self.classes:
            if c.name == name:
                return c
        raise KeyError(name)


# --- loading and dumping --------------------------------------------------------------

def _describe(err: dict[str, Any], model: type[StageConfig] | None) -> str:
    """One human sentence for one pydantic error."""
    etype = err.get("type", "")
    ctx = err.get("ctx") or {}
    got = err.get("input")
    got_s = f" (got {got!r})" if not isinstance(got, dict) else ""
    simple = {
        "greater_than": "must be > {gt}",
        "greater_than_equal": "must be >= {ge}",
        "less_than": "must be < {lt}",
        "less_than_equal": "must be <= {le}",
        "string_too_short": "must be at least {min_length} characters",
        "string_pattern_mismatch": "must match {pattern}",
    }
    if etype in simple:
        return simple[etype].format(**ctx) + got_s
    if etype == "literal_error":
        return f"must be one of {ctx.get('expected')}{got_s}"
    if etype == "extra_forbidden":
        allowed = ", ".join(sorted(model.model_fields)) if model is not None else "see docs"
        return f"unknown key (allowed here: {allowed})"
    if etype == "missing":
        return "is required"
    if etype == "value_error":
        msg = str(ctx.get("error", err.get("msg", "")))
        return msg
    return f"{err.get('msg', 'invalid')}{got_s}"


def _model_at(loc: tuple[Any, ...]) -> type[StageConfig] | None:
    """The model class that owns the key at ``loc`` (for listing allowed keys)."""
    model: Any = CompanionConfig
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        field = model.model_fields.get(part) if hasattr(model, "model_fields") else None
        if field is None:
            return None
        ann = field.annotation
        args = getattr(ann, "__args__", ())
        candidates = [ann, *args]
        nxt = next((c for c in candidates if isinstance(c, type) and issubclass(c, StageConfig)), None)
        if nxt is None:
            return None
        model = nxt
    return model if isinstance(model, type) else None


def format_validation_error(exc: ValidationError, source: str) -> str:
    lines = []
    for err in exc.errors():
        loc = tuple(err.get("loc", ()))
        path = ".".join(str(p) for p in loc) or "(root)"
        lines.append(f"{source}: {path}: {_describe(err, _model_at(loc))}")
    return "\n".join(lines)


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> CompanionConfig:
    """Validate a plain dict (as read from YAML). Raises :class:`ConfigError`."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: top level must be a mapping (got {type(data).__name__})")
    try:
        return CompanionConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source)) from exc


class _UniqueKeyLoader(yaml.SafeLoader):
    """A safe YAML loader that refuses a key given twice in one mapping (YAML's last-wins
    would silently drop the first value)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _value in node.value:
            key = self.construct_object(key_node, deep=deep)  # type: ignore[no-untyped-call]
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first at line {seen[key] + 1})",
                    key_node.start_mark)
            seen[key] = key_node.start_mark.line
        return super().construct_mapping(node, deep=deep)


def _read_config_text(p: Path, allow_empty: bool) -> str:
    """The file's text; an empty file or one cut off mid-line is refused unless allowed,
    since it would silently run the built-in defaults (the simulator)."""
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config file: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        line = p.read_bytes()[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{p}: not UTF-8 text: byte 0x{exc.object[exc.start]:02x} at line "
                          f"{line} (offset {exc.start})") from exc
    if allow_empty:
        return text
    if not any(ln.strip() and not ln.lstrip().startswith("#") for ln in text.splitlines()):
        raise ConfigError(f"{p}: the config file is empty: it would run the built-in defaults "
                          "(the simulator); give the keys, or run without --config")
    if not text.endswith("\n"):
        raise ConfigError(f"{p}: the config file does not end with a newline: it looks "
                          "truncated")
    return text


def load_config(path: str | Path | None, *, allow_empty: bool = False) -> CompanionConfig:
    """Read a YAML config file; None gives the embedded default. Raises :class:`ConfigError`.

    ``allow_empty``: accept an empty file (the defaults) or one without a final newline.
    """
    if path is None:
        return CompanionConfig()
    p = Path(path)
    text = _read_config_text(p, allow_empty)
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ConfigError(f"{p}: not valid YAML{where}: {getattr(exc, 'problem', exc)}") from exc
    if data is None:
        data = {}
    cfg = config_from_dict(data, str(p))
    log.debug("loaded config from %s", p)
    return cfg


def dump_config(cfg: CompanionConfig) -> str:
    """The effective config as YAML (round-trips through :func:`load_config`)."""
    data = cfg.model_dump(mode="json")
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


def write_effective_config(cfg: CompanionConfig, out_dir: str | Path) -> Path:
    """Write the effective config into a run's output folder; returns the file path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "effective-config.yaml"
    path.write_text(dump_config(cfg), encoding="utf-8")
    return path
