"""A SITL-free PX4 stand-in: MAVLink over UDP, a kinematic multicopter and fault hooks.

``MockAutopilot`` (in :mod:`.mock`) is what tests and ``companion sim-autopilot`` run; the
pieces are one module each: :mod:`.vehicle` (kinematic model), :mod:`.navigator` (auto
modes), :mod:`.commands` (command protocol), :mod:`.mission_server` (mission protocol),
:mod:`.params` (parameters), :mod:`.offboard` (setpoint interpretation), :mod:`.telemetry`
(streamed messages), :mod:`.transport` (UDP and link faults). PX4 mode numbers live in :mod:`companion.px4`.
"""

from companion.sim.autopilot.mock import MockAutopilot, VisionSample
from companion.sim.autopilot.transport import Faults

__all__ = ["Faults", "MockAutopilot", "VisionSample"]
