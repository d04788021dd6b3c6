"""Mapping on real RGB-D frames against furniture truth measured from the data.

Run: ``python bench/real.py`` (every real set with poses and truth) or ``--quick`` (the dining
room only); ``--data DIR`` for another copy of ``../shared/data``.

Each set of ``../shared/data/rgbd`` is mapped by the offline pipeline (:func:`build_offline_map`,
what ``companion map`` runs) with the default configuration: the COCO detector shipped with
the package (``builtin:coco``, a YOLOX-nano run through our own ONNX runtime), tracking, object
geometry, the object map. Sets that are not in the recorder's folder layout are staged in a
temporary folder first (colour, 16-bit millimetre depth, ``pose.txt``, ``intrinsics.json``).
TUM fr1 desk has no poses; its one RGB-D view with depth is mapped from an identity pose
(the floor is found from the points as for every set).

The truth (``tests/data/real_furniture_truth.json``, method in the file) lists each set's
furniture in the recording's world frame: centre and, where measured, footprint rectangle on
the floor, and the height above the floor. Mapped objects (confirmed ones, as the costmap gets
them) are brought into that frame with the map's ``T_map_world`` and matched one to one to the
truth by centre distance (Hungarian; gate ``MATCH_GATE_M`` plus half the truth's short side).
Per truth object: ``found``, ``class_ok`` (a table as any of our three table classes, a chair
as chair, the armchair as chair or sofa), ``height_error_m`` (mapped top minus truth),
``footprint_side_errors_m`` (long and short side of the least-perimeter rectangle, where the
truth has a rectangle), ``footprint_area_m2`` and ``centre_error_m``. ``spurious``: confirmed
objects matching no truth object (optional truth objects, such as a sofa hidden behind the
chairs, are neither required nor spurious when mapped).

The last line printed is one JSON object: per set, its figures and per-object results.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.config import load_config  # noqa: E402
from companion.offline_map import OfflineMapOptions, build_offline_map  # noqa: E402
from semmap.objects import MappedObject  # noqa: E402
from semmap.polygons import min_perimeter_rectangle, polygon_area_m2  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TRUTH = REPO / "tests" / "data" / "real_furniture_truth.json"
DATA = REPO / ".." / "shared" / "data"
#: A mapped object matches a truth object within this distance plus half the truth's short side.
MATCH_GATE_M = 0.5
#: Our classes a truth class may be mapped as.
ACCEPTED = {"table": {"desk", "coffee_table", "conference_table"}, "chair": {"chair"},
            "armchair": {"chair", "sofa"}, "sofa": {"sofa"}}
#: Sets in the order they run; ``--quick`` runs the first.
SETS = ("diningroom", "iclnuim_livingroom", "tum_fr1_desk")


@dataclass(frozen=True)
class TruthObject:
    name: str
    cls: str
    required: bool
    centre_xy_m: NDArray[np.float64]  # map frame of the run
    height_m: float | None
    sides_m: tuple[float, float] | None
    gate_m: float


def stage_set(name: str, data_dir: Path, tmp: Path) -> Path:
    """The set's folder in the recorder's folder layout (the set itself when it is in it)."""
    src = data_dir / "rgbd" / name
    if not src.is_dir():
        raise FileNotFoundError(f"real set {name} not found at {src} (give --data ../shared/data)")
    if (src / "color").is_dir():
        return src
    doc = json.loads((src / "frames.json").read_text(encoding="utf-8"))
    out = tmp / name
    (out / "color").mkdir(parents=True)
    (out / "depth").mkdir()
    lines = []
    for i, f in enumerate(x for x in doc["frames"] if "depth" in x):
        T = np.asarray(f.get("T_world_from_cam", np.eye(4)), np.float64)
        if np.linalg.det(T[:3, :3]) < 0:
            T = np.diag([1.0, -1.0, 1.0, 1.0]) @ T  # a mirrored world (ICL's y-up camera): mirror it back
        q = Rotation.from_matrix(T[:3, :3]).as_quat()  # (x, y, z, w)
        lines.append(" ".join(f"{v:.9f}" for v in [*T[:3, 3], *q]))
        (out / "color" / f"{i}.png").write_bytes((src / f["color"]).read_bytes())
        (out / "depth" / f"{i}.png").write_bytes((src / f["depth"]).read_bytes())
        if "T_world_from_cam" not in f:
            break  # no poses: one view, from the identity
    (out / "pose.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    intr = json.loads((src / "intrinsics.json").read_text(encoding="utf-8"))
    intr.update(width=intr.get("width", 640), height=intr.get("height", 480), depth_scale=1000.0)
    (out / "intrinsics.json").write_text(json.dumps(intr), encoding="utf-8")
    return out


def load_truth(set_doc: dict[str, Any], T_map_world: NDArray[np.float64]) -> list[TruthObject]:
    """The set's truth objects with their centres in the run's map frame."""
    out = []
    for o in set_doc["objects"]:
        c = T_map_world @ np.array([*o["centre_world_m"], 1.0])
        sides = tuple(o["sides_m"]) if "sides_m" in o else None
        short = min(sides) if sides else 0.0
        gate = o.get("radius_m", MATCH_GATE_M + 0.5 * short)
        out.append(TruthObject(o["name"], o["class"], bool(o["required"]), c[:2].copy(), o.get("height_m"),
                               sides, float(gate)))  # type: ignore[arg-type]
    return out


def rect_sides(poly: NDArray[np.float64]) -> tuple[float, float]:
    r = min_perimeter_rectangle(np.asarray(poly, np.float64))
    a, b = float(np.hypot(*(r[1] - r[0]))), float(np.hypot(*(r[3] - r[0])))
    return max(a, b), min(a, b)


def score(truth: list[TruthObject], mapped: list[MappedObject]) -> dict[str, Any]:
    """Per-object results and the set's figures (see the module doc)."""
    centres = [min_perimeter_rectangle(o.footprint_xy_m).mean(axis=0) for o in mapped]
    cost = np.full((len(truth), len(mapped)), 1e6)
    for i, t in enumerate(truth):
        for j, c in enumerate(centres):
            d = float(np.linalg.norm(c - t.centre_xy_m))
            if d <= t.gate_m:
                cost[i, j] = d
    pairs: dict[int, int] = {}
    if truth and mapped:
        rows, cols = linear_sum_assignment(cost)
        pairs = {int(r): int(c) for r, c in zip(rows, cols, strict=True) if cost[r, c] < 1e6}
    objects: dict[str, Any] = {}
    for i, t in enumerate(truth):
        j = pairs.get(i)
        if j is None:
            objects[t.name] = {"class": t.cls, "required": t.required, "found": False}
            continue
        o = mapped[j]
        long_m, short_m = rect_sides(o.footprint_xy_m)
        r: dict[str, Any] = {
            "class": t.cls, "required": t.required, "found": True, "mapped_class": o.class_name,
            "class_ok": o.class_name in ACCEPTED[t.cls], "object_id": o.object_id,
            "height_m": round(o.z_max_m, 3),
            "height_error_m": None if t.height_m is None else round(o.z_max_m - t.height_m, 3),
            "footprint_sides_m": [round(long_m, 3), round(short_m, 3)],
            "footprint_area_m2": round(polygon_area_m2(o.footprint_xy_m), 3),
            "centre_error_m": round(float(np.linalg.norm(centres[j] - t.centre_xy_m)), 3),
        }
        if t.sides_m is not None:
            r["footprint_side_errors_m"] = [round(long_m - max(t.sides_m), 3), round(short_m - min(t.sides_m), 3)]
        objects[t.name] = r
    matched = set(pairs.values())
    spurious = [{"object_id": o.object_id, "class": o.class_name, "height_m": round(o.z_max_m, 3),
                 "centre_xy_m": [round(float(v), 2) for v in centres[j]]}
                for j, o in enumerate(mapped) if j not in matched]
    req = [t for t in truth if t.required]
    found_ok = [t for t in req if objects[t.name]["found"] and objects[t.name]["class_ok"]]
    herr = [abs(objects[t.name]["height_error_m"]) for t in req
            if objects[t.name]["found"] and objects[t.name].get("height_error_m") is not None]
    return {
        "required": len(req), "found": sum(objects[t.name]["found"] for t in req),
        "found_class_ok": len(found_ok), "spurious": len(spurious),
        "height_error_max_m": round(max(herr), 3) if herr else None,
        "mapped_objects": len(mapped), "objects": objects, "spurious_objects": spurious,
    }


