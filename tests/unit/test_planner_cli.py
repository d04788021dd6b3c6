"""``companion plan`` on a ROS map folder with objects.json: altitude rule, picture, exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.cli import main
from semmap.export import write_ros_map
from semmap.grid import GridSpec

SPEC = GridSpec(0.05, (-1.0, -1.0), (80, 140))  # x -1..6, y -1..3


@pytest.fixture()
def map_dir(tmp_path: Path) -> Path:
    """Walls around, a desk across the room seen only as its four legs (a metric slice)."""
    prob = np.zeros(SPEC.shape_rc, np.float32)
    prob[:2, :] = prob[-2:, :] = prob[:, :2] = prob[:, -2:] = 1.0
    desk = np.array([[2.6, -0.9], [3.4, -0.9], [3.4, 2.9], [2.6, 2.9]])
    for x, y in desk:
        r, c = SPEC.cell_of(np.array([[x, y]]))[0]
        prob[max(r - 1, 0):r + 1, max(c - 1, 0):c + 1] = 1.0
    write_ros_map(tmp_path / "map", prob, SPEC)
    doc = {"objects": [{
        "object_id": 1, "class_name": "desk", "existence": 0.9, "polygon_xy_m": desk.tolist(),
        "z_min_m": 0.0, "z_max_m": 0.75, "margin_m": 0.0,
    }]}
    (tmp_path / "objects.json").write_text(json.dumps(doc), encoding="utf-8")
    return tmp_path


def _plan(map_dir: Path, *extra: str) -> tuple[int, dict]:
    out = map_dir / "plan.png"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["plan", "--map", str(map_dir), "--start", "1,1", "--goal", "5,1", "--out", str(out),
                   "--time-limit", "0.1", "--json", *extra])
    return rc, json.loads(buf.getvalue().strip().splitlines()[-1])


def test_desk_blocks_at_low_altitude(map_dir: Path) -> None:
    rc, res = _plan(map_dir, "--altitude", "0.5")
    assert rc == 1 and res["status"] == "disconnected"
    img = cv2.imread(str(map_dir / "plan.png"))
    assert img is not None and img.shape[0] > 100


def test_flies_over_desk_at_1_5_m_and_draws_path(map_dir: Path) -> None:
    rc, res = _plan(map_dir, "--altitude", "1.5")
    assert rc == 0 and res["status"] == "ok"
    assert res["length_m"] == pytest.approx(4.0, abs=1e-6)
    img = cv2.imread(str(map_dir / "plan.png"))
    assert img is not None
    # The path colour is drawn somewhere in the picture.
    assert np.any(np.all(img == (200, 90, 20), axis=2))


def test_bad_coordinates_exit_2(map_dir: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["plan", "--map", str(map_dir), "--start", "1;1", "--goal", "5,1"])
    assert exc.value.code == 2


def test_missing_map_folder_exit_2(tmp_path: Path) -> None:
    assert main(["plan", "--map", str(tmp_path / "nope"), "--start", "1,1", "--goal", "5,1"]) == 2


def test_plans_on_a_saved_semantic_map(tmp_path: Path) -> None:
    from semmap.costmap import ObjectFootprint, VerticalBand
    from semmap.semantic_map import SemanticMap, SemanticMapSettings

    settings = SemanticMapSettings(
        class_names=("desk",), scan_band=VerticalBand(0.4, 0.6), origin_xy_m=(0.0, 0.0),
        size_xy_m=(6.0, 3.0), fixed_size=True,
    )
    smap = SemanticMap(settings)
    desk = np.array([[2.6, -0.5], [3.4, -0.5], [3.4, 3.5], [2.6, 3.5]])
    smap.set_objects([ObjectFootprint(1, "desk", desk, 0.0, 0.75, existence=0.95)], stamp_s=0.0)
    smap.save(tmp_path / "semantic_map.npz")
    rc, res = _plan(tmp_path, "--altitude", "0.5")
    assert rc == 1 and res["status"] == "disconnected"
    rc, res = _plan(tmp_path, "--altitude", "1.5")
    assert rc == 0 and res["status"] == "ok"
