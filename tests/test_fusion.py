"""Tests of appfusion.fusion (tracking + TSDF fusion) and appfusion.geometry_pass (paper §4.1)."""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from appfusion.errors import AppFusionError, EstimationError
from appfusion.frame import Intrinsics, invert_pose, make_pose, transform_points
from appfusion.fusion import (FusionConfig, TSDFFusion, depth_range_hint, downsample_depth, drop_grazing, kabsch,
                              orthonormalize, rotation_angle_deg, voxel_size_for_box)
from appfusion.geometry_pass import GeometryConfig, GeometryPass
from appfusion.geometry_synth import make_sequence

K320 = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5).scaled(320, 240)


def _plane_depth(K: Intrinsics, z: float = 0.7, tilt_deg: float = 20.0) -> np.ndarray:
    """Depth of a plane through (0, 0, z) tilted about the camera x axis."""
    t = np.deg2rad(tilt_deg)
    n = np.array([0.0, np.sin(t), -np.cos(t)])           # plane n.x + d = 0 facing the camera
    d = -n @ np.array([0.0, 0.0, z])
    rays = K.rays().astype(np.float64)
    return (-d / (rays @ n)).astype(np.float32)


def _ate(P: np.ndarray, Q: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((P[:, :3, 3] - Q[:, :3, 3]) ** 2, axis=1))))


@pytest.fixture(scope="module")
def seq():
    return make_sequence(30, 320, 240, seed=0)


# -- the Open3D pin -----------------------------------------------------------------------------
def test_integration_is_not_empty():
    """Fails when the installed Open3D integrates nothing (0.20's legacy ScalableTSDFVolume does)."""
    depth = _plane_depth(K320)
    fu = TSDFFusion(K320, FusionConfig())
    res = fu.process(depth)
    assert res.state == "first" and res.integrated
    assert fu.n_blocks > 0
    mesh = fu.extract_mesh(weight_threshold=0.5)
    assert len(mesh.triangles) > 1000
    assert len(fu.extract_point_cloud(weight_threshold=0.5).points) > 1000
    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=0.004, sdf_trunc=0.016, color_type=o3d.pipelines.integration.TSDFVolumeColorType.NoColor)
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(np.zeros((240, 320, 3), np.uint8)), o3d.geometry.Image(depth), depth_scale=1.0,
        depth_trunc=2.0, convert_rgb_to_intensity=False)
    vol.integrate(rgbd, o3d.camera.PinholeCameraIntrinsic(320, 240, K320.fx, K320.fy, K320.cx, K320.cy), np.eye(4))
    assert len(vol.extract_triangle_mesh().triangles) > 1000, "legacy ScalableTSDFVolume integrated nothing"


def test_fused_plane_and_raycast_are_unbiased():
    """The mesh and the (refined) ray cast of a fused plane lie on the plane (guards the half-pixel
    and half-voxel corrections around Open3D's kernels)."""
    K = K320
    depth = _plane_depth(K, 0.7, 25.0)
    fu = TSDFFusion(K, FusionConfig())
    for _ in range(3):
        fu.integrate(depth, np.eye(4))
    P = np.asarray(fu.extract_mesh(weight_threshold=1.0).vertices)
    t = np.deg2rad(25.0)
    n = np.array([0.0, np.sin(t), -np.cos(t)])
    dist = P @ n + n @ np.array([0.0, 0.0, -0.7])
    inner = np.abs(P[:, 0]) < 0.15
    assert abs(np.median(dist[inner])) < 2e-4
    r = fu.raycast(np.eye(4), K)
    rr = fu.raycast(np.eye(4), K, refine=False)
    ok = np.isfinite(r) & np.isfinite(depth)
    assert ok.mean() > 0.8
    assert abs(np.median(r[ok] - depth[ok])) < 2e-4
    assert np.sqrt(np.mean((r[ok] - depth[ok]) ** 2)) < 6e-4
    # the raw Open3D ray cast is visibly worse (nearest-voxel marching)
    assert np.sqrt(np.nanmean((rr - depth) ** 2)) > 2 * np.sqrt(np.mean((r[ok] - depth[ok]) ** 2))


def test_drop_grazing_and_the_surface_volume():
    """Pixels seen beyond the incidence limit, and those at a depth jump, stay out of the surface
    volume (the extracted mesh) while the tracking volume fuses them."""
    K = K320
    assert np.isfinite(drop_grazing(_plane_depth(K, 0.7, 25.0), K, 70.0)[1:-1, 1:-1]).all()
    tilt = np.deg2rad(75.0)
    steep = _plane_depth(K, 0.7, 75.0)
    with np.errstate(invalid="ignore"):
        steep[~(steep > 0.2) | ~(steep < 1.5)] = np.nan
    rays = K.rays() / np.linalg.norm(K.rays(), axis=-1, keepdims=True)
    inc = np.degrees(np.arccos(np.abs(rays @ np.array([0.0, np.sin(tilt), -np.cos(tilt)]))))
    kept = np.isfinite(drop_grazing(steep, K, 70.0))
    ok = np.isfinite(steep)
    ok[:2], ok[-2:], ok[:, :2], ok[:, -2:] = False, False, False, False
    assert (inc[ok] > 72).sum() > 1000 and (inc[ok] < 68).sum() > 1000
    assert not kept[ok & (inc > 72)].any() and kept[ok & (inc < 68)].all()
    step = _plane_depth(K, 0.7, 0.0)
    step[:, 160:] += 0.05                                # a 5 cm step: the pixels beside it dropped
    kept = np.isfinite(drop_grazing(step, K, 70.0))
    assert not kept[10:-10, 158:162].any() and kept[10:-10, 150:158].all() and kept[10:-10, 162:170].all()
    steep = np.where(inc > 72, steep, np.nan).astype(np.float32)        # only grazing pixels left
    fu = TSDFFusion(K, FusionConfig())
    assert fu.config.surface_max_incidence_deg == 70.0 and fu.surface_vbg is not None
    for _ in range(3):
        fu.integrate(steep, np.eye(4))
    assert fu.n_blocks > 0
    assert len(fu.extract_mesh(weight_threshold=1.0).vertices) == 0       # nothing the surface trusts
    one = TSDFFusion(K, FusionConfig(surface_max_incidence_deg=None))
    assert one.surface_vbg is None
    for _ in range(3):
        one.integrate(steep, np.eye(4))
    assert len(one.extract_mesh(weight_threshold=1.0).vertices) > 100


def test_all_blocks_raycast_uses_only_active_blocks():
    """``hashmap().key_tensor()`` is the whole key buffer (capacity rows, with the erased warm-up blocks
    far away): the all-blocks ray cast must march only the allocated blocks (it hung Open3D for minutes
    on a relocalisation of a 160 x 120 session)."""
    K = K320
    fu = TSDFFusion(K, FusionConfig())
    fu.integrate(_plane_depth(K, 0.7, 20.0), np.eye(4))
    hm = fu.vbg.hashmap()
    assert hm.key_tensor().shape[0] == hm.capacity() > fu.n_blocks
    act = fu.active_blocks().numpy()
    assert len(act) == fu.n_blocks > 0
    assert np.abs(act).max() < 1000                   # none of the warm-up blocks at z = 100000
    assert len(np.unique(act, axis=0)) == len(act)
    pose = make_pose(None, [0.01, -0.01, 0.0])
    t0 = time.perf_counter()
    d_all = fu.raycast(pose, all_blocks=True)
    assert time.perf_counter() - t0 < 30.0            # a guard against the minutes-long hang, not a timing
    d_last = fu.raycast(pose)
    ok = np.isfinite(d_all) & np.isfinite(d_last)
    assert ok.mean() > 0.5 and np.allclose(d_all[ok], d_last[ok], atol=1e-6)


