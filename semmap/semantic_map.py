"""The semantic map: probability grid, objects and layers behind one facade.

:class:`SemanticMap` is what the service and the offline ``companion map`` command hold. Per
frame it extracts the depth band scan and updates the grid (:meth:`integrate_frame`), takes
the object map's current objects (:meth:`set_objects`), records the vehicle path, answers
:meth:`costmap` for a vehicle band and saves / loads itself atomically so a restart loses
nothing. It does no other I/O.

The object map proper (association, existence filtering) lives in :mod:`semmap.objects`.
A map built with an :class:`~semmap.objects.ObjectMap` feeds it each frame's observations
(``integrate_frame(..., observations=...)``) and takes its confirmed footprints; without one,
callers hand over :class:`~semmap.costmap.ObjectFootprint` s directly (``objects=``).
"""

from __future__ import annotations

import io
import json
import logging
import os
import tempfile
import time
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from semmap.costmap import DEFAULT_CLEARANCE_DECAY_M, Costmap, ObjectFootprint, VerticalBand
from semmap.errors import MapError
from semmap.geometry import ObjectObservation
from semmap.grid import Bounds, GridSpec
from semmap.layers import LayeredCostmap
from semmap.objects import CameraView, ObjectMap
from semmap.occupancy import ProbabilityGrid, ProbabilityTables
from semmap.scan import BandScan, extract_band_scan
from semmap.types import Frame

log = logging.getLogger(__name__)

#: Bumped when the saved file's layout changes incompatibly.
FILE_FORMAT_VERSION = 1
#: Added to the ids of loaded objects kept beside a fresh object map (no id clashes).
RESTORED_ID_OFFSET = 1_000_000
#: What :meth:`SemanticMap.costmap` may be built from (``SemanticMapSettings.mode``).
MAP_MODES = ("semantic", "metric")


