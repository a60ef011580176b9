"""Shared fixtures. Real data is read from ../shared/data (never copied into the repository)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

# Hypothesis: one profile for the suite. In CI (``CI`` set, as .ci/run runs) the examples are
# derandomized, so a run is the same run every time; elsewhere each run explores new ones
# (``HYPOTHESIS_PROFILE=ci`` reproduces CI's). No per-example deadline: a wall-clock limit would
# fail a loaded machine, not a wrong result.
settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
settings.register_profile("dev", deadline=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = Path(os.environ.get("LIGHTPROBE_SHARED_DATA", ROOT.parent / "shared" / "data"))
ENVMAP_NAMES = [
    "studio_small_03_1k.hdr",
    "rooitou_park_1k.hdr",
    "potsdamer_platz_1k.hdr",
    "lebombo_1k.hdr",
    "dikhololo_night_1k.hdr",
    "interior_blender.exr",
]


@pytest.fixture(scope="session", autouse=True)
def table_cache_for_services() -> Path:
    """One cache of projection tables and lens matrices for every service a test starts, in this
    process or a subprocess (``LIGHTPROBE_TEST_CACHE``), built by the real code on first use."""
    from service_harness import shared_cache

    return shared_cache()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}: CI clones ../shared beside the repo")
    return SHARED_DATA


@pytest.fixture(scope="session")
def envmap_paths(shared_data: Path) -> dict[str, Path]:
    return {name: shared_data / "envmaps" / name for name in ENVMAP_NAMES}


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    d = ROOT / "test-artifacts"
    d.mkdir(exist_ok=True)
    return d
