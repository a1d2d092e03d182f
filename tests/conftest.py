"""Shared test fixtures: paths to the real data beside the checkout, a headless Qt platform, the
Hypothesis profiles."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

# Property tests draw the same examples on every run ("ci", the default): a CI run on a fresh machine
# passes or fails on the code alone, never on the draw. `pytest --hypothesis-profile explore` draws
# new random examples (and keeps failures in .hypothesis/) to hunt for bugs.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", print_blob=True)
settings.load_profile("ci")

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


@pytest.fixture(scope="session")
def kinect_sphere(tmp_path_factory):
    """A short synthetic Kinect v1 scan of a glossy sphere (Ward alpha 0.12), 320 x 240, 12 frames a
    pass, rendered once per test session (the live-scan and pipeline tests share it read-only)."""
    from replay.synth import render_session

    out = tmp_path_factory.mktemp("kinect") / "sphere"
    return render_session("sphere", out, frames=12, size=(320, 240), seed=1, detail="test", references=False,
                          show_progress=False)


@pytest.fixture(scope="session")
def kinect_ggx_sphere(tmp_path_factory):
    """The same short scan of the ``ggx-sphere`` (a GGX lobe, alpha 0.15, rho_s 0.22: the model ladder's
    third rung), rendered once per test session (~10 s)."""
    from replay.synth import render_session

    out = tmp_path_factory.mktemp("kinect") / "ggx-sphere"
    return render_session("ggx-sphere", out, frames=12, size=(320, 240), seed=1, detail="test", references=False,
                          show_progress=False)
