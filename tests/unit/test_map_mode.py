"""``map.mode``: the planner's costmap from every layer (semantic) or the occupancy layer alone (metric)."""

from __future__ import annotations

import numpy as np
import pytest

from semmap.costmap import LETHAL_OBSTACLE, ObjectFootprint, VerticalBand
from semmap.errors import MapError
from semmap.semantic_map import SemanticMap, SemanticMapSettings


def _map(mode: str) -> SemanticMap:
    settings = SemanticMapSettings(class_names=("desk",), scan_band=VerticalBand(0.55, 0.65),
                                   origin_xy_m=(-2.0, -2.0), size_xy_m=(4.0, 4.0), mode=mode)
    smap = SemanticMap(settings)
    desk = ObjectFootprint(7, "desk", np.array([[-0.5, -0.3], [0.5, -0.3], [0.5, 0.3], [-0.5, 0.3]]),
                           0.0, 0.75, existence=1.0, margin_m=0.2)
    smap.set_objects([desk], stamp_s=1.0)
    return smap


def test_semantic_mode_plans_on_object_footprints() -> None:
    cm = _map("semantic").costmap(VerticalBand(0.45, 0.75))
    centre = cm.spec.cell_of(np.array([[0.0, 0.0]]))[0]
    assert cm.cost[centre[0], centre[1]] == LETHAL_OBSTACLE
    assert len(cm.objects) == 1


def test_metric_mode_ignores_objects_the_slice_did_not_see() -> None:
    smap = _map("metric")
    cm = smap.costmap(VerticalBand(0.45, 0.75))
    assert not np.any(cm.cost == LETHAL_OBSTACLE)
    assert cm.objects == ()
    assert np.array_equal(cm.cost, smap.metric_costmap().cost)


def test_unknown_mode_is_refused() -> None:
    with pytest.raises(MapError, match="map mode"):
        _map("lidar")
