"""BoT-SORT multi-object tracker (Aharon et al., 2022), as in its reference implementation.

Per frame (:meth:`BoTSORT.update`):

1. Detections split by score: high (``>= track_high_thresh``) and low
   (``track_low_thresh < score < track_high_thresh``); lower ones are dropped.
2. Confirmed and lost tracks are predicted one frame by the Kalman filter
   (:mod:`semmap.tracking.kalman`); lost tracks with their size velocity zeroed.
3. Camera-motion compensation (:mod:`semmap.tracking.cmc`) warps every track's state by the
   frame-to-frame image motion (BoT-SORT's affine, or a homography applied through its local
   affine at each track), so a yawing drone does not tear its tracks apart.
4. First association: confirmed + lost tracks against high-score detections. Cost is
   ``1 - IoU``, fused with the detection score, optionally min-fused with an appearance cost
   (cosine distance / 2 of embeddings, accepted only below ``appearance_thresh`` and for
   pairs with ``1 - IoU <= proximity_thresh``). Hungarian assignment, ``match_thresh``.
5. Second association: confirmed tracks still unmatched against the low-score detections,
   plain IoU, threshold 0.5. This keeps tracks alive through partial occlusion, when the
   detector's confidence drops. Tracks unmatched after it become lost.
6. Unconfirmed (one-frame-old) tracks against the remaining high detections, threshold 0.7;
   unmatched unconfirmed tracks are removed.
7. Remaining high detections with ``score >= new_track_thresh`` start new tracks.
8. Lost tracks older than the buffer are removed; a confirmed and a lost track that overlap
   almost entirely (1 - IoU < 0.15) are duplicates and the younger one goes.

Tracks never change class: pairs of different classes are forbidden in every stage.
Output: confirmed tracks updated in this frame, as :class:`semmap.types.Track`, box from the
filtered state.
"""

from __future__ import annotations

import enum
import itertools
import logging
from collections.abc import Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from semmap.config import TrackerConfig
from semmap.errors import FrameError
from semmap.tracking import kalman
from semmap.tracking.cmc import IDENTITY, SparseFlowCMC
from semmap.tracking.matching import FORBIDDEN, fuse_score, iou_matrix, linear_assignment
from semmap.types import Detection, Track

log = logging.getLogger(__name__)

#: Reference-implementation thresholds of the second and unconfirmed stages, and duplicates.
SECOND_MATCH_THRESH = 0.5
UNCONFIRMED_MATCH_THRESH = 0.7
DUPLICATE_IOU_DIST = 0.15
#: Exponential smoothing of a track's appearance embedding.
FEATURE_ALPHA = 0.9
#: Detections narrower or shorter than this (pixels) are ignored; predicted boxes never
#: shrink below it.
MIN_BOX_PX = 1.0


class AppearanceEncoder(Protocol):
    """Optional re-identification hook: one embedding per box."""

    def __call__(
        self, image_rgb: NDArray[np.uint8], boxes_xyxy_px: NDArray[np.float64]
    ) -> NDArray[np.float32]:
        """(N, 4) boxes in ``image_rgb`` ((H, W, 3) uint8) -> (N, D) embeddings."""
        ...


class TrackState(enum.Enum):
    NEW = 0
    TRACKED = 1
    LOST = 2
    REMOVED = 3


class _STrack:
    """Internal track: Kalman state plus lifecycle bookkeeping."""

    __slots__ = ("track_id", "mean", "cov", "score", "class_name", "state", "is_activated",
                 "frame_id", "start_frame", "tracklet_len", "feature")

    def __init__(self, mean: NDArray[np.float64], cov: NDArray[np.float64], score: float,
                 class_name: str, frame_id: int, track_id: int, activated: bool,
                 feature: NDArray[np.float32] | None) -> None:
        self.track_id = track_id
        self.mean = mean
        self.cov = cov
        self.score = score
        self.class_name = class_name
        self.state = TrackState.TRACKED
        self.is_activated = activated
        self.frame_id = frame_id
        self.start_frame = frame_id
        self.tracklet_len = 0
        self.feature = feature

    @property
    def xyxy(self) -> NDArray[np.float64]:
        x, y, w, h = self.mean[:4]
        return np.array([x - w / 2.0, y - h / 2.0, x + w / 2.0, y + h / 2.0])

    def to_track(self, frame_id: int) -> Track:
        # Plain floats straight from the state: this runs for every track every frame.
        x, y, w, h = self.mean[:4].tolist()
        hw, hh = w / 2.0, h / 2.0
        return Track(self.track_id, (x - hw, y - hh, x + hw, y + hh), float(self.score),
                     self.class_name, frame_id - self.start_frame)


