"""Camera sources: recorded folders (real data), the simulated camera, RealSense with a fake SDK."""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest

from companion.config import CompanionConfig
from companion.sources import (
    FrameSource,
    RealSenseFrameSource,
    RecordedFrameSource,
    SimFrameSource,
    load_tum_pair,
    make_frame_source,
)
from companion.sources.realsense import CaptureClock
from companion.sources.recorded import associate
from companion.sources.stream import FrameStream
from semmap.errors import ConfigError, DataError, FrameError
from semmap.frames import invert, pose_from_xyz_rpy, transform_points
from semmap.pointcloud import backproject
from semmap.types import CameraIntrinsics, Frame


def reprojection_error_m(a: Frame, b: Frame) -> float:
    """Median |depth| disagreement when frame a's points are projected into frame b."""
    assert a.T_map_camera is not None and b.T_map_camera is not None
    pts, _ = backproject(a.depth_m, a.intrinsics, min_m=0.3, max_m=6.0, stride_px=4)
    in_b = transform_points(invert(b.T_map_camera) @ a.T_map_camera, pts)
    K = b.intrinsics
    z = in_b[:, 2]
    ok = z > 0.3
    u = np.round(K.fx_px * in_b[ok, 0] / z[ok] + K.cx_px).astype(int)
    v = np.round(K.fy_px * in_b[ok, 1] / z[ok] + K.cy_px).astype(int)
    inside = (u >= 0) & (u < K.width_px) & (v >= 0) & (v < K.height_px)
    zb = b.depth_m[v[inside], u[inside]]
    valid = zb > 0
    assert valid.sum() > 1000
    return float(np.median(np.abs(zb[valid] - z[ok][inside][valid])))


# --- recorded folders ---------------------------------------------------------------------

def test_diningroom_folder_layout(real_data: Path) -> None:
    src = RecordedFrameSource(real_data / "rgbd" / "diningroom")
    with src:
        frames = list(src)
    assert src.layout == "folders" and len(frames) == 5 and src.frames_read == 5
    assert src.intrinsics == CameraIntrinsics(518.0, 519.0, 325.5, 253.5, 640, 480)
    assert src.depth_scale == 1000.0
    for i, f in enumerate(frames):
        assert f.index == i and f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
        d = f.depth_m[f.depth_m > 0]
        assert f.depth_m.dtype == np.float32 and 1.0 < float(np.median(d)) < 5.0  # metres
        assert f.T_map_camera is not None
    # The world is roughly the first camera's frame: its pose is nearly the identity.
    R0 = frames[0].T_map_camera[:3, :3]
    assert math.degrees(math.acos((np.trace(R0) - 1) / 2)) < 20.0
    # Poses are camera-to-world: consecutive frames' depths agree after reprojection.
    assert reprojection_error_m(frames[0], frames[1]) < 0.12
    assert reprojection_error_m(frames[3], frames[4]) < 0.12
    # Colour is RGB, not OpenCV's BGR.
    bgr = cv2.imread(str(real_data / "rgbd" / "diningroom" / "color" / "1.png"))
    assert np.array_equal(frames[0].rgb, bgr[:, :, ::-1])


def test_depth_range_is_applied(real_data: Path) -> None:
    src = RecordedFrameSource(real_data / "rgbd" / "diningroom", depth_min_m=1.0, depth_max_m=3.0)
    d = src.frame_at(0).depth_m
    valid = d[d > 0]
    assert valid.min() >= 1.0 and valid.max() <= 3.0


def test_tum_pairs_layout(real_data: Path) -> None:
    src = RecordedFrameSource(real_data / "rgbd" / "tum_fr2_desk")
    frames = list(src)
    assert src.layout == "pairs" and len(frames) == 2 and src.depth_scale == 5000.0
    assert src.intrinsics.fx_px == pytest.approx(520.9)
    assert all(f.T_map_camera is None for f in frames)
    d = frames[0].depth_m
    assert 0.5 < float(np.median(d[d > 0])) < 3.0  # a desk at arm's length
    assert src.read() is None


