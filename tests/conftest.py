"""Shared fixtures: the ../shared folder (skipped with a reason when absent) and a cache for generated data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
CACHE = Path(os.environ.get("VI3_TEST_CACHE", REPO / ".cache" / "tests"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not (SHARED / "data").is_dir():
        pytest.skip(f"../shared is absent next to this checkout ({SHARED}); real-fixture tests need it")
    return SHARED


@pytest.fixture(scope="session")
def euroc_fixture(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "euroc_mh01_5frames" / "mav0"
    if not path.is_dir():
        pytest.skip(f"real EuRoC fixture missing at {path}")
    return path


@pytest.fixture(scope="session")
def cache_dir() -> Path:
    CACHE.mkdir(parents=True, exist_ok=True)
    return CACHE