#: (track, measured xyxy box, score, embedding or None): applied in one batch after the three
#: matching stages, which only read the predicted states.
_Update = tuple[_STrack, NDArray[np.float64], float, NDArray[np.float32] | None]


def _track_boxes(tracks: Sequence[_STrack]) -> NDArray[np.float64]:
    """(M, 4) xyxy boxes of the tracks' current states."""
    if not tracks:
        return np.zeros((0, 4))
    xywh = np.array([t.mean[:4] for t in tracks])
    half = xywh[:, 2:4] * 0.5
    return np.concatenate([xywh[:, 0:2] - half, xywh[:, 0:2] + half], axis=1)


def _xyxy_to_xywh(b: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 4) xyxy -> (N, 4) centre x, centre y, width, height."""
    out = np.empty_like(b)
    out[:, 0:2] = (b[:, 0:2] + b[:, 2:4]) * 0.5
    out[:, 2:4] = b[:, 2:4] - b[:, 0:2]
    return out


class _Dets:
    """A subset of the frame's detections as arrays."""

    def __init__(self, boxes: NDArray[np.float64], scores: NDArray[np.float64],
                 classes: list[str], feats: NDArray[np.float32] | None) -> None:
        self.boxes = boxes  # (N, 4) xyxy
        self.scores = scores  # (N,)
        self.classes = classes
        self.feats = feats  # (N, D) unit vectors or None

    def __len__(self) -> int:
        return len(self.classes)

    def take(self, idx: NDArray[np.int64] | Sequence[int]) -> _Dets:
        ix = np.asarray(idx, dtype=np.int64)
        return _Dets(self.boxes[ix], self.scores[ix], [self.classes[i] for i in ix.tolist()],
                     None if self.feats is None else self.feats[ix])


def _class_gate(tracks: Sequence[_STrack], dets: _Dets, cost: NDArray[np.float64]) -> NDArray[np.float64]:
    """Forbid track-detection pairs of different classes."""
    if cost.size == 0:
        return cost
    t_cls = np.array([t.class_name for t in tracks], dtype=object)
    d_cls = np.array(dets.classes, dtype=object)
    return np.where(t_cls[:, None] == d_cls[None, :], cost, FORBIDDEN)


