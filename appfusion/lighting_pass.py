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
from .sphere_fit import (PointReservoir, SphereFit, ball_cues_from_depth, fit_mirror_ball, fit_sphere, locate_ball,
                         points_from_depth, refine_center)


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
        In :meth:`add_frame`, re-locate the ball relative to the camera from the frame's own depth before
        mapping its RGB. This makes the map insensitive to tracking error (a 2 mm / 0.3 degree pose error
        otherwise smears edges by several degrees); needs depth with the RGB (Kinect v1 depth+RGB, Azure
        Kinect). With the mirror cues (``emitter`` given) the ball is found from its silhouette in the
        depth image (:func:`~appfusion.sphere_fit.locate_ball`); a frame where it cannot be found keeps the
        fitted centre and is counted in ``n_unlocated_frames``. Without them the frame's depth points are
        re-fitted (:func:`~appfusion.sphere_fit.refine_center`, radius fixed) and a frame whose ball cannot
        be located is skipped and counted in ``n_skipped_frames``.
    emitter : (3,) array, optional
        Position of the depth camera's emitter in the depth camera's frame (metres; session meta
        ``emitter_position_m``, Kinect v1 ``[0.075, 0, 0]``). Enables the mirror cues of
        :func:`~appfusion.sphere_fit.ball_cues_from_depth`: specular-spot points with known normals and
        silhouette rays, fitted by :func:`~appfusion.sphere_fit.fit_mirror_ball`. A mirror gives depth
        only at its specular spot (plus wrong returns behind it), so a plain sphere fit to its depth
        points comes out too small (measured: 30.2 mm for a 35 mm ball on the synthetic Kinect).
    mirror_cues : bool or "auto"
        Use the mirror cues (needs ``emitter`` and ``box``). ``"auto"``: when available, falling back to
        the plain sphere fit if the mirror fit fails (noted in ``fit_notes``); ``False``: plain fit only.
    on_plane : bool or "auto"
        Mirror fit: constrain the ball to rest on the support plane ``z = plane_z`` (see
        :func:`~appfusion.sphere_fit.fit_mirror_ball`; ``"auto"`` when the unconstrained fit agrees).
    plane_z : float
        Height of the support plane in the world frame (0 in the marker frame).
    mirror_kwargs : dict, optional
        Extra arguments of :func:`~appfusion.sphere_fit.fit_mirror_ball`.
    pixel_sigma : float, optional
        Pixel kernel of the accumulation in pixels (see :class:`~appfusion.envmap.EnvMapAccumulator`);
        None = the plain box (every sub-ray of a pixel weighs the same). 0.35 px tapers the kernel a
        little: measured on the synthetic Kinect (320x240, office), median texel error 4.2% -> 4.2%
        with 40 views and 3.3% -> 3.2% with 80, 90th percentile 1.03 -> 0.87 and 0.93 -> 0.76 (sharper
        light edges). The default 0.25 px (session 12) sharpens the lamps further: at 0.35 the demo's
        four lamps held 4-6 % less energy within two texels of their cores than the truth (spread
        around them), the paint's S on the cap came out 1.7 % low against the truth map and its rho_s
        2.6 % high (0.359 for 0.35). 0.25 / 0.15 px: rho_s 0.358 / 0.356, relit 0.050 -> 0.049 /
        0.048, median texel error 1.4 -> 1.5 / 1.9 % (noise, which the integrals of D and S average
        out; the blur they keep). With few samples per texel the noise wins: the ``--quick`` bench's
        small scan (320 x 240, 40 frames) went 4.2 -> 4.5 / 5.8 % against the 5 % goal.
    """

    def __init__(self, n: int = 128, radius: float | None = None, box: Any = None, rho_mirror: Any = 1.0,
                 min_cos: float = 0.1, supersample: int | str = "auto", depth_stride: int = 2,
                 max_points: int = 200_000, max_pending: int = 32, fit_kwargs: dict[str, Any] | None = None,
                 exclude_viewer_deg: float = 0.0, per_frame_center: bool = False, emitter: Any = None,
                 mirror_cues: bool | str = "auto", on_plane: bool | str = "auto", plane_z: float = 0.0,
                 mirror_kwargs: dict[str, Any] | None = None, pixel_sigma: float | None = 0.25):
        self.radius = None if radius is None else float(radius)
        self.box = box
        self.supersample = supersample
        self.depth_stride = int(depth_stride)
        self.max_pending = int(max_pending)
        self.fit_kwargs = dict(fit_kwargs or {})
        self.acc = EnvMapAccumulator(n, rho_mirror=rho_mirror, min_cos=min_cos,
                                     exclude_viewer_deg=exclude_viewer_deg, pixel_sigma=pixel_sigma)
        self.per_frame_center = bool(per_frame_center)
        if mirror_cues not in (True, False, "auto"):
            raise AppFusionError(f"lighting pass: mirror_cues must be True, False or 'auto', got {mirror_cues!r}")
        if emitter is not None:
            emitter = np.asarray(emitter, dtype=np.float64).reshape(-1)
            if emitter.shape != (3,) or not np.isfinite(emitter).all():
                raise AppFusionError(f"lighting pass: emitter position must be 3 finite numbers (metres), got {emitter}")
        if mirror_cues is True and emitter is None:
            raise AppFusionError("lighting pass: mirror_cues=True needs the emitter position (session meta "
                                 "emitter_position_m)")
        self.emitter = emitter
        self.mirror_cues = mirror_cues
        self.on_plane = on_plane
        self.plane_z = float(plane_z)
        self.mirror_kwargs = dict(mirror_kwargs or {})
        self.spots = PointReservoir(max_points, seed=1, dim=6)
        self.rays = PointReservoir(max_points, seed=2, dim=7)
        self.fit_notes: list[str] = []
        self.center_shifts_m: list[float] = []   # per-frame centre corrections applied (metres)
        self.points = PointReservoir(max_points)
        self.sphere: SphereFit | None = None
        self.n_depth_frames = 0
        self.n_rgb_frames = 0
        self.n_skipped_frames = 0     # RGB frames skipped because per-frame centring found no ball
        self.n_unlocated_frames = 0   # RGB frames mapped with the fitted centre (silhouette not found)
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
        box = box if box is not None else self.box
        pts = points_from_depth(depth, intrinsics, pose, box, self.depth_stride)
        self.points.add(pts)
        if self._cues_possible(box):
            cues = ball_cues_from_depth(depth, intrinsics, pose, box, self.emitter)
            self.spots.add(cues.spots)
            self.rays.add(cues.rays)
        self.n_depth_frames += 1
        self._last_depth = depth        # add_frame does not add the same image twice
        return len(pts)

    def _cues_possible(self, box: Any = None) -> bool:
        return self.mirror_cues is not False and self.emitter is not None and (box if box is not None else self.box) is not None

    def fit(self) -> SphereFit:
        """Fit the sphere to the depth collected so far (paper §4.3) and flush pending RGB frames.

        With the mirror cues (see the class parameters) :func:`~appfusion.sphere_fit.fit_mirror_ball`;
        else, or when that fails with ``mirror_cues="auto"``, the plain robust sphere fit of the depth
        points (:func:`~appfusion.sphere_fit.fit_sphere`).

        Raises
        ------
        EstimationError
            No points, or a degenerate set (see :func:`appfusion.sphere_fit.fit_sphere`).
        """
        sphere = None
        if self._cues_possible() and (len(self.spots) or len(self.rays)):
            kw = {"where": "lighting pass mirror-ball fit", "on_plane": self.on_plane, "plane_z": self.plane_z,
                  **self.mirror_kwargs}
            try:
                sphere = fit_mirror_ball(self.spots.points, self.rays.points, radius=self.radius, **kw)
            except EstimationError as e:
                if self.mirror_cues is True:
                    raise
                self.fit_notes.append(f"mirror-ball fit failed ({e}); plain sphere fit of the depth points used")
        if sphere is None:
            if len(self.points) == 0:
                raise EstimationError("lighting pass: no depth points of the mirror ball to fit a sphere to "
                                      f"({self.n_depth_frames} depth frames; is the object box right?)")
            kw = {"where": "lighting pass sphere fit", **self.fit_kwargs}
            sphere = fit_sphere(self.points.points, radius=self.radius, **kw)
        self.sphere = sphere
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

        With the mirror cues: the ball's silhouette in this depth image, put in the world with the frame's
        own ``pose``, re-locates the ball (radius fixed; :func:`~appfusion.sphere_fit.locate_ball`).
        Without them: the frame's depth points (inside the object box) are re-fitted with the radius fixed,
        starting from the fitted centre (:func:`~appfusion.sphere_fit.refine_center`). Mapping this frame's
        RGB with the result and the same ``pose`` takes the ball's position relative to the camera from
        the measurement rather than from the tracking. None when the frame does not show enough of the
        ball.
        """
        if self.sphere is None:
            raise EstimationError("lighting pass: fit the mirror ball before locating it per frame")
        if self._cues_possible():
            cues = ball_cues_from_depth(depth, intrinsics, pose, self.box, self.emitter,
                                        near=(self.sphere.center, self.sphere.radius))
            ref = locate_ball(cues.rays, self.sphere.center, self.sphere.radius)
            if ref is not None:
                self.center_shifts_m.append(float(np.linalg.norm(ref - self.sphere.center)))
            return ref
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
                    center, skip = self._center_or_skip(frame.depth, frame.depth_intrinsics, pose)
                    if skip:                    # the ball cannot be located in this frame: skip it
                        return
                self.add_rgb(rgb, frame.rgb_intrinsics, pose_rgb, mask, center)
            elif len(self._pending) < self.max_pending:
                self._pending.append((rgb, frame.rgb_intrinsics, pose_rgb, mask))

    def _center_or_skip(self, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray
                        ) -> tuple[np.ndarray | None, bool]:
        """Per-frame centre and whether to skip the frame (see ``per_frame_center``)."""
        center = self.frame_center(depth, intrinsics, pose)
        if center is not None:
            return center, False
        if self._cues_possible():
            self.n_unlocated_frames += 1        # keep the fitted centre (the tracking's prediction)
            return None, False
        self.n_skipped_frames += 1
        return None, True

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
                                "skipped_frames": self.n_skipped_frames,
                                "unlocated_frames": self.n_unlocated_frames,
                                "mirror_cues": bool(self._cues_possible())}
        if self.fit_notes:
            info["fit_notes"] = list(self.fit_notes)
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
                center, skip = lp._center_or_skip(f.depth, f.depth_intrinsics, pose)
                if skip:
                    continue
            lp.add_rgb(rgb, f.rgb_intrinsics, pose_rgb, center=center)
            used += 1
            if progress:
                progress("rgb", used)
    if used == 0:
        raise PassMissingError(f"lighting pass: no posed RGB frames in pass {pass_name!r}")
    return lp.envmap(fill), lp.sphere
