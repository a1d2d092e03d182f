"""The four white circles: detection, support plane, marker frame and object box (paper §4.1, §4.3).

The paper's markers are "four white circles over a black background ... placed on a supporting
plane"; they "define a virtual box with a pre-defined size on top of the supporting plane; anything
outside of the box is considered part of the background", and the environment map and the object
are both expressed in "the local coordinate system defined by markers".

Detection, per frame
--------------------
1. Bright blobs in the IR image (white paper is bright in IR on black paper; on a Kinect v1 the IR
   camera *is* the depth camera) or, lacking IR, in the RGB luminance: several thresholds relative
   to the image's bright level, contours, and an ellipse fit each (:func:`detect_circles`).
2. The support plane: RANSAC over the depth points that project around the candidate blobs
   (:func:`fit_plane_ransac`).
3. Each blob's contour is back-projected onto that plane and a circle is fitted there
   (:func:`circle_on_plane`): this gives the exact 3-D centre (the centre of the image ellipse is
   not the projection of the circle's centre) and the radius, which must match the known radius.
   The circle is then fitted to the blob's pixels themselves, a blurred disc on the plane over an
   uneven plateau and background (:func:`refine_circle`): a contour's fraction-of-a-pixel inset,
   seen at an angle, moved the centres 0.15 mm towards the camera.
4. Four circles forming the known square are chosen and numbered (:func:`number_square`).

Marker frame (``docs/conventions.md``)
--------------------------------------
Origin at the centre of the four circles, z the plane normal towards the camera side (up), x from
the midpoint of circles 3/4 to the midpoint of circles 1/2, y = z x x. Circles are numbered
clockwise seen from +z starting at the (+x, +y) one: 1 = (+, +), 2 = (+, -), 3 = (-, -),
4 = (-, +). A square of four identical circles is symmetric under 90 degree turns; the turn is
fixed by the first frame that sees all four: x is the square's side direction closest to that
camera's image-right direction. Start every pass of a scan (environment, geometry) from the same
side of the table to get the same frame.

The object box is ``|x|, |y| <= side / 2`` (the square spanned by the circle centres) and
``z_min <= z <= height`` (default height 0.30 m, ``z_min`` a few mm to drop the plane itself).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d

from .brdf import local_frame
from .errors import AppFusionError, EstimationError
from .frame import REC709_LUMA, Frame, Intrinsics, invert_pose, transform_points

__all__ = ["MarkerConfig", "Ellipse", "MarkerDetection", "MarkerTracker", "ObjectBox", "view_weight",
           "detect_circles", "fit_plane_ransac", "circle_on_plane", "refine_circle", "number_square", "number_three",
           "number_two", "key_mask", "marker_frame",
           "detect_markers", "marker_config_from_meta"]


@dataclass(frozen=True)
class MarkerConfig:
    """What is known about the printed markers.

    Attributes
    ----------
    radius_m : float
        Radius of each white circle, metres.
    side_m : float or None
        Distance between neighbouring circle centres (the square's side); None = unknown (any
        square whose circles have ``radius_m`` is accepted).
    layout : str
        Only ``"square"`` is supported.
    key_radius_m : float or None
        Radius of the printed *key* circle (circle 1), larger than the others. A square of four equal
        circles has a quarter-turn ambiguity: its numbering, and so the marker frame, depends on the
        side a pass starts from, and an environment map would not line up with a later scan. With a
        key circle the numbering is absolute. None: four equal circles (the numbering then follows
        the first complete detection).
    radius_tol : float
        Relative tolerance of the measured radius.
    side_tol : float
        Relative tolerance of the square's sides and diagonals.
    refine : bool
        Fit each circle to the image of its blob (:func:`refine_circle`) after the contour fit.
    """

    radius_m: float = 0.02
    side_m: float | None = None
    layout: str = "square"
    key_radius_m: float | None = None
    radius_tol: float = 0.25
    side_tol: float = 0.08
    refine: bool = True

    def __post_init__(self):
        if not (self.radius_m > 0):
            raise AppFusionError(f"markers: radius_m must be positive, got {self.radius_m}")
        if self.side_m is not None and not (self.side_m > 4 * self.radius_m):
            raise AppFusionError(f"markers: side_m {self.side_m} must exceed 4 x radius_m {self.radius_m}")
        if self.layout != "square":
            raise AppFusionError(f"markers: layout {self.layout!r} is not supported (only 'square')")
        if self.key_radius_m is not None and not (self.key_radius_m > (1 + self.radius_tol) * self.radius_m):
            raise AppFusionError(f"markers: key_radius_m {self.key_radius_m} must exceed radius_m {self.radius_m} "
                                 f"by more than the radius tolerance ({self.radius_tol:.0%})")

    def centres(self) -> np.ndarray:
        """Printed circle centres (4, 3) in the marker frame, metres: circle 1 (the key) at (+h, +h),
        then clockwise seen from +z, h = side / 2. Needs ``side_m``."""
        if self.side_m is None:
            raise AppFusionError("markers: the circle centres need the printed layout's side (side_m)")
        h = self.side_m / 2
        return np.array([[h, h, 0], [h, -h, 0], [-h, -h, 0], [-h, h, 0]], float)

    def radii(self) -> np.ndarray:
        """Printed radius of each circle (4,), metres: the key circle's first."""
        return np.array([self.key_radius_m or self.radius_m] + [self.radius_m] * 3, float)

    def radius_ok(self, r: float) -> bool:
        """True if a measured radius matches a printed circle (the key circle included)."""
        radii = [self.radius_m] + ([self.key_radius_m] if self.key_radius_m else [])
        return any(abs(r - R) <= self.radius_tol * R for R in radii)


def marker_config_from_meta(meta: dict | None) -> MarkerConfig:
    """A :class:`MarkerConfig` from session meta ``extra = {"markers": {"radius_m", "layout", "side_m"}}``
    (or from that inner dict); defaults where absent."""
    m = dict(meta or {})
    m = m.get("extra", m)
    m = m.get("markers", m) if isinstance(m, dict) else {}
    try:
        return MarkerConfig(radius_m=float(m.get("radius_m", 0.02)),
                            side_m=None if m.get("side_m") is None else float(m["side_m"]),
                            layout=str(m.get("layout", "square")),
                            key_radius_m=None if m.get("key_radius_m") is None else float(m["key_radius_m"]))
    except (TypeError, ValueError) as e:
        raise AppFusionError(f"session meta 'markers' is malformed: {e}") from None


