"""What ``companion run`` needs of a configuration beyond its schema, checked before it runs.

:func:`check_runtime` looks at the machine the config is meant for: the files it names
exist and can be read (MQTT password and TLS files, the MAVLink signing key, the detector
model, a recording), the output and map folders can be written, and a map checkpoint in
``service.map_dir`` was made with the configured map settings. ``config check`` and ``run``
both call it, so a config that passes ``config check`` does not fail at start for these.
Problems are :class:`~companion.errors.ConfigError` naming the key and the path.
"""

from __future__ import annotations

import os
from pathlib import Path

from companion.config import CompanionConfig
from companion.errors import ConfigError
from semmap.detection.builtin import resolve_model_path


def _readable_file(key: str, path: str | None, problems: list[str], *,
                   non_empty: bool = False) -> None:
    if path is None:
        return
    p = Path(path)
    if not p.is_file():
        problems.append(f"{key}: {p} does not exist or is not a file")
    elif not os.access(p, os.R_OK):
        problems.append(f"{key}: {p} is not readable by this user")
    elif non_empty and p.stat().st_size == 0:
        problems.append(f"{key}: {p} is empty")


def _writable_dir(key: str, path: str, problems: list[str]) -> None:
    """``path`` is a writable folder, or can be created as one."""
    p = Path(path).absolute()
    for candidate in (p, *p.parents):
        if candidate.exists():
            if not candidate.is_dir():
                problems.append(f"{key}: {p} cannot be a folder: {candidate} is a file")
            elif not os.access(candidate, os.W_OK | os.X_OK):
                problems.append(f"{key}: {p} is not writable ({candidate} is not writable "
                                "by this user)")
            return


def _signing_key(path: str | None, problems: list[str]) -> None:
    if path is None:
        return
    from companion.mavlink.link import load_signing_key  # local: keeps config imports light

    try:
        load_signing_key(path)
    except ConfigError as exc:
        problems.append(f"link.signing_key_path: {exc}")


def _detector_model(cfg: CompanionConfig, problems: list[str]) -> None:
    path = resolve_model_path(cfg.detector.model_path, real_camera=cfg.camera.is_real)
    if cfg.detector.kind != "onnx" or path is None or path.startswith("builtin:"):
        return  # built-in models ship with the package (a test keeps them loadable)
    _readable_file("detector.model_path", path, problems)


def runtime_problems(cfg: CompanionConfig) -> list[str]:
    """Every reason ``cfg`` would fail at ``run`` on this machine (empty when none)."""
    problems: list[str] = []
    if cfg.mqtt.enabled:
        _readable_file("mqtt.password_file", cfg.mqtt.password_file, problems, non_empty=True)
        _readable_file("mqtt.tls_ca_file", cfg.mqtt.tls_ca_file, problems)
        _readable_file("mqtt.tls_cert_file", cfg.mqtt.tls_cert_file, problems)
        _readable_file("mqtt.tls_key_file", cfg.mqtt.tls_key_file, problems)
    _signing_key(cfg.link.signing_key_path, problems)
    _detector_model(cfg, problems)
    if cfg.camera.source == "recorded":
        rec = cfg.camera.recorded_path
        if rec is not None and not Path(rec).exists():
            problems.append(f"camera.recorded_path: {rec} does not exist")
    _writable_dir("service.output_dir", cfg.service.output_dir, problems)
    # The perception process saves the map there; a bad folder must not surface only when it
    # fails to start.
    _writable_dir("service.map_dir", cfg.service.map_dir, problems)
    from companion.service.checkpoint import checkpoint_mismatch, checkpoint_path

    mismatch = checkpoint_mismatch(cfg, checkpoint_path(cfg))
    if mismatch is not None:
        problems.append(mismatch)
    return problems


def check_runtime(cfg: CompanionConfig, source: str) -> None:
    """Raise :class:`ConfigError` listing every problem of :func:`runtime_problems`."""
    problems = runtime_problems(cfg)
    if problems:
        raise ConfigError("\n".join(f"{source}: {p}" for p in problems))
