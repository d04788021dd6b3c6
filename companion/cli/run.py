"""``companion run --config FILE``: the onboard service, until SIGTERM or Ctrl-C.

This is what ``systemd/companion.service`` starts. With ``camera.source: sim`` (the embedded
default) the simulated world runs in the same process: the mock PX4 autopilot on the
``sim`` ports (the link's default ``udpin://0.0.0.0:14540`` hears it) and the simulated
camera riding on it; with ``sim.autopilot: external`` as well, the autopilot on ``link.url``
(PX4 SITL) flies and the simulated camera renders the room from the pose it reports. ``--fly-mission`` downloads the autopilot's mission once connected and
flies it; otherwise missions start with a ``cmd/mission`` ``start`` over MQTT and goals come
on ``cmd/goal``. SIGTERM ends cleanly: hold or land (``service.on_sigterm``), stop
streaming, save the map.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
from typing import Any

from companion.config import load_config
from companion.config_checks import check_runtime

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "run", help="run the companion service (camera, map, planner, offboard, MQTT)",
        description="Run the onboard service until SIGTERM/Ctrl-C. With camera.source 'sim' the "
        "simulated world (mock autopilot + simulated camera) runs in-process.",
    )
    p.add_argument("--config", default=None, help="config file (default: embedded default)")
    p.add_argument("--fly-mission", action="store_true",
                   help="download the autopilot's mission once connected and fly it")
    p.add_argument("--out", default=None, help="output folder for the flight log (default service.output_dir)")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    check_runtime(cfg, args.config or "the embedded default config")
    asyncio.run(_serve(cfg, args.fly_mission, args.out))
    return 0


async def _serve(cfg: Any, fly_mission: bool, out: str | None) -> None:
    from companion.service.app import CompanionService
    from companion.service.shutdown import HUNG_STOP_EXIT_CODE
    from companion.sources import make_frame_source

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    async with contextlib.AsyncExitStack() as stack:
        object_classes = None
        world_px4 = None
        if cfg.camera.source == "sim" and cfg.sim.autopilot == "external":
            from companion.sim.px4_world import Px4World, vehicle_start_map_xy

            # The autopilot on link.url flies; the simulated room is placed around where it stands.
            world_px4 = Px4World(cfg, await vehicle_start_map_xy(cfg.link), target_system=cfg.link.target_system,
                                 target_component=cfg.link.target_component)
            source = world_px4.frame_source()
            object_classes = {o.object_id: o.class_name for o in world_px4.room.objects}
        elif cfg.camera.source == "sim":
            from companion.sim.sim_world import SimWorld

            world = await stack.enter_async_context(SimWorld(cfg))
            source = world.frame_source()
            object_classes = {o.object_id: o.class_name for o in world.room.objects}
        else:
            source = make_frame_source(cfg)
        service = CompanionService(cfg, source, out_dir=out, object_classes=object_classes,
                                   fly_mission=fly_mission, land_after_mission=False)
        # A stop the event loop cannot end ends this process (systemd restarts a failed unit).
        service.hung_stop_exit_code = HUNG_STOP_EXIT_CODE
        if world_px4 is not None:
            follower = world_px4

            def follow(svc: CompanionService) -> None:
                assert svc.vehicle is not None
                follower.follow(svc.vehicle.link)

            service.on_active = follow
        log.info("companion service starting (camera %s, link %s)", cfg.camera.source, cfg.link.url)
        report = await service.run(stop)
        if report.stop_overruns:
            # Tasks that ignored their cancellation are still alive: asyncio.run's own clean-up
            # would wait for them for good.
            log.critical("the stop overran (%s): ending the process with exit code %d",
                         "; ".join(report.stop_overruns), HUNG_STOP_EXIT_CODE)
            logging.shutdown()
            os._exit(HUNG_STOP_EXIT_CODE)
