"""YOLOv8 / YOLOX object detection with ONNX Runtime.

Everything that can be wrong with a model is found when the detector is built, not at the
first frame in flight: the file, its protobuf, the input layout, the execution providers, the
output layout (one warm-up inference checks the real output shape) and the class map. Each
failure is a :class:`PerceptionError` that names the model file and the problem.

Per frame, :meth:`OnnxDetector.detect` = :meth:`preprocess` (letterbox) + :meth:`infer`
(ONNX Runtime) + :meth:`postprocess` (decode, per-class thresholds, class-aware NMS, back to
original-image pixels). The three are public so benchmarks can time them separately.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort
from numpy.typing import NDArray

from semmap.config import DetectorConfig
from semmap.detection.builtin import (
    BUILTIN_PREFIX,
    BuiltinDefaults,
    builtin_defaults,
    builtin_model_file,
    effective_class_map,
    effective_operating_point,
)
from semmap.detection.classmap import ClassMap, parse_names_metadata
from semmap.detection.decode import (
    Candidates,
    HeadKind,
    YoloxDecoder,
    check_head,
    decode_yolov8,
    recognise_head,
)
from semmap.detection.letterbox import LetterboxTransform, letterbox
from semmap.detection.nms import nms_class_aware
from semmap.errors import PerceptionError
from semmap.types import Detection, Frame

log = logging.getLogger(__name__)

_GRAPH_OPT = {
    "disable": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
    "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
    "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
}

_INPUT_DTYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16}


def select_providers(preferred: Sequence[str], available: Sequence[str] | None = None) -> list[str]:
    """The preferred execution providers this ONNX Runtime build has, in preference order.

    Raises :class:`PerceptionError` naming both lists if none is available.
    """
    have = list(ort.get_available_providers() if available is None else available)
    chosen = [p for p in preferred if p in have]
    skipped = [p for p in preferred if p not in have]
    if skipped:
        log.info("ONNX Runtime providers not available here, skipped: %s", ", ".join(skipped))
    if not chosen:
        raise PerceptionError(
            f"none of detector.providers {list(preferred)} is available in this ONNX Runtime "
            f"build (available: {have})"
        )
    return chosen


def _provider_entries(
    providers: Sequence[str], trt_fp16: bool, trt_cache_dir: str | None
) -> list[Any]:
    """Provider list for InferenceSession, with TensorRT's engine cache and precision set."""
    out: list[Any] = []
    for p in providers:
        if p == "TensorrtExecutionProvider":
            opts: dict[str, Any] = {"trt_fp16_enable": trt_fp16}
            if trt_cache_dir:
                # Building a TensorRT engine takes minutes on a Jetson; cache it across runs.
                opts.update(trt_engine_cache_enable=True, trt_engine_cache_path=trt_cache_dir)
            out.append((p, opts))
        else:
            out.append(p)
    return out


def _static_dim(dim: Any) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


