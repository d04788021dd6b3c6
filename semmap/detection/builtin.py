"""The detector models shipped in the package, named ``builtin:NAME`` in ``detector.model_path``.

Two ship (see their model cards in ``semmap/models/``):

* ``builtin:furniture``: a YOLOv8n trained on our simulated rooms, the six classes of the
  reference design. The simulator's default.
* ``builtin:coco``: a COCO-trained YOLOX-nano (Megvii, Apache-2.0). The default for a real
  camera: it was trained on real photographs, names chairs, sofas and tables, and its one
  ``diningtable`` class is told apart into desk, coffee table or conference table by the
  object map's geometric class prior (:mod:`semmap.class_prior`).

``detector.model_path: auto`` (the default) picks one by camera: :func:`resolve_model_path`.

A shipped model may carry two side files beside ``NAME_*.onnx``: ``<stem>.classes.txt`` (its
class names, one per line, for a model whose ONNX file has no ``names`` metadata) and
``<stem>.classmap.json`` (``{"class_map": {model class: our class or [ours, ...]},
"operating_point": {"score_threshold", "class_score_thresholds", "nms_iou"}}``, used where the
config's ``detector`` keys are empty or null). The config overrides them.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from semmap.config import DetectorConfig
from semmap.errors import PerceptionError

BUILTIN_PREFIX = "builtin:"
#: The models shipped in the package.
BUILTIN_MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
#: ``detector.model_path`` value that picks the shipped model for the camera.
AUTO_MODEL = "auto"
#: What ``auto`` means on a real camera (a RealSense, a recording) and in the simulator.
REAL_CAMERA_MODEL = "builtin:coco"
SIMULATOR_MODEL = "builtin:furniture"


def resolve_model_path(model_path: str | None, real_camera: bool) -> str | None:
    """``model_path`` with ``auto`` replaced by the shipped model for the camera: the COCO
    model for real images, the furniture model (trained on our renders) for the simulator."""
    if model_path != AUTO_MODEL:
        return model_path
    return REAL_CAMERA_MODEL if real_camera else SIMULATOR_MODEL


def builtin_model_file(folder: Path, name: str) -> Path:
    """The file ``builtin:NAME`` names in ``folder``: ``NAME.onnx``, else the only
    ``NAME_*.onnx`` (a shipped model's file name also states its architecture and input size,
    e.g. ``furniture_yolov8n_320.onnx``). A missing file is reported when it is loaded."""
    exact = folder / f"{name}.onnx"
    variants = sorted(folder.glob(f"{name}_*.onnx"))
    return exact if exact.exists() or len(variants) != 1 else variants[0]


#: What a model class maps to: one of our classes, or several it cannot tell apart.
ClassTarget = str | list[str]

#: The operating point of a model that states none.
DEFAULT_SCORE_THRESHOLD = 0.25
DEFAULT_NMS_IOU = 0.6


@dataclass(frozen=True)
class BuiltinDefaults:
    """What a shipped model's side files say: its class names (None: read the ONNX metadata),
    its class map onto our classes (empty: names that already are ours) and its operating
    point (score threshold, per-class thresholds keyed by our classes, NMS IoU)."""

    class_names: list[str] | None = None
    class_map: dict[str, ClassTarget] = field(default_factory=dict)
    score_threshold: float = DEFAULT_SCORE_THRESHOLD
    class_score_thresholds: dict[str, float] = field(default_factory=dict)
    nms_iou: float = DEFAULT_NMS_IOU


def builtin_defaults(model_file: Path) -> BuiltinDefaults:
    """The side files of ``model_file`` (see the module docstring); missing ones give the
    defaults. Raises :class:`PerceptionError` naming a side file that cannot be read."""
    names_file = model_file.with_suffix(".classes.txt")
    map_file = model_file.with_suffix(".classmap.json")
    names = None
    doc: dict[str, Any] = {}
    try:
        if names_file.is_file():
            names = [ln.strip() for ln in names_file.read_text(encoding="utf-8").splitlines() if ln.strip()]
        if map_file.is_file():
            doc = json.loads(map_file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PerceptionError(f"shipped model side file beside {model_file.name}: {exc}") from exc
    if not map_file.is_file():
        return BuiltinDefaults(class_names=names)
    class_map = doc.get("class_map") if isinstance(doc, dict) else None
    op = doc.get("operating_point", {}) if isinstance(doc, dict) else None
    if not isinstance(class_map, dict) or not isinstance(op, dict):
        raise PerceptionError(f"{map_file}: expected {{\"class_map\": {{model class: our class}}, "
                              f"\"operating_point\": {{...}}}}")
    try:
        return BuiltinDefaults(
            class_names=names,
            class_map={str(k): v if isinstance(v, str) else [str(t) for t in v] for k, v in class_map.items()},
            score_threshold=float(op.get("score_threshold", DEFAULT_SCORE_THRESHOLD)),
            class_score_thresholds={str(k): float(v) for k, v in dict(op.get("class_score_thresholds", {})).items()},
            nms_iou=float(op.get("nms_iou", DEFAULT_NMS_IOU)),
        )
    except (TypeError, ValueError) as exc:
        raise PerceptionError(f"{map_file}: operating_point needs numbers for score_threshold, "
                              f"class_score_thresholds and nms_iou ({exc})") from exc


def default_class_map(defaults: BuiltinDefaults, semantic_classes: Sequence[str]) -> dict[str, ClassTarget]:
    """The shipped class map restricted to the configured classes: a deployment that drops a
    class (no sofas here) keeps the rest of the map instead of failing on it."""
    wanted = set(semantic_classes)
    out: dict[str, ClassTarget] = {}
    for k, v in defaults.class_map.items():
        kept = [t for t in ([v] if isinstance(v, str) else v) if t in wanted]
        if kept:
            out[k] = kept[0] if isinstance(v, str) or len(kept) == 1 else kept
    return out


def effective_class_map(
    configured: Mapping[str, ClassTarget], defaults: BuiltinDefaults, semantic_classes: Sequence[str],
) -> dict[str, ClassTarget]:
    """The config's class map if it has one, else the shipped model's."""
    return dict(configured) if configured else default_class_map(defaults, semantic_classes)


def vote_groups(class_map: Mapping[str, ClassTarget]) -> dict[str, tuple[str, ...]]:
    """Reported class -> the classes a detection of it votes for, for the class map's list
    targets (a model class that stands for several of ours; the first is reported)."""
    return {v[0]: tuple(v) for v in class_map.values() if not isinstance(v, str) and len(v) > 1}


def detector_vote_groups(
    cfg: DetectorConfig, semantic_classes: Sequence[str], real_camera: bool,
    builtin_dir: Path = BUILTIN_MODELS_DIR,
) -> dict[str, tuple[str, ...]]:
    """The vote groups of the detector ``cfg`` builds (see :func:`vote_groups`), without
    loading the model: the object map needs them to weigh that detector's class votes."""
    if cfg.kind != "onnx":
        return {}
    model_path = resolve_model_path(cfg.model_path, real_camera)
    defaults = BuiltinDefaults()
    if model_path is not None and model_path.startswith(BUILTIN_PREFIX):
        defaults = builtin_defaults(builtin_model_file(builtin_dir, model_path[len(BUILTIN_PREFIX):]))
    return vote_groups(effective_class_map(cfg.class_map, defaults, semantic_classes))


def effective_operating_point(
    score_threshold: float | None, class_score_thresholds: Mapping[str, float], nms_iou: float | None,
    defaults: BuiltinDefaults, semantic_classes: Sequence[str],
) -> tuple[float, dict[str, float], float]:
    """(score threshold, per-class thresholds, NMS IoU): what the config sets, else the
    shipped model's (per-class thresholds only for configured classes)."""
    if class_score_thresholds:
        per_class = dict(class_score_thresholds)
    else:
        wanted = set(semantic_classes)
        per_class = {k: v for k, v in defaults.class_score_thresholds.items() if k in wanted}
    return (defaults.score_threshold if score_threshold is None else float(score_threshold), per_class,
            defaults.nms_iou if nms_iou is None else float(nms_iou))