class BoTSORT:
    """The tracker. Feed it every frame's detections in order; it returns confirmed tracks."""

    def __init__(
        self,
        *,
        track_high_thresh: float = 0.5,
        track_low_thresh: float = 0.1,
        new_track_thresh: float = 0.6,
        track_buffer_frames: int = 30,
        match_thresh: float = 0.8,
        proximity_thresh: float = 0.5,
        appearance_thresh: float = 0.25,
        fuse_score: bool = True,
        frame_rate_hz: float = 30.0,
        cmc: SparseFlowCMC | None = None,
        appearance: AppearanceEncoder | None = None,
    ) -> None:
        """Thresholds as in :class:`semmap.config.TrackerConfig`. ``cmc``: camera-motion
        estimator (None = no compensation). ``appearance``: optional embedding hook."""
        self.track_high_thresh = track_high_thresh
        self.track_low_thresh = track_low_thresh
        self.new_track_thresh = new_track_thresh
        self.match_thresh = match_thresh
        self.proximity_thresh = proximity_thresh
        self.appearance_thresh = appearance_thresh
        self.fuse_score = fuse_score
        #: Frames a lost track survives (BoT-SORT's buffer, given at 30 Hz).
        self.max_time_lost = max(1, int(frame_rate_hz / 30.0 * track_buffer_frames))
        self.cmc = cmc
        self.appearance = appearance
        self.frame_id = 0
        self._ids = itertools.count(1)
        self._tracked: list[_STrack] = []
        self._lost: list[_STrack] = []
        #: The camera motion used in the last update, (3, 3).
        self.last_warp = IDENTITY.copy()

    @classmethod
    def from_config(cls, cfg: TrackerConfig, appearance: AppearanceEncoder | None = None) -> BoTSORT:
        """Build from :class:`TrackerConfig` (CMC per ``cmc_method``)."""
        cmc = None
        if cfg.cmc_method == "sparse_optflow":
            cmc = SparseFlowCMC(downscale=cfg.cmc_downscale, model=cfg.cmc_model)
        return cls(
            track_high_thresh=cfg.track_high_thresh,
            track_low_thresh=cfg.track_low_thresh,
            new_track_thresh=cfg.new_track_thresh,
            track_buffer_frames=cfg.track_buffer_frames,
            match_thresh=cfg.match_thresh,
            proximity_thresh=cfg.proximity_thresh,
            appearance_thresh=cfg.appearance_thresh,
            fuse_score=cfg.fuse_score,
            frame_rate_hz=cfg.frame_rate_hz,
            cmc=cmc,
            appearance=appearance,
        )

    @property
    def active_count(self) -> int:
        """Confirmed tracks currently tracked (not lost)."""
        return sum(1 for t in self._tracked if t.is_activated)

    @property
    def lost_count(self) -> int:
        return len(self._lost)

    def reset(self) -> None:
        """Drop all tracks (ids keep increasing, so old ids are never reused)."""
        self._tracked, self._lost = [], []
        self.frame_id = 0
        if self.cmc is not None:
            self.cmc.reset()

    # --- costs -------------------------------------------------------------------------

    def _cost(self, tracks: Sequence[_STrack], dets: _Dets, use_appearance: bool) -> NDArray[np.float64]:
        iou_d = 1.0 - iou_matrix(_track_boxes(tracks), dets.boxes)
        far = iou_d > self.proximity_thresh
        cost = fuse_score(iou_d, dets.scores) if self.fuse_score else iou_d
        if use_appearance and dets.feats is not None and len(tracks) and len(dets):
            t_feat = [t.feature for t in tracks]
            if all(f is not None for f in t_feat):
                tf = np.stack(t_feat)  # type: ignore[arg-type]
                emb = np.clip(1.0 - tf @ dets.feats.T, 0.0, 2.0) / 2.0
                emb[emb > self.appearance_thresh] = 1.0
                emb[far] = 1.0
                cost = np.minimum(cost, emb)
        return _class_gate(tracks, dets, cost)

    # --- the update --------------------------------------------------------------------

    def update(
        self,
        detections: Sequence[Detection],
        image_rgb: NDArray[np.uint8] | None = None,
        warp: NDArray[np.float64] | None = None,
    ) -> list[Track]:
        """Advance one frame. Returns the confirmed tracks matched in this frame.

        ``detections``: this frame's detections (original-image pixels). ``image_rgb``:
        (H, W, 3) uint8, needed when CMC or the appearance hook is on. ``warp``: a known
        previous->current image motion, (3, 3) or a (2, 3) affine, used instead of estimating
        one.
        """
        self.frame_id += 1
        fid = self.frame_id
        all_dets = self._frame_detections(detections, image_rgb)
        scores = all_dets.scores
        high = all_dets.take(np.flatnonzero(scores >= self.track_high_thresh))
        low = all_dets.take(np.flatnonzero((scores > self.track_low_thresh) & (scores < self.track_high_thresh)))

        unconfirmed = [t for t in self._tracked if not t.is_activated]
        confirmed = [t for t in self._tracked if t.is_activated]
        pool = confirmed + self._lost

        self._predict(pool)
        self.last_warp = self._camera_motion(image_rgb, all_dets.boxes, warp)
        if not np.array_equal(self.last_warp, IDENTITY):
            self._warp(pool + unconfirmed, self.last_warp)

        updates, refound, r_tracked, new_dets = self._associate(pool, unconfirmed, high, low)
        self._apply_updates(updates, fid)
        new_tracks = self._start(new_dets, fid)
        self._rebuild_lists(refound, r_tracked, new_tracks, fid)
        return [t.to_track(fid) for t in self._tracked if t.is_activated and t.frame_id == fid]

    def _frame_detections(self, detections: Sequence[Detection], image_rgb: NDArray[np.uint8] | None) -> _Dets:
        """This frame's detections as arrays, degenerate boxes dropped, with their unit
        appearance embeddings when the appearance hook is on."""
        boxes = np.array([d.xyxy_px for d in detections], dtype=np.float64).reshape(-1, 4)
        # A degenerate box would give the Kalman filter a zero (singular) noise model.
        valid = np.all(np.isfinite(boxes), axis=1) & (boxes[:, 2] - boxes[:, 0] >= MIN_BOX_PX) & (
            boxes[:, 3] - boxes[:, 1] >= MIN_BOX_PX)
        if not valid.all():
            log.debug("tracker: ignoring %d degenerate detection box(es)", int((~valid).sum()))
            detections = [d for d, ok in zip(detections, valid, strict=True) if ok]
            boxes = boxes[valid]
        scores = np.array([d.score for d in detections], dtype=np.float64)
        classes = [d.class_name for d in detections]
        feats = None
        if self.appearance is not None:
            if image_rgb is None:
                raise FrameError("tracker has an appearance encoder but update() got no image")
            f = np.asarray(self.appearance(image_rgb, boxes), dtype=np.float32).reshape(len(boxes), -1)
            feats = f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
        return _Dets(boxes, scores, classes, feats)

    def _camera_motion(self, image_rgb: NDArray[np.uint8] | None, boxes: NDArray[np.float64],
                       warp: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """The previous->current image motion as (3, 3): the given ``warp``, else CMC's
        estimate, else the identity."""
        if warp is None:
            if self.cmc is not None:
                if image_rgb is None:
                    raise FrameError("tracker has camera-motion compensation on but update() got no image")
                warp = self.cmc.apply(image_rgb, boxes)
            else:
                warp = IDENTITY
        warp = np.asarray(warp, dtype=np.float64)
        return np.vstack([warp, [0.0, 0.0, 1.0]]) if warp.shape == (2, 3) else warp

    def _associate(
        self, pool: list[_STrack], unconfirmed: list[_STrack], high: _Dets, low: _Dets
    ) -> tuple[list[_Update], list[_STrack], list[_STrack], _Dets]:
        """BoT-SORT's three matching stages on the predicted states. Returns the updates to
        apply in one batch, the lost tracks found again, the tracked leftovers of stage 2
        (those unmatched now LOST) and the high detections nobody matched."""
        updates: list[_Update] = []
        refound: list[_STrack] = []

        # Stage 1: confirmed + lost vs high-score detections.
        m1, u_pool, u_high = linear_assignment(self._cost(pool, high, True), self.match_thresh)
        for ti, di in m1:
            tr = pool[ti]
            updates.append((tr, high.boxes[di], float(high.scores[di]), None if high.feats is None else high.feats[di]))
            if tr.state != TrackState.TRACKED:
                refound.append(tr)

        # Stage 2: still-tracked leftovers vs low-score detections, plain IoU.
        r_tracked = [pool[i] for i in u_pool if pool[i].state == TrackState.TRACKED]
        cost2 = _class_gate(r_tracked, low, 1.0 - iou_matrix(_track_boxes(r_tracked), low.boxes))
        m2, u_r, _ = linear_assignment(cost2, SECOND_MATCH_THRESH)
        for ti, di in m2:
            updates.append((r_tracked[ti], low.boxes[di], float(low.scores[di]), None if low.feats is None else low.feats[di]))
        for i in u_r:
            r_tracked[i].state = TrackState.LOST

        # Stage 3: unconfirmed tracks vs the high detections left over.
        rest = high.take(u_high)
        m3, u_unconf, u_new = linear_assignment(self._cost(unconfirmed, rest, True), UNCONFIRMED_MATCH_THRESH)
        for ti, di in m3:
            updates.append((unconfirmed[ti], rest.boxes[di], float(rest.scores[di]), None if rest.feats is None else rest.feats[di]))
        for i in u_unconf:
            unconfirmed[i].state = TrackState.REMOVED
        return updates, refound, r_tracked, rest.take(u_new)

    def _rebuild_lists(self, refound: list[_STrack], r_tracked: list[_STrack], new_tracks: list[_STrack],
                       fid: int) -> None:
        """Tracked and lost lists after the matching: lost tracks out of time dropped,
        duplicates between the two removed."""
        tracked = [t for t in self._tracked if t.state == TrackState.TRACKED]
        tracked_ids = {t.track_id for t in tracked}
        tracked += [t for t in refound if t.track_id not in tracked_ids]
        tracked += new_tracks
        lost = [t for t in self._lost if t.state == TrackState.LOST]
        lost += [t for t in r_tracked if t.state == TrackState.LOST]
        lost = [t for t in lost if fid - t.frame_id <= self.max_time_lost]
        self._tracked, self._lost = self._remove_duplicates(tracked, lost)

    # --- helpers -----------------------------------------------------------------------

    @staticmethod
    def _predict(tracks: Sequence[_STrack]) -> None:
        if not tracks:
            return
        means = np.array([t.mean for t in tracks])
        covs = np.array([t.cov for t in tracks])
        not_tracked = np.array([t.state != TrackState.TRACKED for t in tracks])
        means[not_tracked, 6:8] = 0.0
        means, covs = kalman.predict(means, covs)
        # A shrinking box extrapolated too far would turn inside out; the noise model scales
        # with w and h, so keep them positive.
        np.maximum(means[:, 2:4], MIN_BOX_PX, out=means[:, 2:4])
        for t, m, c in zip(tracks, means, covs, strict=True):
            t.mean, t.cov = m, c

    @staticmethod
    def _warp(tracks: Sequence[_STrack], warp: NDArray[np.float64]) -> None:
        if not tracks:
            return
        means, covs = kalman.apply_warp(
            np.array([t.mean for t in tracks]), np.array([t.cov for t in tracks]), warp
        )
        for t, m, c in zip(tracks, means, covs, strict=True):
            t.mean, t.cov = m, c

    @staticmethod
    def _apply_updates(
        updates: list[_Update], fid: int
    ) -> None:
        if not updates:
            return
        tracks = [u[0] for u in updates]
        z = _xyxy_to_xywh(np.array([u[1] for u in updates]))
        means, covs = kalman.update(np.array([t.mean for t in tracks]), np.array([t.cov for t in tracks]), z)
        for (t, _box, score, feat), m, c in zip(updates, means, covs, strict=True):
            reactivated = t.state != TrackState.TRACKED
            t.mean, t.cov = m, c
            t.score = score
            t.frame_id = fid
            t.tracklet_len = 0 if reactivated else t.tracklet_len + 1
            t.state = TrackState.TRACKED
            t.is_activated = True
            if feat is not None:
                f = feat if t.feature is None else FEATURE_ALPHA * t.feature + (1.0 - FEATURE_ALPHA) * feat
                t.feature = (f / max(float(np.linalg.norm(f)), 1e-12)).astype(np.float32)

    def _start(self, dets: _Dets, fid: int) -> list[_STrack]:
        keep = np.flatnonzero(dets.scores >= self.new_track_thresh)
        if keep.size == 0:
            return []
        means, covs = kalman.initiate(_xyxy_to_xywh(dets.boxes[keep]))
        out = []
        for j, i in enumerate(keep.tolist()):
            feat = None if dets.feats is None else dets.feats[i]
            # As in the reference, tracks born on the very first frame are confirmed at once.
            out.append(_STrack(means[j], covs[j], float(dets.scores[i]), dets.classes[i], fid,
                               next(self._ids), fid == 1, feat))
        return out

    @staticmethod
    def _remove_duplicates(
        tracked: list[_STrack], lost: list[_STrack]
    ) -> tuple[list[_STrack], list[_STrack]]:
        if not tracked or not lost:
            return tracked, lost
        d = 1.0 - iou_matrix(_track_boxes(tracked), _track_boxes(lost))
        drop_a, drop_b = set(), set()
        for p, q in zip(*np.nonzero(d < DUPLICATE_IOU_DIST), strict=True):
            age_p = tracked[p].frame_id - tracked[p].start_frame
            age_q = lost[q].frame_id - lost[q].start_frame
            if age_p > age_q:
                drop_b.add(int(q))
            else:
                drop_a.add(int(p))
        return ([t for i, t in enumerate(tracked) if i not in drop_a],
                [t for i, t in enumerate(lost) if i not in drop_b])
