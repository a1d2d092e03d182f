"""Discretised object surface: point sampling, bilateral normal filter, pixel-to-point registration.

Paper §4.1: after the geometry is separated from the background, the object's surface mesh is
discretised "by randomly sampling points with a probability proportional to the surface area"; the
points {p_i} are "stored in a spatial grid based on their positions, for fast point-wise nearest
neighbor query" (used by the IR pass, §5.1, and the RGB pass, §5.3), and the normals {n_i} are
smoothed with a bilateral filter [Fleishman et al. 2003].

The spatial grid
----------------
:class:`PointGrid` is a dense voxel look-up table over the points' bounding box (grown by
``max_dist``). Each cell of edge ``cell`` (default ``min(max_dist / 2, spacing)``) that lies within reach of the
surface stores the index of the sampled point nearest to the cell's *centre* (computed once with a
k-d tree). Registering a depth image then costs a handful of vectorised numpy operations per pixel:
back-project, compute the cell, read the table, check the true distance. The answer is the nearest
point up to the cell size: the returned point is at most ``cell * sqrt(3)`` farther from the pixel
than the true nearest point, and never farther than ``max_dist``.

:func:`register_pixels` is the entry point other passes call; it keeps the grids of the last few
point sets it saw, so calling it every frame with the same arrays builds the grid once.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .brdf import local_frame
from .errors import AppFusionError, EstimationError
from .frame import Intrinsics

__all__ = ["PointGrid", "register_pixels", "mean_spacing", "sample_points", "bilateral_filter_normals",
           "bilateral_denoise_points", "sharpen_creases", "normal_gradient", "normal_at_offset", "NormalField"]

#: largest look-up table a grid may allocate (cells; int32 each, so 2**25 cells = 128 MiB)
MAX_GRID_CELLS = 2 ** 25

#: smallest default registration distance, metres: Kinect depth noise is 1.2-2 mm (sigma) at 0.5-1 m,
#: so with 1.5 x the point spacing alone (~1 mm for 100k points) only ~60% of an object's pixels
#: register (measured on the geometry test scene); 3 mm registers 98%.
MIN_REGISTER_DIST = 0.003


def _check_points(positions: np.ndarray, normals: np.ndarray | None, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    P = np.asarray(positions)
    if P.ndim != 2 or P.shape[1] != 3:
        raise AppFusionError(f"{where}: positions must have shape (N, 3), got {P.shape}")
    if len(P) == 0:
        raise EstimationError(f"{where}: no points given")
    if not np.isfinite(P).all():
        raise AppFusionError(f"{where}: positions contain NaN or infinite values "
                             f"(first bad row {int(np.flatnonzero(~np.isfinite(P).all(1))[0])})")
    if normals is not None:
        Nn = np.asarray(normals)
        if Nn.shape != P.shape:
            raise AppFusionError(f"{where}: normals of shape {Nn.shape} do not match positions {P.shape}")
        normals = Nn
    return P, normals


def interior_mask(positions: np.ndarray, labels: np.ndarray, radius: float) -> np.ndarray:
    """Points farther than ``radius`` from every point of another label (beyond the paper).

    Along a material seam a point's registered pixels (IR and colour) and its neighbourhood mix both
    materials; the per-cluster estimates that such mixtures bias (a cluster's rho_s in the colour
    pass, its IR lobe refitted to the final clusters) pool only the points this leaves True.

    Parameters
    ----------
    positions : (N, 3) array, metres
    labels : (N,) int array
    radius : float, metres (0: every point is interior)

    Returns
    -------
    (N,) bool array
    """
    P = np.asarray(positions, dtype=np.float64)
    lab = np.asarray(labels)
    if P.ndim != 2 or P.shape[1] != 3 or lab.shape != (len(P),):
        raise AppFusionError(f"interior_mask: need (N, 3) positions and (N,) labels, got {P.shape} and {lab.shape}")
    if not (np.isfinite(radius) and radius >= 0):
        raise AppFusionError(f"interior_mask: radius must be finite and >= 0, got {radius}")
    far = np.ones(len(P), bool)
    if radius == 0:
        return far
    for c in np.unique(lab):
        m = lab == c
        if m.all():
            continue
        d, _ = cKDTree(P[~m]).query(P[m], distance_upper_bound=radius)
        far[m] = ~(d <= radius)
    return far


def interior_or_all(far: np.ndarray, labels: np.ndarray, use: np.ndarray | None = None,
                    min_fraction: float = 0.25) -> np.ndarray:
    """The points of ``use`` (default all) that are ``far`` (:func:`interior_mask`), per label where
    at least ``min_fraction`` of its points in ``use`` are; a label with fewer keeps all of its
    points in ``use`` (a small cluster that is all seam still gets an estimate). (N,) bool."""
    lab = np.asarray(labels)
    use = np.ones(len(lab), bool) if use is None else np.asarray(use, bool)
    inner = use & np.asarray(far, bool)
    k = int(lab.max()) + 1 if lab.size else 0
    enough = np.bincount(lab[inner], minlength=k) >= min_fraction * np.bincount(lab[use], minlength=k)
    return np.where(enough[lab], inner, use)


def check_oriented_points(positions, normals, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Validated surface points: (N, 3) float64 positions (N >= 1) and their normals made unit length.

    Raises
    ------
    AppFusionError
        Wrong shapes, a non-finite position or normal, or a zero normal, naming ``where`` and the point.
    """
    P = np.asarray(positions, dtype=np.float64)
    Nn = np.asarray(normals, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0:
        raise AppFusionError(f"{where}: positions must have shape (N, 3) with N >= 1, got {P.shape}")
    if Nn.shape != P.shape:
        raise AppFusionError(f"{where}: normals of shape {Nn.shape} do not match positions {P.shape}")
    bad = ~(np.isfinite(P).all(1) & np.isfinite(Nn).all(1))
    if bad.any():
        raise AppFusionError(f"{where}: point {int(np.flatnonzero(bad)[0])} has a non-finite position or normal")
    ln = np.linalg.norm(Nn, axis=1)
    if np.any(ln < 1e-6):
        raise AppFusionError(f"{where}: point {int(np.flatnonzero(ln < 1e-6)[0])} has a zero normal")
    return P, Nn / ln[:, None]


def mean_spacing(positions: np.ndarray, k: int = 8) -> float:
    """Mean point spacing of a point set sampled on a surface, metres.

    Defined as ``sqrt(area per point)``: the local density is estimated from the median distance
    ``r_k`` to the k-th nearest neighbour (``rho = k / (pi r_k^2)`` on a surface), giving
    ``spacing = r_k * sqrt(pi / k)``. For uniformly sampled points this equals
    ``sqrt(surface area / N)``; a disc of radius 1.5 x spacing then contains a point with
    probability ~0.999.

    Parameters
    ----------
    positions : (N, 3) array
        Points, metres.
    k : int
        Neighbour rank used for the density estimate.
    """
    P, _ = _check_points(positions, None, "mean_spacing")
    if len(P) < 2:
        raise EstimationError("mean_spacing: need at least two points")
    k = int(min(k, len(P) - 1))
    sub = P if len(P) <= 20000 else P[np.random.default_rng(0).choice(len(P), 20000, replace=False)]
    tree = cKDTree(P)
    d, _ = tree.query(sub, k=k + 1, workers=-1)
    rk = float(np.median(d[:, k]))
    if not rk > 0:
        raise EstimationError("mean_spacing: points are all coincident")
    return rk * float(np.sqrt(np.pi / k))


class PointGrid:
    """Voxel look-up table for nearest-point queries of depth pixels (paper §4.1 "spatial grid").

    Parameters
    ----------
    positions : (N, 3) array
        Sampled surface points in the world (marker) frame, metres.
    normals : (N, 3) array or None
        Unit normals of the points; when given, :meth:`register` rejects matches whose point faces
        away from the camera (a pixel on the front of a thin part is not registered to its back).
    max_dist : float, optional
        Largest pixel-to-point distance that registers, metres; default
        ``max(1.5 x mean_spacing, MIN_REGISTER_DIST)``: 1.5 spacings, but at least the depth noise.
    cell : float, optional
        Cell edge, metres; default ``min(max_dist / 2, mean_spacing)`` (grown if the table would
        exceed :data:`MAX_GRID_CELLS`).
    """

    def __init__(self, positions: np.ndarray, normals: np.ndarray | None = None,
                 max_dist: float | None = None, cell: float | None = None):
        P, Nn = _check_points(positions, normals, "PointGrid")
        self.positions = np.ascontiguousarray(P, dtype=np.float32)
        self.normals = None if Nn is None else np.ascontiguousarray(Nn, dtype=np.float32)
        spacing = mean_spacing(self.positions) if len(P) > 1 else 1e-3
        if max_dist is None:
            max_dist = max(1.5 * spacing, MIN_REGISTER_DIST)
        if not (np.isfinite(max_dist) and max_dist > 0):
            raise AppFusionError(f"PointGrid: max_dist must be a positive distance in metres, got {max_dist}")
        self.max_dist = float(max_dist)
        s = min(self.max_dist / 2, spacing) if cell is None else float(cell)
        if not s > 0:
            raise AppFusionError(f"PointGrid: cell must be positive, got {cell}")
        lo = self.positions.min(0).astype(np.float64) - self.max_dist
        hi = self.positions.max(0).astype(np.float64) + self.max_dist
        while True:
            dims = np.maximum(np.ceil((hi - lo) / s).astype(np.int64) + 1, 1)
            if int(np.prod(dims)) <= MAX_GRID_CELLS:
                break
            s *= 1.25
        self.cell = float(s)
        self.origin = lo
        self.dims = dims
        self._build()

    def _build(self) -> None:
        s, dims, lo = self.cell, self.dims, self.origin
        ci = np.floor((self.positions - lo) / s).astype(np.int64)
        np.clip(ci, 0, dims - 1, out=ci)
        occ = np.zeros(tuple(dims), bool)
        occ[ci[:, 0], ci[:, 1], ci[:, 2]] = True
        reach = self.max_dist + s * np.sqrt(3) / 2      # a cell whose centre is farther cannot register
        r = int(np.ceil(reach / s))
        band = ndimage.binary_dilation(occ, structure=ndimage.generate_binary_structure(3, 3), iterations=r)
        cells = np.flatnonzero(band)
        centres = (np.stack(np.unravel_index(cells, tuple(dims)), axis=1) + 0.5) * s + lo
        self._tree = cKDTree(self.positions)
        dist, idx = self._tree.query(centres, distance_upper_bound=reach, workers=-1)
        ok = np.isfinite(dist)
        self.lut = np.full(int(np.prod(dims)) + 1, -1, np.int32)   # + a sentinel cell
        self.lut[cells[ok]] = idx[ok].astype(np.int32)
        self.strides = np.array([dims[1] * dims[2], dims[2], 1], np.int64)
        self._pc = [np.ascontiguousarray((self.positions[:, a] - lo[a]) / s, dtype=np.float32) for a in range(3)]
        self._corners = lo + np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) * (dims * s)

    @property
    def nbytes(self) -> int:
        """Memory of the look-up table, bytes."""
        return int(self.lut.nbytes)

    def nearest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid nearest point of arbitrary world points.

        Parameters
        ----------
        points : (M, 3) array, metres (world frame).

        Returns
        -------
        query_idx : (K,) int64
            Rows of ``points`` that found a sampled point within ``max_dist``.
        point_idx : (K,) int32
            The matched sampled point of each.
        """
        Q = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            f = (Q - self.origin) / self.cell
            ok = np.isfinite(f).all(1) & (f >= 0).all(1) & (f < self.dims).all(1)
        qi = np.flatnonzero(ok)
        c = f[qi].astype(np.int64)
        idx = self.lut[c @ self.strides]
        m = idx >= 0
        qi, idx = qi[m], idx[m]
        d2 = ((Q[qi] - self.positions[idx]) ** 2).sum(1)
        keep = d2 <= self.max_dist ** 2
        return qi[keep], idx[keep]

    def register(self, depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                 backface_cos: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Register the pixels of a depth image to the sampled points (paper §5.1, "register it to
        the geometry, by finding the nearest neighbor p_i in the spatial grid").

        Parameters
        ----------
        depth : (H, W) float array
            Depth in metres, NaN (or 0) invalid; lens distortion is ignored.
        intrinsics : Intrinsics
            Intrinsics of the depth image.
        pose : (4, 4) array
            Camera-to-world pose of the depth camera (world = the frame of ``positions``).
        backface_cos : float
            With normals, a match is dropped when ``n . v < backface_cos``, ``v`` the unit direction
            from the point to the camera (0: drop points that face away).

        Returns
        -------
        pixel_idx : (K,) int64
            Flat indices ``row * W + col`` of the pixels that registered, ascending.
        point_idx : (K,) int32
            Index of the sampled point each registered to (within ``max_dist``).
        """
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.shape != intrinsics.shape:
            raise AppFusionError(f"register_pixels: depth image of shape {depth.shape} does not match the "
                                 f"intrinsics ({intrinsics.height}x{intrinsics.width})")
        T = np.asarray(pose, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise AppFusionError(f"register_pixels: pose must be a finite 4x4 matrix, got shape {T.shape}")
        if depth.dtype != np.float32:
            depth = depth.astype(np.float32)
        H, W = depth.shape
        R, t = T[:3, :3], T[:3, 3]
        # Crop to the image rectangle the grid's box projects to (when it lies in front of the camera).
        r0, r1, c0, c1 = 0, H, 0, W
        cam = (self._corners - t) @ R              # world -> camera: R^T (x - t)
        if (cam[:, 2] > 1e-3).all():
            u = intrinsics.fx * cam[:, 0] / cam[:, 2] + intrinsics.cx
            v = intrinsics.fy * cam[:, 1] / cam[:, 2] + intrinsics.cy
            c0, c1 = max(int(np.floor(u.min())), 0), min(int(np.ceil(u.max())) + 1, W)
            r0, r1 = max(int(np.floor(v.min())), 0), min(int(np.ceil(v.max())) + 1, H)
            if c0 >= c1 or r0 >= r1:
                return np.zeros(0, np.int64), np.zeros(0, np.int32)
        d = depth[r0:r1, c0:c1]
        ru = ((np.arange(c0, c1) - intrinsics.cx) / intrinsics.fx).astype(np.float32)
        rv = ((np.arange(r0, r1) - intrinsics.cy) / intrinsics.fy).astype(np.float32)
        inv = 1.0 / self.cell
        lin = None
        inside = None
        fs = []
        with np.errstate(invalid="ignore"):
            for a in range(3):
                # cell coordinate along axis a: (R[a] . ray * depth + t[a] - origin[a]) / cell
                A = np.float32(R[a, 0] * inv) * ru[None, :] + (np.float32(R[a, 1] * inv) * rv + np.float32(R[a, 2] * inv))[:, None]
                f = d * A
                f += np.float32((t[a] - self.origin[a]) * inv)
                c = f.astype(np.int32)       # NaN -> INT_MIN; (-1, 0) -> 0 is harmless (exact check below)
                ok = c.view(np.uint32) < np.uint32(self.dims[a])
                inside = ok if inside is None else np.logical_and(inside, ok, out=inside)
                if self.strides[a] != 1:
                    c *= np.int32(self.strides[a])
                lin = c if lin is None else np.add(lin, c, out=lin)
                fs.append(f)
        lin[~inside] = len(self.lut) - 1                  # the sentinel cell, always -1
        idx = self.lut[lin]
        # exact distance check (and back-face test), in cell units, per axis, on the whole crop
        d2 = np.zeros(d.shape, np.float32)
        for a in range(3):
            diff = fs[a] - self._pc[a][idx]
            diff = diff * diff
            d2 += diff
        keep = d2 <= np.float32((self.max_dist * inv) ** 2)
        if self.normals is not None:
            # back-face test per point (N of them, cheaper than per pixel): n . (camera - p) >= cos |camera - p|
            v = t.astype(np.float32) - self.positions
            dot = np.einsum("ij,ij->i", v, self.normals)
            front = dot >= 0 if backface_cos == 0.0 else dot >= np.float32(backface_cos) * np.linalg.norm(v, axis=1)
            front = np.append(front, False)                 # idx -1 (no point) -> not kept
            keep &= front[idx]
        else:
            keep &= idx >= 0
        sub = np.flatnonzero(keep)
        idx = idx.ravel()[sub]
        w = c1 - c0
        pix = (sub // w + r0) * W + (sub % w + c0)
        return pix.astype(np.int64), idx


_GRID_CACHE: "OrderedDict[tuple, PointGrid]" = OrderedDict()
_GRID_CACHE_SIZE = 4


def _cache_key(P: np.ndarray, Nn: np.ndarray | None, max_dist: float | None) -> tuple:
    step = max(1, len(P) // 512)
    probe = np.ascontiguousarray(P[::step]).tobytes()
    nprobe = b"" if Nn is None else np.ascontiguousarray(Nn[::step]).tobytes()
    return (id(P), P.shape, str(P.dtype), hash(probe), None if Nn is None else (id(Nn), hash(nprobe)),
            None if max_dist is None else float(max_dist))


def register_pixels(positions: np.ndarray, normals: np.ndarray | None, depth: np.ndarray,
                    intrinsics: Intrinsics, pose: np.ndarray, max_dist: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Register every valid depth pixel to its nearest sampled surface point (paper §4.1, §5.1).

    Builds (once per point set, cached) a :class:`PointGrid` and calls :meth:`PointGrid.register`.
    Pass the same ``positions`` array every frame; a grid is rebuilt when the array changes
    (identity or contents of a sparse probe of it). ~3-10 ms per 640x480 frame on one core.

    Parameters
    ----------
    positions : (N, 3) array
        Sampled points, world (marker) frame, metres.
    normals : (N, 3) array or None
        Their unit normals (points facing away from the camera are not matched), or None.
    depth : (H, W) float array
        Depth image, metres, NaN invalid.
    intrinsics : Intrinsics
        Of the depth image.
    pose : (4, 4) array
        Camera-to-world pose of the depth camera.
    max_dist : float, optional
        Metres; default ``max(1.5 x mean_spacing(positions), MIN_REGISTER_DIST)`` (3 mm: the depth
        noise, see :data:`MIN_REGISTER_DIST`).

    Returns
    -------
    pixel_idx : (K,) int64
        Flat indices ``row * W + col`` into the depth image of the pixels that registered.
    point_idx : (K,) int32
        The nearest sampled point (within ``max_dist``) of each of those pixels.
    """
    P, Nn = _check_points(positions, normals, "register_pixels")
    key = _cache_key(P, Nn, max_dist)
    grid = _GRID_CACHE.get(key)
    if grid is None:
        grid = PointGrid(P, Nn, max_dist=max_dist)
        _GRID_CACHE[key] = grid
        while len(_GRID_CACHE) > _GRID_CACHE_SIZE:
            _GRID_CACHE.popitem(last=False)
    else:
        _GRID_CACHE.move_to_end(key)
    return grid.register(depth, intrinsics, pose)


# -- the normal's change across a point's neighbourhood (for samples registered off the point) --------
#: :func:`normal_gradient`: neighbours whose normal is farther than this from the point's are left out
#: (a crease, the other side of a thin wall)
GRADIENT_MAX_ANGLE_DEG = 30.0
#: :func:`normal_at_offset` tilts a normal by at most this much (a bad gradient at a crease or a
#: hole's edge can't throw a sample far off)
MAX_TILT_DEG = 10.0


def normal_gradient(positions: np.ndarray, normals: np.ndarray, k: int = 16,
                    max_angle_deg: float = GRADIENT_MAX_ANGLE_DEG) -> np.ndarray:
    """How each point's unit normal turns as one moves along its tangent plane (a 2 x 2 shape operator).

    Pixels are registered to the *nearest sampled point* (paper §4.1), on average half a point
    spacing away (0.7 mm on the demo's 100k points). On a curved surface the pixel's own normal then
    differs from the point's: on the demo bottle by 0.84 degrees median, 1.85 degrees RMS, which is
    what widens a 3.4-degree Ward lobe (alpha 0.06) fitted from the samples by +4 to +8 %. With this
    gradient, :func:`normal_at_offset` gives the sample the normal at its own place on the surface
    (0.005 degrees median off the truth with exact normals at the points).

    For each point, the tangent components ``(n_j . t, n_j . b)`` of its ``k`` nearest neighbours'
    normals are fitted, by least squares, as a linear function of their tangent offsets
    ``((p_j - p) . t, (p_j - p) . b)``; ``t, b, n`` is :func:`appfusion.brdf.local_frame` of the point's
    normal. Neighbours whose normals are more than ``max_angle_deg`` from the point's (a crease) are
    left out; the normal equations are regularised by 1e-3 of their trace, so a point whose
    neighbours lie on a line gets no slope across it.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals.
    k : int
        Neighbours per point.
    max_angle_deg : float
        Largest angle between a neighbour's normal and the point's.

    Returns
    -------
    (N, 2, 2) float32 array
        ``G[i] @ (du, dv)`` is the change of ``(n . t, n . b)`` for a tangent offset ``(du, dv)``
        (metres), so ``G`` is in 1/m (the curvature, up to sign convention; ~1/radius on a cylinder).
    """
    P, Nn = check_oriented_points(positions, normals, "normal_gradient")
    n = len(P)
    G = np.zeros((n, 2, 2), np.float32)
    kk = int(min(k, n - 1))
    if kk < 2:
        return G
    F = local_frame(Nn)                                  # (N, 3, 3): rows t, b, n
    cos_max = np.cos(np.radians(max_angle_deg))
    nb = cKDTree(P).query(P, k=kk + 1, workers=-1)[1][:, 1:]
    for lo in range(0, n, 20000):                        # bounded memory: 20k x k x 3 at a time
        sl = slice(lo, min(lo + 20000, n))
        Fi, j = F[sl], nb[sl]
        D = P[j] - P[sl, None]
        Nj = Nn[j]
        A = np.stack([np.einsum("pkj,pj->pk", D, Fi[:, 0]), np.einsum("pkj,pj->pk", D, Fi[:, 1])], -1)
        y = np.stack([np.einsum("pkj,pj->pk", Nj, Fi[:, 0]), np.einsum("pkj,pj->pk", Nj, Fi[:, 1])], -1)
        w = (np.einsum("pkj,pj->pk", Nj, Fi[:, 2]) > cos_max).astype(np.float64)
        M = np.einsum("pk,pki,pkj->pij", w, A, A)
        tr = M[:, 0, 0] + M[:, 1, 1]
        M += (1e-3 * tr + 1e-30)[:, None, None] * np.eye(2)
        R = np.einsum("pk,pki,pkj->pji", w, A, y)          # sum w y A^T: (p, 2 [out], 2 [in])
        G[sl] = (R @ np.linalg.inv(M)).astype(np.float32)  # M is symmetric
    return G


def normal_at_offset(frame_rows, gradient, du, dv, max_tilt_deg: float = MAX_TILT_DEG):
    """A point's local frame tilted to a place ``(du, dv)`` along its tangent plane (first order).

    With ``(a, b) = G (du, dv)`` (:func:`normal_gradient`, clipped to ``tan(max_tilt_deg)``), the normal
    there is ``n + a t + b b`` (normalised) and the tangents ``t - a n``, ``b - b n``, orthonormal up
    to second order in the tilt (0.07 degrees at a 3-degree tilt).

    Parameters
    ----------
    frame_rows : sequence of 9 (m,) arrays
        ``t_x, t_y, t_z, b_x, b_y, b_z, n_x, n_y, n_z`` of the samples' points.
    gradient : sequence of 4 (m,) arrays
        ``G00, G01, G10, G11`` of the samples' points.
    du, dv : (m,) arrays
        Tangent offsets of the samples from their points, metres.

    Returns
    -------
    list of 9 (m,) float32 arrays
        The tilted frame, same order.
    """
    f32 = np.float32
    lim = f32(np.tan(np.radians(max_tilt_deg)))
    g00, g01, g10, g11 = gradient
    a = g00 * du
    a += g01 * dv
    b = g10 * du
    b += g11 * dv
    for x in (a, b):                                  # in place: np.clip is ~3x slower
        np.minimum(x, lim, out=x)
        np.maximum(x, -lim, out=x)
    tx, ty, tz, bx, by, bz, nx, ny, nz = frame_rows
    inv = a * a
    inv += b * b
    inv += f32(1.0)
    np.sqrt(inv, out=inv)
    np.divide(f32(1.0), inv, out=inv)
    out = [tx - a * nx, ty - a * ny, tz - a * nz, bx - b * nx, by - b * ny, bz - b * nz]
    for n_, t_, b_ in ((nx, tx, bx), (ny, ty, by), (nz, tz, bz)):
        v = a * t_
        v += b * b_
        v += n_
        v *= inv
        out.append(v)
    return out


class NormalField:
    """The surface normal anywhere near a set of oriented points: the nearest point's normal tilted
    by its gradient to the query's place (:func:`normal_gradient`, :func:`normal_at_offset`).

    Used to shade relit views at each ray hit: on the demo bottle the normals interpolated from the
    points to the mesh's vertices (inverse distance over 4, then barycentric) were 0.41 degrees off
    (median), the tilted nearest point's 0.34 degrees, and the sun's highlights sit closer.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals.
    k : int
        Neighbours of :func:`normal_gradient`.
    """

    def __init__(self, positions, normals, k: int = 16):
        P, Nn = check_oriented_points(positions, normals, "NormalField")
        self.positions = P
        self.tree = cKDTree(P)                                   # over the points (interpolate_mls shares it)
        F = local_frame(Nn).reshape(-1, 9).astype(np.float32)     # rows t, b, n
        self._frame = [np.ascontiguousarray(F[:, j]) for j in range(9)]
        G = normal_gradient(P, Nn, k=k)
        self._grad = [np.ascontiguousarray(G[:, i, j]) for i in (0, 1) for j in (0, 1)]

    def __call__(self, query: np.ndarray) -> np.ndarray:
        """Unit normals (M, 3) float64 at query positions (M, 3), metres."""
        Q = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        if len(Q) == 0:
            return np.zeros((0, 3))
        if not np.isfinite(Q).all():
            raise AppFusionError("NormalField: query positions contain NaN or inf")
        if len(self.positions) == 1:
            return self._tilted(Q, np.zeros(len(Q), np.int64))
        d, nb = self.tree.query(Q, k=2)
        n = self._tilted(Q, nb[:, 0])
        # two points at one place (a crease's duplicated vertices: a mesh's own vertices given as
        # points) share the query: their normals are averaged, as an inverse-distance weighting would
        tie = d[:, 1] - d[:, 0] < 1e-9
        if tie.any():
            n[tie] += self._tilted(Q[tie], nb[tie, 1])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    def nearest(self, query: np.ndarray) -> np.ndarray:
        """The nearest point's own normal (M, 3) at query positions (M, 3), not tilted."""
        Q = np.asarray(query, dtype=np.float64).reshape(-1, 3)
        if len(Q) == 0:
            return np.zeros((0, 3))
        _, i = self.tree.query(Q)
        n = np.stack([self._frame[6][i], self._frame[7][i], self._frame[8][i]], 1).astype(np.float64)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def _tilted(self, Q: np.ndarray, i: np.ndarray) -> np.ndarray:
        off = (Q - self.positions[i]).astype(np.float32)
        fr = [f[i] for f in self._frame]
        du = off[:, 0] * fr[0] + off[:, 1] * fr[1] + off[:, 2] * fr[2]
        dv = off[:, 0] * fr[3] + off[:, 1] * fr[4] + off[:, 2] * fr[5]
        out = normal_at_offset(fr, [g[i] for g in self._grad], du, dv)
        n = np.stack(out[6:9], axis=1).astype(np.float64)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def interpolate_mls(positions: np.ndarray, normals: np.ndarray, values: np.ndarray, queries: np.ndarray,
                    k: int = 6, clamp: bool = True, batch: int = 200_000, tree: cKDTree | None = None) -> np.ndarray:
    """Per-point values at query positions by a moving-least-squares linear fit (beyond the paper).

    Each query takes the value at its own place of the plane ``v ~ a + b u + c w`` fitted, by weighted
    least squares, to its ``k`` nearest points' values over their offsets ``(u, w)`` in the tangent
    plane of the nearest point's normal (Gaussian weights ``exp(-(d / h)^2)``, ``h`` the distance to
    the 4th nearest point; Lancaster and Salkauskas 1981, Levin 1998). It reproduces a linear field
    exactly, where the inverse-distance weighting of :func:`appfusion.export.transfer_to_vertices`
    flattens it towards each point's value (bull's-eyes: a gradient turns into steps one point
    spacing wide; a sharp step comes out about the same either way). With ``clamp`` the value stays
    within its neighbours' range (no overshoot at an edge; on a linear field a query whose 6
    neighbours all lie on one side along the gradient is then a little off). Relit views (session 33), the albedo at each ray hit from the scan's points: the
    ``bench --quick`` matte scan (10k points) 0.0554 -> 0.0497 (k 4: 0.0517, 8: 0.0514, 12:
    0.0532), the demo 0.0307 -> 0.0299, the pepper and the vase unchanged (0.064, 0.105).

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals.
    values : (N,) or (N, C) array
        Per-point values (e.g. ``rho_d``).
    queries : (M, 3) array
        Metres.
    k : int
        Neighbours per fit (>= 3; fewer points than 3: the nearest point's value).
    clamp : bool
        Keep each result within the per-channel range of its ``k`` neighbours.
    batch : int
        Queries per block (memory).
    tree : scipy.spatial.cKDTree, optional
        A tree over ``positions`` built already.

    Returns
    -------
    (M,) or (M, C) array of ``values``' dtype (floating) or float64.
    """
    P, Nn = check_oriented_points(positions, normals, "interpolate_mls")
    V = np.asarray(values)
    if V.shape[:1] != (len(P),) or V.ndim > 2:
        raise AppFusionError(f"interpolate_mls: values of shape {V.shape} do not match {len(P)} points")
    Q = np.asarray(queries, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(Q).all():
        raise AppFusionError("interpolate_mls: query positions contain NaN or inf")
    if k < 3:
        raise AppFusionError(f"interpolate_mls: k must be at least 3, got {k}")
    dtype = V.dtype if np.issubdtype(V.dtype, np.floating) else np.float64
    flat = V.ndim == 1
    V2 = np.asarray(V, np.float64).reshape(len(P), -1)
    tree = cKDTree(P) if tree is None else tree
    out = np.empty((len(Q), V2.shape[1]))
    if len(P) < 3:
        out[:] = V2[tree.query(Q)[1]] if len(Q) else 0.0
        return (out[:, 0] if flat else out).astype(dtype, copy=False)
    k = int(min(k, len(P)))
    F = local_frame(Nn)                                            # rows t, b, n
    for s in range(0, len(Q), batch):
        q = Q[s:s + batch]
        d, j = tree.query(q, k=k, workers=-1)
        h = np.maximum(d[:, min(3, k - 1)], 1e-9)[:, None]
        w = np.exp(-(d / h) ** 2)
        off = P[j] - q[:, None]
        fr = F[j[:, 0]]
        u = np.einsum("mkc,mc->mk", off, fr[:, 0]) / h
        v = np.einsum("mkc,mc->mk", off, fr[:, 1]) / h
        A = np.stack([np.ones_like(u), u, v], -1)                  # (m, k, 3)
        Aw = A * w[..., None]
        M = np.einsum("mki,mkj->mij", Aw, A) + 1e-6 * np.eye(3)   # neighbours on a line: near plain average
        vals = V2[j]                                               # (m, k, C)
        coef = np.linalg.solve(M, np.einsum("mki,mkc->mic", Aw, vals))
        r = coef[:, 0]
        if clamp:
            r = np.clip(r, vals.min(1), vals.max(1))
        out[s:s + batch] = r
    return (out[:, 0] if flat else out).astype(dtype, copy=False)



def snap_planes(positions: np.ndarray, normals: np.ndarray, voxel: float, k: int = 32, flat: float = 0.025,
                plane: float = 0.03, min_extent_voxels: float = 4.0, edge_deg: float = 2.0,
                reach_voxels: float = 1.5, reach_offset: float = 0.25, reach_deg: float = 25.0,
                min_points: int = 100, stats: dict | None = None) -> np.ndarray:
    """Normals of the points on large planar faces: the face's own plane normal (beyond the paper).

    A TSDF rounds the edge of a flat face over about a voxel: on the synthetic vase (2 mm voxels) the
    lid's top drooped by 0.35 mm within 1 mm of its rim and 0.13 mm at 1-2 mm, and its filtered and
    crease-sharpened normals tilted outwards by 8-11 and 4.5 degrees there (:func:`sharpen_creases`
    keeps a curve the positions really have). A grazing sun's glint on that lid is lost for a few
    degrees: the oracle with the truth's normals on the top face within 3 mm of its rim took the
    vase's relit error from 0.157 to 0.129 (session 26).

    A planar face is found as a connected set of points whose local plane (``k`` neighbours, PCA) has
    an RMS residual under ``flat`` voxels, joined where neighbours (within 2.5 point spacings) differ
    in normal by less than ``edge_deg``; it is a plane if the plane fitted to all of it has an RMS
    residual under ``plane`` voxels and it spans at least ``min_extent_voxels`` voxels in both
    directions (twice the square root of its second PCA eigenvalue). A curved surface joins into one
    set whose plane fit fails (the capsules, the sphere and the pepper find none; a cylinder would
    have to be over ~12 cm in radius for a strip wide enough to pass). Every point within
    ``reach_voxels`` voxels of a face's points, within ``reach_offset`` voxels of its plane and
    within ``reach_deg`` degrees of its normal (the rounded edge's points on the face's side) then
    takes the plane's normal, oriented like its own.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals (e.g. :func:`sharpen_creases`' output).
    voxel : float
        The TSDF voxel (metres) the thresholds scale with.
    k, flat, plane, min_extent_voxels, edge_deg, reach_voxels, reach_offset, reach_deg, min_points
        See above; ``min_points``: smallest face, points.
    stats : dict, optional
        Filled with ``"flat"`` (points with a flat neighbourhood), ``"planes"`` (per candidate face:
        points, RMS and extent in mm, kept, points snapped) and ``"snapped"`` (total).

    Returns
    -------
    (N, 3) float64 unit normals: the input's where no face claims the point.
    """
    P, Nn = _check_points(positions, normals, "snap_planes")
    if Nn is None:
        raise AppFusionError("snap_planes: normals are required")
    if not (np.isfinite(voxel) and voxel > 0):
        raise AppFusionError(f"snap_planes: voxel must be a positive length in metres, got {voxel}")
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    P = P.astype(np.float64)
    out = np.asarray(Nn, np.float64).copy()
    st = {"flat": 0, "planes": [], "snapped": 0}
    if stats is not None:
        stats.update(st)
        st = stats
    n = len(P)
    if n < max(min_points, k + 1):
        return out
    tree = cKDTree(P)
    d, nb = tree.query(P, k=k)
    local_n = np.empty((n, 3))
    local_rms = np.empty(n)
    for s0 in range(0, n, 32768):                        # local planes in chunks: (chunk, k, 3) at a time
        Q = P[nb[s0:s0 + 32768]]
        Q -= Q.mean(axis=1, keepdims=True)
        w, v = np.linalg.eigh(np.einsum("pki,pkj->pij", Q, Q) / k)
        local_n[s0:s0 + 32768] = v[:, :, 0]
        local_rms[s0:s0 + 32768] = np.sqrt(np.maximum(w[:, 0], 0.0))
    flat_idx = np.flatnonzero(local_rms < flat * voxel)
    st["flat"] = int(len(flat_idx))
    if len(flat_idx) < min_points:
        return out
    spacing = float(np.median(d[:, min(8, k - 1)]))
    pairs = cKDTree(P[flat_idx]).query_pairs(2.5 * spacing, output_type="ndarray")
    a, b = flat_idx[pairs[:, 0]], flat_idx[pairs[:, 1]]
    keep = np.abs(np.einsum("ij,ij->i", local_n[a], local_n[b])) > np.cos(np.radians(edge_deg))
    a, b = a[keep], b[keep]
    _, comp = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)
    sizes = np.bincount(comp[flat_idx])
    for c in np.flatnonzero(sizes >= min_points):
        idx = flat_idx[comp[flat_idx] == c]
        X = P[idx]
        m = X.mean(axis=0)
        ew, ev = np.linalg.eigh(np.cov((X - m).T))
        nc, rms, extent = ev[:, 0], float(np.sqrt(max(ew[0], 0.0))), float(2 * np.sqrt(max(ew[1], 0.0)))
        face = {"points": int(len(idx)), "rms_mm": round(rms * 1e3, 4), "extent_mm": round(extent * 1e3, 2),
                "kept": bool(rms < plane * voxel and extent >= min_extent_voxels * voxel), "snapped": 0}
        st["planes"].append(face)
        if not face["kept"]:
            continue
        near, _ = cKDTree(X).query(P, distance_upper_bound=reach_voxels * voxel)
        sel = (np.isfinite(near) & (np.abs((P - m) @ nc) < reach_offset * voxel)
               & (np.abs(out @ nc) > np.cos(np.radians(reach_deg))))
        out[sel] = np.where((out[sel] @ nc)[:, None] < 0, -nc, nc)
        face["snapped"] = int(sel.sum())
        st["snapped"] += face["snapped"]
    return out


# -- sampling (paper §4.1: "randomly sampling points with a probability proportional to the surface area")
def sample_points(mesh, n: int = 100_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Sample points on a triangle mesh with probability proportional to area, with mesh normals.

    A triangle is drawn with probability area / total area, then a uniform point in it
    (``u = 1 - sqrt(r1)``, ``v = r2 sqrt(r1)``). The normal is the barycentric interpolation of the
    vertex normals when the mesh has them (smooth, but noisy on a TSDF mesh: see
    :func:`bilateral_filter_normals`), else the face normal.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or (vertices (V, 3), triangles (T, 3))
    n : int
        Number of points (the paper uses 100k).
    seed : int

    Returns
    -------
    positions : (n, 3) float64, metres (frame of the mesh)
    normals : (n, 3) float64, unit
    """
    if isinstance(mesh, tuple):
        V, F = np.asarray(mesh[0], np.float64), np.asarray(mesh[1], np.int64)
        VN = None
    else:
        V, F = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)
        VN = np.asarray(mesh.vertex_normals, np.float64) if mesh.has_vertex_normals() else None
    if len(F) == 0 or len(V) == 0:
        raise EstimationError("sample_points: the mesh is empty (nothing inside the object box?)")
    if int(n) < 1:
        raise AppFusionError(f"sample_points: n must be positive, got {n}")
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cr = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cr, axis=1)
    total = area2.sum()
    if not total > 0:
        raise EstimationError("sample_points: the mesh has zero area")
    rng = np.random.default_rng(seed)
    tri = np.searchsorted(np.cumsum(area2) / total, rng.random(int(n)), side="right")
    tri = np.minimum(tri, len(F) - 1)
    r1, r2 = rng.random(int(n)), rng.random(int(n))
    s1 = np.sqrt(r1)
    wa, wb, wc = 1 - s1, s1 * (1 - r2), s1 * r2
    P = wa[:, None] * a[tri] + wb[:, None] * b[tri] + wc[:, None] * c[tri]
    fn = cr[tri] / np.maximum(area2[tri], 1e-300)[:, None]
    if VN is not None and len(VN) == len(V):
        Nn = wa[:, None] * VN[F[tri, 0]] + wb[:, None] * VN[F[tri, 1]] + wc[:, None] * VN[F[tri, 2]]
        ln = np.linalg.norm(Nn, axis=1)
        bad = ln < 1e-9
        Nn[~bad] /= ln[~bad, None]
        Nn[bad] = fn[bad]
        Nn *= np.sign(np.einsum("ij,ij->i", Nn, fn) + 1e-12)[:, None]      # agree with the winding
    else:
        Nn = fn
    return P, Nn


def _nearest_within(tree: cKDTree, Q: np.ndarray, k: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest of ``tree``'s points to each of ``Q`` (M, 3) within ``radius``: their indices
    (M, k), 0 where there is none, and which are found (M, k) bool."""
    d, j = tree.query(Q, k=k, distance_upper_bound=radius, workers=-1)
    d, j = d.reshape(len(Q), k), j.reshape(len(Q), k)
    ok = np.isfinite(d)
    return np.where(ok, j, 0), ok


def _neighbourhoods(P: np.ndarray, radius: float, k: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """k nearest neighbours of every point among a random subset dense enough that k of them
    cover ``radius``; returns (indices (N, k) into P, distances (N, k), valid (N, k))."""
    spacing = mean_spacing(P)
    expected = np.pi * radius ** 2 / spacing ** 2           # points of the full set within radius
    if expected > k:
        m = max(int(len(P) * k / expected), k + 1)
        sub = np.sort(np.random.default_rng(seed).choice(len(P), m, replace=False))
    else:
        sub = np.arange(len(P))
    kk = int(min(k, len(sub)))
    d, j = cKDTree(P[sub]).query(P, k=kk, distance_upper_bound=radius, workers=-1)
    valid = np.isfinite(d)
    j = np.where(valid, j, 0)
    return sub[j], np.where(valid, d, 0.0), valid


def bilateral_filter_normals(positions: np.ndarray, normals: np.ndarray, sigma_s: float | None = None,
                             sigma_n: float = 0.35, iterations: int = 2, k: int = 32, seed: int = 0,
                             local_linear: bool = True, adaptive_stages: tuple[int, ...] = (),
                             adaptive_c: float = 2.5, adaptive_converge: float | None = 0.7,
                             stats: dict | None = None) -> np.ndarray:
    """Bilateral filter of point normals (paper §4.1, after Fleishman et al. 2003).

    Each normal becomes the normalised average of its neighbours' normals weighted by a spatial
    Gaussian and a normal-difference Gaussian::

        n_i' ~ sum_j w_ij n_j,   w_ij = exp(-|p_j - p_i|^2 / 2 sigma_s^2) exp(-|n_j - n_i|^2 / 2 sigma_n^2)

    so that noise is smoothed on smooth parts while creases (large normal differences) are kept.
    Neighbours are the ``k`` nearest within ``2 sigma_s`` among a random subset dense enough to
    reach that radius (a Monte Carlo estimate of the weighted average; fully vectorised with a
    cKDTree).

    ``local_linear`` (beyond the paper): the weighted average is the normal at the neighbours'
    weighted centroid, and with a random subset that centroid lies ~``sigma_s / sqrt(k)`` from
    ``p_i``; on a curved surface that offset is a normal error (1 mm on a 4 cm radius: 1.4 degrees).
    The local-linear estimate fits ``n_j ~ a + b u_j + c v_j`` by weighted least squares over the
    neighbours' tangent coordinates ``(u_j, v_j)`` around ``p_i`` and takes ``a``, the fit's value at
    the point itself (first-order kernel regression, unbiased where the normal varies linearly). On
    the demo bottle (3 mm, 64 neighbours, 3 passes): median error 0.76 -> 0.34 degrees. A point
    whose neighbours do not span two tangent directions keeps the plain average.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals.
    sigma_s : float, optional
        Spatial sigma, metres; default 3 x :func:`mean_spacing`.
    sigma_n : float
        Normal-difference sigma (chord length |n_j - n_i|; 0.35 ~ 20 degrees).
    iterations : int
        Filter passes.
    k : int
        Neighbours per point.
    local_linear : bool
        First-order (local-linear) instead of the plain weighted average, see above.
    adaptive_stages : tuple of int
        Further passes after ``iterations``, in stages (beyond the paper): each point keeps the
        smoothest stage whose normal moved from the previous stage's by at most ``adaptive_c`` times
        the median move of that stage over all points, and none after the first it fails. More
        passes smooth more (a wider effective kernel) but bias the normal where the curvature
        changes, e.g. where a cylinder meets its hemispherical cap: the local-linear fit assumes
        the normal varies linearly. A point near such a change moves much more between stages than
        noise makes points elsewhere move, and stops there (a simple form of the intersection of
        confidence intervals rule for choosing a local bandwidth: Katkovnik 1999, "A new method for
        varying adaptive bandwidth selection", IEEE Trans. Signal Processing 47(9)). On the capsule
        of the seed-1 demo scene (3 mm, 128 neighbours, 3 passes, then stages of 3 and 6): median
        error on the cap 0.204 -> 0.135 degrees, cylinder 0.216 -> 0.116, along the cap's seam
        0.559 -> 0.563 (12 passes everywhere: 0.134, 0.118, 2.22).
    adaptive_c : float
        The stage test's multiple of the median move.
    adaptive_converge : float or None
        The stages run only while the filter converges (session 14): a stage's median move per pass
        must be at most this fraction of the pass before it (the last of ``iterations``, then the
        previous stage's per-pass rate), else it and the later ones are skipped for every point.
        Noise is averaged out geometrically, so the moves of a converging filter shrink pass by
        pass; where the normal's variation is not linear over the kernel *everywhere* (a pepper's
        lobes, no smooth part to compare with) every pass moves every normal by about the same bias,
        the median move with it, and the per-point test above lets it accumulate. Capsule (seed 3):
        median moves 0.80, 0.16, 0.08, 0.05 deg in passes 1-4, error 1.05 -> 0.12 deg after 15;
        pepper: 0.89, 0.28, 0.24, 0.23 deg, error 1.09 -> 0.55 after one pass and 4.6 after 24.
        None: no such test.
    stats : dict, optional
        Filled with ``"stage_rates"`` (median move per pass of each stage run, radians),
        ``"base_rate"`` and ``"stages_run"``.

    Returns
    -------
    (N, 3) float64 unit normals, oriented like the input.
    """
    P, Nn = _check_points(positions, normals, "bilateral_filter_normals")
    if Nn is None:
        raise AppFusionError("bilateral_filter_normals: normals are required")
    P = np.asarray(P, np.float64)
    N0 = np.asarray(Nn, np.float64)
    ln = np.linalg.norm(N0, axis=1)
    if not np.all(np.isfinite(N0)) or np.any(ln < 1e-9):
        raise AppFusionError("bilateral_filter_normals: normals contain NaN or zero vectors")
    N0 = N0 / ln[:, None]
    if len(P) < 3:
        return N0
    if sigma_s is None:
        sigma_s = 3.0 * mean_spacing(P)
    if not sigma_s > 0:
        raise AppFusionError(f"bilateral_filter_normals: sigma_s must be positive, got {sigma_s}")
    stages = [int(s) for s in adaptive_stages]
    if any(s < 1 for s in stages) or not (np.isfinite(adaptive_c) and adaptive_c > 0):
        raise AppFusionError(f"bilateral_filter_normals: adaptive stages must be positive pass counts and "
                             f"adaptive_c > 0, got {tuple(adaptive_stages)}, {adaptive_c}")
    j, d, valid = _neighbourhoods(P, 2.0 * sigma_s, k, seed)
    # the (N, k) arrays of the passes in float32 (half the memory traffic, which is their cost: 46 ->
    # 23 s for the demo's 100k points, 128 neighbours, 24 passes; normals within 1e-5 degrees of float64)
    ws = np.where(valid, np.exp(-0.5 * (d / sigma_s) ** 2), 0.0).astype(np.float32)
    # neighbour offsets in units of sigma_s, one contiguous (N, k) array per axis (the passes read them
    # per component: strided (N, k, 3) slices were most of their time)
    X = [((P[j, c] - P[:, None, c]) / sigma_s).astype(np.float32) for c in range(3)] if local_linear else None
    inv2sn2 = np.float32(0.5 / sigma_n ** 2)

    last_move = [0.0]

    def passes(Ncur: np.ndarray, count: int) -> np.ndarray:
        for _ in range(count):
            prev = Ncur
            N32 = Ncur.astype(np.float32)
            Nj = [N32[:, c][j] for c in range(3)]               # neighbours' normals, (N, k) per axis
            dn2 = (Nj[0] - N32[:, None, 0]) ** 2
            dn2 += (Nj[1] - N32[:, None, 1]) ** 2
            dn2 += (Nj[2] - N32[:, None, 2]) ** 2
            dn2 *= -inv2sn2
            w = ws * np.exp(dn2)
            acc = np.stack([(w * Nj[c]).sum(1, dtype=np.float64) for c in range(3)], 1) + 1e-12 * Ncur
            if local_linear:
                acc = _local_linear_value(X, w, Nj, Ncur, acc)
            Ncur = acc / np.linalg.norm(acc, axis=1, keepdims=True)
            last_move[0] = float(np.median(np.arccos(np.clip(np.einsum("nc,nc->n", Ncur, prev), -1.0, 1.0))))
        return Ncur

    if adaptive_converge is not None and not (np.isfinite(adaptive_converge) and adaptive_converge > 0):
        raise AppFusionError(f"bilateral_filter_normals: adaptive_converge must be positive or None, got {adaptive_converge}")
    Ncur = passes(N0, int(iterations))
    rate = last_move[0] if int(iterations) > 0 else np.inf
    if stats is not None:
        stats.update(base_rate=rate, stage_rates=[], stages_run=0)
    if not stages:
        return Ncur
    out, alive = Ncur.copy(), np.ones(len(P), bool)
    for count in stages:
        Nnext = passes(Ncur, count)
        move = np.einsum("nc,nc->n", Nnext, Ncur)               # cos of each point's move
        ang = np.arccos(np.clip(move, -1.0, 1.0))
        stage_rate = float(np.median(ang)) / count
        if stats is not None:
            stats["stage_rates"].append(stage_rate)
        if adaptive_converge is not None and stage_rate > adaptive_converge * rate:
            break                                               # drifting, not converging: no point takes it
        rate = stage_rate
        alive &= ang <= adaptive_c * np.median(ang)
        if not alive.any():                                     # no point takes later stages
            break
        out[alive] = Nnext[alive]
        Ncur = Nnext
        if stats is not None:
            stats["stages_run"] += 1
    return out


def _monomials(x: np.ndarray, y: np.ndarray, degree: int) -> np.ndarray:
    """The monomials ``x^i y^j`` with ``i + j <= degree`` of arrays x, y (..., k), stacked last:
    ``1, x, y, x^2, x y, y^2, ...`` (so columns 1 and 2 are the linear terms)."""
    cols = [np.ones_like(x)]
    for d in range(1, degree + 1):
        cols.extend(x ** i * y ** (d - i) for i in range(d, -1, -1))
    return np.stack(cols, -1)


def jet_normals(positions: np.ndarray, normals: np.ndarray, support: np.ndarray, support_normals: np.ndarray,
                radius: float, degree: int = 3, k: int = 256, cos_min: float = 0.5,
                batch: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a weighted polynomial height fit (an osculating jet) around each point (beyond the paper).

    In the tangent frame of each point's normal ``n`` (unit vectors ``t1, t2``) the support points
    within ``radius`` give heights ``h = (q - p) . n`` over ``(x, y) = ((q - p) . t1, (q - p) . t2)``;
    a polynomial ``h(x, y)`` of total degree ``degree`` is fitted by least squares with Gaussian
    weights (sigma ``radius / 2``), and the normal is that of the fitted surface at the point:
    ``n - h_x t1 - h_y t2``, normalised (Cazals & Pouget 2005, "Estimating differential quantities
    using polynomial fitting of osculating jets"). Neighbours whose normals differ from ``n`` by more
    than ``arccos(cos_min)`` are left out (the far side of a thin wall, a crease).

    The bilateral filter (:func:`bilateral_filter_normals`) is a local-linear regression of the
    normals: unbiased where the normal varies linearly over its kernel, so its kernel must stay
    small where it does not, and a small kernel leaves the fused surface's noise. A cubic height
    field is unbiased where the normal varies quadratically (the odd terms of degree 3 are what bias
    a quadric's slope over a symmetric neighbourhood), so it can average over a wider disk. The
    support should be the mesh's vertices, not points sampled on the mesh: those are interpolations
    of the vertices and add no information.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Where to estimate (metres) and the normals that set each local frame (unit).
    support, support_normals : (M, 3) arrays
        Surface samples to fit (metres; e.g. the fused mesh's vertices) and their normals.
    radius : float
        Fit radius, metres.
    degree : int
        Total degree of the height polynomial (1-4).
    k : int
        Nearest support points per fit (those within ``radius``).
    cos_min : float
        Smallest cosine between a support normal and the point's normal for it to count.
    batch : int
        Points per vectorised batch (memory ~ ``batch * k * 15 * 8`` bytes at degree 3).

    Returns
    -------
    normals : (N, 3) float64
        Unit normals, oriented like the input.
    residual : (N,) float64
        Weighted RMS of the fit's height residuals, metres (noise where the polynomial fits, more
        where it does not: a crease, a rim, a fold within ``radius``). Where fewer support points
        than twice the polynomial's terms are usable the input normal is kept and the residual is inf.
    """
    P, Nn = _check_points(positions, normals, "jet_normals")
    S, SN = _check_points(support, support_normals, "jet_normals (support)")
    if Nn is None or SN is None:
        raise AppFusionError("jet_normals: normals of the points and of the support are required")
    if not (np.isfinite(radius) and radius > 0):
        raise AppFusionError(f"jet_normals: radius must be positive, got {radius}")
    if not 1 <= int(degree) <= 4:
        raise AppFusionError(f"jet_normals: degree must be 1-4, got {degree}")
    P = np.asarray(P, np.float64)
    N = np.asarray(Nn, np.float64)
    S = np.asarray(S, np.float64)
    SN = np.asarray(SN, np.float64)
    for name, A in (("normals", N), ("support normals", SN)):
        ln = np.linalg.norm(A, axis=1)
        if not np.all(np.isfinite(ln)) or np.any(ln < 1e-9):
            raise AppFusionError(f"jet_normals: {name} contain NaN or zero vectors "
                                 f"(first bad row {int(np.flatnonzero(~(np.isfinite(ln) & (ln >= 1e-9)))[0])})")
    N = N / np.linalg.norm(N, axis=1, keepdims=True)
    SN = SN / np.linalg.norm(SN, axis=1, keepdims=True)
    degree = int(degree)
    n_terms = (degree + 1) * (degree + 2) // 2
    k = int(min(k, len(S)))
    tree = cKDTree(S)
    out = N.copy()
    resid = np.full(len(P), np.inf)
    for s0 in range(0, len(P), batch):
        q, n0 = P[s0:s0 + batch], N[s0:s0 + batch]
        idx, ok = _nearest_within(tree, q, k, radius)
        fr = local_frame(n0)
        t1, t2 = fr[:, 0], fr[:, 1]
        D = (S[idx] - q[:, None]) / radius                       # in radii: a well-conditioned fit
        x = np.einsum("bkc,bc->bk", D, t1)
        y = np.einsum("bkc,bc->bk", D, t2)
        h = np.einsum("bkc,bc->bk", D, n0)
        w = np.exp(-2.0 * (x * x + y * y)) * ok                  # sigma radius / 2
        w *= np.einsum("bkc,bc->bk", SN[idx], n0) > cos_min
        A = _monomials(x, y, degree)                             # (B, k, terms)
        Aw = A * w[..., None]
        M = np.matmul(Aw.transpose(0, 2, 1), A)
        M += (1e-12 * np.trace(M, axis1=1, axis2=2) + 1e-300)[:, None, None] * np.eye(n_terms)  # a tiny ridge
        c = np.linalg.solve(M, np.matmul(Aw.transpose(0, 2, 1), h[..., None]))[..., 0]
        r = h - np.matmul(A, c[..., None])[..., 0]
        wsum = w.sum(1)
        good = ((w > 0).sum(1) >= 2 * n_terms) & np.isfinite(c).all(1)
        nn = n0 - c[:, 1:2] * t1 - c[:, 2:3] * t2
        nn /= np.linalg.norm(nn, axis=1, keepdims=True)
        out[s0:s0 + batch][good] = nn[good]
        rr = np.sqrt((w * r * r).sum(1) / np.maximum(wsum, 1e-300)) * radius
        resid[s0:s0 + batch][good] = rr[good]
    return out, resid


def _plane_fits(X: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes through point sets X (M, k, 3), each point weighted by ``w`` (M, k) if
    given: centroids (M, 3), unit normals (M, 3) and RMS distances of the points from their plane (M,)."""
    if w is None:
        c = X.mean(1)
        D = X - c[:, None]
        C = np.einsum("mki,mkj->mij", D, D) / X.shape[1]
    else:
        W = w.sum(1)
        c = np.einsum("mk,mkc->mc", w, X) / W[:, None]
        D = X - c[:, None]
        C = np.einsum("mk,mki,mkj->mij", w, D, D) / W[:, None, None]
    ev, evec = np.linalg.eigh(C)
    return c, evec[:, :, 0], np.sqrt(np.maximum(ev[:, 0], 0.0))


def sharpen_creases(positions: np.ndarray, normals: np.ndarray, radius: float, detect_deg: float = 25.0,
                    k: int | None = None, shifts: int = 16, shift_radius: float | None = None,
                    tau: float | None = None, flatness: float = 0.5, min_change_deg: float = 3.0, refit: int = 6,
                    seed: int = 0, band_deg: float | None = 5.0, stats: dict | None = None) -> np.ndarray:
    """Normals of points near a sharp crease from one-sided plane fits (beyond the paper).

    A TSDF volume blurs a crease's normals over a few voxels on either side (its gradient, then the
    bilateral filter, which sees a continuum of normals and keeps it): on the synthetic vase, whose
    lid meets the flaring neck at 110 degrees, the normals within 6 mm of the lid's edge were 5-40
    degrees off while the points' positions lay within 0.4 mm of the truth there. Positions keep the
    crease where normals lose it, so near a crease each point takes the normal of the flattest
    plane fitted to a neighbourhood *shifted off the point* that still passes through it: a
    neighbourhood on one side of the crease is flat, one straddling it is not (the idea of fitting
    outlier-free one-sided neighbourhoods at sharp features: Fleishman, Cohen-Or and Silva 2005,
    "Robust moving least-squares fitting with sharp features", ACM TOG 24(3)).

    Only points with a neighbour within ``radius`` whose normal differs by more than ``detect_deg``
    are candidates (none on the capsules and spheres: a 4 cm radius turns the normal 11 degrees over
    7.5 mm). A candidate whose own (centred) neighbourhood straddles the crease, i.e. whose best
    one-sided plane's RMS residual is below ``flatness`` times its own plane's, takes that side: the
    best plane refitted over its own ``refit * k`` nearest neighbours within ``2 rms + tau`` of it
    (the best neighbourhood lies off the point, so on a curved side its normal is tilted by offset /
    radius of curvature; and a plane over ~1.5 voxels of a TSDF mesh is tilted ~2 degrees by its
    facets). A candidate whose own neighbourhood lies on one side takes its own plane's normal where
    that differs from the given one by more than ``min_change_deg`` (the filter spread the crease's
    blur over a few voxels; a centred fit has no offset bias). On a smooth bend no side is flatter,
    so a point at most takes its own plane.

    Parameters
    ----------
    positions, normals : (N, 3) arrays
        Points (metres) and unit normals (e.g. :func:`bilateral_filter_normals`' output).
    radius : float
        Metres; the neighbourhood searched for a crease (default in the geometry pass: 2.5 voxels).
    detect_deg : float
        Normal difference within ``radius`` that makes a point a candidate, degrees.
    k : int, optional
        Points per plane fit; default those within ``radius / 3`` (by :func:`mean_spacing`), 16-128
        (32 on the vase at 7.5 mm).
    shifts : int
        Shifted neighbourhoods tried per candidate (centred at neighbours within ``shift_radius``).
    shift_radius : float, optional
        Metres; default ``radius / 2``.
    tau : float, optional
        Metres; a plane passes through the point if the point lies within ``2 rms + tau`` of it.
        Default ``radius / 25`` (0.3 mm at 7.5 mm).
    flatness, min_change_deg, refit : float, float, int
        See above.
    band_deg : float or None
        Then the crease's rounded band (:func:`_crease_band`, session 32): a candidate whose normal
        is more than this many degrees from that of every face point within ``2 radius`` takes the
        face whose plane it lies closer to. On the vase (200 frames a pass, 2 mm voxels; the lid's
        rim rounded over ~2.5 mm): normals' 99th percentile 25.7 -> 7.7 degrees, relit 0.128 ->
        0.103 (3 degrees: 0.103, 10: 0.110). None: off.
    stats : dict, optional
        Filled with ``"candidates"``, ``"changed"`` and ``"band"`` (counts).

    Returns
    -------
    (N, 3) float64 unit normals, oriented like the input; the input's own values where unchanged.
    """
    P, Nn = _check_points(positions, normals, "sharpen_creases")
    if Nn is None:
        raise AppFusionError("sharpen_creases: normals are required")
    if not (np.isfinite(radius) and radius > 0) or not (0 < flatness <= 1) or (k is not None and k < 4) or shifts < 1:
        raise AppFusionError(f"sharpen_creases: need radius > 0, 0 < flatness <= 1, k >= 4, shifts >= 1 "
                             f"(got {radius}, {flatness}, {k}, {shifts})")
    P = np.asarray(P, np.float64)
    out = np.array(Nn, np.float64)
    ln = np.linalg.norm(out, axis=1)
    if not np.all(np.isfinite(out)) or np.any(ln < 1e-9):
        raise AppFusionError("sharpen_creases: normals contain NaN or zero vectors")
    if np.any(np.abs(ln - 1) > 1e-6):
        out /= ln[:, None]
    if stats is not None:
        stats.update(candidates=0, changed=0, band=0)
    if len(P) < 64:
        return out
    if k is None:
        k = int(np.clip(np.pi * (radius / 3) ** 2 / mean_spacing(P) ** 2, 16, 128))
    k = int(min(k, len(P) // 4))
    shift_radius = 0.5 * radius if shift_radius is None else float(shift_radius)
    tau = radius / 25.0 if tau is None else float(tau)
    j, _, valid = _neighbourhoods(P, radius, 24, seed)
    cosmin = np.where(valid, np.einsum("nkc,nc->nk", out[j], out), 1.0).min(1)
    cand = np.flatnonzero(cosmin < np.cos(np.radians(detect_deg)))
    if stats is not None:
        stats["candidates"] = int(len(cand))
    if len(cand) == 0:
        return out
    tree = cKDTree(P)
    Pc = P[cand]
    _, nb = tree.query(Pc, k=k, workers=-1)
    _, n_centred, s_centred = _plane_fits(P[nb])
    ds, js = tree.query(Pc, k=4 * shifts, distance_upper_bound=shift_radius, workers=-1)
    best_s = np.full(len(cand), np.inf)
    best_n = out[cand].copy()
    best_c = Pc.copy()
    for col in np.linspace(0, ds.shape[1] - 1, shifts).astype(int):
        centre = np.where(np.isfinite(ds[:, col]), js[:, col], cand)      # a missing neighbour: the point
        _, nb = tree.query(P[centre], k=k, workers=-1)
        c0, n0, s0 = _plane_fits(P[nb])
        through = np.abs(np.einsum("mc,mc->m", Pc - c0, n0)) < 2 * s0 + tau
        better = through & (s0 < best_s)
        best_s = np.where(better, s0, best_s)
        best_n[better] = n0[better]
        best_c[better] = c0[better]
    straddle = np.isfinite(best_s) & (best_s < flatness * s_centred)
    n_centred *= np.sign(np.einsum("mc,mc->m", n_centred, out[cand]))[:, None]
    own = ~straddle & (np.einsum("mc,mc->m", n_centred, out[cand]) < np.cos(np.radians(min_change_deg)))
    # the best plane refitted over the point's own nearest neighbours on it (see above)
    _, nb = tree.query(Pc, k=min(refit * k, len(P)), workers=-1)
    X = P[nb]
    w = (np.abs(np.einsum("mkc,mc->mk", X - best_c[:, None], best_n)) < (2 * best_s + tau)[:, None]).astype(np.float64)
    w[:, 0] = 1.0
    _, n_refit, _ = _plane_fits(X, w)
    local = w.sum(1) >= k // 2
    best_n[local] = n_refit[local]
    best_n *= np.sign(np.einsum("mc,mc->m", best_n, out[cand]))[:, None]
    best_n[own] = n_centred[own]
    crease = straddle | own
    changed = cand[crease]
    out[changed] = best_n[crease]
    if stats is not None:
        stats["changed"] = int(crease.sum())
    if band_deg is not None:
        _crease_band(P, out, cand, radius, float(band_deg), stats)
    return out


def _crease_band(P: np.ndarray, out: np.ndarray, cand: np.ndarray, radius: float, band_deg: float,
                 stats: dict | None) -> None:
    """The rounded band of a crease (in place; :func:`sharpen_creases`, session 32). The TSDF rounds a
    sharp edge over a band a voxel or two wide whose points lie below both faces' planes; a plane
    fitted over a few of them is flat enough to pass for a side, so they kept normals between the
    faces' (the vase's lid rim: 380 points at 47 degrees between its top, 0, and its neck, 110), and
    a relit view saw glints on the band where the truth shows a face. A candidate whose normal is
    more than ``band_deg`` from that of every face point (a point that is no candidate: no normal
    within ``radius`` differs by ``detect_deg``) within ``2 radius`` lies on the band. It takes the
    face whose plane (through a face point, with its normal) it lies closest to, so the band is split
    where the faces' planes are equally far, and the normal of its nearest non-band candidate on that
    face (nearer the edge than the face points; the face's own normal where there is none)."""
    face = np.ones(len(P), bool)
    face[cand] = False
    fidx = np.flatnonzero(face)
    if len(fidx) == 0:
        return
    kk = int(min(64, len(fidx)))
    jj, ok = _nearest_within(cKDTree(P[fidx]), P[cand], kk, 2.0 * radius)
    jj = fidx[jj]
    fn = out[jj]                                                      # (C, kk, 3) the faces' normals
    cos_band = np.cos(np.radians(band_deg))
    band = ok.any(1) & (np.where(ok, np.einsum("ckx,cx->ck", fn, out[cand]), -1.0).max(1) < cos_band)
    if stats is not None:
        stats["band"] = int(band.sum())
    if not band.any():
        return
    r = np.flatnonzero(band)
    off = np.where(ok[r], np.abs(np.einsum("rkx,rkx->rk", P[cand[r]][:, None] - P[jj[r]], fn[r])), np.inf)
    side = fn[r, off.argmin(1)]                                       # (R, 3)
    new = side.copy()
    rest = cand[~band]
    if len(rest):
        k2 = int(min(16, len(rest)))
        j2, ok2 = _nearest_within(cKDTree(P[rest]), P[cand[r]], k2, radius)
        n2 = out[rest[j2]]
        same = ok2 & (np.einsum("rkx,rx->rk", n2, side) > cos_band)   # on the chosen face, nearest first
        has = same.any(1)
        first = same.argmax(1)
        new[has] = n2[np.flatnonzero(has), first[has]]
    out[cand[r]] = new


def _local_linear_value(X: list, w: np.ndarray, Nj: list, Ncur: np.ndarray,
                        fallback: np.ndarray) -> np.ndarray:
    """Value at each point of the weighted least-squares plane ``n ~ a + b u + c v`` through its
    neighbours' normals (``bilateral_filter_normals(local_linear=True)``).

    X : three (N, k) neighbour offsets (x, y, z; units of sigma_s); w : (N, k) weights; Nj : three
    (N, k) components of their normals; Ncur : (N, 3) the points' normals (define the tangent
    plane); fallback : (N, 3) the plain weighted sums, kept where the 3 x 3 normal equations are
    ill-conditioned (neighbours on a line, one neighbour) or the fitted value turns away from the
    average.
    """
    F = local_frame(Ncur)                                   # rows t, b, n; the fit's value at the point
    t1, t2 = F[:, 0].astype(w.dtype), F[:, 1].astype(w.dtype)   # does not depend on the tangent basis
    # the 3 x 3 normal equations M a = R of the basis (1, u, v), their sums written out (the three-operand
    # einsums they replace took two thirds of the filter's time)
    u = X[0] * t1[:, None, 0]
    u += X[1] * t1[:, None, 1]
    u += X[2] * t1[:, None, 2]
    v = X[0] * t2[:, None, 0]
    v += X[1] * t2[:, None, 1]
    v += X[2] * t2[:, None, 2]
    wu, wv = w * u, w * v
    f8 = np.float64                                         # the sums and the 3 x 3 solves in float64
    s_1, s_u, s_v = w.sum(1, dtype=f8), wu.sum(1, dtype=f8), wv.sum(1, dtype=f8)
    s_uu, s_uv, s_vv = (wu * u).sum(1, dtype=f8), (wu * v).sum(1, dtype=f8), (wv * v).sum(1, dtype=f8)
    M = np.stack([np.stack([s_1, s_u, s_v], -1), np.stack([s_u, s_uu, s_uv], -1),
                  np.stack([s_v, s_uv, s_vv], -1)], 1)
    R = np.stack([np.stack([(g * Nj[c]).sum(1, dtype=f8) for c in range(3)], 1) for g in (w, wu, wv)], 1)
    s0 = M[:, 0, 0]
    # conditioning: the tangent spread (second moments about the centroid) must cover both directions
    ok = s0 > 1e-12
    cov = M[:, 1:, 1:] - np.einsum("ni,nj->nij", M[:, 0, 1:], M[:, 0, 1:]) / np.where(ok, s0, 1.0)[:, None, None]
    lam_min = np.linalg.eigvalsh(cov)[:, 0] / np.where(ok, s0, 1.0)
    ok &= lam_min > 0.05                                    # spread > 0.22 sigma_s in every direction
    out = fallback.copy()
    if np.any(ok):
        a = np.linalg.solve(M[ok], R[ok])[:, 0, :]          # (n, 3): the fit's value at the point
        f = fallback[ok] / np.linalg.norm(fallback[ok], axis=1, keepdims=True)
        na = np.linalg.norm(a, axis=1)
        good = np.isfinite(na) & (na > 1e-9) & (np.einsum("nc,nc->n", a, f) > 0.9 * na)
        idx = np.flatnonzero(ok)[good]
        out[idx] = a[good]
    return out


def bilateral_denoise_points(positions: np.ndarray, normals: np.ndarray, sigma_c: float | None = None,
                             sigma_s: float | None = None, k: int = 32, seed: int = 0) -> np.ndarray:
    """Bilateral point denoising of Fleishman et al. (2003): move each point along its normal by

        d_i = sum_j W_c(t_j) W_s(h_j) h_j / sum_j W_c(t_j) W_s(h_j),
        t_j = |p_j - p_i|,  h_j = n_i . (p_j - p_i),

    with Gaussians ``W_c`` (sigma_c, spatial) and ``W_s`` (sigma_s, offsets along the normal).

    Parameters
    ----------
    positions, normals : (N, 3) arrays (metres, unit normals)
    sigma_c : float, optional
        Default 3 x :func:`mean_spacing`.
    sigma_s : float, optional
        Default ``sigma_c / 2``.

    Returns
    -------
    (N, 3) float64 positions.
    """
    P, Nn = _check_points(positions, normals, "bilateral_denoise_points")
    if Nn is None:
        raise AppFusionError("bilateral_denoise_points: normals are required")
    P = np.asarray(P, np.float64)
    Nn = np.asarray(Nn, np.float64)
    if sigma_c is None:
        sigma_c = 3.0 * mean_spacing(P)
    sigma_s = sigma_c / 2 if sigma_s is None else sigma_s
    j, d, valid = _neighbourhoods(P, 2.0 * sigma_c, k, seed)
    h = np.einsum("ikc,ic->ik", P[j] - P[:, None, :], Nn)
    w = np.where(valid, np.exp(-0.5 * (d / sigma_c) ** 2) * np.exp(-0.5 * (h / sigma_s) ** 2), 0.0)
    off = (w * h).sum(1) / np.maximum(w.sum(1), 1e-12)
    return P + off[:, None] * Nn
