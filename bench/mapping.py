"""Mapping accuracy on seeded simulated rooms: object geometry and the object map.

Run: ``python bench/mapping.py`` (20 rooms) or ``--quick`` (3 short rooms, under a minute on
an idle machine); ``--seed 2000`` for other rooms than the usual 1000-1019, ``--tail N`` to
list the N objects with the largest position error. Each room is flown once around a loop at 1.0-1.5 m, the camera looking at
the room's centre and tilted down; every frame is rendered (RGB-D and instance masks), boxes
come from the masks (an oracle detector with box noise, misses, class confusions and false
positives), track ids come from instance ids (a new id whenever an object was out of view for
a while, so re-association after a lost track is exercised), and the geometry + object map
run on each frame. ``--detector builtin:furniture`` (or an .onnx path) replaces the oracle with
a shipped model run through our runtime on the rendered colour image, tracked as the service
tracks (BoT-SORT giving way to 3D association after camera steps it cannot follow; the
survey's frames are such steps).

Figures (section ``objects``), against the ground truth of objects seen well during the flight:

* position error: xy distance between the map object's footprint centre and the ground-truth
  footprint centre (``center_xy_m``). The fused centroid of the object's points is not
  comparable with that (a chair's points crowd on its backrest), so it is reported separately
  against the ground-truth volume centroid, for information;
* footprint IoU (polygons rasterised at 1 cm), height error (top of the object above the floor),
  class correctness, spurious objects (confirmed map objects matching no real one) and duplicate
  objects (confirmed map objects left unmatched over a real object that has its match: one
  thing mapped twice, as a detector's class confusions can cause).

The output is structured in sections (``SECTIONS``): each section is a function taking the
parsed arguments and returning (table lines, figures dict). The last line printed is one JSON
object with every section's figures.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.sim.groundtruth import clearance_m  # noqa: E402
from companion.sim.render import DepthNoise, RoomRenderer  # noqa: E402
from companion.sim.world import LAYOUTS, Room, generate_room  # noqa: E402
from semmap.config import (  # noqa: E402
    ClassConfig,
    DetectorConfig,
    ExtrinsicsConfig,
    GeometryConfig,
    MapConfig,
    TrackerConfig,
    default_classes,
)
from semmap.detection import Detector, detector_from_config  # noqa: E402
from semmap.frame_objects import observe_frame  # noqa: E402
from semmap.frames import pose_from_xyz_rpy  # noqa: E402
from semmap.grid import GridSpec, rasterize_polygon  # noqa: E402
from semmap.objects import CameraView, MappedObject, ObjectMap  # noqa: E402
from semmap.pipeline import step_aware_tracker  # noqa: E402
from semmap.types import CameraIntrinsics, Frame, Track  # noqa: E402

INTRINSICS = CameraIntrinsics(383.0, 383.0, 320.0, 240.0, 640, 480)
DEPTH_RANGE_M = (0.3, 6.0)


@dataclass(frozen=True)
class OracleNoise:
    """Detector failure modes of the mask-based oracle."""

    box_noise_px: float = 3.0
    miss_rate: float = 0.05
    confusion_rate: float = 0.05
    false_positive_rate: float = 0.02
    min_visible_px: int = 400
    #: A track id is retired after the object was unseen for this many frames.
    lost_after_frames: int = 8
    #: Classes the detector reports as another, (ours, reported): COCO's one table class.
    merge_classes: tuple[tuple[str, str], ...] = ()


def _loop(room: Room, inset_m: float, n: int) -> list[np.ndarray]:
    """``n`` points (2,) evenly spaced along a rectangle inset from the walls."""
    x0, x1, y0, y1 = inset_m, room.width_m - inset_m, inset_m, room.depth_m - inset_m
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
    seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    ends = np.cumsum(seg)
    out = []
    for si in np.linspace(0.0, ends[-1], n, endpoint=False):
        k = int(np.searchsorted(ends, si, side="right"))
        t = (si - (ends[k - 1] if k > 0 else 0.0)) / seg[k]
        out.append(corners[k] + t * (corners[k + 1] - corners[k]))
    return out


def flight_poses(room: Room, n_frames: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera poses ``T_map_camera`` of a survey flight: a loop near the walls looking at the
    room's centre, then an inner loop looking out at the walls, so objects in the middle and
    along the walls are both seen from several sides."""
    altitude = float(rng.uniform(1.0, 1.5))
    pitch = math.radians(float(rng.uniform(15.0, 25.0)))
    T_body_camera = ExtrinsicsConfig(xyz_m=(0.1, 0.0, 0.0), rpy_deg=(0.0, math.degrees(pitch), 0.0)).T_body_camera()
    centre = np.array([room.width_m / 2, room.depth_m / 2])
    inner = min(1.8, 0.5 * min(room.width_m, room.depth_m) - 0.6)
    n_out = n_frames // 2
    legs = [(xy, 1.0) for xy in _loop(room, 0.7, n_out)]
    legs += [(xy, -1.0) for xy in _loop(room, inner, n_frames - n_out)]
    poses = []
    for xy, sign in legs:
        if clearance_m(room, np.array([[xy[0], xy[1], altitude]]), 0.3)[0] < 0.3:
            continue  # the vehicle would be inside furniture here
        yaw = math.atan2(sign * (centre[1] - xy[1]), sign * (centre[0] - xy[0]))
        T_map_body = pose_from_xyz_rpy(xy[0], xy[1], altitude, 0.0, 0.0, yaw)
        poses.append(T_map_body @ T_body_camera)  # full SE(3) composition
    return poses


