"""`companion --version` is the version in pyproject.toml, and the changelog has its entry."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from companion.cli import main

REPO = Path(__file__).resolve().parents[2]


def test_version_matches_pyproject_and_changelog(capsys: pytest.CaptureFixture[str]) -> None:
    found = re.search(r'^version = "([^"]+)"$', (REPO / "pyproject.toml").read_text(), re.M)
    assert found is not None
    declared = found.group(1)
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out.split() == ["companion", declared]
    changelog = (REPO / "CHANGELOG.md").read_text()
    assert re.search(rf"^## \[{re.escape(declared)}\] - \d{{4}}-\d{{2}}-\d{{2}}$", changelog, re.M)
