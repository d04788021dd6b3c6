"""``companion config check`` refuses what ``companion run`` would fail on or misuse
(issue 33, item 6): every case exits 2 with a message naming the key or the file."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.cli import main
from companion.config import load_config
from companion.errors import ConfigError
from companion.service.checkpoint import checkpoint_path, restore_map
from companion.service.perception_worker import new_semantic_map


def _write(tmp_path: Path, text: str | bytes, name: str = "drone.yaml") -> Path:
    p = tmp_path / name
    if isinstance(text, bytes):
        p.write_bytes(text)
    else:
        p.write_text(text, encoding="utf-8")
    return p


def _check(path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, str]:
    rc = main(["config", "check", str(path), *extra])
    return rc, capsys.readouterr().err


def _service(tmp_path: Path) -> str:
    """A service section whose folders are in ``tmp_path`` (so no checkpoint is found)."""
    return f"service: {{output_dir: {tmp_path / 'out'}, map_dir: {tmp_path / 'map'}}}\n"


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_empty_config_is_refused_unless_allow_empty(tmp_path: Path, text: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    p = _write(tmp_path, text)
    rc, err = _check(p, capsys)
    assert rc == 2 and f"{p}: the config file is empty" in err
    assert _check(p, capsys, "--allow-empty")[0] == 0


def test_truncated_config_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = _write(tmp_path, "camera: {source: realsense}\nmap: {resolution_m: 0.0")
    rc, err = _check(p, capsys)
    assert rc == 2 and "does not end with a newline: it looks truncated" in err


def test_non_utf8_config_is_a_clear_error(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    p = _write(tmp_path, b"map:\n  resolution_m: 0.05 # \xe9t\xe9\n")
    rc, err = _check(p, capsys)
    assert rc == 2 and f"{p}: not UTF-8 text: byte 0xe9 at line 2" in err
    assert "Traceback" not in err


@pytest.mark.parametrize(("text", "message"), [
    ("map:\n  resolution_m: true\n", "map: resolution_m: must be a number (got true)"),
    ("planner: {max_speed_m_s: false}\n", "planner: max_speed_m_s: must be a number (got false)"),
    ("map:\n  resolution_m: 0.05\n  resolution_m: 0.5\n",
     "duplicate key 'resolution_m' (first at line 2)"),
    ("map: {origin_xy_m: [.nan, 0.0]}\n", "map.origin_xy_m.0: Input should be a finite number"),
    ("planner: {flight_altitude_m: 5.0, max_altitude_m: 3.0}\n",
     "planner: flight_altitude_m (5.0) is above max_altitude_m (3.0)"),
    ("map: {width_m: 1.0e9}\n", "map: width_m x height_m (1e+09 x 20 m) at resolution_m 0.05"),
    ("mqtt: {host: broker.example.com, username: d1, password_file: /x/pw}\n",
     "mqtt: password_file set for the remote broker 'broker.example.com' without TLS"),
])
def test_config_rule_is_refused_naming_the_key(tmp_path: Path, text: str, message: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    p = _write(tmp_path, text)
    rc, err = _check(p, capsys)
    assert rc == 2 and message in err, err


def test_password_to_a_loopback_broker_without_tls_is_allowed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pw = _write(tmp_path, "secret\n", "pw")
    p = _write(tmp_path, f"mqtt: {{host: 127.0.0.1, username: d1, password_file: {pw}}}\n"
               + _service(tmp_path))
    assert _check(p, capsys) == (0, "")


def test_ten_byte_signing_key_is_refused(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    key = _write(tmp_path, b"0123456789", "signing.key")
    p = _write(tmp_path, f"link: {{signing_key_path: {key}}}\n" + _service(tmp_path))
    rc, err = _check(p, capsys)
    assert rc == 2 and "link.signing_key_path:" in err and "32" in err


def test_missing_files_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = _write(tmp_path, "mqtt: {username: d1, password_file: /nonexistent/pw, "
               "tls_ca_file: /nonexistent/ca.crt}\n"
               "detector: {model_path: /nonexistent/model.onnx}\n" + _service(tmp_path))
    rc, err = _check(p, capsys)
    assert rc == 2
    assert "mqtt.password_file: /nonexistent/pw does not exist" in err
    assert "mqtt.tls_ca_file: /nonexistent/ca.crt does not exist" in err
    assert "detector.model_path: /nonexistent/model.onnx does not exist" in err


def test_missing_password_file_exits_2_at_run(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    # The README promises exit code 2 for a bad configuration; run used to exit 1.
    p = _write(tmp_path, "mqtt: {username: d1, password_file: /nonexistent/pw}\n"
               + _service(tmp_path))
    assert main(["run", "--config", str(p)]) == 2
    assert "mqtt.password_file: /nonexistent/pw does not exist" in capsys.readouterr().err


def test_unwritable_output_dir_is_refused(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    blocker = _write(tmp_path, "not a folder\n", "afile")
    p = _write(tmp_path, f"service: {{output_dir: {blocker}/out, map_dir: {tmp_path}/map}}\n")
    rc, err = _check(p, capsys)
    assert rc == 2 and f"service.output_dir: {blocker}/out cannot be a folder" in err


def _checkpoint(tmp_path: Path, map_yaml: str) -> Path:
    """A map checkpoint saved under ``map_yaml``'s settings in tmp_path/map."""
    cfg_path = _write(tmp_path, map_yaml + _service(tmp_path), "made.yaml")
    cfg = load_config(cfg_path)
    path = checkpoint_path(cfg)
    path.parent.mkdir(parents=True, exist_ok=True)
    new_semantic_map(cfg).save(path)
    return path


def test_checkpoint_with_other_map_settings_is_refused(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    ckpt = _checkpoint(tmp_path, "map: {resolution_m: 0.1}\n")
    p = _write(tmp_path, "map: {resolution_m: 0.05}\n" + _service(tmp_path))
    rc, err = _check(p, capsys)
    assert rc == 2
    assert f"the map checkpoint {ckpt} (resolution_m 0.1," in err
    assert "does not match the configured map (resolution_m 0.05," in err
    with pytest.raises(ConfigError, match="does not match the configured map"):
        restore_map(load_config(p), ckpt)
    assert ckpt.is_file()  # refused, not set aside or overwritten


def test_checkpoint_with_other_origin_of_a_fixed_map_is_refused(tmp_path: Path) -> None:
    ckpt = _checkpoint(tmp_path, "map: {fixed_size: true, origin_xy_m: [-5.0, -5.0]}\n")
    p = _write(tmp_path, "map: {fixed_size: true}\n" + _service(tmp_path))
    with pytest.raises(ConfigError, match=r"origin_xy_m \[-5, -5\].*origin_xy_m \[-10, -10\]"):
        restore_map(load_config(p), ckpt)


def test_checkpoint_with_the_same_map_settings_is_restored(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    ckpt = _checkpoint(tmp_path, "map: {resolution_m: 0.1}\n")
    p = _write(tmp_path, "map: {resolution_m: 0.1}\n" + _service(tmp_path))
    assert _check(p, capsys) == (0, "")
    smap = restore_map(load_config(p), ckpt)
    assert smap is not None and smap.spec.resolution_m == pytest.approx(0.1)
