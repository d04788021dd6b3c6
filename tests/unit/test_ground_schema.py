"""The ground link's wire schema and command validation (no broker involved)."""

from __future__ import annotations

import base64
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from pydantic import ValidationError

from companion.config import MqttConfig
from companion.ground.messages import (
    OUTBOUND_MODELS,
    MapMessage,
    decode_cost_png,
    encode,
    encode_cost_png,
    objects_message,
    path_message,
    telemetry_message,
)
from companion.ground.schema import (
    COMMAND_MODELS,
    GoalCommand,
    MissionCommand,
    Rejection,
    Topics,
    VehicleCommand,
    parse_command,
    peek_request_id,
)
from companion.ground.validation import CommandValidator, TokenBucket
from planner.config import PlannerConfig
from semmap.costmap import ObjectFootprint
from semmap.errors import ConfigError

DOC = Path(__file__).resolve().parents[2] / "docs" / "mqtt.md"


def goal(**kw: object) -> bytes:
    data: dict[str, object] = {"schema_version": 1, "request_id": "g-1", "x_m": 1.0, "y_m": 2.0}
    data.update(kw)
    return json.dumps({k: v for k, v in data.items() if v is not ...}).encode()


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


# --- parsing ------------------------------------------------------------------------------

def test_valid_commands_parse_to_typed_values() -> None:
    assert parse_command("goal", goal(altitude_m=1.5, yaw_deg=-90)) == GoalCommand(
        schema_version=1, request_id="g-1", x_m=1.0, y_m=2.0, altitude_m=1.5, yaw_deg=-90.0)
    assert parse_command("mission", b'{"schema_version": 1, "request_id": "m", "action": "abort"}'
                         ) == MissionCommand(schema_version=1, request_id="m", action="abort")
    assert parse_command("vehicle", '{"schema_version": 1, "request_id": "v", "action": "land"}'
                         ) == VehicleCommand(schema_version=1, request_id="v", action="land")


@pytest.mark.parametrize(
    ("kind", "payload", "reason"),
    [
        ("goal", b"{", "goal: not valid JSON"),
        ("goal", b"[1, 2]", "goal: must be a JSON object (got list)"),
        ("goal", goal(y_m=...), "goal.y_m: is required"),
        ("goal", goal(speed=2), "goal.speed: unknown field (allowed: schema_version, request_id"),
        ("goal", goal(x_m="1"), "goal.x_m: must be a number (got '1')"),
        ("goal", goal(x_m=True), "goal.x_m: must be a number (got True)"),
        ("goal", b'{"schema_version": 1, "request_id": "g-1", "x_m": NaN, "y_m": 0}',
         "goal.x_m: must be a finite number"),
        ("goal", goal(altitude_m=0), "goal.altitude_m: must be > 0.0 (got 0)"),
        ("goal", goal(yaw_deg=400), "goal.yaw_deg: must be <= 360"),
        ("goal", goal(schema_version=2), "goal.schema_version: must be one of 1 (got 2)"),
        ("goal", goal(request_id="has space"), "goal.request_id: must match"),
        ("goal", goal(request_id=""), "goal.request_id: must be at least 1 characters"),
        ("mission", b'{"schema_version": 1, "request_id": "m", "action": "fly"}',
         "mission.action: must be one of 'start', 'pause' or 'abort' (got 'fly')"),
        ("vehicle", b'{"schema_version": 1, "request_id": "v"}', "vehicle.action: is required"),
        ("takeoff", b"{}", "unknown command topic cmd/takeoff (known: goal, mission, vehicle)"),
        ("goal", b"{" + b" " * 5000 + b"}", "goal: payload too large (5002 > 4096 bytes)"),
    ],
)
def test_bad_commands_are_rejected_with_the_field_named(kind: str, payload: bytes, reason: str) -> None:
    result = parse_command(kind, payload)
    assert isinstance(result, Rejection)
    assert result.kind == kind
    assert result.reason.startswith(reason), result.reason


