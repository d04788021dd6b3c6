"""RealSense-like RGB-D frames of a simulated :class:`~companion.sim.world.Room` from any pose.

One ray per pixel is cast with Open3D's tensor ``RaycastingScene`` (Embree) against a triangle
mesh per primitive box (walls, floor, ceiling and every furniture part). Each primitive keeps
its owner (object id, 0 for the building, negative for clutter) and class index, so the instance and class masks
come straight from the noise-free geometry.

Pixel convention: pixel ``(u, v)`` samples the ray through image coordinates ``(u, v)`` with
pixel centres at integer coordinates (OpenCV's convention), i.e. the camera-frame direction
``((u - cx) / fx, (v - cy) / fy, 1)``. That is exactly what :func:`semmap.pointcloud.backproject`
inverts, so back-projecting a noise-free rendered depth reproduces the surface points. Because
the direction's z component is 1, the ray parameter ``t_hit`` *is* the z-depth.

Appearance: the object's or building's base colour, Lambertian shading from the primitive's
normal (a ceiling light direction plus a camera headlight and ambient), and a procedural
texture per material fixed to the surfaces (floor planks, wood grain, fabric weave, mottled
paint), so optical flow and feature trackers find stable corners that move with the geometry.

Depth and colour: what a D455 does to the perfect images (:mod:`companion.sim.d455`): range
noise, flying pixels, holes, minimum range, quantisation; auto-exposure and motion blur. All
randomness comes from a seeded :class:`numpy.random.Generator`, so runs are reproducible.

Open3D is imported lazily (the ``sim`` extra), so importing this module costs nothing.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import SimulationError
from companion.sim.d455 import (
    SHINY_COS,
    ColorModel,
    DepthNoise,
    apply_color,
    apply_depth,
    exposure_gain,
    rotation_blur_px,
)
from companion.sim.furniture import SHINY_CLUTTER
from companion.sim.world import Box, Room
from semmap.frames import Transform
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

#: Material (texture) indices.
MAT_WALL, MAT_FLOOR, MAT_CEILING, MAT_WOOD, MAT_FABRIC, MAT_BOARD = range(6)
_CLASS_MATERIAL = {
    "plant": MAT_FABRIC,
    "box": MAT_BOARD,
    "chair": MAT_WOOD,
    "desk": MAT_WOOD,
    "coffee_table": MAT_WOOD,
    "conference_table": MAT_WOOD,
    "sofa": MAT_FABRIC,
    "whiteboard": MAT_BOARD,
}
#: Texture tiles: TEX_SIZE x TEX_SIZE texels of TEXEL_M metres (a power of two, so the
#: wrap-around is a bit mask).
TEX_SIZE = 256
TEXEL_M = 0.01
#: Floor and ceiling extend this far beyond the walls (seen through doorways).
FLOOR_MARGIN_M = 3.0
CEILING_COLOR_RGB = (235, 235, 230)
#: Colour of pixels whose ray hits nothing (outside the building, beyond the floor).
BACKGROUND_RGB = (30, 30, 35)
_INVALID_GEOMETRY = 4294967295  # Open3D's RaycastingScene.INVALID_ID
#: The six faces of a box mesh in triangle order (triangles 2k, 2k+1 are face k): the local
#: axis the face is normal to and the normal's sign. Must match :func:`_box_mesh_arrays`.
_FACE_AXES = ((2, -1.0), (2, 1.0), (1, -1.0), (1, 1.0), (0, -1.0), (0, 1.0))
#: In-plane texture axes (u, v) of a face normal to local axis 0, 1, 2.
_FACE_PLANE = ((1, 2), (0, 2), (0, 1))
#: Primitive indices of the floor and ceiling slabs (the first two building boxes).
FLOOR_PRIM, CEILING_PRIM = 0, 1
#: Shading weights: ambient + sun * max(0, n.L) + headlight * |n.d|.
AMBIENT, SUN, HEADLIGHT = 0.38, 0.42, 0.25


@dataclass(frozen=True, eq=False)
class VisibleObject:
    """Ground truth of one object seen in a frame (map frame, metres).

    ``pixel_count`` counts its pixels in the instance mask (occlusion included);
    ``bbox_xyxy_px`` is the mask's bounding box (half-open max, like detector boxes);
    ``footprint_xy_m`` (4, 2) the oriented footprint of the whole object; ``z_range_m`` its
    vertical extent above the floor; ``parts`` its primitive boxes.
    """

    object_id: int
    class_name: str
    class_index: int
    pixel_count: int
    bbox_xyxy_px: tuple[float, float, float, float]
    center_xy_m: tuple[float, float]
    yaw_rad: float
    size_m: tuple[float, float, float]
    footprint_xy_m: NDArray[np.float64]
    z_range_m: tuple[float, float]
    parts: tuple[Box, ...]

    @property
    def height_m(self) -> float:
        """Top of the object above the floor, metres."""
        return self.z_range_m[1]


def _box_mesh_arrays(box: Box) -> tuple[NDArray[np.float32], NDArray[np.int32]]:
    """(8, 3) vertices in the map frame and (12, 3) outward-wound triangles of a box."""
    hx, hy, hz = (s / 2.0 for s in box.size_m)
    corners = np.array(
        [[sx * hx, sy * hy, sz * hz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)]
    )
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    verts = corners @ R.T + np.asarray(box.center_m)
    # Vertex index = ix + 2*iy + 4*iz. Counter-clockwise seen from outside.
    tris = np.array(
        [
            [0, 2, 1], [1, 2, 3],  # z-
            [4, 5, 6], [5, 7, 6],  # z+
            [0, 1, 4], [1, 5, 4],  # y-
            [2, 6, 3], [3, 6, 7],  # y+
            [0, 4, 2], [2, 4, 6],  # x-
            [1, 3, 5], [3, 7, 5],  # x+
        ]
    )
    return verts.astype(np.float32), tris.astype(np.int32)


def _box_mesh(o3d: Any, box: Box) -> Any:
    """An Open3D tensor triangle mesh of a box (:func:`_box_mesh_arrays`)."""
    verts, tris = _box_mesh_arrays(box)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(verts)
    mesh.triangle.indices = o3d.core.Tensor(tris)
    return mesh


def _checked_pose(T_map_camera: Transform) -> NDArray[np.float64]:
    """The camera pose as a float (4, 4) array, or a :class:`SimulationError` naming what is wrong."""
    T = np.asarray(T_map_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise SimulationError(f"T_map_camera must be a finite (4, 4) transform (got shape {T.shape})")
    return T


def _smooth_noise(rng: np.random.Generator, size: int, blur_px: float) -> NDArray[np.float32]:
    """(size, size) zero-mean, unit-std noise blurred with wrap-around (tiles seamlessly)."""
    import cv2

    n = rng.standard_normal((size, size)).astype(np.float32)
    if blur_px > 0:
        pad = int(3 * blur_px) + 1
        big = np.pad(n, pad, mode="wrap")
        big = np.asarray(cv2.GaussianBlur(big, (0, 0), blur_px), dtype=np.float32)
        n = big[pad:-pad, pad:-pad]
    n -= n.mean()
    return n / max(float(n.std()), 1e-6)


def make_textures(seed: int, size: int = TEX_SIZE) -> NDArray[np.float32]:
    """(6, size, size) luminance factors (about 0.6..1.2) for the materials ``MAT_*``.

    Seamlessly tiling, so a texel index wraps with a bit mask. Deterministic in ``seed``.
    """
    rng = np.random.default_rng([seed, 7919])
    tex = np.ones((6, size, size), dtype=np.float32)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)

    # Paint: gentle low-frequency mottling and a little fine grain.
    tex[MAT_WALL] = 1.0 + 0.035 * _smooth_noise(rng, size, 14.0) + 0.02 * _smooth_noise(rng, size, 1.0)
    tex[MAT_CEILING] = 1.0 + 0.03 * _smooth_noise(rng, size, 10.0)

    # Floor: planks 16 texels (16 cm) wide along u, random lengths, per-plank tint, grain and
    # dark seams: corners at plank ends give the tracker's optical flow something to hold.
    floor = np.empty((size, size), dtype=np.float32)
    plank_w = 16
    grain = _smooth_noise(rng, size, 1.5)
    for row0 in range(0, size, plank_w):
        rows = slice(row0, row0 + plank_w)
        cuts = [0]
        while cuts[-1] < size:
            cuts.append(cuts[-1] + int(rng.integers(48, 120)))
        cuts[-1] = size
        for a, b in zip(cuts[:-1], cuts[1:], strict=False):
            floor[rows, a:b] = rng.uniform(0.75, 1.1)
            floor[rows, a:min(a + 1, b)] = 0.45  # end seam
        floor[row0, :] = 0.5  # side seam
    streak = np.sin(2 * np.pi * (yy / 5.3 + 0.8 * _smooth_noise(rng, size, 6.0)))
    tex[MAT_FLOOR] = floor * (1.0 + 0.06 * streak + 0.05 * grain)

    # Wood: grain streaks along u with wobble, plus knots of darker tone.
    wobble = _smooth_noise(rng, size, 8.0)
    rings = np.sin(2 * np.pi * (yy / 7.0 + 0.6 * wobble))
    knots = np.clip(_smooth_noise(rng, size, 4.0) - 2.0, 0.0, None)
    tex[MAT_WOOD] = 1.0 + 0.10 * rings + 0.05 * _smooth_noise(rng, size, 1.0) - 0.25 * knots

    # Fabric: a fine weave and soft blotches.
    weave = np.sin(np.pi * xx / 1.5) * np.sin(np.pi * yy / 1.5)
    tex[MAT_FABRIC] = 1.0 + 0.06 * weave + 0.08 * _smooth_noise(rng, size, 5.0)

    # Whiteboard: nearly uniform, faint smudges, and a few marker strokes.
    board = 1.0 + 0.02 * _smooth_noise(rng, size, 8.0)
    for _ in range(6):
        v0 = int(rng.integers(0, size))
        u0, u1 = sorted(int(x) for x in rng.integers(0, size, 2))
        board[v0:v0 + 2, u0:u1] = 0.35
    tex[MAT_BOARD] = board
    return np.clip(tex, 0.3, 1.3).astype(np.float32)


class RoomRenderer:
    """Renders RGB-D :class:`Frame` s of one room (not thread-safe: one caller at a time).

    ``class_names`` gives the class index of the ``"class"`` mask (the config's class order);
    objects whose class is not in it get -1. ``seed`` seeds the textures and, when no
    generator is passed to :meth:`render`, the per-frame noise (``(seed, frame index)``).
    ``n_threads`` are Open3D's ray-casting threads (0: all cores); ``shade_threads`` (0: up to
    two, one per core) split the per-pixel numpy work into horizontal bands run side by side.
    """

    def __init__(
        self,
        room: Room,
        class_names: Sequence[str],
        intrinsics: CameraIntrinsics,
        noise: DepthNoise | None = None,
        seed: int = 0,
        color: ColorModel | None = None,
        light_dir_map: tuple[float, float, float] = (0.35, 0.25, 1.0),
        rgb_noise_std: float = 2.0,
        n_threads: int = 0,
        shade_threads: int = 0,
    ) -> None:
        try:
            import open3d as o3d
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise SimulationError(
                "the simulated camera needs Open3D: install the 'sim' extra (pip install .[sim])"
            ) from exc
        self._o3d: Any = o3d
        self.room = room
        self.class_names = list(class_names)
        self.intrinsics = intrinsics
        self.noise = noise or DepthNoise()
        self.color = color or ColorModel()
        #: (stamp_s, camera rotation) of the last frame: a fast turn between frames blurs.
        self._last_view: tuple[float, NDArray[np.float64]] | None = None
        self.seed = int(seed)
        self.rgb_noise_std = float(rgb_noise_std)
        self.n_threads = int(n_threads)
        #: Threads that shade the colour image in bands (1: shade in the caller's thread).
        self.shade_threads = int(shade_threads) if shade_threads else min(2, os.cpu_count() or 1)
        self._pool: ThreadPoolExecutor | None = None
        #: Intersect the floor and ceiling analytically when the camera is between them (the
        #: same result as casting against their slabs, for a third less ray-casting time).
        self.analytic_slabs = True
        light = np.asarray(light_dir_map, dtype=np.float32)
        self._light = light / np.linalg.norm(light)
        self._textures = make_textures(self.seed)
        self._tex_flat = self._textures.reshape(-1)
        self._build_scene()
        # Per-pixel camera-frame ray directions (x, y, 1) as contiguous columns: the per-frame
        # work is elementwise (no BLAS, whose threads stall on a busy CPU).
        dirs = self._pixel_directions(intrinsics)
        self._xc = np.ascontiguousarray(dirs[:, 0])
        self._yc = np.ascontiguousarray(dirs[:, 1])
        self._inv_len = (1.0 / np.sqrt(self._xc**2 + self._yc**2 + 1.0)).astype(np.float32)
        self._rays = np.empty((dirs.shape[0], 6), dtype=np.float32)
        n_px = dirs.shape[0]
        self._noise_bank = np.random.default_rng([self.seed, 15485863]).standard_normal(
            4 * n_px, dtype=np.float32)
        self._slab_bufs = {
            "t": np.empty(n_px, np.float32), "coord": np.empty(n_px, np.float32),
            "down": np.empty(n_px, bool), "take": np.empty(n_px, bool), "ok": np.empty(n_px, bool),
        }
        self._objects = {o.object_id: o for o in room.objects}
        # The furniture alone, built on first use by :meth:`silhouette_px`.
        self._object_scene: Any = None
        self._object_owner = np.zeros(0, dtype=np.int64)

    # --- scene -------------------------------------------------------------------------

    def _building_boxes(self) -> list[tuple[Box, int, tuple[int, int, int]]]:
        """Walls, floor and ceiling with their material and colour."""
        r = self.room
        m = FLOOR_MARGIN_M
        cx, cy = r.width_m / 2.0, r.depth_m / 2.0
        size_xy = (r.width_m + 2 * m, r.depth_m + 2 * m)
        out: list[tuple[Box, int, tuple[int, int, int]]] = [
            (Box((cx, cy, -0.05), (*size_xy, 0.1)), MAT_FLOOR, r.floor_color_rgb),
            (Box((cx, cy, r.wall_height_m + 0.05), (*size_xy, 0.1)), MAT_CEILING, CEILING_COLOR_RGB),
        ]
        out.extend((w, MAT_WALL, r.wall_color_rgb) for w in r.walls)
        return out

    def _build_scene(self) -> None:
        o3d = self._o3d
        scene = o3d.t.geometry.RaycastingScene(nthreads=self.n_threads)
        # The same scene without the floor and ceiling slabs: a camera between them finds
        # those two planes analytically, and Embree, spared the rays that end on them,
        # traverses a third less (see :meth:`cast`).
        inner = o3d.t.geometry.RaycastingScene(nthreads=self.n_threads)
        rng = np.random.default_rng([self.seed, 104729])
        entries: list[tuple[Box, int, int, int, tuple[int, int, int]]] = [
            (b, 0, -1, mat, col) for b, mat, col in self._building_boxes()
        ]
        for obj in (*self.room.objects, *self.room.clutter):
            cls = self.class_names.index(obj.class_name) if obj.class_name in self.class_names else -1
            if obj.object_id < 0:
                cls = -1  # clutter is never one of our classes, whatever it is called
            mat = _CLASS_MATERIAL.get(obj.class_name, MAT_WOOD)
            entries.extend((p, obj.object_id, cls, mat, obj.color_rgb) for p in obj.parts)
        n = len(entries)
        cls_name_of = {o.object_id: o.class_name for o in self.room.clutter}
        # Per-primitive tables, one extra row (index n) for rays that hit nothing.
        self._owner = np.zeros(n + 1, dtype=np.int32)
        self._class = np.full(n + 1, -1, dtype=np.int16)
        self._color = np.zeros((n + 1, 3), dtype=np.float32)
        self._color[n] = BACKGROUND_RGB
        self._shiny = np.zeros(n + 1, dtype=bool)
        # Per-face tables (6 faces per primitive in _FACE_AXES order, plus the miss row):
        # world normal, sun-light term, and the affine map from a map-frame point to texel
        # coordinates (u, v) on that face, offset into the material's texture.
        nf = 6 * n
        self._face_normal = np.zeros((nf + 1, 3), dtype=np.float32)
        self._face_sun = np.zeros(nf + 1, dtype=np.float32)
        self._face_tex = np.zeros((nf + 1, 2, 4), dtype=np.float32)
        self._face_tex_base = np.zeros(nf + 1, dtype=np.intp)
        self._boxes: list[Box] = []
        for i, (box, owner, cls, mat, col) in enumerate(entries):
            mesh = _box_mesh(o3d, box)
            gid = int(scene.add_triangles(mesh))
            if gid != i:
                raise SimulationError(f"unexpected Open3D geometry id {gid} for primitive {i}")
            if i not in (FLOOR_PRIM, CEILING_PRIM):
                inner_gid = int(inner.add_triangles(mesh))
                if inner_gid != i - 2:
                    raise SimulationError(f"unexpected Open3D geometry id {inner_gid} for primitive {i}")
            self._owner[i] = owner
            self._class[i] = cls
            self._color[i] = col
            self._shiny[i] = (mat == MAT_BOARD and owner > 0) or (owner < 0 and cls_name_of.get(owner) in SHINY_CLUTTER)
            # Building surfaces share one texture frame so seams line up; furniture parts get
            # a random offset so two chairs do not look stamped from one mould.
            off = rng.uniform(0.0, TEX_SIZE * TEXEL_M, 2) if owner != 0 else np.zeros(2)
            c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
            axes = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # local x, y, z in map
            centre = np.asarray(box.center_m, dtype=np.float64)
            for k, (axis, sign) in enumerate(_FACE_AXES):
                f = 6 * i + k
                normal = sign * axes[axis]
                self._face_normal[f] = normal
                self._face_sun[f] = max(0.0, float(normal @ self._light))
                for row, (plane_axis, o) in enumerate(zip(_FACE_PLANE[axis], off, strict=True)):
                    a = axes[plane_axis]
                    self._face_tex[f, row, :3] = a / TEXEL_M
                    self._face_tex[f, row, 3] = (o - a @ centre) / TEXEL_M
                self._face_tex_base[f] = mat * TEX_SIZE * TEX_SIZE
            self._boxes.append(box)
        self._face_flat_light = (AMBIENT + SUN * self._face_sun).astype(np.float32)
        self._color_cols = [np.ascontiguousarray(self._color[:, k]) for k in range(3)]
        self._albedo = (self._color.mean(axis=1) / 255.0).astype(np.float32)
        self._n_prims = n
        self._scene = scene
        self._inner_scene = inner
        slab = self._boxes[FLOOR_PRIM]
        hx, hy = slab.size_m[0] / 2, slab.size_m[1] / 2
        self._slab_xy_m = (slab.center_m[0] - hx, slab.center_m[0] + hx,
                           slab.center_m[1] - hy, slab.center_m[1] + hy)
        log.debug("raycasting scene: %d primitives (%d objects)", n, len(self.room.objects))

    @property
    def n_primitives(self) -> int:
        """Number of primitive boxes in the scene (floor, ceiling, walls, furniture parts)."""
        return self._n_prims

    @staticmethod
    def _pixel_directions(intr: CameraIntrinsics) -> NDArray[np.float32]:
        """(H*W, 3) camera-frame ray directions with z = 1 (see the module's pixel convention)."""
        u = (np.arange(intr.width_px, dtype=np.float64) - intr.cx_px) / intr.fx_px
        v = (np.arange(intr.height_px, dtype=np.float64) - intr.cy_px) / intr.fy_px
        U, V = np.meshgrid(u, v)
        return np.stack([U, V, np.ones_like(U)], axis=-1).reshape(-1, 3).astype(np.float32)

    # --- rendering ---------------------------------------------------------------------

    def cast(self, T_map_camera: Transform) -> dict[str, Any]:
        """Noise-free ray cast from a camera pose (4, 4), map frame, optical axes.

        Returns flat (H*W,) arrays, row-major over the image: ``"depth_m"`` float32 z-depth
        (inf on a miss), ``"prim"`` primitive index (``n_primitives`` on a miss), ``"face"``
        face index ``6 * prim + k`` (``6 * n_primitives`` on a miss), and ``"T"`` the pose.
        """
        T = _checked_pose(T_map_camera)
        R = T[:3, :3].astype(np.float32)
        rays = self._rays  # reused: a fresh 7 MB buffer per frame costs page faults
        n_px = rays.shape[0]
        bands = self._bands(self.intrinsics.height_px, self.intrinsics.width_px)

        def set_rays(lo: int, hi: int) -> None:
            rays[lo:hi, :3] = T[:3, 3]
            xc, yc = self._xc[lo:hi], self._yc[lo:hi]
            for i in range(3):  # map-frame direction = R @ (x, y, 1)
                col = rays[lo:hi, 3 + i]
                np.multiply(xc, R[i, 0], out=col)
                col += R[i, 1] * yc
                col += R[i, 2]

        self._run_bands(set_rays, bands)
        o3d = self._o3d
        ox, oy, oz = (float(v) for v in T[:3, 3])
        analytic = self.analytic_slabs and 0.0 < oz < self.room.wall_height_m
        scene, first = (self._inner_scene, 2) if analytic else (self._scene, 0)
        ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self.n_threads)
        t_hit = ans["t_hit"].numpy()
        gids = ans["geometry_ids"].numpy().view(np.int32)  # INVALID_ID reads as -1
        tri = ans["primitive_ids"].numpy().view(np.int32)
        prim = np.empty(n_px, dtype=np.intp)
        face = np.empty(n_px, dtype=np.intp)
        n_prims = self._n_prims

        def decode(lo: int, hi: int) -> None:
            g, p, f = gids[lo:hi], prim[lo:hi], face[lo:hi]
            miss = g < 0
            np.add(g, first, out=p)
            p[miss] = n_prims
            np.multiply(p, 6, out=f)
            f += tri[lo:hi] >> 1
            f[miss] = 6 * n_prims
            if analytic:
                bufs = {k: v[lo:hi] for k, v in self._slab_bufs.items()}
                self._add_slabs(rays[lo:hi], ox, oy, oz, t_hit[lo:hi], p, f, bufs)

        self._run_bands(decode, bands)
        return {"depth_m": t_hit, "prim": prim, "face": face, "T": T}

    def _run_bands(self, fn: Any, bands: list[tuple[int, int]]) -> None:
        """``fn(lo, hi)`` for every band, on the shading pool when there are several."""
        if len(bands) == 1:
            fn(*bands[0])
            return
        futures = [self._shade_pool().submit(fn, lo, hi) for lo, hi in bands]
        for fut in futures:
            fut.result()

    def _add_slabs(
        self, rays: NDArray[np.float32], ox: float, oy: float, oz: float,
        t_hit: NDArray[np.float32], prim: NDArray[np.intp], face: NDArray[np.intp],
        b: dict[str, NDArray[Any]],
    ) -> None:
        """In place: where the floor (z = 0, its top face) or the ceiling (z = H, its bottom
        face) is nearer than the scene's hit, and its slab exists there, take it.

        Written with preallocated buffers: fresh multi-megabyte temporaries each frame cost
        more in page faults than the arithmetic. ``b`` holds those buffers (same length as
        the rays), so bands of one frame can run side by side.
        """
        dz = rays[:, 5]
        down = np.less(dz, 0.0, out=b["down"])
        t_p = b["t"]
        t_p.fill(self.room.wall_height_m - oz)
        np.copyto(t_p, np.float32(-oz), where=down)
        x0, x1, y0, y1 = self._slab_xy_m
        take, ok, coord = b["take"], b["ok"], b["coord"]
        # Horizontal rays give inf (and inf * 0 = nan), which every test below rejects.
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(t_p, dz, out=t_p)
            np.greater(t_p, 0.0, out=take)
            take &= np.less(t_p, t_hit, out=ok)
            for col, origin, lo, hi in ((3, ox, x0, x1), (4, oy, y0, y1)):
                np.multiply(t_p, rays[:, col], out=coord)
                coord += np.float32(origin)
                take &= np.greater_equal(coord, lo, out=ok)
                take &= np.less_equal(coord, hi, out=ok)
        np.copyto(t_hit, t_p, where=take)
        take_floor = np.logical_and(take, down, out=ok)
        np.copyto(prim, FLOOR_PRIM, where=take_floor)
        np.copyto(face, 6 * FLOOR_PRIM + 1, where=take_floor)  # top face (k = 1, z+)
        take_ceiling = np.logical_and(take, np.logical_not(down, out=down), out=take)
        np.copyto(prim, CEILING_PRIM, where=take_ceiling)
        np.copyto(face, 6 * CEILING_PRIM + 0, where=take_ceiling)  # bottom face (k = 0, z-)

    def render(
        self,
        T_map_camera: Transform,
        stamp_s: float = 0.0,
        index: int = 0,
        rng: np.random.Generator | None = None,
    ) -> Frame:
        """One RGB-D frame from camera pose ``T_map_camera`` (4, 4; map frame ENU, optical
        camera axes).

        ``rng`` drives all noise; None seeds a generator from ``(seed, index)``, so the same
        pose and index always give the same frame. Masks are from the noise-free geometry.

        After the ray cast (Open3D, all cores), the colour is shaded in horizontal bands on a
        small thread pool while this thread adds the depth noise and the masks: numpy's
        gathers and ufuncs release the GIL, so the per-pixel work uses both cores of the
        drone's computer. The bands only split the work; the frame is the same bit for bit
        whatever the thread count (every random draw happens in this thread, in a fixed order).
        """
        intr = self.intrinsics
        H, W = intr.height_px, intr.width_px
        if rng is None:
            rng = np.random.default_rng([self.seed, int(index) & 0x7FFFFFFF])
        c = self.cast(T_map_camera)
        prim = c["prim"]
        n_px = H * W
        rgb = np.empty((n_px, 3), dtype=np.uint8)
        lum_noise = self._gaussian(rng, n_px) if self.rgb_noise_std > 0 else None
        tables = self._shade_tables(c["T"])
        bands = self._bands(H, W)
        pool = self._shade_pool() if len(bands) > 1 else None
        if pool is None:
            for lo, hi in bands:
                self._shade_band(c, tables, lo, hi, lum_noise, rgb)
            depth = self._noisy_depth(c["depth_m"].reshape(H, W), rng, c)
        else:
            futures = [pool.submit(self._shade_band, c, tables, lo, hi, lum_noise, rgb)
                       for lo, hi in bands]
            try:
                depth = self._noisy_depth(c["depth_m"].reshape(H, W), rng, c)
            finally:
                for fut in futures:
                    fut.result()
        image = self._camera_color(rgb.reshape(H, W, 3), c["T"], float(stamp_s), rng)
        masks: dict[str, NDArray[np.generic]] = {
            "instance": self._owner[prim].reshape(H, W),
            "class": self._class[prim].reshape(H, W),
        }
        return Frame(
            stamp_s=float(stamp_s), rgb=image, depth_m=depth, intrinsics=intr,
            T_map_camera=np.array(T_map_camera, dtype=np.float64), index=int(index), masks=masks,
        )

    def _camera_color(self, rgb: NDArray[np.uint8], T: NDArray[np.float64], stamp_s: float,
                      rng: np.random.Generator) -> NDArray[np.uint8]:
        """Auto-exposure, and motion blur from the turn since the previous frame (a frame
        whose stamp does not follow the previous one within half a second is not blurred)."""
        cm = self.color
        gain = exposure_gain(rgb, cm, rng)
        blur = (0.0, 0.0)
        R = np.array(T[:3, :3], dtype=np.float64)
        if cm.motion_blur and self._last_view is not None:
            dt = stamp_s - self._last_view[0]
            if 0.0 < dt <= 0.5:
                blur = rotation_blur_px(self._last_view[1], R, dt, self.intrinsics.fx_px, cm.exposure_s * gain)
        self._last_view = (stamp_s, R)
        return apply_color(rgb, gain, blur)

    def _bands(self, H: int, W: int) -> list[tuple[int, int]]:
        """Flat pixel ranges ``[lo, hi)`` of ``shade_threads`` horizontal bands of whole rows."""
        k = max(1, min(int(self.shade_threads), H))
        rows = np.linspace(0, H, k + 1).round().astype(int)
        return [(int(a) * W, int(b) * W) for a, b in zip(rows[:-1], rows[1:], strict=True)]

    def _shade_pool(self) -> ThreadPoolExecutor:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(
                max_workers=max(1, int(self.shade_threads)), thread_name_prefix="render-shade")
        return self._pool

    def close(self) -> None:
        """Stop the shading threads (the renderer stays usable: they restart on demand)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _shade_tables(self, T: NDArray[np.float64]) -> dict[str, Any]:
        """Per-face tables for one pose (F = 6 * primitives + 1 rows, small).

        ``n_cam`` (F, 3): face normals in the camera frame (rows = R^T n), for the headlight
        term ``|n.d| / |d| = |n_cam . (x, y, 1)| / |(x, y, 1)|``. For the texture, a face maps
        a map-frame point p to texel coordinates ``a . p + b``; with the hit at
        ``p = o + t R (x, y, 1)`` that is ``(a . o + b) + t (R^T a) . (x, y, 1)``: ``a_cam``
        (2, F, 3) holds ``R^T a`` and ``const`` (2, F) holds ``a . o + b`` per texture axis.
        """
        R, o = T[:3, :3], T[:3, 3]
        n_cam = (self._face_normal @ R).astype(np.float32)
        a_cam, const = [], []
        for row in (0, 1):
            A = self._face_tex[:, row, :3]  # (F, 3) texel axis per metre, map frame
            const.append((A @ o + self._face_tex[:, row, 3]).astype(np.float32))
            a_cam.append((A @ R).astype(np.float32))
        return {
            "n_cam": [np.ascontiguousarray(n_cam[:, k]) for k in range(3)],
            "a_cam": [[np.ascontiguousarray(a[:, k]) for k in range(3)] for a in a_cam],
            "const": const,
        }

    def _shade_band(
        self, c: dict[str, Any], tables: dict[str, Any], lo: int, hi: int,
        lum_noise: NDArray[np.float32] | None, rgb_out: NDArray[np.uint8],
    ) -> None:
        """Shade flat pixels ``[lo, hi)`` into ``rgb_out`` (H*W, 3) uint8: base colour x
        Lambert shading x material texture (+ sensor noise)."""
        face = c["face"][lo:hi]
        prim = c["prim"][lo:hi]
        xc, yc = self._xc[lo:hi], self._yc[lo:hi]
        hit = face < 6 * self._n_prims
        nx, ny, nz = tables["n_cam"]
        ndotd = nx[face] * xc
        ndotd += ny[face] * yc
        ndotd += nz[face]
        lum = np.abs(ndotd)
        lum *= self._inv_len[lo:hi]
        lum *= np.float32(HEADLIGHT)
        lum += self._face_flat_light[face]
        lum *= self._texture_band(c["depth_m"][lo:hi], face, hit, xc, yc, tables)
        if lum_noise is not None:
            lum += lum_noise[lo:hi] * np.float32(self.rgb_noise_std / 128.0)
        lum[~hit] = 1.0
        out = rgb_out[lo:hi]
        for k in range(3):
            ch = self._color_cols[k][prim] * lum
            np.clip(ch, 0.0, 255.0, out=ch)
            out[:, k] = ch

    def _texture_band(
        self, depth_m: NDArray[np.float32], face: NDArray[np.intp], hit: NDArray[np.bool_],
        xc: NDArray[np.float32], yc: NDArray[np.float32], tables: dict[str, Any],
    ) -> NDArray[np.float32]:
        """Texture factor of a band's pixels, from each hit's texel coordinates on its face
        (see :meth:`_shade_tables`): a few gathers and products per pixel."""
        t = np.where(hit, depth_m, np.float32(0.0))
        mask = TEX_SIZE - 1
        idx = self._face_tex_base[face]
        for row, stride in ((0, 1), (1, TEX_SIZE)):
            ax, ay, az = tables["a_cam"][row]
            coord = ax[face] * xc
            coord += ay[face] * yc
            coord += az[face]
            coord *= t
            coord += tables["const"][row][face]
            idx += (np.floor(coord).astype(np.intp) & mask) * stride
        return self._tex_flat[idx]

    def _gaussian(self, rng: np.random.Generator, n: int) -> NDArray[np.float32]:
        """(n,) standard normal float32: a window of a fixed bank at a random offset.

        Drawing 300 k normals costs ~3 ms; a window costs a copy. Neighbouring pixels stay
        independent, and frames draw fresh offsets, so pixels do not repeat frame to frame.
        """
        bank = self._noise_bank
        if n > bank.shape[0] // 2:
            return rng.standard_normal(n, dtype=np.float32)
        start = int(rng.integers(0, bank.shape[0] - n))
        return bank[start:start + n]

    def _noisy_depth(self, z: NDArray[np.float32], rng: np.random.Generator,
                     c: dict[str, Any]) -> NDArray[np.float32]:
        """(H, W) float32 metres with the D455 depth model (:func:`~companion.sim.d455.apply_depth`); 0 where invalid."""
        nz = self.noise
        H, W = z.shape
        gaussian = self._gaussian(rng, z.size) if nz.noise_coeff > 0 else None
        prim = c["prim"]
        albedo = self._albedo[prim].reshape(H, W) if nz.dark_holes > 0 else None
        shiny = None
        if nz.shiny_holes > 0:
            flat = self._shiny[prim]
            idx = np.nonzero(flat)[0]
            if len(idx):
                normal = self._face_normal[c["face"][idx]] @ c["T"][:3, :3].astype(np.float32)
                cos = np.abs(normal[:, 0] * self._xc[idx] + normal[:, 1] * self._yc[idx] + normal[:, 2])
                cos *= self._inv_len[idx]
                flat = np.zeros_like(flat)
                flat[idx[cos > SHINY_COS]] = True
            shiny = flat.reshape(H, W)
        return apply_depth(z, nz, rng, gaussian, self.intrinsics.fx_px, albedo, shiny)

    # --- ground truth ------------------------------------------------------------------

    def visible_objects(self, frame: Frame, min_pixels: int = 1) -> list[VisibleObject]:
        """Objects present in the frame's instance mask with at least ``min_pixels`` pixels,
        largest first, with their ground-truth geometry (map frame)."""
        if "instance" not in frame.masks:
            raise SimulationError("frame has no instance mask (not rendered by the simulator)")
        inst = np.asarray(frame.masks["instance"], dtype=np.int32)
        ids, counts = np.unique(inst[inst > 0], return_counts=True)
        out: list[VisibleObject] = []
        for oid, cnt in zip(ids.tolist(), counts.tolist(), strict=True):
            if cnt < min_pixels or oid not in self._objects:
                continue
            obj = self._objects[oid]
            vv, uu = np.nonzero(inst == oid)
            cls = self.class_names.index(obj.class_name) if obj.class_name in self.class_names else -1
            out.append(
                VisibleObject(
                    object_id=oid, class_name=obj.class_name, class_index=cls, pixel_count=cnt,
                    bbox_xyxy_px=(float(uu.min()), float(vv.min()), float(uu.max() + 1), float(vv.max() + 1)),
                    center_xy_m=obj.center_xy_m, yaw_rad=obj.yaw_rad, size_m=obj.size_m,
                    footprint_xy_m=obj.footprint_xy_m(), z_range_m=obj.z_range_m, parts=obj.parts,
                )
            )
        out.sort(key=lambda o: -o.pixel_count)
        return out

    def silhouette_px(
        self, T_map_camera: Transform, margin_images: float = 1.0, stride_px: int = 2,
    ) -> dict[int, float]:
        """Unoccluded silhouette area of every object, in pixels, on the image plane extended
        by ``margin_images`` image widths/heights beyond each border: what the object would
        cover with nothing in front of it and an image large enough to hold it.

        An object's visible pixels (instance mask) over this area is its visible fraction,
        occlusion and truncation together (KITTI labels the two apart; one figure is enough
        to say "a sliver"). Rays are cast on a ``stride_px`` grid (each sample stands for
        ``stride_px**2`` pixels) against the furniture alone, with every hit along each ray
        listed, so an object counts wherever any part of it lies on the ray. Parts beyond the
        extended plane or behind the camera do not count: for an object that large the
        figure falls short of what it covers, so its visible fraction errs high.
        """
        T = _checked_pose(T_map_camera)
        if margin_images < 0 or stride_px < 1:
            raise SimulationError(
                f"silhouette_px needs margin_images >= 0 and stride_px >= 1 (got {margin_images}, {stride_px})")
        if not self.room.objects:
            return {}
        o3d = self._o3d
        if self._object_scene is None:
            scene = o3d.t.geometry.RaycastingScene(nthreads=self.n_threads)
            owners = []
            for obj in self.room.objects:
                for part in obj.parts:
                    if int(scene.add_triangles(_box_mesh(o3d, part))) != len(owners):
                        raise SimulationError("unexpected Open3D geometry id in the furniture-only scene")
                    owners.append(obj.object_id)
            self._object_scene = scene
            self._object_owner = np.asarray(owners, dtype=np.int64)
        # Sample k of the grid is pixel u = -margin + k * stride: the pixel grid of a camera
        # with fx / stride and (cx + margin) / stride, through the module's pixel convention.
        intr = self.intrinsics
        mu, mv = int(round(margin_images * intr.width_px)), int(round(margin_images * intr.height_px))
        grid = replace(
            intr, fx_px=intr.fx_px / stride_px, fy_px=intr.fy_px / stride_px,
            cx_px=(intr.cx_px + mu) / stride_px, cy_px=(intr.cy_px + mv) / stride_px,
            width_px=-(-(intr.width_px + 2 * mu) // stride_px), height_px=-(-(intr.height_px + 2 * mv) // stride_px),
        )
        dirs = self._pixel_directions(grid)
        rays = np.empty((dirs.shape[0], 6), dtype=np.float32)
        rays[:, :3] = T[:3, 3]
        rays[:, 3:] = dirs @ T[:3, :3].T
        hits = self._object_scene.list_intersections(o3d.core.Tensor.from_numpy(rays), nthreads=self.n_threads)
        owner = self._object_owner[hits["geometry_ids"].numpy().astype(np.int64)]
        ray = hits["ray_ids"].numpy().astype(np.int64)
        n_ids = int(self._object_owner.max(initial=0)) + 1
        pairs = np.unique(ray * n_ids + owner)  # one count per (ray, object)
        ids, counts = np.unique(pairs % n_ids, return_counts=True)
        area = float(stride_px * stride_px)
        return {int(i): float(c) * area for i, c in zip(ids.tolist(), counts.tolist(), strict=True)}


def renderer_from_config(room: Room, cfg: Any, seed: int | None = None) -> RoomRenderer:
    """A :class:`RoomRenderer` for a :class:`companion.config.CompanionConfig`: camera
    intrinsics and depth range from ``cfg.camera``, noise from ``cfg.sim``, class order from
    ``cfg.classes``; ``seed`` defaults to ``cfg.sim.seed``."""
    cam = cfg.camera
    sim = cfg.sim
    noise = DepthNoise(
        noise_coeff=sim.depth_noise_coeff, edge_dropout=sim.depth_edge_dropout,
        min_m=cam.depth_min_m, max_m=cam.depth_max_m, flying_pixels=sim.depth_flying_pixels,
        dark_holes=sim.depth_dark_holes, shiny_holes=sim.depth_shiny_holes, far_dropout=sim.depth_far_dropout,
        disparity_step_px=1.0 / 32.0 if sim.depth_disparity_quantisation else 0.0, min_z_m=sim.depth_min_z_m,
    )
    color = ColorModel(auto_exposure=sim.rgb_auto_exposure, motion_blur=sim.rgb_motion_blur)
    return RoomRenderer(
        room, [c.name for c in cfg.classes], cam.intrinsics(), noise=noise,
        seed=sim.seed if seed is None else seed, color=color,
    )