def make_tum_folder(real_data: Path, dst: Path) -> Path:
    """A TUM RGB-D layout (rgb.txt, depth.txt, groundtruth.txt) made of the real fr2 frames."""
    src = real_data / "rgbd" / "tum_fr2_desk"
    (dst / "rgb").mkdir(parents=True)
    (dst / "depth").mkdir()
    stamps = [1311868164.363181, 1311868164.399454]
    for i, t in enumerate(stamps, start=1):
        shutil.copy(src / f"{i}.png", dst / "rgb" / f"{t:.6f}.png")
        shutil.copy(src / f"{i}_depth.png", dst / "depth" / f"{t + 0.008:.6f}.png")
    (dst / "rgb.txt").write_text(
        "# color images\n# timestamp filename\n"
        + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in stamps)
        + "1311868199.000000 rgb/orphan.png\n"  # no depth near it: dropped by association
    )
    (dst / "depth.txt").write_text("# depth\n" + "".join(f"{t + 0.008:.6f} depth/{t + 0.008:.6f}.png\n" for t in stamps))
    (dst / "groundtruth.txt").write_text(
        "# timestamp tx ty tz qx qy qz qw\n"
        "1311868164.30 1.0 2.0 1.5 0 0 0 1\n"
        "1311868164.40 2.0 2.0 1.5 0 0 0.0871557 0.9961947\n"
    )
    shutil.copy(src / "intrinsics.json", dst / "intrinsics.json")
    return dst


def test_tum_layout_associates_and_interpolates_ground_truth(real_data: Path, tmp_path: Path) -> None:
    src = RecordedFrameSource(make_tum_folder(real_data, tmp_path / "tum"))
    frames = list(src)
    assert src.layout == "tum" and len(frames) == 2
    assert frames[0].stamp_s == pytest.approx(1311868164.363181)
    T = frames[0].T_map_camera
    assert T is not None
    # Linear between the two ground-truth poses at 63 % of the way.
    assert T[0, 3] == pytest.approx(1.0 + 0.63181, abs=1e-4)
    yaw = math.degrees(math.atan2(T[1, 0], T[0, 0]))
    assert yaw == pytest.approx(10.0 * 0.63181, abs=0.05)
    # The second colour frame is 0.6 ms before the last ground truth: interpolated as well.
    assert frames[1].T_map_camera is not None
    ref = RecordedFrameSource(real_data / "rgbd" / "tum_fr2_desk").frame_at(0)
    assert np.array_equal(frames[0].depth_m, ref.depth_m)


def test_tum_folder_named_after_its_camera_gets_the_published_calibration(
    real_data: Path, tmp_path: Path,
) -> None:
    folder = make_tum_folder(real_data, tmp_path / "rgbd_dataset_freiburg2_desk")
    (folder / "intrinsics.json").unlink()
    src = RecordedFrameSource(folder, default_intrinsics=CameraIntrinsics(1, 1, 1, 1, 640, 480))
    assert src.intrinsics == CameraIntrinsics(520.9, 521.0, 325.1, 249.7, 640, 480)
    assert src.depth_scale == 5000.0


def test_associate_is_one_to_one_and_respects_max_dt() -> None:
    a = np.array([0.0, 0.033, 0.066, 0.5])
    b = np.array([0.001, 0.030, 0.035, 0.07])
    pairs = associate(a, b, max_dt_s=0.02)
    assert pairs == [(0, 0), (1, 2), (2, 3)]  # 0.033 is closer to 0.035 than to 0.030
    # Two colour frames competing for one depth frame: the closer wins, the other goes unpaired.
    assert associate(np.array([0.0, 0.004]), np.array([0.003]), 0.02) == [(1, 0)]
    assert associate(a, np.array([]), 0.02) == []


def test_tum_fr1_case_pairs_have_consistent_poses(real_data: Path) -> None:
    prev, curr = load_tum_pair(real_data / "rgbd" / "tum_fr1_xyz" / "case_1")
    assert prev.rgb.shape == (480, 640, 3) and prev.T_map_camera is not None
    assert np.linalg.norm(prev.T_map_camera[:3, 3] - curr.T_map_camera[:3, 3]) < 0.2
    assert reprojection_error_m(prev, curr) < 0.1


