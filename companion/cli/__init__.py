"""The ``companion`` command line.

The only place that sets up logging, prints for the user and turns errors into exit codes
(0 ok, 1 runtime failure, 2 bad input or config, 130 interrupted) so systemd's restart policy
can act. Each subcommand lives in its own ``companion.cli.*`` module exposing
``register(subparsers)``; the module sets ``func`` on its parser.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from companion import __version__
from companion.errors import CompanionError, ConfigError, DataError

log = logging.getLogger("companion")

#: Subcommand modules, in the order ``--help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "companion.cli.config",
    "companion.cli.demo",
    "companion.cli.sim",
    "companion.cli.mission",
    "companion.cli.dataset",
    "companion.cli.map",
    "companion.cli.plan",
    "companion.cli.run",
    "companion.cli.keygen",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Onboard companion for PX4 drones: semantic mapping of hollow-bottom "
        "furniture, planning around it, and offboard flight.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument(
        "--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="logging threshold (default INFO)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        rc = args.func(args)
    except (ConfigError, DataError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except CompanionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
