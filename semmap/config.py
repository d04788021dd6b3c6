"""Typed configuration of the perception and mapping stages.

One frozen pydantic model per stage; unknown keys are rejected. The root model that composes
them and reads YAML lives in :mod:`companion.config` (``semmap`` does no I/O). Components take
plain values; the ``from_config`` factories next to them take these models.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from semmap.costmap import DEFAULT_CLEARANCE_DECAY_M
from semmap.frames import R_BODY_CAMERA_FORWARD, make_transform, rotation_from_rpy
from semmap.types import CameraIntrinsics


def _is_number_type(annotation: object) -> bool:
    """True for ``float``/``int`` annotations, optional ones included (``bool`` excluded)."""
    if annotation in (float, int):
        return True
    args = getattr(annotation, "__args__", ())
    return bool(args) and type(None) in args and all(a in (float, int, type(None)) for a in args)


class StageConfig(BaseModel):
    """Base of every config model: frozen, unknown keys are an error, numbers are finite
    and ``true``/``false`` are not numbers."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)
    #: Keys this model no longer takes, each with where its setting went: an old file fails
    #: naming the replacement instead of "unknown key".
    moved_keys: ClassVar[dict[str, str]] = {}

    @model_validator(mode="before")
    @classmethod
    def _no_moved_keys(cls, data: object) -> object:
        if isinstance(data, dict):
            for name, instead in cls.moved_keys.items():
                if name in data:
                    raise ValueError(f"{name} is not a key here (got {data[name]!r}): {instead}")
        return data

    @model_validator(mode="before")
    @classmethod
    def _no_bool_numbers(cls, data: object) -> object:
        # pydantic reads YAML's `true` as 1.0 for a float field: a typo must not become a size.
        if isinstance(data, dict):
            for name, field in cls.model_fields.items():
                value = data.get(name)
                if isinstance(value, bool) and _is_number_type(field.annotation):
                    raise ValueError(f"{name}: must be a number (got {str(value).lower()})")
        return data


HollowKind = Literal["full", "partial", "none"]
#: What an object of a class looks like in depth, for separating it from what touches it
#: (:mod:`semmap.shape_prior`): ``table`` (its top is its highest large horizontal surface),
#: ``seat`` (a seat with a back above, never a large surface at table height), ``free``.
ShapeKind = Literal["table", "seat", "free"]


