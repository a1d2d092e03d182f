"""A small ray-cast scanning sequence with ground truth, for testing and benchmarking the geometry pass.

Scene (marker frame, metres, z up): a black support plane z = 0 (albedo 0.04) with four white circles
(albedo 1.0, radius ``marker_radius``) at the corners ``(+-side/2, +-side/2)`` of a square, and an
object inside the square made of a rotated box, a sphere and a cylinder standing on the plane. A depth
camera orbits the object looking at it; the RGB camera sits ``rgb_offset`` to the side of it.

Per frame it renders, with Open3D's RaycastingScene:

- depth (float32 metres, NaN invalid) with the Kinect v1 axial noise model of Nguyen et al. (2012),
  ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2``, and dropouts at grazing angles;
- IR (float32 counts, 0..1023): the emitter at the camera lights Lambertian surfaces, ``~ cos / z^2``,
  with multiplicative speckle;
- RGB (linear float32): Lambertian shading under a directional and an ambient light, times a
  per-frame colour cast and exposure (``rgb_gain``), clipped to [0, 1].

This is the geometry pass's own test scene; the project's full synthetic scanner lives in
``replay/synth``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from .frame import Frame, Intrinsics, invert_pose, make_pose

#: Kinect v1 depth noise (Nguyen, Izadi, Lovell 2012): sigma_z = a + b (z - 0.4)^2, metres
NOISE_A, NOISE_B = 0.0012, 0.0019


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) of a camera at ``eye`` looking at
    ``target``, with image-up along ``up``. Returns a 4x4 float64 matrix."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def object_meshes() -> list[tuple[o3d.geometry.TriangleMesh, tuple[float, float, float], float]]:
    """The test object: (mesh in the marker frame, linear RGB albedo, IR albedo) per part."""
    box = o3d.geometry.TriangleMesh.create_box(0.10, 0.07, 0.06)
    box.translate([-0.05, -0.035, 0.0])
    box.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0, 0, np.deg2rad(25))), center=(0, 0, 0))
    box.translate([-0.02, 0.04, 0.0])
    sph = o3d.geometry.TriangleMesh.create_sphere(0.04, 60)
    sph.translate([0.055, -0.055, 0.04])
    cyl = o3d.geometry.TriangleMesh.create_cylinder(0.025, 0.09, 60, 4)
    cyl.translate([-0.06, -0.06, 0.045])
    return [(box, (0.6, 0.3, 0.2), 0.6), (sph, (0.2, 0.5, 0.3), 0.5), (cyl, (0.5, 0.5, 0.6), 0.55)]


@dataclass
class GeometrySequence:
    """A rendered sequence and its ground truth (all in the marker frame)."""

    frames: list[Frame]
    poses: np.ndarray                    # (F, 4, 4) true camera-to-world poses of the depth camera
    object_mesh: o3d.geometry.TriangleMesh
    visible_points: np.ndarray           # (M, 3) noiseless object surface points seen in some frame
    marker_centers: np.ndarray           # (4, 3), numbered 1..4 as in appfusion.markers
    marker_radius: float
    side: float
    box_height: float
    rgb_gain: np.ndarray                 # (F, 3) colour cast x exposure applied to each frame
    markers_visible: np.ndarray          # (F, 4) bool: circle fully visible (in view, unoccluded) in IR
    intrinsics: Intrinsics
    depth_to_rgb: np.ndarray
    meta_extra: dict = field(default_factory=dict)


def make_sequence(n_frames: int = 30, width: int = 320, height: int = 240, seed: int = 0,
                  radius: float = 0.65, elevation_deg: float = 45.0, sweep_deg: float = 60.0,
                  side: float = 0.30, marker_radius: float = 0.02, noise: float = 1.0,
                  colour_cast: bool = True, occluder_frames: tuple[int, ...] = ()) -> GeometrySequence:
    """Render a geometry-pass sequence (see the module docstring).

    Parameters
    ----------
    n_frames : int
        Number of frames; the camera sweeps ``sweep_deg`` of azimuth around the object.
    width, height : int
        Image size; intrinsics are those of a Kinect v1 (fx = fy = 525 at 640x480) scaled.
    seed : int
        Random seed of noise, speckle and colour casts.
    radius, elevation_deg : float
        Camera distance from the look-at point (metres) and elevation above the plane (degrees).
    side, marker_radius : float
        Marker square side and circle radius, metres.
    noise : float
        Multiplier of the Kinect depth noise (0 = noiseless).
    colour_cast : bool
        Apply a random per-frame colour cast and exposure drift to RGB.
    occluder_frames : tuple of int
        Frames in which the depth image is replaced by a wall 0.3 m in front of the camera
        (tracking must be lost there and resume afterwards).
    """
    rng = np.random.default_rng(seed)
    K = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5).scaled(width, height)
    parts = object_meshes()
    scene = o3d.t.geometry.RaycastingScene()
    plane = o3d.geometry.TriangleMesh.create_box(1.6, 1.6, 0.02)
    plane.translate([-0.8, -0.8, -0.02])
    plane_id = scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(plane))
    ids = {}
    obj = o3d.geometry.TriangleMesh()
    for m, rgb, ir in parts:
        m.compute_vertex_normals()
        ids[scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))] = (np.array(rgb), ir)
        obj += m
    obj.compute_vertex_normals()
    h = side / 2
    centers = np.array([[h, h, 0], [h, -h, 0], [-h, -h, 0], [-h, h, 0]], float)
    depth_to_rgb = make_pose(t=[-0.025, 0.0, 0.0])
    light = np.array([0.3, -0.4, 1.0])
    light /= np.linalg.norm(light)
    target = np.array([0.0, 0.0, 0.05])
    az0 = np.deg2rad(-90 - sweep_deg / 2)
    el = np.deg2rad(elevation_deg)
    frames, poses, gains, vis, mvis = [], [], [], [], []
    ang = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
    rays_cam = K.rays().astype(np.float64)
    rnorm = np.linalg.norm(rays_cam, axis=-1)
    for i in range(n_frames):
        az = az0 + np.deg2rad(sweep_deg) * i / max(n_frames - 1, 1)
        eye = target + radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        # a slow hand-held wobble so that the motion is not a pure planar orbit
        eye += 0.012 * np.array([np.sin(0.21 * i), np.cos(0.15 * i) - 1.0, np.sin(0.11 * i)])
        pose = look_at(eye, target + 0.008 * np.array([np.cos(0.17 * i) - 1.0, np.sin(0.13 * i), 0.0]))
        poses.append(pose)

        def cast(cam_pose):
            dirs = (rays_cam / rnorm[..., None]) @ cam_pose[:3, :3].T
            org = np.broadcast_to(cam_pose[:3, 3], dirs.shape)
            ans = scene.cast_rays(o3d.core.Tensor(np.concatenate([org, dirs], -1).astype(np.float32)))
            t = ans["t_hit"].numpy().astype(np.float64)
            gid = ans["geometry_ids"].numpy()
            nrm = ans["primitive_normals"].numpy().astype(np.float64)
            hit = np.isfinite(t)
            pts = org + dirs * np.where(hit, t, 0)[..., None]
            cosv = np.abs(np.einsum("hwc,hwc->hw", nrm, -dirs))
            return t / rnorm, hit, gid, nrm, pts, cosv

        z, hit, gid, nrm, pts, cosv = cast(pose)
        # albedos
        alb_ir = np.zeros(z.shape)
        on_plane = hit & (gid == plane_id)
        disc = np.zeros(z.shape, bool)
        for c in centers:
            disc |= on_plane & (((pts[..., 0] - c[0]) ** 2 + (pts[..., 1] - c[1]) ** 2) <= marker_radius ** 2)
        alb_ir[on_plane] = 0.04
        alb_ir[disc] = 1.0
        for g, (_, ir) in ids.items():
            alb_ir[hit & (gid == g)] = ir
        # which circles are fully visible: every pixel of the disc's ring lands on the disc
        cam_pts = []
        for c in centers:
            ring_w = c + marker_radius * ring
            pc = (ring_w - pose[:3, 3]) @ pose[:3, :3]
            uv, zc = K.project(pc)
            u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
            ok = (zc > 0) & (u >= 1) & (u < width - 1) & (v >= 1) & (v < height - 1)
            if ok.all():
                hp = pts[v, u]
                ok &= hit[v, u] & (gid[v, u] == plane_id) & (np.hypot(hp[:, 0] - c[0], hp[:, 1] - c[1]) < 1.3 * marker_radius)
            cam_pts.append(bool(ok.all()))
        mvis.append(cam_pts)
        in_obj = hit & (gid != plane_id)
        vis.append(pts[in_obj][:: max(1, int(in_obj.sum()) // 1500)])
        depth = z.copy()
        sigma = noise * (NOISE_A + NOISE_B * (z - 0.4) ** 2)
        depth = depth + rng.normal(size=z.shape) * np.where(hit, sigma, 0)
        drop = ~hit | (cosv < 0.12) | (rng.random(z.shape) < 0.01)
        depth[drop] = np.nan
        if i in occluder_frames:
            depth = np.full(z.shape, 0.3) + rng.normal(size=z.shape) * 0.001
        ir = 900.0 * alb_ir * cosv * (0.6 / np.where(hit, z, 1.0)) ** 2
        ir *= rng.gamma(16.0, 1 / 16.0, size=z.shape)              # speckle
        ir = np.clip(np.where(hit, ir, 0.0), 0, 1023)
        # RGB from the RGB camera
        rgb_pose = pose @ invert_pose(depth_to_rgb)
        _, hit_c, gid_c, nrm_c, pts_c, _ = cast(rgb_pose)
        alb = np.zeros(z.shape + (3,))
        on_plane_c = hit_c & (gid_c == plane_id)
        alb[on_plane_c] = 0.04
        for c in centers:
            d_c = on_plane_c & (((pts_c[..., 0] - c[0]) ** 2 + (pts_c[..., 1] - c[1]) ** 2) <= marker_radius ** 2)
            alb[d_c] = 1.0
        for g, (rgbc, _) in ids.items():
            alb[hit_c & (gid_c == g)] = rgbc
        n_up = np.where((nrm_c @ light)[..., None] > 0, nrm_c, nrm_c)
        shade = 0.25 + 0.55 * np.clip(n_up @ light, 0, None)
        gain = (np.array([1.0, 1.0, 1.0]) if not colour_cast else
                rng.uniform(0.5, 1.0) * np.array([rng.uniform(0.8, 1.2), 1.0, rng.uniform(0.75, 1.2)]))
        gains.append(gain)
        rgb = np.clip(alb * shade[..., None] * gain, 0, 1)
        rgb += rng.normal(size=rgb.shape) * 0.003
        frames.append(Frame(index=i, timestamp=i / 30.0, depth=depth.astype(np.float32),
                            ir=ir.astype(np.float32), rgb=np.clip(rgb, 0, 1).astype(np.float32),
                            rgb_encoding="linear", depth_intrinsics=K, ir_intrinsics=K, rgb_intrinsics=K,
                            depth_to_ir=np.eye(4), depth_to_rgb=depth_to_rgb.copy(), pose=pose.copy(),
                            pass_name="geometry"))
    extra = {"markers": {"radius_m": marker_radius, "layout": "square", "side_m": side}}
    return GeometrySequence(frames=frames, poses=np.array(poses), object_mesh=obj,
                            visible_points=np.concatenate(vis), marker_centers=centers,
                            marker_radius=marker_radius, side=side, box_height=0.30,
                            rgb_gain=np.array(gains), markers_visible=np.array(mvis), intrinsics=K, depth_to_rgb=depth_to_rgb,
                            meta_extra=extra)
