"""``companion keygen FILE``: a new MAVLink 2 signing key for ``link.signing_key_path``."""

from __future__ import annotations

import argparse

from companion.mavlink.signing import write_key_file


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "keygen", help="write a new MAVLink 2 signing key file (mode 0600)",
        description="Write a random 32-byte MAVLink 2 signing key as 64 hex characters into FILE, "
        "readable by its owner only. Set link.signing_key_path to it and give the autopilot the "
        "same key (docs/mavlink.md).",
    )
    p.add_argument("file", help="the key file to create")
    p.add_argument("--force", action="store_true", help="replace an existing key file")
    p.set_defaults(func=_keygen)


def _keygen(args: argparse.Namespace) -> int:
    write_key_file(args.file, overwrite=args.force)
    print(f"{args.file}: new MAVLink 2 signing key written (mode 0600)")
    return 0
