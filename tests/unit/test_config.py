"""Configuration: the embedded default, file errors that name file/key/allowed, CLI checks."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from pydantic import ValidationError

from companion.cli import main
from companion.config import CompanionConfig, config_from_dict, dump_config, load_config
from companion.errors import ConfigError
from semmap.costmap import VerticalBand

REPO = Path(__file__).resolve().parents[2]


def test_default_yaml_equals_model_defaults() -> None:
    # config/default.yaml spells out the embedded default; they must not drift apart.
    assert load_config(REPO / "config" / "default.yaml") == CompanionConfig()


def test_dump_round_trips(tmp_path: Path) -> None:
    cfg = config_from_dict({"map": {"resolution_m": 0.1}, "planner": {"flight_altitude_m": 1.5}})
    p = tmp_path / "c.yaml"
    p.write_text(dump_config(cfg))
    assert load_config(p) == cfg


def test_example_configs_are_valid() -> None:
    files = sorted((REPO / "config").glob("*.yaml"))
    assert len(files) >= 2
    for f in files:
        load_config(f)


def test_drone_example_has_real_drone_settings() -> None:
    cfg = load_config(REPO / "config" / "hummingbird-d455.yaml")
    assert cfg.camera.source == "realsense"
    assert cfg.link.url.startswith("serial://")
    T = cfg.camera.extrinsics.T_body_camera()
    # The optical axis (camera +z) points forward-ish along body +x.
    assert T[0, 2] > 0.9


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "drone.yaml"
    p.write_text(text)
    return p


def test_error_names_file_key_and_value(tmp_path: Path) -> None:
    p = _write(tmp_path, "map:\n  resolution_m: -0.05\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value) == f"{p}: map.resolution_m: must be > 0.0 (got -0.05)"


def test_unknown_key_lists_allowed_keys(tmp_path: Path) -> None:
    p = _write(tmp_path, "map:\n  resolution: 0.05\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert f"{p}: map.resolution: unknown key" in msg
    assert "resolution_m" in msg


def test_unknown_top_level_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"mapp: unknown key .*map"):
        load_config(_write(tmp_path, "mapp: {}\n"))


def test_literal_error_lists_choices(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"camera.source: must be one of 'sim', 'recorded' or 'realsense' \(got 'kinect'\)"):
        load_config(_write(tmp_path, "camera:\n  source: kinect\n"))


def test_nested_list_error_has_index(tmp_path: Path) -> None:
    text = "classes:\n  - {name: chair, hollow: maybe, margin_m: 0.2, color_rgb: [1, 2, 3]}\n"
    with pytest.raises(ConfigError, match=r"classes.0.hollow: must be one of"):
        load_config(_write(tmp_path, text))


def test_cross_check_class_map_target(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown class 'table'"):
        load_config(_write(tmp_path, "detector:\n  class_map: {dining table: table}\n"))


def test_duplicate_classes_rejected() -> None:
    c = {"name": "chair", "hollow": "full", "margin_m": 0.2, "color_rgb": [1, 2, 3]}
    with pytest.raises(ConfigError, match="duplicate class names"):
        config_from_dict({"classes": [c, c]})


def test_colour_out_of_range() -> None:
    c = {"name": "chair", "hollow": "full", "margin_m": 0.2, "color_rgb": [1, 2, 300]}
    with pytest.raises(ConfigError, match=r"classes.0.color_rgb: .*0..255"):
        config_from_dict({"classes": [c]})


def test_bad_yaml_names_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"not valid YAML at line 2"):
        load_config(_write(tmp_path, "map:\n\tresolution_m: 0.05\n"))


def test_missing_file() -> None:
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config("/nonexistent/drone.yaml")


def test_config_is_frozen() -> None:
    cfg = CompanionConfig()
    with pytest.raises(ValidationError, match="frozen"):
        cfg.map.resolution_m = 1.0  # type: ignore[misc]


def test_classes_are_configuration() -> None:
    cfg = CompanionConfig()
    kinds = {c.name: c.hollow for c in cfg.classes}
    assert kinds == {
        "chair": "full", "coffee_table": "full", "conference_table": "partial",
        "sofa": "none", "whiteboard": "full", "desk": "full",
    }


def test_cli_config_check_ok_and_bad(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "check", str(REPO / "config" / "default.yaml")]) == 0
    bad = _write(tmp_path, "planner:\n  max_speed_m_s: 0\n")
    assert main(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "planner.max_speed_m_s: must be > 0.0 (got 0)" in err


def test_cli_config_dump_is_loadable(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "dump"]) == 0
    out = capsys.readouterr().out
    assert config_from_dict(yaml.safe_load(out)) == CompanionConfig()


def test_cli_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith("companion ")


@pytest.mark.parametrize("given", [{"slam": {"mode": "odometry"}},
                                   {"slam": {"mode": "slam"}, "service": {"localization": "slam"}}])
def test_slam_mode_is_refused_naming_service_localization(given: dict[str, object]) -> None:
    # One switch chooses whether SLAM poses the map; a second one could contradict it.
    with pytest.raises(ConfigError, match=r"<t>: slam: mode is not a key here.*service\.localization"):
        config_from_dict(given, "<t>")


@pytest.mark.parametrize("given", [{"map": {"margin_decay_m": 0.3}}, {"planner": {"clearance_decay_m": 0.15}}])
def test_old_decay_keys_are_refused_naming_the_one_decay(given: dict[str, object]) -> None:
    # One decay shapes the map's margins and the planner's proximity cost; the map owns it.
    (section, keys), = given.items()
    key = next(iter(keys))  # type: ignore[call-overload]
    with pytest.raises(ConfigError, match=rf"<t>: {section}: {key} is not a key here.*map\.clearance_decay_m"):
        config_from_dict(given, "<t>")


def test_the_one_decay_reaches_the_planners_costmap() -> None:
    from semmap.semantic_map import SemanticMap, SemanticMapSettings

    cfg = config_from_dict({"map": {"clearance_decay_m": 0.4}})
    band = VerticalBand(0.4, 0.8)
    smap = SemanticMap(SemanticMapSettings.from_config(cfg.map, cfg.classes, band))
    assert smap.costmap(band).clearance_decay_m == 0.4
    assert smap.metric_costmap(band).clearance_decay_m == 0.4


def test_the_effective_config_names_one_localization_switch() -> None:
    data = yaml.safe_load(dump_config(config_from_dict({"service": {"localization": "slam"}})))
    assert data["service"]["localization"] == "slam"
    assert "mode" not in data["slam"]
