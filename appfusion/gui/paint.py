"""Manual cluster refinement (paper §5.2, "Manual Clustering Refinement"): a screen-space brush.

The paper offers "a simple, optional 3D painting interface" in which the user paints correct cluster
assignments onto parts of the object "using a brush with an adjustable size". Here the brush is a
disc of ``radius_px`` screen pixels around the mouse. A stroke selects the fused points that

1. project inside the disc with the 3-D view's own camera (model-view-projection matrix),
2. face the camera (``n . (eye - p) > 0`` where normals are known), and
3. lie on the nearest-to-camera layer: a coarse z-buffer of cells ``cell_px`` pixels wide is filled
   with the eye-space depth of every visible point, and a point is kept only when it is within
   ``depth_tol`` of its cell's nearest depth (so a brush never paints through the object onto its
   far side).

Everything here is pure numpy (no Qt), so it is tested without a display. The GUI keeps its own
record of strokes (:class:`PaintStrokes`) that mirrors what it sent to the engine with
``runner.paint`` / ``runner.undo_paint``, so painted labels show at once, before the next snapshot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import AppFusionError
from ..frame import Intrinsics


def qmatrix_to_numpy(m) -> np.ndarray:
    """A ``QMatrix4x4`` (or anything with ``.data()`` in column-major order) as a (4, 4) float64 array."""
    if isinstance(m, np.ndarray):
        a = np.asarray(m, np.float64)
    else:
        a = np.asarray(list(m.data()), np.float64).reshape(4, 4).T  # Qt stores column-major
    if a.shape != (4, 4):
        raise AppFusionError(f"paint: a camera matrix must be 4x4, got shape {a.shape}")
    return a


def project_points(points: np.ndarray, mvp: np.ndarray, view: np.ndarray, width: float, height: float):
    """Project world points to widget pixels with an OpenGL camera.

    Parameters
    ----------
    points : (P, 3) array
        World positions (metres, the scan's marker frame).
    mvp : (4, 4) array
        Projection @ view (OpenGL conventions: eye looks down -z, NDC in [-1, 1]^3).
    view : (4, 4) array
        World-to-eye matrix (for the eye-space depth).
    width, height : float
        Widget size in logical pixels.

    Returns
    -------
    xy : (P, 2) float64
        Pixel coordinates (x right, y down; origin at the top-left corner of the widget).
    depth : (P,) float64
        Distance in front of the eye along the view axis (metres); <= 0 behind the camera.
    visible : (P,) bool
        In front of the camera and inside the view frustum.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    ph = np.concatenate([p, np.ones((len(p), 1))], axis=1)
    clip = ph @ np.asarray(mvp, np.float64).T
    w = clip[:, 3]
    safe = np.where(np.abs(w) > 1e-12, w, 1e-12)
    ndc = clip[:, :3] / safe[:, None]
    xy = np.stack([(ndc[:, 0] + 1.0) * 0.5 * width, (1.0 - ndc[:, 1]) * 0.5 * height], axis=1)
    depth = -(ph @ np.asarray(view, np.float64)[2])  # eye z is negative in front of the camera
    visible = (w > 0) & (depth > 0) & np.all(np.abs(ndc) <= 1.0, axis=1)
    return xy, depth, visible


def brush_select(points: np.ndarray, mvp: np.ndarray, view: np.ndarray, width: float, height: float,
                 center_xy, radius_px: float, normals: np.ndarray | None = None, eye=None,
                 cell_px: float = 6.0, depth_tol: float | None = None) -> np.ndarray:
    """Indices of the points a screen-space brush covers, nearest-to-camera layer only (§5.2).

    Parameters
    ----------
    points : (P, 3) array
        World positions (metres).
    mvp, view : (4, 4) arrays
        The 3-D view's projection @ view and view (world-to-eye) matrices.
    width, height : float
        Widget size (logical pixels).
    center_xy : (2,) float
        Brush centre in widget pixels (x right, y down).
    radius_px : float
        Brush radius in pixels (> 0).
    normals : (P, 3) array, optional
        Unit normals; points facing away from the eye are never painted.
    eye : (3,) array, optional
        Camera position in world coordinates (needed with ``normals``; taken from ``view`` if None).
    cell_px : float
        Side of the z-buffer cells (pixels); about twice the on-screen point spacing.
    depth_tol : float, optional
        Depth band (metres) behind a cell's nearest point still counted as the front layer; default
        two cell widths at the brush's depth plus 2 mm, so a surface tilted up to ~63 degrees from the
        view is painted whole while anything a few centimetres behind it is not.

    Returns
    -------
    (K,) int64
        Sorted indices into ``points``.
    """
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if radius_px <= 0 or not np.isfinite(radius_px):
        raise AppFusionError(f"paint: the brush radius must be positive, got {radius_px}")
    if len(p) == 0:
        return np.zeros(0, np.int64)
    view = np.asarray(view, np.float64)
    xy, depth, visible = project_points(p, mvp, view, width, height)
    if normals is not None:
        n = np.asarray(normals, np.float64).reshape(-1, 3)
        if len(n) != len(p):
            raise AppFusionError(f"paint: {len(n)} normals for {len(p)} points")
        if eye is None:
            eye = np.linalg.inv(view)[:3, 3]
        facing = np.einsum("ij,ij->i", n, np.asarray(eye, np.float64)[None, :] - p) > 0
        visible &= facing
    c = np.asarray(center_xy, np.float64).reshape(2)
    # candidates: visible points in the brush's bounding square (one cell of margin for the z-buffer)
    margin = radius_px + cell_px
    box = visible & np.all(np.abs(xy - c) <= margin, axis=1)
    cand = np.flatnonzero(box)
    if len(cand) == 0:
        return np.zeros(0, np.int64)
    cxy = xy[cand]
    cz = depth[cand]
    inside = np.sum((cxy - c) ** 2, axis=1) <= radius_px ** 2
    # coarse z-buffer over the candidates: nearest depth per cell
    cells = np.floor((cxy - (c - margin)) / cell_px).astype(np.int64)
    ncol = int(np.ceil(2 * margin / cell_px)) + 1
    key = cells[:, 1] * ncol + cells[:, 0]
    uniq, inv = np.unique(key, return_inverse=True)
    zmin = np.full(len(uniq), np.inf)
    np.minimum.at(zmin, inv, cz)
    if depth_tol is None:
        # a tilted surface's depth changes across a cell: allow two cell widths (in metres at the
        # brush's depth; slopes up to ~63 degrees) plus 2 mm of noise
        proj = np.asarray(mvp, np.float64) @ np.linalg.inv(view)
        f_px = abs(proj[0, 0]) * 0.5 * width
        z = float(np.median(cz[inside])) if inside.any() else float(np.median(cz))
        depth_tol = 2.0 * cell_px * z / max(f_px, 1e-9) + 0.002
    front = cz <= zmin[inv] + depth_tol
    return np.sort(cand[inside & front]).astype(np.int64)


@dataclass
class PaintStrokes:
    """The strokes painted so far, in order, for showing them before the engine's next snapshot.

    Attributes
    ----------
    strokes : list of (indices (K,) int64, label int)
    """

    strokes: list[tuple[np.ndarray, int]] = field(default_factory=list)

    def add(self, idx: np.ndarray, label: int) -> None:
        self.strokes.append((np.asarray(idx, np.int64).copy(), int(label)))

    def undo(self) -> tuple[np.ndarray, int] | None:
        """Forget the last stroke; returns it (None when there is none)."""
        return self.strokes.pop() if self.strokes else None

    def __len__(self) -> int:
        return len(self.strokes)

    def apply(self, labels: np.ndarray | None) -> np.ndarray | None:
        """``labels`` (P,) with every stroke applied in order (a copy; indices out of range ignored)."""
        if labels is None or not self.strokes:
            return labels
        out = np.array(labels, np.int32, copy=True)
        for idx, lab in self.strokes:
            out[idx[idx < len(out)]] = lab
        return out


def gl_camera_to_cv(view: np.ndarray, fov_deg: float, width: int, height: int) -> tuple[Intrinsics, np.ndarray]:
    """The 3-D view's OpenGL camera as an OpenCV camera, for :func:`appfusion.relight.render_view`.

    Parameters
    ----------
    view : (4, 4) array
        World-to-eye matrix (OpenGL: x right, y up, looking down -z).
    fov_deg : float
        Horizontal field of view (pyqtgraph's ``opts['fov']``), degrees.
    width, height : int
        Size of the rendered image (pixels).

    Returns
    -------
    intrinsics : Intrinsics
        Pinhole with ``fx = fy = (width / 2) / tan(fov / 2)``, principal point at the image centre.
    pose : (4, 4) float64
        Camera-to-world pose in OpenCV axes (x right, y down, z forward).
    """
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    cv_from_world = flip @ np.asarray(view, np.float64)
    pose = np.linalg.inv(cv_from_world)
    f = 0.5 * width / np.tan(0.5 * np.radians(fov_deg))
    return Intrinsics(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0), pose
