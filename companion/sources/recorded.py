"""Recorded RGB-D folders read frame by frame, in three layouts.

* **TUM RGB-D** (``rgb.txt``, ``depth.txt``, optional ``groundtruth.txt``): colour and depth
  are associated by nearest timestamp (at most ``max_dt_s`` apart, one to one, as the
  benchmark's ``associate.py``); ground-truth poses (``timestamp tx ty tz qx qy qz qw``,
  camera-to-world) are interpolated to the colour stamp. Depth PNG / 5000 = metres.
* **Folders** (``color/N.png``, ``depth/N.png`` or ``depth/N.pgm`` 16-bit millimetres,
  optional ``pose.txt`` with one ``tx ty tz qx qy qz qw`` camera-to-world line per frame in
  frame order), as in ``../shared/data/rgbd/diningroom``.
* **Pairs** (``N.png`` with ``N_depth.png`` side by side, depth / 5000), as in
  ``../shared/data/rgbd/tum_fr2_desk``.

Intrinsics come from ``intrinsics.json`` in the folder (keys ``width``, ``height``, ``fx``,
``fy``, ``cx``, ``cy`` and optionally ``depth_scale``, raw units per metre); else, for a TUM
folder named after its camera (``rgbd_dataset_freiburg2_desk``), the benchmark's published
calibration; else the ``default_intrinsics`` argument.

Frame poses: ``Frame.T_map_camera`` is the recording's camera-to-world pose, so "map" here
means *the recording's world frame*, not our ENU map. For the dining room that world is
roughly the first camera's optical frame (x right, y down, z forward) and its floor is not
axis-aligned; for TUM it is the motion-capture frame. Frames without a pose have None.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.sources.base import FrameSource
from companion.sources.poses import PoseTrack
from semmap.errors import DataError, FrameError
from semmap.frames import make_transform, quaternion_to_rotation
from semmap.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
MM_DEPTH_SCALE = 1000.0

#: The TUM RGB-D benchmark's published colour calibrations (640x480), used for a TUM-layout
#: folder without ``intrinsics.json`` whose name says which Kinect recorded it.
TUM_INTRINSICS = {
    "freiburg1": CameraIntrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    "freiburg2": CameraIntrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    "freiburg3": CameraIntrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}


@dataclass(frozen=True)
class RecordedEntry:
    """One frame of a recording: files, stamp (s) and camera-to-world pose (4, 4) or None."""

    rgb_path: Path
    depth_path: Path
    stamp_s: float
    T_world_camera: NDArray[np.float64] | None


def read_intrinsics_json(path: Path) -> tuple[CameraIntrinsics, float | None]:
    """``intrinsics.json`` -> (intrinsics, depth_scale or None). Raises :class:`DataError`
    naming the file and the key."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: not valid JSON at line {exc.lineno}: {exc.msg}") from exc
    if not isinstance(data, dict):
        raise DataError(f"{path}: top level must be an object")
    vals: dict[str, float] = {}
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        v = data.get(key)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or v <= 0:
            raise DataError(f"{path}: {key}: must be a positive number (got {v!r})")
        vals[key] = float(v)
    scale = data.get("depth_scale")
    if scale is not None and (not isinstance(scale, (int, float)) or scale <= 0):
        raise DataError(f"{path}: depth_scale: must be a positive number (got {scale!r})")
    intr = CameraIntrinsics(
        vals["fx"], vals["fy"], vals["cx"], vals["cy"], int(vals["width"]), int(vals["height"])
    )
    return intr, (float(scale) if scale is not None else None)


def _pose_from_tum(values: list[float]) -> NDArray[np.float64]:
    tx, ty, tz, qx, qy, qz, qw = values
    return make_transform(quaternion_to_rotation(qx, qy, qz, qw), np.array([tx, ty, tz]))


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, stripped line) of a text file's lines that are neither blank nor ``#``
    comments. Raises :class:`DataError` naming the file when it cannot be read."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read: {exc}") from exc
    lines = ((lineno, line.strip()) for lineno, line in enumerate(text.splitlines(), start=1))
    return [(lineno, s) for lineno, s in lines if s and not s.startswith("#")]