@dataclass(frozen=True)
class SemanticMapSettings:
    """Every parameter of a :class:`SemanticMap` (plain values; see ``from_config``)."""

    class_names: tuple[str, ...]
    scan_band: VerticalBand
    resolution_m: float = 0.05
    origin_xy_m: tuple[float, float] = (-10.0, -10.0)
    size_xy_m: tuple[float, float] = (20.0, 20.0)
    fixed_size: bool = False
    hit_probability: float = 0.55
    miss_probability: float = 0.49
    min_probability: float = 0.12
    max_probability: float = 0.97
    depth_min_m: float = 0.3
    depth_max_m: float = 6.0
    scan_stride_px: int = 2
    #: One ray per 4th column: 0.6 degrees apart with a D455, as accurate on simulated rooms
    #: as every 2nd column (fewer stray hits beside surfaces) at half the cost.
    scan_column_stride_px: int = 4
    scan_min_hit_points: int = 2
    #: Grid cells at or above this probability are lethal, at or below ``free_threshold`` free.
    occupied_threshold: float = 0.6
    free_threshold: float = 0.5
    existence_confirm: float = 0.6
    clearance_decay_m: float = DEFAULT_CLEARANCE_DECAY_M
    #: Per-class safety margin (metres) used when an object arrives without one.
    class_margins_m: tuple[tuple[str, float], ...] = ()
    combine_rule: str = "maximum"
    stale_after_s: float = 2.0
    #: ``semantic``: :meth:`SemanticMap.costmap` combines every layer; ``metric``: the
    #: occupancy layer alone (see :meth:`SemanticMap.metric_costmap`).
    mode: str = "semantic"
    #: A path point is recorded when the vehicle moved at least this far.
    path_min_step_m: float = 0.05

    @classmethod
    def from_config(
        cls, map_cfg: Any, classes: Sequence[Any], default_band: VerticalBand,
        depth_min_m: float = 0.3, depth_max_m: float = 6.0,
    ) -> "SemanticMapSettings":
        """From a :class:`semmap.config.MapConfig`, the configured classes (``name``,
        ``margin_m``) and the band to scan when the config has no ``scan_band_m``."""
        band = (
            VerticalBand(*map_cfg.scan_band_m) if map_cfg.scan_band_m is not None else default_band
        )
        return cls(
            class_names=tuple(c.name for c in classes), scan_band=band,
            resolution_m=map_cfg.resolution_m, origin_xy_m=tuple(map_cfg.origin_xy_m),
            size_xy_m=(map_cfg.width_m, map_cfg.height_m), fixed_size=map_cfg.fixed_size,
            hit_probability=map_cfg.hit_probability, miss_probability=map_cfg.miss_probability,
            min_probability=map_cfg.min_probability, max_probability=map_cfg.max_probability,
            depth_min_m=depth_min_m, depth_max_m=depth_max_m,
            existence_confirm=map_cfg.existence_confirm, clearance_decay_m=map_cfg.clearance_decay_m,
            class_margins_m=tuple((c.name, float(c.margin_m)) for c in classes),
            stale_after_s=map_cfg.stale_after_s, mode=map_cfg.mode,
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["scan_band"] = [self.scan_band.z_min_m, self.scan_band.z_max_m]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SemanticMapSettings":
        data = dict(d)
        # Maps saved before the one decay setting name it by its old key.
        if "margin_decay_m" in data and "clearance_decay_m" not in data:
            data["clearance_decay_m"] = data.pop("margin_decay_m")
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise MapError(f"settings: unknown keys {unknown}")
        data["scan_band"] = VerticalBand(*data["scan_band"])
        data["class_names"] = tuple(data["class_names"])
        data["origin_xy_m"] = tuple(data["origin_xy_m"])
        data["size_xy_m"] = tuple(data["size_xy_m"])
        data["class_margins_m"] = tuple((str(n), float(m)) for n, m in data.get("class_margins_m", ()))
        return cls(**data)


@dataclass(frozen=True, eq=False)
class FrameIntegration:
    """What one :meth:`SemanticMap.integrate_frame` did: the scan and the touched windows."""

    scan: BandScan
    grid_bounds: Bounds
    object_bounds: Bounds = field(default_factory=Bounds.empty)


class SemanticMap:
    """Grid + objects + layers + path, see the module docstring."""

    def __init__(self, settings: SemanticMapSettings, object_map: ObjectMap | None = None) -> None:
        s = settings
        self.settings = s
        self.object_map = object_map
        if s.mode not in MAP_MODES:
            raise MapError(f"settings: unknown map mode {s.mode!r} (known: {list(MAP_MODES)})")
        if object_map is not None and list(object_map.class_names) != list(s.class_names):
            raise MapError(
                f"object map classes {object_map.class_names} differ from the map's {list(s.class_names)}"
            )
        spec = GridSpec.covering(
            s.origin_xy_m[0], s.origin_xy_m[1], s.origin_xy_m[0] + s.size_xy_m[0],
            s.origin_xy_m[1] + s.size_xy_m[1], s.resolution_m,
        )
        tables = ProbabilityTables(s.hit_probability, s.miss_probability, s.min_probability, s.max_probability)
        self.grid = ProbabilityGrid(spec, tables, fixed_size=s.fixed_size)
        self.layers = LayeredCostmap(
            self.grid, s.class_names, rule=s.combine_rule,
            occupied_threshold=s.occupied_threshold, free_threshold=s.free_threshold,
            existence_confirm=s.existence_confirm, clearance_decay_m=s.clearance_decay_m,
        )
        self._objects: tuple[ObjectFootprint, ...] = ()
        self._class_probs: dict[int, NDArray[np.float32]] = {}
        self._path: list[tuple[float, float, float, float]] = []
        #: Objects loaded from a file that the object map could not take over (ids offset).
        self._restored: list[ObjectFootprint] = []
        self._restored_probs: dict[int, NDArray[np.float32]] = {}
        self.frames_integrated = 0

    # --- updating ---------------------------------------------------------------------

    def integrate_frame(
        self, frame: Frame, T_map_camera: NDArray[np.float64] | None = None,
        objects: Sequence[ObjectFootprint] | None = None,
        class_probs: Mapping[int, NDArray[np.floating]] | None = None,
        T_map_body: NDArray[np.float64] | None = None,
        observations: Sequence[ObjectObservation] | None = None,
    ) -> FrameIntegration:
        """Add one frame: band scan into the grid, path point, and the objects.

        ``T_map_camera`` (4, 4) defaults to ``frame.T_map_camera``; the vehicle path records
        ``T_map_body``'s position when given, else the camera's. ``observations`` (this
        frame's object geometry, map frame) go to the object map, whose confirmed objects
        then replace the object set; or ``objects`` replaces it directly; with neither the
        object set is kept.
        """
        T = T_map_camera if T_map_camera is not None else frame.T_map_camera
        if T is None:
            raise MapError(f"frame {frame.index}: no camera pose (T_map_camera) to map it with")
        s = self.settings
        if observations is not None:
            if self.object_map is None:
                raise MapError("observations given but this semantic map has no object map")
            if objects is not None:
                raise MapError("give observations (for the object map) or objects, not both")
            view = CameraView(frame.depth_m, frame.intrinsics, np.asarray(T, np.float64),
                              (s.depth_min_m, s.depth_max_m))
            self.object_map.update(observations, frame.stamp_s, view)
            objects = self.object_map.footprints(confirmed_only=True)
            class_probs = dict(self.object_map.class_probabilities())
            if self._restored:
                objects, class_probs = self._with_restored(objects, class_probs)
        scan = extract_band_scan(
            frame.depth_m, frame.intrinsics, np.asarray(T, np.float64), s.scan_band,
            min_depth_m=s.depth_min_m, max_depth_m=s.depth_max_m, stride_px=s.scan_stride_px,
            min_hit_points=s.scan_min_hit_points, stamp_s=frame.stamp_s,
            column_stride_px=s.scan_column_stride_px,
        )
        grid_bounds = self.layers.update_scan(scan)
        pose = T_map_body if T_map_body is not None else T
        self._record_path(frame.stamp_s, np.asarray(pose, np.float64)[:3, 3])
        self.frames_integrated += 1
        obj_bounds = Bounds.empty()
        if objects is not None:
            obj_bounds = self.set_objects(objects, frame.stamp_s, class_probs)
        return FrameIntegration(scan, grid_bounds, obj_bounds)

    def set_objects(
        self, objects: Sequence[ObjectFootprint], stamp_s: float,
        class_probs: Mapping[int, NDArray[np.floating]] | None = None,
    ) -> Bounds:
        """Replace the object set (map frame). Objects whose margin is None get their class's.

        ``class_probs`` maps object id -> (K,) probabilities over ``settings.class_names``;
        objects without an entry count as certain of their ``class_name``. Grows the grid to
        cover the objects and their margins. Returns the touched window.
        """
        margins = dict(self.settings.class_margins_m)
        fps = tuple(fp.with_class_margin(margins) for fp in objects)
        if fps and not self.grid.fixed_size:
            reach = max(self.layers.rasters.reach_m(fp) for fp in fps) + self.grid.spec.resolution_m
            pts = np.concatenate([np.asarray(fp.polygon_xy_m, np.float64).reshape(-1, 2) for fp in fps])
            lo, hi = pts.min(axis=0) - reach, pts.max(axis=0) + reach
            self.grid.ensure_contains(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        probs = {int(k): np.asarray(v, np.float32).reshape(-1) for k, v in (class_probs or {}).items()}
        bounds = self.layers.update_objects(fps, stamp_s, probs)
        self._objects = fps
        self._class_probs = {fp.object_id: probs[fp.object_id] for fp in fps if fp.object_id in probs}
        return bounds

    def _with_restored(
        self, objects: Sequence[ObjectFootprint], class_probs: dict[int, NDArray[np.floating]],
    ) -> tuple[list[ObjectFootprint], dict[int, NDArray[np.floating]]]:
        """Objects loaded from a file whose object map could not restore its state stay until
        the object map has an object overlapping them (bounding boxes)."""
        out = list(objects)

        def overlaps(a: ObjectFootprint, b: ObjectFootprint) -> bool:
            pa, pb = np.asarray(a.polygon_xy_m), np.asarray(b.polygon_xy_m)
            return bool(np.all(pa.min(axis=0) <= pb.max(axis=0)) and np.all(pb.min(axis=0) <= pa.max(axis=0)))

        self._restored = [r for r in self._restored if not any(overlaps(r, o) for o in out)]
        for r in self._restored:
            out.append(r)
            if r.object_id in self._restored_probs:
                class_probs[r.object_id] = self._restored_probs[r.object_id]
        return out, class_probs

    def _record_path(self, stamp_s: float, xyz_m: NDArray[np.float64]) -> None:
        if self._path:
            last = np.asarray(self._path[-1][1:])
            if float(np.linalg.norm(xyz_m - last)) < self.settings.path_min_step_m:
                return
        self._path.append((float(stamp_s), float(xyz_m[0]), float(xyz_m[1]), float(xyz_m[2])))

    # --- reading ----------------------------------------------------------------------

    @property
    def spec(self) -> GridSpec:
        return self.grid.spec

    @property
    def class_names(self) -> tuple[str, ...]:
        return self.settings.class_names

    @property
    def objects(self) -> tuple[ObjectFootprint, ...]:
        return self._objects

    def class_probabilities(self, object_id: int) -> NDArray[np.float32]:
        """(K,) class probabilities of an object (one-hot on its class if none were given)."""
        if object_id in self._class_probs:
            return self._class_probs[object_id]
        for fp in self._objects:
            if fp.object_id == object_id:
                return self.layers.rasters.one_hot(fp.class_name)
        raise MapError(f"no object with id {object_id}")

    @property
    def path_xyz_m(self) -> NDArray[np.float64]:
        """(N, 3) recorded vehicle positions in the map frame."""
        if not self._path:
            return np.zeros((0, 3))
        return np.asarray(self._path, np.float64)[:, 1:]

    @property
    def path_stamps_s(self) -> NDArray[np.float64]:
        """(N,) times of the recorded path points."""
        return np.asarray([p[0] for p in self._path], np.float64)

    def costmap(self, band: VerticalBand | None = None) -> Costmap:
        """The costmap the planner is given for a vehicle band (default: the scan band): every
        layer combined, or the occupancy layer alone when ``settings.mode`` is ``metric``."""
        if self.settings.mode == "metric":
            return self.metric_costmap(band)
        return self.layers.costmap(band or self.settings.scan_band)

    def metric_costmap(self, band: VerticalBand | None = None) -> Costmap:
        """The occupancy layer alone as a costmap (no object footprints, margins or classes):
        what a plain 2D map built from the depth slice gives. ``band`` only labels the result
        (the grid holds what the scan band saw); default: the scan band."""
        layers = self.layers
        layers.sync_spec()
        spec = layers.spec
        band = band or self.settings.scan_band
        cost = layers.occupancy.costs(spec, band, spec.bounds)
        stamp = layers.occupancy.stamp_s
        return Costmap(spec, np.ascontiguousarray(cost), band, stamp_s=stamp if np.isfinite(stamp) else 0.0,
                       clearance_decay_m=self.settings.clearance_decay_m)

    def stale_layers(self, now_s: float) -> list[str]:
        """Layers older than ``settings.stale_after_s`` at ``now_s`` (empty = fresh map)."""
        return self.layers.stale_layers(now_s, self.settings.stale_after_s)

    def is_fresh(self, now_s: float | None = None) -> bool:
        """True if the grid was updated within ``settings.stale_after_s`` of ``now_s`` and so
        were the object layers, when this map has object input (an object map, or objects
        set before). ``now_s`` defaults to ``time.monotonic()``: the frames' clock must then
        be the monotonic clock (as a live camera source stamps them). A planner holds
        position when this is False."""
        now = time.monotonic() if now_s is None else float(now_s)
        max_age = self.settings.stale_after_s
        if not self.layers.occupancy.is_fresh(now, max_age):
            return False
        has_objects = self.object_map is not None or np.isfinite(self.layers.footprints.stamp_s)
        return not has_objects or self.layers.footprints.is_fresh(now, max_age)

    def nbytes(self) -> int:
        """Bytes held by the grid, cached costmap and object rasters."""
        return self.layers.nbytes()

    # --- persistence ------------------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write the whole map to one ``.npz`` file atomically (temp file in the same folder,
        fsync, rename): a crash leaves the previous file intact, never a partial one."""
        path = Path(path)
        meta = {
            "format_version": FILE_FORMAT_VERSION,
            "settings": self.settings.to_dict(),
            "grid": {"resolution_m": self.spec.resolution_m, "origin_xy_m": list(self.spec.origin_xy_m),
                     "shape_rc": list(self.spec.shape_rc)},
            "objects": [_footprint_to_dict(fp, self._class_probs.get(fp.object_id)) for fp in self._objects],
            "stamps_s": {layer.name: _finite_or_none(layer.stamp_s) for layer in self.layers.layers},
            "frames_integrated": self.frames_integrated,
            "object_map": None if self.object_map is None else self.object_map.to_dict(),
        }
        path_arr = np.asarray(self._path, np.float64).reshape(-1, 4)
        buf = io.BytesIO()
        np.savez_compressed(
            buf, grid_values=self.grid.values, path=path_arr,
            meta=np.frombuffer(json.dumps(meta).encode("utf-8"), np.uint8),
        )
        atomic_write_bytes(path, buf.getvalue())
        log.info("saved map (%dx%d cells, %d objects) to %s", *self.spec.shape_rc, len(self._objects), path)
        return path

    @classmethod
    def load(cls, path: str | Path, object_map: ObjectMap | None = None) -> "SemanticMap":
        """Read a map written by :meth:`save`. Raises :class:`MapError` naming the file and
        the missing or bad entry.

        ``object_map``: the object map to keep feeding; the saved object map is restored into
        it (:meth:`ObjectMap.load_dict`: ids, class probabilities, existence, footprints). When
        that dump does not fit (other classes, damaged), it starts empty instead and each saved
        object (id + ``RESTORED_ID_OFFSET``) stays until the object map has one overlapping it.
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except FileNotFoundError as exc:
            raise MapError(f"{path}: no such map file") from exc
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise MapError(f"{path}: not a readable map file ({exc})") from exc
        for key in ("grid_values", "path", "meta"):
            if key not in arrays:
                raise MapError(f"{path}: missing entry {key!r}")
        try:
            meta = json.loads(arrays["meta"].tobytes().decode("utf-8"))
            version = meta.get("format_version")
            if version != FILE_FORMAT_VERSION:
                raise MapError(f"{path}: format_version {version!r}, this program reads {FILE_FORMAT_VERSION}")
            settings = SemanticMapSettings.from_dict(meta["settings"])
            g = meta["grid"]
            spec = GridSpec(float(g["resolution_m"]), tuple(g["origin_xy_m"]), tuple(g["shape_rc"]))
            out = cls(settings, object_map)
            saved_objects = meta.get("object_map")
            restore_objects = False
            if object_map is not None and saved_objects:
                try:
                    object_map.load_dict(saved_objects)
                except MapError as exc:
                    restore_objects = True
                    log.warning("%s: the saved object map cannot be restored (%s); it starts empty and the "
                                "saved objects stay until it sees them again", path, exc)
            out.grid.spec = spec
            out.grid.set_values(arrays["grid_values"])
            out.layers.sync_spec()
            out._restore_layers(meta["objects"], meta.get("stamps_s", {}), restore_objects)
            out._path = [tuple(map(float, row)) for row in arrays["path"].reshape(-1, 4)]  # type: ignore[misc]
            out.frames_integrated = int(meta.get("frames_integrated", 0))
        except MapError:
            raise
        except (KeyError, TypeError, ValueError, UnicodeDecodeError) as exc:
            raise MapError(f"{path}: corrupt map metadata ({type(exc).__name__}: {exc})") from exc
        return out

    def _restore_layers(self, records: Sequence[Mapping[str, Any]], stamps_s: Mapping[str, Any],
                        keep_apart: bool) -> None:
        """Set the saved objects and layer times; ``keep_apart``: beside the object map, ids offset."""
        objects = [_footprint_from_dict(d) for d in records]
        probs = {int(d["object_id"]): np.asarray(d["class_probs"], np.float32)
                 for d in records if d.get("class_probs") is not None}
        obj_stamp = stamps_s.get("objects")
        if keep_apart:
            objects = [replace(o, object_id=o.object_id + RESTORED_ID_OFFSET) for o in objects]
            probs = {k + RESTORED_ID_OFFSET: v for k, v in probs.items()}
            self._restored, self._restored_probs = list(objects), dict(probs)
        self.set_objects(objects, float("-inf") if obj_stamp is None else obj_stamp, probs)
        for layer in self.layers.layers:
            st = stamps_s.get(layer.name)
            layer.stamp_s = float("-inf") if st is None else float(st)


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _footprint_to_dict(fp: ObjectFootprint, class_probs: NDArray[np.float32] | None) -> dict[str, Any]:
    return {
        "object_id": fp.object_id, "class_name": fp.class_name,
        "polygon_xy_m": np.asarray(fp.polygon_xy_m, np.float64).round(6).tolist(),
        "z_min_m": fp.z_min_m, "z_max_m": fp.z_max_m, "existence": fp.existence,
        "margin_m": fp.margin_m,
        "class_probs": None if class_probs is None else [float(p) for p in class_probs],
    }


def _footprint_from_dict(d: Mapping[str, Any]) -> ObjectFootprint:
    return ObjectFootprint(
        object_id=int(d["object_id"]), class_name=str(d["class_name"]),
        polygon_xy_m=np.asarray(d["polygon_xy_m"], np.float64).reshape(-1, 2),
        z_min_m=float(d["z_min_m"]), z_max_m=float(d["z_max_m"]),
        existence=float(d["existence"]), margin_m=_margin_or_none(d.get("margin_m")),
    )


def _margin_or_none(value: Any) -> float | None:
    """A saved margin; None (or a file from before margins were saved) means the class's."""
    return None if value is None else float(value)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temp file in the same folder and ``os.replace``.

    On any failure the temp file is removed and ``path`` keeps its previous content.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o644)  # mkstemp makes 0600; maps are for other tools to read
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            raise MapError(f"{path}: could not write ({exc})") from exc
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)