# -- 2-D detection --------------------------------------------------------------------------------
@dataclass
class Ellipse:
    """A bright elliptical blob in an image (pixels)."""

    center: np.ndarray      # (2,) u, v
    axes: np.ndarray        # (2,) semi-axes, major first
    angle_deg: float
    contour: np.ndarray     # (N, 2) float boundary points
    fill: float             # contour area / ellipse area


def _to_gray01(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image, np.float32)
    if img.ndim == 3:
        img = img @ REC709_LUMA.astype(np.float32)
    img = np.where(np.isfinite(img), img, 0)
    hi = float(np.percentile(img, 99.9))
    if hi <= 0:
        return np.zeros(img.shape, np.float32)
    return np.clip(img / hi, 0, 1).astype(np.float32)


def detect_circles(image: np.ndarray, min_radius_px: float = 2.5, max_radius_px: float | None = None,
                   levels: tuple[float, ...] = (0.08, 0.13, 0.2, 0.3, 0.45, 0.6), min_fill: float = 0.85,
                   min_axis_ratio: float = 0.15) -> list[Ellipse]:
    """Bright elliptical blobs (the white circles seen in perspective) in an image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        IR counts or linear RGB (luminance is used); any scale.
    min_radius_px, max_radius_px : float
        Accepted semi-major axis range in pixels (default max: a quarter of the image height).
    levels : tuple of float
        Thresholds relative to the image's 99.9th percentile; a blob found at several levels is
        kept once (the level where its ellipse fits best).
    min_fill : float
        Minimum contour-area / ellipse-area ratio (a disc seen in perspective fills its ellipse).
    min_axis_ratio : float
        Minimum minor/major axis ratio (grazing views below it are too thin to measure).

    Returns
    -------
    list of Ellipse
    """
    g = _to_gray01(image)
    H, W = g.shape
    max_r = max_radius_px or H / 4
    g8 = cv2.GaussianBlur((g * 255).astype(np.uint8), (5, 5), 1.0)
    cands: list[tuple[Ellipse, float]] = []
    for lev in levels:
        _, bw = cv2.threshold(g8, int(lev * 255), 255, cv2.THRESH_BINARY)
        contours, _ = cv2.findContours(bw, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for c in contours:
            if len(c) < 8:
                continue
            area = cv2.contourArea(c)
            if area < np.pi * min_radius_px ** 2 * min_axis_ratio:
                continue
            (cx, cy), (a2, b2), ang = cv2.fitEllipse(c)
            a, b = max(a2, b2) / 2, min(a2, b2) / 2
            if not (min_radius_px <= a <= max_r) or b < min_axis_ratio * a or b <= 0:
                continue
            pts = c[:, 0, :].astype(np.float64)
            if (pts[:, 0].min() <= 0 or pts[:, 1].min() <= 0 or pts[:, 0].max() >= W - 1
                    or pts[:, 1].max() >= H - 1):
                continue                      # touches the border: not fully visible
            fill = area / (np.pi * a * b)
            # a pixel contour of a small disc loses about half a pixel all around
            fill_expected = (max(a - 0.5, 0.1) * max(b - 0.5, 0.1)) / (a * b)
            if fill < min_fill * fill_expected or fill > 1.15:
                continue
            hull = cv2.convexHull(c)
            if area < 0.9 * cv2.contourArea(hull):
                continue
            # every boundary point on the fitted ellipse (a square or a blob with corners is not)
            th = np.deg2rad(ang)
            dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
            xr = (np.cos(th) * dx + np.sin(th) * dy) / (a2 / 2)
            yr = (-np.sin(th) * dx + np.cos(th) * dy) / (b2 / 2)
            if np.hypot(xr, yr).std() > 0.045 + 0.12 / max(b, 1.0):   # a square: ~0.1 at any size
                continue
            cands.append((Ellipse(np.array([cx, cy]), np.array([a, b]), float(ang), pts, float(fill)), lev))
    # one ellipse per blob: the level closest to half of the blob's peak brightness, where the
    # blurred edge of a uniform disc crosses (the contour there has the true size)
    found: list[Ellipse] = []
    used = np.zeros(len(cands), bool)
    for i, (e, _) in enumerate(cands):
        if used[i]:
            continue
        group = [j for j, (f, _) in enumerate(cands)
                 if not used[j] and np.hypot(*(f.center - e.center)) < 0.5 * min(f.axes[1], e.axes[1]) + 1]
        used[group] = True
        u0, v0 = int(round(e.center[0])), int(round(e.center[1]))
        r = max(1, int(min(cands[j][0].axes[1] for j in group) * 0.6))
        peak = float(np.percentile(g8[max(v0 - r, 0):v0 + r + 1, max(u0 - r, 0):u0 + r + 1], 75)) / 255.0
        best = min(group, key=lambda j: abs(cands[j][1] - 0.5 * peak))
        found.append(cands[best][0])
    return found


# -- plane and circles in 3-D -------------------------------------------------------------------
def fit_plane_ransac(points: np.ndarray, threshold: float = 0.004, iterations: int = 128,
                     seed: int = 0) -> tuple[np.ndarray, float, np.ndarray]:
    """Plane through 3-D points by RANSAC then least squares on the inliers.

    Parameters
    ----------
    points : (N, 3) array, metres.
    threshold : float
        Inlier distance, metres.
    iterations : int
        RANSAC samples.

    Returns
    -------
    normal : (3,) unit normal
    d : float
        Offset: ``normal . x + d = 0`` on the plane.
    inliers : (N,) bool
    """
    P = np.asarray(points, np.float64)
    P = P[np.isfinite(P).all(1)]
    if len(P) < 10:
        raise EstimationError(f"plane fit: only {len(P)} valid points")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(P), size=(iterations, 3))
    a, b, c = P[idx[:, 0]], P[idx[:, 1]], P[idx[:, 2]]
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n, axis=1)
    ok = ln > 1e-9
    n, a = n[ok] / ln[ok, None], a[ok]
    if len(n) == 0:
        raise EstimationError("plane fit: points are degenerate (collinear)")
    d = -np.einsum("ij,ij->i", n, a)
    sub = P if len(P) <= 2000 else P[rng.choice(len(P), 2000, replace=False)]
    counts = (np.abs(sub @ n.T + d) < threshold).sum(0)
    best = int(np.argmax(counts))
    inl = np.abs(P @ n[best] + d[best]) < threshold
    for _ in range(2):
        Q = P[inl]
        c0 = Q.mean(0)
        _, _, vt = np.linalg.svd(Q - c0, full_matrices=False)
        nn = vt[2]
        dd = -nn @ c0
        inl = np.abs(P @ nn + dd) < threshold
    full = np.zeros(len(points), bool)
    full[np.flatnonzero(np.isfinite(np.asarray(points)).all(1))[inl]] = True
    return nn, float(dd), full


