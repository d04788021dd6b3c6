"""MAVLink 2 signing keys on disk: the file the link and the mock autopilot read, and its checks.

A key file holds the 32-byte secret as 64 hex characters (``companion keygen`` writes one) or as
the 32 raw bytes. It must be readable by its owner only (mode 0600 or stricter): anyone who can
read it can command the vehicle.
"""

from __future__ import annotations

import os
import secrets
import stat
from pathlib import Path

from semmap.errors import ConfigError

#: MAVLink 2 signing keys are 32 bytes.
SIGNING_KEY_BYTES = 32


def parse_key(raw: bytes) -> bytes | None:
    """The key in a key file's content (raw or hex), or None when it is neither."""
    if len(raw) == SIGNING_KEY_BYTES:
        return raw
    text = raw.decode("ascii", errors="replace").strip()
    if len(text) == 2 * SIGNING_KEY_BYTES:
        try:
            return bytes.fromhex(text)
        except ValueError:
            return None
    return None


def key_file_problem(path: Path) -> str | None:
    """Why ``path`` is not a usable signing key file (naming the path), or None."""
    try:
        st = path.stat()
        raw = path.read_bytes()
    except OSError as exc:
        return f"{path}: cannot read MAVLink signing key: {exc.strerror or exc}"
    if parse_key(raw) is None:
        return (f"{path}: MAVLink signing key must be {SIGNING_KEY_BYTES} raw bytes or "
                f"{2 * SIGNING_KEY_BYTES} hex characters (got {len(raw)} bytes)")
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        return (f"{path}: MAVLink signing key is readable by others (mode {stat.S_IMODE(st.st_mode):04o}); "
                f"run: chmod 600 {path}")
    return None


def read_key_file(path: str | Path) -> bytes:
    """The 32-byte key in ``path``; raises :class:`ConfigError` naming the file when it is
    missing, malformed or readable by others."""
    p = Path(path)
    why = key_file_problem(p)
    if why is not None:
        raise ConfigError(why)
    key = parse_key(p.read_bytes())
    assert key is not None
    return key


def write_key_file(path: str | Path, *, overwrite: bool = False) -> bytes:
    """Write a new random key to ``path`` as hex, mode 0600 from its creation; returns the key.
    Refuses to replace an existing file unless ``overwrite``."""
    p = Path(path)
    key = secrets.token_bytes(SIGNING_KEY_BYTES)
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
    try:
        fd = os.open(p, flags, 0o600)
    except FileExistsError as exc:
        raise ConfigError(f"{p}: a key file exists already (give --force to replace it)") from exc
    except OSError as exc:
        raise ConfigError(f"{p}: cannot write the signing key: {exc.strerror or exc}") from exc
    with os.fdopen(fd, "w", encoding="ascii") as f:
        os.fchmod(f.fileno(), 0o600)
        f.write(key.hex() + "\n")
    return key
