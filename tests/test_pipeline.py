"""ScanRunner over a recording: checkpoints, a scan stopped midway and rerun, stale checkpoints."""

from __future__ import annotations

import json

import numpy as np

from appfusion.pipeline import CHECKPOINT_VERSION, ScanConfig, ScanRunner
from replay.session import SessionReader

SMALL = dict(n_points=3000, texture_size=64, envmap_n=32, hbsab_n=16)


def _run(session, out, stop_at=None, **cfg):
    env = session / "truth" / "envmaps" / "office.exr"        # 12 frames are too few for the ball fit
    log: list[str] = []
    with SessionReader(session) as src:
        r = ScanRunner(src, out, ScanConfig(**{**SMALL, **cfg}), envmap=env, log=log.append)
        if stop_at:
            r.subscribe(lambda snap: r.stop() if snap.stage == stop_at else None)
        res = r.run()
    return r, res


def test_a_scan_stopped_midway_resumes_from_its_checkpoints(kinect_sphere, tmp_path):
    _, full = _run(kinect_sphere, tmp_path / "full")
    out = tmp_path / "resumed"
    r1, part = _run(kinect_sphere, out, stop_at="ir")       # stopped as the IR stage began
    state = out / "state"
    assert (state / "geometry.done").exists() and not (state / "rgb.done").exists()
    assert part.info["rho_d_source"].startswith("not estimated")
    r2, res = _run(kinect_sphere, out)
    assert any("geometry: reusing the checkpointed geometry" in m for m in r2.messages)
    assert (state / "rgb.done").exists()
    # the resumed scan = the uninterrupted one where it only reused the same geometry
    np.testing.assert_array_equal(res.positions, part.positions)
    assert res.n_clusters >= 1 and np.isfinite(res.rho_d).all() and np.isfinite(res.alpha).all()
    assert res.info["rho_d_source"].startswith("rgb pass")
    assert res.positions.shape == full.positions.shape
    key = json.loads((state / "rgb.done").read_text())["key"]
    assert json.loads(key)["engine"] == CHECKPOINT_VERSION


def test_checkpoints_of_another_configuration_are_recomputed(kinect_sphere, tmp_path):
    out = tmp_path / "scan"
    _run(kinect_sphere, out)
    r, res = _run(kinect_sphere, out, n_points=2000)          # another point count: nothing reusable
    assert any("checkpoint" in m and "recomputing" in m for m in r.messages)
    assert len(res.positions) == 2000
    r3, _ = _run(kinect_sphere, out, n_points=2000)            # same again: all reused
    assert not any("recomputing" in m for m in r3.messages)
    assert any("reusing the checkpointed" in m for m in r3.messages)