def test_keyframes_skip_frames_without_new_coverage(monkeypatch):
    """A frame at the keyframe's pose seeing only surfaces the volume has is tracked but not fused, and
    tracking reuses the keyframe's ray cast; one that reveals a new surface is fused whatever its motion."""
    K = K320
    plane = _plane_depth(K, 0.7, 20.0)
    bump = plane.copy()
    bump[60:120, 40:120] -= 0.12                     # a box 12 cm in front of the plane: new voxel blocks
    fu = TSDFFusion(K, FusionConfig())
    assert fu.config.keyframe_m > 0 and fu.config.keyframe_deg > 0       # on by default
    calls = []
    orig = TSDFFusion.raycast
    monkeypatch.setattr(TSDFFusion, "raycast", lambda self, *a, **k: calls.append(1) or orig(self, *a, **k))
    res = [fu.process(d) for d in (plane, plane, plane, bump)]
    assert [r.state for r in res] == ["first", "ok", "ok", "ok"], [r.reason for r in res]
    assert [r.integrated for r in res] == [True, False, False, True]
    assert fu.n_skipped == 2 and fu.n_integrated == 2
    assert len(calls) == 1                            # frames 2-4 track against frame 1's ray cast
    assert "integrate" not in res[1].ms and "skip_check" in res[1].ms
    # keyframes off: every tracked frame is fused (KinectFusion)
    off = TSDFFusion(K, FusionConfig(keyframe_m=0.0, keyframe_deg=0.0))
    assert all(off.process(d).integrated for d in (plane, plane, plane))


def test_keyframes_keep_tracking_on_a_dense_sequence():
    """0.5 degrees per frame: about half the frames skip fusion, the poses stay within 5 mm and the mesh
    matches the one fused from every frame."""
    s = make_sequence(24, 320, 240, seed=2, sweep_deg=12.0, colour_cast=False)
    runs = {}
    for name, km in (("on", 0.01), ("off", 0.0)):
        fu = TSDFFusion(s.intrinsics, FusionConfig(keyframe_m=km), initial_pose=s.poses[0])
        h = s.side / 2 + 0.05
        fu.set_roi(np.eye(4), [-h, -h, -0.05], [h, h, 0.35])
        res = [fu.process(f.depth) for f in s.frames]
        assert all(r.state != "lost" for r in res)
        err = np.linalg.norm(np.array([r.pose[:3, 3] - p[:3, 3] for r, p in zip(res, s.poses)]), axis=1)
        assert err.max() < 0.005, name
        runs[name] = (fu, res)
    on, off = runs["on"][0], runs["off"][0]
    assert 6 <= on.n_skipped <= 18 and off.n_skipped == 0
    a = np.asarray(on.extract_mesh(1.0).vertices)
    b = o3d.t.geometry.RaycastingScene()
    b.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(off.extract_mesh(1.0)))
    d = b.compute_distance(o3d.core.Tensor(a.astype(np.float32))).numpy()
    assert np.median(d) < 1e-3


def test_downsample_depth_block_means():
    rng = np.random.default_rng(0)
    d = (1.0 + rng.normal(0, 0.004, (48, 64))).astype(np.float32)
    d[rng.random(d.shape) < 0.3] = np.nan
    d[10:14, 10:14] = 0.5                                     # a discontinuity inside some blocks
    d[11, 12] = 1.0
    b = d.reshape(24, 2, 32, 2)
    valid = np.isfinite(b)
    n = valid.sum((1, 3))
    mean = np.where(valid, b, 0).sum((1, 3)) / np.maximum(n, 1)
    jump = np.where(valid, b, -1).max((1, 3)) - np.where(valid, b, 9).min((1, 3))
    for min_valid, need in ((0.5, 2), (1.0, 4)):              # default 1.0: complete blocks only
        out = downsample_depth(d, 2, min_valid=min_valid) if min_valid != 1.0 else downsample_depth(d, 2)
        expect = np.where((n >= need) & (jump <= 0.03), mean, np.nan)
        assert np.array_equal(np.isnan(out), np.isnan(expect))
        assert np.nanmax(np.abs(out - expect)) < 1e-6
        assert np.isnan(out[5, 6])                            # the block with the 0.5 / 1.0 jump
    # an infinite or negative pixel is no depth either (it made its block infinite, with a warning)
    bad = np.full((4, 4), 1.0, np.float32)
    bad[0, 0], bad[2, 3] = np.inf, -1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = downsample_depth(bad, 2, min_valid=0.5)
    assert np.array_equal(out, np.ones((2, 2), np.float32))
    assert np.isnan(downsample_depth(bad, 2)[[0, 1], [0, 1]]).all()    # complete blocks only by default


def test_pose_helpers():
    rng = np.random.default_rng(1)
    R = o3d.geometry.get_rotation_matrix_from_xyz(rng.normal(size=3))
    T = make_pose(R, [0.1, -0.2, 0.3])
    A = rng.normal(size=(6, 3))
    assert np.allclose(kabsch(A, A @ R.T + T[:3, 3]), T, atol=1e-9)
    noisy = T.copy()
    noisy[:3, :3] *= 1.01
    Tn = orthonormalize(noisy)
    assert np.allclose(Tn[:3, :3].T @ Tn[:3, :3], np.eye(3), atol=1e-12)
    assert rotation_angle_deg(invert_pose(T) @ Tn) < 1e-4
    assert voxel_size_for_box(0.30) == pytest.approx(0.003)
    assert voxel_size_for_box(0.60, 0.30) == pytest.approx(0.006)
    assert voxel_size_for_box(0.05, 0.05) == pytest.approx(0.002)
    assert voxel_size_for_box(0.30, pixel_m=0.001) == pytest.approx(0.003)     # VGA at 0.6 m: the box rules
    assert voxel_size_for_box(0.30, pixel_m=0.0026) == pytest.approx(0.0039)   # QVGA at 0.75 m: 1.5 pixels
    with pytest.raises(AppFusionError, match="pixel"):
        voxel_size_for_box(0.30, pixel_m=0.0)
    with pytest.raises(AppFusionError):
        voxel_size_for_box(-1.0)


# -- tracking -------------------------------------------------------------------------------------
def test_tracking_synthetic_sequence(seq):
    """Frame-to-model tracking without markers on the ray-cast sequence: ATE RMSE <= 5 mm."""
    fu = TSDFFusion(seq.intrinsics, FusionConfig(), initial_pose=seq.poses[0])
    h = seq.side / 2 + 0.05
    fu.set_roi(np.eye(4), [-h, -h, -0.05], [h, h, 0.35])
    res = [fu.process(f.depth) for f in seq.frames]
    assert [r.state for r in res].count("lost") == 0
    P = np.array([r.pose for r in res])
    assert _ate(P, seq.poses) < 0.005
    assert all(r.overlap > 0.6 and r.inlier_fraction > 0.95 for r in res[1:])


def test_tracking_lost_and_relocalised():
    """A wall in front of the camera for three frames: those are reported lost (not fused) and the
    scan resumes when the view returns."""
    s = make_sequence(20, 320, 240, seed=3, occluder_frames=(9, 10, 11))
    fu = TSDFFusion(s.intrinsics, FusionConfig(), initial_pose=s.poses[0])
    h = s.side / 2 + 0.05
    fu.set_roi(np.eye(4), [-h, -h, -0.05], [h, h, 0.35])
    res = [fu.process(f.depth) for f in s.frames]
    states = [r.state for r in res]
    assert states[9:12] == ["lost"] * 3, states
    assert not any(r.integrated for r in res[9:12])
    assert all(st == "ok" for st in states[13:]), states
    assert "overlap" in res[10].reason or "jump" in res[10].reason or "inlier" in res[10].reason
    ok = [i for i, r in enumerate(res) if r.state != "lost"]
    err = np.linalg.norm(np.array([res[i].pose[:3, 3] - s.poses[i][:3, 3] for i in ok]), axis=1)
    assert err.max() < 0.01
    # while lost the pose is the last good one
    assert np.allclose(res[10].pose, res[8].pose)


def _read_log(path: Path) -> np.ndarray:
    lines = path.read_text().split("\n")
    poses = []
    for i in range(0, len(lines) - 4, 5):
        if not lines[i].strip():
            break
        poses.append(np.array([[float(x) for x in lines[i + k].split()] for k in range(1, 5)]))
    return np.array(poses)


