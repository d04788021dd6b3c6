"""What a RealSense D455 does to the simulated camera's perfect images (see docs/simulation.md).

Depth (:class:`DepthNoise`, :func:`apply_depth`), each effect switchable and driven by the
caller's seeded generator:

* noise growing with the square of range: ``sigma = noise_coeff * z**2`` (Intel's datasheet:
  under 2 % RMS error at 4 m, so ``0.02 * 4 / 16 = 0.005`` per metre);
* flying pixels: along depth edges, stereo matching mixes foreground and background, giving
  points between the two surfaces; or no depth at all there (``edge_dropout``);
* holes on dark surfaces (too little texture from the IR projector) and on shiny ones seen
  head-on (the projector's glare), and more holes towards the end of the usable range;
* the minimum range, which scales with the depth resolution (about 0.5 m at 848x480);
* quantisation: disparity in sub-pixel steps (depth steps growing with z**2), then z16
  millimetres.

Colour (:class:`ColorModel`, :func:`apply_color`): auto-exposure that brightens dark views and
darkens bright ones frame by frame (with clipped highlights), and motion blur along the image
motion of a fast turn during the exposure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: D455 stereo baseline (Intel's datasheet), metres.
D455_BASELINE_M = 0.095
#: Depth resolution width at which :attr:`DepthNoise.min_z_m` holds (the issue's anchor:
#: about 0.5 m at 848x480); min-Z scales with the resolution (Intel's tuning guide).
MIN_Z_REFERENCE_WIDTH_PX = 848


@dataclass(frozen=True)
class DepthNoise:
    """D455-like depth model (metres); every effect is off at 0 / False."""

    #: sigma = coeff * z**2 (0.005: 2 % RMS at 4 m).
    noise_coeff: float = 0.005
    #: Probability a pixel at a depth discontinuity is invalid.
    edge_dropout: float = 0.5
    min_m: float = 0.3
    max_m: float = 6.0
    #: Neighbouring depths differing by more than this fraction of the nearer are an edge.
    edge_rel_jump: float = 0.05
    #: Output quantisation step (RealSense z16 counts millimetres).
    quantum_m: float = 0.001
    #: Probability an edge pixel that keeps its depth gets one between its two surfaces.
    flying_pixels: float = 0.3
    #: Surfaces darker than this albedo (0..1) lose depth, with probability growing to
    #: ``dark_holes`` at black.
    dark_albedo: float = 0.15
    dark_holes: float = 0.8
    #: Probability a shiny surface (screens, whiteboards, glazing) seen within about 18
    #: degrees of head-on loses its depth.
    shiny_holes: float = 0.7
    #: Probability of a hole grows linearly from 0 at ``far_start * max_m`` to this at ``max_m``.
    far_dropout: float = 0.4
    far_start: float = 0.75
    #: Disparity quantisation step (D4 vision processor: 1/32 pixel sub-pixel steps); 0: off.
    disparity_step_px: float = 1.0 / 32.0
    #: Minimum range at :data:`MIN_Z_REFERENCE_WIDTH_PX`; 0: only ``min_m`` applies.
    min_z_m: float = 0.5

    def effective_min_m(self, width_px: int) -> float:
        """The nearest valid depth at a depth image ``width_px`` wide."""
        return max(self.min_m, self.min_z_m * width_px / MIN_Z_REFERENCE_WIDTH_PX)


#: Every depth effect off: the noise-free geometry within [min_m, max_m].
def exact_depth(min_m: float = 0.0, max_m: float = 100.0) -> DepthNoise:
    return DepthNoise(noise_coeff=0.0, edge_dropout=0.0, min_m=min_m, max_m=max_m, quantum_m=0.0,
                      flying_pixels=0.0, dark_holes=0.0, shiny_holes=0.0, far_dropout=0.0,
                      disparity_step_px=0.0, min_z_m=0.0)


def depth_edges(zf: NDArray[np.float32], rel_jump: float) -> NDArray[np.bool_]:
    """(H, W) True at both pixels of every horizontally or vertically jumping pair."""
    edge = np.zeros(zf.shape, dtype=bool)
    jump_h = np.abs(zf[:, 1:] - zf[:, :-1]) > rel_jump * np.minimum(zf[:, 1:], zf[:, :-1])
    jump_v = np.abs(zf[1:, :] - zf[:-1, :]) > rel_jump * np.minimum(zf[1:, :], zf[:-1, :])
    edge[:, 1:] |= jump_h
    edge[:, :-1] |= jump_h
    edge[1:, :] |= jump_v
    edge[:-1, :] |= jump_v
    return edge


def _neighbour_range(zf: NDArray[np.float32], v: NDArray[np.intp],
                     u: NDArray[np.intp]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Nearest and farthest depth among pixels (v, u) and their four neighbours."""
    H, W = zf.shape
    stack = np.stack([zf[v, u], zf[np.maximum(v - 1, 0), u], zf[np.minimum(v + 1, H - 1), u],
                      zf[v, np.maximum(u - 1, 0)], zf[v, np.minimum(u + 1, W - 1)]])
    return stack.min(axis=0), stack.max(axis=0)


