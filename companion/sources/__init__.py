"""Camera sources behind one interface: simulated, recorded folders, live RealSense; and
:class:`FrameStream`, any of them as an asyncio stream that drops old frames for a slow
consumer."""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.sources.base import FrameSource
from companion.sources.realsense import RealSenseFrameSource
from companion.sources.recorded import RecordedFrameSource, load_tum_pair
from companion.sources.sim import PoseProvider, SimFrameSource, room_from_config
from companion.sources.stream import FrameStream
from semmap.errors import ConfigError

if TYPE_CHECKING:
    from companion.config import CompanionConfig
    from companion.sim.world import Room

__all__ = [
    "FrameSource", "FrameStream", "PoseProvider", "RealSenseFrameSource", "RecordedFrameSource",
    "SimFrameSource", "load_tum_pair", "make_frame_source", "room_from_config",
]


def make_frame_source(
    cfg: CompanionConfig, pose_provider: PoseProvider | None = None, room: Room | None = None,
    max_frames: int | None = None,
) -> FrameSource:
    """The camera ``cfg.camera.source`` names.

    ``sim`` needs ``pose_provider`` (the vehicle's pose; the camera rides on it) and renders
    ``room`` (default: the seeded room of ``cfg.sim``). ``recorded`` reads
    ``cfg.camera.recorded_path`` (intrinsics from the folder, else from ``cfg.camera``).
    ``realsense`` opens ``cfg.camera.realsense_serial`` (or the first camera).
    """
    cam = cfg.camera
    if cam.source == "sim":
        if pose_provider is None:
            raise ConfigError("camera.source: 'sim' needs a pose provider (the vehicle's state)")
        return SimFrameSource.from_config(cfg, pose_provider, room=room, max_frames=max_frames)
    if cam.source == "recorded":
        assert cam.recorded_path is not None  # the config validator guarantees it
        return RecordedFrameSource(
            cam.recorded_path, default_intrinsics=cam.intrinsics(), depth_min_m=cam.depth_min_m,
            depth_max_m=cam.depth_max_m, rate_hz=cam.rate_hz,
        )
    return RealSenseFrameSource(
        serial=cam.realsense_serial, width_px=cam.width_px, height_px=cam.height_px,
        rate_hz=cam.rate_hz, depth_min_m=cam.depth_min_m, depth_max_m=cam.depth_max_m,
    )
