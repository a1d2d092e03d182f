"""The IR pass: IR frames -> registered reflectance samples -> BRDF-cut leaf HBSABs (paper §5.1, §5.2).

For every IR frame (with its depth image and tracked pose) the pass

1. registers each valid depth pixel to the nearest sampled surface point
   (:func:`appfusion.points.register_pixels`, the §4.1 spatial grid; points facing away are not
   matched),
2. back-projects the pixel to its 3-D point ``X`` (world frame) and forms the directions to the camera
   ``w_o = (C - X) / |C - X|`` and to the emitter ``w_i = (E - X) / |E - X|`` (``E`` = the emitter position,
   ``meta["emitter_position_m"]`` in the depth-camera frame, moved to the world by the pose), both
   rotated into the local frame of the registered point (its normal = +z), tilted to the pixel's own
   place on the surface: where the pixel's ray meets the point's tangent plane, by the gradient of
   the normal along that plane (:func:`appfusion.points.normal_gradient`; the nearest point is on
   average half a point spacing away, and on a curved surface its normal is not the pixel's),
3. turns the raw IR value into a reflectance sample with the device profile
   (``calibration.ir_profile.IRProfile.apply``: ``((raw - b0) / gain)^(1/gamma) / (E[x](|E - X|) cos theta_i)``;
   saturated pixels keep their clipped value and are counted per texel, so that the Ward fit can
   model texels a clipped highlight biased), and, when the profile has the emitter's pattern map
   (:mod:`calibration.ir_pattern`), divides it by the map's value at the pixel's emitter direction
   (the camera-frame point relative to the emitter),
4. adds the samples to the HBSABs of the points' BRDF-cut leaves (Eq. 3; samples with ``theta_i`` or
   ``theta_o`` beyond the grazing cut-off are dropped), one ``bincount`` per channel for the frame.

:meth:`IRPass.result` runs the cut, the clustering and the Ward fits (:class:`appfusion.brdf_cut.BRDFCut`).
The state is the leaf HBSAB array plus the tree: its size depends on the points and ``hbsab_n`` only,
never on the number of frames.

The IR image must be on the depth image's pixel grid (Kinect v1: ``depth_to_ir`` is the identity;
Azure Kinect and OAK-D give depth registered to their IR/mono camera).
"""

from __future__ import annotations

import time

import numpy as np

from .brdf import local_frame
from .brdf_cut import BRDFCut, CutResult
from .errors import AppFusionError
from .frame import Intrinsics
from .hbsab import CH_SAT, DEFAULT_MAX_ANGLE_DEG, DEFAULT_N, _channels
from .points import normal_at_offset
from .points import normal_gradient as _normal_gradient