def read_pose_lines(path: Path, n_fields: int) -> list[list[float]]:
    """Numeric rows of a whitespace-separated text file (``#`` comments and blank lines
    skipped), each with exactly ``n_fields`` numbers. Raises :class:`DataError` naming the
    file and line."""
    rows = []
    for lineno, s in _data_lines(path):
        parts = s.split()
        try:
            nums = [float(p) for p in parts]
        except ValueError as exc:
            raise DataError(f"{path}:{lineno}: not a number in {s!r}") from exc
        if len(nums) != n_fields or not all(np.isfinite(nums)):
            raise DataError(f"{path}:{lineno}: expected {n_fields} finite numbers, got {s!r}")
        rows.append(nums)
    return rows


def _read_list(path: Path) -> list[tuple[float, str]]:
    """TUM ``rgb.txt``/``depth.txt``: ``timestamp filename`` rows."""
    rows = []
    for lineno, s in _data_lines(path):
        parts = s.split()
        try:
            rows.append((float(parts[0]), parts[1]))
        except (ValueError, IndexError) as exc:
            raise DataError(f"{path}:{lineno}: expected 'timestamp filename', got {s!r}") from exc
    return rows


def associate(
    a_stamps_s: NDArray[np.float64], b_stamps_s: NDArray[np.float64], max_dt_s: float
) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) of closest stamps at most ``max_dt_s`` apart, closest pairs
    first (the TUM benchmark's ``associate.py``), returned sorted by i."""
    a = np.asarray(a_stamps_s, dtype=np.float64)
    b = np.asarray(b_stamps_s, dtype=np.float64)
    if len(a) == 0 or len(b) == 0:
        return []
    order = np.argsort(b)
    bs = b[order]
    cands: list[tuple[float, int, int]] = []
    for i, t in enumerate(a):
        # Neighbours in time are enough: a window of a few around the insertion point.
        k = int(np.searchsorted(bs, t))
        for kk in range(max(0, k - 2), min(len(bs), k + 3)):
            dt = abs(bs[kk] - t)
            if dt <= max_dt_s:
                cands.append((dt, i, int(order[kk])))
    cands.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


def _numeric_key(p: Path) -> tuple[int, float, str]:
    m = re.fullmatch(r"\d+(\.\d+)?", p.stem)
    return (0, float(p.stem), "") if m else (1, 0.0, p.stem)


def read_color(path: Path, intrinsics: CameraIntrinsics | None = None) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB from an 8-bit colour image. Raises :class:`FrameError` naming the
    file when it is missing, corrupt or of the wrong size."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        what = "missing" if not path.exists() else "corrupt or not an image"
        raise FrameError(f"{path}: cannot read colour image ({what})")
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4):
        raise FrameError(f"{path}: colour image must be 8-bit RGB (got {img.dtype} {img.shape})")
    _check_size(path, img.shape[:2], intrinsics)
    return np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB))


