"""Per-frame white balance and exposure from the white circles (paper §4.2).

"For each RGB image frame, we pre-process the data to compensate for potential color shift and
time-varying exposures, based on the markers ... we first map the calibrated positions of white
circles from the 3D space to the image. If one or more centers are found in the image, the
corresponding pixels are averaged to obtain a reference white pixel. We then divide every pixel in
the image by the reference white pixel on a per-channel basis."

:class:`WhiteBalancer` does exactly that on linear RGB: each circle (known centre and radius on
the support plane, marker frame) is drawn into the RGB image from the RGB camera's pose as a
polygon shrunk by ``erode`` of its radius (to stay clear of the black paper and of blur at the
edge); circles outside the image or hidden behind something nearer (checked against the depth
image) are skipped; saturated pixels and outliers are dropped; the remaining pixels of all visible
circles are averaged into the reference white, and the frame is divided by it per channel and
multiplied by ``white_level`` (the circles' known albedo; 1.0 = "white paper"). A frame where no
circle is visible keeps the last good reference and is flagged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from appfusion.errors import AppFusionError
from appfusion.frame import Frame, invert_pose, transform_points

__all__ = ["WhiteBalanceResult", "WhiteBalancer", "circle_pixel_masks"]


@dataclass
class WhiteBalanceResult:
    """The white-balanced frame and how it was balanced.

    Attributes
    ----------
    rgb : (H, W, 3) float32
        Linear RGB divided by the reference white, times ``white_level`` (not clipped).
    gain : (3,) float64
        Per-channel factor applied (``white_level / reference``); ones when no reference exists yet.
    reference : (3,) float64 or None
        Reference white used (linear RGB), None when none has been seen yet.
    circles : list of int
        Circles (0-based numbers) whose pixels made this frame's reference.
    n_pixels : int
        Pixels averaged.
    flagged : bool
        No circle was visible: the last good reference was reused (or none applied).
    """

    rgb: np.ndarray
    gain: np.ndarray
    reference: np.ndarray | None
    circles: list
    n_pixels: int
    flagged: bool


def _ring(center: np.ndarray, radius: float, normal: np.ndarray, n: int) -> np.ndarray:
    """``n`` points (n, 3) on a circle of ``radius`` about ``center``, in the plane of ``normal``."""
    nn = np.asarray(normal, float) / np.linalg.norm(normal)
    e1 = np.cross(nn, [1.0, 0.0, 0.0] if abs(nn[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nn, e1)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.asarray(center, float) + radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)


def circle_pixel_masks(centers: np.ndarray, radius: float, normal: np.ndarray, world_to_cam: np.ndarray,
                       K, shrink: float = 0.25, n_ring: int = 48) -> list[tuple[np.ndarray, tuple] | None]:
    """Pixels covered by each circle (shrunk by ``shrink`` x radius) in a camera image.

    Parameters
    ----------
    centers : (C, 3)
        Circle centres (world/marker frame, metres).
    radius : float
    normal : (3,)
        Plane normal of the circles.
    world_to_cam : (4, 4)
        World -> camera transform of the image's camera.
    K : Intrinsics
        Of the image.
    shrink : float
        Fraction of the radius removed at the edge.

    Returns
    -------
    list, per circle: None when (partly) outside the image or behind the camera, else
    ``(mask, (r0, r1, c0, c1))`` with a boolean mask of the bounding window ``[r0:r1, c0:c1]``.
    """
    ring = _ring(np.zeros(3), (1.0 - shrink) * radius, normal, n_ring)
    out = []
    for c in np.asarray(centers, float):
        pc = transform_points(world_to_cam, c + ring)
        if np.any(pc[:, 2] <= 1e-3):
            out.append(None)
            continue
        uv, _ = K.project(pc)
        if uv[:, 0].min() < 0 or uv[:, 1].min() < 0 or uv[:, 0].max() > K.width - 1 or uv[:, 1].max() > K.height - 1:
            out.append(None)
            continue
        c0, r0 = int(np.floor(uv[:, 0].min())), int(np.floor(uv[:, 1].min()))
        c1, r1 = int(np.ceil(uv[:, 0].max())) + 1, int(np.ceil(uv[:, 1].max())) + 1
        mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
        poly = np.rint((uv - [c0, r0]) * 16).astype(np.int32)      # 4 fractional bits
        cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=4)
        out.append((mask.astype(bool), (r0, r1, c0, c1)))
    return out


@dataclass
class WhiteBalancer:
    """Reference white from the marker circles, per RGB frame (paper §4.2).

    Parameters
    ----------
    centers : (C, 3) array
        Circle centres in the frame poses are given in (the marker frame), metres.
    radius : float
        Circle radius, metres.
    normal : (3,) array
        Normal of the support plane in that frame (+z in the marker frame).
    white_level : float
        Albedo the circles should read after balancing (1.0 = white paper).
    erode : float
        Fraction of the radius dropped at each circle's edge.
    saturation : float
        Pixels with any channel at or above this (linear) are dropped.
    occlusion_tol : float
        A circle is hidden when the depth image is nearer than the circle by more than this
        (metres) at its centre or ring.
    min_pixels : int
        Fewest usable pixels for a circle to count.
    min_contrast : float
        A circle counts only when its pixels are at least this many times brighter (median
        luminance) than the black paper on a ring around it (1.6 radii), where that ring is in view:
        a pose that puts the circle's outline on the paper (tracking gone wrong) would otherwise make
        the paper the reference white. A frame whose circles in view all fail is not balanced
        (``reference`` None, flagged).
    """

    centers: np.ndarray
    radius: float
    normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    white_level: float = 1.0
    erode: float = 0.25
    saturation: float = 0.98
    occlusion_tol: float = 0.02
    min_pixels: int = 6
    min_contrast: float = 3.0
    last_reference: np.ndarray | None = None
    flagged_frames: list = field(default_factory=list)

    def __post_init__(self):
        self.centers = np.asarray(self.centers, float).reshape(-1, 3)
        if not (self.radius > 0) or not (self.white_level > 0) or not (0 <= self.erode < 1):
            raise AppFusionError(f"white balance: invalid radius {self.radius}, white_level {self.white_level} "
                                 f"or erode {self.erode}")

    def _hidden(self, frame: Frame, pose: np.ndarray, c: np.ndarray) -> bool:
        """True when the depth image shows something nearer than the circle at its centre / ring."""
        if frame.depth is None or frame.depth_intrinsics is None:
            return False
        K = frame.depth_intrinsics
        pts = np.vstack([c, _ring(c, 0.7 * self.radius, self.normal, 8)])
        pc = transform_points(invert_pose(pose), pts)
        uv, z = K.project(pc)
        u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        if not ok.any():
            return False
        d = frame.depth[v[ok], u[ok]]
        nearer = np.isfinite(d) & (d < z[ok] - self.occlusion_tol)
        return bool(nearer.sum() >= 2)

    def _paper_luminance(self, rgb: np.ndarray, K, world_to_cam: np.ndarray, c: np.ndarray) -> float | None:
        """Median luminance of the paper on a ring of 1.6 radii around circle centre ``c``, or None
        when fewer than half of the ring's 24 points are in the image."""
        pc = transform_points(world_to_cam, _ring(c, 1.6 * self.radius, self.normal, 24))
        ok = pc[:, 2] > 1e-3
        if ok.sum() < 12:
            return None
        uv, _ = K.project(pc[ok])
        u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        inside = (u >= 0) & (u < K.width) & (v >= 0) & (v < K.height)
        if inside.sum() < 12:
            return None
        lum = rgb[v[inside], u[inside]].astype(np.float64).mean(axis=1)
        lum = lum[np.isfinite(lum)]
        return float(np.median(lum)) if len(lum) >= 12 else None

    def balance(self, frame: Frame, pose: np.ndarray) -> WhiteBalanceResult:
        """White-balance one frame.

        Parameters
        ----------
        frame : Frame
            With RGB, RGB intrinsics and ``depth_to_rgb`` (depth is used for the occlusion test
            when present).
        pose : (4, 4) array
            Depth camera-to-world pose in the frame of ``centers`` (the marker frame).

        Returns
        -------
        WhiteBalanceResult
        """
        if frame.rgb is None or frame.rgb_intrinsics is None:
            raise AppFusionError(f"white balance: frame {frame.index} has no RGB image with intrinsics")
        rgb = frame.rgb_linear()
        K = frame.rgb_intrinsics
        if rgb.shape[:2] != K.shape:
            raise AppFusionError(f"white balance: frame {frame.index} RGB {rgb.shape[:2]} does not match its intrinsics {K.shape}")
        pose = np.asarray(pose, float)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise AppFusionError(f"white balance: frame {frame.index} has no valid pose")
        w2c = invert_pose(pose @ invert_pose(frame.depth_to_rgb))          # world -> RGB camera
        masks = circle_pixel_masks(self.centers, self.radius, self.normal, w2c, K, shrink=self.erode)
        samples, used = [], []
        n_in_view = n_low_contrast = 0
        for i, m in enumerate(masks):
            if m is None or self._hidden(frame, pose, self.centers[i]):
                continue
            n_in_view += 1
            mask, (r0, r1, c0, c1) = m
            px = rgb[r0:r1, c0:c1][mask].astype(np.float64)
            px = px[np.all(np.isfinite(px), axis=1) & np.all(px < self.saturation, axis=1)]
            if len(px) < self.min_pixels:
                continue
            lum = px.mean(1)
            med = np.median(lum)
            if not med > 0:
                continue
            px = px[np.abs(lum - med) < 0.2 * med]          # specks, a finger on the edge, ...
            if len(px) < self.min_pixels:
                continue
            paper = self._paper_luminance(rgb, K, w2c, self.centers[i])
            if paper is not None and med < self.min_contrast * paper:
                n_low_contrast += 1                           # not a white circle there: the pose is off
                continue
            samples.append(px)
            used.append(i)
        if samples:
            allpx = np.concatenate(samples)
            ref = allpx.mean(0)
            if np.all(ref > 0):
                self.last_reference = ref
                gain = self.white_level / ref
                return WhiteBalanceResult((rgb * gain).astype(np.float32), gain, ref, used, len(allpx), False)
        self.flagged_frames.append(frame.index)
        # no reference at all when none was seen yet, or when every circle in view sits on paper (the
        # pose is wrong, and so would be this frame's use)
        if self.last_reference is None or (n_low_contrast and n_low_contrast == n_in_view):
            return WhiteBalanceResult(rgb.astype(np.float32, copy=True), np.ones(3), None, [], 0, True)
        gain = self.white_level / self.last_reference
        return WhiteBalanceResult((rgb * gain).astype(np.float32), gain, self.last_reference.copy(), [], 0, True)
