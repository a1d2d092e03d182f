"""The geometry pass (paper §4.1): tracking + TSDF fusion, markers and object box, sampled points.

:class:`GeometryPass` consumes the frames of a ``geometry`` (or ``scan``) pass one at a time::

    gp = GeometryPass(meta=reader.meta)
    for frame in reader:
        state = gp.add_frame(frame)        # tracking state for the GUI: ok / lost, pose, markers
    res = gp.result()                      # mesh in the box, 100k points + normals, poses, marker frame

Per frame it detects the four white circles (:mod:`appfusion.markers`), tracks the depth frame
against the fused model with the detected circle centres as anchors once their world positions
are known (:mod:`appfusion.fusion`), integrates it, and adds the detection to the running mean of
the circle centres. The fusion's world frame is the first camera; as soon as one frame shows all
four circles the marker frame is defined, the volume is limited to the object box (plus a margin),
and :meth:`GeometryPass.result` expresses everything in the marker frame (``docs/conventions.md``).

Bad input does not raise from :meth:`add_frame`: a frame without depth, with all-NaN depth, out of
order or of the wrong size is reported (``state = "skipped"`` and a reason) and ignored.
:meth:`result` raises a clear :class:`~appfusion.errors.EstimationError` when no frame ever showed
the markers (use ``require_markers=False`` for the uncropped model in the first camera's frame).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d

from .errors import AppFusionError, EstimationError
from .frame import Frame, Intrinsics, invert_pose, transform_points
from .fusion import (FusionConfig, TSDFFusion, _skew, _twist_to_pose, anchor_information, blas_threads,
                     downsample_depth, kabsch, voxel_size_for_box)
from .markers import (MarkerConfig, MarkerDetection, MarkerTracker, ObjectBox, detect_markers,
                      marker_config_from_meta)
from .points import (PointGrid, bilateral_filter_normals, jet_normals, sample_points, sharpen_creases,
                     snap_planes)

__all__ = ["GeometryConfig", "FrameState", "GeometryResult", "GeometryPass", "PoseRefiner", "tight_curvature_fraction"]


@dataclass
class GeometryConfig:
    """Settings of the geometry pass.

    Attributes
    ----------
    fusion : FusionConfig, optional
        Tracking/fusion settings; ``voxel_size`` is replaced by :func:`voxel_size_for_box` of the
        object box unless ``fixed_voxel`` is set.
    fixed_voxel : bool
        Keep ``fusion.voxel_size`` as given.
    markers : MarkerConfig, optional
        Default: from the session meta, else :class:`MarkerConfig` defaults.
    marker_stream : {"ir", "rgb"} or None
        Image to find the circles in; default IR when the frame has it.
    box_height : float
        Height of the object box above the plane, metres (paper: "a pre-defined size").
    box_z_min : float or None
        Lowest kept height (drops the plane); default max(4 mm, one voxel).
    roi_margin : float
        Margin around the box (and circles) within which depth is fused, metres.
    use_anchors : bool
        Use detected circle centres as tracking anchors.
    three_circle_numbers : bool
        With a key circle, number three circles by it (:func:`appfusion.markers.number_three`): they
        start the marker frame before a frame shows all four, and they pair with the fused circles
        by number rather than through the predicted pose; so does the key circle with the one
        across the diagonal (:func:`appfusion.markers.number_two`), which with the plane's normal
        fixes a pose (default; beyond the paper).
    n_points : int
        Points sampled on the object's surface (paper: 100k).
    bilateral_sigma_s : float or None
        Spatial sigma of the normal filter, metres; default 1 voxel. At 4 mm voxels on the test scene,
        0.75 voxel measured best of 2-6 mm (median normal error 2.3 deg against 3.1 unfiltered). On
        the demo at 3 mm voxels, 1 voxel with 64 neighbours and 3 iterations gave 1.12 deg against
        1.27 deg for 0.75 voxel, 32 neighbours and 2 iterations; rho_d 3.1 % against 3.4 %.
    bilateral_sigma_n : float
        Normal-difference sigma of the normal filter.
    bilateral_iterations : int
    bilateral_k : int
        Neighbours per point of the normal filter (a random subset: the filter is a Monte Carlo
        estimate of its weighted mean). The demo's relit error, same geometry, four point samplings:
        0.051-0.065 at 64, 0.050-0.058 at 128, 0.048-0.055 at 256 (the filter 6 / 12 / 28 s).
    bilateral_adaptive_stages, bilateral_adaptive_c : tuple of int, float
        Further filter passes that each point takes only while they move it no more than noise moves
        points elsewhere (:func:`appfusion.points.bilateral_filter_normals`, ``adaptive_stages``):
        smooths more where the surface allows it. () keeps the ``bilateral_iterations`` passes alone.
        (3, 6, 12) since session 13 ((3, 6) before): normals' median on three capsule scans
        0.109 / 0.113 / 0.107 -> 0.088 / 0.093 / 0.093 deg, relit 0.063 / 0.044 / 0.059 ->
        0.049 / 0.045 / 0.060 (the same points and appearance re-filtered), ~10 s more.
    bilateral_adaptive_converge : float or None
        The stages run only while the filter's median move per pass shrinks below this fraction of
        the previous one (``adaptive_converge`` of the filter; session 14). On surfaces whose normal
        varies non-linearly over the kernel everywhere the stages drifted: the pepper's normals
        0.93 deg after the three passes, 4.6 deg after the stages; the vase's 1.11 -> 0.35 deg with the
        test, the capsules' unchanged (their stages' rates fall to 0.4-0.5 of the previous).
    crease_radius_voxels : float or None
        After the normal filter, points near a sharp crease take the normal of a one-sided plane fit
        (:func:`appfusion.points.sharpen_creases`, radius this many voxels; session 17). None: off.
    plane_snap : bool
        Then the points on large planar faces, up to their rounded edges, take the face's plane normal
        (:func:`appfusion.points.snap_planes`; session 26). The vase's lid; none on the capsules,
        the sphere or the pepper.
    refuse_voxel_scale : float
        Voxel of :meth:`GeometryPass.refuse`'s fresh TSDF as a fraction of tracking's (the scan
        passes ``ScanConfig.refuse_voxel_scale``, 1 by default); the normal filter's width follows it.
    refuse_fine_scale : float or None
        Voxel scale of that re-fusion where the object curves tightly (session 17), used when
        ``refuse_voxel_scale`` is 1: if at least ``refuse_fine_fraction`` of the first mesh's
        vertices have a principal radius of curvature below ``refuse_fine_radius_voxels`` voxels
        (:func:`tight_curvature_fraction`), the re-fusion's voxel is scaled by it. A 3 mm TSDF rounds
        a rim or a dimple off, where the sun's glints sit; on the capsules (radius 4 cm, no vertex
        under 34 mm) a finer voxel only adds noise. None: never.
    refuse_fine_radius_voxels, refuse_fine_fraction : float, float
        See ``refuse_fine_scale``.
    refuse_trunc_voxels : float or None
        Truncation of that re-fusion, in its voxels (None, the default: tracking's
        ``FusionConfig.trunc_voxels``, 4, or ``refuse_fine_trunc_voxels`` where the object curves
        tightly). A ray that hits an overhanging edge (a lid's rim seen from above) writes "behind
        the surface" into the free space under the edge for a truncation's length along the ray, and
        the views that see that space are few: the vase's neck bulged out 1.5-2.4 mm over the 10 mm
        below its lid at 4 voxels, 0.15-0.4 mm at 2 (session 17). 2 everywhere is not the default:
        seed 3's relit error rose 0.057 -> 0.066 (docs/geometry-pass.md).
    refuse_fine_trunc_voxels : float or None
        The re-fusion's truncation where ``refuse_fine_scale`` applies (the object curves tightly;
        never on the capsules) and at least ``refuse_fine_trunc_min_frames`` frames are re-fused,
        unless ``refuse_trunc_voxels`` is given (session 26; default 2 since session 30; None:
        tracking's 4). At 2 the vase's neck no longer bulges below its lid (its normals 2-6 mm below
        the lid 10-18 -> 2.5-3.6 degrees). Session 30, 200 frames a pass, 4 -> 2 voxels: vase relit
        0.134 -> 0.115, pepper 0.200 -> 0.197 and its rho_d 3.06 -> 2.87 %.
    refuse_fine_trunc_min_frames : int
        Frames the re-fusion must integrate for ``refuse_fine_trunc_voxels`` to apply (default 60):
        a TSDF truncated at 2 voxels averages each voxel over fewer depth samples, and a few noisy
        frames are also what makes the fine re-fusion trigger on noise: the tests' 12-frame Kinect
        sphere (3.0 % of the first mesh of a 7 cm sphere "curves tightly") read its IR alpha 0.180
        for 0.12 at 2 voxels.
    min_component : float
        Connected mesh pieces inside the box with fewer triangles than this fraction of the largest
        are dropped (flying fragments).
    jet_radius : float or None
        Where the normal filter's adaptive stages stop converging (``bilateral_adaptive_converge``:
        the normal varies non-linearly over the kernel all over the object, e.g. the pepper's lobes,
        so the filter keeps only its first passes and the fused surface's noise with them), the
        normals are refitted as cubic height fields to the mesh's vertices within this radius,
        metres (:func:`appfusion.points.jet_normals`; session 32), before creases and planes are
        sharpened. 200 frames a pass at 2 mm voxels, end to end: pepper normals 0.47 -> 0.29
        degrees (median), relit 0.129 -> 0.0755; vase 0.29 -> 0.26 degrees, relit 0.133 -> 0.128.
        On the capsules the filter's stages converge and the fits are not made (there they are
        noisier than the filter: demo 0.078 -> 0.31 degrees). None: off.
    jet_min_vertices : int
        The fits are made only where a fit's disk holds at least this many of the mesh's vertices
        (their density times ``pi jet_radius^2``): 312 on the pepper and the vase at 2 mm voxels;
        the geometry bench's 4 mm scene holds 88, and there the fits were noisier than the filter
        (median 1.20 -> 1.35 degrees).
    jet_degree : int
        Degree of those height fields (3: the odd terms that bias a quadric's slope are fitted).
    jet_max_residual : float
        Points whose fit leaves an RMS residual over this multiple of the median keep the filter's
        normal (a rim or crease within ``jet_radius``).
    hole_radius : float
        Holes of the fused mesh up to this radius (metres: the largest distance of the hole's rim from
        its mean) are closed (paper §6: "we then clean holes in the mesh"; :func:`fill_small_holes`);
        0 keeps them. The open rim where the object meets the plane stays open whatever its size (it
        reaches down to the object box's floor). 2 cm (session 31; 1 cm before): the vase's flared
        neck, re-fused at 2 mm, had a 17.5 mm hole a relit view saw into.
    seed : int
    """

    fusion: FusionConfig | None = None
    fixed_voxel: bool = False
    markers: MarkerConfig | None = None
    marker_stream: str | None = None
    box_height: float = 0.30
    box_z_min: float | None = None
    roi_margin: float = 0.05
    use_anchors: bool = True
    three_circle_numbers: bool = True
    n_points: int = 100_000
    bilateral_sigma_s: float | None = None
    bilateral_sigma_n: float = 0.25
    bilateral_iterations: int = 3
    bilateral_k: int = 128
    bilateral_adaptive_stages: tuple[int, ...] = (3, 6, 12)
    bilateral_adaptive_c: float = 2.5
    bilateral_adaptive_converge: float | None = 0.7
    crease_radius_voxels: float | None = 2.5
    plane_snap: bool = True
    refuse_voxel_scale: float = 1.0
    refuse_fine_scale: float | None = 2.0 / 3.0
    refuse_fine_radius_voxels: float = 6.5
    refuse_fine_fraction: float = 0.01
    refuse_trunc_voxels: float | None = None
    refuse_fine_trunc_voxels: float | None = 2.0
    refuse_fine_trunc_min_frames: int = 60
    min_component: float = 0.02
    jet_radius: float | None = 0.016
    jet_min_vertices: int = 200
    jet_degree: int = 3
    jet_max_residual: float = 3.0
    hole_radius: float = 0.02
    seed: int = 0


@dataclass
class FrameState:
    """What the geometry pass says about one frame (shown live by the GUI).

    Attributes
    ----------
    index : int
        ``Frame.index`` of the frame.
    timestamp : float
    state : {"first", "ok", "lost", "skipped"}
    pose : (4, 4) ndarray or None
        Depth camera-to-world pose in the fusion world (the first camera); the last good pose
        when lost; None when skipped.
    pose_marker : (4, 4) ndarray or None
        The same pose in the marker frame, once the markers are known.
    markers_found : int
        Circles detected in this frame (0..4).
    markers_complete : bool
        All four found forming the square.
    reason : str
        Why the frame is lost or skipped.
    ms : dict
        Milliseconds per step ("markers", "prep", "raycast", "track", "integrate").
    detection : MarkerDetection or None
        The circles found in the frame (camera frame), kept for :meth:`GeometryPass.refuse`.
    """

    index: int
    timestamp: float
    state: str
    pose: np.ndarray | None = None
    pose_marker: np.ndarray | None = None
    markers_found: int = 0
    markers_complete: bool = False
    reason: str = ""
    ms: dict = field(default_factory=dict)
    detection: MarkerDetection | None = None

    @property
    def ok(self) -> bool:
        return self.state in ("first", "ok")


@dataclass
class GeometryResult:
    """Output of the geometry pass, in the marker frame (metres).

    Attributes
    ----------
    mesh : open3d.geometry.TriangleMesh
        The fused surface inside the object box, with vertex normals.
    points, normals : (N, 3) float64
        Sampled surface points (area-proportional) and their bilateral-filtered unit normals.
    raw_normals : (N, 3) float64
        The normals before filtering.
    poses : (F, 4, 4) float64
        Depth camera-to-marker pose of every frame given (NaN for skipped frames; the last good
        pose for lost ones).
    states : list of FrameState
    frame_indices : (F,) int
    marker_to_world : (4, 4)
        Marker frame -> fusion world (first depth camera).
    marker_centers : (4, 3)
        Fused circle centres 1..4 in the marker frame.
    box : ObjectBox
    voxel_size : float
    spacing : float
        Mean point spacing (``sqrt(area per point)``), metres.
    """

    mesh: o3d.geometry.TriangleMesh
    points: np.ndarray
    normals: np.ndarray
    raw_normals: np.ndarray
    poses: np.ndarray
    states: list
    frame_indices: np.ndarray
    marker_to_world: np.ndarray
    marker_centers: np.ndarray
    box: ObjectBox
    voxel_size: float
    spacing: float
    _grid: PointGrid | None = None

    def grid(self, max_dist: float | None = None) -> PointGrid:
        """The spatial grid over :attr:`points` for pixel registration (built once)."""
        if self._grid is None or (max_dist is not None and abs(self._grid.max_dist - max_dist) > 1e-12):
            self._grid = PointGrid(self.points, self.normals, max_dist=max_dist)
        return self._grid

    @property
    def lost_frames(self) -> list[int]:
        return [s.index for s in self.states if s.state == "lost"]


class GeometryPass:
    """KinectFusion geometry acquisition with the marker frame and object box (paper §4.1).

    Parameters
    ----------
    config : GeometryConfig, optional
    meta : dict, optional
        Session meta (``SessionReader.meta``); its ``extra["markers"]`` describes the circles.
    intrinsics : Intrinsics, optional
        Depth intrinsics; default those of the first frame.
    """

    def __init__(self, config: GeometryConfig | None = None, meta: dict | None = None,
                 intrinsics: Intrinsics | None = None):
        self.config = cfg = config or GeometryConfig()
        self.marker_config = cfg.markers or marker_config_from_meta(meta)
        self.intrinsics = intrinsics
        self.fusion: TSDFFusion | None = None
        self._tracking_voxel: float | None = None
        #: the re-fusion's voxel as a fraction of tracking's, once :meth:`refuse` has decided it, and
        #: the first mesh's fraction of tightly curved vertices it decided from (``refuse_fine_scale``)
        self.refuse_scale: float | None = None
        self.tight_fraction: float | None = None
        self.fine_triggered = False                  # refuse_fine_scale applied (the object curves tightly)
        #: fraction of the points whose normals :meth:`result` took from jet fits (None: not run), and
        #: each point's fit residual over the median (inf where no fit; None: not run)
        self.jet_fraction: float | None = None
        self.jet_residual: np.ndarray | None = None
        self.tracker = MarkerTracker(self.marker_config, from_three=self.config.three_circle_numbers)
        self.states: list[FrameState] = []
        self.box: ObjectBox | None = None
        self._last_key: tuple[int, float] | None = None
        self._roi_set = False
        #: circles seen before all four were in one frame: weighted sums of their world centres and
        #: the weights (at most four rows; :meth:`_provisional_anchors`)
        self._prov_sums = np.zeros((0, 3))
        self._prov_weights = np.zeros(0)
        self._prov_since: int | None = None          # len(self.states) when the first of them was seen
        #: frames tracked before the marker frame whose circles did not confirm their pose
        #: (:meth:`_backfill_marker_poses`): left without a marker-frame pose
        self.backfill_rejected = 0

    # -- helpers ----------------------------------------------------------------------------------
    def _skip(self, frame: Frame, reason: str) -> FrameState:
        st = FrameState(getattr(frame, "index", -1), float(getattr(frame, "timestamp", np.nan)), "skipped",
                        reason=reason)
        self.states.append(st)
        return st

    def _voxel(self, det: MarkerDetection | None, K: Intrinsics | None = None) -> float:
        fc = self.config.fusion or FusionConfig()
        if self.config.fixed_voxel:
            return fc.voxel_size
        side = self.marker_config.side_m
        if side is None and det is not None and det.complete:
            C = det.centers
            side = float(np.mean([np.linalg.norm(C[i] - C[(i + 1) % 4]) for i in range(4)]))
        pixel = None
        if K is not None and K.fx > 0:
            # the depth pixel's footprint at the working distance: the circles' depth, else 0.75 m
            z = 0.75
            if det is not None and det.n and np.isfinite(np.asarray(det.centers, float)).all():
                z = float(np.median(np.asarray(det.centers, float)[:, 2]))
            pixel = max(z, 0.1) / float(K.fx)
        return voxel_size_for_box(side if side else 0.30, self.config.box_height, pixel)

    def _set_roi(self) -> None:
        cfg, mc = self.config, self.marker_config
        side = self.tracker.side()
        vs = self.fusion.config.voxel_size
        z_min = cfg.box_z_min if cfg.box_z_min is not None else max(0.004, vs)
        self.box = ObjectBox.from_side(side, cfg.box_height, z_min)
        m = cfg.roi_margin + mc.radius_m
        lo = np.array([-side / 2 - m, -side / 2 - m, -cfg.roi_margin])
        hi = np.array([side / 2 + m, side / 2 + m, cfg.box_height + cfg.roi_margin])
        self.fusion.set_roi(invert_pose(self.tracker.marker_to_world()), lo, hi)
        self._roi_set = True

    def _anchors(self, det: MarkerDetection, pose: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """(centres in the camera frame, the fused circles they are, the plane normal), world frame:
        each detected centre matched to the nearest fused circle through ``pose`` (camera to world;
        default the tracker's prediction for the next frame), or None. A complete detection with the
        key circle (``MarkerConfig.key_radius_m``) keeps its own, absolute numbering, whatever the pose
        (a 30-degree step of the prediction pairs no circle within the distance allowed); so do three
        circles numbered by the key (:meth:`MarkerTracker.number_three`) unless the prediction pairs
        all three otherwise (a misread radius turns the numbering by a quarter turn, which tracking
        does not), and the key circle with the one across the diagonal
        (:meth:`MarkerTracker.number_two`), whose anchors then carry a fourth element, the plane's
        normal in this frame, with which the two fix the pose (:func:`appfusion.fusion.anchor_pose`).
        A circle the tracker has only inferred (:attr:`MarkerTracker.inferred`) is no anchor: its
        place is not a measurement."""
        pairs = self._paired(det, pose)
        if pairs is None:
            return None
        k, j, numbered = pairs
        measured = ~self.tracker.inferred[j]
        if not measured.any():
            return None
        # with the support plane's normal: a centre's error across the plane weighs more than within
        # it (FusionConfig.anchor_normal_weight)
        out = det.centers[k[measured]], self.tracker.centers[j[measured]], self.tracker.normal
        if numbered and measured.sum() == 2 and det.normal is not None and self.tracker.normal is not None:
            # two numbered circles and the plane's normal in this frame fix the pose (fusion.anchor_pose);
            # two paired by nearness do not (one side of the square fits any other)
            out = out + (np.asarray(det.normal, float),)
        return out

    def _paired(self, det: MarkerDetection, pose: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """(detections, fused circle numbers, whether numbered by the key circle) of :meth:`_anchors`,
        or None."""
        if not (self.config.use_anchors and self.tracker.initialised and det.n):
            return None
        C = self.tracker.centers
        every = np.arange(det.n)
        if self.marker_config.key_radius_m and det.complete and det.n == len(C):
            return every, every, True
        fu = self.fusion
        W = transform_points(fu.predicted_pose() if pose is None else pose, det.centers)
        dist = np.linalg.norm(W[:, None] - C[None], axis=2)
        j = dist.argmin(1)
        if det.n in (2, 3) and self.config.three_circle_numbers:
            idx = self.tracker.number_three(det) if det.n == 3 else self.tracker.number_two(det)
            if idx is not None:
                near = dist[every, j] < max(3 * self.marker_config.radius_m, 0.05)
                if fu.lost or not near.all() or len(set(j)) < det.n or np.array_equal(j, idx):
                    return every, idx, True
        # while lost the prediction may be far off (the last good pose, a fast sweep's 20-30 degrees
        # away): match three or more circles by their shape, not by where the stale pose puts them
        if fu.lost and pose is None and 3 <= det.n <= len(C):
            j = self._match_lost(det)
            if j is None:
                return None
            keep = np.ones(det.n, bool)
        else:
            dj = dist[every, j]
            keep = dj < max(3 * self.marker_config.radius_m, 0.05)
            # two detections near one fused circle (an ellipse found twice, a reflection): the nearer
            # one is that circle. Dropping every anchor of the frame instead let the ICP slide 4 cm
            # on a symmetric object with four circles in view
            for c in np.unique(j[keep]):
                dup = np.flatnonzero(keep & (j == c))
                if len(dup) > 1:
                    keep[dup[dup != dup[np.argmin(dj[dup])]]] = False
        if keep.sum() == 0 or len(set(j[keep])) < keep.sum():
            return None
        return every[keep], j[keep], False

    def _provisional_anchors(self, det: MarkerDetection) -> tuple[np.ndarray, np.ndarray] | None:
        """Anchors before the marker frame exists: each detected centre paired with the nearest circle
        seen so far (:meth:`_update_provisional`) through the predicted pose, within the distance
        :meth:`_anchors` allows; None if none pairs.

        A pass that starts with three circles in view has no marker frame until a frame shows all
        four, and depth alone does not fix a rotation about the axis of an object that is a surface
        of revolution standing on the plane. On the 32-frame quick matte session the geometry pass
        tracked 25 frames that way as "ok" while the pose turned 11 degrees a frame away from the
        truth (1 m off by the 20th); with the circles seen so far as anchors it follows the truth.
        """
        if not (self.config.use_anchors and det.n and len(self._prov_weights)):
            return None
        P = self._prov_sums / self._prov_weights[:, None]
        W = transform_points(self.fusion.predicted_pose(), det.centers)
        dist = np.linalg.norm(W[:, None] - P[None], axis=2)
        j = dist.argmin(1)
        keep = dist[np.arange(det.n), j] < max(3 * self.marker_config.radius_m, 0.05)
        if not keep.any() or len(set(j[keep])) < keep.sum():
            return None
        return det.centers[keep], P[j[keep]]

    @property
    def _circle_fit_tol_m(self) -> float:
        """RMS distance, metres, within which detected circle centres fit the fused ones: half a
        circle's radius, at least 5 mm (:meth:`_match_lost`, :meth:`_backfill_marker_poses`)."""
        return max(0.5 * self.marker_config.radius_m, 0.005)

    def _backfill_marker_poses(self, tol_m: float | None = None) -> None:
        """Give the frames tracked before the marker frame existed, anchored on the circles seen so
        far (:meth:`_provisional_anchors`), their marker-frame pose once it does, so that re-fusion and
        the appearance passes use them. Without those anchors such frames had come out 5-10 cm off
        and were left out; the 32-frame quick matte session's geometry pass starts with 25 of them.

        A frame gets its pose only where its own circles confirm it: two or more detected centres,
        carried into the world by its tracked pose, lie within an RMS of ``tol_m`` (default half a
        circle's radius, at least 5 mm) of the fused circles. A frame without such a detection is
        confirmed by the nearest checked frames before and after it (the marker frame counts as
        one). The chain of tracked poses can break where tracking relocalised on circles paired
        wrongly: on the 12-frames-a-pass synthetic Kinect sphere the first frame of the geometry
        pass came out 293 mm and 61 degrees off that way, and the IR pass's alpha 0.125 -> 0.153
        (truth 0.12). Frames left out are counted in ``backfill_rejected``.
        """
        if self._prov_since is None:
            return
        if tol_m is None:
            tol_m = self._circle_fit_tol_m
        W2M = invert_pose(self.tracker.marker_to_world())
        C = self.tracker.centers
        cand = [st for st in self.states[self._prov_since:]
                if st.ok and st.pose_marker is None and st.pose is not None]
        verdict: list[bool | None] = []
        for st in cand:
            det = st.detection
            if det is None or det.n < 2:
                verdict.append(None)
                continue
            W = transform_points(st.pose, det.centers)
            d = np.linalg.norm(W[:, None] - C[None], axis=2).min(1)
            verdict.append(bool(np.all(np.isfinite(d)) and np.sqrt(np.mean(d * d)) < tol_m))
        for k, st in enumerate(cand):
            ok = verdict[k]
            if ok is None:
                before = next((v for v in reversed(verdict[:k]) if v is not None), None)
                after = next((v for v in verdict[k + 1:] if v is not None), True)   # the marker frame
                ok = after and before is not False
            if ok:
                st.pose_marker = W2M @ st.pose
            else:
                self.backfill_rejected += 1

    def _update_provisional(self, det: MarkerDetection, pose: np.ndarray) -> None:
        """Fuse a detection made from ``pose`` into the circles seen before the marker frame exists:
        a centre within the tracker's match distance of one of them updates its weighted mean
        (weights as :class:`~appfusion.markers.MarkerTracker`'s), another starts a new one while
        there are fewer than four."""
        W = transform_points(pose, det.centers)
        w = self.tracker._weights(det)
        md = self.tracker.match_dist or 1.5 * self.marker_config.radius_m
        for k in range(det.n):
            if not (np.all(np.isfinite(W[k])) and w[k] > 0):
                continue
            if len(self._prov_weights):
                P = self._prov_sums / self._prov_weights[:, None]
                d = np.linalg.norm(P - W[k], axis=1)
                i = int(d.argmin())
                if d[i] < md:
                    self._prov_sums[i] += w[k] * W[k]
                    self._prov_weights[i] += w[k]
                    continue
            if len(self._prov_weights) < 4:
                self._prov_sums = np.vstack([self._prov_sums, w[k] * W[k]])
                self._prov_weights = np.append(self._prov_weights, w[k])
                if self._prov_since is None:
                    self._prov_since = len(self.states)

    def _match_lost(self, det: MarkerDetection, tol_m: float | None = None) -> np.ndarray | None:
        """Fused circle numbers of three or more detected circles while tracking is lost, or None.

        Every one-to-one assignment of the detected centres to the fused ones whose rigid fit
        (:func:`~appfusion.fusion.kabsch`) leaves an RMS residual below ``tol_m`` (default half a
        circle's radius, at least 5 mm) is a candidate. The circles form a square, so several are
        (the four cyclic shifts of a complete detection, the four corners of three circles' right
        triangle, and their flips through the plane); the one whose camera rotation is closest to the
        last good pose's wins: the camera has not turned 45 degrees about the table while lost.
        Matching by nearest circle through that stale pose instead paired three circles wrongly after
        a 24-degree gap, and the relocalised pose ran away (the 30-frame quick matte session).
        (A complete detection with the key circle never gets here: :meth:`_anchors` numbers it.)
        """
        from itertools import permutations

        from .fusion import rotation_angle_deg
        C = self.tracker.centers
        if tol_m is None:
            tol_m = self._circle_fit_tol_m
        last = self.fusion.predicted_pose()
        best, best_ang = None, np.inf
        for perm in permutations(range(len(C)), det.n):
            perm = np.array(perm)
            T = kabsch(det.centers, C[perm])
            r = transform_points(T, det.centers) - C[perm]
            if np.sqrt(np.mean(np.sum(r * r, axis=1))) > tol_m:
                continue
            ang = rotation_angle_deg(last[:3, :3].T @ T[:3, :3])
            if ang < best_ang:
                best, best_ang = perm, ang
        return best

    # -- per frame ----------------------------------------------------------------------------------
    def add_frame(self, frame: Frame) -> FrameState:
        """Track, fuse and look for markers in one frame. Never raises for bad frame data: the
        returned state says ``skipped`` and why."""
        with blas_threads(1):
            return self._add_frame(frame)

    def _add_frame(self, frame: Frame) -> FrameState:
        if not isinstance(frame, Frame):
            raise AppFusionError(f"geometry pass: expected a Frame, got {type(frame).__name__}")
        if frame.depth is None:
            return self._skip(frame, f"frame {frame.index}: no depth image")
        K = self.intrinsics or frame.depth_intrinsics
        if K is None:
            return self._skip(frame, f"frame {frame.index}: no depth intrinsics")
        if frame.depth.shape != K.shape:
            return self._skip(frame, f"frame {frame.index}: depth {frame.depth.shape} does not match the intrinsics {K.shape}")
        key = (int(frame.index), float(frame.timestamp))
        if self._last_key is not None and (key[1] < self._last_key[1] or
                                           (key[1] == self._last_key[1] and key[0] <= self._last_key[0])):
            return self._skip(frame, f"frame {frame.index} (t={frame.timestamp:.3f} s) is out of order: "
                                     f"the previous frame was {self._last_key[0]} (t={self._last_key[1]:.3f} s)")
        with np.errstate(invalid="ignore"):
            n_valid = int(np.count_nonzero(frame.depth > 0))
        if n_valid < 0.01 * frame.depth.size:
            self._last_key = key
            return self._skip(frame, f"frame {frame.index}: no valid depth ({n_valid} valid pixels)")
        self._last_key = key
        t0 = time.perf_counter()
        try:
            fr = frame if frame.depth_intrinsics is not None else frame.replace(depth_intrinsics=K)
            det = detect_markers(fr, self.marker_config, self.config.marker_stream)
        except AppFusionError as e:
            det = None
            marker_reason = str(e)
        else:
            marker_reason = ""
        t_markers = (time.perf_counter() - t0) * 1e3
        if self.fusion is None:
            fc = replace(self.config.fusion or FusionConfig(), voxel_size=self._voxel(det, K))
            self.fusion = TSDFFusion(K, fc)
            self._tracking_voxel = fc.voxel_size       # refuse's volume is scaled from this one
            if det is not None:
                self.tracker.update(det, self.fusion.pose)
                if self.tracker.initialised:
                    self._set_roi()
        if det is not None:
            anchors = self._anchors(det) if self.tracker.initialised else self._provisional_anchors(det)
        else:
            anchors = None
        res = self.fusion.process(frame.depth, anchors)
        was_initialised = self.tracker.initialised
        if det is not None and res.state in ("ok",) and self.fusion.n_frames > 1:
            self.tracker.update(det, res.pose)
        if det is not None and res.state in ("ok", "first") and not self.tracker.initialised:
            self._update_provisional(det, res.pose)
        if self.tracker.initialised and not was_initialised:
            self._backfill_marker_poses()
        if self.tracker.initialised and not self._roi_set:
            self._set_roi()
        ms = dict(res.ms)
        ms["markers"] = t_markers
        pm = None
        if self.tracker.initialised:
            pm = invert_pose(self.tracker.marker_to_world()) @ res.pose
        reason = res.reason or marker_reason
        st = FrameState(frame.index, float(frame.timestamp), res.state, res.pose.copy(), pm,
                        0 if det is None else det.n, bool(det is not None and det.complete), reason, ms, det)
        self.states.append(st)
        return st

    # -- results -----------------------------------------------------------------------------------
    @property
    def marker_to_world(self) -> np.ndarray:
        """Marker frame -> fusion world (first camera); raises until the markers have been seen."""
        if not self.tracker.initialised:
            raise EstimationError("geometry pass: no marker frame yet (no frame has shown all four white circles, "
                                  "or three with the key circle)")
        return self.tracker.marker_to_world()

    def fused_mesh(self) -> o3d.geometry.TriangleMesh:
        """The whole fused surface, uncropped, in the fusion's world frame (the first tracked depth
        camera's, metres): what is left of a scan whose markers never gave a marker frame."""
        if self.fusion is None or self.fusion.n_integrated == 0:
            raise EstimationError("geometry pass: no frame could be fused")
        return self.fusion.extract_mesh()

    def _object_mesh(self, W2M: np.ndarray, box) -> o3d.geometry.TriangleMesh:
        """The fused surface in the marker frame, cropped to the object box (its small pieces
        dropped) and its small holes filled."""
        cfg = self.config
        mesh = self.fusion.extract_mesh()
        mesh.transform(W2M)
        if box is not None:
            mesh = box.crop_mesh(mesh)
            mesh = _drop_small_components(mesh, cfg.min_component)
        # the rim on the plane (cut by the box's floor) stays open: nothing below it was ever seen
        floor = None if box is None else box.z_min + 2 * self.fusion.config.voxel_size
        return fill_small_holes(mesh, cfg.hole_radius, keep_open_below=floor)

    def refuse(self, frames, depth_weight: float = 0.1, anchor_sigma: tuple[float, float] = (3e-4, 6e-5)) -> int:
        """Re-register every tracked frame to the fused object with its marker anchors, and fuse the
        frames again at those poses (beyond the paper).

        Tracking registers a frame to the model *as fused so far*; on the demo its poses move the
        object's surface by 0.28 mm (RMS over five object points against the truth), and the mesh
        fused at them is what the normals come from. Each frame is re-registered to the object mesh
        fused from all frames (:class:`PoseRefiner`) with its circle centres as anchors (the in-plane
        and across-plane sigmas ``anchor_sigma``, metres; the depth pixels weighted ``depth_weight``,
        since their errors are correlated), then a fresh TSDF (same voxel size, region and surface
        volume; the voxel scaled by ``config.refuse_voxel_scale``, or by ``config.refuse_fine_scale``
        where the object curves tightly: :attr:`refuse_scale`) integrates every frame at its new
        pose, and :meth:`result` extracts that one.
        Demo: poses 0.28 -> 0.12 mm (ICP to the mesh alone: 0.15, worse than tracking at steep
        views where the object constrains the pose least); see docs/geometry-pass.md. Afterwards the
        circle centres are fused again from the same detections at the new poses
        (:meth:`appfusion.markers.MarkerTracker.refit`): the marker frame the result is put in.

        Parameters
        ----------
        frames : iterable of Frame
            The frames :meth:`add_frame` saw (again, in any order; their circles are not looked for
            again, each frame's state keeps its detection); those without a tracked pose in the
            marker frame are left out.
        depth_weight : float
            Weight of each depth pixel's term relative to its noise variance.
        anchor_sigma : (float, float)
            Circle-centre sigmas within and across the support plane, metres.

        Returns
        -------
        int
            Frames fused again (0: nothing changed, e.g. no marker frame yet).
        """
        if self.fusion is None or not self.tracker.initialised:
            return 0
        M2W = self.tracker.marker_to_world()
        W2M = invert_pose(M2W)
        old = self._object_mesh(W2M, self.box)
        if len(old.triangles) == 0:
            return 0
        refiner = PoseRefiner(np.asarray(old.vertices), np.asarray(old.triangles), iterations=4,
                              depth_weight=depth_weight, anchor_sigma=anchor_sigma,
                              sight_weighting=self.fusion.config.anchor_sight_weighting)
        by_index = {s.index: s for s in self.states if s.pose_marker is not None and s.ok}
        fc = self.fusion.config
        if self.refuse_scale is None:                            # decided once, in the first round
            self.refuse_scale = float(self.config.refuse_voxel_scale)
            fine = self.config.refuse_fine_scale
            if self.refuse_scale == 1.0 and fine is not None:
                self.tight_fraction = tight_curvature_fraction(
                    old, self.config.refuse_fine_radius_voxels * self._tracking_voxel)
                if self.tight_fraction >= self.config.refuse_fine_fraction:
                    self.refuse_scale = float(fine)
                    self.fine_triggered = True
        if self.refuse_scale != 1.0:
            # scaled from tracking's voxel, also in a second round (whose volume is already scaled)
            fc = replace(fc, voxel_size=self._tracking_voxel * self.refuse_scale)
        trunc = self.config.refuse_trunc_voxels
        if trunc is None and self.fine_triggered and len(by_index) >= self.config.refuse_fine_trunc_min_frames:
            trunc = self.config.refuse_fine_trunc_voxels
        if trunc is not None:
            fc = replace(fc, trunc_voxels=float(trunc))
        new = TSDFFusion(self.fusion.intrinsics, fc)
        if self.fusion.roi is not None:
            new.set_roi(*self.fusion.roi)
        n, refused = 0, set()
        with blas_threads(1):
            for frame in frames:
                st = by_index.get(frame.index)
                if st is None or frame.depth is None:
                    continue
                anchors = None
                det = st.detection                               # found while tracking the frame
                a = self._anchors(det, st.pose) if det is not None and det.n else None
                if a is not None and len(a[0]):
                    c_cam, C_w, n_w = a[:3]
                    C_m = transform_points(W2M, C_w)
                    n_m = W2M[:3, :3] @ n_w if n_w is not None else None
                    anchors = (c_cam, C_m, n_m)
                K = frame.depth_intrinsics or self.fusion.intrinsics
                # from the tracked pose through the final marker frame (pose_marker used the marker
                # frame as known when the frame was tracked)
                pm, _ = refiner.refine(frame.depth, K, W2M @ st.pose, anchors=anchors)
                pose = M2W @ pm
                d_int = downsample_depth(frame.depth, new.f_int)
                new.integrate(new._mask_roi(d_int, new.K_int, pose), pose)
                st.pose, st.pose_marker = pose, pm
                refused.add(st.index)
                n += 1
        if n:
            self.fusion = new
            # the circle centres again, from the same detections at the refined poses: the marker
            # frame the mesh and every pose are put in (MarkerTracker.refit)
            if self.tracker.refit((by_index[f].detection, by_index[f].pose) for f in refused):
                W2M = invert_pose(self.tracker.marker_to_world())
                for f in refused:
                    by_index[f].pose_marker = W2M @ by_index[f].pose
        return n

    def _jet_normals(self, mesh: o3d.geometry.TriangleMesh, P: np.ndarray, N: np.ndarray) -> tuple[np.ndarray, float]:
        """The filtered normals ``N`` replaced by cubic jet fits to the mesh's vertices where the fit's
        residual is at most ``config.jet_max_residual`` times its median (:func:`jet_normals`;
        ``config.jet_radius``); returns the normals and the fraction of points replaced, and keeps
        each point's residual over the median in :attr:`jet_residual`."""
        cfg = self.config
        Nj, resid = jet_normals(P, N, np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals),
                                radius=float(cfg.jet_radius), degree=int(cfg.jet_degree))
        fin = np.isfinite(resid)
        if not fin.any():
            self.jet_residual = np.full(len(P), np.inf)
            return N, 0.0
        self.jet_residual = resid / np.median(resid[fin])
        use = self.jet_residual <= float(cfg.jet_max_residual)
        return np.where(use[:, None], Nj, N), float(use.mean())

    def result(self, n_points: int | None = None, require_markers: bool = True) -> GeometryResult:
        """Mesh cropped to the object box, sampled points with filtered normals, poses, marker frame.

        Parameters
        ----------
        n_points : int, optional
            Default ``config.n_points``.
        require_markers : bool
            Without markers: raise (default), or return the whole model in the first camera's frame.
        """
        cfg = self.config
        if self.fusion is None or self.fusion.n_integrated == 0:
            reasons = sorted({s.reason for s in self.states if s.reason})[:3]
            raise EstimationError("geometry pass: no frame could be fused"
                                  + (f" ({'; '.join(reasons)})" if reasons else " (no frames given)"))
        if self.tracker.initialised:
            M2W = self.tracker.marker_to_world()
            box = self.box
        elif require_markers:
            raise EstimationError(
                f"geometry pass: the four white circles were never seen together"
                + (" (nor three of them with the key circle)"
                   if self.marker_config.key_radius_m and self.config.three_circle_numbers else "")
                + f" in {len(self.states)} frame{'s' if len(self.states) != 1 else ''} "
                f"(radius {self.marker_config.radius_m * 1e3:.0f} mm"
                + ("" if self.marker_config.side_m is None else f", square side {self.marker_config.side_m * 1e3:.0f} mm")
                + "), so there is no marker frame and no object box; check the markers are in view and the "
                  "session meta 'markers' entry")
        else:
            M2W = np.eye(4)
            box = None
        W2M = invert_pose(M2W)
        mesh = self._object_mesh(W2M, box)
        if len(mesh.triangles) == 0:
            raise EstimationError("geometry pass: the fused surface inside the object box is empty "
                                  "(is the object inside the square of circles, and was it in view?)")
        mesh.compute_vertex_normals()
        n = int(n_points or cfg.n_points)
        P, Nraw = sample_points(mesh, n, seed=cfg.seed)
        area = mesh.get_surface_area()
        spacing = float(np.sqrt(area / n))
        vs = self.fusion.config.voxel_size
        sig = cfg.bilateral_sigma_s or 1.0 * vs
        fstats: dict = {}
        Nf = bilateral_filter_normals(P, Nraw, sigma_s=sig, sigma_n=cfg.bilateral_sigma_n,
                                      iterations=cfg.bilateral_iterations, k=cfg.bilateral_k, seed=cfg.seed,
                                      adaptive_stages=cfg.bilateral_adaptive_stages,
                                      adaptive_c=cfg.bilateral_adaptive_c,
                                      adaptive_converge=cfg.bilateral_adaptive_converge, stats=fstats)
        self.jet_fraction = self.jet_residual = None
        if (cfg.jet_radius is not None and cfg.bilateral_adaptive_stages
                and fstats["stages_run"] < len(cfg.bilateral_adaptive_stages)
                and len(mesh.vertices) / max(area, 1e-12) * np.pi * cfg.jet_radius ** 2 >= cfg.jet_min_vertices):
            Nf, self.jet_fraction = self._jet_normals(mesh, P, Nf)
        if cfg.crease_radius_voxels is not None:
            Nf = sharpen_creases(P, Nf, radius=float(cfg.crease_radius_voxels) * vs, seed=cfg.seed)
        if cfg.plane_snap:
            Nf = snap_planes(P, Nf, voxel=vs)
        poses = np.full((len(self.states), 4, 4), np.nan)
        for i, s in enumerate(self.states):
            if s.pose is not None:
                poses[i] = W2M @ s.pose
        C = transform_points(W2M, self.tracker.centers) if self.tracker.initialised else np.full((4, 3), np.nan)
        return GeometryResult(mesh=mesh, points=P, normals=Nf, raw_normals=Nraw, poses=poses, states=list(self.states),
                              frame_indices=np.array([s.index for s in self.states]), marker_to_world=M2W,
                              marker_centers=C, box=box, voxel_size=vs, spacing=spacing)


def tight_curvature_fraction(mesh: o3d.geometry.TriangleMesh, radius: float, k: int = 32) -> float:
    """Fraction of a mesh's vertices whose larger principal curvature exceeds ``1 / radius``.

    The curvature is the shape operator of the vertex normals (:func:`appfusion.points.normal_gradient`
    over ``k`` neighbours, symmetrised). A fused mesh's vertex normals carry ~1-2 degrees of noise,
    which reads as radii of ~100 mm over those neighbours; measured on scans at 3 mm (k = 32): no
    vertex of the demo's or seed 3's capsule under 34 mm (1st percentile), the pepper 2.2 % and the
    vase 2.8 % of their vertices under 20 mm (its lid's rim, the pepper's stem dimple).

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
    radius : float
        Metres.
    k : int
        Neighbours of the shape operator's fit.
    """
    from .points import normal_gradient

    if len(mesh.vertices) < k + 1 or not radius > 0:
        return 0.0
    m = o3d.geometry.TriangleMesh(mesh)
    m.compute_vertex_normals()
    V, N = np.asarray(m.vertices), np.asarray(m.vertex_normals)
    ok = np.isfinite(N).all(1) & (np.linalg.norm(N, axis=1) > 0.5)
    if ok.sum() < k + 1:
        return 0.0
    G = normal_gradient(V[ok], N[ok], k=k).astype(np.float64)
    S = 0.5 * (G + np.transpose(G, (0, 2, 1)))
    kappa = np.abs(np.linalg.eigvalsh(S)).max(1)
    return float(np.mean(kappa > 1.0 / radius))


def _boundary_edges(F: np.ndarray) -> np.ndarray:
    """(B, 2) the edges of exactly one triangle of ``F`` (F, 3), each as that triangle runs it."""
    if len(F) == 0:
        return np.zeros((0, 2), np.int64)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    _, inv, cnt = np.unique(np.sort(E, axis=1), axis=0, return_inverse=True, return_counts=True)
    return E[cnt[inv.ravel()] == 1]


def open_boundary_points(positions: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                         radius: float) -> np.ndarray:
    """Which points lie within ``radius`` of the mesh's open boundary (its edges of one triangle).

    On a scan that is where the object box cut the fused surface off the support plane (and the rim
    of any hole too large to fill): the fused normals are worst there, and depth pixels of the plane
    can register to the object's lowest points. The IR pass keeps the leaves holding such points
    out of its Ward fits (``rim`` of :class:`appfusion.brdf_cut.BRDFCut`).

    Parameters
    ----------
    positions : (N, 3) array
        Points, metres.
    vertices : (V, 3) array
    faces : (F, 3) int array
        The mesh, same frame.
    radius : float
        Metres; points within it of a boundary edge's end or middle count.

    Returns
    -------
    (N,) bool
        False everywhere for a closed mesh (or no mesh).
    """
    from scipy.spatial import cKDTree

    P = np.asarray(positions, np.float64).reshape(-1, 3)
    V = np.asarray(vertices, np.float64).reshape(-1, 3)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    out = np.zeros(len(P), bool)
    if len(F) == 0 or len(P) == 0 or not radius > 0:
        return out
    b = _boundary_edges(F)
    if len(b) == 0:
        return out
    probes = np.concatenate([V[b[:, 0]], V[b[:, 1]], 0.5 * (V[b[:, 0]] + V[b[:, 1]])])
    d, _ = cKDTree(probes).query(P, distance_upper_bound=float(radius))
    return np.isfinite(d)


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """The closed boundary loops of a triangle mesh (the rims of its holes).

    Parameters
    ----------
    faces : (F, 3) int ndarray
        Triangles, consistently wound.

    Returns
    -------
    list of (k,) int64 ndarray
        Each loop's vertex indices, in the direction of the directed edges of the triangles along it
        (a triangle closing the hole runs each of those edges the other way). A vertex where two
        holes touch appears in both loops; an edge used by more than two triangles is not a
        boundary edge.
    """
    B = _boundary_edges(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
    if len(B) == 0:
        return []
    nxt: dict[int, list[int]] = {}
    for a, b in B.tolist():
        nxt.setdefault(a, []).append(b)
    loops = []
    for start in list(nxt):
        while nxt.get(start):
            loop, v = [start], nxt[start].pop()
            while v != start and nxt.get(v):
                loop.append(v)
                v = nxt[v].pop()
            if v == start and len(loop) >= 3:
                loops.append(np.asarray(loop, np.int64))
    return loops


def fill_small_holes(mesh: o3d.geometry.TriangleMesh, max_radius: float, fair: bool = True,
                     keep_open_below: float | None = None) -> o3d.geometry.TriangleMesh:
    """Close the mesh's holes up to ``max_radius`` metres (paper §6's hole cleaning).

    Marching cubes leaves holes where the surface volume's weight stayed below its threshold: on the
    capsules' domes, seen only obliquely, holes of 6-10 mm; on the vase's flared neck one of 17 mm. A
    relit view sees through them onto the inside of the far wall, whose normal faces away from the
    camera and into the object's shadow: black spots (the 40-frame matte scan: 4 pixels held half of
    a view's relit error), and the exported mesh is open there.

    Each boundary loop (:func:`boundary_loops`) whose vertices lie within ``max_radius`` of their
    mean is closed in three steps: ears are cut off it until it is star-shaped about its mean, seen
    along the area-weighted normal of the triangles around it (:func:`_clip_to_star`); a web of
    rings spans it from there to its mean, about one median mesh edge apart, wound like the mesh
    around it; with ``fair`` the web's vertices then move along that normal to where the uniform
    bi-Laplacian vanishes at them and at the loop, every old vertex held (Botsch & Kobbelt's
    fairing), so the patch continues the surface's curvature instead of lying flat across a curved
    wall (on a 5 cm sphere 0.022 mm off it on average, the flat web 0.114 mm). The open rim where
    the object meets the plane stays open (``keep_open_below``). Open3D's ``fill_holes`` (VTK's
    filler), used until session 31, closed only 1 of the 4 triangles the demo's 6-vertex hole needs
    and missed the matte scan's 10 mm one at 1 cm.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
    max_radius : float
        Largest distance (metres) of a loop's vertex from the loop's mean; 0 or less keeps every hole.
    fair : bool
        Fair the new vertices (default); False leaves them on straight lines to the loop's mean.
    keep_open_below : float, optional
        A loop with a vertex below this height (metres, the mesh's z: the marker frame's) stays open
        whatever its size: the rim where the object meets the plane, which the object box cuts.

    Returns
    -------
    open3d.geometry.TriangleMesh
        A new legacy mesh (the input itself when nothing is closed or ``max_radius <= 0``); the
        input's vertices and triangles come first, unchanged.
    """
    if max_radius <= 0 or len(mesh.triangles) == 0:
        return mesh
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.triangles, dtype=np.int64)
    loops = [lp for lp in boundary_loops(F)
             if np.linalg.norm(V[lp] - V[lp].mean(0), axis=1).max() <= max_radius
             and (keep_open_below is None or V[lp, 2].min() >= keep_open_below)]
    if not loops:
        return mesh
    e = V[F[:, [1, 2, 0]]] - V[F]
    edge = float(np.median(np.linalg.norm(e, axis=2)))
    newV, newF = [], []
    n = len(V)
    lift = []
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])   # area-weighted, by the winding
    for lp in loops:
        nrm = fn[np.isin(F, lp).any(axis=1)].sum(0)
        nrm = nrm / max(np.linalg.norm(nrm), 1e-300)
        ids, ears = _clip_to_star(V, lp, nrm)
        newF += ears
        P = V[ids]
        c = P.mean(0)
        k = len(ids)
        rings = max(1, int(np.ceil(np.linalg.norm(P - c, axis=1).mean() / max(edge, 1e-12))))
        idx = [ids]                                      # ring 0: the (clipped) loop
        for r in range(1, rings):
            t = r / rings
            newV.append((1 - t) * P + t * c)
            idx.append(np.arange(n, n + k))
            n += k
        newV.append(c[None])
        lift.append(np.tile(nrm, ((rings - 1) * k + 1, 1)))
        centre = n
        n += 1
        for r in range(rings):
            a, b = idx[r], np.roll(idx[r], -1)           # counter-clockwise about the normal: a -> b
            if r == rings - 1:
                newF.append(np.stack([a, b, np.full(k, centre)], 1))
            else:
                a2, b2 = idx[r + 1], np.roll(idx[r + 1], -1)
                newF.append(np.stack([a, b, b2], 1))
                newF.append(np.stack([a, b2, a2], 1))
    V2 = np.concatenate([V] + newV)
    F2 = np.concatenate([F] + newF)
    if fair and len(V2) > len(V):
        V2 = _fair_new_vertices(V2, F2, len(V), np.unique(np.concatenate(loops)), np.concatenate(lift))
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V2), o3d.utility.Vector3iVector(F2.astype(np.int32)))
    out.remove_degenerate_triangles()
    return out


