"""The package arrows: companion -> planner -> semmap, never back; the onboard service apart
from the simulation harness."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
#: What each package may not import.
FORBIDDEN = {"semmap": ("companion", "planner"), "planner": ("companion",)}


def _imported_modules(path: Path) -> set[tuple[str, int]]:
    """The absolute modules ``path`` imports, each with the line that imports it."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out: set[tuple[str, int]] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update((alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add((node.module, node.lineno))
    return out


def _imported_packages(path: Path) -> set[tuple[str, int]]:
    return {(name.split(".")[0], line) for name, line in _imported_modules(path)}


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_a_lower_package_never_imports_a_higher_one(package: str) -> None:
    wrong = [f"{path.relative_to(REPO)}:{line} imports {name}"
             for path in sorted((REPO / package).rglob("*.py"))
             for name, line in sorted(_imported_packages(path)) if name in FORBIDDEN[package]]
    assert not wrong, "\n".join(wrong)


def test_the_onboard_service_never_imports_the_simulation_harness() -> None:
    wrong = [f"{path.relative_to(REPO)}:{line} imports {name}"
             for path in sorted((REPO / "companion" / "service").rglob("*.py"))
             for name, line in sorted(_imported_modules(path))
             if name == "companion.sim" or name.startswith("companion.sim.")]
    assert not wrong, "\n".join(wrong)


def test_the_command_line_is_one_package() -> None:
    flat = sorted(p.name for p in (REPO / "companion").glob("cmd_*.py"))
    assert not flat, f"subcommand modules outside companion/cli/: {flat}"
    from companion.cli import COMMAND_MODULES

    assert all(name.startswith("companion.cli.") for name in COMMAND_MODULES)


def test_one_exception_tree_with_each_error_where_its_concept_lives() -> None:
    import companion.errors as companion_errors
    import semmap.errors as semmap_errors

    for module in (semmap_errors, companion_errors):
        errors = [v for v in vars(module).values() if isinstance(v, type) and issubclass(v, BaseException)]
        assert errors and all(issubclass(e, semmap_errors.CompanionError) for e in errors), module.__name__
    # The link, mission, ground-link and simulator errors are the companion's own.
    for name in ("LinkError", "CommandError", "MissionError", "GroundLinkError", "SimulationError"):
        assert getattr(companion_errors, name).__module__ == "companion.errors", name
        assert not hasattr(semmap_errors, name), f"semmap.errors defines the companion's {name}"
    # Every error companion code raises is importable from one place.
    assert set(companion_errors.__all__) >= {n for n, v in vars(semmap_errors).items()
                                             if isinstance(v, type) and issubclass(v, BaseException)}


def test_the_onboard_service_builds_no_configuration_space() -> None:
    """Path checks and escape points are the planning process's: a configuration-space update
    in the service would compete with the setpoint stream for its GIL."""
    wrong = [f"{path.relative_to(REPO)}:{line} imports {name}"
             for path in sorted((REPO / "companion" / "service").rglob("*.py"))
             for name, line in sorted(_imported_modules(path))
             if name in ("planner.cspace", "planner.planner")]
    assert not wrong, "\n".join(wrong)


def test_angles_are_wrapped_in_one_place() -> None:
    """semmap.frames.wrap_angle_rad is the one angle wrap; a second copy drifts (one wrapped
    to [-pi, pi], another to [-pi, pi))."""
    import re

    hand_wrap = re.compile(r"remainder\(.*\bpi\b|%\s*\(?\s*2(\.0)?\s*\*\s*(math|np)\.pi|%\s*(math|np)\.tau")
    wrong = [f"{path.relative_to(REPO)}:{n}: {line.strip()}"
             for package in ("semmap", "planner", "companion", "bench")
             for path in sorted((REPO / package).rglob("*.py")) if path != REPO / "semmap" / "frames.py"
             for n, line in enumerate(path.read_text().splitlines(), 1) if hand_wrap.search(line)]
    assert not wrong, "\n".join(wrong)