class MaskOracle:
    """Boxes and track ids from a rendered frame's instance mask (see the module doc)."""

    def __init__(self, room: Room, noise: OracleNoise, rng: np.random.Generator) -> None:
        self.room = room
        self.noise = noise
        self.rng = rng
        self.class_names = [c.name for c in default_classes()]
        self._track_of: dict[int, tuple[int, int]] = {}  # object id -> (track id, last frame)
        self._next_track = 1
        self._fp_track = 100000

    def tracks(self, frame: Frame) -> list[Track]:
        inst = np.asarray(frame.masks["instance"])
        H, W = inst.shape
        ids, counts = np.unique(inst[inst > 0], return_counts=True)
        out: list[Track] = []
        nz = self.noise
        for oid, cnt in zip(ids.tolist(), counts.tolist(), strict=True):
            if cnt < nz.min_visible_px or self.rng.random() < nz.miss_rate:
                continue
            vv, uu = np.nonzero(inst == oid)
            box = np.array([uu.min(), vv.min(), uu.max() + 1, vv.max() + 1], dtype=np.float64)
            box += self.rng.normal(0.0, nz.box_noise_px, 4)
            box = np.clip(box, 0, [W, H, W, H])
            cls = self.room.object_by_id(oid).class_name
            if self.rng.random() < nz.confusion_rate:
                cls = self.class_names[int(self.rng.integers(len(self.class_names)))]
            cls = dict(nz.merge_classes).get(cls, cls)
            tid, last = self._track_of.get(oid, (0, -10**9))
            if frame.index - last > nz.lost_after_frames:
                tid = self._next_track
                self._next_track += 1
            self._track_of[oid] = (tid, frame.index)
            score = float(np.clip(0.55 + 0.4 * min(1.0, cnt / 5000.0) + self.rng.normal(0, 0.05), 0.3, 0.99))
            out.append(Track(tid, (box[0], box[1], box[2], box[3]), score, cls))
        if self.rng.random() < nz.false_positive_rate:
            w, h = self.rng.uniform(40, 200, 2)
            u, v = self.rng.uniform(0, W - w), self.rng.uniform(0, H - h)
            cls = self.class_names[int(self.rng.integers(len(self.class_names)))]
            cls = dict(nz.merge_classes).get(cls, cls)
            self._fp_track += 1
            out.append(Track(self._fp_track, (u, v, u + w, v + h), float(self.rng.uniform(0.3, 0.6)), cls))
        return out


