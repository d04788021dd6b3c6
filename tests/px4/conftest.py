"""One real PX4 SITL for the whole ``px4`` session (skipped, with the reason, when the SITL
tarball is not beside the repository)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from companion.sim.px4_sitl import Px4Sitl, sitl_available


@pytest.fixture(scope="session")
def sitl() -> Iterator[Px4Sitl]:
    """A running PX4 SITL (SIH, no lockstep, free ports), ready for take-off; stopped at the end."""
    ok, why = sitl_available()
    if not ok:
        pytest.skip(why)
    with Px4Sitl(keep_workdir=False) as running:
        yield running
