"""The MQTT ground link: wire schema, command validation and the broker bridge."""

from companion.ground.bridge import LinkStats, MqttBridge
from companion.ground.schema import (
    Command,
    GoalCommand,
    MissionCommand,
    Rejection,
    Topics,
    VehicleCommand,
)
from companion.ground.validation import CommandValidator, TokenBucket

__all__ = [
    "Command",
    "CommandValidator",
    "GoalCommand",
    "LinkStats",
    "MissionCommand",
    "MqttBridge",
    "Rejection",
    "Topics",
    "TokenBucket",
    "VehicleCommand",
]