def circle_on_plane(contour_px: np.ndarray, K: Intrinsics, normal: np.ndarray, d: float
                    ) -> tuple[np.ndarray, float, float]:
    """Exact 3-D circle from its image contour and its plane (camera frame of ``K``).

    Each contour pixel's ray is intersected with the plane ``normal . x + d = 0``; a circle is
    fitted to the intersections in plane coordinates (algebraic fit, Kasa 1976). The contour of a
    thresholded blob lies half a pixel inside the true edge on average, so the fitted radius is
    corrected by half a pixel's footprint.

    Returns
    -------
    center : (3,) metres, camera frame
    radius : float, metres
    rms : float
        RMS distance of the intersections from the fitted circle, metres.
    """
    uv = np.asarray(contour_px, np.float64)
    rays = np.stack([(uv[:, 0] - K.cx) / K.fx, (uv[:, 1] - K.cy) / K.fy, np.ones(len(uv))], axis=1)
    denom = rays @ normal
    if np.any(np.abs(denom) < 1e-9):
        raise EstimationError("circle on plane: a contour ray is parallel to the plane")
    t = -d / denom
    X = rays * t[:, None]
    c0 = X.mean(0)
    e1, e2, _ = local_frame(normal / np.linalg.norm(normal))    # a basis of the plane
    x, y = (X - c0) @ e1, (X - c0) @ e2
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    cx, cy = sol[0], sol[1]
    r = float(np.sqrt(max(sol[2] + cx * cx + cy * cy, 0.0)))
    rms = float(np.sqrt(np.mean((np.hypot(x - cx, y - cy) - r) ** 2)))
    center = c0 + cx * e1 + cy * e2
    pix_m = float(np.mean(t)) / K.fx             # metres per pixel at the circle
    return center, r + 0.5 * pix_m, rms


def _ellipse_size_ok(ellipse: Ellipse, center: np.ndarray, K: Intrinsics, config: MarkerConfig) -> bool:
    """True if a blob is as long as a printed circle at its depth (beyond the paper).

    The disc's diameter across the line of sight is not foreshortened: a circle of radius ``R``
    whose centre is at depth ``z`` images as an ellipse with semi-major axis at least ``f R / z``
    (``f`` the smaller focal length; the detections of the demo and the small sessions measure
    1.0-1.5 times that). :func:`circle_on_plane` alone cannot tell: at a grazing view a
    1-pixel-thin blob's rays stretch over centimetres of the plane, so a speckle of the IR pattern
    on the paper (3.7 x 1.1 px at 84 cm in a 320 x 240 session) or a fragment of a speckled circle
    passed as a circle with its centre 5-19 mm off, and as a tracking anchor pulled the pose 16 mm
    away. A blob whose semi-major axis (plus the contour's half pixel) is below ``1 - radius_tol``
    of the smallest printed radius's image is rejected.
    """
    z = float(center[2])
    if not z > 0:
        return False
    r_min = min(config.radius_m, config.key_radius_m or np.inf)
    return float(ellipse.axes[0]) + 0.5 >= (1.0 - config.radius_tol) * min(K.fx, K.fy) * r_min / z