def _load_session(
    path: Path, providers: list[str], intra_op_threads: int, graph_optimization: str,
    trt_fp16: bool, trt_cache_dir: str | None,
) -> ort.InferenceSession:
    """An ONNX Runtime session for the model at ``path`` on ``providers``, one inter-op
    thread, or a :class:`PerceptionError` naming the file."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = int(intra_op_threads)
    so.inter_op_num_threads = 1
    so.graph_optimization_level = _GRAPH_OPT[graph_optimization]
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(
            str(path), sess_options=so, providers=_provider_entries(providers, trt_fp16, trt_cache_dir),
        )
    # ONNX Runtime's pybind exceptions (InvalidProtobuf, Fail, NoSuchFile, ...) derive
    # straight from Exception, so this boundary has to catch that.
    except Exception as exc:
        raise PerceptionError(f"detector model {path}: ONNX Runtime cannot load it: {exc}") from exc


def _class_thresholds(
    semantic_classes: list[str], score_threshold: float, class_score_thresholds: Mapping[str, float] | None
) -> NDArray[np.float32]:
    """(S,) score threshold per semantic class: its own if given, else ``score_threshold``."""
    thresholds = dict(class_score_thresholds or {})
    unknown = sorted(set(thresholds) - set(semantic_classes))
    if unknown:
        raise PerceptionError(
            f"detector.class_score_thresholds has unknown classes {unknown} "
            f"(classes: {semantic_classes})"
        )
    return np.array([thresholds.get(n, score_threshold) for n in semantic_classes], dtype=np.float32)


class OnnxDetector:
    """A YOLOv8- or YOLOX-head detector behind ONNX Runtime, reporting our semantic classes."""

    def __init__(
        self,
        model_path: str | Path,
        semantic_classes: Sequence[str],
        *,
        head: str = "auto",
        input_size_px: int = 320,
        model_class_names: Sequence[str] | None = None,
        class_map: Mapping[str, str | list[str]] | None = None,
        score_threshold: float = 0.25,
        class_score_thresholds: Mapping[str, float] | None = None,
        nms_iou: float = 0.6,
        max_detections: int = 100,
        providers: Sequence[str] = ("CPUExecutionProvider",),
        intra_op_threads: int = 1,
        graph_optimization: str = "all",
        yolox_predecoded: bool = False,
        trt_fp16: bool = True,
        trt_cache_dir: str | None = None,
    ) -> None:
        """Load and check the model. See :class:`semmap.config.DetectorConfig` for the options.

        ``input_size_px`` is used only when the model's input size is dynamic. Raises
        :class:`PerceptionError` for any problem with the file, providers, layout or classes.
        """
        path = Path(model_path)
        self.model_path = path
        if not path.is_file():
            raise PerceptionError(f"detector model {path}: file not found")
        if graph_optimization not in _GRAPH_OPT:
            raise PerceptionError(
                f"graph_optimization must be one of {sorted(_GRAPH_OPT)} (got {graph_optimization!r})"
            )
        self.providers = select_providers(providers)
        self._session = _load_session(path, self.providers, intra_op_threads, graph_optimization,
                                      trt_fp16, trt_cache_dir)
        log.info("detector %s on %s", path.name, ", ".join(self._session.get_providers()))
        self._adopt_input(input_size_px)
        names = list(model_class_names) if model_class_names is not None else self._metadata_names()
        self.head, n_cls = self._recognise_head(head, names)
        if not names:
            # No names anywhere: class ids as strings, so a class map keyed by id still works.
            names = [str(i) for i in range(n_cls)]
        self.class_map = ClassMap(names, semantic_classes, class_map)
        self.semantic_classes = list(semantic_classes)
        self._yolox = YoloxDecoder(self.input_hw_px, yolox_predecoded) if self.head == "yolox" else None
        #: (S,) score threshold per semantic class.
        self._thresholds = _class_thresholds(self.semantic_classes, score_threshold, class_score_thresholds)
        self._score_floor = float(self._thresholds.min())
        self.nms_iou = float(nms_iou)
        self.max_detections = int(max_detections)
        log.info(
            "detector %s: %s head, %dx%d input, %d model classes, %d mapped",
            path.name, self.head, self.input_hw_px[1], self.input_hw_px[0], n_cls,
            int(self.class_map.wanted_mask.sum()),
        )

    def _adopt_input(self, input_size_px: int) -> None:
        """Check the model's single [1, 3, H, W] float input and take its name, dtype and size
        (``input_size_px`` square when the size is dynamic), and the first output's name."""
        path = self.model_path
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise PerceptionError(f"detector model {path}: expected 1 input, it has {len(inputs)}")
        shape = list(inputs[0].shape)
        if len(shape) != 4 or _static_dim(shape[1]) not in (None, 3):
            raise PerceptionError(
                f"detector model {path}: input {inputs[0].name!r} has shape {shape}; expected "
                f"[1, 3, H, W]"
            )
        if inputs[0].type not in _INPUT_DTYPES:
            raise PerceptionError(
                f"detector model {path}: input type {inputs[0].type}; expected tensor(float) "
                f"or tensor(float16)"
            )
        #: fp16 exports (Ultralytics ``half=True``) take a half-precision tensor.
        self._input_dtype = _INPUT_DTYPES[inputs[0].type]
        h_s, w_s = _static_dim(shape[2]), _static_dim(shape[3])
        if h_s is not None and w_s is not None:
            self.input_hw_px: tuple[int, int] = (h_s, w_s)
            if (h_s, w_s) != (input_size_px, input_size_px):
                log.info("detector %s has a fixed %dx%d input; input_size_px=%d ignored",
                         path.name, w_s, h_s, input_size_px)
        else:
            self.input_hw_px = (input_size_px, input_size_px)
        if self.input_hw_px[0] % 32 or self.input_hw_px[1] % 32:
            raise PerceptionError(
                f"detector model {path}: input size {self.input_hw_px[1]}x{self.input_hw_px[0]} "
                f"is not a multiple of 32 (the largest stride)"
            )
        self._input_name = inputs[0].name
        self._output_name = self._session.get_outputs()[0].name

    def _recognise_head(self, head: str, names: list[str] | None) -> tuple[HeadKind, int]:
        """The head kind (``head``, or recognised when ``auto``) and the model's class count,
        checked against a warm-up inference's output shape."""
        out_shape = self._probe_output_shape()
        if head == "auto":
            return recognise_head(out_shape, self.input_hw_px, len(names) if names else None)
        if head in ("yolov8", "yolox"):
            kind: HeadKind = head  # type: ignore[assignment]
            return kind, check_head(kind, out_shape, len(names) if names else None)
        raise PerceptionError(f"detector.head must be auto, yolov8 or yolox (got {head!r})")

    @classmethod
    def from_config(
        cls,
        cfg: DetectorConfig,
        semantic_classes: Sequence[str],
        builtin_dir: str | Path | None = None,
    ) -> OnnxDetector:
        """Build from :class:`DetectorConfig` (``model_path`` already resolved from ``auto``,
        see :func:`semmap.detection.builtin.resolve_model_path`). ``builtin:NAME`` resolves in
        ``builtin_dir`` (see :func:`builtin_model_file`), with the class names and class map
        its side files give where the config gives none."""
        if cfg.model_path is None:
            raise PerceptionError("detector.kind is 'onnx' but detector.model_path is not set")
        path = Path(cfg.model_path)
        defaults = BuiltinDefaults()
        if cfg.model_path.startswith(BUILTIN_PREFIX):
            name = cfg.model_path[len(BUILTIN_PREFIX):]
            if builtin_dir is None:
                raise PerceptionError(f"detector.model_path {cfg.model_path!r}: no built-in model folder given")
            path = builtin_model_file(Path(builtin_dir), name)
            defaults = builtin_defaults(path)
        score, per_class, nms_iou = effective_operating_point(
            cfg.score_threshold, cfg.class_score_thresholds, cfg.nms_iou, defaults, semantic_classes)
        return cls(
            path,
            semantic_classes,
            head=cfg.head,
            input_size_px=cfg.input_size_px,
            model_class_names=cfg.model_class_names if cfg.model_class_names is not None else defaults.class_names,
            class_map=effective_class_map(cfg.class_map, defaults, semantic_classes),
            score_threshold=score,
            class_score_thresholds=per_class,
            nms_iou=nms_iou,
            max_detections=cfg.max_detections,
            providers=cfg.providers,
            intra_op_threads=cfg.intra_op_threads,
            graph_optimization=cfg.graph_optimization,
            yolox_predecoded=cfg.yolox_predecoded,
            trt_fp16=cfg.trt_fp16,
            trt_cache_dir=cfg.trt_cache_dir,
        )

    # --- start-up checks -------------------------------------------------------------

    def _metadata_names(self) -> list[str] | None:
        meta = self._session.get_modelmeta().custom_metadata_map
        text = meta.get("names")
        return parse_names_metadata(text) if text else None

    def _probe_output_shape(self) -> tuple[int, ...]:
        """Run one inference on a grey image: checks the graph runs and gives the real shape."""
        h, w = self.input_hw_px
        probe = np.full((1, 3, h, w), 0.5, dtype=self._input_dtype)
        try:
            out = self._session.run([self._output_name], {self._input_name: probe})[0]
        except Exception as exc:  # ONNX Runtime exceptions derive from Exception only
            raise PerceptionError(
                f"detector model {self.model_path}: warm-up inference at {w}x{h} failed: {exc}"
            ) from exc
        return tuple(int(d) for d in np.shape(out))

    # --- per frame -------------------------------------------------------------------

    def preprocess(self, image_rgb: NDArray[np.uint8]) -> tuple[NDArray[np.float32], LetterboxTransform]:
        """(H, W, 3) uint8 RGB -> network tensor (1, 3, H_in, W_in) and the inverse transform."""
        return letterbox(image_rgb, self.input_hw_px, self.head)

    def infer(self, tensor: NDArray[np.float32]) -> NDArray[np.float32]:
        """Run the network; returns its raw output (see :mod:`semmap.detection.decode`)."""
        if tensor.dtype != self._input_dtype:
            tensor = tensor.astype(self._input_dtype)
        try:
            out = self._session.run([self._output_name], {self._input_name: tensor})[0]
        except Exception as exc:  # ONNX Runtime exceptions derive from Exception only
            raise PerceptionError(f"detector inference failed: {exc}") from exc
        return np.asarray(out, dtype=np.float32)

    def decode(self, raw: NDArray[np.float32]) -> Candidates:
        """Raw output -> candidates above the lowest class threshold (network-input pixels)."""
        mask = self.class_map.wanted_mask
        if self._yolox is not None:
            return self._yolox(raw, self._score_floor, mask)
        return decode_yolov8(raw, self._score_floor, mask)

    def postprocess(self, raw: NDArray[np.float32], transform: LetterboxTransform) -> list[Detection]:
        """Decode, apply per-class thresholds and class-aware NMS, map to original pixels."""
        cand = self.decode(raw)
        sem = self.class_map.semantic_ids(cand.class_ids)
        keep = cand.scores >= self._thresholds[sem]
        boxes, scores, sem = cand.xyxy_in_px[keep], cand.scores[keep], sem[keep]
        idx = nms_class_aware(boxes, scores, sem, self.nms_iou, self.max_detections)
        orig = transform.boxes_to_original(boxes[idx])
        dets = []
        for (u0, v0, u1, v1), s, c in zip(orig.tolist(), scores[idx].tolist(), sem[idx].tolist(), strict=True):
            if u1 - u0 < 1.0 or v1 - v0 < 1.0:
                continue  # entirely in the padding
            dets.append(Detection((u0, v0, u1, v1), float(s), self.semantic_classes[c]))
        return dets

    def detect(self, image_rgb: NDArray[np.uint8]) -> list[Detection]:
        """Detections in ``image_rgb`` ((H, W, 3) uint8 RGB), boxes in its pixels, best first."""
        tensor, transform = self.preprocess(image_rgb)
        return self.postprocess(self.infer(tensor), transform)

    def detect_frame(self, frame: Frame) -> list[Detection]:
        """Detections in ``frame.rgb`` (the :class:`semmap.detection.Detector` interface)."""
        return self.detect(frame.rgb)
