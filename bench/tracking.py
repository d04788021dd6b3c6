"""Tracking benchmark: BoT-SORT against plain SORT, on real MOT data and simulated flights.

1. MOTChallenge 2015 TUD-Campus and TUD-Stadtmitte with their public detections
   (``../shared/data/mot``), scored with py-motmetrics (IoU >= 0.5): MOTA, IDF1, identity
   switches. BoT-SORT runs with the reference implementation's MOTChallenge settings and CMC
   off (there are no images); SORT with its published settings (max_age 1, min_hits 3, IoU 0.3).
2. Simulated flights through generated furnished rooms (oracle detector with noise, misses and
   false positives; 60 deg/s yaw turns): identity switches per 100 frames for BoT-SORT with
   and without CMC, and SORT, all fed the same detections.

Run ``python bench/tracking.py`` (``--quick``: one short flight at 320x240). The last line
printed is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# The repo root goes first: bench/ (this script's folder, on the path already) holds modules
# named like packages (bench/planner.py); our helpers are imported as bench._name.
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

if not hasattr(np, "asfarray"):  # motmetrics 1.4 still calls it; NumPy 2 removed it
    np.asfarray = lambda a, dtype=np.float64: np.asarray(a, dtype=dtype)  # type: ignore[attr-defined]

import motmetrics as mm  # noqa: E402
import pandas as pd  # noqa: E402

from bench._sort_baseline import SORT  # noqa: E402
from semmap.config import TrackerConfig  # noqa: E402
from semmap.tracking.botsort import BoTSORT  # noqa: E402
from semmap.types import CameraIntrinsics, Detection, Track  # noqa: E402

#: The MOT data beside the repository (``--mot-dir`` for a checkout elsewhere, e.g. a worktree).
MOT_DIR = REPO / ".." / "shared" / "data" / "mot"
#: Sequence -> frame rate (MOT15 seqinfo).
SEQUENCES = {"TUD-Campus": 25.0, "TUD-Stadtmitte": 25.0}
#: BoT-SORT's own defaults for MOTChallenge (tools/track.py of the reference implementation).
BOTSORT_MOT = dict(track_high_thresh=0.6, track_low_thresh=0.1, new_track_thresh=0.7,
                   track_buffer_frames=30, match_thresh=0.8, cmc_method="none")
METRICS = ["mota", "idf1", "num_switches", "num_false_positives", "num_misses", "mostly_tracked"]


# --- MOTChallenge -------------------------------------------------------------------------

def _mot_detections(mot_dir: Path, seq: str) -> dict[int, list[Detection]]:
    rows = np.loadtxt(mot_dir / seq / "det.txt", delimiter=",", ndmin=2)
    out: dict[int, list[Detection]] = {f: [] for f in range(1, int(rows[:, 0].max()) + 1)}
    for f, _id, x, y, w, h, conf, *_ in rows:
        out[int(f)].append(Detection((x, y, x + w, y + h), float(conf), "person"))
    return out


def _run_mot(mot_dir: Path, seq: str, update) -> tuple[pd.DataFrame, float]:
    dets = _mot_detections(mot_dir, seq)
    rows, t_total = [], 0.0
    for f in sorted(dets):
        t0 = time.perf_counter()
        tracks: list[Track] = update(dets[f])
        t_total += time.perf_counter() - t0
        for t in tracks:
            u0, v0, u1, v1 = t.xyxy_px
            rows.append((f, t.track_id, u0, v0, u1 - u0, v1 - v0, 1.0, -1, -1, -1))
    cols = ["FrameId", "Id", "X", "Y", "Width", "Height", "Confidence", "ClassId", "Visibility", "unused"]
    df = pd.DataFrame(rows, columns=cols).set_index(["FrameId", "Id"])
    return df, 1e3 * t_total / max(len(dets), 1)


def bench_mot(mot_dir: Path = MOT_DIR) -> dict[str, dict[str, dict[str, float]]]:
    """MOTA/IDF1/switches of BoT-SORT and SORT on both TUD sequences."""
    mh = mm.metrics.create()
    results: dict[str, dict[str, dict[str, float]]] = {}
    print("== MOTChallenge 2015 public detections (py-motmetrics, IoU >= 0.5) ==")
    print(f"{'sequence':<16}{'tracker':<19}{'MOTA':>8}{'IDF1':>8}{'IDsw':>6}{'FP':>6}{'FN':>6}{'MT':>5}{'ms/frame':>10}")
    for seq, fps in SEQUENCES.items():
        gt = mm.io.loadtxt(str(mot_dir / seq / "gt.txt"), fmt="mot15-2D", min_confidence=1)
        trackers = {
            "botsort": BoTSORT.from_config(TrackerConfig(**BOTSORT_MOT, frame_rate_hz=fps)).update,
            "sort": SORT(max_age=1, min_hits=3, iou_threshold=0.3).update,
            # For information: the drone's defaults (tuned for furniture and our detector's
            # scores), CMC off. Not the MOTChallenge setting; not part of the comparison.
            "botsort_drone_cfg": BoTSORT.from_config(
                TrackerConfig(cmc_method="none", frame_rate_hz=fps)).update,
        }
        results[seq] = {}
        for name, update in trackers.items():
            res, ms = _run_mot(mot_dir, seq, update)
            acc = mm.utils.compare_to_groundtruth(gt, res, "iou", distth=0.5)
            s = mh.compute(acc, metrics=METRICS, name=name).iloc[0]
            r = {
                "mota": round(float(s["mota"]), 4), "idf1": round(float(s["idf1"]), 4),
                "id_switches": int(s["num_switches"]), "false_positives": int(s["num_false_positives"]),
                "misses": int(s["num_misses"]), "mostly_tracked": int(s["mostly_tracked"]),
                "update_ms_mean": round(ms, 3),
            }
            results[seq][name] = r
            print(f"{seq:<16}{name:<19}{r['mota']:>8.3f}{r['idf1']:>8.3f}{r['id_switches']:>6}"
                  f"{r['false_positives']:>6}{r['misses']:>6}{r['mostly_tracked']:>5}{ms:>10.3f}")
        b, s_ = results[seq]["botsort"], results[seq]["sort"]
        results[seq]["botsort_ge_sort"] = {"mota": b["mota"] >= s_["mota"], "idf1": b["idf1"] >= s_["idf1"]}  # type: ignore[dict-item]
    print("(botsort: BoT-SORT's MOTChallenge settings, CMC off (no images); sort: max_age 1,\n"
          " min_hits 3, IoU 0.3; botsort_drone_cfg: config/default.yaml's tracker, for information.)")
    return results


# --- simulated flights --------------------------------------------------------------------

def bench_sim(quick: bool, layout: str = "realistic") -> dict[str, object]:
    """Identity switches per 100 frames on simulated flights with 60 deg/s yaw turns, in rooms
    laid out ``layout``."""
    from bench._sim_flight import fly, scripted_flight
    from companion.config import CompanionConfig
    from companion.sim.world import generate_room

    cfg = CompanionConfig()
    names = [c.name for c in cfg.classes]
    rooms = [0] if quick else [0, 1, 2]
    duration_s = 20.0 if quick else 40.0
    intr = CameraIntrinsics(191.5, 191.5, 160.0, 120.0, 320, 240) if quick else cfg.camera.intrinsics()
    gap = int(cfg.tracker.frame_rate_hz / 30.0 * cfg.tracker.track_buffer_frames)
    no_cmc = cfg.tracker.model_copy(update={"cmc_method": "none"})
    # BoT-SORT as published: similarity CMC and its 0.8 first-stage gate.
    reference = cfg.tracker.model_copy(update={"cmc_model": "affine", "match_thresh": 0.8})
    totals: dict[str, dict[str, float]] = {}
    times: dict[str, list[float]] = {}
    print(f"\n== Simulated flights, {layout} rooms: {len(rooms)} room(s) x {duration_s:.0f} s at {cfg.camera.rate_hz:.0f} Hz, "
          f"{intr.width_px}x{intr.height_px}, 60 deg/s yaw turns, oracle detector ==")
    for seed in rooms:
        room = generate_room(seed, width_m=cfg.sim.room_width_m, depth_m=cfg.sim.room_depth_m,
                             n_objects=cfg.sim.n_objects, class_names=names, layout=layout)
        poses = scripted_flight(room, duration_s, rate_hz=cfg.camera.rate_hz, yaw_rate_dps=60.0, seed=seed)
        sort = SORT()
        trackers = {
            "botsort": BoTSORT.from_config(cfg.tracker).update,
            "botsort_reference": BoTSORT.from_config(reference).update,
            "botsort_no_cmc": BoTSORT.from_config(no_cmc).update,
            "sort": lambda d, _img, s=sort: s.update(d),
        }
        out = fly(room, cfg, poses, trackers, intrinsics=intr, seed=seed, gap_frames=gap)
        for name, (c, ts) in out.items():
            t = totals.setdefault(name, {"frames": 0, "switches": 0, "reentries": 0, "matched": 0, "gt_boxes": 0})
            t["frames"] += c.frames
            t["switches"] += c.continuous
            t["reentries"] += c.reentry
            t["matched"] += c.matched
            t["gt_boxes"] += c.gt_boxes
            times.setdefault(name, []).extend(ts)
            print(f"  room {seed}: {name:<18} switches {c.continuous:>3}  re-entries {c.reentry:>3}  "
                  f"coverage {c.matched / max(c.gt_boxes, 1):.3f}")
    print(f"{'tracker':<19}{'frames':>7}{'IDsw':>6}{'IDsw/100f':>11}{'re-entry':>10}{'coverage':>10}{'update ms':>11}")
    result: dict[str, object] = {"world": layout, "rooms": len(rooms), "duration_s_per_room": duration_s,
                                 "image_px": [intr.width_px, intr.height_px], "yaw_rate_dps": 60.0}
    for name, t in totals.items():
        per100 = 100.0 * t["switches"] / max(t["frames"], 1)
        cov = t["matched"] / max(t["gt_boxes"], 1)
        ms = 1e3 * float(np.mean(times[name]))
        print(f"{name:<19}{int(t['frames']):>7}{int(t['switches']):>6}{per100:>11.2f}{int(t['reentries']):>10}{cov:>10.3f}{ms:>11.2f}")
        result[name] = {"frames": int(t["frames"]), "id_switches": int(t["switches"]),
                        "id_switches_per_100_frames": round(per100, 3), "reentries": int(t["reentries"]),
                        "coverage": round(cov, 4), "update_ms_mean": round(ms, 3)}
    print("(botsort: our defaults, homography CMC, match_thresh 0.9; botsort_reference: BoT-SORT's\n"
          " similarity CMC and 0.8. IDsw: an object's track id changed while it stayed in view, gaps\n"
          " <= the lost buffer; re-entry: new id after it was out of view longer than the buffer;\n"
          " coverage: fraction of visible objects matched by a reported track at IoU >= 0.5.\n"
          " BoT-SORT update times include CMC. Target: botsort IDsw/100f <= 1.)")
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one short low-resolution flight")
    ap.add_argument("--skip-sim", action="store_true", help="MOTChallenge only")
    ap.add_argument("--mot-dir", default=str(MOT_DIR), help="MOT15 sequences folder (default ../shared/data/mot)")
    ap.add_argument("--world", choices=("realistic", "scattered"), default="realistic",
                    help="simulated flights' room layout")
    ap.add_argument("--no-scattered", action="store_true",
                    help="with --world realistic: skip flying the same rooms scattered")
    args = ap.parse_args()
    mot_dir = Path(args.mot_dir)
    if not mot_dir.is_dir():
        sys.exit(f"MOT data not found at {mot_dir.resolve()}")
    out: dict[str, object] = {"world": args.world, "mot": bench_mot(mot_dir)}
    if not args.skip_sim:
        out["sim"] = bench_sim(args.quick, args.world)
        if args.world == "realistic" and not args.no_scattered:
            out["sim_scattered"] = bench_sim(args.quick, "scattered")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