def refine_circle(image01: np.ndarray, K: Intrinsics, normal: np.ndarray, d: float, center: np.ndarray,
                  radius: float, margin: float = 1.6) -> tuple[np.ndarray, float] | None:
    """A circle on a known plane fitted to the image of the blob itself (beyond the paper).

    Model of each pixel in a window around the circle: ``I = B + (Pl - B) Phi(-s / sigma)``, with
    ``s`` the pixel's signed distance to the circle's edge on the plane converted to pixels (the
    plane's footprint there), ``Pl`` and ``B`` the plateau and the paper around it as planes in the
    image (an uneven light), ``sigma`` the blur. Centre (on the plane), radius, blur and the two
    planes are fitted by robust least squares (Huber, Levenberg-Marquardt) from
    :func:`circle_on_plane`'s answer.

    Why: the contour of a thresholded blob lies a fraction of a pixel inside the edge, by an amount
    that depends on the threshold and the light; seen at an angle, 0.1 pixel of contour offset moves
    the centre ~0.1 mm along the line of sight (20 degrees of elevation), and the far side's pixels
    cover more of the plane, so the centres came out 0.15 mm towards the camera on the demo. Every
    pixel of the blob enters the fit, which also averages the IR emitter's dot pattern.

    Measured: rendered discs at 20-60 degrees of elevation, within 0.03 mm (contour 0.1-0.2 mm off);
    the demo's geometry frames against the truth, along the line of sight within the plane, mean
    +0.01 mm (std 0.29) against -0.15 mm (0.42) from the contour, across it 0.22 mm std (0.30). A
    light falling off as 1/d^2 across a disc at 20 degrees still leaves -0.16 mm (the contour -0.47;
    not traced). ~10 ms a circle on one core.

    Parameters
    ----------
    image01 : (H, W) float array
        The image the circle was found in, scaled to about 0-1.
    K : Intrinsics
    normal, d : the plane ``normal . x + d = 0`` (camera frame of ``K``, metres).
    center : (3,) array, radius : float
        Starting circle (metres).
    margin : float
        Window: the circle's image out to ``margin`` radii.

    Returns
    -------
    (center (3,), radius) or None when the fit fails or strays (centre moved more than a third of
    the radius, radius changed by more than 20 %).
    """
    from scipy.special import ndtr

    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    e1, e2, _ = local_frame(n)                                # a basis of the plane
    c0 = np.asarray(center, np.float64)
    H, W = image01.shape
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = c0 + margin * radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    uvr, zr = K.project(ring)
    if not (np.all(zr > 0) and np.all(np.isfinite(uvr))):
        return None
    x0, y0 = int(np.floor(uvr[:, 0].min())), int(np.floor(uvr[:, 1].min()))
    x1, y1 = int(np.ceil(uvr[:, 0].max())) + 1, int(np.ceil(uvr[:, 1].max())) + 1
    if x0 < 0 or y0 < 0 or x1 > W or y1 > H or (x1 - x0) * (y1 - y0) > 40000 or (x1 - x0) < 6 or (y1 - y0) < 6:
        return None
    vv, uu = np.mgrid[y0:y1, x0:x1]
    uu, vv = uu.ravel().astype(np.float64), vv.ravel().astype(np.float64)
    I = np.asarray(image01, np.float64)[y0:y1, x0:x1].ravel()
    rays = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones_like(uu)], axis=1)
    den = rays @ n
    if np.any(np.abs(den) < 1e-9):
        return None
    X = rays * (-d / den)[:, None]
    px, py = (X - c0) @ e1, (X - c0) @ e2                    # plane coordinates (metres)
    rr0 = np.hypot(px, py)
    inside = rr0 < radius
    # pixels per metre along the radial direction on the plane, at each pixel
    ru = np.where(rr0 > 1e-9, px / np.maximum(rr0, 1e-12), 1.0)
    rv = np.where(rr0 > 1e-9, py / np.maximum(rr0, 1e-12), 0.0)
    h = 1e-4
    Xs = X + h * (ru[:, None] * e1 + rv[:, None] * e2)
    k = np.hypot(K.fx * (Xs[:, 0] / Xs[:, 2] - X[:, 0] / X[:, 2]), K.fy * (Xs[:, 1] / Xs[:, 2] - X[:, 1] / X[:, 2])) / h
    du, dv = (uu - uu.mean()) / 10.0, (vv - vv.mean()) / 10.0
    hi = float(np.median(I[inside])) if inside.any() else float(I.max())
    lo = float(np.median(I[rr0 > 1.3 * radius])) if (rr0 > 1.3 * radius).any() else float(I.min())
    if not hi > lo:
        return None

    def parts(q):
        cx, cy, r, sig = q[:4]
        sig = max(abs(sig), 0.05)
        pl = q[4] + q[5] * du + q[6] * dv
        bg = q[7] + q[8] * du + q[9] * dv
        ddx, ddy = px - cx, py - cy
        rho = np.maximum(np.hypot(ddx, ddy), 1e-12)
        t = -(rho - r) * k / sig                           # minus the signed distance in blurs
        return pl, bg, ddx, ddy, rho, t, sig

    def resid(q):
        pl, bg, _, _, _, t, _ = parts(q)
        return bg + (pl - bg) * ndtr(t) - I

    def jac(q):
        pl, bg, ddx, ddy, rho, t, sig = parts(q)
        f = ndtr(t)
        g = (pl - bg) * np.exp(-0.5 * t * t) * (1.0 / np.sqrt(2 * np.pi))   # d model / d t
        return np.stack([g * k * ddx / (rho * sig), g * k * ddy / (rho * sig), g * k / sig, -g * t / sig,
                         f, f * du, f * dv, 1 - f, (1 - f) * du, (1 - f) * dv], axis=1)

    # Levenberg-Marquardt on Huber-weighted residuals (a neighbouring object's pixels in the window,
    # the emitter's dots), normal equations of the 10 unknowns: ~1 ms an iteration at 5000 pixels
    huber = 0.1 * (hi - lo)

    def weighted(q):
        res = resid(q)
        w = np.where(np.abs(res) < huber, 1.0, huber / np.maximum(np.abs(res), 1e-12))
        return res, w, float(np.sum(w * res * res))

    q = np.array([0.0, 0.0, radius, 0.8, hi, 0.0, 0.0, lo, 0.0, 0.0])
    res, w, cost = weighted(q)
    lam, A = 1e-3, None
    for _ in range(30):
        if A is None:                                      # the normal equations at a new q
            J = jac(q)
            A, g = J.T @ (J * w[:, None]), J.T @ (w * res)
        step = np.linalg.solve(A + lam * np.diag(np.diag(A) + 1e-12), -g)
        res_t, w_t, cost_t = weighted(q + step)
        if not cost_t <= cost:                             # worse (or NaN): keep q, damp more
            lam *= 10
            if lam > 1e6:
                break
            continue
        q, res, w, cost, lam, A = q + step, res_t, w_t, cost_t, max(lam * 0.3, 1e-7), None
        if np.all(np.abs(step[:3]) < 1e-7) and abs(step[3]) < 1e-4:
            break
    if not np.isfinite(q).all():
        return None
    cx, cy, r = q[:3]
    if not (np.hypot(cx, cy) < radius / 3 and abs(r / radius - 1) < 0.2):
        return None
    return c0 + cx * e1 + cy * e2, float(r)


