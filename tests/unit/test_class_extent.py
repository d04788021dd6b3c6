"""An object taller than its class allows keeps its measured footprint but not the class's
margin or least footprint (semmap.class_extent, ObjectMap.footprints)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from semmap.class_extent import MEASURED_ONLY_MARGIN_M, class_height_limit_m, contradicts_class
from semmap.config import default_classes
from semmap.objects import ObjectMap
from semmap.polygons import polygon_area_m2

CLASSES = default_classes()
BY_NAME = {c.name: c for c in CLASSES}


def _dump(class_name: str, lo_xy: tuple[float, float], hi_xy: tuple[float, float], z_max_m: float,
          top_m: float | None) -> dict[str, Any]:
    (x0, y0), (x1, y1) = lo_xy, hi_xy
    # Votes certain enough that the geometric class prior does not overturn them.
    probs = {c.name: (1.0 - 1e-6 if c.name == class_name else 1e-6 / (len(CLASSES) - 1)) for c in CLASSES}
    return {
        "object_id": 1, "class_name": class_name, "class_probs": probs, "existence": 0.95,
        "position_map_m": [(x0 + x1) / 2, (y0 + y1) / 2, z_max_m / 2], "position_std_m": 0.03,
        "footprint_xy_m": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]], "z_min_m": 0.0, "z_max_m": z_max_m,
        "top_height_m": top_m, "first_seen_s": 0.0, "last_seen_s": 1.0, "n_observations": 20,
        "confirmed": True, "view_dir_xy": [0.0, 1.0],
    }


def _footprint(dump: dict[str, Any]) -> Any:
    omap = ObjectMap(CLASSES)
    omap.load_dict({"classes": [c.name for c in CLASSES], "objects": [dump]})
    (fp,) = omap.footprints(confirmed_only=True)
    assert fp.class_name == dump["class_name"]
    return fp


def test_limits_follow_the_class_priors() -> None:
    for cls in CLASSES:
        limit = class_height_limit_m(cls)
        assert limit is not None and cls.prior is not None and cls.prior.height_m is not None
        assert limit > cls.prior.height_m[1]
        assert not contradicts_class(cls, cls.prior.height_m[1])


def test_cabinet_called_conference_table_is_not_grown_to_a_table() -> None:
    # A 0.84 x 0.46 m cabinet 1.71 m high (room 1053's phantom conference table).
    fp = _footprint(_dump("conference_table", (3.6, 5.52), (4.44, 5.98), 1.71, 0.63))
    assert fp.margin_m == pytest.approx(MEASURED_ONLY_MARGIN_M)
    assert polygon_area_m2(fp.polygon_xy_m) == pytest.approx(0.84 * 0.46, rel=0.1)


def test_cabinet_called_chair_gets_no_chair_margin() -> None:
    fp = _footprint(_dump("chair", (3.62, 5.52), (4.44, 5.76), 1.67, 0.96))
    assert fp.margin_m == pytest.approx(MEASURED_ONLY_MARGIN_M)
    assert fp.margin_m < BY_NAME["chair"].margin_m


@pytest.mark.parametrize("z_max_m", [0.75, 1.15, 1.35])
def test_table_with_things_on_its_top_keeps_class_size_and_margin(z_max_m: float) -> None:
    # A conference table seen short from one side, a monitor or a vase on its top.
    fp = _footprint(_dump("conference_table", (0.0, 0.0), (1.2, 0.6), z_max_m, 0.75))
    assert fp.margin_m == pytest.approx(BY_NAME["conference_table"].margin_m)
    sides = np.ptp(np.asarray(fp.polygon_xy_m), axis=0)
    assert max(sides) >= 1.8 - 1e-6 and min(sides) >= 0.9 - 1e-6


def test_real_chair_keeps_its_margin() -> None:
    fp = _footprint(_dump("chair", (0.0, 0.0), (0.6, 0.6), 1.09, 0.45))
    assert fp.margin_m == pytest.approx(BY_NAME["chair"].margin_m)