def apply_depth(
    z: NDArray[np.float32],
    model: DepthNoise,
    rng: np.random.Generator,
    gaussian: NDArray[np.float32] | None,
    fx_px: float,
    albedo: NDArray[np.float32] | None = None,
    shiny_head_on: NDArray[np.bool_] | None = None,
) -> NDArray[np.float32]:
    """(H, W) float32 metres with the D455 effects; 0 where invalid.

    ``z`` is the noise-free z-depth (inf where nothing is hit); ``gaussian`` (H*W,) standard
    normals for the range noise (None when ``noise_coeff`` is 0); ``albedo`` (H, W) each
    pixel's surface albedo 0..1; ``shiny_head_on`` (H, W) True on shiny surfaces seen nearly
    head-on. Draws from ``rng`` in a fixed order, so a seed reproduces the frame.
    """
    m = model
    H, W = z.shape
    finite = np.isfinite(z)
    zf = np.where(finite, z, np.float32(1e6)).astype(np.float32)
    edge = depth_edges(zf, m.edge_rel_jump)
    out = zf.copy()
    if m.noise_coeff > 0 and gaussian is not None:
        out += gaussian.reshape(z.shape) * (np.float32(m.noise_coeff) * zf * zf)
    ev, eu = np.nonzero(edge)
    u_edge = rng.random(len(ev)) if len(ev) else np.zeros(0)
    drop_edge = u_edge < m.edge_dropout
    if m.flying_pixels > 0 and len(ev):
        # A kept edge pixel flies: its depth lands anywhere between its surface and the far one.
        fly = ~drop_edge & (u_edge < m.edge_dropout + m.flying_pixels * (1.0 - m.edge_dropout))
        fv, fu = ev[fly], eu[fly]
        near, far = _neighbour_range(zf, fv, fu)
        ok = far < 1e5
        t = rng.random(len(fv)).astype(np.float32)
        out[fv[ok], fu[ok]] = near[ok] + t[ok] * (far[ok] - near[ok])
    if m.disparity_step_px > 0:
        # Disparity in sub-pixel steps: d / step = fB / (z step), rounded, back to depth.
        k = np.float32(fx_px * D455_BASELINE_M / m.disparity_step_px)
        np.maximum(out, np.float32(1e-3), out=out)
        np.divide(k, out, out=out)
        np.rint(out, out=out)
        np.maximum(out, np.float32(1.0), out=out)
        np.divide(k, out, out=out)
    if m.quantum_m > 0:
        q = np.float32(m.quantum_m)
        np.divide(out, q, out=out)
        np.rint(out, out=out)
        out *= q
    invalid = ~finite | (out < m.effective_min_m(W)) | (out > m.max_m)
    invalid[ev[drop_edge], eu[drop_edge]] = True
    # Random draws only for the pixels an effect can touch (a whole-image draw costs ~3 ms).
    if m.far_dropout > 0:
        start = m.far_start * m.max_m
        fv, fu = np.nonzero(finite & (zf > start))
        p_far = np.minimum((zf[fv, fu] - start) / max(m.max_m - start, 1e-6), 1.0) * m.far_dropout
        hit = rng.random(len(fv)) < p_far
        invalid[fv[hit], fu[hit]] = True
    if m.dark_holes > 0 and albedo is not None:
        dv, du = np.nonzero(albedo < m.dark_albedo)
        p_dark = (1.0 - albedo[dv, du] / max(m.dark_albedo, 1e-6)) * m.dark_holes
        hit = rng.random(len(dv)) < p_dark
        invalid[dv[hit], du[hit]] = True
    if m.shiny_holes > 0 and shiny_head_on is not None:
        sv, su = np.nonzero(shiny_head_on)
        hit = rng.random(len(sv)) < m.shiny_holes
        invalid[sv[hit], su[hit]] = True
    out[invalid] = 0.0
    return out


