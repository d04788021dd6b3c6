"""Detector training data from the simulated world: images and YOLO labels of the six classes.

Each room of a split is :func:`~companion.sim.world.generate_room` with a seed from the split's
own range (:data:`ROOM_SEED_START`): the held-out rooms are never seen in training. Per room,
the size, wall height, furniture count, doorways, wall/floor colours, furniture colours,
textures (the renderer's seed) and the light direction vary; per image the camera pose and the
photometric conditions vary:

* camera poses a multicopter has indoors: height 0.5-2.5 m (below the ceiling), anywhere in
  the room at least :attr:`DatasetSpec.min_clearance_m` from walls and furniture, yaw either
  towards a piece of furniture (with an offset, so objects are not always centred; optionally
  class-balanced, :attr:`DatasetSpec.aim_class_balanced`) or random,
  a look-down tilt of -10..50 degrees plus the vehicle's own pitch and roll of +-10 degrees;
* gain, gamma, white balance, sensor noise, and optional linear motion blur.

Labels come from the renderer's noise-free instance mask: the tight box of each object's
visible pixels. Objects with fewer than :attr:`DatasetSpec.min_visible_px` visible pixels are
not labelled (the detector is not asked to find slivers; the evaluator ignores them too, see
``bench/detector.py``). Objects cut by the image border keep the box of their visible part,
as in COCO.

Output follows the Ultralytics layout: ``images/<split>/*.jpg``, ``labels/<split>/*.txt``
(``class cx cy w h`` normalised to the image) and a ``data.yaml`` naming the classes.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.errors import SimulationError
from companion.sim.groundtruth import clearance_m
from companion.sim.render import DepthNoise, RoomRenderer
from companion.sim.world import FurnitureObject, Room, generate_room
from semmap.frames import make_transform, rotation_from_rpy
from semmap.types import CameraIntrinsics

log = logging.getLogger(__name__)

#: First room seed of each split; room ``i`` of a split has seed ``start + i``. The ranges are
#: disjoint for up to :data:`MAX_ROOMS_PER_SPLIT` rooms, so held-out rooms never leak: ``train``
#: for training, ``val`` for the per-epoch validation that picks the exported epoch, ``heldout``
#: only for the reported metrics (``bench/detector.py``).
ROOM_SEED_START: dict[str, int] = {"train": 100_000, "val": 800_000, "heldout": 900_000}
MAX_ROOMS_PER_SPLIT = 100_000
#: Optical camera axes (x right, y down, z forward) in the body frame (x forward, y left, z up).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class DatasetSpec:
    """What to generate. Angles in degrees, lengths in metres, image sizes in pixels."""

    split: str = "train"
    n_rooms: int = 10
    images_per_room: int = 20
    #: Seeds the per-room appearance and per-image pose/photometry (not the room geometry,
    #: which the split's room seeds fix).
    seed: int = 0
    class_names: tuple[str, ...] = (
        "chair", "coffee_table", "conference_table", "sofa", "whiteboard", "desk",
    )
    intrinsics: CameraIntrinsics = CameraIntrinsics(383.0, 383.0, 320.0, 240.0, 640, 480)
    height_range_m: tuple[float, float] = (0.5, 2.5)
    tilt_range_deg: tuple[float, float] = (-10.0, 50.0)
    max_roll_pitch_deg: float = 10.0
    #: Fraction of images aimed at a random piece of furniture (the rest look anywhere).
    aim_fraction: float = 0.75
    #: Aim at a class drawn uniformly from the room's classes, then at one of its objects,
    #: instead of at a uniformly drawn object: rare classes (a room has one conference table
    #: and eight chairs) get as many aimed views as common ones. Training data only; the
    #: held-out split keeps the plain draw so its class mix is what a flight sees.
    aim_class_balanced: bool = False
    #: Fraction of the aimed images aimed at a piece of clutter (cabinets, shelves, lamps,
    #: boxes) instead: hard negatives, since clutter seen only at the edge of furniture views
    #: is what a detector learns least and then names a chair. Training data only.
    aim_clutter_fraction: float = 0.0
    #: Relative class frequencies of the generated rooms, ``((name, weight), ...)``; empty
    #: keeps :data:`companion.sim.world.CLASS_WEIGHTS`. Training data only, to give rare
    #: classes (conference tables) more instances.
    class_weights: tuple[tuple[str, float], ...] = ()
    #: Room generator (:data:`companion.sim.world.LAYOUTS`): furniture in groups as people
    #: arrange it, or each piece alone.
    layout: str = "realistic"
    min_clearance_m: float = 0.3
    min_visible_px: int = 120
    #: Also measure each labelled object's visible fraction (visible pixels over its
    #: unoccluded silhouette on an image plane three times the size,
    #: :meth:`~companion.sim.render.RoomRenderer.silhouette_px`): for evaluation by
    #: visibility (``bench/detector.py``); about 0.2 s a frame, so off for training data.
    measure_visibility: bool = False
    motion_blur_fraction: float = 0.3
    max_motion_blur_px: int = 9
    jpeg_quality: int = 92

    def __post_init__(self) -> None:
        if self.split not in ROOM_SEED_START:
            raise SimulationError(f"dataset split must be one of {sorted(ROOM_SEED_START)} (got {self.split!r})")
        if not 0 < self.n_rooms <= MAX_ROOMS_PER_SPLIT:
            raise SimulationError(f"n_rooms must be in 1..{MAX_ROOMS_PER_SPLIT} (got {self.n_rooms})")
        if self.images_per_room < 1:
            raise SimulationError(f"images_per_room must be >= 1 (got {self.images_per_room})")
        lo, hi = self.height_range_m
        if not 0.0 < lo <= hi:
            raise SimulationError(f"height_range_m must be 0 < low <= high (got {self.height_range_m})")
        if not 0.0 <= self.aim_clutter_fraction <= 1.0:
            raise SimulationError(f"aim_clutter_fraction must be in 0..1 (got {self.aim_clutter_fraction})")


@dataclass(frozen=True)
class LabeledImage:
    """One rendered image and its labels.

    ``rgb`` (H, W, 3) uint8; ``boxes_xyxy_px`` (N, 4) visible-pixel boxes (half-open max);
    ``class_ids`` (N,) indices into the spec's class names; ``visible_px`` (N,) pixel counts;
    ``object_ids`` (N,) the room's object ids; ``visible_fraction`` (N,) in (0, 1], occlusion
    and truncation together, when the spec asks for it (:attr:`DatasetSpec.measure_visibility`).
    """

    name: str
    room_seed: int
    rgb: NDArray[np.uint8]
    boxes_xyxy_px: NDArray[np.float64]
    class_ids: NDArray[np.int64]
    visible_px: NDArray[np.int64]
    T_map_camera: NDArray[np.float64]
    object_ids: NDArray[np.int64]
    visible_fraction: NDArray[np.float64] | None = None


def room_seeds(split: str, n_rooms: int, start: int = 0) -> list[int]:
    """The room seeds of ``n_rooms`` rooms of ``split`` from its room ``start``."""
    if split not in ROOM_SEED_START:
        raise SimulationError(f"dataset split must be one of {sorted(ROOM_SEED_START)} (got {split!r})")
    if start < 0:
        raise SimulationError(f"room start must be >= 0 (got {start})")
    if start + n_rooms > MAX_ROOMS_PER_SPLIT:
        raise SimulationError(f"a split has at most {MAX_ROOMS_PER_SPLIT} rooms (asked for {start + n_rooms})")
    return [ROOM_SEED_START[split] + start + i for i in range(n_rooms)]


def _random_color(rng: np.random.Generator) -> tuple[int, int, int]:
    """A colour anywhere in a plausible furniture gamut (saturation and value bounded)."""
    import cv2

    hsv = np.array([[[rng.uniform(0, 180), rng.uniform(0, 200), rng.uniform(40, 240)]]], dtype=np.uint8)
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0]
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


def varied_room(room_seed: int, rng: np.random.Generator, class_names: Sequence[str],
                class_weights: Sequence[tuple[str, float]] = (), layout: str = "realistic") -> Room:
    """A room of ``room_seed`` with a random size, wall height, furniture count, doorways and
    colours (from ``rng``). The geometry depends on both; the seed range keeps splits apart."""
    geo = np.random.default_rng([room_seed, int(rng.integers(1 << 31))])
    room = generate_room(
        room_seed * 7 + int(geo.integers(7)),
        width_m=float(geo.uniform(4.0, 10.0)),
        depth_m=float(geo.uniform(3.5, 8.0)),
        wall_height_m=float(geo.uniform(2.5, 3.2)),
        n_objects=int(geo.integers(4, 13)),
        n_doorways=int(geo.integers(1, 4)),
        class_names=list(class_names),
        class_weights=dict(class_weights) or None,
        layout=layout,
    )
    objects: list[FurnitureObject] = []
    for obj in room.objects:
        if obj.class_name != "whiteboard" and rng.random() < 0.4:
            obj = dataclasses.replace(obj, color_rgb=_random_color(rng))
        objects.append(obj)
    wall = tuple(int(v) for v in np.clip(rng.normal(205, 25, 3) + rng.normal(0, 10), 90, 255))
    floor = _random_color(rng)
    return dataclasses.replace(
        room, objects=tuple(objects), wall_color_rgb=wall, floor_color_rgb=floor,  # type: ignore[arg-type]
    )


def sample_camera_pose(
    room: Room, spec: DatasetSpec, rng: np.random.Generator, max_tries: int = 200,
) -> NDArray[np.float64]:
    """(4, 4) ``T_map_camera`` (optical axes) of a multicopter's camera in ``room``.

    The position keeps ``spec.min_clearance_m`` from every wall and furniture part at the
    camera's height. Raises :class:`SimulationError` if no such position is found.
    """
    lo, hi = spec.height_range_m
    hi = min(hi, room.wall_height_m - 0.2)
    for _ in range(max_tries):
        xyz = np.array([
            rng.uniform(0.2, room.width_m - 0.2),
            rng.uniform(0.2, room.depth_m - 0.2),
            rng.uniform(lo, max(lo, hi)),
        ])
        if clearance_m(room, xyz[None, :], vehicle_height_m=0.2)[0] < spec.min_clearance_m:
            continue
        if room.objects and rng.random() < spec.aim_fraction:
            if room.clutter and spec.aim_clutter_fraction > 0 and rng.random() < spec.aim_clutter_fraction:
                pool = list(room.clutter)
            elif spec.aim_class_balanced:
                names = sorted({o.class_name for o in room.objects})
                name = names[int(rng.integers(len(names)))]
                pool = [o for o in room.objects if o.class_name == name]
            else:
                pool = list(room.objects)
            target = pool[int(rng.integers(len(pool)))].centroid_m()
            d = target - xyz
            yaw = math.atan2(d[1], d[0]) + rng.normal(0.0, math.radians(15.0))
            tilt = math.degrees(math.atan2(-d[2], math.hypot(d[0], d[1]))) + rng.normal(0.0, 8.0)
            tilt = float(np.clip(tilt, *spec.tilt_range_deg))
        else:
            yaw = rng.uniform(-math.pi, math.pi)
            tilt = rng.uniform(*spec.tilt_range_deg)
        wobble = spec.max_roll_pitch_deg
        pitch = math.radians(tilt + rng.uniform(-wobble, wobble))
        roll = math.radians(rng.uniform(-wobble, wobble))
        R = rotation_from_rpy(roll, pitch, yaw) @ R_BODY_OPTICAL
        return make_transform(R, xyz)
    raise SimulationError(f"room {room.seed}: no camera position with {spec.min_clearance_m} m clearance")


def photometric(rgb: NDArray[np.uint8], spec: DatasetSpec, rng: np.random.Generator) -> NDArray[np.uint8]:
    """Gain, gamma, white balance and optional linear motion blur of an (H, W, 3) image."""
    import cv2

    img = rgb.astype(np.float32) / 255.0
    img = img ** np.float32(rng.uniform(0.75, 1.3))
    img *= (rng.uniform(0.6, 1.3) * rng.uniform(0.92, 1.08, 3)).astype(np.float32)
    if rng.random() < spec.motion_blur_fraction and spec.max_motion_blur_px >= 3:
        k = int(rng.integers(3, spec.max_motion_blur_px + 1))
        kernel = np.zeros((k, k), dtype=np.float32)
        kernel[k // 2, :] = 1.0 / k
        rot = cv2.getRotationMatrix2D(((k - 1) / 2.0, (k - 1) / 2.0), float(rng.uniform(0, 180)), 1.0)
        kernel = cv2.warpAffine(kernel, rot, (k, k))
        kernel /= max(float(kernel.sum()), 1e-6)
        img = cv2.filter2D(img, -1, kernel)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def labels_from_instance_mask(
    instance: NDArray[np.integer], class_mask: NDArray[np.integer], min_visible_px: int,
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Boxes of the visible pixels of every labelled object in an instance mask.

    ``instance`` (H, W) object ids (0 = none), ``class_mask`` (H, W) class indices (-1 = none).
    Returns ``(boxes (N, 4) xyxy px, half-open max; class ids (N,); visible pixel counts (N,);
    object ids (N,))`` for objects with a class and at least ``min_visible_px`` pixels, ordered
    by object id.
    """
    inst = np.asarray(instance)
    cls = np.asarray(class_mask)
    fg = (inst > 0) & (cls >= 0)
    ids, counts = np.unique(inst[fg], return_counts=True)
    boxes, classes, px, oids = [], [], [], []
    for oid, cnt in zip(ids.tolist(), counts.tolist(), strict=True):
        if cnt < min_visible_px:
            continue
        vv, uu = np.nonzero(inst == oid)
        boxes.append((uu.min(), vv.min(), uu.max() + 1, vv.max() + 1))
        classes.append(int(cls[vv[0], uu[0]]))
        px.append(cnt)
        oids.append(int(oid))
    return (
        np.asarray(boxes, dtype=np.float64).reshape(-1, 4),
        np.asarray(classes, dtype=np.int64),
        np.asarray(px, dtype=np.int64),
        np.asarray(oids, dtype=np.int64),
    )


