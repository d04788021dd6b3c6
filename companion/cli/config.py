"""``companion config check FILE`` and ``companion config dump``.

``check`` runs what ``run`` would check before starting: the schema and cross-key rules,
then the files, folders and map checkpoint the config names (:mod:`companion.config_checks`).
"""

from __future__ import annotations

import argparse

from companion.config import dump_config, load_config
from companion.config_checks import check_runtime


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("config", help="check or print configuration")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION")
    csub.required = True
    check = csub.add_parser("check", help="validate a config file; exit 2 with the reason if bad")
    check.add_argument("file")
    check.add_argument("--allow-empty", action="store_true",
                       help="accept an empty file (the built-in defaults) or one without a "
                            "final newline")
    check.set_defaults(func=_check)
    dump = csub.add_parser("dump", help="print the effective config as YAML")
    dump.add_argument("--config", default=None, help="file to load (default: embedded default)")
    dump.set_defaults(func=_dump)


def _check(args: argparse.Namespace) -> int:
    check_runtime(load_config(args.file, allow_empty=args.allow_empty), args.file)
    print(f"{args.file}: ok")
    return 0


def _dump(args: argparse.Namespace) -> int:
    print(dump_config(load_config(args.config)), end="")
    return 0