def number_square(centers: np.ndarray, normal: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    """Order four circle centres 1..4 (see the module docstring) given the marker normal (z) and a
    direction that x should be closest to. Returns the permutation (indices into ``centers``)."""
    C = np.asarray(centers, float)
    z = normal / np.linalg.norm(normal)
    xh = x_hint - (x_hint @ z) * z
    if np.linalg.norm(xh) < 1e-9:
        xh = np.cross(z, [0.0, 1.0, 0.0])
    xh /= np.linalg.norm(xh)
    yh = np.cross(z, xh)
    p = C - C.mean(0)
    th = np.arctan2(p @ yh, p @ xh)
    # corners of an axis-aligned square sit at 45 + k 90 degrees: rotation of the square
    phi = np.angle(np.mean(np.exp(4j * (th - np.pi / 4)))) / 4
    x = np.cos(phi) * xh + np.sin(phi) * yh
    y = np.cross(z, x)
    px, py = p @ x, p @ y
    quad = {(True, True): 0, (True, False): 1, (False, False): 2, (False, True): 3}
    order = np.full(4, -1)
    for i in range(4):
        order[quad[(bool(px[i] > 0), bool(py[i] > 0))]] = i
    if (order < 0).any():
        raise EstimationError("markers: the four circles do not form a square around their centre")
    return order


def _square_corner(P: np.ndarray, m: int) -> np.ndarray:
    """Circle ``m``'s centre (0-based) where the square of the other three, numbered ``P`` (4, 3), puts
    it: its neighbours' sum less the circle across from it."""
    return P[(m - 1) % 4] + P[(m + 1) % 4] - P[(m + 2) % 4]


def key_mask(radii: np.ndarray, config: MarkerConfig, margin: float = 0.5) -> np.ndarray | None:
    """Which measured radii are the key circle's (circle 1), or None where that is unclear.

    Parameters
    ----------
    radii : (K,) array
        Measured circle radii, metres.
    config : MarkerConfig
        Needs ``key_radius_m``.
    margin : float
        A radius is the key's within ``margin`` times the difference of the two printed radii of
        ``key_radius_m``, a plain circle's within that of ``radius_m``. At 0.5 (default) every radius
        is one or the other; below it a radius in the band between them makes the answer None (a
        partly hidden 25 mm circle fitted at 31.9 mm, beside a 35 mm key).

    Returns
    -------
    (K,) bool array, or None without a key circle in ``config`` or with a radius in neither band.
    """
    if not config.key_radius_m:
        return None
    r = np.asarray(radii, float)
    key_r, r0 = float(config.key_radius_m), float(config.radius_m)
    band = margin * abs(key_r - r0)
    is_key = np.abs(r - key_r) < band
    if not np.all(is_key | (np.abs(r - r0) < band)):
        return None
    return is_key


def number_two(det: "MarkerDetection", config: MarkerConfig, side_m: float | None = None,
               margin: float = 0.5) -> np.ndarray | None:
    """Circle numbers (0-based) of two detected circles when the key circle alone fixes them, or None.

    Only the key circle (circle 1) with the circle across the diagonal (circle 3) is unambiguous: any
    other pair fits two or more places of the square (beyond the paper; with the support plane's
    normal such a pair fixes the camera pose, :func:`appfusion.fusion.anchor_pose`).

    Parameters
    ----------
    det : MarkerDetection
        Two circles (``det.n == 2``).
    config : MarkerConfig
        Needs ``key_radius_m``.
    side_m : float, optional
        The square's side, metres (default ``config.side_m``); without either, the pair's distance is
        not checked against the diagonal and None is returned.
    margin : float
        Radius bands of :func:`key_mask`.

    Returns
    -------
    (2,) int array: 0 for the key circle and 2 for the other; or None.
    """
    if det.n != 2 or not config.key_radius_m:
        return None
    side = side_m or config.side_m
    P = np.asarray(det.centers, float)
    if not side or not np.all(np.isfinite(P)):
        return None
    if abs(float(np.linalg.norm(P[1] - P[0])) - side * np.sqrt(2)) > 0.015:
        return None
    is_key = key_mask(det.radii, config, margin)
    if is_key is None or is_key.sum() != 1:
        return None
    return np.where(is_key, 0, 2).astype(np.int64)


def number_three(det: "MarkerDetection", config: MarkerConfig, side_m: float | None = None,
                 margin: float = 0.5) -> np.ndarray | None:
    """Circle numbers (0-based) of three detected circles of the printed square, or None.

    Three corners of the square determine it: the right-angle corner ``c`` is the one opposite the
    longest side; its neighbours are ``c - 1`` and ``c + 1`` (cyclic), told apart by the handedness
    of the triangle about the plane normal (circles 1-4 run clockwise seen from +z); ``c`` is fixed
    by the key circle if it is among the three, else the missing circle is the key (circle 1) and
    ``c`` is circle 3 (beyond the paper, whose four circles are alike).

    Parameters
    ----------
    det : MarkerDetection
        Three circles (``det.n == 3``) with the support plane's normal.
    config : MarkerConfig
        Needs ``key_radius_m``.
    side_m : float, optional
        The square's side, metres; default ``config.side_m``, else the mean of the triangle's two
        legs. Legs and hypotenuse must match it within 1.5 cm.
    margin : float
        Radius bands of the key and the plain circles (:func:`key_mask`).

    Returns
    -------
    (3,) int array, or None: not three circles, no normal or key circle, a triangle that is not
    three corners of the square, more than one key-sized circle, or a radius in neither band.
    """
    if det.n != 3 or det.normal is None or not config.key_radius_m:
        return None
    P = np.asarray(det.centers, float)
    if not np.all(np.isfinite(P)):
        return None
    d = np.linalg.norm(P[[1, 2, 0]] - P[[2, 0, 1]], axis=1)     # side opposite each vertex
    c = int(np.argmax(d))
    a, b = [i for i in range(3) if i != c]
    legs = np.linalg.norm(P[[a, b]] - P[c], axis=1)
    side = float(side_m or config.side_m or legs.mean())
    if np.abs(legs - side).max() > 0.015 or abs(d[c] - side * np.sqrt(2)) > 0.015:
        return None
    # order the legs: p = c - 1, q = c + 1 satisfy ((p - c) x (q - c)) . n > 0
    if np.dot(np.cross(P[a] - P[c], P[b] - P[c]), det.normal) < 0:
        a, b = b, a
    is_key = key_mask(det.radii, config, margin)
    if is_key is None or is_key.sum() > 1:
        return None
    if not is_key.any():
        nc = 2                                      # circles 2, 3, 4 seen: the corner is circle 3
    elif is_key[c]:
        nc = 0
    elif is_key[a]:                                 # a = c - 1 is circle 1
        nc = 1
    else:                                           # b = c + 1 is circle 1
        nc = 3
    out = np.empty(3, np.int64)
    out[c], out[a], out[b] = nc, (nc - 1) % 4, (nc + 1) % 4
    return out


def marker_frame(centers: np.ndarray, normal: np.ndarray | None = None) -> np.ndarray:
    """Marker-to-camera (or marker-to-world) 4x4 transform from the four numbered circle centres.

    Parameters
    ----------
    centers : (4, 3) array
        Circles 1..4 in some frame (metres).
    normal : (3,) array, optional
        Plane normal towards the camera side; default: the normal of the centres' best-fit plane
        oriented by the numbering (clockwise seen from +z).
    """
    C = np.asarray(centers, float)
    o = C.mean(0)
    x = (C[0] + C[1]) / 2 - (C[2] + C[3]) / 2
    if normal is None:
        _, _, vt = np.linalg.svd(C - o)
        z = vt[2]
        # clockwise from +z: (c1 - o) x (c2 - o) points along -z
        if np.cross(C[0] - o, C[1] - o) @ z > 0:
            z = -z
    else:
        z = np.asarray(normal, float) / np.linalg.norm(normal)
    x = x - (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, o
    return T


# -- per-frame detection ---------------------------------------------------------------------------
@dataclass
class MarkerDetection:
    """Markers found in one frame (all 3-D quantities in the depth camera frame, metres).

    Attributes
    ----------
    centers : (K, 3) array
        Centres of the circles found (K = 0..4, more only when no square was found).
    radii : (K,) array
    pixels : (K, 2) array
        Ellipse centres in the detection image.
    normal : (3,) array or None
        Support-plane normal towards the camera.
    plane_d : float
        ``normal . x + plane_d = 0``.
    complete : bool
        All four circles were found and form the square; ``centers`` is then numbered 1..4.
    stream : str
        Image used ("ir" or "rgb").
    """

    centers: np.ndarray
    radii: np.ndarray
    pixels: np.ndarray
    normal: np.ndarray | None
    plane_d: float
    complete: bool
    stream: str

    @property
    def n(self) -> int:
        return int(len(self.centers))

    def frame(self) -> np.ndarray:
        """Marker-to-depth-camera transform (complete detections only)."""
        if not self.complete:
            raise EstimationError("markers: the marker frame needs all four circles")
        return marker_frame(self.centers, self.normal)


def _empty(stream: str) -> MarkerDetection:
    return MarkerDetection(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)), None, 0.0, False, stream)