def test_tracking_real_redwood_frames(redwood_dir):
    """The five real PrimeSense frames: tracking stays within 2 cm of trajectory.log."""
    traj = _read_log(redwood_dir / "trajectory.log")
    K = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)
    fu = TSDFFusion(K, FusionConfig(voxel_size=0.01, depth_max=3.5), initial_pose=traj[0])
    for i in range(len(traj)):
        raw = cv2.imread(str(redwood_dir / "depth" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED)
        assert raw is not None and raw.dtype == np.uint16
        depth = raw.astype(np.float32) / 1000.0
        depth[raw == 0] = np.nan
        r = fu.process(depth)
        assert r.state in ("first", "ok"), r.reason
        err = np.linalg.norm(r.pose[:3, 3] - traj[i][:3, 3])
        assert err < 0.02, f"frame {i}: {err * 1e3:.1f} mm from trajectory.log"
        assert rotation_angle_deg(invert_pose(traj[i]) @ r.pose) < 1.0


def test_tracking_fusion_speed_640():
    """Tracking + fusion of 640x480 frames (integration at 320, tracking at 160): a regression bound
    for a loaded 2-core CI machine (measured ~27-40 ms a frame, see docs/geometry-pass.md)."""
    s = make_sequence(8, 640, 480, seed=5, colour_cast=False)
    fu = TSDFFusion(s.intrinsics, FusionConfig(), initial_pose=s.poses[0])
    h = s.side / 2 + 0.05
    fu.set_roi(np.eye(4), [-h, -h, -0.05], [h, h, 0.35])
    times = []
    for f in s.frames:
        t0 = time.perf_counter()
        r = fu.process(f.depth)
        times.append(time.perf_counter() - t0)
        assert r.state != "lost"
    assert np.median(times[1:]) < 0.2, f"{np.median(times[1:]) * 1e3:.0f} ms per frame"


def test_fusion_bad_input():
    fu = TSDFFusion(K320, FusionConfig())
    with pytest.raises(AppFusionError, match="does not match"):
        fu.process(np.zeros((10, 10), np.float32))
    r = fu.process(np.full(K320.shape, np.nan, np.float32))
    assert r.state == "lost" and "no valid depth" in r.reason
    assert len(fu.extract_mesh().triangles) == 0
    with pytest.raises(AppFusionError, match="lo < hi"):
        fu.set_roi(np.eye(4), [0, 0, 0], [0, 1, 1])
    with pytest.raises(AppFusionError, match="invalid configuration"):
        TSDFFusion(K320, FusionConfig(voxel_size=-1))


# -- the geometry pass ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def geometry(seq):
    gp = GeometryPass(GeometryConfig(n_points=30000), meta={"extra": seq.meta_extra})
    states = [gp.add_frame(f) for f in seq.frames]
    return gp, states, gp.result()


def test_geometry_pass_poses_and_markers(seq, geometry):
    gp, states, res = geometry
    assert all(s.ok for s in states)
    assert res.poses.shape == (30, 4, 4)
    assert _ate(res.poses, seq.poses) < 0.005               # measured ~0.7 mm
    # markers found in every frame where all four are fully visible
    vis = seq.markers_visible.all(1)
    found = np.array([s.markers_complete for s in states])
    assert found[vis].mean() >= 0.99
    assert np.linalg.norm(res.marker_centers - seq.marker_centers, axis=1).max() < 0.003
    assert res.box.half_x == pytest.approx(seq.side / 2, abs=0.003)
    assert res.box.z_max == pytest.approx(0.30)
    assert np.allclose(res.marker_to_world, invert_pose(seq.poses[0]), atol=0.003)
    assert states[5].pose_marker is not None
    assert np.linalg.norm(states[5].pose_marker[:3, 3] - seq.poses[5][:3, 3]) < 0.005


def test_geometry_pass_mesh_points_normals(seq, geometry):
    _, _, res = geometry
    # 320 x 240, circles ~0.75 m away: 1.5 depth pixels' footprint (~4 mm) sets the voxel, not the box's 3 mm
    assert 0.0035 < res.voxel_size < 0.0045
    V = np.asarray(res.mesh.vertices)
    assert res.box.contains(V).all()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(seq.object_mesh))
    acc = scene.compute_distance(o3d.core.Tensor(
        np.asarray(res.mesh.sample_points_uniformly(20000).points, np.float32))).numpy()
    ours = o3d.t.geometry.RaycastingScene()
    ours.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(res.mesh))
    vis = seq.visible_points[seq.visible_points[:, 2] > res.box.z_min]
    comp = ours.compute_distance(o3d.core.Tensor(vis.astype(np.float32))).numpy()
    chamfer = (acc.mean() + comp.mean()) / 2
    assert chamfer < 0.002, f"chamfer {chamfer * 1e3:.2f} mm"
    assert res.points.shape == (30000, 3) and res.normals.shape == (30000, 3)
    assert np.allclose(np.linalg.norm(res.normals, axis=1), 1.0)
    gn = scene.compute_closest_points(o3d.core.Tensor(res.points.astype(np.float32)))["primitive_normals"].numpy()
    err = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", res.normals, gn)), 0, 1)))
    raw = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", res.raw_normals, gn)), 0, 1)))
    assert np.median(err) <= 3.0, f"median normal error {np.median(err):.2f} deg"
    assert np.median(err) < np.median(raw)                    # the bilateral filter helps
    # the spatial grid of the sampled points registers a frame's pixels
    grid = res.grid()
    f = seq.frames[10]
    pix, pt = grid.register(f.depth, f.depth_intrinsics, res.poses[10])
    assert len(pix) > 1000 and len(pix) == len(pt)


def test_geometry_pass_bad_input(seq):
    gp = GeometryPass(meta={"extra": seq.meta_extra})
    f0, f1, f2 = seq.frames[0], seq.frames[1], seq.frames[2]
    st = gp.add_frame(f0.replace(depth=np.full_like(f0.depth, np.nan)))
    assert st.state == "skipped" and "no valid depth" in st.reason
    st = gp.add_frame(f0.replace(depth=None))
    assert st.state == "skipped" and "no depth" in st.reason
    assert gp.add_frame(f1).state == "first"
    st = gp.add_frame(f1)                                     # the same frame again
    assert st.state == "skipped" and "out of order" in st.reason
    assert gp.add_frame(f2).state == "ok"
    st = gp.add_frame(f0.replace(index=3, timestamp=-1.0))    # older timestamp
    assert st.state == "skipped" and "out of order" in st.reason
    st = gp.add_frame(f2.replace(index=4, timestamp=1.0, depth=f2.depth[:100]))
    assert st.state == "skipped" and "does not match" in st.reason
    with pytest.raises(AppFusionError):
        gp.add_frame("not a frame")


def test_geometry_pass_without_markers(seq):
    """No marker ever visible: result() says so clearly; the uncropped model is still available."""
    gp = GeometryPass(meta={"extra": seq.meta_extra})
    for f in seq.frames[:4]:
        gp.add_frame(f.replace(ir=np.zeros_like(f.ir)))       # circles invisible
    with pytest.raises(EstimationError, match="never seen"):
        gp.result(n_points=1000)
    with pytest.raises(EstimationError):
        _ = gp.marker_to_world
    res = gp.result(n_points=1000, require_markers=False)
    assert res.box is None and len(res.mesh.triangles) > 0
    assert np.allclose(res.poses[0], np.eye(4))
    empty = GeometryPass()
    with pytest.raises(EstimationError, match="no frame could be fused"):
        empty.result()


def test_geometry_pass_lost_frames_resume():
    """The GUI's view of a loss: frames hidden by a wall are ``lost`` with the last good pose, and
    the pass resumes (relocalised on the markers) when the view returns."""
    s = make_sequence(18, 320, 240, seed=4, occluder_frames=(8, 9, 10))
    gp = GeometryPass(GeometryConfig(n_points=5000), meta={"extra": s.meta_extra})
    states = [gp.add_frame(f) for f in s.frames]
    assert [st.state for st in states[8:11]] == ["lost"] * 3
    assert all(st.ok for st in states[11:]) and all(st.ok for st in states[:8])
    assert all(st.reason for st in states[8:11])
    res = gp.result()
    assert res.lost_frames == [8, 9, 10]
    ok = [i for i, st in enumerate(states) if st.ok]
    assert _ate(res.poses[ok], s.poses[ok]) < 0.003


