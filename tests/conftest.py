"""Fixtures shared by the test modules (see local_ray.py for the shared local Ray)."""
from __future__ import annotations

import pytest

from local_ray import start_local_ray, stop_local_ray


@pytest.fixture
def local_ray() -> str:
    """The shared local Ray's GCS address (local_ray.py)."""
    return start_local_ray()


@pytest.fixture(scope="session", autouse=True)
def _stop_local_ray_at_the_end():
    yield
    stop_local_ray()