#: Cosine of the angle between a shiny surface's normal and the viewing ray beyond which the
#: projector's glare blinds the stereo pair (about 18 degrees).
SHINY_COS = 0.95


@dataclass(frozen=True)
class ColorModel:
    """The colour camera's auto-exposure and motion blur."""

    auto_exposure: bool = True
    #: Mean brightness (0..1) auto-exposure aims for, how strongly it follows (0..1), and the
    #: gain limits.
    exposure_target: float = 0.45
    exposure_strength: float = 0.6
    gain_range: tuple[float, float] = (0.6, 1.8)
    #: Frame-to-frame exposure flicker (log-normal sigma).
    exposure_jitter: float = 0.04
    motion_blur: bool = True
    #: Exposure time at gain 1 (indoors, seconds); it grows with the gain.
    exposure_s: float = 0.012


def exposure_gain(rgb: NDArray[np.uint8], model: ColorModel, rng: np.random.Generator) -> float:
    """The auto-exposure gain for a shaded image (1 when auto-exposure is off)."""
    if not model.auto_exposure:
        return 1.0
    mean = max(float(rgb[::4, ::4].mean()) / 255.0, 1e-3)
    g = (model.exposure_target / mean) ** model.exposure_strength
    g *= math.exp(float(rng.normal(0.0, model.exposure_jitter)))
    return float(np.clip(g, *model.gain_range))


def rotation_blur_px(R_prev: NDArray[np.float64], R_now: NDArray[np.float64], dt_s: float,
                     fx_px: float, exposure_s: float) -> tuple[float, float]:
    """Image motion (u, v) px of the image centre during one exposure, from the camera's
    rotation between two frames (optical axes: x right, y down, z forward)."""
    if dt_s <= 0:
        return 0.0, 0.0
    dR = R_prev.T @ R_now  # rotation in the previous camera frame
    angle = math.acos(float(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-9:
        return 0.0, 0.0
    axis = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
    axis /= max(float(np.linalg.norm(axis)), 1e-12)
    w = axis * angle / dt_s  # rad/s in the camera frame
    # A point on the optical axis moves by -w x (0, 0, 1) = (-w_y, w_x, 0) per second.
    return float(-w[1] * fx_px * exposure_s), float(w[0] * fx_px * exposure_s)


def apply_color(rgb: NDArray[np.uint8], gain: float, blur_px: tuple[float, float]) -> NDArray[np.uint8]:
    """(H, W, 3) uint8: exposure ``gain`` (highlights clip) and a linear motion blur of
    ``blur_px`` (u, v) pixels."""
    import cv2

    out = rgb
    length = math.hypot(*blur_px)
    if length >= 1.5:
        n = int(math.ceil(length)) | 1
        k = np.zeros((n, n), dtype=np.float32)
        c = n // 2
        for t in np.linspace(-0.5, 0.5, 2 * n):
            k[int(round(c + t * blur_px[1])), int(round(c + t * blur_px[0]))] = 1.0
        out = np.asarray(cv2.filter2D(out, -1, k / k.sum(), borderType=cv2.BORDER_REFLECT), dtype=np.uint8)
    if abs(gain - 1.0) > 1e-3:
        out = np.asarray(cv2.convertScaleAbs(out, alpha=gain), dtype=np.uint8)
    return np.asarray(out, dtype=np.uint8)