def _clip_to_star(V: np.ndarray, loop: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, list]:
    """Cut ears off a hole's boundary until it is star-shaped about its mean (seen along ``normal``).

    ``loop`` runs the way the triangles along it run their edges, so the hole is on its right seen
    from ``normal`` (the area-weighted normal of those triangles, by their winding). Returns the
    remaining boundary counter-clockwise about ``normal`` (reversed) and the ears, each a triangle
    ``(1, 3)`` wound like the mesh. Each step cuts, among the vertices whose ear is convex and holds
    no other boundary vertex, the one of smallest interior angle, preferring the ends of edges that
    the mean does not see from inside; marching cubes' boundaries zig-zag, and the web of rings
    :func:`fill_small_holes` spans from the mean folds over an edge it sees from outside.
    """
    nrm = normal / max(np.linalg.norm(normal), 1e-300)
    ids = [int(i) for i in loop[::-1]]
    ears = []
    while len(ids) > 3:
        P = V[ids]
        c = P.mean(0)
        d = P - c
        seen = np.cross(d, np.roll(d, -1, 0)) @ nrm > 0          # edge i -> i+1 seen from inside
        if seen.all():
            break
        u = np.roll(P, 1, 0) - P
        w = np.roll(P, -1, 0) - P
        ang = np.mod(np.arctan2(np.cross(w, u) @ nrm, np.einsum("ij,ij->i", w, u)), 2 * np.pi)
        bad_end = ~seen | ~np.roll(seen, 1)
        order = np.lexsort((ang, ~bad_end))
        cut = None
        for i in order:
            if ang[i] >= np.pi:
                continue
            k = len(ids)
            tri = P[[(i - 1) % k, i, (i + 1) % k]]
            if _holds_vertex(tri, np.delete(P, [(i - 1) % k, i, (i + 1) % k], axis=0), nrm):
                continue
            cut = int(i)
            break
        if cut is None:
            break                                            # no clean ear: span the web as it is
        k = len(ids)
        ears.append(np.array([[ids[(cut - 1) % k], ids[cut], ids[(cut + 1) % k]]], np.int64))
        del ids[cut]
    return np.asarray(ids, np.int64), ears


