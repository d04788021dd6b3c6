"""Cartographer-style 2D SLAM: local scan-to-submap matching and background loop closure.

Modules: :mod:`~semmap.slam.pose2d` (SE(2) maths), :mod:`~semmap.slam.scan2d` (the band scan
in the gravity-aligned frame), :mod:`~semmap.slam.correlative` (real-time and branch-and-bound correlative
matchers), :mod:`~semmap.slam.refine` (least-squares refinement), :mod:`~semmap.slam.submaps`,
:mod:`~semmap.slam.local` (local SLAM), :mod:`~semmap.slam.pose_graph` (SPA),
:mod:`~semmap.slam.global_` (loop closure worker), :mod:`~semmap.slam.slam2d` (``Slam2D``).
"""

from semmap.slam.local import SlamStatus
from semmap.slam.scan2d import level_scan_from_depth
from semmap.slam.slam2d import Slam2D, SlamPose, SlamStats, SubmapView

__all__ = ["Slam2D", "SlamPose", "SlamStats", "SlamStatus", "SubmapView", "level_scan_from_depth"]
