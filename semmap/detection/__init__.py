"""Object detection: ONNX Runtime YOLOv8/YOLOX detectors and the simulator's oracle.

Both implement :class:`Detector`; :func:`detector_from_config` builds the one the config's
``detector.kind`` names.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Protocol

from semmap.config import DetectorConfig
from semmap.detection.builtin import BUILTIN_MODELS_DIR, resolve_model_path
from semmap.types import Detection, Frame

__all__ = ["BUILTIN_MODELS_DIR", "Detector", "detector_from_config", "resolve_model_path"]


class Detector(Protocol):
    """Anything that turns a frame into detections (original-image pixels, our classes)."""

    def detect_frame(self, frame: Frame) -> list[Detection]:
        """Detections in ``frame``, best score first."""
        ...


def detector_from_config(
    cfg: DetectorConfig,
    class_names: Sequence[str],
    *,
    builtin_dir: str | Path | None = None,
    object_classes: Mapping[int, str] | None = None,
    seed: int = 0,
    real_camera: bool = False,
) -> Detector:
    """The detector ``cfg.kind`` names. ``class_names``: our classes in config order.

    ``real_camera``: the frames come from a real camera (a RealSense or a recording), which
    decides what ``model_path: auto`` loads (:func:`resolve_model_path`). ``builtin_dir`` resolves ``builtin:NAME`` model paths (ONNX; default: the models shipped
    in the package, :data:`BUILTIN_MODELS_DIR`); ``object_classes`` and
    ``seed`` are for the oracle (see :class:`semmap.detection.oracle.OracleDetector`). Raises
    :class:`semmap.errors.PerceptionError` if the ONNX model cannot be used.
    """
    if cfg.kind == "oracle":
        from semmap.detection.oracle import OracleDetector

        return OracleDetector.from_config(cfg, class_names, object_classes=object_classes, seed=seed)
    from semmap.detection.onnx_detector import OnnxDetector

    model_path = resolve_model_path(cfg.model_path, real_camera)
    if model_path != cfg.model_path:
        cfg = cfg.model_copy(update={"model_path": model_path})
    return OnnxDetector.from_config(
        cfg, class_names, builtin_dir=BUILTIN_MODELS_DIR if builtin_dir is None else builtin_dir
    )
