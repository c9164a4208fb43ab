"""Shared fixtures: the ../shared folder (skipped with a reason when absent; VI3_SHARED points to another one) and a
cache for generated data. The test folders are importable from each other (a test module may use another's helpers,
whichever file or folder pytest is given)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path[:0] = [str(d) for d in sorted(Path(__file__).parent.iterdir()) if d.is_dir() and d.name != "__pycache__"]

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("VI3_SHARED", REPO.parent / "shared"))
CACHE = Path(os.environ.get("VI3_TEST_CACHE", REPO / ".cache" / "tests"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not (SHARED / "data").is_dir():
        pytest.skip(f"../shared is absent next to this checkout ({SHARED}); real-fixture tests need it")
    return SHARED


def _shared_mav0(shared_dir: Path, name: str, what: str) -> Path:
    path = shared_dir / "data" / name / "mav0"
    if not path.is_dir():
        pytest.skip(f"{what} missing at {path}")
    return path


@pytest.fixture(scope="session")
def euroc_fixture(shared_dir: Path) -> Path:
    return _shared_mav0(shared_dir, "euroc_mh01_5frames", "real EuRoC fixture")


@pytest.fixture(scope="session")
def cache_dir() -> Path:
    CACHE.mkdir(parents=True, exist_ok=True)
    return CACHE


@pytest.fixture(scope="session")
def euroc_v102(shared_dir: Path) -> Path:
    """Real EuRoC V1_02_medium IMU (200 Hz, 40 s) and ground truth (40 Hz, 83 s), calibration files, no images."""
    return _shared_mav0(shared_dir, "euroc_v102_imu_gt", "real EuRoC V1_02 IMU + GT")


@pytest.fixture(scope="session")
def v203(shared_dir: Path):
    """The real EuRoC V2_03_difficult flight (IMU and ground truth at 200 Hz, no images) opened as a ``Sequence``."""
    from vi3_core.dataset.asl import read_asl

    return read_asl(_shared_mav0(shared_dir, "euroc_v203_imu_gt", "real EuRoC V2_03 IMU + GT"))


@pytest.fixture(scope="session")
def v102(euroc_v102: Path):
    """The real V1_02 recording opened as a ``Sequence`` (camera stamps on the IMU clock; no images)."""
    from vi3_core.dataset.asl import read_asl

    return read_asl(euroc_v102)