def test_jet_normals_only_where_the_normal_filter_stages_do_not_converge(monkeypatch):
    """``GeometryConfig.jet_radius``: the cubic fits replace the filtered normals when the filter ran
    fewer adaptive stages than configured (its convergence test stopped them: the pepper, the vase),
    and not when it ran them all (the capsules, whose filtered normals the fits would make noisier),
    nor on a mesh too coarse for the fit's disk (``jet_min_vertices``)."""
    import appfusion.geometry_pass as gpm

    s = make_sequence(10, 320, 240, seed=6)
    gp = GeometryPass(GeometryConfig(n_points=5000, jet_min_vertices=0), meta={"extra": s.meta_extra})
    for f in s.frames:
        gp.add_frame(f)
    real, sample = gpm.bilateral_filter_normals, gpm.sample_points
    first = []                       # the same points each time (Open3D's mesh extraction may reorder)
    monkeypatch.setattr(gpm, "sample_points", lambda *a, **k: first[0] if first else first.append(sample(*a, **k)) or first[0])

    def stages_run(n):
        def filt(*a, stats=None, **k):
            out = real(*a, stats=stats, **k)
            stats["stages_run"] = n
            return out
        return filt

    monkeypatch.setattr(gpm, "bilateral_filter_normals", stages_run(3))
    kept = gp.result()
    assert gp.jet_fraction is None
    monkeypatch.setattr(gpm, "bilateral_filter_normals", stages_run(1))
    jet = gp.result()
    assert gp.jet_fraction > 0.8
    assert gp.jet_residual.shape == (5000,)
    assert np.median(gp.jet_residual[np.isfinite(gp.jet_residual)]) == pytest.approx(1.0)
    assert gp.jet_fraction == pytest.approx(np.mean(gp.jet_residual <= GeometryConfig().jet_max_residual))
    assert np.array_equal(jet.points, kept.points)
    moved = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", jet.normals, kept.normals), -1, 1)))
    assert np.median(moved) > 0.01 and np.allclose(np.linalg.norm(jet.normals, axis=1), 1)
    gp.config.jet_min_vertices = GeometryConfig().jet_min_vertices   # this 4 mm mesh: ~90 in a disk
    assert np.array_equal(gp.result().normals, kept.normals) and gp.jet_fraction is None
    gp.config.jet_min_vertices, gp.config.jet_radius = 0, None
    assert np.array_equal(gp.result().normals, kept.normals) and gp.jet_fraction is None


def test_geometry_pass_reads_a_recorded_session(tmp_path):
    """Frames written with replay.session and read back (depth quantised to 1/5000 m, IR to
    10 bits, RGB to 16-bit linear) go through the geometry pass like the in-memory ones."""
    from replay.session import SessionReader, SessionWriter

    s = make_sequence(10, 320, 240, seed=6)
    K = s.intrinsics
    with SessionWriter(tmp_path / "sess", device="synthetic", intrinsics={"depth": K, "ir": K, "rgb": K},
                       depth_to_ir=np.eye(4), depth_to_rgb=s.depth_to_rgb, rgb_encoding="linear",
                       extra=s.meta_extra) as w:
        w.event(0.0, "pass", "geometry")
        for f in s.frames:
            w.write(f.replace(pose=None))
    r = SessionReader(tmp_path / "sess")
    gp = GeometryPass(GeometryConfig(n_points=5000), meta=r.meta)
    assert gp.marker_config.side_m == pytest.approx(s.side)
    states = [gp.add_frame(f) for f in r]
    assert all(st.ok for st in states) and all(st.markers_complete for st in states)
    res = gp.result()
    assert _ate(res.poses, s.poses) < 0.003


def _boundary_loops(mesh):
    """Boundary loops of a legacy mesh: (vertex count, radius of its bounding circle about the mean, m)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(mesh.triangles)
    V = np.asarray(mesh.vertices)
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    u, c = np.unique(E, axis=0, return_counts=True)
    b = u[c == 1]
    if len(b) == 0:
        return []
    A = sp.coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(len(V), len(V)))
    _, lab = connected_components(A, directed=False)
    vb = np.unique(b)
    out = []
    for L in np.unique(lab[vb]):
        P = V[vb[lab[vb] == L]]
        out.append((len(P), float(np.linalg.norm(P - P.mean(0), axis=1).max())))
    return sorted(out, key=lambda x: x[1])


def test_fill_small_holes_closes_small_holes_only():
    """Paper §6 hole cleaning: a 5 cm sphere cut open at the bottom (a 3.5 cm rim, like an object on
    the plane) with two ~5 mm holes in its top: the small holes are closed, wound like the sphere, the
    patches faired onto the sphere's curvature, the rim stays open."""
    from appfusion.geometry_pass import boundary_loops, fill_small_holes

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=60)
    V = np.asarray(mesh.vertices)
    F = np.asarray(mesh.triangles)
    cen = V[F].mean(axis=1)
    cut = cen[:, 2] < -0.035
    for d in (np.array([0.3, 0.0, 0.95]), np.array([-0.2, 0.4, 0.9])):
        d = 0.05 * d / np.linalg.norm(d)
        cut |= np.linalg.norm(cen - d, axis=1) < 0.004
    mesh.remove_triangles_by_mask(cut)
    mesh.remove_unreferenced_vertices()
    before = _boundary_loops(mesh)
    assert len(before) == 3 and before[-1][1] > 0.03 and before[1][1] < 0.008
    assert sorted(len(lp) for lp in boundary_loops(np.asarray(mesh.triangles))) == sorted(b[0] for b in before)
    out = fill_small_holes(mesh, 0.01)
    after = _boundary_loops(out)
    assert len(after) == 1 and after[0][1] > 0.03                  # only the rim is left open
    assert len(out.triangles) > len(mesh.triangles)
    # the input comes first, unchanged; the new vertices lie on the sphere (faired: within 0.1 mm,
    # the straight web to the holes' means up to 0.18 mm inside it)
    n0 = len(mesh.vertices)
    assert np.array_equal(np.asarray(out.vertices)[:n0], np.asarray(mesh.vertices))
    assert np.array_equal(np.asarray(out.triangles)[:len(mesh.triangles)], np.asarray(mesh.triangles))
    r_new = np.linalg.norm(np.asarray(out.vertices)[n0:], axis=1)
    assert len(r_new) > 10 and np.abs(r_new - 0.05).max() < 1e-4
    r_web = np.linalg.norm(np.asarray(fill_small_holes(mesh, 0.01, fair=False).vertices)[n0:], axis=1)
    assert np.abs(r_web - 0.05).mean() > 3 * np.abs(r_new - 0.05).mean()
    # the patches are wound like the sphere around them: no edge run twice the same way, every
    # triangle facing out (VTK's filler, used before, had wound 45 of them inwards)
    Fo = np.asarray(out.triangles).astype(np.int64)
    Vo = np.asarray(out.vertices)
    E = np.concatenate([Fo[:, [0, 1]], Fo[:, [1, 2]], Fo[:, [2, 0]]])
    assert len(np.unique(E[:, 0] * len(Vo) + E[:, 1])) == len(E)
    fn = np.cross(Vo[Fo[:, 1]] - Vo[Fo[:, 0]], Vo[Fo[:, 2]] - Vo[Fo[:, 0]])
    assert (np.einsum("ij,ij->i", fn, Vo[Fo].mean(axis=1)) > 0).all()
    assert fill_small_holes(mesh, 0.0) is mesh                     # switched off
    assert len(_boundary_loops(fill_small_holes(mesh, 0.002))) == 3   # holes above the radius stay
    assert len(_boundary_loops(fill_small_holes(mesh, 0.1))) == 0     # the rim too, at 10 cm ...
    kept = _boundary_loops(fill_small_holes(mesh, 0.1, keep_open_below=-0.03))
    assert len(kept) == 1 and kept[0][1] > 0.03                    # ... unless it reaches the floor
    assert boundary_loops(np.zeros((0, 3), np.int64)) == []