def detect_markers(frame: Frame, config: MarkerConfig | None = None, stream: str | None = None
                   ) -> MarkerDetection:
    """Find the white circles of a frame in 3-D (paper §4.1).

    Parameters
    ----------
    frame : Frame
        Needs depth with its intrinsics, and an IR or RGB image with intrinsics (and
        ``depth_to_ir`` / ``depth_to_rgb``).
    config : MarkerConfig, optional
    stream : {"ir", "rgb"}, optional
        Image to detect in; default IR when present, else RGB.

    Returns
    -------
    MarkerDetection
        Possibly empty (``n == 0``) when no circle is visible.
    """
    cfg = config or MarkerConfig()
    if frame.depth is None or frame.depth_intrinsics is None:
        raise AppFusionError(f"frame {frame.index}: marker detection needs depth with intrinsics")
    stream = stream or ("ir" if frame.ir is not None else "rgb")
    if stream == "ir":
        img, K, T = frame.ir, frame.ir_intrinsics or frame.depth_intrinsics, frame.depth_to_ir
    elif stream == "rgb":
        img, K, T = frame.rgb_linear(), frame.rgb_intrinsics, frame.depth_to_rgb
    else:
        raise AppFusionError(f"markers: unknown stream {stream!r} (use 'ir' or 'rgb')")
    if img is None or K is None:
        raise AppFusionError(f"frame {frame.index}: no {stream} image with intrinsics for marker detection")
    if img.shape[:2] != K.shape:
        raise AppFusionError(f"frame {frame.index}: {stream} image {img.shape[:2]} does not match its intrinsics {K.shape}")
    Kd = frame.depth_intrinsics
    depth = np.asarray(frame.depth, np.float32)
    # depth points (every `step`-th pixel) in the detection camera, and where they land in its image
    step = max(1, int(np.ceil(np.sqrt(depth.size / 20000))))
    ds = depth[::step, ::step]
    vv, uu = np.nonzero(np.isfinite(ds) & (ds > 0))
    if len(vv) < 50:
        return _empty(stream)
    z0 = ds[vv, uu].astype(np.float64)
    Pd = np.stack([(uu * step - Kd.cx) / Kd.fx * z0, (vv * step - Kd.cy) / Kd.fy * z0, z0], axis=1)
    P = Pd @ T[:3, :3].T + T[:3, 3]
    P = P[P[:, 2] > 0]
    if len(P) < 50:
        return _empty(stream)
    uv, z = K.project(P)
    zmed = float(np.median(z))
    min_r = max(2.5, 0.5 * K.fx * cfg.radius_m / max(zmed * 2.5, 1e-3))
    max_r = 2.0 * K.fx * cfg.radius_m / max(float(np.percentile(z, 1)), 0.05)
    ells = detect_circles(img, min_radius_px=min_r, max_radius_px=max_r)
    g01 = _to_gray01(img) if cfg.refine else None
    if not ells:
        return _empty(stream)
    # plane from the depth points around the blobs
    near = np.zeros(len(P), bool)
    for e in ells:
        r = 2.5 * e.axes[0]
        box = np.flatnonzero((np.abs(uv[:, 0] - e.center[0]) < r) & (np.abs(uv[:, 1] - e.center[1]) < r))
        near[box[np.hypot(uv[box, 0] - e.center[0], uv[box, 1] - e.center[1]) < r]] = True
    if near.sum() < 30:
        return _empty(stream)
    try:
        n, d, inl = fit_plane_ransac(P[near], threshold=max(0.004, 0.006 * zmed))
    except EstimationError:
        return _empty(stream)
    if d < 0:                                      # orient the normal towards the camera (origin)
        n, d = -n, -d
    Pn = P[near]
    cands = []
    for e in ells:
        sel = np.hypot(uv[near][:, 0] - e.center[0], uv[near][:, 1] - e.center[1]) < 1.5 * e.axes[0]
        if sel.sum() >= 3 and np.median(np.abs(Pn[sel] @ n + d)) > max(0.006, 0.01 * zmed):
            continue                              # a bright blob that is not on the plane
        try:
            c, r, rms = circle_on_plane(e.contour, K, n, d)
        except EstimationError:
            continue
        if not cfg.radius_ok(r) or rms > 0.3 * cfg.radius_m:
            continue
        if not _ellipse_size_ok(e, c, K, cfg):
            continue
        if cfg.refine:
            better = refine_circle(g01, K, n, d, c, r)
            if better is not None and cfg.radius_ok(better[1]):
                c, r = better
        cands.append((c, r, e.center))
    if not cands:
        return MarkerDetection(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)), _to_depth_dir(n, T),
                               _to_depth_d(n, d, T), False, stream)
    C = np.array([c[0] for c in cands])
    R = np.array([c[1] for c in cands])
    UV = np.array([c[2] for c in cands])
    best, best_err = None, np.inf
    if len(C) >= 4:
        for combo in itertools.combinations(range(min(len(C), 10)), 4):
            Q = C[list(combo)]
            D = np.sort([np.linalg.norm(Q[i] - Q[j]) for i, j in itertools.combinations(range(4), 2)])
            side = D[:4].mean() if cfg.side_m is None else cfg.side_m
            err = max(np.abs(D[:4] - side).max() / side, np.abs(D[4:] - side * np.sqrt(2)).max() / (side * np.sqrt(2)))
            if err < cfg.side_tol and err < best_err:
                best, best_err = list(combo), err
    Tinv = invert_pose(T)
    n_depth = _to_depth_dir(n, T)
    d_depth = _to_depth_d(n, d, T)
    if best is None:
        return MarkerDetection(transform_points(Tinv, C), R, UV, n_depth, d_depth, False, stream)
    Cb = transform_points(Tinv, C[best])
    order = number_square(Cb, n_depth, np.array([1.0, 0.0, 0.0]))
    idx = np.array(best)[order]
    if cfg.key_radius_m:
        # the key circle is circle 1: rotate the numbering (keeps its handedness)
        k = int(np.argmax(R[idx]))
        others = np.delete(R[idx], k)
        if R[idx][k] > 0.5 * (cfg.radius_m + cfg.key_radius_m) and np.all(others < 0.5 * (cfg.radius_m + cfg.key_radius_m)):
            idx = np.roll(idx, -k)
        else:  # the key circle is not recognisable: do not let an arbitrary numbering define the frame
            return MarkerDetection(transform_points(Tinv, C[idx]), R[idx], UV[idx], n_depth, d_depth, False, stream)
    return MarkerDetection(transform_points(Tinv, C[idx]), R[idx], UV[idx], n_depth, d_depth, True, stream)


