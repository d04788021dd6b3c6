"""Our own MAVLink link to a PX4 autopilot: transports, link, state, commands, offboard.

Modules: :mod:`~companion.mavlink.urls` (connection URLs), :mod:`~companion.mavlink.transport_base`
(the byte channel), :mod:`~companion.mavlink.transport` (UDP/TCP/serial on the event loop),
:mod:`~companion.mavlink.replay` (a telemetry log as a link), :mod:`~companion.mavlink.link` (MavlinkLink, the one
adapter over pymavlink), :mod:`~companion.mavlink.state` (VehicleState from telemetry),
:mod:`~companion.mavlink.commands` (COMMAND_LONG with acks), :mod:`~companion.mavlink.failsafe`
and :mod:`~companion.mavlink.offboard` (setpoint streaming and the failsafe rules),
:mod:`~companion.mavlink.obstacle_distance` (OBSTACLE_DISTANCE from the costmap),
:mod:`~companion.mavlink.mission_download` (reading the autopilot's mission),
:mod:`~companion.mavlink.vision` (our pose to PX4 as external vision),
:mod:`~companion.mavlink.tlog` (record and replay telemetry logs),
:mod:`~companion.mavlink.sched` (a short scheduler slice for the event loop) and
:mod:`~companion.mavlink.vehicle` (all of it as one context manager built from LinkConfig).
"""
