"""``companion mission check|upload|download|clear``: mission files and transfer via MAVSDK.

``check FILE`` validates a ``.plan`` or YAML mission offline; ``upload FILE`` sends it to the
autopilot (``--start`` also arms and starts it), ``download FILE`` saves the vehicle's mission
(``.plan`` or ``.yaml`` by suffix), ``clear`` deletes it. The connection URL defaults to
``link.url`` of the config (``udpin://0.0.0.0:14540``).
"""

from __future__ import annotations

import argparse
import asyncio
import math
from typing import TYPE_CHECKING

from companion.config import load_config
from companion.errors import DataError, MissionError
from companion.mission_files import load_mission, save_mission
from companion.mission_validation import check_plan
from companion.missions import MissionPlan

if TYPE_CHECKING:
    from companion.mavsdk_client import MavsdkClient


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("mission", help="check, upload or download missions (.plan / YAML)")
    msub = p.add_subparsers(dest="mission_command", metavar="ACTION")
    msub.required = True

    def common(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--config", default=None, help="config file (default: embedded default)")
        sp.add_argument("--url", default=None,
                        help="MAVSDK connection URL (default: link.url from the config)")
        sp.add_argument("--timeout", type=float, default=10.0,
                        help="seconds to wait for the autopilot (default 10)")

    check = msub.add_parser("check", help="validate a mission file offline")
    check.add_argument("file")
    check.set_defaults(func=_check)
    up = msub.add_parser("upload", help="upload a mission file to the autopilot")
    up.add_argument("file")
    up.add_argument("--start", action="store_true", help="arm and start the mission after upload")
    common(up)
    up.set_defaults(func=_upload)
    down = msub.add_parser("download", help="save the autopilot's mission to FILE")
    down.add_argument("file")
    common(down)
    down.set_defaults(func=_download)
    clear = msub.add_parser("clear", help="delete the autopilot's mission")
    common(clear)
    clear.set_defaults(func=_clear)


def _load(path: str) -> MissionPlan:
    """The mission in ``path``, checked as upload checks it (check and upload agree)."""
    try:
        plan = load_mission(path)
        if plan.home is not None:  # the positions upload will send are known: check them too
            check_plan(plan.resolved(None))
        return plan
    except MissionError as exc:
        raise DataError(str(exc)) from exc  # a bad file is bad input (exit code 2)


def _summary(plan: MissionPlan) -> str:
    counts: dict[str, int] = {}
    for w in plan.waypoints:
        counts[w.action] = counts.get(w.action, 0) + 1
    parts = ", ".join(f"{n} {a}" for a, n in counts.items())
    return f"{len(plan.waypoints)} steps ({parts})"


def _url(args: argparse.Namespace) -> str:
    return str(args.url or load_config(args.config).link.url)


def _client(args: argparse.Namespace) -> MavsdkClient:
    # Imported here: loading MAVSDK's native core costs time every other command should not pay.
    from companion.mavsdk_client import MavsdkClient

    return MavsdkClient(_url(args), connect_timeout_s=args.timeout)


def _check(args: argparse.Namespace) -> int:
    plan = _load(args.file)
    print(f"{args.file}: ok, {_summary(plan)}")
    for i, w in enumerate(plan.waypoints):
        if w.xyz_map_m is not None:
            where = "x={:.2f} y={:.2f} z={:.2f} m (map)".format(*w.xyz_map_m)
        elif math.isfinite(w.lat_deg):
            where = f"lat={w.lat_deg:.7f} lon={w.lon_deg:.7f} alt={w.rel_alt_m:.2f} m"
        else:
            where = "here" if w.action != "takeoff" else f"alt={w.rel_alt_m:.2f} m"
        print(f"  {i:3d} {w.action:<8} {where}")
    return 0


def _upload(args: argparse.Namespace) -> int:
    plan = _load(args.file)

    async def run() -> None:
        async with _client(args) as client:
            imap = await client.upload_mission(plan)
            print(f"uploaded {args.file}: {_summary(plan)} as {len(imap.items)} MAVLink items")
            if args.start:
                await client.arm()
                await client.start_mission()
                print("mission started")

    asyncio.run(run())
    return 0


def _download(args: argparse.Namespace) -> int:
    async def run() -> None:
        async with _client(args) as client:
            plan = await client.download_mission()
        path = save_mission(plan, args.file)
        print(f"saved the vehicle's mission to {path}: {_summary(plan)}")

    asyncio.run(run())
    return 0


def _clear(args: argparse.Namespace) -> int:
    async def run() -> None:
        async with _client(args) as client:
            await client.clear_mission()
        print("mission cleared")

    asyncio.run(run())
    return 0
