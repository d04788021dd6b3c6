"""``companion sim-autopilot``: run the mock PX4 autopilot until Ctrl-C or SIGTERM.

PX4's port layout by default: the mock sends from UDP 14580 to 14540 (the API/offboard link
that MAVSDK and our link listen on with ``udpin://0.0.0.0:14540``) and to 14550 (a ground
station such as QGroundControl). Ports and home come from the ``sim`` config section and can
be overridden on the command line.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
from typing import TYPE_CHECKING

from companion.config import load_config
from companion.geo import GeoOrigin

if TYPE_CHECKING:
    from companion.sim.autopilot.behaviour import Px4Behaviour

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("sim-autopilot", help="run the mock PX4 autopilot (MAVLink over UDP)")
    p.add_argument("--config", default=None, help="config file (default: embedded default)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1; 0.0.0.0 for other machines)")
    p.add_argument("--remote-host", default=None,
                   help="address of the API and ground-station peers (default: --host, or "
                   "127.0.0.1 when binding 0.0.0.0)")
    p.add_argument("--local-port", type=int, default=None,
                   help="UDP port the mock binds (default sim.autopilot_local_port, 14580)")
    p.add_argument("--offboard-port", type=int, default=None,
                   help="API/offboard port it sends to (default sim.autopilot_offboard_port, 14540)")
    p.add_argument("--gcs-port", type=int, default=None,
                   help="ground-station port it sends to (default sim.autopilot_gcs_port, 14550); "
                   "0 disables")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="set a PX4 parameter, e.g. --param COM_DISARM_PRFLT=-1 (repeatable)")
    p.add_argument("--naive", action="store_true",
                   help="an idealised autopilot instead of PX4's ways (origin on the floor, ready at "
                   "once, ...; docs/mock-autopilot.md)")
    p.add_argument("--behaviour", action="append", default=[], metavar="NAME=VALUE",
                   help="one PX4 behaviour switch, e.g. --behaviour ready_after_s=20 (repeatable)")
    p.set_defaults(func=_run)


def _parse_params(items: list[str]) -> dict[str, float]:
    from companion.errors import ConfigError
    from companion.sim.autopilot.params import PARAM_SPECS

    known = {s.name for s in PARAM_SPECS}
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--param {item!r}: expected NAME=VALUE")
        if name not in known:
            raise ConfigError(f"--param {name}: unknown parameter (known: {', '.join(sorted(known))})")
        try:
            out[name] = float(value)
        except ValueError as exc:
            raise ConfigError(f"--param {name}: {value!r} is not a number") from exc
    return out


def _run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config).sim
    local = args.local_port if args.local_port is not None else cfg.autopilot_local_port
    offboard = args.offboard_port if args.offboard_port is not None else cfg.autopilot_offboard_port
    gcs = args.gcs_port if args.gcs_port is not None else cfg.autopilot_gcs_port
    remotes = [p for p in (offboard, gcs) if p]
    home = GeoOrigin(cfg.home_lat_deg, cfg.home_lon_deg, cfg.home_alt_m)
    params = _parse_params(args.param)
    behaviour = _parse_behaviour(args.behaviour, args.naive)
    remote_host = args.remote_host or ("127.0.0.1" if args.host == "0.0.0.0" else args.host)
    asyncio.run(_serve(args.host, local, remote_host, remotes, home, params, behaviour))
    return 0


def _parse_behaviour(items: list[str], naive: bool) -> Px4Behaviour:
    from companion.errors import ConfigError
    from companion.sim.autopilot.behaviour import Px4Behaviour, behaviour_from_settings

    try:
        return behaviour_from_settings(items, Px4Behaviour.naive() if naive else None)
    except ValueError as exc:
        raise ConfigError(f"--behaviour: {exc}") from exc


async def _serve(host: str, local: int, remote_host: str, remotes: list[int],
                 home: GeoOrigin, params: dict[str, float], behaviour: Px4Behaviour) -> None:
    from companion.sim.autopilot import MockAutopilot  # pymavlink's dialect is slow to import

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    async with MockAutopilot(host=host, local_port=local, remote_ports=remotes,
                             remote_host=remote_host, home=home, params=params, behaviour=behaviour):
        await stop.wait()
        log.info("stopping mock autopilot")