def test_a_rejection_echoes_a_readable_request_id() -> None:
    assert parse_command("goal", goal(x_m="nope")).request_id == "g-1"  # type: ignore[union-attr]
    assert parse_command("goal", b"{").request_id is None  # type: ignore[union-attr]
    assert peek_request_id(b'{"request_id": "abc", "junk": 1}') == "abc"
    assert peek_request_id(b'{"request_id": 5}') is None
    assert peek_request_id(b"\xff\x00") is None


@given(st.binary(max_size=300))
@settings(max_examples=200, deadline=None)
def test_arbitrary_bytes_never_raise(payload: bytes) -> None:
    for kind in (*COMMAND_MODELS, "other"):
        assert isinstance(parse_command(kind, payload), (Rejection, *COMMAND_MODELS.values()))


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=8), children, max_size=3),
    max_leaves=10,
)


@given(st.dictionaries(
    st.sampled_from(["schema_version", "request_id", "x_m", "y_m", "altitude_m", "yaw_deg",
                     "action", "extra"]),
    json_values, max_size=7))
@settings(max_examples=200, deadline=None)
def test_arbitrary_json_objects_never_raise(data: dict[str, object]) -> None:
    payload = json.dumps(data)
    for kind in COMMAND_MODELS:
        result = parse_command(kind, payload)
        if isinstance(result, Rejection):
            assert result.reason.startswith(kind)
        else:
            assert math.isfinite(getattr(result, "x_m", 0.0))


# --- limits -------------------------------------------------------------------------------

def test_token_bucket_allows_a_burst_then_the_rate() -> None:
    clock = FakeClock()
    bucket = TokenBucket(rate_hz=2.0, burst=3, clock=clock)
    assert [bucket.try_take() for _ in range(4)] == [True, True, True, False]
    clock.t += 0.5  # one token back
    assert [bucket.try_take() for _ in range(2)] == [True, False]
    clock.t += 100.0  # never more than the burst saved up
    assert [bucket.try_take() for _ in range(4)] == [True, True, True, False]


def test_validator_enforces_fence_altitude_and_rate() -> None:
    clock = FakeClock()
    v = CommandValidator(geofence_xy_m=(0.0, -1.0, 8.0, 6.0), max_altitude_m=3.0,
                         rate_limit_hz=1.0, burst=10, clock=clock)
    assert isinstance(v.validate("goal", goal(x_m=8.0, y_m=-1.0, altitude_m=3.0)), GoalCommand)
    r = v.validate("goal", goal(altitude_m=12))
    assert isinstance(r, Rejection) and r.reason == "goal.altitude_m: must be <= 3.0 (got 12.0)"
    assert r.request_id == "g-1"
    r = v.validate("goal", goal(x_m=-0.1))
    assert isinstance(r, Rejection)
    assert r.reason == "goal.x_m: -0.1 is outside the geofence x in [0.0, 8.0] m"
    r = v.validate("goal", goal(y_m=6.5))
    assert isinstance(r, Rejection) and r.reason.startswith("goal.y_m: 6.5 is outside")
    # Non-goal commands have no position to fence.
    assert isinstance(v.validate("vehicle", b'{"schema_version": 1, "request_id": "v", '
                                            b'"action": "hold"}'), VehicleCommand)
    for _ in range(10):
        v.validate("goal", b"junk")
    r = v.validate("goal", goal(request_id="late"))
    assert isinstance(r, Rejection) and r.reason == "rate limited: more than 1 commands/s (burst 10)"
    assert r.request_id == "late"
    clock.t += 1.0
    assert isinstance(v.validate("goal", goal()), GoalCommand)


def test_without_a_configured_fence_the_map_extent_is_used() -> None:
    v = CommandValidator.from_config(PlannerConfig(), MqttConfig())
    assert v.max_altitude_m == PlannerConfig().max_altitude_m
    r = v.validate("goal", goal())
    assert isinstance(r, Rejection) and "no geofence configured and no map extent" in r.reason
    v.set_map_extent((-2.0, -2.0, 2.0, 2.0))
    assert isinstance(v.validate("goal", goal(x_m=1.0, y_m=2.0)), GoalCommand)
    r = v.validate("goal", goal(x_m=3.0))
    assert isinstance(r, Rejection) and "[-2.0, 2.0]" in r.reason
    v2 = CommandValidator.from_config(PlannerConfig(geofence_xy_m=(0, 0, 1, 1)), MqttConfig())
    v2.set_map_extent((-50.0, -50.0, 50.0, 50.0))  # the configured fence wins
    assert isinstance(v2.validate("goal", goal(x_m=1.0, y_m=2.0)), Rejection)