def dining_targets(fig: dict[str, Any]) -> dict[str, bool]:
    """The issue's dining-room targets, each True when met."""
    objs = fig["objects"]
    table = objs["dining_table"]
    chairs = [v for k, v in objs.items() if k.startswith("chair_")]
    good_chairs = [c for c in chairs if c["found"] and c["class_ok"] and 0.85 <= c["height_m"] <= 1.15
                   and c["footprint_area_m2"] < 0.5]
    table_ok = bool(table["found"] and table["class_ok"] and 0.70 <= table["height_m"] <= 0.85
                    and all(abs(e) <= 0.25 for e in table["footprint_side_errors_m"]))
    tall = [v for k, v in objs.items() if k != "armchair" and v.get("found") and v["height_m"] > 1.4]
    tall += [s for s in fig["spurious_objects"] if s["height_m"] > 1.4]
    return {"table_one_object": table_ok, "chairs_5_of_6": len(good_chairs) >= 5,
            "nothing_taller_than_1_4_m": not tall, "no_spurious": fig["spurious"] == 0}


def run_set(name: str, data_dir: Path, truth_doc: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    cfg = load_config(None)
    with tempfile.TemporaryDirectory(prefix=f"real-{name}-") as tmp:
        folder = stage_set(name, data_dir, Path(tmp))
        t0 = time.perf_counter()
        res = build_offline_map(folder, Path(tmp) / "out", cfg, OfflineMapOptions())
        elapsed = time.perf_counter() - t0
    mapped = res.object_map.objects(confirmed_only=True)
    truth = load_truth(truth_doc["sets"][name], res.T_map_world)
    fig = score(truth, mapped)
    fig["frames"] = res.frames_used
    fig["map_time_s"] = round(elapsed, 2)
    if name == "diningroom":
        fig["targets"] = dining_targets(fig)
    lines = [f"== {name}: {res.frames_used} frames, {len(mapped)} confirmed objects, "
             f"{fig['found']}/{fig['required']} required found ({fig['found_class_ok']} right class), "
             f"{fig['spurious']} spurious, {elapsed:.1f} s",
             f"  {'truth':<14} {'class':<9} {'found':<5} {'mapped as':<17} {'height':>7} {'err':>7} "
             f"{'sides (m)':>12} {'side err':>13} {'area':>6} {'centre':>7}"]
    for k, v in fig["objects"].items():
        if not v["found"]:
            lines.append(f"  {k:<14} {v['class']:<9} {'no':<5}")
            continue
        se = v.get("footprint_side_errors_m")
        he = v["height_error_m"]
        lines.append(
            f"  {k:<14} {v['class']:<9} {'yes':<5} {v['mapped_class']:<17} {v['height_m']:>7.2f} "
            f"{'' if he is None else f'{he:+.2f}':>7} {v['footprint_sides_m'][0]:>5.2f}x{v['footprint_sides_m'][1]:<5.2f}"
            f" {'' if se is None else f'{se[0]:+.2f},{se[1]:+.2f}':>13} {v['footprint_area_m2']:>6.2f}"
            f" {v['centre_error_m']:>7.2f}")
    for s in fig["spurious_objects"]:
        lines.append(f"  spurious #{s['object_id']} {s['class']} height {s['height_m']:.2f} m at {s['centre_xy_m']}")
    if "targets" in fig:
        lines.append("  targets: " + ", ".join(f"{k} {'MET' if ok else 'missed'}" for k, ok in fig["targets"].items()))
    return lines, fig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the dining room only (under a minute)")
    ap.add_argument("--data", default=str(DATA), help="the real data folder (default ../shared/data)")
    ap.add_argument("--sets", nargs="*", default=None, help=f"sets to run (default: {' '.join(SETS)})")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    truth_doc = json.loads(TRUTH.read_text(encoding="utf-8"))
    names = args.sets or (SETS[:1] if args.quick else [s for s in SETS if s in truth_doc["sets"]])
    out: dict[str, Any] = {}
    for name in names:
        lines, fig = run_set(name, Path(args.data), truth_doc)
        print("\n".join(lines), flush=True)
        out[name] = fig
    print(json.dumps(out, separators=(",", ":"), default=lambda x: bool(x) if isinstance(x, np.bool_) else str(x)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
