"""The geometric class prior: the object map weighs class votes by the measured object's
height and footprint, and a detector class standing for several of ours (COCO's one table
class) votes for all of them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import CompanionConfig, config_from_dict
from semmap.class_prior import ClassPrior, footprint_sides_m, range_likelihood
from semmap.config import ClassConfig, DetectorConfig, GeometricPrior, default_classes
from semmap.detection.builtin import detector_vote_groups, vote_groups
from semmap.errors import ConfigError
from semmap.geometry import ObjectObservation
from semmap.objects import ObjectMap

TABLES = ("desk", "coffee_table", "conference_table")
COCO_GROUPS = {"desk": TABLES}


def obs(track: int, cls: str, height_m: float, size_m: tuple[float, float], stamp: float,
        score: float = 0.9, xy: tuple[float, float] = (3.0, 0.0)) -> ObjectObservation:
    """An observation of a box-shaped object ``size_m`` (length, width) and ``height_m`` tall."""
    x, y = xy
    hl, hw = size_m[0] / 2, size_m[1] / 2
    fp = np.array([[x - hl, y - hw], [x + hl, y - hw], [x + hl, y + hw], [x - hl, y + hw]])
    return ObjectObservation(track, cls, score, stamp, (x, y, height_m / 2), fp, 0.0, height_m,
                             500, 100, 3.0, top_height_m=height_m)


def mapped(cls: str, height_m: float, size_m: tuple[float, float], classes: list[ClassConfig] | None = None,
           groups: dict[str, tuple[str, ...]] | None = None, n: int = 8) -> tuple[str, dict[str, float]]:
    """The class the object map reports after ``n`` confident detections as ``cls``."""
    m = ObjectMap(classes or default_classes(), vote_groups=groups)
    for t in range(n):
        m.update([obs(1, cls, height_m, size_m, float(t))], float(t))
    (o,) = m.objects()
    return o.class_name, dict(o.class_probs)


def test_inside_its_range_a_measure_fits_and_outside_it_fits_less_the_further_it_is() -> None:
    assert range_likelihood(0.7, (0.62, 0.9), 0.03, 0.03) == 1.0
    assert range_likelihood(0.5, None, 0.03, 0.03) == 1.0
    near, far = range_likelihood(0.58, (0.62, 0.9), 0.03, 0.03), range_likelihood(0.45, (0.62, 0.9), 0.03, 0.03)
    assert 0.0 < far < near < 1.0
    assert near == pytest.approx(math.exp(-0.5 * (0.04 / 0.03) ** 2))
    # A side too short is weak evidence (a partial view), one too long strong.
    assert range_likelihood(0.5, (0.8, 2.0), 0.4, 0.1) > range_likelihood(2.3, (0.8, 2.0), 0.4, 0.1)


def test_footprint_sides_are_those_of_the_rotated_rectangle() -> None:
    a = math.radians(30)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    rect = np.array([[-1.2, -0.4], [1.2, -0.4], [1.2, 0.4], [-1.2, 0.4]]) @ R.T + [5.0, 1.0]
    long_m, short_m = footprint_sides_m(rect)
    assert (long_m, short_m) == (pytest.approx(2.4, abs=1e-6), pytest.approx(0.8, abs=1e-6))
    assert footprint_sides_m(np.zeros((2, 2))) is None


def test_a_desk_0_45_m_high_becomes_a_coffee_table_whatever_the_detector_says() -> None:
    name, probs = mapped("desk", 0.45, (1.0, 0.6))
    assert name == "coffee_table" and probs["desk"] < 0.01


def test_a_chair_2_m_high_is_not_believed() -> None:
    name, probs = mapped("chair", 2.0, (0.5, 0.5))
    assert name != "chair" and probs["chair"] < 0.01


def test_a_plausible_object_keeps_the_class_its_detections_give() -> None:
    assert mapped("desk", 0.75, (1.4, 0.7))[0] == "desk"
    assert mapped("chair", 0.9, (0.5, 0.5))[0] == "chair"
    assert mapped("sofa", 0.85, (2.0, 0.9))[0] == "sofa"


@pytest.mark.parametrize(("height_m", "size_m", "kind"), [
    (0.45, (1.0, 0.6), "coffee_table"),
    (0.75, (1.4, 0.7), "desk"),
    (0.75, (1.6, 0.9), "desk"),            # a dining table is a desk here
    (0.75, (2.4, 1.2), "conference_table"),
    (0.76, (2.0, 1.1), "conference_table"),
])
def test_coco_table_votes_become_the_table_kind_the_geometry_says(height_m: float, size_m: tuple[float, float],
                                                                    kind: str) -> None:
    assert mapped("desk", height_m, size_m, groups=COCO_GROUPS)[0] == kind


def test_without_vote_groups_a_big_table_voted_desk_stays_a_desk_unless_clearly_too_big() -> None:
    """The votes of a model that names desks (the furniture model) count: a table between the
    desk and conference ranges stays what the detector said."""
    assert mapped("desk", 0.75, (1.95, 0.9))[0] == "desk"


def test_classes_without_a_prior_leave_the_votes_alone() -> None:
    bare = [c.model_copy(update={"prior": None}) for c in default_classes()]
    assert mapped("desk", 0.45, (1.0, 0.6), classes=bare)[0] == "desk"
    assert not ClassPrior(bare).active


def test_a_group_vote_keeps_reassociating_its_table() -> None:
    """A grouped desk vote ties the three table classes; a new track over the same table must
    still find it (association by class must accept any class of the group)."""
    m = ObjectMap(default_classes(), vote_groups=COCO_GROUPS)
    for t in range(3):
        m.update([obs(1, "desk", 0.75, (2.4, 1.2), float(t))], float(t))
    m.update([obs(2, "desk", 0.75, (2.4, 1.2), 3.0, xy=(3.1, 0.05))], 3.0)
    assert len(m) == 1


def test_a_deployment_adds_a_class_with_its_prior_by_configuration_alone() -> None:
    cfg = config_from_dict({
        "classes": [*[c.model_dump(mode="json") for c in default_classes()],
                    {"name": "bed", "hollow": "none", "margin_m": 0.2, "color_rgb": [200, 200, 0],
                     "prior": {"height_m": [0.3, 0.7], "footprint_long_m": [1.8, 2.3],
                               "footprint_short_m": [0.8, 2.0]}}],
        "detector": {"class_map": {"chair": "chair", "bed": "bed"}},
    })
    assert cfg.class_by_name("bed").prior == GeometricPrior(height_m=(0.3, 0.7), footprint_long_m=(1.8, 2.3),
                                                            footprint_short_m=(0.8, 2.0))
    classes = list(cfg.classes)
    assert mapped("bed", 0.5, (2.0, 1.6), classes=classes)[0] == "bed"
    # A "sofa" 0.5 m high and 2 x 1.8 m (a king-size bed's footprint) is a bed.
    assert mapped("sofa", 0.5, (2.0, 1.8), classes=classes)[0] == "bed"


def test_a_bad_prior_or_class_map_list_is_an_error_naming_the_key() -> None:
    with pytest.raises(ConfigError, match=r"classes.0.prior.height_m"):
        config_from_dict({"classes": [{"name": "chair", "hollow": "full", "margin_m": 0.2,
                                       "color_rgb": [1, 2, 3], "prior": {"height_m": [1.3, 0.4]}}]})
    with pytest.raises(ConfigError, match=r"diningtable.*unknown class 'bench'"):
        config_from_dict({"detector": {"class_map": {"diningtable": ["desk", "bench"]}}})


def test_the_coco_model_votes_for_all_three_tables_and_the_furniture_model_for_one() -> None:
    names = [c.name for c in CompanionConfig().classes]
    auto = DetectorConfig(model_path="auto")
    assert detector_vote_groups(auto, names, real_camera=True) == {"desk": ("desk", "coffee_table",
                                                                           "conference_table")}
    assert detector_vote_groups(auto, names, real_camera=False) == {}
    assert detector_vote_groups(DetectorConfig(kind="oracle"), names, real_camera=True) == {}
    assert vote_groups({"chair": "chair", "diningtable": ["desk", "coffee_table"]}) == {
        "desk": ("desk", "coffee_table")}
