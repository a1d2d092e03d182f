"""Robust sphere fit to the mirror ball's geometry (paper §4.3).

The paper scans the mirror ball with KinectFusion and, because a mirror returns weak and noisy depth,
"fit[s] a perfect sphere to the captured geometry using least squares, right after the automatic
object/background geometry separation". This module does that robustly:

1. validation (finite points, plausible units, not coincident / collinear / coplanar);
2. RANSAC over minimal 4-point spheres (vectorised, MSAC cost) for outlier-free starts;
3. geometric least squares ``r_i = |p_i - c| - R`` with a robust ``soft_l1`` loss
   (:func:`scipy.optimize.least_squares`), a few rounds on the points within a band around the current
   sphere that shrinks to 3 sigma of the noise; the best of the refined candidates wins;
4. checks that the answer is determined: the radius must lie in a plausible range, enough points must
   lie on the shell, the shell must be much denser than its surroundings (a cloud of outliers is not),
   the scatter must be small against the radius, and the radius (when it is estimated) must be
   determined by the patch's curvature (its standard error from the Gauss-Newton covariance, and the
   cap's sagitta against the noise).

Anything that fails raises :class:`~appfusion.errors.EstimationError` naming the reason; the result
never contains NaN.

Points can come from a fused mesh (:func:`fit_sphere`) or straight from depth frames cropped to the
object box (:func:`points_from_depth`, :class:`PointReservoir`, :func:`fit_sphere_from_depth`).
:func:`refine_center` re-locates a ball of known radius in a single frame's points (used per frame by
the lighting pass to cancel tracking error).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np
from scipy.optimize import least_squares

from .errors import AppFusionError, EstimationError
from .frame import Intrinsics, transform_points

#: largest coordinate magnitude accepted (metres); anything beyond is taken as a units mistake
MAX_COORD_M = 1.0e4


@dataclass(frozen=True)
class SphereFit:
    """Result of a sphere fit. All lengths in metres.

    Attributes
    ----------
    center : (3,) float64 ndarray
        Sphere centre in the frame of the input points (the marker/world frame in the pipeline).
    radius : float
        Sphere radius (the given one when the radius was fixed).
    rms_m : float
        Root-mean-square geometric residual ``|p - c| - R`` over the inliers.
    inlier_fraction : float
        Fraction of the (finite) points within ``inlier_threshold_m`` of the sphere.
    n_points, n_inliers : int
        Number of finite points used and of inliers among them.
    radius_std_m : float
        Standard error of the radius from the Gauss-Newton covariance (0 when the radius was fixed).
    center_std_m : float
        Largest standard error of a centre coordinate, from the same covariance.
    radius_fixed : bool
        True if the radius was given and only the centre was fitted.
    """

    center: np.ndarray
    radius: float
    rms_m: float
    inlier_fraction: float
    n_points: int
    n_inliers: int
    radius_std_m: float = 0.0
    center_std_m: float = 0.0
    radius_fixed: bool = False

    def residuals(self, points: np.ndarray) -> np.ndarray:
        """Signed distances ``|p - c| - R`` (metres) of points (N, 3) to this sphere, shape (N,)."""
        return np.linalg.norm(np.asarray(points, float) - self.center, axis=-1) - self.radius

    def to_json(self) -> dict[str, Any]:
        return {"center": [float(x) for x in self.center], "radius": float(self.radius),
                "rms_m": float(self.rms_m), "inlier_fraction": float(self.inlier_fraction),
                "n_points": int(self.n_points), "n_inliers": int(self.n_inliers),
                "radius_std_m": float(self.radius_std_m), "center_std_m": float(self.center_std_m),
                "radius_fixed": bool(self.radius_fixed)}


# -- validation --------------------------------------------------------------------------------

def _validate(points: Any, min_points: int, where: str) -> np.ndarray:
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise EstimationError(f"{where}: points must be numbers of shape (N, 3): {e}") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise EstimationError(f"{where}: points must have shape (N, 3), got {p.shape}")
    p = p[np.isfinite(p).all(axis=1)]
    if len(p) < min_points:
        raise EstimationError(f"{where}: too few points: {len(p)} finite points, need at least {min_points}")
    if np.abs(p).max() > MAX_COORD_M:
        raise EstimationError(f"{where}: coordinates up to {np.abs(p).max():.3g} m; points must be in metres "
                              f"within {MAX_COORD_M:g} m of the origin")
    return p


def _shape_check(p: np.ndarray, where: str) -> None:
    """Reject coincident, collinear and coplanar point sets (singular values of the centred cloud)."""
    q = p - p.mean(axis=0)
    s = np.linalg.svd(q, compute_uv=False) / np.sqrt(len(p))  # standard deviations along principal axes
    scale = max(s[0], np.abs(p).max(), 1e-300)
    tol = 1e-9 * scale
    if s[0] <= tol:
        raise EstimationError(f"{where}: all {len(p)} points coincide; a sphere needs a spread of points")
    if s[1] <= tol + 1e-6 * s[0]:
        raise EstimationError(f"{where}: the {len(p)} points are collinear; a sphere cannot be fitted")
    if s[2] <= tol + 1e-6 * s[0]:
        raise EstimationError(f"{where}: the {len(p)} points are coplanar; a plane does not determine a sphere")


# -- algebraic pieces ------------------------------------------------------------------------------

def algebraic_fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Linear least-squares sphere ``|p|^2 = 2 c.p + (R^2 - |c|^2)`` (Kasa fit).

    Parameters
    ----------
    points : (N, 3) array, metres, N >= 4, not coplanar.

    Returns
    -------
    center : (3,) ndarray
    radius : float

    Raises
    ------
    EstimationError
        If the system is singular or the radius comes out imaginary.
    """
    p = np.asarray(points, dtype=np.float64)
    m = p.mean(axis=0)
    q = p - m
    A = np.column_stack([2.0 * q, np.ones(len(q))])
    b = (q * q).sum(axis=1)
    sol, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < 4 or not np.isfinite(sol).all():
        raise EstimationError("sphere fit: algebraic fit is singular (points coplanar or too few)")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if not np.isfinite(r2) or r2 <= 0:
        raise EstimationError("sphere fit: algebraic fit gave no real radius")
    return c + m, float(np.sqrt(r2))