def yolo_label_lines(boxes_xyxy_px: NDArray[np.floating], class_ids: NDArray[np.integer],
                     width_px: int, height_px: int) -> list[str]:
    """YOLO label lines ``"class cx cy w h"`` (normalised to the image) for (N, 4) xyxy boxes."""
    lines = []
    for (u0, v0, u1, v1), c in zip(np.asarray(boxes_xyxy_px).tolist(), np.asarray(class_ids).tolist(), strict=True):
        cx, cy = (u0 + u1) / 2.0 / width_px, (v0 + v1) / 2.0 / height_px
        w, h = (u1 - u0) / width_px, (v1 - v0) / height_px
        lines.append(f"{int(c)} {cx:.6f} {cy:.6f} {w:.6f} {h:.6f}")
    return lines


def generate(spec: DatasetSpec, room_start: int = 0) -> Iterator[LabeledImage]:
    """Render ``spec.n_rooms`` rooms of the split (from room ``room_start``) and yield their
    labelled images, ``spec.images_per_room`` each. Deterministic in the spec."""
    intr = spec.intrinsics
    for i, room_seed in enumerate(room_seeds(spec.split, spec.n_rooms, start=room_start)):
        rng = np.random.default_rng([spec.seed, room_seed])
        room = varied_room(room_seed, rng, spec.class_names, spec.class_weights, spec.layout)
        renderer = RoomRenderer(
            room, spec.class_names, intr, noise=DepthNoise(), seed=int(rng.integers(1 << 31)),
            light_dir_map=(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1)), float(rng.uniform(0.5, 1.5))),
            rgb_noise_std=float(rng.uniform(1.0, 5.0)), n_threads=1,
        )
        log.debug("room %d/%d (seed %d): %d objects", i + 1, spec.n_rooms, room_seed, len(room.objects))
        for k in range(spec.images_per_room):
            T = sample_camera_pose(room, spec, rng)
            frame = renderer.render(T, index=k, rng=rng)
            boxes, classes, px, oids = labels_from_instance_mask(
                frame.masks["instance"], frame.masks["class"], spec.min_visible_px
            )
            visible_fraction = None
            if spec.measure_visibility:
                silhouette = renderer.silhouette_px(T)
                visible_fraction = np.array(
                    [min(1.0, p / max(silhouette.get(o, 0.0), 1.0)) for p, o in zip(px.tolist(), oids.tolist(), strict=True)],
                    dtype=np.float64,
                )
            yield LabeledImage(
                name=f"{spec.split}_r{room_seed}_{k:03d}", room_seed=room_seed,
                rgb=photometric(frame.rgb, spec, rng), boxes_xyxy_px=boxes, class_ids=classes,
                visible_px=px, T_map_camera=T, object_ids=oids, visible_fraction=visible_fraction,
            )


