"""Cameras and hand-held camera paths of the synthetic scanner.

Camera model (Kinect v1 as in the paper §7, OpenCV axes x right, y down, z forward):

- depth camera = IR camera: 640 x 480, fx = fy = 580, principal point at the image centre;
  ``depth_to_ir`` is the identity;
- RGB camera: 640 x 480, fx = fy = 525, 2.5 cm beside the IR camera: ``depth_to_rgb`` is a pure
  translation (-0.025, 0, 0) (a point's RGB-frame coordinates are its depth-frame coordinates minus
  2.5 cm in x, so the RGB camera centre is at x = +2.5 cm in the depth frame);
- IR emitter at (0.075, 0, 0) in the depth frame (paper §5.1: 7.5 cm baseline).

Other output sizes scale the intrinsics (``Intrinsics.scaled``).

Paths (``orbit_path``): what a person does when walking the Kinect around an object on a table -
an orbit about the object's centre at 0.4-1.0 m (default 0.6 m) whose azimuth advances steadily, whose
elevation drifts slowly between 15 and 60 degrees and whose distance breathes by +-8%, looking at the
object, with hand shake: smooth random rotation (~0.4 degrees rms) and translation (~2 mm rms) made of
a few random sinusoids between 0.3 and 3 Hz, and a slow roll of a few degrees. Frames are 1/30 s apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from appfusion.errors import AppFusionError
from appfusion.frame import Intrinsics, make_pose

FPS = 30.0
NATIVE_SIZE = (640, 480)
EMITTER_POSITION_M = (0.075, 0.0, 0.0)
RGB_OFFSET_M = (-0.025, 0.0, 0.0)


def depth_intrinsics(width: int = 640, height: int = 480) -> Intrinsics:
    """Kinect v1 depth/IR camera (fx = fy = 580 at 640 x 480), scaled to ``width`` x ``height``."""
    return Intrinsics(640, 480, 580.0, 580.0, 319.5, 239.5).scaled(width, height)


def rgb_intrinsics(width: int = 640, height: int = 480) -> Intrinsics:
    """Kinect v1 RGB camera (fx = fy = 525 at 640 x 480), scaled to ``width`` x ``height``."""
    return Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5).scaled(width, height)


def depth_to_rgb() -> np.ndarray:
    """Extrinsics depth -> RGB: translation (-0.025, 0, 0) m."""
    return make_pose(t=RGB_OFFSET_M)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) of a camera at ``eye`` looking at ``target`` with ``up`` up."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    nx = np.linalg.norm(x)
    if nx < 1e-9:
        raise AppFusionError("look_at: viewing direction is parallel to 'up'")
    x /= nx
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(axis, dtype=np.float64) * angle).as_matrix()


def smooth_noise(rng: np.random.Generator, t: np.ndarray, dims: int, rms: float, fmin: float = 0.3,
                 fmax: float = 3.0, n_terms: int = 6) -> np.ndarray:
    """Smooth random signals (len(t), dims) of about ``rms`` standard deviation: sums of ``n_terms``
    sinusoids with random frequencies in [fmin, fmax] Hz (log-uniform), phases and 1/f amplitudes."""
    out = np.zeros((len(t), dims))
    for d in range(dims):
        f = np.exp(rng.uniform(np.log(fmin), np.log(fmax), n_terms))
        a = 1.0 / f
        a *= rms * np.sqrt(2.0) / np.sqrt(np.sum(a * a))
        ph = rng.uniform(0, 2 * np.pi, n_terms)
        out[:, d] = np.sum(a * np.sin(2 * np.pi * f * t[:, None] + ph), axis=1)
    return out


@dataclass
class PathParams:
    """Parameters of one hand-held orbit (all recorded in ``scene.json``)."""

    radius_m: float = 0.6
    radius_breathing: float = 0.08
    elev_min_deg: float = 15.0
    elev_max_deg: float = 60.0
    sweep_deg: float = 360.0
    target_height_m: float = 0.07
    shake_rot_deg: float = 0.4
    shake_trans_m: float = 0.002
    roll_deg: float = 3.0

    def to_json(self) -> dict:
        return dict(self.__dict__)


def orbit_path(n: int, seed: int, params: PathParams | None = None, t0: float = 0.0):
    """Poses of a hand-held orbit of ``n`` frames.

    Returns
    -------
    times : (n,) float64 seconds (``t0 + i / 30``)
    poses : (n, 4, 4) float64 camera-to-world poses of the depth camera (marker frame)
    """
    p = params or PathParams()
    if not 0.3 <= p.radius_m <= 2.0:
        raise AppFusionError(f"orbit radius must be within 0.3-2.0 m, got {p.radius_m}")
    rng = np.random.default_rng(seed)
    i = np.arange(n, dtype=np.float64)
    t = i / FPS
    s = i / max(n, 1)
    az0 = rng.uniform(0, 2 * np.pi)
    az = az0 + np.radians(p.sweep_deg) * s * rng.choice([-1.0, 1.0])
    mid = 0.5 * (p.elev_min_deg + p.elev_max_deg)
    amp = 0.5 * (p.elev_max_deg - p.elev_min_deg)
    ph = rng.uniform(0, 2 * np.pi)
    elev = np.radians(mid + amp * np.sin(2 * np.pi * s + ph))
    rad = p.radius_m * (1 + p.radius_breathing * np.sin(2 * np.pi * 1.5 * s + rng.uniform(0, 2 * np.pi)))
    target = np.array([0.0, 0.0, p.target_height_m]) + smooth_noise(rng, t, 3, 0.008, 0.05, 0.3, 3)
    eye = target + rad[:, None] * np.stack([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)], -1)
    shake_r = np.radians(smooth_noise(rng, t, 3, p.shake_rot_deg))
    shake_t = smooth_noise(rng, t, 3, p.shake_trans_m)
    roll = np.radians(p.roll_deg) * np.sin(2 * np.pi * 0.7 * s + rng.uniform(0, 2 * np.pi))
    poses = np.zeros((n, 4, 4))
    for k in range(n):
        P = look_at(eye[k] + shake_t[k], target[k])
        R = P[:3, :3] @ _rot([0, 0, 1], roll[k]) @ _rot(shake_r[k] / max(np.linalg.norm(shake_r[k]), 1e-12),
                                                        np.linalg.norm(shake_r[k]))
        P[:3, :3] = R
        poses[k] = P
    return t0 + t, poses


def fronto_parallel_poses(distances, frames_each: int, seed: int, t0: float = 0.0, shake_deg: float = 0.3):
    """Poses for the IR calibration sheet (§6): the camera faces the sheet plane y = 0 (normal -y)
    from ``distance`` metres, with a little hand shake; camera centre at (0, -d, 0.5).

    Returns times (N,), poses (N, 4, 4), distances per frame (N,).
    """
    rng = np.random.default_rng(seed)
    d = np.repeat(np.asarray(distances, dtype=np.float64), frames_each)
    n = len(d)
    t = t0 + np.arange(n) / FPS
    shake = np.radians(smooth_noise(rng, t - t0, 3, shake_deg))
    poses = np.zeros((n, 4, 4))
    for k in range(n):
        P = look_at([0.0, -d[k], 0.5], [0.0, 0.0, 0.5])
        a = np.linalg.norm(shake[k])
        P[:3, :3] = P[:3, :3] @ _rot(shake[k] / max(a, 1e-12), a)
        poses[k] = P
    return t, poses, d