def test_an_inverted_fence_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"planner.geofence_xy_m: must be \[x_min"):
        CommandValidator.from_config(PlannerConfig(geofence_xy_m=(5, 0, 1, 1)), MqttConfig())


# --- topics and outbound messages ---------------------------------------------------------

def test_topics_live_under_prefix_and_vehicle() -> None:
    t = Topics("fleet/site-a/", "drone7")
    assert t.status == "fleet/site-a/drone7/status"
    assert t.command_filter == "fleet/site-a/drone7/cmd/+"
    assert t.command_kind("fleet/site-a/drone7/cmd/goal") == "goal"
    assert t.command_kind("fleet/site-a/drone8/cmd/goal") is None
    assert t.command_kind("fleet/site-a/drone7/cmd/goal/x") is None
    assert t.command_kind("fleet/site-a/drone7/status") is None


@given(arrays(np.uint8, st.tuples(st.integers(1, 40), st.integers(1, 40))))
@settings(max_examples=50, deadline=None)
def test_cost_png_round_trips_exactly(cost: np.ndarray) -> None:
    png = encode_cost_png(cost)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    np.testing.assert_array_equal(decode_cost_png(png), cost)


def test_png_is_north_up() -> None:
    import cv2

    cost = np.zeros((3, 2), np.uint8)
    cost[0, 0] = 254  # the south-west cell
    picture = cv2.imdecode(np.frombuffer(encode_cost_png(cost), np.uint8), cv2.IMREAD_UNCHANGED)
    assert picture[2, 0] == 254 and picture.sum() == 254  # bottom-left pixel


def test_builders_round_and_reject_non_finite_values() -> None:
    tel = telemetry_message("d", np.array([1.23456, 2.0, 0.6]), [0, 0, 0], math.pi, True, True, "HOLD")
    assert tel.xyz_map_m == (1.235, 2.0, 0.6) and tel.yaw_deg == 180.0
    with pytest.raises(ValidationError):
        telemetry_message("d", [math.nan, 0, 0], [0, 0, 0], 0.0, True, True, "HOLD")
    p = path_message("d", np.array([[0, 0, 1], [3, 4, 1], [3, 4, 2]], float))
    assert p.length_m == 6.0 and len(p.waypoints_xyz_map_m) == 3
    assert path_message("d", np.zeros((0, 3))).waypoints_xyz_map_m == []
    with pytest.raises(ValueError, match="waypoints_xyz_map_m must be finite"):
        path_message("d", [[0, 0, math.inf]])
    fps = [ObjectFootprint(k, "chair", np.array([[0.0, 0.0], [0.5, 0.0], [0.5, 0.5]]), 0.0, 0.9, margin_m=0.2)
           for k in (7, 2)]
    assert [o.object_id for o in objects_message("d", fps).objects] == [2, 7]


# --- the documentation --------------------------------------------------------------------

def doc_examples() -> dict[str, str]:
    text = DOC.read_text(encoding="utf-8")
    return dict(re.findall(r"<!-- example: (\w+) -->\s*```json\n(.*?)```", text, re.S))


def test_every_message_and_command_has_a_valid_example_in_the_docs() -> None:
    examples = doc_examples()
    assert set(examples) == set(OUTBOUND_MODELS) | set(COMMAND_MODELS)
    for name, body in examples.items():
        if name in COMMAND_MODELS:
            assert not isinstance(parse_command(name, body), Rejection), name
        else:
            msg = OUTBOUND_MODELS[name].model_validate_json(body)
            assert json.loads(encode(msg)) == json.loads(body), name  # nothing defaulted away
    m = MapMessage.model_validate_json(examples["map"])
    grid = decode_cost_png(base64.b64decode(m.png_base64))
    assert grid.shape == (m.height_px, m.width_px)
