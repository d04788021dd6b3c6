"""The simulated camera: renders the simulated room from the vehicle's current pose."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from companion.errors import SimulationError
from companion.sim.render import RoomRenderer, renderer_from_config
from companion.sim.world import BUILDERS, Room, generate_room
from companion.sources.base import FrameSource
from semmap.types import CameraIntrinsics, Frame

if TYPE_CHECKING:
    from companion.config import CompanionConfig

log = logging.getLogger(__name__)

#: ``() -> (stamp_s, T_map_body (4, 4))``, or None when the flight is over.
PoseProvider = Callable[[], "tuple[float, NDArray[np.float64]] | None"]


def room_from_config(cfg: CompanionConfig) -> Room:
    """The seeded room of ``cfg.sim`` furnished with the configured classes that the
    generator can build (classes without a builder are simply not placed)."""
    s = cfg.sim
    names = [c.name for c in cfg.classes if c.name in BUILDERS]
    return generate_room(
        s.seed, s.room_width_m, s.room_depth_m, s.wall_height_m, s.n_objects, s.n_doorways,
        class_names=names or None, layout=s.layout,
    )


class SimFrameSource(FrameSource):
    """Frames of a simulated room seen by a camera riding on the vehicle.

    ``pose_provider`` gives the vehicle's pose (the mock autopilot's kinematic state or a
    scripted trajectory); the camera pose is ``T_map_body @ T_body_camera``. Frame ``i`` is
    rendered with noise seeded by ``(renderer.seed, i)``, so a replayed flight reproduces
    its frames exactly. ``max_frames`` ends the stream after that many frames.
    """

    def __init__(
        self,
        renderer: RoomRenderer,
        pose_provider: PoseProvider,
        T_body_camera: NDArray[np.float64],
        max_frames: int | None = None,
    ) -> None:
        T = np.asarray(T_body_camera, dtype=np.float64)
        if T.shape != (4, 4):
            raise SimulationError(f"T_body_camera must be (4, 4), got {T.shape}")
        self.renderer = renderer
        self._pose_provider = pose_provider
        self.T_body_camera = T
        self.max_frames = max_frames
        self.frames_read = 0
        self.dropped_frames = 0

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The simulated camera's intrinsics."""
        return self.renderer.intrinsics

    @property
    def room(self) -> Room:
        """The room being rendered (the ground truth)."""
        return self.renderer.room

    def read(self) -> Frame | None:
        """Render the next frame from the provider's current pose; None when the provider
        says the flight is over or ``max_frames`` were delivered."""
        if self.max_frames is not None and self.frames_read >= self.max_frames:
            return None
        state = self._pose_provider()
        if state is None:
            return None
        stamp_s, T_map_body = state
        T_map_camera = np.asarray(T_map_body, dtype=np.float64) @ self.T_body_camera
        frame = self.renderer.render(T_map_camera, stamp_s=stamp_s, index=self.frames_read)
        self.frames_read += 1
        return frame

    @classmethod
    def from_config(
        cls, cfg: CompanionConfig, pose_provider: PoseProvider, room: Room | None = None,
        max_frames: int | None = None,
    ) -> SimFrameSource:
        """The simulated camera of ``cfg``: its room (``room_from_config`` unless given),
        intrinsics, noise and mounting (``cfg.camera.extrinsics``)."""
        room = room if room is not None else room_from_config(cfg)
        return cls(
            renderer_from_config(room, cfg), pose_provider,
            cfg.camera.extrinsics.T_body_camera(), max_frames=max_frames,
        )