class ShippedDetector:
    """Tracks of a room's frames from a detector model and the service's tracker (one tracker
    per room, one model for all)."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector
        self.tracker = step_aware_tracker(TrackerConfig())

    @classmethod
    def load(cls, model_path: str) -> Detector:
        """The model (``builtin:NAME`` or an .onnx path) at its shipped operating point."""
        return detector_from_config(DetectorConfig(kind="onnx", model_path=model_path),
                                    [c.name for c in default_classes()])

    def tracks(self, frame: Frame) -> list[Track]:
        return self.tracker.update(list(self.detector.detect_frame(frame)), frame.rgb, frame.T_map_camera)


@dataclass
class RoomResult:
    """Per-object figures of one room."""

    position_err_m: list[float]
    centroid_err_m: list[float]
    iou: list[float]
    height_err_m: list[float]
    class_ok: list[bool]
    n_gt: int
    n_matched: int
    n_in_room: int
    n_spurious: int
    geometry_ms: list[float]
    #: Confirmed objects left unmatched whose best-overlapping real object already has its
    #: match: one thing mapped twice (e.g. under two classes).
    n_duplicate: int = 0
    #: Per scored object, in the order of the lists above: (ground-truth id, class, frames
    #: seen whole, map object id, map object's observations), for ``--tail``.
    labels: list[tuple[int, str, int, int, int]] = field(default_factory=list)


def raster_iou(a_xy_m: np.ndarray, b_xy_m: np.ndarray, resolution_m: float = 0.01) -> float:
    """IoU of two polygons rasterised on a common grid."""
    pts = np.concatenate([a_xy_m, b_xy_m])
    lo, hi = pts.min(axis=0) - 0.05, pts.max(axis=0) + 0.05
    spec = GridSpec.covering(lo[0], lo[1], hi[0], hi[1], resolution_m)
    a, b = rasterize_polygon(spec, a_xy_m), rasterize_polygon(spec, b_xy_m)
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 0.0


def well_seen(inst: np.ndarray, room: Room, T_map_camera: np.ndarray, min_px: int = 1500,
              margin_px: int = 3, max_range_m: float = 4.0) -> list[int]:
    """Object ids seen well in a frame: at least ``min_px`` pixels in the instance mask (H, W),
    not cut by the image border, and the object's centre within ``max_range_m`` of the camera
    (the D455's accurate range; beyond it depth noise alone exceeds the 10 cm target). The
    accuracy figures score objects seen well in a few frames; ``objects_in_rooms`` counts all."""
    H, W = inst.shape
    out = []
    cam_xy = T_map_camera[:2, 3]
    ids, counts = np.unique(inst[inst > 0], return_counts=True)
    for oid, cnt in zip(ids.tolist(), counts.tolist(), strict=True):
        if cnt < min_px or oid not in {o.object_id for o in room.objects}:
            continue
        if np.linalg.norm(np.asarray(room.object_by_id(oid).center_xy_m) - cam_xy) > max_range_m:
            continue
        vv, uu = np.nonzero(inst == oid)
        if uu.min() >= margin_px and vv.min() >= margin_px and uu.max() < W - margin_px and vv.max() < H - margin_px:
            out.append(oid)
    return out


def map_room(
    seed: int, n_frames: int, noise: OracleNoise | None = None,
    geometry: GeometryConfig | None = None, map_cfg: MapConfig | None = None,
    classes: list[ClassConfig] | None = None, vote_groups: dict[str, tuple[str, ...]] | None = None,
    class_weights: dict[str, float] | None = None, layout: str = "realistic",
    detector: Detector | None = None,
) -> tuple[Room, ObjectMap, dict[int, int], list[float]]:
    """Fly one seeded room (``layout``: :data:`companion.sim.world.LAYOUTS`) and build its
    object map (``classes``: the object map's, default :func:`default_classes`;
    ``vote_groups`` as :class:`ObjectMap` takes them; ``class_weights``: the room's furniture
    mix, default the generator's; ``detector``: a model in place of the mask oracle, see the
    module doc). Returns the room, the map, how many frames each
    ground-truth object was seen whole in, and per-frame geometry times (ms)."""
    rng = np.random.default_rng(seed)
    room = generate_room(seed, width_m=float(rng.uniform(6.0, 8.0)), depth_m=float(rng.uniform(5.0, 6.5)),
                         class_weights=class_weights, layout=layout)
    classes = classes or default_classes()
    cfg_by_name = {c.name: c for c in classes}
    renderer = RoomRenderer(room, [c.name for c in classes], INTRINSICS,
                            noise=DepthNoise(min_m=DEPTH_RANGE_M[0], max_m=DEPTH_RANGE_M[1]), seed=seed)
    boxes: MaskOracle | ShippedDetector = (MaskOracle(room, noise or OracleNoise(), rng) if detector is None
                                           else ShippedDetector(detector))
    geo = geometry or GeometryConfig()
    omap = ObjectMap(classes, map_cfg or MapConfig(), vote_groups=vote_groups)
    seen: dict[int, int] = {}
    times: list[float] = []
    for i, T in enumerate(flight_poses(room, n_frames, rng)):
        stamp = i / 15.0
        frame = renderer.render(T, stamp_s=stamp, index=i)
        for oid in well_seen(np.asarray(frame.masks["instance"]), room, T):
            seen[oid] = seen.get(oid, 0) + 1
        tracks = boxes.tracks(frame)
        t0 = time.perf_counter()
        obs = observe_frame(frame.depth_m, INTRINSICS, T, tracks, cfg_by_name, geo, depth_range_m=DEPTH_RANGE_M,
                            stamp_s=stamp, rng=rng)
        times.append((time.perf_counter() - t0) * 1e3)
        omap.update(obs, stamp, CameraView(frame.depth_m, INTRINSICS, T, DEPTH_RANGE_M))
    return room, omap, seen, times


def score_room(room: Room, omap: ObjectMap, seen: dict[int, int], min_frames: int = 3) -> RoomResult:
    """Match confirmed map objects to well-seen ground-truth objects (best footprint IoU)."""
    objs: list[MappedObject] = omap.objects(confirmed_only=True)
    gts = [o for o in room.objects if seen.get(o.object_id, 0) >= min_frames]
    pairs = []
    for gi, g in enumerate(gts):
        for mi, m in enumerate(objs):
            iou = raster_iou(g.footprint_xy_m(), m.footprint_xy_m)
            if iou > 0:
                pairs.append((iou, gi, mi))
    pairs.sort(reverse=True)
    used_g: set[int] = set()
    used_m: set[int] = set()
    res = RoomResult([], [], [], [], [], len(gts), 0, len(room.objects), 0, [])
    for iou, gi, mi in pairs:
        if gi in used_g or mi in used_m:
            continue
        used_g.add(gi)
        used_m.add(mi)
        g, m = gts[gi], objs[mi]
        res.iou.append(iou)
        res.position_err_m.append(float(np.linalg.norm(m.footprint_center_xy_m - np.array(g.center_xy_m))))
        res.centroid_err_m.append(float(np.linalg.norm(np.array(m.position_map_m[:2]) - g.centroid_m()[:2])))
        res.height_err_m.append(abs(m.z_max_m - g.height_m))
        res.class_ok.append(m.class_name == g.class_name)
        res.labels.append((g.object_id, g.class_name, seen.get(g.object_id, 0), m.object_id, m.n_observations))
    res.n_matched = len(used_g)
    # Spurious: confirmed objects that overlap no real object at all (real but unscored
    # objects, e.g. seen in fewer frames, are not spurious).
    all_fp = [o.footprint_xy_m() for o in room.objects]
    matched_ids = {gts[gi].object_id for gi in used_g}
    for mi, m in enumerate(objs):
        if mi in used_m:
            continue
        overlap = [raster_iou(fp, m.footprint_xy_m) for fp in all_fp]
        if max(overlap, default=0.0) <= 0:
            res.n_spurious += 1
        elif room.objects[int(np.argmax(overlap))].object_id in matched_ids:
            res.n_duplicate += 1
    return res


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


#: The headline figures under the issue's names (``--world``'s and, beside it, ``scattered``'s).
HEADLINE = {
    "position_error_p95_m": "position_err_m_p95", "footprint_iou_median": "footprint_iou_median",
    "height_error_p95_m": "height_err_m_p95", "class_accuracy": "class_correct_frac",
    "duplicates": "duplicate_objects", "spurious": "spurious_objects",
}


def objects_section(args: argparse.Namespace) -> tuple[list[str], dict[str, Any]]:
    """Object geometry + object map accuracy over seeded rooms of ``--world``; with
    ``--world realistic`` the same rooms' seeds laid out ``scattered`` too, under "scattered"."""
    lines, figures = _objects_in(args, args.world)
    figures.update({k: figures[v] for k, v in HEADLINE.items()})
    if args.world == "realistic" and not args.no_scattered:
        more, scattered = _objects_in(args, "scattered")
        lines += ["", "-- the same seeds, scattered layout", *more]
        figures["scattered"] = {**{k: scattered[v] for k, v in HEADLINE.items()}, "detail": scattered}
    return lines, figures


def _objects_in(args: argparse.Namespace, layout: str) -> tuple[list[str], dict[str, Any]]:
    n_rooms, n_frames = (3, 40) if args.quick else (args.rooms, args.frames)
    detector = None if args.detector == "oracle" else ShippedDetector.load(args.detector)
    results = []
    lines = [f"{'seed':>4} {'gt':>3} {'match':>5} {'spur':>4} {'dup':>3} {'pos p95 cm':>10} "
             f"{'IoU med':>7} {'h p95 cm':>8} {'class %':>7}"]
    for k in range(n_rooms):
        seed = args.seed + k
        room, omap, seen, times = map_room(seed, n_frames, layout=layout, detector=detector)
        r = score_room(room, omap, seen)
        r.geometry_ms = times
        results.append(r)
        lines.append(
            f"{seed:>4} {r.n_gt:>3} {r.n_matched:>5} {r.n_spurious:>4} {r.n_duplicate:>3} "
            f"{_pct(r.position_err_m, 95) * 100:>10.1f} {_pct(r.iou, 50):>7.2f} "
            f"{_pct(r.height_err_m, 95) * 100:>8.1f} {100 * np.mean(r.class_ok) if r.class_ok else float('nan'):>7.0f}"
        )
    if args.tail:
        # The worst objects by position error: where to look first (seed, objects, ids).
        rows = [(e, seed, r, i) for seed, r in zip(range(args.seed, args.seed + n_rooms), results, strict=True)
                for i, e in enumerate(r.position_err_m)]
        lines.append("")
        lines.append(f"worst {args.tail} by position error: seed, gt id, class, frames seen whole, map id, "
                     "observations, position cm, IoU, height cm")
        for e, seed, r, i in sorted(rows, key=lambda t: -t[0])[: args.tail]:
            gid, cname, n_seen, mid, n_obs = r.labels[i]
            lines.append(f"  {seed:>4} gt {gid:>2} {cname:<16} seen {n_seen:>3} map {mid:>3} obs {n_obs:>3} "
                         f"pos {100 * e:5.1f} IoU {r.iou[i]:.2f} h {100 * r.height_err_m[i]:4.1f}")
    pos = [e for r in results for e in r.position_err_m]
    cen = [e for r in results for e in r.centroid_err_m]
    iou = [e for r in results for e in r.iou]
    h = [e for r in results for e in r.height_err_m]
    cls = [c for r in results for c in r.class_ok]
    n_gt = sum(r.n_gt for r in results)
    n_all = sum(r.n_in_room for r in results)
    n_match = sum(r.n_matched for r in results)
    figures = {
        "rooms": n_rooms,
        "objects_scored": len(pos),
        "objects_gt": n_gt,
        "objects_in_rooms": n_all,
        "recall": n_match / n_gt if n_gt else float("nan"),
        "position_err_m_p50": _pct(pos, 50),
        "position_err_m_p95": _pct(pos, 95),
        "centroid_vs_gt_centroid_err_m_p95": _pct(cen, 95),
        "footprint_iou_median": _pct(iou, 50),
        "footprint_iou_p10": _pct(iou, 10),
        "height_err_m_p95": _pct(h, 95),
        "class_correct_frac": float(np.mean(cls)) if cls else float("nan"),
        "spurious_objects": int(sum(r.n_spurious for r in results)),
        "duplicate_objects": int(sum(r.n_duplicate for r in results)),
        "geometry_ms_per_frame_p50": _pct([t for r in results for t in r.geometry_ms], 50),
    }
    targets = {
        "position_err_m_p95": (figures["position_err_m_p95"] <= 0.10, "<= 0.10"),
        "footprint_iou_median": (figures["footprint_iou_median"] >= 0.8, ">= 0.8"),
        "height_err_m_p95": (figures["height_err_m_p95"] <= 0.05, "<= 0.05"),
        "class_correct_frac": (figures["class_correct_frac"] >= 0.95, ">= 0.95"),
        "spurious_objects": (figures["spurious_objects"] == 0, "== 0"),
    }
    lines.append("")
    for key, (ok, target) in targets.items():
        lines.append(f"  {key:<28} {figures[key]:>8.3f}  target {target:<7} {'PASS' if ok else 'FAIL'}")
    figures["targets_met"] = all(ok for ok, _ in targets.values())
    return lines, figures


#: Benchmark sections in print order: name -> function(args) -> (table lines, figures).
#: The occupancy-grid agreement figure is a section of its own, registered here beside
#: ``objects``.
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _class_prior import class_prior_section  # noqa: E402  (table kinds from geometry)
from _grid import grid_section  # noqa: E402  (occupancy grid agreement, stage times, memory)

SECTIONS: dict[str, Callable[[argparse.Namespace], tuple[list[str], dict[str, Any]]]] = {
    "objects": objects_section,
    "grid": grid_section,
    "class_prior": class_prior_section,
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 short rooms (under a minute)")
    ap.add_argument("--rooms", type=int, default=20)
    ap.add_argument("--frames", type=int, default=80, help="frames per room")
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--world", choices=LAYOUTS, default="realistic",
                    help="room layout (realistic also measures the same seeds scattered)")
    ap.add_argument("--detector", default="oracle",
                    help="objects section: oracle (boxes from the masks, default), builtin:NAME or an .onnx path")
    ap.add_argument("--no-scattered", action="store_true", help="with --world realistic: skip the scattered rooms")
    ap.add_argument("--tail", type=int, default=0, metavar="N",
                    help="objects section: also list the N objects with the largest position error")
    ap.add_argument("--section", choices=sorted(SECTIONS), action="append",
                    help="run only these sections (default: all)")
    args = ap.parse_args(argv)
    out: dict[str, Any] = {"world": args.world, "detector": args.detector}
    for name, fn in SECTIONS.items():
        if args.section and name not in args.section:
            continue
        t0 = time.perf_counter()
        lines, figures = fn(args)
        print(f"== {name} ({time.perf_counter() - t0:.0f} s)")
        for line in lines:
            print(line)
        print()
        out[name] = figures
    if "objects" in out:
        # The headline figures first-level too, as the status table quotes them.
        out.update({k: out["objects"][k] for k in HEADLINE})
        if "scattered" in out["objects"]:
            out["scattered"] = {k: out["objects"]["scattered"][k] for k in HEADLINE}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