@pytest.fixture
def dining_copy(real_data: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "dining"
    shutil.copytree(real_data / "rgbd" / "diningroom", dst)
    return dst


def test_corrupt_colour_image_names_the_file_and_reading_continues(dining_copy: Path) -> None:
    bad = dining_copy / "color" / "2.png"
    bad.write_bytes(bad.read_bytes()[:200])  # truncated PNG
    src = RecordedFrameSource(dining_copy)
    assert src.read() is not None
    with pytest.raises(FrameError, match=r"color/2\.png.*corrupt"):
        src.read()
    assert src.read().index == 2  # the caller may skip the bad frame


def test_missing_depth_file_names_the_expected_file(dining_copy: Path) -> None:
    (dining_copy / "depth" / "4.pgm").unlink()
    src = RecordedFrameSource(dining_copy)
    with pytest.raises(FrameError, match=r"depth/4\.pgm.*missing"):
        src.frame_at(3)


def test_wrong_kind_of_depth_image(dining_copy: Path) -> None:
    img = cv2.imread(str(dining_copy / "color" / "1.png"), cv2.IMREAD_GRAYSCALE)
    (dining_copy / "depth" / "1.pgm").unlink()
    cv2.imwrite(str(dining_copy / "depth" / "1.png"), img)  # 8-bit
    with pytest.raises(FrameError, match=r"depth/1\.png.*16-bit"):
        RecordedFrameSource(dining_copy).frame_at(0)


def test_image_size_must_match_intrinsics(dining_copy: Path) -> None:
    small = cv2.imread(str(dining_copy / "color" / "1.png"))[:240, :320]
    cv2.imwrite(str(dining_copy / "color" / "1.png"), small)
    with pytest.raises(FrameError, match=r"color/1\.png: image is 320x240"):
        RecordedFrameSource(dining_copy).frame_at(0)


def test_bad_pose_line_names_file_and_line(dining_copy: Path) -> None:
    lines = (dining_copy / "pose.txt").read_text().splitlines()
    lines[2] = "1.0 2.0 three 0 0 0 1"
    (dining_copy / "pose.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"pose\.txt:3: not a number"):
        RecordedFrameSource(dining_copy).open()
    (dining_copy / "pose.txt").write_text("\n".join(lines[:1]) + "\n")
    with pytest.raises(DataError, match=r"pose\.txt: 1 poses for 5 colour frames"):
        RecordedFrameSource(dining_copy).open()


def test_bad_intrinsics_json_names_the_key(dining_copy: Path) -> None:
    data = json.loads((dining_copy / "intrinsics.json").read_text())
    data["fx"] = -1
    (dining_copy / "intrinsics.json").write_text(json.dumps(data))
    with pytest.raises(DataError, match=r"intrinsics\.json: fx: must be a positive number"):
        RecordedFrameSource(dining_copy).open()
    (dining_copy / "intrinsics.json").write_text("{not json")
    with pytest.raises(DataError, match=r"intrinsics\.json: not valid JSON"):
        RecordedFrameSource(dining_copy).open()


def test_missing_intrinsics_fall_back_to_given_ones(dining_copy: Path) -> None:
    (dining_copy / "intrinsics.json").unlink()
    with pytest.raises(DataError, match="no intrinsics.json"):
        RecordedFrameSource(dining_copy).open()
    intr = CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    src = RecordedFrameSource(dining_copy, default_intrinsics=intr)
    assert src.read().intrinsics == intr


def test_unknown_folder_layouts(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="not found"):
        RecordedFrameSource(tmp_path / "nope").open()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="not a recognised RGB-D recording"):
        RecordedFrameSource(tmp_path / "empty").open()


# --- the simulated camera -----------------------------------------------------------------

SMALL_CAMERA = {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0}


def test_sim_source_renders_from_the_vehicle_pose() -> None:
    pytest.importorskip("open3d")
    cfg = CompanionConfig.model_validate({"camera": SMALL_CAMERA, "sim": {"n_objects": 3}})
    poses = [(0.1 * i, pose_from_xyz_rpy(4.0, 3.0, 1.0, 0.0, 0.0, 0.3 * i)) for i in range(4)]
    it = iter(poses)
    src = make_frame_source(cfg, pose_provider=lambda: next(it, None))
    assert isinstance(src, SimFrameSource) and isinstance(src, FrameSource)
    with src:
        frames = list(src)
    assert len(frames) == 4 and [f.index for f in frames] == [0, 1, 2, 3]
    T_bc = cfg.camera.extrinsics.T_body_camera()
    for f, (t, T_mb) in zip(frames, poses, strict=True):
        assert f.stamp_s == t
        assert np.allclose(f.T_map_camera, T_mb @ T_bc)
        assert f.rgb.shape == (120, 160, 3) and "instance" in f.masks
    # The same flight replays to the same frames.
    it2 = iter(poses)
    again = SimFrameSource.from_config(cfg, lambda: next(it2, None), room=src.room)
    assert np.array_equal(again.read().depth_m, frames[0].depth_m)


def test_sim_source_stops_after_max_frames() -> None:
    pytest.importorskip("open3d")
    cfg = CompanionConfig.model_validate({"camera": SMALL_CAMERA, "sim": {"n_objects": 0}})
    src = make_frame_source(cfg, pose_provider=lambda: (0.0, pose_from_xyz_rpy(3.0, 3.0, 1.0)), max_frames=2)
    assert len(list(src)) == 2


def test_factory_picks_the_configured_source(real_data: Path) -> None:
    with pytest.raises(ConfigError, match="pose provider"):
        make_frame_source(CompanionConfig())
    rec = make_frame_source(CompanionConfig.model_validate(
        {"camera": {"source": "recorded", "recorded_path": str(real_data / "rgbd" / "diningroom")}}
    ))
    assert isinstance(rec, RecordedFrameSource) and len(rec) == 5
    live = make_frame_source(CompanionConfig.model_validate({"camera": {"source": "realsense", "realsense_serial": "123"}}))
    assert isinstance(live, RealSenseFrameSource) and live.serial == "123"


# --- RealSense with a fake SDK ------------------------------------------------------------

class FakeVideoFrame:
    def __init__(self, data: np.ndarray | None, stamp_ms: float = 0.0, domain: str = "hardware_clock") -> None:
        self.data, self.stamp_ms, self.domain = data, stamp_ms, domain

    def __bool__(self) -> bool:
        return self.data is not None

    def get_data(self) -> np.ndarray:
        assert self.data is not None
        return self.data

    def get_timestamp(self) -> float:
        return self.stamp_ms

    def get_frame_timestamp_domain(self) -> str:
        return f"timestamp_domain.{self.domain}"  # as str() of pyrealsense2's enum prints


class FakeFrameset:
    def __init__(self, depth: np.ndarray | None, color: np.ndarray | None, stamp_ms: float,
                 domain: str = "hardware_clock") -> None:
        self.depth, self.color, self.stamp_ms, self.domain = depth, color, stamp_ms, domain

    def get_depth_frame(self) -> FakeVideoFrame:
        return FakeVideoFrame(self.depth, self.stamp_ms, self.domain)

    def get_color_frame(self) -> FakeVideoFrame:
        return FakeVideoFrame(self.color, self.stamp_ms, self.domain)

    def get_timestamp(self) -> float:
        return self.stamp_ms


class FakePipeline:
    """Plays a script: framesets, or exceptions to raise from wait_for_frames."""

    def __init__(self, script: list[Any], depth_scale: float = 0.001, fail_start: bool = False,
                 sensors: list[Any] | None = None) -> None:
        self.script = list(script)
        self.sensors = sensors or []
        self.depth_scale = depth_scale
        self.fail_start = fail_start
        self.started_with: Any = None
        self.stopped = False
        self.timeouts: list[int] = []

    def start(self, config: Any) -> Any:
        if self.fail_start:
            raise RuntimeError("No device connected")
        self.started_with = config
        intr = SimpleNamespace(fx=380.5, fy=380.0, ppx=321.2, ppy=239.1, width=640, height=480)
        sensor = SimpleNamespace(get_depth_scale=lambda: self.depth_scale)
        stream = SimpleNamespace(as_video_stream_profile=lambda: SimpleNamespace(get_intrinsics=lambda: intr))
        return SimpleNamespace(
            get_device=lambda: SimpleNamespace(first_depth_sensor=lambda: sensor,
                                               query_sensors=lambda: self.sensors),
            get_stream=lambda s: stream,
        )

    def wait_for_frames(self, timeout_ms: int) -> Any:
        self.timeouts.append(timeout_ms)
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    def stop(self) -> None:
        self.stopped = True


class FakeConfig:
    def __init__(self) -> None:
        self.streams: list[tuple[Any, ...]] = []
        self.device: str | None = None

    def enable_device(self, serial: str) -> None:
        self.device = serial

    def enable_stream(self, *args: Any) -> None:
        self.streams.append(args)


class FakeAlign:
    def __init__(self, to: str) -> None:
        assert to == "color"

    def process(self, frames: Any) -> Any:
        return frames


class FakeSensor:
    def __init__(self, global_time: float | None) -> None:
        self.options = {} if global_time is None else {"global_time_enabled": global_time}

    def supports(self, option: str) -> bool:
        return option in self.options

    def get_option(self, option: str) -> float:
        return self.options[option]

    def set_option(self, option: str, value: float) -> None:
        assert option in self.options
        self.options[option] = value


FAKE_RS = SimpleNamespace(
    stream=SimpleNamespace(depth="depth", color="color"), format=SimpleNamespace(z16="z16", rgb8="rgb8"),
    option=SimpleNamespace(global_time_enabled="global_time_enabled"),
    config=FakeConfig, align=FakeAlign,
)


def good_frameset(depth_mm: int = 1500, stamp_ms: float = 1000.0, domain: str = "hardware_clock") -> FakeFrameset:
    depth = np.full((480, 640), depth_mm, dtype=np.uint16)
    depth[0, 0] = 9000  # beyond the range
    color = np.zeros((480, 640, 3), dtype=np.uint8)
    color[..., 0] = 200
    return FakeFrameset(depth, color, stamp_ms, domain)


def test_realsense_reads_aligned_frames_and_skips_bad_ones() -> None:
    pipe = FakePipeline([
        good_frameset(1500),
        RuntimeError("Frame didn't arrive within 1000"),
        FakeFrameset(None, np.zeros((480, 640, 3), np.uint8), 1066.0),  # no depth
        FakeFrameset(np.zeros((240, 320), np.uint16), np.zeros((480, 640, 3), np.uint8), 1100.0),
        good_frameset(2000, 1133.0),
    ], depth_scale=0.001)
    src = RealSenseFrameSource(serial="0123", rate_hz=30, depth_max_m=6.0, rs_module=FAKE_RS, pipeline=pipe)
    with src:
        a = src.read()
        b = src.read()
    assert pipe.started_with.device == "0123"
    assert ("depth", 640, 480, "z16", 30) in pipe.started_with.streams
    assert ("color", 640, 480, "rgb8", 30) in pipe.started_with.streams
    assert src.intrinsics == CameraIntrinsics(380.5, 380.0, 321.2, 239.1, 640, 480)
    assert a is not None and b is not None
    assert a.depth_m[100, 100] == pytest.approx(1.5) and a.depth_m[0, 0] == 0.0
    assert b.depth_m[100, 100] == pytest.approx(2.0)
    assert a.rgb[0, 0, 0] == 200 and a.T_map_camera is None
    assert b.stamp_s >= a.stamp_s and src.last_device_stamp_ms == 1133.0
    assert src.dropped_frames == 3 and src.frames_read == 2
    assert pipe.stopped


def test_realsense_stamps_frames_at_capture_on_the_monotonic_clock() -> None:
    """A global-time stamp 40 ms old gives a frame stamped 40 ms before its arrival; one the
    host clock does not believe (in the future, or 10 s old) falls back to arrival, counted."""
    ref_monotonic_s, now_wall_ms = time.monotonic(), time.time() * 1e3
    pipe = FakePipeline([
        good_frameset(stamp_ms=now_wall_ms - 40.0, domain="global_time"),
        good_frameset(stamp_ms=now_wall_ms + 1000.0, domain="global_time"),
        good_frameset(stamp_ms=now_wall_ms - 10_000.0, domain="system_time"),
    ], sensors=[FakeSensor(global_time=0.0), FakeSensor(global_time=None)])
    src = RealSenseFrameSource(rs_module=FAKE_RS, pipeline=pipe)
    with src:
        t0 = time.monotonic()
        a = src.read()
        lat_a, dom_a = src.last_latency_s, src.last_stamp_domain
        b = src.read()
        c = src.read()
        t1 = time.monotonic()
    assert pipe.sensors[0].options["global_time_enabled"] == 1  # switched on where offered
    assert a is not None and b is not None and c is not None
    assert dom_a == "global_time"
    # Captured 40 ms before the reference instant, whatever the start-up took:
    assert a.stamp_s == pytest.approx(ref_monotonic_s - 0.040, abs=0.003)
    assert lat_a >= 0.040 and a.stamp_s < t0
    assert t0 <= b.stamp_s <= t1 and t0 <= c.stamp_s <= t1  # on arrival
    assert src.capture_clock.stamps_on_arrival == 2


def test_capture_clock_removes_the_varying_latency_of_a_hardware_clock() -> None:
    """Device counter 1000 s ahead of the host; latency 30 ms plus up to 40 ms of jitter: the
    stamps keep only the smallest latency, so their spacing is the device's, not the arrivals'."""
    clock = CaptureClock()
    rng = np.random.default_rng(0)
    stamps, arrivals, captures = [], [], []
    for k in range(60):
        capture_s = 10.0 + k / 30.0
        arrival = capture_s + 0.030 + float(rng.uniform(0.0, 0.040))
        stamps.append(clock.capture_stamp_s((capture_s + 1000.0) * 1e3, "hardware_clock", arrival, 0.0))
        arrivals.append(arrival)
        captures.append(capture_s)
    latency = np.asarray(arrivals) - np.asarray(stamps)
    assert np.all(latency >= 0.0)
    # After the first frames the offset has settled at the smallest latency seen (30 ms + a
    # little): the stamps' error is constant to a few ms while the arrivals' varies by ~40 ms.
    stamp_err = np.asarray(stamps[20:]) - np.asarray(captures[20:]) - 0.030
    arrival_err = np.asarray(arrivals[20:]) - np.asarray(captures[20:]) - 0.030
    assert np.all((stamp_err >= 0.0) & (stamp_err < 0.006))
    assert np.ptp(arrival_err) > 0.025
    assert clock.stamps_on_arrival == 0
    # A domain it does not know is stamped on arrival, counted.
    assert clock.capture_stamp_s(5.0, "unknown", 42.0, 0.0) == 42.0 and clock.stamps_on_arrival == 1


def test_realsense_gives_up_after_too_many_failures_in_a_row() -> None:
    pipe = FakePipeline([RuntimeError("timeout")] * 5)
    src = RealSenseFrameSource(rs_module=FAKE_RS, pipeline=pipe, max_consecutive_failures=3)
    with pytest.raises(FrameError, match="3 bad frames in a row"):
        src.read()
    assert src.dropped_frames == 3


def test_realsense_start_failure_is_a_frame_error() -> None:
    src = RealSenseFrameSource(serial="999", rs_module=FAKE_RS, pipeline=FakePipeline([], fail_start=True))
    with pytest.raises(FrameError, match="RealSense 999: cannot start.*No device connected"):
        src.open()


# --- the asyncio stream -------------------------------------------------------------------

class ListSource(FrameSource):
    """Frames from a list; optionally fails at one index; records open/close."""

    def __init__(self, n: int, fail_at: int | None = None) -> None:
        import threading

        self.n, self.fail_at = n, fail_at
        self.i = 0
        self.opened = self.closed = False
        self.exhausted = threading.Event()
        self._intr = CameraIntrinsics(10.0, 10.0, 2.0, 2.0, 4, 4)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intr

    def open(self) -> None:
        self.opened = True

    def close(self) -> None:
        self.closed = True

    def read(self) -> Frame | None:
        if self.i == self.fail_at:
            self.exhausted.set()
            raise FrameError("camera unplugged")
        if self.i >= self.n:
            self.exhausted.set()
            return None
        self.i += 1
        return Frame(float(self.i), np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32),
                     self._intr, index=self.i - 1)


