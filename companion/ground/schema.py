"""Wire format of the MQTT ground link: topics and inbound commands.

Every payload is a JSON object with ``"schema_version": 1``; ``docs/mqtt.md`` documents each
one with an example (a test keeps those examples valid against these models). Positions are
in the map frame (ENU: x east, y north, z up, metres; see :mod:`semmap.frames`); times are
Unix seconds (``stamp_s``) so a ground station can compare them with its own clock.

The outbound messages are :mod:`companion.ground.messages`.

Inbound commands are parsed strictly (no string-to-number coercion, no NaN or infinity, no
unknown fields); :func:`parse_command` returns either a typed command or a
:class:`Rejection` whose reason names the field, e.g.
``goal.altitude_m: must be > 0 (got -1.0)``. Limits that depend on the configuration
(geofence, altitude ceiling, rate) are checked by :mod:`companion.ground.validation`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

#: Bumped when a field is renamed or removed or its meaning changes.
SCHEMA_VERSION = 1
#: Larger command payloads are refused before parsing.
MAX_COMMAND_BYTES = 4096
#: Commands are flat objects; deeper nesting is refused before parsing.
MAX_JSON_DEPTH = 8


# --- topics -----------------------------------------------------------------------------

#: Command kinds, each received on ``<base>/cmd/<kind>``.
COMMAND_KINDS: tuple[str, ...] = ("goal", "mission", "vehicle")


@dataclass(frozen=True)
class Topics:
    """The topic names of one vehicle: everything lives under ``<prefix>/<vehicle_id>/``."""

    prefix: str
    vehicle_id: str

    @property
    def base(self) -> str:
        return f"{self.prefix.strip('/')}/{self.vehicle_id}"

    @property
    def status(self) -> str:
        return f"{self.base}/status"

    @property
    def telemetry(self) -> str:
        return f"{self.base}/telemetry"

    @property
    def objects(self) -> str:
        return f"{self.base}/objects"

    @property
    def map(self) -> str:
        return f"{self.base}/map"

    @property
    def path(self) -> str:
        return f"{self.base}/path"

    @property
    def reply(self) -> str:
        return f"{self.base}/reply"

    @property
    def online(self) -> str:
        return f"{self.base}/online"

    @property
    def command_filter(self) -> str:
        """The subscription that receives every command kind."""
        return f"{self.base}/cmd/+"

    def command(self, kind: str) -> str:
        """Topic on which commands of ``kind`` (goal, mission, vehicle) arrive."""
        return f"{self.base}/cmd/{kind}"

    def command_kind(self, topic: str) -> str | None:
        """The command kind of a topic under this vehicle's ``cmd/``; None for other topics."""
        head = f"{self.base}/cmd/"
        if not topic.startswith(head):
            return None
        kind = topic[len(head):]
        return kind if kind and "/" not in kind else None


# --- inbound commands -------------------------------------------------------------------

_REQUEST_ID = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:-]+$")


class _Command(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    schema_version: Literal[1]
    #: Chosen by the ground station; echoed in the reply so it can match answers.
    request_id: str = _REQUEST_ID


class GoalCommand(_Command):
    """Fly to a point of the map frame (ENU metres). Topic ``cmd/goal``."""

    x_m: float
    y_m: float
    #: Height above the floor; None = the planner's ``flight_altitude_m``.
    altitude_m: float | None = Field(default=None, gt=0.0)
    #: Heading at the goal, degrees counter-clockwise from east (map frame); None = keep.
    yaw_deg: float | None = Field(default=None, ge=-360.0, le=360.0)


class MissionCommand(_Command):
    """Start (or resume after a pause), pause or abort the mission. Topic ``cmd/mission``."""

    action: Literal["start", "pause", "abort"]


class VehicleCommand(_Command):
    """Hold position or land now. Topic ``cmd/vehicle``."""

    action: Literal["hold", "land"]


Command = GoalCommand | MissionCommand | VehicleCommand

COMMAND_MODELS: dict[str, type[_Command]] = {
    "goal": GoalCommand,
    "mission": MissionCommand,
    "vehicle": VehicleCommand,
}


def command_kind_of(cmd: Command) -> str:
    """The kind (``goal``, ``mission``, ``vehicle``) of a parsed command."""
    for kind, model in COMMAND_MODELS.items():
        if isinstance(cmd, model):
            return kind
    raise TypeError(f"not a ground command: {type(cmd).__name__}")


@dataclass(frozen=True)
class Rejection:
    """A command that never reaches the vehicle, with the reason sent back to the sender.

    ``request_id`` is the sender's id when it could be read from the payload, else None.
    """

    kind: str
    reason: str
    request_id: str | None = None


def _describe(err: Mapping[str, Any], model: type[BaseModel]) -> str:
    """One sentence for one pydantic error (the field path is added by the caller)."""
    etype = err.get("type", "")
    ctx = err.get("ctx") or {}
    got = err.get("input")
    got_s = "" if isinstance(got, (dict, list)) else f" (got {got!r})"
    bounds = {
        "greater_than": "must be > {gt}",
        "greater_than_equal": "must be >= {ge}",
        "less_than": "must be < {lt}",
        "less_than_equal": "must be <= {le}",
        "string_too_short": "must be at least {min_length} characters",
        "string_too_long": "must be at most {max_length} characters",
        "string_pattern_mismatch": "must match {pattern}",
    }
    if etype in bounds:
        return bounds[etype].format(**ctx) + got_s
    if etype == "missing":
        return "is required"
    if etype == "extra_forbidden":
        return f"unknown field (allowed: {', '.join(model.model_fields)})"
    if etype == "literal_error":
        return f"must be one of {ctx.get('expected')}{got_s}"
    if etype == "finite_number":
        return f"must be a finite number{got_s}"
    if etype in ("float_type", "int_type", "float_parsing"):
        return f"must be a number{got_s}"
    if etype == "string_type":
        return f"must be a string{got_s}"
    if etype in ("model_type", "dict_type"):
        return "must be a JSON object"
    return f"{err.get('msg', 'invalid')}{got_s}"


def describe_validation_error(exc: ValidationError, kind: str, model: type[BaseModel]) -> str:
    """All errors of ``exc`` as ``<kind>.<field>: <what is wrong>``, joined by ``; ``."""
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in (kind, *err.get("loc", ())))
        parts.append(f"{loc}: {_describe(err, model)}")
    return "; ".join(parts)


