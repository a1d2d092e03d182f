"""Tests of appfusion.points: sampling, bilateral normal filter, pixel-to-point registration (§4.1)."""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from appfusion.errors import AppFusionError
from appfusion.frame import Intrinsics, invert_pose, make_pose, transform_points
from appfusion.points import PointGrid, mean_spacing, register_pixels

K640 = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)


def _raycast_depth(mesh: o3d.geometry.TriangleMesh, K: Intrinsics, pose: np.ndarray) -> np.ndarray:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    r = K.rays().astype(np.float64)
    n = np.linalg.norm(r, axis=-1)
    dirs = (r / n[..., None]) @ pose[:3, :3].T
    org = np.broadcast_to(pose[:3, 3], dirs.shape)
    t = scene.cast_rays(o3d.core.Tensor(np.concatenate([org, dirs], -1).astype(np.float32)))["t_hit"].numpy()
    depth = (t / n).astype(np.float32)
    depth[~np.isfinite(depth)] = np.nan
    return depth


@pytest.fixture(scope="module")
def sphere_scene():
    mesh = o3d.geometry.TriangleMesh.create_sphere(0.1, 80)
    mesh.compute_vertex_normals()
    pc = mesh.sample_points_uniformly(60000, use_triangle_normal=False)
    P = np.asarray(pc.points)
    N = P / np.linalg.norm(P, axis=1, keepdims=True)
    # camera 0.5 m away on -z of a rotated world, looking at the origin
    R = o3d.geometry.get_rotation_matrix_from_xyz((0.3, -0.2, 0.1))
    pose = make_pose(R, R @ np.array([0.0, 0.0, -0.5]))
    depth = _raycast_depth(mesh, K640, pose)
    return P, N, pose, depth


def test_mean_spacing_matches_area_per_point(sphere_scene):
    P = sphere_scene[0]
    expected = np.sqrt(4 * np.pi * 0.1 ** 2 / len(P))
    assert mean_spacing(P) == pytest.approx(expected, rel=0.08)


def test_register_pixels_matches_bruteforce(sphere_scene):
    P, N, pose, depth = sphere_scene
    pix, pt = register_pixels(P, N, depth, K640, pose)
    grid = PointGrid(P, N)
    assert pix.dtype == np.int64 and pt.shape == pix.shape
    assert np.all(np.diff(pix) > 0)
    valid = np.flatnonzero(np.isfinite(depth.ravel()))
    assert len(valid) > 20000
    Xw = transform_points(pose, K640.backproject(depth).reshape(-1, 3))
    d_ret = np.linalg.norm(Xw[pix] - P[pt], axis=1)
    assert d_ret.max() <= grid.max_dist * (1 + 1e-5)
    # against the exact nearest neighbour
    tree = cKDTree(P)
    d_ex, i_ex = tree.query(Xw[valid])
    near = valid[d_ex <= 0.7 * grid.max_dist]
    assert np.isin(near, pix).mean() > 0.995
    d_ex_at = tree.query(Xw[pix])[0]
    assert np.all(d_ret <= d_ex_at + grid.cell * np.sqrt(3) + 1e-6)
    assert np.median(d_ret) < 1.3 * np.median(d_ex_at)
    # the registered fraction of the object's pixels (0.1 m sphere, ~1.3 mm spacing)
    assert len(pix) / len(valid) > 0.97


def test_register_pixels_rejects_backfacing_and_far_points(sphere_scene):
    P, N, pose, depth = sphere_scene
    # flip all normals: every point faces away from the camera -> nothing registers (but for the
    # silhouette, where n . v is 0 up to rounding)
    pix, _ = register_pixels(P, -N, depth, K640, pose)
    assert len(pix) <= 5
    # without normals, every pixel registers again
    assert len(register_pixels(P, None, depth, K640, pose)[0]) > 20000
    # depth pushed 2 cm behind the surface -> no pixel is within max_dist
    pix, _ = register_pixels(P, N, depth + 0.02, K640, pose)
    assert len(pix) == 0
    # a camera looking away sees nothing of the grid
    away = pose @ make_pose(o3d.geometry.get_rotation_matrix_from_xyz((0, np.pi, 0)))
    assert len(register_pixels(P, N, depth, K640, away)[0]) == 0


def test_register_pixels_respects_pose_translation(sphere_scene):
    P, N, pose, depth = sphere_scene
    shift = make_pose(t=[0.03, -0.01, 0.02])
    # the same image and the points moved by `shift`, camera moved by `shift`: same registration
    a = register_pixels(P, N, depth, K640, pose)
    P2 = transform_points(shift, P)
    b = register_pixels(P2, N, depth, K640, shift @ pose)
    assert np.array_equal(a[0], b[0])
    assert np.mean(a[1] == b[1]) > 0.99
    assert np.allclose(invert_pose(invert_pose(pose)), pose)


def test_register_pixels_speed_full_frame():
    # a plane filling the whole 640x480 frame: the worst case (every pixel is a query)
    mesh = o3d.geometry.TriangleMesh.create_box(0.8, 0.6, 0.01)
    mesh.translate([-0.4, -0.3, 0.6])
    pc = mesh.sample_points_uniformly(200000)
    P = np.asarray(pc.points)
    P = P[P[:, 2] < 0.6 + 1e-4]
    N = np.tile([0.0, 0.0, -1.0], (len(P), 1))
    depth = _raycast_depth(mesh, K640, np.eye(4))
    register_pixels(P, N, depth, K640, np.eye(4))          # builds the grid
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        pix, _ = register_pixels(P, N, depth, K640, np.eye(4))
        times.append(time.perf_counter() - t0)
    assert len(pix) > 0.99 * np.isfinite(depth).sum()
    # measured ~9.5 ms on an idle core; generous bound for a loaded CI machine
    assert np.median(times) < 0.040, f"register_pixels took {np.median(times) * 1e3:.1f} ms per frame"


def test_register_pixels_bad_input(sphere_scene):
    P, N, pose, depth = sphere_scene
    with pytest.raises(AppFusionError, match="shape"):
        register_pixels(P[:, :2], None, depth, K640, pose)
    with pytest.raises(AppFusionError, match="do not match"):
        register_pixels(P, N[:10], depth, K640, pose)
    with pytest.raises(AppFusionError, match="intrinsics"):
        register_pixels(P, N, depth[:100], K640, pose)
    with pytest.raises(AppFusionError, match="pose"):
        register_pixels(P, N, depth, K640, np.full((4, 4), np.nan))
    bad = P.copy()
    bad[5] = np.nan
    with pytest.raises(AppFusionError, match="NaN"):
        register_pixels(bad, N, depth, K640, pose)
