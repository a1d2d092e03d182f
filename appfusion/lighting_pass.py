"""The lighting pass (paper §4.3): mirror-ball depth -> fitted sphere -> environment map, frame by frame.

Usage, live or from a recording::

    lp = LightingPass(n=128, radius=None, box=object_box)
    for frame in depth_frames:                      # the ball's geometry (object box only)
        lp.add_depth(frame.depth, frame.depth_intrinsics, pose)
    lp.fit()                                        # robust sphere fit (appfusion.sphere_fit)
    for frame in rgb_frames:                        # calibrated linear RGB (§4.2), RGB-camera pose
        lp.add_rgb(rgb_linear, frame.rgb_intrinsics, pose @ invert_pose(frame.depth_to_rgb))
    env = lp.envmap()                               # EnvMap in the marker frame; env.save("env.npz")

or :func:`run_lighting_pass` over a seekable :class:`~appfusion.source.Source` (two sweeps: depth for the
fit, then RGB). :meth:`LightingPass.add_frame` takes whole frames in any order: RGB that arrives before the
fit is held (at most ``max_pending`` frames) and accumulated when :meth:`LightingPass.fit` runs.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from .envmap import EnvMap, EnvMapAccumulator
from .errors import AppFusionError, EstimationError, PassMissingError
from .frame import Frame, Intrinsics, invert_pose
from .sphere_fit import PointReservoir, SphereFit, fit_sphere, points_from_depth, refine_center


class LightingPass:
    """Per-frame glue of the lighting pass: collects ball points, fits the sphere, accumulates the map.

    Parameters
    ----------
    n : int
        Side of each octahedral square of the environment map (paper: 128).
    radius : float, optional
        Known ball radius (metres); then only the centre is fitted.
    box : optional
        Object box in the world (marker) frame that holds the ball: an object with
        ``contains(points)`` or ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` (metres). Depth points
        outside are ignored (the paper's object/background separation, §4.1).
    rho_mirror : float or (3,) array
        Reflectance of the mirror ball, divided out (1 = perfect mirror; see :mod:`appfusion.envmap`).
    min_cos : float
        Skip samples with ``w_o . n`` below this (grazing).
    supersample : int or "auto"
        Sub-rays per pixel side (see :meth:`EnvMapAccumulator.add_view`).
    depth_stride : int
        Back-project every ``depth_stride``-th depth pixel in each direction.
    max_points : int
        Points kept for the fit (uniform reservoir sample over all depth frames; constant memory).
    max_pending : int
        RGB frames held by :meth:`add_frame` until the sphere is fitted.
    fit_kwargs : dict, optional
        Extra arguments of :func:`appfusion.sphere_fit.fit_sphere` (``inlier_threshold_m``, ...).
    exclude_viewer_deg : float
        Skip reflections within this angle of the camera (the user's reflection); see
        :class:`~appfusion.envmap.EnvMapAccumulator`. 0 = the paper's plain weighted mean.
    per_frame_center : bool
        In :meth:`add_frame`, re-locate the ball relative to the camera from the frame's own depth
        (:func:`~appfusion.sphere_fit.refine_center`, radius fixed) before mapping its RGB. This makes the
        map insensitive to tracking error (a 2 mm / 0.3 degree pose error otherwise smears edges by several
        degrees); needs depth with the RGB (Kinect v1 depth+RGB, Azure Kinect). A frame whose ball cannot
        be located (too few depth points near it) is skipped and counted in ``n_skipped_frames``.
    """

    def __init__(self, n: int = 128, radius: float | None = None, box: Any = None, rho_mirror: Any = 1.0,
                 min_cos: float = 0.1, supersample: int | str = "auto", depth_stride: int = 2,
                 max_points: int = 200_000, max_pending: int = 32, fit_kwargs: dict[str, Any] | None = None,
                 exclude_viewer_deg: float = 0.0, per_frame_center: bool = False):
        self.radius = None if radius is None else float(radius)
        self.box = box
        self.supersample = supersample
        self.depth_stride = int(depth_stride)
        self.max_pending = int(max_pending)
        self.fit_kwargs = dict(fit_kwargs or {})
        self.acc = EnvMapAccumulator(n, rho_mirror=rho_mirror, min_cos=min_cos,
                                     exclude_viewer_deg=exclude_viewer_deg)
        self.per_frame_center = bool(per_frame_center)
        self.center_shifts_m: list[float] = []   # per-frame centre corrections applied (metres)
        self.points = PointReservoir(max_points)
        self.sphere: SphereFit | None = None
        self.n_depth_frames = 0
        self.n_rgb_frames = 0
        self.n_skipped_frames = 0     # RGB frames skipped because per-frame centring found no ball
        self._pending: list[tuple[np.ndarray, Intrinsics, np.ndarray, np.ndarray | None]] = []
        self._last_depth: np.ndarray | None = None

    # -- geometry ---------------------------------------------------------------------------------
    def add_depth(self, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray, box: Any = None) -> int:
        """Add the ball's points of one depth frame (world = marker frame); returns the number kept.

        Parameters
        ----------
        depth : (H, W) float array
            Metres, NaN where invalid.
        intrinsics : Intrinsics
            Of the depth camera.
        pose : (4, 4) array
            Camera-to-world pose of the depth camera.
        box : optional
            Overrides the pass's object box for this frame.
        """
        pts = points_from_depth(depth, intrinsics, pose, box if box is not None else self.box, self.depth_stride)
        self.points.add(pts)
        self.n_depth_frames += 1
        self._last_depth = depth        # add_frame does not add the same image twice
        return len(pts)

    def fit(self) -> SphereFit:
        """Fit the sphere to the points collected so far (paper §4.3) and flush pending RGB frames.

        Raises
        ------
        EstimationError
            No points, or a degenerate set (see :func:`appfusion.sphere_fit.fit_sphere`).
        """
        if len(self.points) == 0:
            raise EstimationError("lighting pass: no depth points of the mirror ball to fit a sphere to "
                                  f"({self.n_depth_frames} depth frames; is the object box right?)")
        kw = {"where": "lighting pass sphere fit", **self.fit_kwargs}
        self.sphere = fit_sphere(self.points.points, radius=self.radius, **kw)
        pending, self._pending = self._pending, []
        for rgb, intr, pose, mask in pending:
            self.add_rgb(rgb, intr, pose, mask)
        return self.sphere

    def set_sphere(self, center: Any, radius: float) -> None:
        """Use a known sphere (world frame, metres) instead of fitting one."""
        c = np.asarray(center, dtype=np.float64).reshape(3)
        if not (np.isfinite(c).all() and np.isfinite(radius) and radius > 0):
            raise AppFusionError(f"lighting pass: sphere centre must be finite and radius > 0, got {c}, {radius}")
        self.sphere = SphereFit(c, float(radius), 0.0, 1.0, 0, 0, radius_fixed=True)

    # -- radiance ---------------------------------------------------------------------------------
    def add_rgb(self, rgb_linear: np.ndarray, rgb_intrinsics: Intrinsics, pose_rgb: np.ndarray,
                mask: np.ndarray | None = None, center: np.ndarray | None = None) -> int:
        """Accumulate one calibrated linear RGB frame; returns the number of samples added.

        Parameters
        ----------
        rgb_linear : (H, W, 3) float array
            White-balanced linear RGB (paper §4.2).
        rgb_intrinsics : Intrinsics
            Of the RGB camera.
        pose_rgb : (4, 4) array
            Camera-to-world pose of the RGB camera (``pose @ invert_pose(depth_to_rgb)``).
        mask : (H, W) bool, optional
            Pixels allowed to contribute.
        center : (3,) array, optional
            Where this frame sees the ball (world frame, see :meth:`frame_center`); default the fitted centre.

        Raises
        ------
        EstimationError
            If the sphere has not been fitted (or set) yet.
        """
        if self.sphere is None:
            raise EstimationError("lighting pass: fit the mirror ball (fit()) before adding RGB frames")
        c = self.sphere.center if center is None else center
        n = self.acc.add_view(rgb_linear, rgb_intrinsics, pose_rgb, c, self.sphere.radius, self.supersample, mask)
        self.n_rgb_frames += 1
        return n

    def frame_center(self, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray) -> np.ndarray | None:
        """Where this depth frame sees the ball, as a world point consistent with ``pose`` (or None).

        The frame's depth points (inside the object box) are put in the world with the frame's own
        ``pose`` and the sphere is re-fitted to them with its radius fixed, starting from the fitted
        centre (:func:`~appfusion.sphere_fit.refine_center`). Mapping this frame's RGB with the result and
        the same ``pose`` takes the ball's position relative to the camera from the measurement rather
        than from the tracking. None when the frame has too few ball points.
        """
        if self.sphere is None:
            raise EstimationError("lighting pass: fit the mirror ball before locating it per frame")
        pts = points_from_depth(depth, intrinsics, pose, self.box, self.depth_stride)
        tau = float(self.fit_kwargs.get("inlier_threshold_m", 0.01))
        band = max(tau, 0.01)
        ref = refine_center(pts, self.sphere.center, self.sphere.radius, band_m=band, max_shift_m=3 * band)
        if ref is None:
            return None
        self.center_shifts_m.append(float(np.linalg.norm(ref - self.sphere.center)))
        return ref

    def add_frame(self, frame: Frame, pose: np.ndarray | None = None, rgb_linear: np.ndarray | None = None,
                  mask: np.ndarray | None = None) -> None:
        """Feed a whole frame: its depth (until the sphere is fitted; not again if that very image was just
        given to :meth:`add_depth`) and its RGB.

        Parameters
        ----------
        frame : Frame
            A frame of the ``environment`` pass.
        pose : (4, 4) array, optional
            Camera-to-world pose of the depth camera; default ``frame.pose``.
        rgb_linear : (H, W, 3) array, optional
            Calibrated RGB to use instead of ``frame.rgb_linear()`` (which is not white-balanced).
        mask : (H, W) bool, optional
            RGB pixels allowed to contribute.
        """
        pose = frame.pose if pose is None else pose
        if pose is None:
            raise AppFusionError(f"lighting pass: frame {frame.index} has no pose (track it first)")
        if frame.depth is not None and self.sphere is None and frame.depth is not self._last_depth:
            if frame.depth_intrinsics is None:
                raise AppFusionError(f"lighting pass: frame {frame.index} has depth but no depth intrinsics")
            self.add_depth(frame.depth, frame.depth_intrinsics, pose)
        if frame.rgb is not None:
            if frame.rgb_intrinsics is None:
                raise AppFusionError(f"lighting pass: frame {frame.index} has RGB but no RGB intrinsics")
            rgb = frame.rgb_linear() if rgb_linear is None else rgb_linear
            pose_rgb = np.asarray(pose, float) @ invert_pose(np.asarray(frame.depth_to_rgb, float))
            if self.sphere is not None:
                center = None
                if self.per_frame_center and frame.depth is not None and frame.depth_intrinsics is not None:
                    center = self.frame_center(frame.depth, frame.depth_intrinsics, pose)
                    if center is None:          # the ball cannot be located in this frame: skip it
                        self.n_skipped_frames += 1
                        return
                self.add_rgb(rgb, frame.rgb_intrinsics, pose_rgb, mask, center)
            elif len(self._pending) < self.max_pending:
                self._pending.append((rgb, frame.rgb_intrinsics, pose_rgb, mask))

    # -- result -----------------------------------------------------------------------------------
    def envmap(self, fill: str | None = None, meta: dict[str, Any] | None = None) -> EnvMap:
        """The environment map so far (marker frame).

        Parameters
        ----------
        fill : str, optional
            An :meth:`EnvMap.fill` method to apply, or None.
        meta : dict, optional
            Extra JSON-serialisable provenance to store (e.g. which marker set the map belongs to).
        """
        info: dict[str, Any] = {"rgb_frames": self.n_rgb_frames, "depth_frames": self.n_depth_frames,
                                "per_frame_center": self.per_frame_center,
                                "skipped_frames": self.n_skipped_frames}
        if self.center_shifts_m:
            info["per_frame_center_shift_mm"] = {"frames": len(self.center_shifts_m),
                                                 "median": 1000 * float(np.median(self.center_shifts_m)),
                                                 "max": 1000 * float(np.max(self.center_shifts_m))}
        if self.sphere is not None:
            info["sphere"] = self.sphere.to_json()
        info.update(meta or {})
        env = self.acc.envmap(info)
        return env.fill(fill) if fill else env


def run_lighting_pass(source, box: Any = None, radius: float | None = None, n: int = 128,
                      poses: Any = None, pass_name: str | None = "environment",
                      calibrate: Callable[[Frame, np.ndarray], np.ndarray] | None = None,
                      fill: str | None = None, progress: Callable[[str, int], None] | None = None,
                      **kwargs) -> tuple[EnvMap, SphereFit]:
    """Run the lighting pass over a seekable source: depth frames for the fit, then RGB frames.

    Parameters
    ----------
    source : Source
        Seekable (a recording); frames of the pass named ``pass_name`` are used (all if None).
    box : optional
        Object box holding the ball (world frame).
    radius : float, optional
        Known ball radius, metres.
    n : int
        Map side.
    poses : sequence or mapping of (4, 4) arrays, optional
        Depth-camera poses by frame index; default each frame's ``pose``.
    calibrate : callable, optional
        ``calibrate(frame, pose_rgb) -> rgb`` returning white-balanced linear RGB (§4.2); default
        ``frame.rgb_linear()``.
    fill : str, optional
        Fill method applied to the result (see :meth:`EnvMap.fill`).
    progress : callable, optional
        Called as ``progress(stage, frames_done)``.
    **kwargs
        Passed to :class:`LightingPass`.

    Returns
    -------
    (EnvMap, SphereFit)
    """
    lp = LightingPass(n=n, radius=radius, box=box, **kwargs)

    def frames():
        source.seek(0)
        for f in source:
            if pass_name is None or f.pass_name == pass_name:
                p = f.pose if poses is None else poses[f.index]
                if p is not None:
                    yield f, np.asarray(p, float)

    used = 0
    for f, pose in frames():
        if f.depth is not None and f.depth_intrinsics is not None:
            lp.add_depth(f.depth, f.depth_intrinsics, pose)
            used += 1
            if progress:
                progress("depth", used)
    if used == 0:
        raise PassMissingError(f"lighting pass: no posed depth frames in pass {pass_name!r}")
    lp.fit()
    used = 0
    for f, pose in frames():
        if f.rgb is not None and f.rgb_intrinsics is not None:
            pose_rgb = pose @ invert_pose(np.asarray(f.depth_to_rgb, float))
            rgb = calibrate(f, pose_rgb) if calibrate else f.rgb_linear()
            center = None
            if lp.per_frame_center and f.depth is not None and f.depth_intrinsics is not None:
                center = lp.frame_center(f.depth, f.depth_intrinsics, pose)
                if center is None:
                    lp.n_skipped_frames += 1
                    continue
            lp.add_rgb(rgb, f.rgb_intrinsics, pose_rgb, center=center)
            used += 1
            if progress:
                progress("rgb", used)
    if used == 0:
        raise PassMissingError(f"lighting pass: no posed RGB frames in pass {pass_name!r}")
    return lp.envmap(fill), lp.sphere
