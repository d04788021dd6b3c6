"""``companion plan`` input and output at the edges (issue 33, item 7): negative start and
goal coordinates parse in both spellings, and ``--json`` is strict JSON (null, never NaN)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from companion.cli import main
from semmap.export import write_ros_map
from semmap.grid import GridSpec

SPEC = GridSpec(0.05, (-2.0, -2.0), (80, 160))  # x -2..6, y -2..2


@pytest.fixture()
def map_dir(tmp_path: Path) -> Path:
    """A walled room with a wall across it at x = 2 (a closed gap: no path across)."""
    prob = np.zeros(SPEC.shape_rc, np.float32)
    prob[:2, :] = prob[-2:, :] = prob[:, :2] = prob[:, -2:] = 1.0
    prob[:, 78:82] = 1.0
    write_ros_map(tmp_path / "map", prob, SPEC)
    return tmp_path


def _plan(*argv: str) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["plan", *argv, "--time-limit", "0.1", "--json"])
    return rc, buf.getvalue().strip().splitlines()[-1]


def _strict_json(text: str) -> dict:
    def refuse(const: str) -> None:
        raise AssertionError(f"{const} is not JSON: {text}")
    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize("argv", [
    ["--start", "-1.5,-0.5", "--goal", "-0.5,1.3"],
    ["--start=-1.5,-0.5", "--goal=-0.5,1.3"],
    ["--start", "-1.5,-.5", "--goal", "-5e-1,1.3"],
])
def test_negative_start_and_goal_parse(map_dir: Path, argv: list[str]) -> None:
    rc, out = _plan("--map", str(map_dir), *argv)
    res = _strict_json(out)
    assert rc == 0 and res["status"] == "ok"
    assert res["path_xy_m"][0] == pytest.approx([-1.5, -0.5], abs=1e-6)
    assert res["path_xy_m"][-1] == pytest.approx([-0.5, 1.3], abs=1e-6)


def test_a_real_option_after_start_is_still_an_option(map_dir: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["plan", "--map", str(map_dir), "--start", "--goal", "1,1"])
    assert exc.value.code == 2


def test_json_without_a_path_has_null_not_nan(map_dir: Path) -> None:
    rc, out = _plan("--map", str(map_dir), "--start", "-1,0", "--goal", "4,0")
    assert rc == 1 and "NaN" not in out and "Infinity" not in out
    res = _strict_json(out)
    assert res["status"] != "ok" and res["path_xy_m"] == []
    assert res["length_m"] is None and res["cost"] is None