def _holds_vertex(tri: np.ndarray, pts: np.ndarray, nrm: np.ndarray) -> bool:
    """Whether any of ``pts`` lies inside the triangle ``tri`` (3, 3) seen along ``nrm``."""
    if len(pts) == 0:
        return False
    s = [np.cross(tri[(j + 1) % 3] - tri[j], pts - tri[j]) @ nrm for j in range(3)]
    return bool(np.any((s[0] > 0) & (s[1] > 0) & (s[2] > 0)))


def _fair_new_vertices(V: np.ndarray, F: np.ndarray, first_new: int, rim: np.ndarray, lift: np.ndarray) -> np.ndarray:
    """Move each vertex ``V[first_new + j]`` along the unit vector ``lift[j]`` so that the uniform
    bi-Laplacian vanishes at the new vertices and at the ``rim`` vertices (least squares; every other
    vertex held). Moving only along its hole's normal keeps the patch's triangulation as seen along
    that normal (free moves let uniform weights drag vertices sideways and fold triangles). Returns a
    copy."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    nv = len(V)
    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(nv, nv)).tocsr()
    A = ((A + A.T) > 0).astype(np.float64)
    deg = np.asarray(A.sum(1)).ravel()
    L = sp.diags(1.0 / np.maximum(deg, 1)) @ A - sp.identity(nv)     # uniform Laplacian, rows sum to 0
    rows = np.concatenate([rim, np.arange(first_new, nv)])
    LL = (L[rows] @ L).tocsc()
    Af = LL[:, first_new:]
    r0 = LL @ V                                                  # the bi-Laplacian of the web, (rows, 3)
    # residual r0 + sum_j Af[:, j] lift[j] h_j, per coordinate: minimise over h
    Ah = sp.vstack([Af @ sp.diags(lift[:, c]) for c in range(3)]).tocsc()
    rhs = -np.concatenate([r0[:, c] for c in range(3)])
    M = (Ah.T @ Ah).tocsc()
    out = V.copy()
    try:
        h = spsolve(M + 1e-12 * float(M.diagonal().max()) * sp.identity(M.shape[0], format="csc"), Ah.T @ rhs)
    except Exception:  # singular: keep the web
        return out
    h = np.asarray(h).ravel()
    if np.isfinite(h).all():
        out[first_new:] += lift * h[:, None]
    return out


def _drop_small_components(mesh: o3d.geometry.TriangleMesh, min_fraction: float) -> o3d.geometry.TriangleMesh:
    """Remove connected pieces with fewer triangles than ``min_fraction`` of the largest one."""
    if len(mesh.triangles) == 0 or min_fraction <= 0:
        return mesh
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels, counts = np.asarray(labels), np.asarray(counts)
    small = counts < min_fraction * counts.max()
    if small.any():
        mesh.remove_triangles_by_mask(small[labels])
        mesh.remove_unreferenced_vertices()
    return mesh


class PoseRefiner:
    """Frame-to-model refinement of tracked poses against the final mesh (beyond the paper).

    Tracking registers each depth frame to the model *as fused so far*; on the demo its poses move
    the object's surface by 0.45 mm (median over frames; 0.57 mm RMS) against the truth. The mesh
    fused from all frames averages that jitter out (Chamfer 0.13 mm), so a frame re-registered to
    it lands closer: 0.27 mm median, 0.28 mm RMS. The appearance passes need exactly that: which
    point of the surface a pixel sees. On a curved surface 0.5 mm is a normal error of 0.7 degrees
    on a 4 cm radius, and the IR pass's sharp lobe widened by it (demo paint alpha, truth labels:
    0.0636 with the tracked poses, 0.0608 refined, 0.06 truth).

    :meth:`refine` runs a few Gauss-Newton steps of point-to-plane ICP: the frame's depth pixels
    (every ``step``-th, those inside the mesh's bounding box grown by 1 cm) against their closest
    points on the mesh (Open3D ``RaycastingScene``), pairs farther than ``max_dist`` left out,
    Huber weights (1 mm), depth noise ``sigma_depth``. A Gaussian prior on the change of pose
    (``sigma_rot``, ``sigma_trans``) keeps what the surface does not constrain where tracking put it:
    a surface of revolution leaves the rotation about its axis free.

    Parameters
    ----------
    vertices : (V, 3) array
        The final mesh's vertices, world (= marker) frame, metres.
    faces : (F, 3) int array
    step : int
        Pixel stride in both directions.
    iterations : int
        Gauss-Newton steps (demo: 2 -> 0.272 mm, 3 -> 0.266 mm, 4 no better).
    max_dist : float
        Largest point-to-mesh distance of a pair, metres.
    sigma_depth, sigma_rot, sigma_trans : float
        Depth noise (metres), prior sigmas of the rotation (radians) and translation (metres).
    min_pairs : int
        Fewer pairs than this and the pose is returned unchanged.
    depth_weight : float
        Scales every depth pair's inverse variance (their errors are correlated across a frame, so
        with anchors they count as fewer: :meth:`GeometryPass.refuse` uses 0.1).
    anchor_sigma : (float, float)
        Sigmas of an anchor (a circle centre, :meth:`refine`) within and across the support plane,
        metres.
    sight_weighting : bool
        The in-plane sigma along an anchor's line of sight grows as ``1 / sin`` of its elevation
        above the plane (:func:`appfusion.fusion.anchor_information`).
    """

    def __init__(self, vertices, faces, step: int = 2, iterations: int = 3, max_dist: float = 0.004,
                 sigma_depth: float = 0.0007, sigma_rot: float = np.radians(0.2), sigma_trans: float = 0.0015,
                 min_pairs: int = 200, depth_weight: float = 1.0, anchor_sigma: tuple[float, float] = (3e-4, 6e-5),
                 sight_weighting: bool = False):
        V = np.asarray(vertices, dtype=np.float32)
        F = np.asarray(faces)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or len(V) == 0 or len(F) == 0:
            raise AppFusionError(f"PoseRefiner: needs a non-empty mesh, got vertices {V.shape} and faces {F.shape}")
        if not np.isfinite(V).all():
            raise AppFusionError("PoseRefiner: mesh vertices contain NaN or inf")
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F.astype(np.uint32)))
        self.lo, self.hi = V.min(0).astype(np.float64) - 0.01, V.max(0).astype(np.float64) + 0.01
        self.step, self.iterations, self.max_dist = int(step), int(iterations), float(max_dist)
        self.sigma_depth = float(sigma_depth)
        self.prior = np.r_[np.full(3, float(sigma_rot) ** -2), np.full(3, float(sigma_trans) ** -2)]
        self.min_pairs = int(min_pairs)
        self.depth_weight = float(depth_weight)
        if not (self.depth_weight > 0 and len(anchor_sigma) == 2 and min(anchor_sigma) > 0):
            raise AppFusionError(f"PoseRefiner: depth_weight and anchor_sigma must be positive, got "
                                 f"{depth_weight} and {anchor_sigma}")
        self.anchor_sigma = (float(anchor_sigma[0]), float(anchor_sigma[1]))
        self.sight_weighting = bool(sight_weighting)

    def refine(self, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
               anchors: tuple | None = None) -> tuple[np.ndarray, int]:
        """The refined camera-to-world pose of one depth frame, and the number of pairs used (0: the
        pose came back unchanged: too few pixels on the mesh and no anchors).

        Parameters
        ----------
        depth : (H, W) float array
            Metres, NaN or 0 invalid.
        intrinsics : Intrinsics
            Of the depth image.
        pose : (4, 4) array
            Tracked camera-to-world pose.
        anchors : (centres_cam, centres_world, normal_world), optional
            Circle centres seen in this frame (camera frame, (k, 3)) and where they are in the
            mesh's frame ((k, 3)), and the support plane's unit normal there (None: isotropic, the
            in-plane sigma). Each adds ``e^T W e``, ``e = C_world - T c_cam``, ``W`` the inverse of
            the anchor covariance (``anchor_sigma`` within / across the plane).
        """
        T = np.asarray(pose, dtype=np.float64)
        d = np.asarray(depth)
        if d.shape != intrinsics.shape:
            raise AppFusionError(f"PoseRefiner: depth image {d.shape} does not match the intrinsics {intrinsics.shape}")
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise AppFusionError(f"PoseRefiner: pose must be a finite 4x4 matrix, got shape {T.shape}")
        st = self.step
        z = d[::st, ::st].astype(np.float64)
        v, u = np.mgrid[0:d.shape[0]:st, 0:d.shape[1]:st]
        ok = np.isfinite(z) & (z > 0)
        z = z[ok]
        Pc = np.stack([(u[ok] - intrinsics.cx) / intrinsics.fx * z, (v[ok] - intrinsics.cy) / intrinsics.fy * z, z], 1)
        Pw = Pc @ T[:3, :3].T + T[:3, 3]
        Pc = Pc[np.all((Pw > self.lo) & (Pw < self.hi), axis=1)]
        anc = self._anchor_terms(anchors, T[:3, :3])
        if len(Pc) < self.min_pairs and anc is None:
            return T.copy(), 0
        total = np.zeros(6)
        used = 0
        for _ in range(self.iterations):
            H = np.diag(self.prior)
            g = -self.prior * total
            if len(Pc) >= self.min_pairs:
                Pw = Pc @ T[:3, :3].T + T[:3, 3]
                q = self.scene.compute_closest_points(o3d.core.Tensor(Pw.astype(np.float32)))
                Q = q["points"].numpy().astype(np.float64)
                n = q["primitive_normals"].numpy().astype(np.float64)
                diff = Pw - Q
                near = np.einsum("ij,ij->i", diff, diff) < self.max_dist ** 2
                used = int(near.sum())
            else:
                used = 0
            if used >= self.min_pairs:
                P, n, r = Pw[near], n[near], -np.einsum("ij,ij->i", diff[near], n[near])
                A = np.concatenate([np.cross(P, n), n], axis=1)            # d r / d (omega, tau), left update
                w = np.minimum(1.0, 0.001 / np.maximum(np.abs(r), 1e-12)) * (self.depth_weight / self.sigma_depth ** 2)
                H = H + (A * w[:, None]).T @ A                              # (Huber, 1 mm)
                g = g + (A * w[:, None]).T @ r
            elif anc is None:
                return np.asarray(pose, dtype=np.float64).copy(), 0
            if anc is not None:
                c_cam, C_w, Ws = anc
                p = c_cam @ T[:3, :3].T + T[:3, 3]
                for pk, Ck, W in zip(p, C_w, Ws):                           # d p / d (omega, tau) = [-[p]x, I]
                    J = np.concatenate([-_skew(pk), np.eye(3)], axis=1)
                    H = H + J.T @ W @ J
                    g = g + J.T @ W @ (Ck - pk)
            xi = np.linalg.solve(H, g)
            total += xi
            T = _twist_to_pose(xi) @ T
        return T, used

    def _anchor_terms(self, anchors, rotation: np.ndarray):
        """(centres_cam, centres_world, [W per anchor]) of :meth:`refine`'s anchors, or None;
        ``rotation``: the initial pose's, which turns each centre's line of sight into the world."""
        if anchors is None:
            return None
        c_cam = np.asarray(anchors[0], dtype=np.float64).reshape(-1, 3)
        C_w = np.asarray(anchors[1], dtype=np.float64).reshape(-1, 3)
        if len(c_cam) != len(C_w):
            raise AppFusionError(f"PoseRefiner: {len(c_cam)} anchor centres seen but {len(C_w)} placed")
        ok = np.isfinite(c_cam).all(axis=1) & np.isfinite(C_w).all(axis=1)
        if not ok.any():
            return None
        s_in, s_n = self.anchor_sigma
        nrm = anchors[2] if len(anchors) > 2 else None
        nrm = None if nrm is None else np.asarray(nrm, dtype=np.float64)
        if nrm is not None and (not np.isfinite(nrm).all() or np.linalg.norm(nrm) < 1e-9):
            nrm = None
        c_cam, C_w = c_cam[ok], C_w[ok]
        if nrm is not None and self.sight_weighting:
            Ws = [anchor_information(nrm, s_in ** -2, s_n ** -2, sight) for sight in c_cam @ rotation.T]
        else:
            Ws = [anchor_information(nrm, s_in ** -2, s_n ** -2)] * len(c_cam)
        return c_cam, C_w, Ws