def read_depth(
    path: Path, depth_scale: float, intrinsics: CameraIntrinsics | None = None
) -> NDArray[np.float32]:
    """(H, W) float32 metres from a 16-bit depth image (raw / ``depth_scale``; 0 = invalid).
    Raises :class:`FrameError` naming the file when it is missing, corrupt or not 16-bit."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        what = "missing" if not path.exists() else "corrupt or not an image"
        raise FrameError(f"{path}: cannot read depth image ({what})")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise FrameError(f"{path}: depth image must be single-channel 16-bit (got {img.dtype} {img.shape})")
    _check_size(path, img.shape, intrinsics)
    return (img.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)


def _check_size(path: Path, hw: tuple[int, ...], intrinsics: CameraIntrinsics | None) -> None:
    if intrinsics is not None and (hw[1], hw[0]) != (intrinsics.width_px, intrinsics.height_px):
        raise FrameError(
            f"{path}: image is {hw[1]}x{hw[0]} but the intrinsics are for "
            f"{intrinsics.width_px}x{intrinsics.height_px}"
        )


class RecordedFrameSource(FrameSource):
    """Frames of a recorded folder (see the module docstring for the layouts).

    The folder is indexed on :meth:`open`; images are read one at a time. A frame whose file
    is missing or corrupt raises :class:`FrameError` naming it; the cursor has already moved
    on, so a caller that wants to skip bad frames catches the error and reads again.
    ``depth_min_m``/``depth_max_m`` invalidate (set to 0) depth outside the range.
    ``rate_hz`` gives stamps to layouts without timestamps (frame i at ``i / rate_hz``).
    """

    def __init__(
        self,
        path: str | Path,
        default_intrinsics: CameraIntrinsics | None = None,
        depth_min_m: float = 0.0,
        depth_max_m: float = float("inf"),
        rate_hz: float = 30.0,
        max_dt_s: float = 0.02,
        depth_scale: float | None = None,
    ) -> None:
        self.path = Path(path)
        self._default_intrinsics = default_intrinsics
        self.depth_min_m = depth_min_m
        self.depth_max_m = depth_max_m
        self.rate_hz = rate_hz
        self.max_dt_s = max_dt_s
        self._depth_scale_override = depth_scale
        self._entries: list[RecordedEntry] | None = None
        self._intrinsics: CameraIntrinsics | None = None
        self.depth_scale = MM_DEPTH_SCALE
        self.layout = ""
        self._cursor = 0
        self.frames_read = 0
        self.dropped_frames = 0

    # --- indexing ----------------------------------------------------------------------

    def open(self) -> None:
        if self._entries is not None:
            return
        p = self.path
        if not p.is_dir():
            raise DataError(f"{p}: recording folder not found")
        if (p / "rgb.txt").is_file() and (p / "depth.txt").is_file():
            self.layout, entries, scale = "tum", self._index_tum(), TUM_DEPTH_SCALE
        elif (p / "color").is_dir() and (p / "depth").is_dir():
            self.layout, entries, scale = "folders", self._index_folders(), MM_DEPTH_SCALE
        elif any(p.glob("*_depth.png")):
            self.layout, entries, scale = "pairs", self._index_pairs(), TUM_DEPTH_SCALE
        else:
            raise DataError(
                f"{p}: not a recognised RGB-D recording (expected rgb.txt + depth.txt, "
                "color/ + depth/, or N.png + N_depth.png)"
            )
        json_path = p / "intrinsics.json"
        tum_camera = next((k for k in TUM_INTRINSICS if k in p.resolve().name), None)
        if json_path.is_file():
            intr, json_scale = read_intrinsics_json(json_path)
            scale = json_scale or scale
        elif self.layout == "tum" and tum_camera is not None:
            intr = TUM_INTRINSICS[tum_camera]
            log.info("%s: no intrinsics.json; using the TUM %s calibration", p, tum_camera)
        elif self._default_intrinsics is not None:
            intr = self._default_intrinsics
        else:
            raise DataError(f"{p}: no intrinsics.json and no intrinsics given")
        self._intrinsics = intr
        self.depth_scale = self._depth_scale_override or scale
        if not entries:
            raise DataError(f"{p}: the recording has no frames")
        self._entries = entries
        log.info("recording %s: %s layout, %d frames, depth scale %g", p, self.layout,
                 len(entries), self.depth_scale)

    def _index_tum(self) -> list[RecordedEntry]:
        p = self.path
        rgb = _read_list(p / "rgb.txt")
        dep = _read_list(p / "depth.txt")
        pairs = associate(np.array([t for t, _ in rgb]), np.array([t for t, _ in dep]), self.max_dt_s)
        track = None
        gt_path = p / "groundtruth.txt"
        if gt_path.is_file():
            rows = read_pose_lines(gt_path, 8)
            track = PoseTrack(np.array([r[0] for r in rows]), [_pose_from_tum(r[1:]) for r in rows],
                               max_gap_s=0.25)
        out = []
        for i, j in pairs:
            t = rgb[i][0]
            out.append(RecordedEntry(p / rgb[i][1], p / dep[j][1], t, track.at(t) if track else None))
        if len(out) < len(rgb):
            log.warning("%s: %d of %d colour frames have no depth within %.3f s", p,
                        len(rgb) - len(out), len(rgb), self.max_dt_s)
        return out

    def _index_folders(self) -> list[RecordedEntry]:
        p = self.path
        colors = sorted((f for f in (p / "color").iterdir() if f.suffix.lower() in (".png", ".jpg")),
                        key=_numeric_key)
        poses: list[NDArray[np.float64] | None] = [None] * len(colors)
        pose_path = p / "pose.txt"
        if pose_path.is_file():
            rows = read_pose_lines(pose_path, 7)
            if len(rows) != len(colors):
                raise DataError(f"{pose_path}: {len(rows)} poses for {len(colors)} colour frames")
            poses = [_pose_from_tum(r) for r in rows]
        # A frame without its depth file gets the path it should have had (the extension most
        # depth files use), so reading it raises an error naming the missing file.
        exts = [f.suffix.lower() for f in (p / "depth").iterdir() if f.suffix.lower() in (".png", ".pgm")]
        usual = max(set(exts), key=exts.count) if exts else ".png"
        out = []
        for i, c in enumerate(colors):
            depth = next((p / "depth" / (c.stem + ext) for ext in (usual, ".png", ".pgm")
                          if (p / "depth" / (c.stem + ext)).exists()), p / "depth" / (c.stem + usual))
            out.append(RecordedEntry(c, depth, i / self.rate_hz, poses[i]))
        return out

    def _index_pairs(self) -> list[RecordedEntry]:
        p = self.path
        colors = sorted((f for f in p.glob("*.png") if not f.stem.endswith("_depth")), key=_numeric_key)
        return [RecordedEntry(c, c.with_name(c.stem + "_depth.png"), i / self.rate_hz, None)
                for i, c in enumerate(colors)]

    # --- reading -----------------------------------------------------------------------

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the recording (indexes the folder on first use)."""
        self.open()
        assert self._intrinsics is not None
        return self._intrinsics

    @property
    def entries(self) -> list[RecordedEntry]:
        """Every frame's files, stamp and pose, in playback order."""
        self.open()
        assert self._entries is not None
        return list(self._entries)

    def __len__(self) -> int:
        return len(self.entries)

    def close(self) -> None:
        """Rewind: the next :meth:`read` starts from the first frame again."""
        self._cursor = 0

    def frame_at(self, i: int) -> Frame:
        """Frame ``i`` of the recording (random access). Raises :class:`FrameError`."""
        self.open()
        assert self._entries is not None and self._intrinsics is not None
        e = self._entries[i]
        rgb = read_color(e.rgb_path, self._intrinsics)
        depth = read_depth(e.depth_path, self.depth_scale, self._intrinsics)
        if self.depth_min_m > 0 or np.isfinite(self.depth_max_m):
            depth[(depth < self.depth_min_m) | (depth > self.depth_max_m)] = 0.0
        return Frame(stamp_s=e.stamp_s, rgb=rgb, depth_m=depth, intrinsics=self._intrinsics,
                     T_map_camera=None if e.T_world_camera is None else e.T_world_camera.copy(),
                     index=i)

    def read(self) -> Frame | None:
        self.open()
        assert self._entries is not None
        if self._cursor >= len(self._entries):
            return None
        i = self._cursor
        self._cursor += 1
        frame = self.frame_at(i)
        self.frames_read += 1
        return frame


