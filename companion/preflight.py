"""Checks of a configuration against the machine it runs on (files and folders it needs).

:func:`check_paths` runs in ``companion config check`` and before ``companion run`` starts
anything, so a folder the service cannot write or a key file it cannot trust is a
configuration error (exit code 2) naming the key and the path, never a failure (or a hang)
after the service has started.
"""

from __future__ import annotations

import os
from pathlib import Path

from companion.config import CompanionConfig
from semmap.errors import ConfigError


def dir_problem(path: Path) -> str | None:
    """Why ``path`` cannot be used as a writable folder (created if missing), or None."""
    if path.exists():
        if not path.is_dir():
            return "exists and is not a directory"
        if not os.access(path, os.W_OK | os.X_OK):
            return "is not writable"
        return None
    ancestor = path.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return f"cannot be created: {ancestor} is not a directory"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"cannot be created: {ancestor} is not writable"
    return None


def check_paths(cfg: CompanionConfig, source: str) -> None:
    """Raise :class:`ConfigError` (every problem, one per line) when a folder the service
    writes cannot be written or the MAVLink signing key file is unusable."""
    problems = []
    for key, value in (("service.map_dir", cfg.service.map_dir), ("service.output_dir", cfg.service.output_dir)):
        why = dir_problem(Path(value))
        if why is not None:
            problems.append(f"{source}: {key}: {value} {why}")
    if cfg.link.signing_key_path is not None:
        from companion.mavlink.signing import key_file_problem  # local: config check stays light

        why = key_file_problem(Path(cfg.link.signing_key_path))
        if why is not None:
            problems.append(f"{source}: link.signing_key_path: {why}")
    if problems:
        raise ConfigError("\n".join(problems))
