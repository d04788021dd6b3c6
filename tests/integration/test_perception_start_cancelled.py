"""A perception process whose start is cancelled (the service's start-up given up: its caller's
task group failed, Ctrl-C) does not outlive it. The child ignores SIGTERM (the service decides
when perception stops), and multiprocessing's exit handler sends daemonic children SIGTERM and
then waits for them: the interpreter never exited."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("open3d")

REPO = Path(__file__).resolve().parents[2]
CFG: dict[str, Any] = {
    "camera": {"width_px": 160, "height_px": 120, "fx_px": 96.0, "fy_px": 96.0, "cx_px": 80.0, "cy_px": 60.0},
    "sim": {"seed": 3, "room_width_m": 6.0, "room_depth_m": 5.0, "n_objects": 4, "layout": "scattered",
            "camera_pose": "autopilot"},
}
SCRIPT = """
import asyncio, contextlib, json, signal, sys
from pathlib import Path
from companion.config import config_from_dict
from companion.service.perception_process import PerceptionProcess
from companion.sim.sim_world import SimWorld

cfg = config_from_dict(json.loads(sys.argv[1]))

def ignores_sigterm(pid):
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigIgn:"):
            return bool(int(line.split()[1], 16) & (1 << (signal.SIGTERM - 1)))
    return False

async def main():
    async with SimWorld(cfg, autopilot_port=0, remote_ports=()) as world:
        p = PerceptionProcess(cfg, world.frame_source())
        start = asyncio.ensure_future(p.__aenter__())
        while p.worker is None or p.worker.pid is None or not ignores_sigterm(p.worker.pid):
            await asyncio.sleep(0.01)
        # It has set SIGTERM aside and now warms up its kernels for seconds: still starting.
        assert not start.done(), "the perception process was ready too soon for this test"
        start.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await start
        print("child", p.worker.pid, flush=True)

asyncio.run(main())
print("returned", flush=True)
"""


def test_perception_start_cancelled_leaves_no_child_for_the_interpreters_exit_to_wait_for(tmp_path: Path) -> None:
    doc = {**CFG, "service": {"map_dir": str(tmp_path / "map")}}
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, json.dumps(doc)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        out, _ = proc.communicate(timeout=120.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate(timeout=10.0)
        pytest.fail(f"the process did not exit after its perception start was cancelled:\n{out[-3000:]}")
    assert "returned" in out, out[-3000:]
    assert proc.returncode == 0, out[-3000:]