def _to_depth_dir(n: np.ndarray, T: np.ndarray) -> np.ndarray:
    return T[:3, :3].T @ n


def _to_depth_d(n: np.ndarray, d: float, T: np.ndarray) -> float:
    # plane n.x + d = 0 in the image camera; x_img = R x_depth + t -> (R^T n).x_depth + (n.t + d) = 0
    return float(n @ T[:3, 3] + d)


# -- fusion over frames -----------------------------------------------------------------------------
def view_weight(centers: np.ndarray, normal: np.ndarray | None, floor: float = 1e-3) -> np.ndarray:
    """Weight ``sin(e)^2`` of circle centres seen at elevation ``e`` above their plane.

    Parameters
    ----------
    centers : (K, 3) array
        Centres in the camera frame (metres); the camera is at the origin.
    normal : (3,) array or None
        The support plane's normal in the same frame; None gives weight 1.
    floor : float
        Smallest weight (a centre seen edge-on).

    Returns
    -------
    (K,) array in ``[floor, 1]``.
    """
    C = np.asarray(centers, np.float64).reshape(-1, 3)
    if normal is None or not len(C):
        return np.ones(len(C))
    n = np.asarray(normal, np.float64)
    n = n / max(float(np.linalg.norm(n)), 1e-12)
    r = C / np.maximum(np.linalg.norm(C, axis=1, keepdims=True), 1e-12)
    return np.clip((r @ n) ** 2, floor, 1.0)


