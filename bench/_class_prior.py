"""``bench/mapping.py`` section ``class_prior``: table kinds told apart by geometry.

A COCO detector has one table class (``dining table``, mapped to ``desk``): the object map's
geometric class prior (``ClassConfig.prior``, :mod:`semmap.class_prior`) must make it a coffee
table or a conference table from the measured height and footprint. The rooms and the oracle
are ``bench/mapping.py``'s, with the oracle's coffee tables and conference tables reported as
desks (after its random class confusions, as a COCO model would report them), and the object
map told that a desk detection votes for all three (as ``builtin:coco``'s class map says).

Each room is mapped twice, with the default priors and with none; table-type accuracy is the
fraction of matched real tables (desk, coffee table, conference table) whose map class is
right. Conference tables are rare in the generator's mix, so the same seeds are also
furnished table-heavy (:data:`TABLE_HEAVY`) and mapped with the priors: more of every kind.
"""

from __future__ import annotations

import argparse
from typing import Any

from semmap.config import default_classes

TABLES = ("coffee_table", "conference_table", "desk")
#: What a COCO detector reports for our table classes (its one table class, mapped to desk).
COCO_MERGE = (("coffee_table", "desk"), ("conference_table", "desk"))
#: A furniture mix with as many tables of each kind as chairs.
TABLE_HEAVY = {"chair": 1.0, "desk": 1.0, "coffee_table": 1.0, "conference_table": 1.0, "sofa": 0.3,
               "whiteboard": 0.3}


def class_prior_section(args: argparse.Namespace) -> tuple[list[str], dict[str, Any]]:
    """Table-type accuracy with and without the geometric prior, COCO-style table votes."""
    from mapping import OracleNoise, map_room, score_room  # here: mapping.py imports this module

    n_rooms, n_frames = (3, 40) if args.quick else (args.rooms, args.frames)
    noise = OracleNoise(merge_classes=COCO_MERGE)
    with_prior = default_classes()
    without = [c.model_copy(update={"prior": None}) for c in with_prior]
    runs = (("prior", with_prior, None), ("no_prior", without, None), ("prior_table_heavy", with_prior, TABLE_HEAVY))
    rows: dict[str, list[tuple[str, str]]] = {key: [] for key, _, _ in runs}
    for k in range(n_rooms):
        seed = args.seed + k
        for key, classes, weights in runs:
            room, omap, seen, _ = map_room(seed, n_frames, noise, classes=classes,
                                           vote_groups={"desk": TABLES}, class_weights=weights)
            res = score_room(room, omap, seen)
            objs = {o.object_id: o for o in omap.objects(confirmed_only=True)}
            for _, gcls, _, mid, _ in res.labels:
                if gcls in TABLES:
                    rows[key].append((gcls, objs[mid].class_name))
    lines = [f"COCO-style table votes (coffee and conference tables reported as desk), {n_rooms} rooms "
             f"x {n_frames} frames from seed {args.seed}; matched real tables by kind -> map class:"]
    figures: dict[str, Any] = {"rooms": n_rooms, "tables": len(rows["prior"])}
    for key, pairs in rows.items():
        ok = sum(g == m for g, m in pairs)
        acc = ok / len(pairs) if pairs else float("nan")
        figures[f"table_type_accuracy_{key}"] = acc
        per_kind = {}
        for kind in TABLES:
            got = [m for g, m in pairs if g == kind]
            per_kind[kind] = {"objects": len(got), "correct": sum(m == kind for m in got),
                              "mapped_as": {c: got.count(c) for c in sorted(set(got))}}
        figures[f"by_kind_{key}"] = per_kind
        lines.append(f"  {key:<17} accuracy {acc:.3f} ({ok}/{len(pairs)}): " + "; ".join(
            f"{kind} {v['correct']}/{v['objects']} {v['mapped_as']}" for kind, v in per_kind.items()))
    figures["table_type_accuracy"] = figures["table_type_accuracy_prior"]
    target_ok = figures["table_type_accuracy"] >= 0.9 and figures["table_type_accuracy_prior_table_heavy"] >= 0.9
    lines.append(f"  table_type_accuracy {figures['table_type_accuracy']:.3f} (table-heavy rooms "
                 f"{figures['table_type_accuracy_prior_table_heavy']:.3f})  target >= 0.9 "
                 f"{'PASS' if target_ok else 'FAIL'}")
    figures["targets_met"] = target_ok
    return lines, figures