def load_tum_pair(
    case_dir: str | Path, intrinsics: CameraIntrinsics | None = None,
    depth_scale: float = TUM_DEPTH_SCALE,
) -> tuple[Frame, Frame]:
    """A ``case_K`` folder of ``../shared/data/rgbd/tum_fr1_xyz``: (previous, current) frames
    from ``img_*.png``, ``dep_*.png`` and ``pose_*.txt`` (camera-to-world). Intrinsics default
    to the parent folder's ``intrinsics.json``. Raises :class:`FrameError`/:class:`DataError`."""
    d = Path(case_dir)
    if intrinsics is None:
        intrinsics, scale = read_intrinsics_json(d.parent / "intrinsics.json")
        depth_scale = scale or depth_scale
    frames = []
    for i, tag in enumerate(("prev", "curr")):
        rows = read_pose_lines(d / f"pose_{tag}.txt", 7)
        if len(rows) != 1:
            raise DataError(f"{d / f'pose_{tag}.txt'}: expected one pose line, got {len(rows)}")
        frames.append(Frame(
            stamp_s=float(i), rgb=read_color(d / f"img_{tag}.png", intrinsics),
            depth_m=read_depth(d / f"dep_{tag}.png", depth_scale, intrinsics),
            intrinsics=intrinsics, T_map_camera=_pose_from_tum(rows[0]), index=i,
        ))
    return frames[0], frames[1]