def write_data_yaml(out_dir: Path, class_names: Sequence[str]) -> Path:
    """Write the Ultralytics ``data.yaml`` for a dataset folder (train/heldout splits)."""
    import yaml

    data = {
        "path": str(out_dir.resolve()),
        "train": "images/train",
        "val": "images/heldout",
        "names": dict(enumerate(class_names)),
    }
    path = out_dir / "data.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def write_dataset(spec: DatasetSpec, out_dir: str | Path, room_start: int = 0) -> dict[str, int]:
    """Generate the split into ``out_dir`` (Ultralytics layout) and return counts:
    ``{"images": ..., "labels": ..., "<class>": ...}``."""
    import cv2

    out = Path(out_dir)
    img_dir, lbl_dir = out / "images" / spec.split, out / "labels" / spec.split
    img_dir.mkdir(parents=True, exist_ok=True)
    lbl_dir.mkdir(parents=True, exist_ok=True)
    counts = {"images": 0, "labels": 0, **{c: 0 for c in spec.class_names}}
    for item in generate(spec, room_start=room_start):
        bgr = cv2.cvtColor(item.rgb, cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(img_dir / f"{item.name}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, spec.jpeg_quality]):
            raise SimulationError(f"cannot write {img_dir / item.name}.jpg")
        lines = yolo_label_lines(item.boxes_xyxy_px, item.class_ids, spec.intrinsics.width_px,
                                 spec.intrinsics.height_px)
        (lbl_dir / f"{item.name}.txt").write_text("".join(f"{ln}\n" for ln in lines))
        counts["images"] += 1
        counts["labels"] += len(lines)
        for c in item.class_ids.tolist():
            counts[spec.class_names[c]] += 1
        if counts["images"] % 100 == 0:
            log.info("%s: %d images, %d labels", spec.split, counts["images"], counts["labels"])
    write_data_yaml(out, spec.class_names)
    return counts