def test_boundary_loops_follow_the_triangles_and_split_at_a_shared_vertex():
    """Two squares of two triangles each, touching at one corner: two loops of four, each run the way
    its triangles run their edges, the shared corner in both."""
    from appfusion.geometry_pass import boundary_loops

    F = np.array([[0, 1, 2], [0, 2, 3], [2, 4, 5], [2, 5, 6]])
    loops = boundary_loops(F)
    assert sorted(len(lp) for lp in loops) == [4, 4]
    assert all(2 in lp for lp in loops)
    directed = {tuple(e) for f in F for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    for lp in loops:
        assert all((int(a), int(b)) in directed for a, b in zip(lp, np.roll(lp, -1)))


def _mesh_depth(V, F, K, eye, target):
    """Camera-to-world pose of a camera at ``eye`` looking at ``target`` (z up), and the noise-free
    depth image (NaN off the mesh) it sees of the mesh ``V, F``."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    T = make_pose(np.stack([right, np.cross(fwd, right), fwd], 1), eye)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    r = K.rays().astype(np.float64)
    dirs = (r / np.linalg.norm(r, axis=-1, keepdims=True)) @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], dirs.shape), dirs], -1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    depth = (t / np.linalg.norm(r, axis=-1)).astype(np.float32)
    depth[~np.isfinite(depth)] = np.nan
    return T, depth


def test_pose_refiner_reregisters_a_frame_to_the_final_mesh():
    """A depth frame of an ellipsoid, its pose off by ~1.6 mm and 0.25 degrees (tracking's jitter):
    re-registered to the mesh, the surface it sees moves back to within 0.2 mm (1.6 mm before); too few pixels on
    the mesh leave the pose unchanged; bad input says what is wrong."""
    from appfusion.geometry_pass import PoseRefiner

    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=60)
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * [0.05, 0.035, 0.025] + [0.0, 0.0, 0.03])
    V, F = np.asarray(m.vertices), np.asarray(m.triangles)
    K = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)
    # camera 0.4 m away looking at the ellipsoid obliquely
    T, depth = _mesh_depth(V, F, K, np.array([0.25, -0.2, 0.25]), np.zeros(3))
    rng = np.random.default_rng(0)
    depth += rng.normal(0, 0.0007, depth.shape).astype(np.float32)          # Kinect-like depth noise
    wrong = make_pose(cv2.Rodrigues(np.radians([0.15, -0.2, 0.1]))[0], [0.0008, -0.001, 0.001]) @ T

    def surface_shift(P):                  # how far the pose moves the points of the surface it sees
        pc = transform_points(invert_pose(T), V[::7])
        return np.median(np.linalg.norm(transform_points(P, pc) - V[::7], axis=1))

    ref = PoseRefiner(V, F, step=1)
    refined, pairs = ref.refine(depth, K, wrong)
    assert pairs > 1500
    assert surface_shift(wrong) > 1.2e-3 and surface_shift(refined) < 2e-4, (surface_shift(wrong), surface_shift(refined))
    # an empty view: unchanged
    same, pairs = ref.refine(np.full(K.shape, np.nan, np.float32), K, wrong)
    assert pairs == 0 and np.array_equal(same, wrong)
    with pytest.raises(AppFusionError, match="depth image"):
        ref.refine(depth[:10], K, wrong)
    with pytest.raises(AppFusionError, match="pose"):
        ref.refine(depth, K, np.eye(3))
    with pytest.raises(AppFusionError, match="non-empty mesh"):
        PoseRefiner(np.zeros((0, 3)), np.zeros((0, 3), int))


def test_pose_refiner_anchors_fix_what_the_surface_leaves_free():
    """A sphere's depth says nothing of a rotation about its centre: re-registered to the mesh alone,
    a pose turned 0.3 degrees about it stays turned; four circle centres on the plane below (anchors,
    anisotropic about the plane's normal) turn it back. Anchors alone, with no pixel on the mesh,
    still move the pose; bad anchors say what is wrong."""
    from appfusion.geometry_pass import PoseRefiner

    c = np.array([0.0, 0.0, 0.05])
    m = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=80)
    m.translate(c)
    V, F = np.asarray(m.vertices), np.asarray(m.triangles)
    K = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)
    T, depth = _mesh_depth(V, F, K, np.array([0.3, -0.25, 0.3]), c)
    # turned 0.3 degrees about the sphere's centre: the same depth, the plane's circles 0.5 mm off
    R = cv2.Rodrigues(np.radians([0.1, -0.15, 0.22]))[0]
    wrong = make_pose(R, c - R @ c) @ T
    C = np.array([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0], [0.1, -0.1, 0.0]])
    c_cam = transform_points(invert_pose(T), C)
    rng = np.random.default_rng(3)
    noisy = c_cam + rng.normal(0, 2e-5, c_cam.shape)

    def circle_shift(P):
        return np.abs(transform_points(P, c_cam) - C).max()

    assert circle_shift(wrong) > 5e-4
    ref = PoseRefiner(V, F, step=1, iterations=4, depth_weight=0.1)
    alone, _ = ref.refine(depth, K, wrong)
    assert circle_shift(alone) > 4e-4, circle_shift(alone)              # the sphere cannot tell
    anchored, pairs = ref.refine(depth, K, wrong, anchors=(noisy, C, [0, 0, 1.0]))
    assert pairs > 1000 and circle_shift(anchored) < 1e-4, circle_shift(anchored)
    # isotropic anchors (no normal) work too; anchors alone move an empty view's pose
    iso, _ = ref.refine(depth, K, wrong, anchors=(noisy, C, None))
    assert circle_shift(iso) < 1.5e-4, circle_shift(iso)
    only, pairs = ref.refine(np.full(K.shape, np.nan, np.float32), K, wrong, anchors=(noisy, C, [0, 0, 1.0]))
    assert pairs == 0 and circle_shift(only) < circle_shift(wrong)
    with pytest.raises(AppFusionError, match="anchor"):
        ref.refine(depth, K, wrong, anchors=(noisy, C[:3], None))
    with pytest.raises(AppFusionError, match="positive"):
        PoseRefiner(V, F, anchor_sigma=(0.0, 1e-4))


def test_open_boundary_points_are_those_near_the_cut_rim():
    """The points within a radius of the mesh's open boundary (a sphere cut open at the bottom, as
    the object box cuts a scan off the plane); none on a closed mesh, none with radius 0."""
    from appfusion.geometry_pass import open_boundary_points

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=60)
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    rng = np.random.default_rng(0)
    P = rng.normal(size=(4000, 3))
    P = 0.05 * P / np.linalg.norm(P, axis=1, keepdims=True)
    assert not open_boundary_points(P, V, F, 0.004).any()            # closed
    keep = V[F].mean(axis=1)[:, 2] >= -0.035
    cut = o3d.geometry.TriangleMesh(mesh)
    cut.remove_triangles_by_mask(~keep)
    cut.remove_unreferenced_vertices()
    Vc, Fc = np.asarray(cut.vertices), np.asarray(cut.triangles)
    P = P[P[:, 2] > -0.034]
    rim = open_boundary_points(P, Vc, Fc, 0.004)
    z_rim = Vc[:, 2].min()                                           # the cut's height (-0.035 or so)
    # the rim is a circle at z_rim; points within ~4 mm of it (along the sphere) are flagged
    near = P[:, 2] < z_rim + 0.0025
    far = P[:, 2] > z_rim + 0.006
    assert rim[near].all() and not rim[far].any() and near.any()
    assert not open_boundary_points(P, Vc, Fc, 0.0).any()
    assert open_boundary_points(P, Vc, np.zeros((0, 3), int), 0.004).shape == (len(P),)


def test_anchor_error_across_the_support_plane_weighs_anchor_normal_weight():
    """An anchor with the support plane's normal weighs its error along that normal by
    ``anchor_normal_weight`` and within the plane by ``anchor_weight`` (a circle centre found on the
    depth's plane is far better known across it). Depth of a fronto-parallel plane pins the motion
    along the camera's z; anchors that ask for 4 mm along z and 2 mm along x get their x in every
    case (nothing else constrains it), and the more of their z the more their normal weighs."""
    def shift(normal_weight, with_normal):
        fu = TSDFFusion(K320, FusionConfig(anchor_weight=3.0, anchor_normal_weight=normal_weight))
        K = fu.K_trk
        depth = _plane_depth(K, 0.7, 0.0)
        normals = np.zeros(depth.shape + (3,), np.float32)
        normals[..., 2] = -1.0
        src = np.array([[0.1, 0.05, 0.7], [-0.1, 0.05, 0.7], [0.0, -0.1, 0.7]])
        anchors = (src, src + [0.002, 0.0, 0.004]) + (((0.0, 0.0, 1.0),) if with_normal else ())
        T, overlap, frac, _ = fu.icp(depth, depth, normals, np.eye(4), 0.02, anchors)
        assert overlap > 0.9 and frac > 0.9
        return T[:3, 3]

    plain, same, heavy = shift(3.0, False), shift(3.0, True), shift(30.0, True)
    np.testing.assert_allclose(same, plain, atol=1e-7)         # equal weights: the isotropic term
    for t in (plain, heavy):
        assert abs(t[0] - 0.002) < 1e-4 and abs(t[1]) < 1e-4
    assert 0.0 < plain[2] < heavy[2] < 0.004
    assert heavy[2] > 2 * plain[2]


def test_anchor_information_along_a_grazing_line_of_sight():
    """With a line of sight, an anchor's in-plane error along the sight's projection on the plane
    weighs ``w_in sin^2(e)`` (e: the sight's elevation above the plane), across it ``w_in``, along
    the normal ``w_n``; a sight along the normal changes nothing; the weight has a floor."""
    from appfusion.fusion import anchor_information

    n = np.array([0.0, 0.0, 1.0])
    e = np.radians(10.0)
    sight = np.array([np.cos(e), 0.0, -np.sin(e)]) * 0.8          # camera above, looking down at 10 deg
    M = anchor_information(n, 3.0, 30.0, sight)
    np.testing.assert_allclose(M, M.T)
    np.testing.assert_allclose(M @ [1.0, 0, 0], [3.0 * np.sin(e) ** 2, 0, 0], atol=1e-12)
    np.testing.assert_allclose(M @ [0, 1.0, 0], [0, 3.0, 0], atol=1e-12)
    np.testing.assert_allclose(M @ n, 30.0 * n, atol=1e-12)
    np.testing.assert_allclose(anchor_information(n, 3.0, 30.0, -n), anchor_information(n, 3.0, 30.0), atol=1e-12)
    flat = anchor_information(n, 3.0, 30.0, [0.0, 1.0, 0.0], floor=1e-3)   # in the plane: the floor
    assert flat[1, 1] == pytest.approx(3e-3) and flat[0, 0] == pytest.approx(3.0)
    assert np.allclose(anchor_information(None, 3.0, 30.0, sight), 3.0 * np.eye(3))


def test_pose_refiner_trusts_a_grazing_circle_across_its_line_of_sight():
    """A circle seen at a grazing angle is off along its line of sight on the plane (its ellipse is thin that way):
    with sight weighting the refined pose keeps the other circles where they are; without, the one
    bad centre drags them."""
    from appfusion.geometry_pass import PoseRefiner

    c = np.array([0.0, 0.0, 0.05])
    m = o3d.geometry.TriangleMesh.create_sphere(radius=0.05, resolution=40)
    m.translate(c)
    V, F = np.asarray(m.vertices), np.asarray(m.triangles)
    K = Intrinsics(320, 240, 290.0, 290.0, 159.5, 119.5)
    T, depth = _mesh_depth(V, F, K, np.array([0.45, -0.05, 0.12]), c)          # a low view (~13 deg)
    C = np.array([[0.15, 0.15, 0.0], [-0.15, 0.15, 0.0], [-0.15, -0.15, 0.0], [0.15, -0.15, 0.0]])
    c_cam = transform_points(invert_pose(T), C)
    far = int(np.argmax(c_cam[:, 2]))                                            # the most grazing one
    along = C[far] - T[:3, 3]
    along[2] = 0.0                                                               # its sight, on the plane
    bad = c_cam.copy()
    bad[far] += T[:3, :3].T @ (0.004 * along / np.linalg.norm(along))           # 4 mm that way (camera frame)
    others = np.arange(4) != far

    def others_shift(weighting):
        ref = PoseRefiner(V, F, step=1, iterations=4, depth_weight=0.1, sight_weighting=weighting)
        P, _ = ref.refine(depth, K, T, anchors=(bad, C, [0, 0, 1.0]))
        return np.abs(transform_points(P, c_cam[others]) - C[others]).max()

    plain, weighted = others_shift(False), others_shift(True)
    assert weighted < 0.2 * plain and plain > 2e-4, (plain, weighted)


def _icosphere_mesh(radius, level, centre=(0.0, 0.0, 0.0)):
    m = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(level)
    v = np.asarray(m.vertices)
    m.vertices = o3d.utility.Vector3dVector(radius * v / np.linalg.norm(v, axis=1, keepdims=True) + centre)
    return m


def test_tight_curvature_fraction_tells_a_tight_rim_from_a_capsule():
    """The re-fusion's voxel test (GeometryConfig.refuse_fine_scale): a 1 cm sphere curves tighter
    than 2 cm everywhere, a 4 cm one nowhere, even with 20 um of radial noise on its ~2 mm mesh; a
    4 cm sphere with a 1 cm one fused onto it (a knob) has the knob's share of its vertices."""
    from appfusion.geometry_pass import tight_curvature_fraction

    big = _icosphere_mesh(0.04, 6)                   # ~1.5 mm edges, like a 3 mm TSDF's
    small = _icosphere_mesh(0.01, 4)
    assert tight_curvature_fraction(big, 0.02) == 0.0
    assert tight_curvature_fraction(small, 0.02) > 0.95
    knob = _icosphere_mesh(0.01, 4, (0.0, 0.0, 0.048))
    both = big + knob
    f = tight_curvature_fraction(both, 0.02)
    share = len(knob.vertices) / len(both.vertices)
    assert 0.5 * share < f < 1.5 * share, (f, share)
    rng = np.random.default_rng(0)
    v = np.asarray(big.vertices)
    noisy = o3d.geometry.TriangleMesh(big)
    noisy.vertices = o3d.utility.Vector3dVector(v * (1 + rng.normal(0, 5e-4, (len(v), 1))))
    assert tight_curvature_fraction(noisy, 0.02) < 0.01
    assert tight_curvature_fraction(o3d.geometry.TriangleMesh(), 0.02) == 0.0


def test_a_fast_sweep_loses_one_frame_not_every_other():
    """14 degrees a frame, over the 12-degree jump limit. Where the circles' rigid fit puts the camera
    beyond the limit from the prediction, tracking starts from it (``anchor_fit_tol_m``, session 29):
    no frame is lost. Without that (tolerance 0), the second frame is lost and relocalised on the
    circles; predicting the next frame with the motion per frame over that gap
    (``relocalise_velocity_frames``) keeps the rest tracked, and predicting no motion after each
    relocalisation lost every other frame (and the 30-frame quick matte session's environment
    pass 15 of its 30 frames)."""
    s = make_sequence(12, 320, 240, seed=1, sweep_deg=150.0)
    lost = {}
    for v, tol in ((0, 0.0), (3, 0.0), (0, 0.005), (3, 0.005)):
        gp = GeometryPass(GeometryConfig(fusion=FusionConfig(relocalise_velocity_frames=v, anchor_fit_tol_m=tol)))
        st = [gp.add_frame(f) for f in s.frames]
        lost[v, tol] = [i for i, x in enumerate(st) if x.state == "lost"]
        if v == 3:
            ok = [i for i, x in enumerate(st) if x.ok]
            rel = [invert_pose(st[0].pose) @ st[i].pose for i in ok]
            true = [invert_pose(s.poses[0]) @ s.poses[i] for i in ok]
            err = max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(rel, true))
            assert err < 0.005, f"{err * 1e3:.1f} mm"
    assert len(lost[0, 0.0]) >= 5, lost      # the old prediction: every other frame
    assert len(lost[3, 0.0]) <= 1, lost
    assert lost[0, 0.005] == lost[3, 0.005] == [], lost


def test_mean_motion_repeated_gives_the_motion_back():
    from appfusion.fusion import mean_motion

    T = np.eye(4)
    T[:3, :3], _ = cv2.Rodrigues(np.array([0.1, -0.35, 0.2]))
    T[:3, 3] = [0.03, -0.02, 0.05]
    M = mean_motion(T, 3)
    assert np.allclose(np.linalg.matrix_power(M, 3)[:3, :3], T[:3, :3], atol=1e-9)
    assert abs(rotation_angle_deg(M[:3, :3]) - rotation_angle_deg(T[:3, :3]) / 3) < 1e-9
    assert np.allclose(M[:3, 3] * 3, T[:3, 3])
    assert np.allclose(mean_motion(T, 1), T)


def test_three_circles_numbered_by_the_key_track_a_30_degree_sweep(kinect_sphere):
    """The tests' synthetic Kinect sphere, 12 frames a pass (30 degrees of orbit a frame, 320 x 240):
    its geometry frames show 3, 4, 2, 3, 3, 1, 2, 4, 2, 3, 4, 4 circles. Numbered by the key circle,
    the first frame's three circles start the marker frame and later three-circle frames pair by
    number, and so does frame 58's key circle with the one across the diagonal (with the plane's
    normal they fix its pose): all 12 frames track, within 6 mm / 0.6 degrees of the truth (11
    before the two-circle numbering). Without the numbering the marker frame waits for the fourth
    circle, ICP cannot follow 30 degrees, and only the last two frames track."""
    from scipy.spatial.transform import Rotation

    from appfusion.fusion import rotation_angle_deg
    from appfusion.pipeline import plan_passes
    from replay.session import SessionReader

    r = SessionReader(kinect_sphere)
    gt = np.loadtxt(kinect_sphere / "truth" / "groundtruth.txt")
    a, b = plan_passes(r)["geometry"]
    tracked = {}
    for numbers in (True, False):
        gp = GeometryPass(GeometryConfig(three_circle_numbers=numbers, n_points=2000), meta=r.meta)
        states = [gp.add_frame(r.frame(i)) for i in range(a, b)]
        tracked[numbers] = [st.index for st in states if st.ok and st.pose_marker is not None]
        for st in states:
            if st.ok and st.pose_marker is not None:
                truth = np.eye(4)
                truth[:3, :3] = Rotation.from_quat(gt[st.index, 4:8]).as_matrix()
                truth[:3, 3] = gt[st.index, 1:4]
                assert np.linalg.norm(st.pose_marker[:3, 3] - truth[:3, 3]) < 0.008, (numbers, st.index)
                assert rotation_angle_deg(st.pose_marker[:3, :3].T @ truth[:3, :3]) < 0.8, (numbers, st.index)
    assert [st.markers_found for st in states] == [3, 4, 2, 3, 3, 1, 2, 4, 2, 3, 4, 4]
    assert len(tracked[True]) == 12 and len(tracked[False]) <= 3, tracked


def test_a_pass_that_never_sees_one_circle_gets_its_marker_frame_from_the_other_three(kinect_sphere, monkeypatch):
    """Circle 4 hidden in every frame of the Kinect sphere's geometry pass (say, behind the object
    all along): with the key circle, three circles give the marker frame, the fourth centre inferred
    at the square's corner, kept so through the re-fusion's refit. Before, such a pass ended in "the
    four white circles were never seen together"."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    import appfusion.geometry_pass as G
    from appfusion.pipeline import plan_passes
    from replay.session import SessionReader

    r = SessionReader(kinect_sphere)
    gt = np.loadtxt(kinect_sphere / "truth" / "groundtruth.txt")

    def truth(i):
        return make_pose(Rotation.from_quat(gt[i, 4:8]).as_matrix(), gt[i, 1:4])

    real = G.detect_markers

    def detect(frame, config=None, stream=None):
        d = real(frame, config, stream)
        if d.n:
            W = transform_points(truth(frame.index), d.centers)                   # marker frame
            keep = np.linalg.norm(W - [-0.15, 0.15, 0.0], axis=1) > 0.05          # circle 4 hidden
            d = replace(d, centers=d.centers[keep], radii=d.radii[keep], pixels=d.pixels[keep], complete=False)
        return d

    monkeypatch.setattr(G, "detect_markers", detect)
    a, b = plan_passes(r)["geometry"]
    frames = [r.frame(i) for i in range(a, b)]
    gp = GeometryPass(GeometryConfig(n_points=2000), meta=r.meta)
    states = [gp.add_frame(f) for f in frames]
    assert not any(st.markers_complete for st in states)
    assert gp.tracker.inferred.tolist() == [False, False, False, True]
    assert gp.refuse(frames) >= 2 and gp.tracker.inferred[3]
    layout = np.array([[0.15, 0.15, 0], [0.15, -0.15, 0], [-0.15, -0.15, 0], [-0.15, 0.15, 0]])
    C = transform_points(invert_pose(gp.tracker.marker_to_world()), gp.tracker.centers)
    assert np.abs(C - layout).max() < 0.002
    res = gp.result()
    assert np.median(np.abs(np.linalg.norm(res.points - [0, 0, 0.07], axis=1) - 0.07)) < 0.001
    for st in states:
        if st.ok and st.pose_marker is not None:
            assert np.linalg.norm(st.pose_marker[:3, 3] - truth(st.index)[:3, 3]) < 0.003, st.index


def _three_circles_first(monkeypatch, n_frames: int) -> None:
    """Make the geometry pass's marker detection hide the leftmost of four circles in frames
    ``0 .. n_frames - 1`` (a pass that starts with three circles in view)."""
    from dataclasses import replace

    import appfusion.geometry_pass as G

    real = G.detect_markers

    def detect(frame, config=None, stream=None):
        d = real(frame, config, stream)
        if frame.index < n_frames and d.n == 4:
            keep = np.arange(4) != int(np.argmin(d.pixels[:, 0]))          # hide the leftmost circle
            d = replace(d, centers=d.centers[keep], radii=d.radii[keep], pixels=d.pixels[keep], complete=False)
        return d

    monkeypatch.setattr(G, "detect_markers", detect)


def test_a_pass_that_starts_with_three_circles_in_view_is_anchored_on_them(monkeypatch):
    """Depth of the bare plane (no object: depth cannot fix the camera's slide along it) and only
    three circles found in the first seven frames: tracking is anchored on the circles seen so far
    (unanchored, it stood still while the camera moved 43 mm a frame), and once the fourth circle
    defines the marker frame those seven frames get their marker-frame poses."""
    s = make_sequence(10, 320, 240, seed=2, sweep_deg=45.0)
    _three_circles_first(monkeypatch, 7)
    gp = GeometryPass()
    states = []
    for i, f in enumerate(s.frames):
        d = f.depth.copy()
        K = f.depth_intrinsics
        v, u = np.mgrid[0:d.shape[0], 0:d.shape[1]]
        X = np.stack([(u - K.cx) / K.fx * d, (v - K.cy) / K.fy * d, d], -1).reshape(-1, 3)
        d[transform_points(s.poses[i], X)[:, 2].reshape(d.shape) > 0.003] = np.nan     # the plane alone
        states.append(gp.add_frame(f.replace(depth=d)))
    assert [st.markers_complete for st in states] == [False] * 7 + [True] * 3
    assert all(st.ok for st in states)
    for i, st in enumerate(states):
        rel = invert_pose(states[0].pose) @ st.pose
        true = invert_pose(s.poses[0]) @ s.poses[i]
        assert np.linalg.norm(rel[:3, 3] - true[:3, 3]) < 0.005, i
        assert st.pose_marker is not None, i
        assert np.linalg.norm(st.pose_marker[:3, 3] - s.poses[i][:3, 3]) < 0.005, i


def test_frames_before_the_marker_frame_get_its_pose_only_where_their_circles_confirm_it(monkeypatch):
    """The back-filled marker-frame poses of frames tracked before the marker frame existed are
    checked against each frame's own circles: one whose tracked pose is 30 degrees off (a chain of
    poses broken by a wrong relocalisation, as on the 12-frames-a-pass synthetic Kinect sphere) gets
    none, nor does the frame without circles right after it; a frame without circles between two
    confirmed ones keeps its pose."""
    s = make_sequence(10, 320, 240, seed=2, sweep_deg=45.0)
    _three_circles_first(monkeypatch, 7)
    gp = GeometryPass()
    states = []
    for i, f in enumerate(s.frames):
        if i == 7:                                   # before the marker frame: break frame 2's pose
            R = np.eye(4)
            R[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(30.0)]))[0]
            states[2].pose = states[2].pose @ R
            states[3].detection = None
            states[5].detection = None
        states.append(gp.add_frame(f))
    assert [st.markers_complete for st in states] == [False] * 7 + [True] * 3
    assert states[2].pose_marker is None and states[3].pose_marker is None
    assert gp.backfill_rejected == 2
    for i, st in enumerate(states):
        if i not in (2, 3):
            assert st.pose_marker is not None, i
            assert np.linalg.norm(st.pose_marker[:3, 3] - s.poses[i][:3, 3]) < 0.005, i


def test_normals_of_a_far_steep_plane_need_the_footprint_threshold():
    """A plane 1.5 m away seen at 65 degrees, at tracking size (160 x 120): neighbouring pixels differ
    by ~23 mm, more than 4 voxels (16 mm), so the fixed threshold calls every pixel a discontinuity;
    with ``max_slope`` 4 (a step of 4 footprints) the normals are there and right. Near (0.5 m) the
    step is 8 mm and both give the same normals."""
    from appfusion.fusion import vertex_normals

    K = Intrinsics(160, 120, 131.25, 131.25, 79.5, 59.5)
    n_true = np.array([0.0, -np.sin(np.radians(65.0)), -np.cos(np.radians(65.0))])     # faces the camera
    rays = K.rays().reshape(-1, 3)
    for dist, fixed_kept in ((1.5, False), (0.5, True)):
        p0 = np.array([0.0, 0.0, dist])
        t = (p0 @ n_true) / (rays @ n_true)                    # ray-plane intersection, z = t
        depth = np.where(t > 0, t, np.nan).reshape(120, 160).astype(np.float32)
        fixed = vertex_normals(depth, K, max_jump=0.016, smooth_px=1.0)
        slope = vertex_normals(depth, K, max_jump=0.016, smooth_px=1.0, max_slope=4.0)
        band = (slice(50, 70), slice(2, -2))                   # the rows around the 65-degree centre
        cover = np.isfinite(slope[band][..., 0]).mean()
        assert cover > 0.95, (dist, cover)
        ang = np.degrees(np.arccos(np.clip(slope[band].reshape(-1, 3) @ n_true, -1, 1)))
        assert np.nanmedian(ang) < 0.5
        fixed_cover = np.isfinite(fixed[band][..., 0]).mean()
        assert (fixed_cover > 0.95) if fixed_kept else (fixed_cover < 0.05), (dist, fixed_cover)


def test_depth_striped_with_invalid_rows_is_fused_without_an_open3d_error():
    """Every third depth row invalid (a sensor's dropped lines): no pixel has a normal, so the
    surface volume's image (:func:`drop_grazing`) is empty. Open3D raised "No block is touched"
    from the first frame (a raw RuntimeError out of ``appfusion scan``); now the tracking volume
    takes the frame and the surface volume nothing."""
    s = make_sequence(2, 320, 240, seed=1)
    d = s.frames[0].depth.copy()
    d[::3] = np.nan
    fu = TSDFFusion(s.frames[0].depth_intrinsics, FusionConfig(voxel_size=0.004))
    res = fu.process(d)
    assert res.state == "first" and res.integrated
    assert fu.n_blocks > 0                                    # the tracking volume took the frame
    assert len(fu.extract_mesh().triangles) == 0              # the surface volume had nothing to take


@pytest.mark.parametrize("scale, word", [(1e-3, "nearer than depth_min"), (1e3, "farther than depth_max")])
def test_depth_in_the_wrong_units_is_named_in_the_reason(scale, word):
    """Depth 1000x too near (metres stored where millimetres are read) or too far (millimetres read as
    metres): the first frame's reason says where the depth lies against the working range."""
    K = K320
    d = _plane_depth(K, 0.7, 20.0) * scale
    d0 = d.copy()
    fu = TSDFFusion(K, FusionConfig())
    assert fu.f_int == 1                               # integration at the frame's own size
    r = fu.process(d)
    assert r.state == "lost" and fu.n_integrated == 0
    # the caller's frame is left as it was (the range mask NaN-ed it in place at f_int 1)
    assert np.array_equal(d, d0, equal_nan=True) and not np.shares_memory(downsample_depth(d, 1), d)
    assert r.reason.startswith("no valid depth to start the model from") and word in r.reason
    assert "depth units" in r.reason and f"{np.median(d[np.isfinite(d)]):.3g} m" in r.reason
    # a camera merely too far (2.4 m, a room) is told the working range, not asked about units
    far = FusionConfig()
    hint = depth_range_hint(_plane_depth(K, 0.7, 20.0) * 3.4, far)
    assert "farther than depth_max 1.6 m" in hint and "scanned from 0.15 to 1.6 m" in hint and "units" not in hint
    # depth in range but with too few valid pixels (a covered lens) names no units
    sparse = np.full(K.shape, np.nan, np.float32)
    sparse[:2, :2] = 0.7
    assert depth_range_hint(sparse, FusionConfig()) == "" and depth_range_hint(np.zeros(K.shape), FusionConfig()) == ""


def test_a_keyed_complete_detection_pairs_its_circles_by_number_not_through_a_stale_prediction():
    """Circles numbered by the key circle are the fused square's circles whatever the prediction says:
    with the camera 40 degrees round the table from the prediction, pairing each centre with the
    nearest fused circle through the prediction found none (checkpoint version 32)."""
    from types import SimpleNamespace

    from appfusion.markers import MarkerConfig, MarkerDetection

    mc = MarkerConfig(radius_m=0.025, key_radius_m=0.035, side_m=0.3)
    gp = GeometryPass(GeometryConfig(markers=mc))
    h = 0.15
    square = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], float)   # world = marker frame
    gp.tracker.sums[:] = square
    gp.tracker.weights[:] = 1.0
    gp.tracker.counts[:] = 1
    gp.tracker.normal_sum = np.array([0.0, 0.0, 1.0])

    def look(az_deg):
        a = np.radians(az_deg)
        eye = np.array([0.5 * np.cos(a), 0.5 * np.sin(a), 0.45])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        return make_pose(np.stack([x, np.cross(z, x), z], 1), eye)

    true, stale = look(0.0), look(40.0)
    Ti = invert_pose(true)
    det = MarkerDetection(transform_points(Ti, square), np.array([0.035, 0.025, 0.025, 0.025]), np.zeros((4, 2)),
                          Ti[:3, :3] @ [0, 0, 1.0], 0.0, True, "ir")
    gp.fusion = SimpleNamespace(predicted_pose=lambda: stale, lost=False)
    cam, world, _ = gp._anchors(det)
    np.testing.assert_allclose(world, square)                            # circle k is fused circle k
    np.testing.assert_allclose(transform_points(true, cam), square, atol=1e-12)
    # through the stale prediction every centre lands beyond the 7.5 cm a nearest pairing accepts: the
    # frame had no anchors before, and tracking, 40 degrees off, lost it
    d = np.linalg.norm(transform_points(stale, det.centers)[:, None] - square[None], axis=2)
    assert d.min(axis=1).min() > max(3 * mc.radius_m, 0.05)