def _ransac(p: np.ndarray, tau: float, radius: float | None, r_range: tuple[float, float],
            n_hyp: int, rng: np.random.Generator, n_keep: int = 4) -> list[tuple[np.ndarray, float]]:
    """The ``n_keep`` best distinct of ``n_hyp`` 4-point spheres by MSAC cost ``sum min(r^2, tau^2)``."""
    n = len(p)
    m = p.mean(axis=0)
    q = p - m
    idx = rng.integers(0, n, size=(n_hyp, 4))
    S = q[idx]                                              # (K, 4, 3)
    A = np.concatenate([2.0 * S, np.ones((n_hyp, 4, 1))], axis=2)
    b = (S * S).sum(axis=2)
    scale = max(np.abs(q).max(), 1e-12)
    det = np.linalg.det(A / np.array([scale, scale, scale, scale * scale]))
    ok = np.abs(det) > 1e-9
    if not ok.any():
        return []
    A = A[ok]
    b = b[ok]
    sol = np.linalg.solve(A, b[..., None])[..., 0]          # (K', 4)
    c = sol[:, :3]
    r2 = sol[:, 3] + (c * c).sum(axis=1)
    good = np.isfinite(r2) & (r2 > 0)
    c, r2 = c[good], r2[good]
    if not len(c):
        return []
    r = np.sqrt(r2)
    if radius is not None:
        good = np.abs(r - radius) < 0.5 * radius
        c, r = c[good], np.full(good.sum(), radius)
    else:
        good = (r >= r_range[0]) & (r <= r_range[1])
        c, r = c[good], r[good]
    if not len(c):
        return []
    # score in chunks so memory stays bounded (K x N distances)
    costs = np.empty(len(c))
    chunk = max(1, int(4e6 // n))
    for s in range(0, len(c), chunk):
        d = np.linalg.norm(q[None, :, :] - c[s:s + chunk, None, :], axis=2) - r[s:s + chunk, None]
        costs[s:s + chunk] = np.minimum(d * d, tau * tau).sum(axis=1)
    # the n_keep best candidates that differ from each other by more than tau
    out: list[tuple[np.ndarray, float]] = []
    for k in np.argsort(costs, kind="stable"):
        if all(np.linalg.norm(c[k] + m - co) > tau or abs(r[k] - ro) > tau for co, ro in out):
            out.append((c[k] + m, float(r[k])))
            if len(out) == n_keep:
                break
    return out


def _refine(p: np.ndarray, c0: np.ndarray, r0: float, radius: float | None, f_scale: float,
            r_bounds: tuple[float, float] | None = None) -> tuple[np.ndarray, float, np.ndarray]:
    """Geometric least squares with a soft-L1 loss; returns centre, radius and the Jacobian at the end.

    ``r_bounds`` (when the radius is free) keeps the radius in a box so that a hopeless start (a plane,
    a blob) cannot run the solver off to an infinite sphere.
    """
    m = p.mean(axis=0)
    q = p - m

    if radius is None:
        def fun(x):
            return np.linalg.norm(q - x[:3], axis=1) - x[3]

        def jac(x):
            d = q - x[:3]
            nrm = np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
            return np.column_stack([-d / nrm, -np.ones(len(d))])

        x0 = np.r_[c0 - m, r0]
    else:
        def fun(x):
            return np.linalg.norm(q - x, axis=1) - radius

        def jac(x):
            d = q - x
            return -d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)

        x0 = np.asarray(c0 - m, dtype=np.float64)
    bounds = (-np.inf, np.inf)
    if radius is None and r_bounds is not None:
        lo, hi = float(r_bounds[0]), float(r_bounds[1])
        x0[3] = np.clip(x0[3], lo * 1.0001, hi * 0.9999)
        bounds = (np.array([-np.inf, -np.inf, -np.inf, lo]), np.array([np.inf, np.inf, np.inf, hi]))
    res = least_squares(fun, x0, jac=jac, bounds=bounds, loss="soft_l1", f_scale=f_scale, method="trf",
                        x_scale="jac", max_nfev=50)
    x = res.x
    if radius is None:
        return x[:3] + m, float(x[3]), jac(x)
    return x + m, float(radius), jac(x)


def _robust_refine(p: np.ndarray, c: np.ndarray, r: float, radius: float | None, tau: float,
                   min_points: int, where: str, r_bounds: tuple[float, float] | None = None
                   ) -> tuple[np.ndarray, float, float]:
    """Robust geometric least squares from a start (c, r); returns centre, radius and noise sigma.

    A few rounds, each on the points within a band around the current sphere that shrinks to 3 sigma of
    the inlier noise (sigma from the MAD): outliers outside the band have no influence at all, those
    inside are damped by the soft-L1 loss.
    """
    band, sigma = tau, tau
    for _ in range(4):
        d = np.abs(np.linalg.norm(p - c, axis=1) - r)
        near = d < band
        if near.sum() < min_points:
            break
        sigma = float(np.clip(1.4826 * np.median(d[near]), 2e-4, tau))
        c, r, _ = _refine(p[near], c, r, radius, sigma, r_bounds)
        if not (np.isfinite(c).all() and np.isfinite(r)):
            raise EstimationError(f"{where}: least squares diverged on {len(p)} points")
        band = float(np.clip(3.0 * sigma, 1e-3, tau))
    return c, r, sigma


# -- the fit ---------------------------------------------------------------------------------------

def fit_sphere(points: Any, radius: float | None = None, *, inlier_threshold_m: float = 0.01,
               radius_range_m: tuple[float, float] = (0.01, 1.0), min_inlier_fraction: float = 0.3,
               min_points: int = 10, max_points: int = 20000, n_hypotheses: int = 256,
               max_radius_rel_std: float = 0.01, max_rms_rel: float = 0.1, seed: int = 0,
               where: str = "sphere fit") -> SphereFit:
    """Fit a sphere to noisy, partial points with outliers (paper §4.3).

    Parameters
    ----------
    points : (N, 3) array_like
        Points in metres (world/marker frame). Rows with NaN/inf are dropped.
    radius : float, optional
        Known radius of the ball (metres); then only the centre is fitted.
    inlier_threshold_m : float
        A point is an inlier if its distance to the sphere is below this (metres). About 2-3x the depth
        noise; the default suits Kinect depth of a mirror ball at 0.5-1 m (sigma 2-5 mm).
    radius_range_m : (float, float)
        Plausible radii (metres); hypotheses outside are discarded and a result outside is an error.
    min_inlier_fraction : float
        Smallest accepted fraction of the points on the sphere; below it the input is taken as outliers.
    min_points : int
        Smallest number of finite points accepted.
    max_points : int
        Larger inputs are randomly subsampled to this many points (deterministic with ``seed``).
    n_hypotheses : int
        RANSAC hypotheses (minimal 4-point spheres).
    max_radius_rel_std : float
        Largest accepted standard error of the radius relative to the radius (only when it is fitted).
    max_rms_rel : float
        Largest accepted RMS residual of the inliers relative to the radius (a blob is not a ball).
    seed : int
        Seed of the random generator (subsampling, RANSAC), for reproducible fits.
    where : str
        Prefix of error messages (which input is being fitted).

    Returns
    -------
    SphereFit

    Raises
    ------
    EstimationError
        Too few points, coincident/collinear/coplanar points, a patch too small or flat to determine the
        radius, no sphere explaining enough points (all outliers), or a radius outside ``radius_range_m``.
    """
    if not (np.isfinite(inlier_threshold_m) and inlier_threshold_m > 0):
        raise AppFusionError(f"{where}: inlier_threshold_m must be a positive number, got {inlier_threshold_m}")
    if radius is not None:
        radius = float(radius)
        if not (np.isfinite(radius) and radius > 0):
            raise AppFusionError(f"{where}: the given radius must be a positive number of metres, got {radius}")
    min_points = max(int(min_points), 5)
    p = _validate(points, min_points, where)
    rng = np.random.default_rng(seed)
    if len(p) > max_points:
        p = p[rng.choice(len(p), size=max_points, replace=False)]
    _shape_check(p, where)
    n = len(p)
    tau = float(inlier_threshold_m)

    cands = _ransac(p, tau, radius, radius_range_m, n_hypotheses, rng)
    if not cands:
        try:
            c, r = algebraic_fit(p)
        except EstimationError as e:
            raise EstimationError(f"{where}: no sphere candidate from {n} points ({e})") from None
        cands = [(c, radius if radius is not None else r)]
    r_bounds = (0.5 * radius_range_m[0], 2.0 * radius_range_m[1])
    refined = [_robust_refine(p, c, r, radius, tau, min_points, where, r_bounds) for c, r in cands]
    # Pick the candidate with the lowest MSAC cost at the finest noise level found (threshold 2.5 sigma):
    # a wrong sphere through a partial cap plus outliers collects points loosely, the right one tightly.
    t2 = (2.5 * min(s for _, _, s in refined)) ** 2
    costs = [float(np.minimum((np.linalg.norm(p - c, axis=1) - r) ** 2, t2).sum()) for c, r, _ in refined]
    c, r, _ = refined[int(np.argmin(costs))]

    res = np.linalg.norm(p - c, axis=1) - r
    inl = np.abs(res) < tau
    n_in = int(inl.sum())
    frac = n_in / n
    if radius is None and not (radius_range_m[0] <= r <= radius_range_m[1]):
        raise EstimationError(f"{where}: fitted radius {r * 1000:.1f} mm is outside the plausible range "
                              f"{radius_range_m[0] * 1000:.0f}-{radius_range_m[1] * 1000:.0f} mm")
    if frac < min_inlier_fraction or n_in < min_points:
        raise EstimationError(f"{where}: no sphere explains the points: the best one has only {n_in} of {n} "
                              f"points ({100 * frac:.0f}%) within {tau * 1000:.1f} mm; need "
                              f"{100 * min_inlier_fraction:.0f}% (all outliers, or noise above the threshold)")
    ri = res[inl]
    # Shell contrast: points on a noisy sphere crowd into the shell |r| < tau, while outliers that happen
    # to meet a shell are as dense there as just outside it (tau < |r| < 3 tau, twice as wide).
    n_out = int(((np.abs(res) >= tau) & (np.abs(res) < 3.0 * tau)).sum())
    contrast = n_in / ((n_out + 4.0) / 2.0)   # 4 pseudo-counts: few points prove little
    if contrast < 4.0:
        raise EstimationError(f"{where}: the {n_in} points within {tau * 1000:.1f} mm of the best sphere are hardly "
                              f"denser than those just outside it ({n_out} within {3 * tau * 1000:.0f} mm), as for "
                              "a cloud of outliers; no sphere in the data, or noise above inlier_threshold_m")
    rms = float(np.sqrt(np.mean(ri * ri)))
    if rms > max_rms_rel * r:
        raise EstimationError(f"{where}: the points scatter {rms * 1000:.1f} mm (RMS) about a sphere of radius "
                              f"{r * 1000:.1f} mm, more than {100 * max_rms_rel:.0f}% of it: a blob of outliers, "
                              "not a ball (or a ball too small for this depth noise)")

    # Determinacy: covariance of the parameters at the solution, over the inliers.
    d = p[inl] - c
    nrm = np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    J = -d / nrm if radius is not None else np.column_stack([-d / nrm, -np.ones(n_in)])
    k = J.shape[1]
    s2 = max(float(ri @ ri) / max(n_in - k, 1), 1e-12)
    JtJ = J.T @ J
    try:
        cond = np.linalg.cond(JtJ)
        cov = s2 * np.linalg.inv(JtJ) if cond < 1e12 else None
    except np.linalg.LinAlgError:
        cov = None
    if cov is None or not np.isfinite(cov).all():
        raise EstimationError(f"{where}: the {n_in} inliers cover too small a part of the sphere to "
                              "determine it (singular normal equations); scan more of the ball or give the radius")
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    center_std = float(std[:3].max())
    radius_std = 0.0
    if radius is None:
        radius_std = float(std[3])
        # Sagitta of the cap the inliers span: how far the patch bulges out of its best plane.
        normals = d / nrm
        mean_n = normals.mean(axis=0)
        cos_half = np.clip(normals @ (mean_n / max(np.linalg.norm(mean_n), 1e-300)), -1, 1).min()
        sagitta = r * (1.0 - cos_half)
        if radius_std > max_radius_rel_std * r or sagitta < 2.0 * rms:
            raise EstimationError(
                f"{where}: the inliers span too small a patch of the ball to determine its radius "
                f"(cap half-angle {np.degrees(np.arccos(cos_half)):.1f} deg, sagitta {sagitta * 1000:.2f} mm "
                f"vs noise {rms * 1000:.2f} mm, radius std {radius_std * 1000:.2f} mm); scan more of the "
                "ball or give its radius")
    out = SphereFit(center=np.asarray(c, float), radius=float(r), rms_m=rms, inlier_fraction=float(frac),
                    n_points=n, n_inliers=n_in, radius_std_m=radius_std, center_std_m=center_std,
                    radius_fixed=radius is not None)
    if not (np.isfinite(out.center).all() and np.isfinite([out.radius, out.rms_m, radius_std, center_std]).all()):
        raise EstimationError(f"{where}: fit produced non-finite values")  # pragma: no cover - guarded above
    return out


def refine_center(points: Any, center: Any, radius: float, band_m: float = 0.01, min_points: int = 50,
                  max_shift_m: float | None = None) -> np.ndarray | None:
    """Re-estimate a sphere's centre (known radius) from a few points, starting at a predicted centre.

    Used per frame by the lighting pass: the ball's depth points of one frame, in that frame's camera
    coordinates, fix where the ball is relative to the camera far better than the tracked pose does
    (a 0.3 degree pose error moves the ball's image by ~3 px, turning its normals by ~4 degrees).
    Robust geometric least squares (soft-L1, radius fixed), first on the points within ``3 band_m`` of
    the predicted sphere, then within ``band_m`` of the first estimate.

    Parameters
    ----------
    points : (N, 3) array
        Points in metres (NaN rows ignored), any frame; ``center`` in the same frame.
    center : (3,) array
        Predicted centre (metres).
    radius : float
        Known radius (metres).
    band_m : float
        Only points within this distance of the predicted sphere are used.
    min_points : int
        Fewer usable points give None.
    max_shift_m : float, optional
        A refined centre farther than this from the prediction is rejected (None); default ``2 band_m``.

    Returns
    -------
    (3,) ndarray or None
        The refined centre, or None when the points do not support a refinement (too few, or the fit
        moved implausibly far).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c0 = np.asarray(center, dtype=np.float64).reshape(3)
    if not (np.isfinite(c0).all() and np.isfinite(radius) and radius > 0 and band_m > 0):
        raise AppFusionError(f"refine_center: centre, radius and band must be finite and positive "
                             f"(got {c0.tolist()}, {radius}, {band_m})")
    p = p[np.isfinite(p).all(axis=1)]
    c = c0
    # Two rounds: a wide band (3x) catches the ball when the prediction is off by up to ~band_m, then the
    # band proper around the first estimate.
    for band in (3.0 * band_m, band_m):
        d = np.abs(np.linalg.norm(p - c, axis=1) - radius)
        near = d < band
        q = p[near]
        if len(q) < max(int(min_points), 5):
            return None
        try:
            _shape_check(q, "refine_center")
        except EstimationError:
            return None
        sigma = float(np.clip(1.4826 * np.median(d[near]), 2e-4, band))
        c, _, _ = _refine(q, c, radius, radius, sigma)
        if not np.isfinite(c).all():
            return None
    limit = 2.0 * band_m if max_shift_m is None else max_shift_m
    if np.linalg.norm(c - c0) > limit:
        return None
    return c


# -- points from depth frames ------------------------------------------------------------------------

def in_box(points: np.ndarray, box: Any) -> np.ndarray:
    """Boolean mask (N,) of points (N, 3) inside ``box``.

    ``box`` is either an object with a ``contains(points) -> (N,) bool`` method (the marker module's
    object box) or an axis-aligned box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` in metres, in the
    frame of the points.
    """
    if hasattr(box, "contains"):
        return np.asarray(box.contains(points), dtype=bool)
    b = np.asarray(box, dtype=np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or (b[1] <= b[0]).any():
        raise AppFusionError("object box must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, "
                             f"got {b.tolist()}")
    return ((points >= b[0]) & (points <= b[1])).all(axis=-1)


def points_from_depth(depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                      box: Any = None, stride: int = 1) -> np.ndarray:
    """World points (M, 3) of a depth image, optionally cropped to the object box.

    Parameters
    ----------
    depth : (H, W) float array
        Metres, NaN or <= 0 where invalid.
    intrinsics : Intrinsics
        Of the depth camera (lens distortion is ignored, as in :meth:`Intrinsics.backproject`).
    pose : (4, 4) array
        Camera-to-world pose of the depth camera (metres).
    box : optional
        See :func:`in_box`; in the world frame of ``pose``.
    stride : int
        Use every ``stride``-th pixel in both directions.
    """
    depth = np.asarray(depth)
    if depth.shape != intrinsics.shape:
        raise AppFusionError(f"depth image of shape {depth.shape} does not match intrinsics {intrinsics.shape}")
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise AppFusionError(f"depth pose must be a finite 4x4 matrix, got shape {pose.shape}")
    s = max(int(stride), 1)
    z = depth[::s, ::s].astype(np.float64)
    rays = intrinsics.rays()[::s, ::s].astype(np.float64)
    ok = np.isfinite(z) & (z > 0)
    pts = transform_points(pose, rays[ok] * z[ok][:, None])
    if box is not None:
        pts = pts[in_box(pts, box)]
    return pts


class PointReservoir:
    """Uniform random sample of at most ``capacity`` points out of all points offered (reservoir sampling).

    Keeps memory constant over a long environment pass while every point offered has the same chance
    of being kept.
    """

    def __init__(self, capacity: int = 200_000, seed: int = 0):
        if capacity < 1:
            raise AppFusionError(f"point reservoir capacity must be positive, got {capacity}")
        self.capacity = int(capacity)
        self._buf = np.empty((self.capacity, 3))
        self._n = 0          # points stored
        self.seen = 0        # points offered
        self._rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self._n

    def add(self, points: np.ndarray) -> None:
        """Offer points (M, 3)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        free = self.capacity - self._n
        if free > 0:
            k = min(free, len(p))
            self._buf[self._n:self._n + k] = p[:k]
            self._n += k
            self.seen += k
            p = p[k:]
        if len(p):
            # Algorithm R, vectorised: point number t (0-based) replaces slot j ~ U{0..t} if j < capacity.
            t = self.seen + np.arange(len(p))
            j = (self._rng.random(len(p)) * (t + 1)).astype(np.int64)
            keep = j < self.capacity
            self._buf[j[keep]] = p[keep]
            self.seen += len(p)

    @property
    def points(self) -> np.ndarray:
        """The kept points, (n, 3) (a view)."""
        return self._buf[:self._n]


def fit_sphere_from_depth(frames: Iterable[tuple[np.ndarray, Intrinsics, np.ndarray]], box: Any = None,
                          radius: float | None = None, stride: int = 2, capacity: int = 200_000,
                          **kwargs) -> SphereFit:
    """Fit the ball straight from depth frames: back-project, crop to the object box, fit.

    Parameters
    ----------
    frames : iterable of (depth, intrinsics, pose)
        Depth images (metres) with their camera intrinsics and camera-to-world poses.
    box : optional
        Object box (see :func:`in_box`) in the world frame; without it every valid pixel counts.
    radius : float, optional
        Known ball radius (metres).
    stride : int
        Pixel stride of the back-projection.
    capacity : int
        Points kept at most (uniform reservoir sample over all frames).
    **kwargs
        Passed to :func:`fit_sphere`.
    """
    res = PointReservoir(capacity)
    for depth, intr, pose in frames:
        res.add(points_from_depth(depth, intr, pose, box, stride))
    return fit_sphere(res.points, radius=radius, where=kwargs.pop("where", "sphere fit from depth"), **kwargs)