@pytest.mark.asyncio
async def test_stream_delivers_every_frame_to_a_prompt_consumer() -> None:
    import asyncio

    src = ListSource(5)
    async with FrameStream(src, queue_size=8) as stream:
        got = [f.index async for f in stream]
        await asyncio.sleep(0)
    assert got == [0, 1, 2, 3, 4]
    assert src.opened and src.closed and stream.dropped_frames == 0


@pytest.mark.asyncio
async def test_stream_drops_the_oldest_frames_for_a_slow_consumer() -> None:
    import asyncio

    src = ListSource(20)
    async with FrameStream(src, queue_size=2) as stream:
        await asyncio.to_thread(src.exhausted.wait, 10.0)
        await asyncio.sleep(0.05)  # let the loop run the hand-overs the thread scheduled
        got = [f.index async for f in stream]
    assert got == [18, 19]  # the newest frames, in order
    assert stream.dropped_frames == 18 and stream.frames_delivered == 2


@pytest.mark.asyncio
async def test_stream_raises_the_source_error_after_the_frames_before_it() -> None:
    src = ListSource(10, fail_at=3)
    got = []
    with pytest.raises(FrameError, match="camera unplugged"):
        async with FrameStream(src, queue_size=10) as stream:
            async for f in stream:
                got.append(f.index)
    assert got == [0, 1, 2] and src.closed


@pytest.mark.asyncio
async def test_stream_paces_a_simulated_source_and_stops_on_exit() -> None:
    src = ListSource(10**6)
    async with FrameStream(src, rate_hz=200.0) as stream:
        first = [await stream.__anext__() for _ in range(3)]
    indices = [f.index for f in first]
    assert indices == sorted(set(indices))  # newest-first hand-over never reorders
    assert src.closed
    assert src.i < 10**6  # the reader stopped with the stream
