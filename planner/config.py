"""Typed configuration of the planner (see :mod:`semmap.config` for the conventions)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator

from semmap.config import StageConfig
from semmap.costmap import VerticalBand


class PlannerConfig(StageConfig):
    """OMPL planning and trajectory limits for a multicopter at a commanded altitude."""

    moved_keys: ClassVar[dict[str, str]] = {
        "clearance_decay_m": "the map owns how cost decays: use map.clearance_decay_m",
    }

    #: OMPL planner. (PRM* is not offered: it grows its roadmap in a second thread that
    #: would call the Python validity checker while ``solve`` holds the GIL: a deadlock.)
    algorithm: Literal["rrtstar", "informed_rrtstar", "bitstar", "rrtconnect"] = (
        "informed_rrtstar"
    )
    #: Planning time budget of a request, the map's preparation included; the best path
    #: found by then is used.
    time_limit_s: float = Field(default=0.5, gt=0.0, le=60.0)
    #: Budget of a re-plan in flight (the path ahead became blocked by a newly mapped
    #: object), the new map's preparation included: the vehicle is moving towards the
    #: obstacle, so a near-optimal path now beats a slightly shorter one later. The first
    #: path (grid search + any-angle smoothing, within a few percent of the shortest) takes
    #: about 10-20 ms and is always computed; OMPL refines for what is left of this budget.
    #: The first plan of a leg, made while holding, keeps ``time_limit_s``.
    replan_time_limit_s: float = Field(default=0.02, gt=0.0, le=60.0)
    flight_altitude_m: float = Field(default=0.6, gt=0.0, le=20.0)
    vehicle_radius_m: float = Field(default=0.25, gt=0.0, le=5.0)
    #: Kept beyond the vehicle radius from walls and unclassified clutter, which have no class
    #: margin: PX4 flies a few centimetres off its setpoints in corners and gusts, and a
    #: depth-mapped edge can be off by a cell. An object keeps its class margin, or this if
    #: that is smaller.
    tracking_margin_m: float = Field(default=0.05, ge=0.0, le=1.0)
    vehicle_height_m: float = Field(default=0.15, gt=0.0, le=5.0)
    #: Added above and below the vehicle's vertical band when deciding if an object blocks.
    vertical_margin_m: float = Field(default=0.10, ge=0.0)
    #: Cost weight of the probabilistic map relative to path length: the objective is
    #: length + weight * integral of the cell cost (0..1) along the path, in metres. Small by
    #: default: the hard clearance already keeps the vehicle's radius off obstacles; this
    #: only prefers the middle of a passage when that costs little extra length.
    cost_weight: float = Field(default=0.2, ge=0.0)
    #: Unknown cells cost this (0..1) times a lethal cell; 1 forbids them.
    unknown_cost: float = Field(default=0.5, ge=0.0, le=1.0)
    #: Plan through mapped free space, keeping the vehicle's radius off unknown cells too, and
    #: through unknown cells (at ``unknown_cost``) only when no such path exists: the unseen
    #: side of a cabinet is unknown, and a path along it at a small unknown cost runs into it
    #: where the camera cannot see (closer than its minimum depth).
    prefer_known_space: bool = True
    snap_goal_to_free: bool = False
    #: Cell size of the grid search that gives the first path (a multiple of the map's
    #: resolution; coarser is faster, the search falls back to full resolution if the coarse
    #: grid disconnects start and goal).
    search_cell_m: float = Field(default=0.1, gt=0.0, le=1.0)
    #: Spend the rest of the time budget on the OMPL planner to improve the first path.
    refine_with_ompl: bool = True
    #: Corners are taken at a speed whose change of velocity vector is at most this.
    corner_speed_jump_m_s: float = Field(default=0.3, gt=0.0, le=20.0)
    max_speed_m_s: float = Field(default=1.0, gt=0.0, le=20.0)
    max_accel_m_s2: float = Field(default=1.0, gt=0.0, le=20.0)
    #: The last ``final_approach_m`` of each path are flown at no more than
    #: ``final_approach_speed_m_s``: PX4 trails its setpoints and overshoots the end of a path
    #: braked at ``max_accel_m_s2`` by up to half a metre; at a crawl it catches up and stops
    #: on the goal (0 = brake at ``max_accel_m_s2`` all the way).
    final_approach_m: float = Field(default=0.5, ge=0.0, le=5.0)
    final_approach_speed_m_s: float = Field(default=0.3, gt=0.0, le=20.0)
    max_yaw_rate_deg_s: float = Field(default=60.0, gt=0.0, le=720.0)
    #: Starting a path from rest, the vehicle turns on the spot until it heads within this of
    #: the path, so the camera (D455: 87 deg wide) sees where it goes; 180 = set off at once.
    max_heading_error_deg: float = Field(default=30.0, ge=0.0, le=180.0)
    #: Yaw turns are centred this far (metres of path) before their corner, so the camera
    #: looks into a turn before the vehicle takes it (see :mod:`planner.trajectory`).
    yaw_lead_m: float = Field(default=0.6, ge=0.0, le=5.0)
    #: After take-off, before the first leg, the vehicle turns on the spot by this much (as
    #: fast as its autopilot turns) so the camera has seen its surroundings: otherwise the map
    #: around the start holds only the view towards the first goal, and a path that sets
    #: off sideways passes furniture beside or behind the vehicle that no frame has shown.
    #: 0 = no survey.
    takeoff_survey_deg: float = Field(default=360.0, ge=0.0, le=720.0)
    #: Geofence in the map frame: [x_min, y_min, x_max, y_max]; None = the map's extent.
    geofence_xy_m: tuple[float, float, float, float] | None = None
    max_altitude_m: float = Field(default=3.0, gt=0.0)

    @model_validator(mode="after")
    def _altitudes(self) -> "PlannerConfig":
        if self.flight_altitude_m > self.max_altitude_m:
            raise ValueError(
                f"flight_altitude_m ({self.flight_altitude_m}) is above max_altitude_m "
                f"({self.max_altitude_m}): every goal at the flight altitude would be refused"
            )
        return self

    def keepout_m(self, class_margin_m: float = 0.0) -> float:
        """How far the vehicle's centre stays from an obstacle with this class margin (0 for a
        wall or unclassified clutter): the radius plus the margin or the tracking margin."""
        return self.vehicle_radius_m + max(class_margin_m, self.tracking_margin_m)

    def band_at(self, altitude_m: float | None = None) -> VerticalBand:
        """The heights the vehicle occupies at ``altitude_m`` (default: the flight altitude),
        grown by the vertical margin: an object blocks when it reaches into this band."""
        altitude = self.flight_altitude_m if altitude_m is None else float(altitude_m)
        return VerticalBand.for_altitude(altitude, self.vehicle_height_m, self.vertical_margin_m)
