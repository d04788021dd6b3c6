"""A 2D world of wall segments and a ray caster: synthetic scans for the SLAM unit tests."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray


def box_segments(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float, float, float]]:
    """The four sides of an axis-aligned rectangle as (xa, ya, xb, yb) segments."""
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def room_world() -> list[tuple[float, float, float, float]]:
    """A 8 m x 6 m room with two pillars and a table's four legs (10 cm squares)."""
    segs = box_segments(0.0, 0.0, 8.0, 6.0)
    segs += box_segments(2.5, 2.0, 3.0, 2.4) + box_segments(5.5, 3.5, 5.8, 4.2)
    for lx, ly in ((4.0, 1.2), (4.9, 1.2), (4.0, 1.8), (4.9, 1.8)):
        segs += box_segments(lx, ly, lx + 0.1, ly + 0.1)
    return segs


def corridor_world(length_m: float = 60.0, width_m: float = 2.0) -> list[tuple[float, float, float, float]]:
    """Two long parallel walls along x (a featureless corridor)."""
    return [(-length_m / 2, 0.0, length_m / 2, 0.0), (-length_m / 2, width_m, length_m / 2, width_m)]


def cast(segments: list[tuple[float, float, float, float]], pose: NDArray[np.float64], fov_deg: float = 80.0,
         n_rays: int = 160, max_range_m: float = 6.0, noise_m: float = 0.0,
         rng: np.random.Generator | None = None) -> NDArray[np.float64]:
    """(K, 2) hit points in the body frame of a scan from ``pose`` (x, y, yaw), ordered by
    bearing; rays that hit nothing within range are dropped."""
    seg = np.asarray(segments, dtype=np.float64)  # (S, 4)
    ang = np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, n_rays))
    th = pose[2] + ang
    d = np.stack([np.cos(th), np.sin(th)], axis=1)  # (R, 2)
    a, b = seg[:, :2], seg[:, 2:]
    e = b - a  # (S, 2)
    o = pose[:2]
    # Solve o + t d = a + u e for each ray and segment.
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (R, S)
    w = a[None, :, :] - o[None, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / den
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / den
    ok = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    t = np.where(ok, t, np.inf).min(axis=1)
    keep = t <= max_range_m
    r = t[keep]
    if noise_m > 0:
        r = r + (rng or np.random.default_rng(0)).normal(0.0, noise_m, size=r.shape)
    return np.stack([r * np.cos(ang[keep]), r * np.sin(ang[keep])], axis=1)


def yaw_sweep_path(n: int, rate_hz: float = 10.0) -> NDArray[np.float64]:
    """(n, 3) poses of a lap around the room at 0.4 m/s with a +-40 deg camera sweep."""
    corners = np.array([(1.2, 1.0), (6.8, 1.0), (6.8, 5.0), (1.2, 5.0), (1.2, 1.0)])
    seg_len = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    out = []
    for i in range(n):
        s = (0.4 * i / rate_hz) % cum[-1]
        k = int(np.searchsorted(cum, s, side="right") - 1)
        f = (s - cum[k]) / seg_len[k]
        p = corners[k] + f * (corners[k + 1] - corners[k])
        heading = math.atan2(*(corners[k + 1] - corners[k])[::-1])
        out.append((p[0], p[1], heading + math.radians(40.0) * math.sin(2 * math.pi * i / rate_hz / 6.0)))
    return np.array(out)