class IRPass:
    """Accumulates IR frames into BRDF-cut HBSABs and clusters / fits them (paper §5.1-5.2).

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Sampled surface points (world = marker frame, metres) and unit normals (paper §4.1).
    profile : calibration.ir_profile.IRProfile
        IR device profile (background, response, emitter model).
    hbsab_n : int
        HBSAB texels per side (default 32).
    min_leaf : int
        Minimum points per BRDF-cut leaf (default 64).
    max_angle_deg : float
        Grazing cut-off for ``w_i`` and ``w_o`` (default 80 degrees).
    max_dist : float, optional
        Largest pixel-to-point registration distance, metres (default: 1.5 x the point spacing).
    areas : (N,) array, optional
        Point areas for area-weighted merging.
    normal_gradient : bool
        Give each sample the normal at its own place on the surface, not its registered point's
        (:func:`appfusion.points.normal_gradient`; default True; see the module docstring, step 2).
    rim : (N,) bool array, optional
        Points at the surface's open boundary; their leaves stay out of the Ward fits
        (:class:`appfusion.brdf_cut.BRDFCut`).
    k : int, optional
        Number of clusters (None: automatic).
    **cut_kwargs
        Further :class:`appfusion.brdf_cut.BRDFCut` parameters (reliability, k selection, fitting).

    Attributes
    ----------
    cut : BRDFCut
    stats : dict
        Counters: frames, registered pixels, samples used, of those saturated (kept, clipped and
        flagged), dropped as grazing (or non-finite); time spent in the HBSAB update (``update_s``).
    """

    def __init__(self, positions, normals, profile, hbsab_n: int = DEFAULT_N, min_leaf: int = 64,
                 max_angle_deg: float = DEFAULT_MAX_ANGLE_DEG, max_dist: float | None = None, areas=None,
                 k: int | None = None, normal_gradient: bool = True, rim=None, **cut_kwargs):
        self.pattern = getattr(profile, "pattern", None)
        if "emitter" not in cut_kwargs:                    # clipped highlights are modelled with it
            if getattr(profile, "emitter_model", "") != "shifted_gamma":
                cut_kwargs["emitter"] = "flat"
            elif self.pattern is not None:
                cut_kwargs["emitter"] = ("pattern", profile.k, profile.theta, profile.shift)
            else:
                cut_kwargs["emitter"] = (profile.k, profile.theta, profile.shift)
        self.cut = BRDFCut(positions, normals, n=hbsab_n, min_leaf=min_leaf, max_angle_deg=max_angle_deg,
                           areas=areas, k=k, rim=rim, **cut_kwargs)
        self.positions = np.ascontiguousarray(self.cut.positions, dtype=np.float32)
        self.normals = np.ascontiguousarray(self.cut.normals, dtype=np.float32)
        self.profile = profile
        self.max_dist = max_dist
        F = local_frame(self.cut.normals).reshape(-1, 9)      # rows t, b, n
        self._nf = [np.ascontiguousarray(F[:, j], dtype=np.float32) for j in range(9)]
        n2 = self.cut.n * self.cut.n
        self._leaf_key = self.cut.tree.point_leaf.astype(np.int64) * n2
        self._cos_max = np.float32(np.cos(np.radians(max_angle_deg)))
        self.stats = {"frames": 0, "registered": 0, "used": 0, "saturated": 0, "grazing": 0, "update_s": 0.0}
        # n . p per point: the tangent planes of the surface depth (pattern look-up, normal tilt)
        self._n_dot_p = np.einsum("ij,ij->i", self.positions, self.normals).astype(np.float32)
        # the normal's gradient along each point's tangent plane, and t . p, b . p (normal tilt)
        self._grad = None
        if normal_gradient and len(self.positions) > 2:
            G = _normal_gradient(self.positions, self.normals)
            self._grad = [np.ascontiguousarray(G[:, i, j]) for i in (0, 1) for j in (0, 1)]
            self._t_dot_p = np.einsum("ij,ij->i", self.positions, F[:, 0:3]).astype(np.float32)
            self._b_dot_p = np.einsum("ij,ij->i", self.positions, F[:, 3:6]).astype(np.float32)

    # -- frames ----------------------------------------------------------------------------------
    def add_frame(self, ir: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                  emitter_position=None) -> int:
        """Add one IR frame (paper §5.1).

        Parameters
        ----------
        ir : (H, W) array
            Raw IR, counts, on the depth image's pixel grid.
        depth : (H, W) float array
            Metres, NaN invalid.
        intrinsics : Intrinsics
            Of the depth (= IR) image.
        pose : (4, 4) array
            Camera-to-world pose of the depth camera.
        emitter_position : 3 floats, optional
            Emitter in the depth-camera frame, metres (default: the profile's).

        Returns
        -------
        int
            Samples added.
        """
        from .points import register_pixels

        ir = np.asarray(ir)
        depth = np.asarray(depth, dtype=np.float32)
        if ir.shape != depth.shape or depth.shape != intrinsics.shape:
            raise AppFusionError(f"IR pass: IR image {ir.shape}, depth {depth.shape} and intrinsics "
                                 f"{intrinsics.shape} must be the same size (IR registered to depth)")
        T = np.asarray(pose, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise AppFusionError(f"IR pass: pose must be a finite 4x4 matrix, got shape {T.shape}")
        e = np.asarray(self.profile.emitter_position_m if emitter_position is None else emitter_position,
                       dtype=np.float64).reshape(3)
        pix, pts = register_pixels(self.positions, self.normals, depth, intrinsics, T, self.max_dist)
        self.stats["frames"] += 1
        if len(pix) == 0:
            return 0
        W = intrinsics.width
        z = depth.ravel()[pix]
        u = (pix % W).astype(np.float32)
        v = (pix // W).astype(np.float32)
        xc = (u - np.float32(intrinsics.cx)) * np.float32(1.0 / intrinsics.fx) * z
        yc = (v - np.float32(intrinsics.cy)) * np.float32(1.0 / intrinsics.fy) * z
        R = T[:3, :3].astype(np.float32)
        t = T[:3, 3]
        X = [R[a, 0] * xc + R[a, 1] * yc + R[a, 2] * z + np.float32(t[a]) for a in range(3)]
        emitter_world = T[:3, :3] @ e + t
        raw = ir.ravel()[pix]
        self.stats["registered"] += len(pix)
        m, frame = self._frame_terms(pts, xc, yc, z, X, T, e)
        return self._add(pts, X[0], X[1], X[2], raw, t, emitter_world, m, frame)

    def _frame_terms(self, pts, xc, yc, z, X, T, emitter_position):
        """Per-pixel terms beside the raw values, for :meth:`_add`: the pattern map's value (None
        without a map) and each sample's local frame (9 arrays ``t, b, n``; None when it is just its
        point's), tilted to where the pixel's ray meets the point's tangent plane when the pass has
        the normal's gradient (``normal_gradient``, :func:`appfusion.points.normal_at_offset`).

        ``xc, yc, z``: the pixels' camera-frame points; ``X``: the same in the world frame (3 arrays)."""
        if self.pattern is None and self._grad is None:
            return None, None
        pts = np.asarray(pts, dtype=np.intp)
        Nf = [np.take(f, pts) for f in self._nf]          # np.take: ~2x faster than fancy indexing
        zp = self._surface_depth(pts, xc, yc, z, T, Nf[6:9])
        m = None if self.pattern is None else self._pattern_values(xc, yc, z, zp, emitter_position)
        if self._grad is not None:
            r = zp / z
            c = np.asarray(T, dtype=np.float64)[:3, 3].astype(np.float32)
            Xs = [c[a] + r * (X[a] - c[a]) for a in range(3)]
            du = Nf[0] * Xs[0] + Nf[1] * Xs[1] + Nf[2] * Xs[2] - np.take(self._t_dot_p, pts)
            dv = Nf[3] * Xs[0] + Nf[4] * Xs[1] + Nf[5] * Xs[2] - np.take(self._b_dot_p, pts)
            Nf = normal_at_offset(Nf, [np.take(g, pts) for g in self._grad], du, dv)
        return m, Nf

    def _pattern_values(self, xc, yc, z, zp, emitter_position) -> np.ndarray:
        """The pattern map's value for each registered pixel: its emitter direction from the pixel's
        ray met with the registered point's tangent plane (depth ``zp``, :meth:`_surface_depth`),
        camera axes."""
        e = np.asarray(emitter_position, dtype=np.float32).reshape(3)
        ez = zp - e[2]
        r = zp / z
        return self.pattern.lookup((xc * r - e[0]) / ez, (yc * r - e[1]) / ez)

    def _surface_depth(self, pts, xc, yc, z, T, normals=None) -> np.ndarray:
        """Depth where each pixel's ray meets the tangent plane of its registered point (metres).

        The pattern map's cells are about one pixel wide: a direction taken from the raw depth
        (Kinect noise ~1.5 mm at 60 cm moves it by ~0.2 cell) picks the neighbouring cell for many
        pixels; the fused surface is ten times smoother. Falls back to the raw depth at grazing rays
        and where the plane lies more than 1 cm off. In the world frame: the plane ``n . X = n . p``
        (``n . p`` kept per point), the ray ``C + s R (x/z, y/z, 1)``, so ``z' = (n . p - n . C) / (n . R r)``."""
        f32 = np.float32
        R = T[:3, :3].astype(f32)
        t = T[:3, 3].astype(f32)
        nx, ny, nz = normals if normals is not None else (np.take(self._nf[j], pts) for j in (6, 7, 8))
        iz = f32(1.0) / z
        rx, ry = xc * iz, yc * iz
        den = (nx * (R[0, 0] * rx + R[0, 1] * ry + R[0, 2]) + ny * (R[1, 0] * rx + R[1, 1] * ry + R[1, 2])
               + nz * (R[2, 0] * rx + R[2, 1] * ry + R[2, 2]))
        num = np.take(self._n_dot_p, pts) - (nx * t[0] + ny * t[1] + nz * t[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            zp = num / den
        bad = ~(np.abs(den) > f32(0.2)) | ~(np.abs(zp - z) < f32(0.01))
        return np.where(bad, z, zp).astype(f32)

    def add(self, frame, emitter_position=None) -> int:
        """Add a :class:`appfusion.frame.Frame` (needs ``ir``, ``depth``, depth intrinsics and ``pose``).

        Frames without IR or depth (e.g. of an RGB pass) add nothing and return 0.
        """
        if frame.ir is None or frame.depth is None:
            return 0
        intr = frame.depth_intrinsics or frame.ir_intrinsics
        if intr is None:
            raise AppFusionError(f"IR pass, frame {frame.index}: no depth intrinsics")
        if frame.pose is None:
            raise AppFusionError(f"IR pass, frame {frame.index}: no camera pose (track the frame first)")
        return self.add_frame(frame.ir, frame.depth, intr, frame.pose, emitter_position)

    def add_samples(self, point_idx: np.ndarray, points: np.ndarray, camera_center, emitter_center,
                    raw: np.ndarray, pattern: np.ndarray | None = None) -> int:
        """Add registered pixels (steps 2-4 of the module docstring); the per-frame hot path.

        Parameters
        ----------
        point_idx : (m,) int array
            Registered point of each pixel.
        points : (m, 3) array
            The pixels' 3-D points, world frame, metres.
        camera_center, emitter_center : 3 floats
            Camera centre and emitter position, world frame, metres.
        raw : (m,) array
            Raw IR values, counts.
        pattern : (m,) array, optional
            The emitter pattern's relative intensity at each pixel's emitter direction
            (``profile.pattern``, :mod:`calibration.ir_pattern`); divided out of the samples.

        Returns
        -------
        int
            Samples added (grazing ones and non-finite values are dropped; saturated ones are kept
            with their clipped value and flagged, see :mod:`appfusion.hbsab`).
        """
        X = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        if pattern is not None:
            pattern = np.asarray(pattern, dtype=np.float32).reshape(-1)
            if len(pattern) != len(X) or not (np.isfinite(pattern).all() and (pattern > 0).all()):
                raise AppFusionError(f"IR pass: pattern values must be {len(X)} finite positive numbers")
        return self._add(point_idx, X[:, 0], X[:, 1], X[:, 2], raw, camera_center, emitter_center, pattern)

    def _add(self, point_idx, xs, ys, zs, raw, camera_center, emitter_center, pattern=None, frame=None) -> int:
        t0 = time.perf_counter()
        f32 = np.float32
        pidx = np.asarray(point_idx, dtype=np.int64).reshape(-1)
        raw = np.asarray(raw, dtype=f32).reshape(-1)
        if not (len(pidx) == len(xs) == len(raw)):
            raise AppFusionError(f"IR pass: {len(pidx)} point indices, {len(xs)} points and {len(raw)} IR values")
        if len(pidx) == 0:
            return 0
        Cx, Cy, Cz = (f32(c) for c in np.asarray(camera_center, dtype=np.float64).reshape(3))
        Ex, Ey, Ez = (f32(c) for c in np.asarray(emitter_center, dtype=np.float64).reshape(3))
        # each sample's local frame: its point's, or tilted to the sample's own place (_frame_terms)
        Nf = frame if frame is not None else [np.take(f, pidx) for f in self._nf]
        nx, ny, nz = Nf[6], Nf[7], Nf[8]
        ox, oy, oz = Cx - xs, Cy - ys, Cz - zs                # towards the camera
        ix, iy, iz = Ex - xs, Ey - ys, Ez - zs                # towards the emitter
        ilo = 1.0 / np.sqrt(ox * ox + oy * oy + oz * oz)
        di = np.sqrt(ix * ix + iy * iy + iz * iz)
        idi = 1.0 / di
        co = (nx * ox + ny * oy + nz * oz) * ilo
        ci = (nx * ix + ny * iy + nz * iz) * idi
        cm = self._cos_max
        keep = (co > cm) & (ci > cm)
        if not np.isfinite(raw).all():
            keep &= np.isfinite(raw)
            raw = np.where(keep, raw, f32(0.0))
        m = int(np.count_nonzero(keep))
        n_drop = len(keep) - m
        if m == 0:
            self._count(0, 0, n_drop, t0)
            return 0
        w = co * keep                      # dropped samples keep weight 0 (cheaper than compacting)
        if n_drop:
            ci = np.maximum(ci, cm)        # keeps their arithmetic finite
            co = np.maximum(co, cm)
        # world half vector (unnormalised sum of unit vectors), then its local x, y; local z = ci + co
        hx = ox * ilo + ix * idi
        hy = oy * ilo + iy * idi
        hz = oz * ilo + iz * idi
        hlx = Nf[0] * hx + Nf[1] * hy + Nf[2] * hz
        hly = Nf[3] * hx + Nf[4] * hy + Nf[5] * hz
        sat = raw >= f32(self.profile.saturation)
        n_sat = int(np.count_nonzero(sat))
        if n_sat and n_drop:
            sat &= keep
            n_sat = int(np.count_nonzero(sat))
        value = self.profile.apply_valid(raw, di, ci)           # clips raw at saturation
        if pattern is not None:
            value /= pattern
        w_val = w
        if n_sat:
            # running mean of the clip level in reflectance units (the censored Ward fit's c)
            self.cut.clip_sum += float(np.sum(value[sat], dtype=np.float64))
            self.cut.clip_n += n_sat
            if pattern is not None:
                # pattern divided out: an unclipped sample is unbiased, a clipped one only a lower
                # bound, so clipped samples stay out of the texel means (counted in WSAT alone)
                w_val = np.where(sat, f32(0.0), w)
        s = _channels(hlx, hly, ci + co, ci, co, value, w_val, self.cut.n)
        if n_sat:
            s.channels[CH_SAT] = w * sat
        self.cut.leaves.add(np.take(self._leaf_key, pidx) + s.texel, s.channels)
        self._count(m, n_sat, n_drop, t0)
        return m

    def _count(self, used, sat, graze, t0):
        self.stats["used"] += used
        self.stats["saturated"] += sat
        self.stats["grazing"] += graze
        self.stats["update_s"] += time.perf_counter() - t0

    # -- results -------------------------------------------------------------------------------
    def result(self, k: int | None = None, fit: bool = True) -> CutResult:
        """Clusters, labels and Ward fits so far (:meth:`appfusion.brdf_cut.BRDFCut.result`)."""
        return self.cut.result(k=k, fit=fit)

    def fit_clusters(self, labels) -> list:
        """Ward fits of the clusters of given per-point labels (:meth:`BRDFCut.fit_clusters`)."""
        return self.cut.fit_clusters(labels)

    def set_labels(self, point_idx, label: int) -> None:
        """Manual refinement: paint points with a cluster label (persists across re-clustering)."""
        self.cut.set_labels(point_idx, label)

    @property
    def nbytes(self) -> int:
        """Memory of the pass's state, bytes (independent of the number of frames added)."""
        return int(self.cut.nbytes + sum(a.nbytes for a in self._nf) + self._leaf_key.nbytes
                   + (0 if self._n_dot_p is None else self._n_dot_p.nbytes))
