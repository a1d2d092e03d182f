"""Shared test fixtures: paths to the real data beside the checkout, a headless Qt platform."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

ROOT = Path(__file__).resolve().parents[1]
SHARED = (ROOT / ".." / "shared").resolve()
REAL = SHARED / "data" / "real"


def _need(path: Path) -> Path:
    if not path.exists():
        if os.environ.get("CI"):
            raise FileNotFoundError(f"shared test data missing in CI: {path}")
        pytest.skip(f"shared data not found at {path}")
    return path


@pytest.fixture(scope="session")
def real_dir() -> Path:
    """``../shared/data/real`` (real captures made by nobody on this project)."""
    return _need(REAL)


@pytest.fixture(scope="session")
def redwood_dir(real_dir) -> Path:
    return _need(real_dir / "redwood-rgbd")


@pytest.fixture(scope="session")
def azure_mkv(real_dir) -> Path:
    return _need(real_dir / "azure-kinect" / "recording.mkv")