class GeometricPrior(StageConfig):
    """What an object of a class measures (metres; null: no constraint): the height of its top
    above the floor (its top plane where one is found: a table top, a chair seat; else its
    highest point), and its footprint's long and short side. The object map weighs detector
    class votes by how well the measured object fits (see :mod:`semmap.class_prior`)."""

    height_m: tuple[float, float] | None = None
    footprint_long_m: tuple[float, float] | None = None
    footprint_short_m: tuple[float, float] | None = None

    @field_validator("height_m", "footprint_long_m", "footprint_short_m")
    @classmethod
    def _ranges(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not (0.0 <= v[0] <= v[1] <= 50.0):
            raise ValueError(f"must be [low, high] metres with 0 <= low <= high <= 50 (got {list(v)})")
        return v


class ClassConfig(StageConfig):
    """One semantic class. Classes are configuration, not code."""

    name: str = Field(min_length=1, pattern=r"^[a-z][a-z0-9_]*$")
    #: ``full``: open underneath (chair, desk): the top's projection is the footprint.
    #: ``partial``: a central pedestal or panel (conference table): same projection, the
    #: depth slice sees only part of it. ``none``: solid down to the floor (sofa).
    hollow: HollowKind
    #: Extra clearance the planner keeps from objects of this class, metres.
    margin_m: float = Field(ge=0.0, le=5.0)
    color_rgb: tuple[int, int, int]
    #: Existence log-odds taken per 0.5 s in which the object should be visible but is not.
    miss_decay: float = Field(default=0.4, ge=0.0, le=5.0)
    #: The least footprint (length, width) metres an object of this class has: the planner's
    #: view of a partly seen one (a table top seen edge-on from a low flight, a chair from
    #: behind) is grown to it on the side its views could not see (see
    #: :func:`semmap.polygons.grow_to_least_size`). The exported map keeps what was measured.
    #: ``null``: no such prior (thin or free-form objects).
    min_footprint_m: tuple[float, float] | None = None
    #: The sizes objects of this class come in (null: any); see :class:`GeometricPrior`.
    prior: GeometricPrior | None = None
    #: The class's shape prior (see :data:`ShapeKind`).
    shape: ShapeKind = "free"

    @field_validator("min_footprint_m")
    @classmethod
    def _footprint_sizes(cls, v: tuple[float, float] | None) -> tuple[float, float] | None:
        if v is not None and not all(0.0 < x <= 20.0 for x in v):
            raise ValueError(f"length and width must be in (0, 20] m (got {list(v)})")
        return v

    @field_validator("color_rgb")
    @classmethod
    def _colour_range(cls, v: tuple[int, int, int]) -> tuple[int, int, int]:
        if any(c < 0 or c > 255 for c in v):
            raise ValueError(f"each component must be in 0..255 (got {list(v)})")
        return v


def default_classes() -> list[ClassConfig]:
    """The six classes of the reference design, with the sizes of common furniture as their
    geometric priors (a dining table is a desk here: same height and size).

    Coffee and conference tables have a least footprint (a small one of each), because their
    tops are seen at grazing angles from a flight band near them (a coffee table's edge-on, a
    conference table's from underneath) and map short until the vehicle is close. Chairs and
    desks show enough of themselves in the band, and growing them closes passages. Chairs and
    sofas span seat to backrest: their top plane, where found, is the seat."""
    return [
        ClassConfig(name="chair", hollow="full", margin_m=0.20, color_rgb=(230, 25, 75), shape="seat",
                    prior=GeometricPrior(height_m=(0.38, 1.3), footprint_long_m=(0.3, 0.9),
                                         footprint_short_m=(0.3, 0.8))),
        ClassConfig(name="coffee_table", hollow="full", margin_m=0.20, color_rgb=(60, 180, 75), shape="table",
                    min_footprint_m=(0.75, 0.45),
                    prior=GeometricPrior(height_m=(0.25, 0.58), footprint_long_m=(0.4, 1.6),
                                         footprint_short_m=(0.3, 1.0))),
        ClassConfig(name="conference_table", hollow="partial", margin_m=0.25, color_rgb=(0, 130, 200),
                    shape="table",
                    min_footprint_m=(1.8, 0.9),
                    prior=GeometricPrior(height_m=(0.68, 0.82), footprint_long_m=(1.9, 8.0),
                                         footprint_short_m=(0.85, 2.5))),
        ClassConfig(name="sofa", hollow="none", margin_m=0.15, color_rgb=(245, 130, 48),
                    prior=GeometricPrior(height_m=(0.35, 1.1), footprint_long_m=(1.0, 3.2),
                                         footprint_short_m=(0.6, 1.2))),
        ClassConfig(name="whiteboard", hollow="full", margin_m=0.25, color_rgb=(145, 30, 180),
                    prior=GeometricPrior(height_m=(1.4, 2.4), footprint_long_m=(0.5, 2.5),
                                         footprint_short_m=(0.0, 0.8))),
        ClassConfig(name="desk", hollow="full", margin_m=0.25, color_rgb=(70, 240, 240), shape="table",
                    prior=GeometricPrior(height_m=(0.62, 0.9), footprint_long_m=(0.7, 2.0),
                                         footprint_short_m=(0.4, 0.95))),
    ]


class ExtrinsicsConfig(StageConfig):
    """Pose of the camera on the body.

    ``xyz_m`` is the optical centre in the body frame (FLU). ``rpy_deg`` rotates a camera that
    looks along body +x (roll about x, then pitch about y: positive pitch tilts it down, then
    yaw about z). The optical axes (x right, y down, z forward) follow by a fixed rotation.
    """

    xyz_m: tuple[float, float, float] = (0.10, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def T_body_camera(self) -> np.ndarray:  # noqa: N802 - frame names
        """(4, 4) transform from the optical camera frame to the body frame."""
        r, p, y = (math.radians(a) for a in self.rpy_deg)
        R = rotation_from_rpy(r, p, y) @ R_BODY_CAMERA_FORWARD
        return make_transform(R, np.asarray(self.xyz_m, dtype=np.float64))


class CameraConfig(StageConfig):
    """The RGB-D camera: which source, its intrinsics and mounting."""

    source: Literal["sim", "recorded", "realsense"] = "sim"
    #: Folder for ``source: recorded`` (TUM layout or color/ depth/ layout).
    recorded_path: str | None = None
    #: Serial number of the RealSense to open; None opens the first one found.
    realsense_serial: str | None = None
    width_px: int = Field(default=640, gt=0, le=4096)
    height_px: int = Field(default=480, gt=0, le=4096)
    #: Intrinsics of the colour stream that depth is aligned to (D455 at 640x480).
    fx_px: float = Field(default=383.0, gt=0.0)
    fy_px: float = Field(default=383.0, gt=0.0)
    cx_px: float = Field(default=320.0, ge=0.0)
    cy_px: float = Field(default=240.0, ge=0.0)
    rate_hz: float = Field(default=15.0, gt=0.0, le=90.0)
    #: Depth outside [min, max] is invalid (the D455's useful range indoors).
    depth_min_m: float = Field(default=0.3, ge=0.0)
    depth_max_m: float = Field(default=6.0, gt=0.0, le=20.0)
    extrinsics: ExtrinsicsConfig = ExtrinsicsConfig()

    @model_validator(mode="after")
    def _check(self) -> "CameraConfig":
        if self.depth_max_m <= self.depth_min_m:
            raise ValueError(
                f"depth_max_m must be > depth_min_m (got {self.depth_max_m} <= {self.depth_min_m})"
            )
        if self.source == "recorded" and not self.recorded_path:
            raise ValueError("source 'recorded' needs recorded_path")
        return self

    @property
    def is_real(self) -> bool:
        """Real images (a RealSense, a recording), not the simulator's renders."""
        return self.source != "sim"

    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics(
            self.fx_px, self.fy_px, self.cx_px, self.cy_px, self.width_px, self.height_px
        )


class DetectorConfig(StageConfig):
    """Object detector: an ONNX model (YOLOv8 or YOLOX head) or the simulator's oracle."""

    #: ``onnx`` (default): the model at ``model_path``. ``oracle``: boxes from the simulated
    #: world's ground truth (the simulator only; unit tests and reference runs).
    kind: Literal["onnx", "oracle"] = "onnx"
    #: Path of the .onnx file, or a model shipped in the package: ``builtin:coco`` (COCO-trained
    #: YOLOX-nano, for real cameras) or ``builtin:furniture`` (trained on our simulated rooms).
    #: ``auto`` (default): ``builtin:coco`` on a real camera (``camera.source`` realsense or
    #: recorded, ``companion map``), ``builtin:furniture`` in the simulator.
    model_path: str | None = "auto"
    head: Literal["auto", "yolov8", "yolox"] = "auto"
    input_size_px: int = Field(default=320, ge=32, le=2048)
    #: Model class names in output order; None reads them from the model's metadata.
    model_class_names: list[str] | None = None
    #: Model class name (or id as a string) -> our semantic class. Names not listed are ignored.
    #: Empty means identity for names that are our classes (or a shipped model's own map). A
    #: list of our classes means the model cannot tell them apart (COCO's one table class):
    #: detections report the first, and the object map counts each as a vote for all of
    #: them, leaving the choice to the measured geometry (``classes[].prior``).
    class_map: dict[str, str | list[str]] = Field(default_factory=dict)
    #: The operating point. None: the shipped model's own (its ``.classmap.json`` side file;
    #: for ``builtin:coco`` score 0.35, tables 0.2, NMS IoU 0.45, see its model card), and
    #: score 0.25, NMS IoU 0.6 for any other model.
    score_threshold: float | None = Field(default=None, ge=0.0, le=1.0)
    #: Per-class overrides of score_threshold, keyed by our class name (empty: the shipped
    #: model's, if any).
    class_score_thresholds: dict[str, float] = Field(default_factory=dict)
    nms_iou: float | None = Field(default=None, gt=0.0, le=1.0)
    max_detections: int = Field(default=100, gt=0)
    #: ONNX Runtime execution providers in order of preference; missing ones are skipped.
    providers: list[str] = Field(
        default_factory=lambda: [
            "TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"
        ]
    )
    intra_op_threads: int = Field(default=1, ge=0, le=64)
    graph_optimization: Literal["disable", "basic", "extended", "all"] = "all"
    #: YOLOX only: the model was exported with ``--decode_in_inference`` (boxes already in
    #: input pixels). YOLOX's exporter default is off: grid offsets decoded here.
    yolox_predecoded: bool = False
    #: TensorRT provider: fp16 engines, and a folder caching built engines (None = no cache).
    trt_fp16: bool = True
    trt_cache_dir: str | None = None
    # Oracle (simulation only) noise model.
    oracle_box_noise_px: float = Field(default=3.0, ge=0.0)
    oracle_miss_rate: float = Field(default=0.05, ge=0.0, le=1.0)
    oracle_false_positive_rate: float = Field(default=0.02, ge=0.0, le=1.0)
    oracle_min_visible_px: int = Field(default=400, ge=1)


class TrackerConfig(StageConfig):
    """BoT-SORT parameters (names follow the BoT-SORT reference implementation)."""

    track_high_thresh: float = Field(default=0.5, ge=0.0, le=1.0)
    track_low_thresh: float = Field(default=0.1, ge=0.0, le=1.0)
    new_track_thresh: float = Field(default=0.6, ge=0.0, le=1.0)
    #: Frames a lost track is kept before removal, counted at 30 Hz as in BoT-SORT (scaled by
    #: frame_rate_hz / 30: 30 at 15 Hz keeps a lost track for 15 frames, one second).
    track_buffer_frames: int = Field(default=30, ge=1)
    #: Maximum (1 - IoU) cost (score-fused) accepted in the first association stage.
    #: BoT-SORT uses 0.8 for pedestrians; static furniture seen by a turning drone changes its
    #: visible extent abruptly (occlusion, image-border truncation) and keeps its id better
    #: at 0.9 (``bench/tracking.py`` flies both).
    match_thresh: float = Field(default=0.9, gt=0.0, le=1.0)
    #: Pairs with (1 - IoU) above this cannot match on appearance alone.
    proximity_thresh: float = Field(default=0.5, gt=0.0, le=1.0)
    #: Maximum appearance cost (half cosine distance) for the optional appearance hook.
    appearance_thresh: float = Field(default=0.25, gt=0.0, le=1.0)
    #: CMC works on the image shrunk by this factor (speed; the flow is scaled back).
    cmc_downscale: int = Field(default=2, ge=1, le=8)
    #: Camera-motion compensation: sparse optical flow on background features, or off.
    cmc_method: Literal["sparse_optflow", "none"] = "sparse_optflow"
    #: CMC motion model: BoT-SORT's similarity ("affine"), or a homography, which is exact
    #: for a rotating camera (a yawing drone; see semmap.tracking.cmc).
    cmc_model: Literal["homography", "affine"] = "homography"
    #: Fuse detection score into the IoU cost (BoT-SORT ``fuse_score``).
    fuse_score: bool = True
    frame_rate_hz: float = Field(default=15.0, gt=0.0)

    @model_validator(mode="after")
    def _order(self) -> "TrackerConfig":
        if self.track_low_thresh > self.track_high_thresh:
            raise ValueError("track_low_thresh must be <= track_high_thresh")
        return self


class GeometryConfig(StageConfig):
    """Point-cloud processing of each tracked object."""

    #: Fraction of the box trimmed from each side before taking points (box edges leak).
    box_shrink_frac: float = Field(default=0.0, ge=0.0, lt=0.5)
    voxel_size_m: float = Field(default=0.03, gt=0.0, le=0.5)
    #: Euclidean clustering distance threshold (epsilon of the reference design).
    cluster_distance_m: float = Field(default=0.05, gt=0.0, le=1.0)
    #: The distance grows to this many sampled-pixel spacings at the 90th-percentile range,
    #: so a surface seen at a grazing angle (rows spaced several pixel spacings apart on a
    #: table top seen from its own height) stays one cluster under exact single linkage.
    cluster_pixel_gaps: float = Field(default=6.0, ge=0.0)
    min_cluster_points: int = Field(default=20, ge=1)
    ransac_distance_m: float = Field(default=0.02, gt=0.0)
    ransac_iterations: int = Field(default=100, ge=1)
    #: The top plane must be within this angle of horizontal.
    plane_max_tilt_deg: float = Field(default=15.0, ge=0.0, le=45.0)
    #: Points within this height of the floor belong to the floor, not the object.
    floor_clearance_m: float = Field(default=0.04, ge=0.0)
    #: ... plus this times the squared camera range (depth noise grows with range squared).
    floor_clearance_per_m2: float = Field(default=0.006, ge=0.0)
    #: Clusters with at least this fraction of the largest cluster's pixels compete; the
    #: nearest wins (the object stands in front of what its box also shows).
    cluster_min_pixel_frac: float = Field(default=0.3, gt=0.0, le=1.0)
    #: ... and must span at least this fraction of the box area that the best-spanning
    #: candidate spans (an occluder in front spans less).
    cluster_min_box_cover: float = Field(default=0.75, gt=0.0, le=1.0)
    #: Pixels taken from one box at most: larger boxes are sampled with a coarser pixel stride.
    max_box_points: int = Field(default=4000, ge=100)
    #: Horizontal-plane RANSAC inliers (voxels) needed to report a top plane.
    min_plane_points: int = Field(default=15, ge=3)
    #: Height of the object = this quantile of its points' heights (robust to stray pixels).
    height_quantile: float = Field(default=0.995, gt=0.5, le=1.0)


#: The initial grid's cell limit (250 m x 250 m at 5 cm): past it a grid does not fit in a
#: companion computer's memory with its layers.
MAX_MAP_CELLS = 25_000_000


class MapConfig(StageConfig):
    """Occupancy grid, object map and semantic layers."""

    moved_keys: ClassVar[dict[str, str]] = {
        "margin_decay_m": "use map.clearance_decay_m (one decay for the map's margins and the planner's proximity cost)",
    }

    resolution_m: float = Field(default=0.05, gt=0.0, le=1.0)
    #: Initial extent; the grid grows as the vehicle explores unless ``fixed_size``.
    width_m: float = Field(default=20.0, gt=0.0)
    height_m: float = Field(default=20.0, gt=0.0)
    origin_xy_m: tuple[float, float] = (-10.0, -10.0)
    fixed_size: bool = False
    # Cartographer-style probability grid.
    hit_probability: float = Field(default=0.55, gt=0.5, lt=1.0)
    miss_probability: float = Field(default=0.49, gt=0.0, lt=0.5)
    min_probability: float = Field(default=0.12, gt=0.0, lt=0.5)
    max_probability: float = Field(default=0.97, gt=0.5, lt=1.0)
    #: Height band (above the floor) of the depth-derived scan; None follows the flight
    #: altitude +- half the vehicle height + margin.
    scan_band_m: tuple[float, float] | None = None
    #: Layers older than this make the planner hold position.
    stale_after_s: float = Field(default=2.0, gt=0.0)
    #: What the planner is given: ``semantic`` (occupancy + object footprints + margins) or
    #: ``metric`` (the occupancy layer alone: with ``scan_band_m`` a thin slice at flight
    #: altitude, what a plain 2D map gives; for comparisons such as ``bench/safety.py``).
    mode: Literal["semantic", "metric"] = "semantic"
    # Object map.
    #: Existence log-odds one view of full quality adds (a close, clean, confident view; see
    #: :func:`semmap.object_evidence.view_quality`): one such view confirms an object.
    existence_hit_logodds: float = Field(default=1.4, gt=0.0)
    #: Prior before the first observation: a weak sighting alone does not confirm an object.
    existence_initial: float = Field(default=0.3, gt=0.0, lt=1.0)
    #: Objects below this existence probability are removed.
    existence_remove_below: float = Field(default=0.15, ge=0.0, lt=1.0)
    #: Objects at or above this existence probability are in the costmap.
    existence_confirm: float = Field(default=0.6, gt=0.0, lt=1.0)
    #: Footprint IoU at which a re-observed object (new track) merges into a known one.
    reassociate_iou: float = Field(default=0.3, gt=0.0, le=1.0)
    #: ... or whose centroid is this close (xy, metres): partial views overlap little.
    reassociate_distance_m: float = Field(default=0.35, ge=0.0)
    #: A track's observation farther than this from its object's centroid starts a new
    #: object (the tracker switched identities).
    track_gate_m: float = Field(default=1.0, gt=0.0)
    #: Existence is clamped here, so a long-seen object that is gone still fades.
    existence_max: float = Field(default=0.98, gt=0.5, lt=1.0)
    #: Unconfirmed objects not seen again for this long are dropped.
    tentative_timeout_s: float = Field(default=5.0, gt=0.0)
    #: Position noise of one observation: base + per_m * range from the camera.
    position_sigma_m: float = Field(default=0.05, gt=0.0)
    position_sigma_per_m: float = Field(default=0.02, ge=0.0)
    #: Fused footprint: minimum-area oriented rectangle of the observed hull, or the hull.
    footprint_shape: Literal["rectangle", "hull"] = "rectangle"
    #: Observations farther than this weigh less in the footprint and its height (far depth
    #: is noisy).
    footprint_max_range_m: float = Field(default=4.0, gt=0.0)
    #: Footprint evidence cells (2 cm) count when their weight (views that saw the object
    #: there) reaches this fraction of the 90th-percentile cell's.
    footprint_evidence_frac: float = Field(default=0.65, gt=0.0, le=1.0)
    #: Negative evidence: the measured depth at an object's centroid pixel must be at least
    #: expected - tolerance (not occluded) for a missed detection to count against it.
    visibility_tolerance_m: float = Field(default=0.3, gt=0.0)
    #: Cost beyond a keep-out zone falls by e over this distance: beyond an object's class
    #: margin in the map, and beyond the vehicle radius in the planner's proximity cost.
    clearance_decay_m: float = Field(default=DEFAULT_CLEARANCE_DECAY_M, gt=0.0, le=5.0)

    @model_validator(mode="after")
    def _size(self) -> "MapConfig":
        if not all(math.isfinite(v) for v in self.origin_xy_m):
            raise ValueError(f"origin_xy_m must be finite (got {list(self.origin_xy_m)})")
        cells = math.ceil(self.width_m / self.resolution_m) * math.ceil(self.height_m / self.resolution_m)
        if cells > MAX_MAP_CELLS:
            raise ValueError(
                f"width_m x height_m ({self.width_m:g} x {self.height_m:g} m) at resolution_m "
                f"{self.resolution_m:g} is {cells:.3g} cells, more than the {MAX_MAP_CELLS:,} a "
                "companion computer can hold: reduce map.width_m/map.height_m or coarsen "
                "map.resolution_m"
            )
        return self

    @model_validator(mode="after")
    def _check(self) -> "MapConfig":
        if self.scan_band_m is not None and self.scan_band_m[1] <= self.scan_band_m[0]:
            raise ValueError(f"scan_band_m must be [low, high] with high > low (got {list(self.scan_band_m)})")
        if self.min_probability >= self.max_probability:
            raise ValueError("min_probability must be < max_probability")
        return self


class SlamConfig(StageConfig):
    """Cartographer-style 2D SLAM (:mod:`semmap.slam`): local scan-to-submap matching and
    background loop closure over a pose graph."""

    moved_keys: ClassVar[dict[str, str]] = {
        "mode": "whether SLAM poses the map is chosen by service.localization (odometry | slam)",
    }
    resolution_m: float = Field(default=0.05, gt=0.0, le=0.5)
    #: Scans each submap receives (consecutive submaps overlap by half of them).
    scans_per_submap: int = Field(default=60, ge=2)
    #: Hits closer than this to each other are merged before matching (voxel filter).
    voxel_filter_m: float = Field(default=0.05, ge=0.0)
    #: Sigma (cells) of a submap's likelihood field for loop closure, and for the live matcher
    #: (half a cell at least): wider, it pulls a turning scan's new end of a wall back onto the
    #: known end, and the heading lags every turn.
    blur_sigma_cells: float = Field(default=1.0, ge=0.0)
    live_blur_sigma_cells: float = Field(default=0.75, ge=0.0)
    # Motion filter: a scan is inserted when one of these is exceeded since the last insert.
    motion_filter_distance_m: float = Field(default=0.1, ge=0.0)
    motion_filter_angle_deg: float = Field(default=5.0, ge=0.0)
    motion_filter_time_s: float = Field(default=2.0, ge=0.0)
    #: Scans within this long (s) of an OK match take the odometry's prediction and are not
    #: matched (0: match every scan). 0.09: every third frame of a 30 Hz camera, every
    #: frame of a 10 Hz one.
    match_interval_s: float = Field(default=0.09, ge=0.0, le=1.0)
    # Real-time correlative search window around the odometry prediction.
    correlative_linear_window_m: float = Field(default=0.1, ge=0.0)
    correlative_angular_window_deg: float = Field(default=5.0, ge=0.0)
    correlative_translation_cost: float = Field(default=1.0, ge=0.0)
    correlative_rotation_cost: float = Field(default=1.0, ge=0.0)
    # Least-squares refinement weights (Cartographer's ceres_scan_matcher).
    occupied_space_weight: float = Field(default=1.0, gt=0.0)
    translation_weight: float = Field(default=10.0, ge=0.0)
    #: Strong, as the odometry calibration below unbiases the prior's yaw: a narrow camera's
    #: scans constrain yaw weakly and the prior holds it between them.
    rotation_weight: float = Field(default=10.0, ge=0.0)
    #: Seconds of matched scans over which the odometry's heading drift rate and distance
    #: scale are measured and taken out of its increments (0: use the increments as they are).
    odometry_calibration_window_s: float = Field(default=10.0, ge=0.0)
    # Degeneracy: fall back to odometry when the scan does not constrain the pose.
    min_scan_points: int = Field(default=20, ge=3)
    #: Smallest eigenvalue of the translational information (mean squared probability
    #: gradient, 1/m^2) a scan needs, and its ratio to the largest one; below either the fit
    #: slides (a featureless corridor).
    min_translation_information: float = Field(default=10.0, ge=0.0)
    min_information_ratio: float = Field(default=0.1, ge=0.0, le=1.0)
    #: Mean probability under the matched hits below which the match is not trusted.
    min_match_score: float = Field(default=0.3, ge=0.0, le=1.0)
    # Loop closure (background).
    loop_closure_every_n_nodes: int = Field(default=5, ge=1)
    loop_closure_linear_window_m: float = Field(default=0.5, gt=0.0)
    loop_closure_angular_window_deg: float = Field(default=8.0, gt=0.0)
    #: Mean likelihood-field value under the node's hits a closure needs.
    loop_closure_min_score: float = Field(default=0.75, gt=0.0, lt=1.0)
    #: Finished submaps whose global centre is farther than this from the node are skipped.
    loop_closure_max_distance_m: float = Field(default=2.5, gt=0.0)
    branch_and_bound_depth: int = Field(default=6, ge=1, le=10)
    loop_closure_queue_size: int = Field(default=64, ge=1)
    # Pose graph.
    constraint_translation_weight: float = Field(default=100.0, gt=0.0)
    constraint_rotation_weight: float = Field(default=100.0, gt=0.0)
    #: Consecutive nodes (local SLAM's relative motion): stiff, so loop closures bend the
    #: trajectory over long spans instead of jolting single nodes.
    local_translation_weight: float = Field(default=200.0, gt=0.0)
    local_rotation_weight: float = Field(default=200.0, gt=0.0)
    loop_translation_weight: float = Field(default=100.0, gt=0.0)
    loop_rotation_weight: float = Field(default=100.0, gt=0.0)
    #: Huber scale of the pose graph's robust loss (in weighted residual units).
    huber_scale: float = Field(default=1.0, gt=0.0)
    optimize_every_n_constraints: int = Field(default=3, ge=1)
    #: Pose-graph iterations per optimisation.
    optimization_iterations: int = Field(default=20, ge=1)