def _request_id_of(data: Mapping[str, Any]) -> str | None:
    rid = data.get("request_id")
    return rid if isinstance(rid, str) and 0 < len(rid) <= 64 else None


class PayloadError(ValueError):
    """A command payload that is not one strict JSON document (the message says why)."""


def _max_depth(text: str) -> int:
    """How deeply ``[``/``{`` nest in a JSON text, brackets inside strings not counted."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise PayloadError(f"duplicate key {key!r}")
        out[key] = value
    return out


def decode_payload(payload: bytes | bytearray | str) -> Any:
    """The JSON document in ``payload``: UTF-8, no duplicate keys, nested at most
    ``MAX_JSON_DEPTH`` deep. Raises :class:`PayloadError` saying what is wrong."""
    if isinstance(payload, (bytes, bytearray)):
        try:
            text = bytes(payload).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise PayloadError(f"not valid UTF-8 (byte 0x{payload[exc.start]:02x} at offset "
                               f"{exc.start})") from exc
    else:
        text = payload
    if _max_depth(text) > MAX_JSON_DEPTH:
        raise PayloadError(f"JSON nested more than {MAX_JSON_DEPTH} levels deep")
    try:
        return json.loads(text, object_pairs_hook=_no_duplicate_keys)
    except json.JSONDecodeError as exc:
        raise PayloadError(f"not valid JSON ({exc})") from exc
    except RecursionError as exc:  # unreachable after the depth check; never let it escape
        raise PayloadError("JSON nested too deeply") from exc


def peek_request_id(payload: bytes | bytearray | str) -> str | None:
    """The ``request_id`` of a payload, if it is readable, without validating the rest."""
    if len(payload) > MAX_COMMAND_BYTES:
        return None
    try:
        data = decode_payload(payload)
    except PayloadError:
        return None
    return _request_id_of(data) if isinstance(data, dict) else None


def parse_command(kind: str, payload: bytes | bytearray | str) -> Command | Rejection:
    """Parse one command payload received on ``cmd/<kind>``.

    Returns the typed command, or a :class:`Rejection` naming what is wrong. Never raises on
    bad input: malformed payloads are the sender's problem, not the service's.
    """
    model = COMMAND_MODELS.get(kind)
    if model is None:
        return Rejection(kind, f"unknown command topic cmd/{kind} (known: {', '.join(COMMAND_KINDS)})")
    if len(payload) > MAX_COMMAND_BYTES:
        return Rejection(kind, f"{kind}: payload too large ({len(payload)} > {MAX_COMMAND_BYTES} bytes)")
    try:
        data = decode_payload(payload)
    except PayloadError as exc:
        return Rejection(kind, f"{kind}: {exc}")
    if not isinstance(data, dict):
        return Rejection(kind, f"{kind}: must be a JSON object (got {type(data).__name__})")
    request_id = _request_id_of(data)
    try:
        return model.model_validate(data)  # type: ignore[return-value]
    except ValidationError as exc:
        return Rejection(kind, describe_validation_error(exc, kind, model), request_id)