@dataclass
class MarkerTracker:
    """Running weighted mean of the four circle centres in the world frame (paper §4.1, §4.3).

    The numbering is fixed by the first complete detection (x closest to that camera's
    image-right direction); later detections, complete or partial, are matched to the fused
    centres by proximity.

    Each detected centre weighs ``sin(e)^2``, ``e`` the elevation of the line of sight above the
    support plane (:func:`view_weight`; beyond the paper). A circle seen at a grazing angle is
    a thin ellipse: a fraction of a pixel of error across it moves the centre by that much over
    ``sin(e)`` along the line of sight on the plane, and the depth around it is sparse. On
    synthetic seed 1 the geometry pass's detections at 12-29 degrees had errors of 0.6-2.2 mm
    (0.14 mm median elsewhere), which put the plain mean of circle 4 0.15 mm off and, through the
    marker frame, the fused object 0.1 mm off the truth (the relit error 0.075; 0.044 with the
    object moved back). The weights bring the circles' mean errors to 0.02-0.03 mm.

    Parameters
    ----------
    config : MarkerConfig
    match_dist : float, optional
        Largest distance (metres) between a detected centre and the fused one it updates;
        default 1.5 x radius.
    view_weighting : bool, optional
        Weight each centre by ``sin(e)^2`` (default); False: the plain mean.
    from_three : bool, optional
        With a key circle (``config.key_radius_m``), let three circles numbered by
        :func:`number_three` start the tracker before any frame shows all four (default): the fourth
        centre is put where the square puts it (:attr:`inferred`) until a detection of it replaces it.
        Only radii clearly the key's or a plain circle's count (:func:`key_mask`, margin
        :attr:`THREE_RADIUS_MARGIN`). On the 12-frames-a-pass synthetic Kinect sphere (30 degrees of
        orbit a frame) the geometry pass starts with three circles, and the marker frame was only
        defined at its eleventh frame; beyond the paper.
    """

    #: radius band of :func:`key_mask` for numbering three circles: a quarter of the difference of
    #: the printed radii (2.5 mm for 25 and 35 mm circles)
    THREE_RADIUS_MARGIN = 0.25

    config: MarkerConfig = field(default_factory=MarkerConfig)
    match_dist: float | None = None
    view_weighting: bool = True
    from_three: bool = True
    sums: np.ndarray = field(default_factory=lambda: np.zeros((4, 3)))      # weighted sums of centres
    weights: np.ndarray = field(default_factory=lambda: np.zeros(4))        # sums of their weights
    counts: np.ndarray = field(default_factory=lambda: np.zeros(4))         # detections fused
    #: circles not detected yet, put where the square of the other three puts them
    inferred: np.ndarray = field(default_factory=lambda: np.zeros(4, bool))
    normal_sum: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n_complete: int = 0
    n_updates: int = 0

    @property
    def initialised(self) -> bool:
        return bool(np.all((self.counts > 0) | self.inferred))

    def number_three(self, det: MarkerDetection) -> np.ndarray | None:
        """Circle numbers of a three-circle detection (:func:`number_three`, with the printed side or,
        once known, the fused one, and clear radii only), or None."""
        side = self.config.side_m or (self.side() if self.initialised else None)
        return number_three(det, self.config, side, self.THREE_RADIUS_MARGIN)

    def number_two(self, det: MarkerDetection) -> np.ndarray | None:
        """Circle numbers of a two-circle detection, the key circle and the one across the diagonal
        (:func:`number_two`, clear radii only), or None."""
        side = self.config.side_m or (self.side() if self.initialised else None)
        return number_two(det, self.config, side, self.THREE_RADIUS_MARGIN)

    @property
    def centers(self) -> np.ndarray:
        """(4, 3) fused centres 1..4 in the world frame."""
        if not self.initialised:
            raise EstimationError("markers: no frame has shown all four circles (or three numbered by the key circle) yet")
        return self.sums / self.weights[:, None]

    def update(self, det: MarkerDetection, pose: np.ndarray) -> np.ndarray:
        """Fuse a detection made from camera ``pose`` (depth camera-to-world).

        Returns
        -------
        (K,) int array: the circle number (0-based) each detected centre was assigned to, -1 if none.
        """
        assign = np.full(det.n, -1)
        if det.n == 0:
            return assign
        W = transform_points(pose, det.centers)
        nw = None if det.normal is None else pose[:3, :3] @ det.normal
        w = self._weights(det)
        if not self.initialised:
            if det.complete:
                self.sums[:] = w[:, None] * W
                self.weights[:] = w
                self.counts[:] = 1
                self.normal_sum = nw.copy()
                self.n_complete = 1
                self.n_updates = 1
                return np.arange(4)
            idx = self.number_three(det) if self.from_three else None
            if idx is None:
                return assign
            m = int(np.setdiff1d(np.arange(4), idx)[0])
            P = np.empty((4, 3))
            P[idx] = W
            P[m] = _square_corner(P, m)
            w4 = np.empty(4)
            w4[idx] = w
            w4[m] = w.min()
            self.sums[:] = w4[:, None] * P
            self.weights[:] = w4
            self.counts[:] = 0
            self.counts[idx] = 1
            self.inferred[:] = False
            self.inferred[m] = True
            self.normal_sum = nw.copy()
            self.n_updates = 1
            return idx
        assign = self._assign(W, self.centers)
        for k, j in enumerate(assign):
            if j >= 0:
                if self.inferred[j]:                    # its first detection replaces the inferred centre
                    self.sums[j] = 0.0
                    self.weights[j] = 0.0
                    self.inferred[j] = False
                self.sums[j] += w[k] * W[k]
                self.weights[j] += w[k]
                self.counts[j] += 1
        if nw is not None and (assign >= 0).any():
            self.normal_sum += nw
        self.n_complete += int(det.complete and (assign >= 0).all())
        self.n_updates += 1
        return assign

    def _weights(self, det: MarkerDetection) -> np.ndarray:
        """(K,) weight of each detected centre in the running mean (:func:`view_weight`, or 1)."""
        return view_weight(det.centers, det.normal) if self.view_weighting else np.ones(det.n)

    def _assign(self, W: np.ndarray, C: np.ndarray) -> np.ndarray:
        """Circle number (0-based) of each world-frame centre ``W``: the nearest of ``C`` within the
        match distance, each circle at most once (in the order of ``W``); -1 for none."""
        md = self.match_dist or 1.5 * self.config.radius_m
        assign = np.full(len(W), -1)
        dist = np.linalg.norm(W[:, None, :] - C[None], axis=2)
        for k in range(len(W)):
            j = int(np.argmin(dist[k]))
            if dist[k, j] < md and j not in assign:
                assign[k] = j
        return assign

    def refit(self, views) -> bool:
        """Fuse the centres again from ``(detection, pose)`` pairs, e.g. the same detections at
        poses refined after tracking (:meth:`appfusion.geometry_pass.GeometryPass.refuse`).

        Each centre is matched to the current fused circles (their numbering stays) and weighed
        as in :meth:`update`; constant memory. Tracking-time poses carry the model's drift (0.28 mm
        RMS on the demo, against 0.12 mm after refusing), and the marker frame the mesh is put in
        is made of these centres: on synthetic seed 1 the fused object's dome sat 0.09 -> 0.04 mm
        off the truth with the centres refitted at the refused poses.

        Parameters
        ----------
        views : iterable of (MarkerDetection or None, (4, 4) array or None)
            Detections in their camera frames and camera-to-world poses; pairs with either missing
            are skipped.

        Returns
        -------
        bool
            True when every circle was matched at least once, or all but one only inferred so far
            (:attr:`inferred`: put again at the square's corner from the other three), and the
            centres were replaced; False (the current centres kept) otherwise, or before the tracker is
            initialised.
        """
        if not self.initialised:
            return False
        C = self.centers
        sums, weights, counts, nsum = np.zeros((4, 3)), np.zeros(4), np.zeros(4), np.zeros(3)
        for det, pose in views:
            if det is None or pose is None or det.n == 0 or not np.all(np.isfinite(pose)):
                continue
            W = transform_points(pose, det.centers)
            w = self._weights(det)
            assign = self._assign(W, C)
            hit = assign >= 0
            np.add.at(sums, assign[hit], w[hit, None] * W[hit])
            np.add.at(weights, assign[hit], w[hit])
            np.add.at(counts, assign[hit], 1)
            if det.normal is not None and hit.any():
                nsum += pose[:3, :3] @ det.normal
        unseen = counts == 0
        # a circle never detected, only inferred, is inferred again from the other three
        if unseen.sum() > 1 or (unseen & ~self.inferred).any() or not np.linalg.norm(nsum) > 0:
            return False
        if unseen.any():
            m = int(np.flatnonzero(unseen)[0])
            P = sums / np.maximum(weights, 1e-300)[:, None]
            w = weights[[(m - 1) % 4, (m + 1) % 4, (m + 2) % 4]].min()
            sums[m] = w * _square_corner(P, m)
            weights[m] = w
        self.sums, self.weights, self.counts, self.normal_sum = sums, weights, counts, nsum
        self.inferred[:] = unseen
        return True

    @property
    def normal(self) -> np.ndarray | None:
        """(3,) the fused support plane's unit normal in the world frame; None before any."""
        ln = float(np.linalg.norm(self.normal_sum))
        return self.normal_sum / ln if ln > 0 else None

    def marker_to_world(self) -> np.ndarray:
        """4x4 transform from the marker frame to the world frame, from the fused centres."""
        return marker_frame(self.centers, self.normal)

    def side(self) -> float:
        """Mean measured side of the square, metres."""
        C = self.centers
        return float(np.mean([np.linalg.norm(C[i] - C[(i + 1) % 4]) for i in range(4)]))


# -- the object box ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class ObjectBox:
    """The virtual box on the support plane that holds the object (marker frame, metres).

    Attributes
    ----------
    half_x, half_y : float
        Half extents in x and y (``side / 2`` for the square of circle centres).
    z_min, z_max : float
        Height range; ``z_min`` a few millimetres above the plane drops the plane itself.
    """

    half_x: float
    half_y: float
    z_min: float = 0.004
    z_max: float = 0.30

    def __post_init__(self):
        if not (self.half_x > 0 and self.half_y > 0 and self.z_max > self.z_min):
            raise AppFusionError(f"object box: invalid extents {self}")

    @classmethod
    def from_side(cls, side_m: float, height_m: float = 0.30, z_min: float = 0.004) -> "ObjectBox":
        return cls(side_m / 2, side_m / 2, z_min, height_m)

    @property
    def lo(self) -> np.ndarray:
        return np.array([-self.half_x, -self.half_y, self.z_min])

    @property
    def hi(self) -> np.ndarray:
        return np.array([self.half_x, self.half_y, self.z_max])

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which marker-frame points (N, 3) lie inside."""
        P = np.asarray(points)
        return np.all((P >= self.lo) & (P <= self.hi), axis=1)

    def crop_mesh(self, mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
        """A copy of a marker-frame mesh without the vertices outside the box (and their triangles)."""
        out = o3d.geometry.TriangleMesh(mesh)
        if len(out.vertices) == 0:
            return out
        out.remove_vertices_by_mask(~self.contains(np.asarray(out.vertices)))
        out.remove_unreferenced_vertices()
        return out
