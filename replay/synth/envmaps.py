"""Procedural HDR environments (distant lighting in the marker frame: z up, the support plane at z = 0).

An :class:`Environment` is an *analytic* radiance function of direction,

    L_env(w) = B(w) + sum_e L_e [w in Omega_e],

with ``B`` a smooth, low-dynamic-range background (continuous in ``w``; its texture has no feature
smaller than about 10 degrees) and ``Omega_e`` a few *emitters* of constant radiance with sharp edges:
the office's four ceiling lights and window, the sunset's sun disc. The renderer integrates the two
parts differently (``B`` by quadrature and lobe sampling, emitters by exact stratified cells over their
solid angle), which is what makes the integration both fast and accurate.

The truth files ``envmaps/NAME.exr`` / ``.hdr`` are lat-long rasterisations of this function (each texel
the mean of 2 x 2 sub-samples of ``B`` plus the exact emitter coverage of 8 x 8 sub-samples), linear
RGB, 512 x 256. Lat-long convention (the project's, see ``appfusion/octahedral.py``): row 0 is the
zenith (+z), rows run to the nadir; column 0 starts at azimuth -pi; a direction is
``(cos(phi) sin(theta), sin(phi) sin(theta), cos(theta))``.

Units: radiance in arbitrary linear units (the RGB camera's exposure maps them to pixel values).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from appfusion.errors import AppFusionError

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")


def _normalize(v):
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def triangle_solid_angle(a, b, c) -> np.ndarray:
    """Solid angle (sr) of triangles seen from the origin (Van Oosterom & Strackee 1983); (..., 3) each."""
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    num = np.abs(np.einsum("...i,...i->...", a, np.cross(b, c)))
    den = (la * lb * lc + np.einsum("...i,...i->...", a, b) * lc + np.einsum("...i,...i->...", a, c) * lb
           + np.einsum("...i,...i->...", b, c) * la)
    return 2.0 * np.arctan2(num, den)


# -- emitters ---------------------------------------------------------------------------------------

@dataclass
class RectEmitter:
    """A planar rectangle of constant radiance, seen as a distant source (only its directions matter).

    Attributes
    ----------
    name : str
    origin : (3,) corner, metres (marker frame)
    edge_u, edge_v : (3,) the two edges from ``origin``, metres
    radiance : (3,) RGB radiance *added* to the background inside the rectangle
    """

    name: str
    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    radiance: np.ndarray

    def __post_init__(self):
        self.origin = np.asarray(self.origin, dtype=np.float64)
        self.edge_u = np.asarray(self.edge_u, dtype=np.float64)
        self.edge_v = np.asarray(self.edge_v, dtype=np.float64)
        self.radiance = np.asarray(self.radiance, dtype=np.float64)
        corners = self.origin + np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) @ np.stack([self.edge_u, self.edge_v])
        dirs = _normalize(corners)
        self.center_dir = _normalize(self.origin + 0.5 * (self.edge_u + self.edge_v))
        self.cone_cos = float(np.min(dirs @ self.center_dir))  # bounding cone of the rectangle's directions
        self.normal = _normalize(np.cross(self.edge_u, self.edge_v))

    def cells(self, cell_deg: float):
        """Split the rectangle into cells about ``cell_deg`` wide as seen from the origin.

        Returns
        -------
        dirs : (K, 3) unit direction to each cell centre
        dw : (K,) exact solid angle of each cell (sr); they sum to the rectangle's solid angle
        """
        dist = np.linalg.norm(self.origin + 0.5 * (self.edge_u + self.edge_v))
        nu = max(2, int(np.ceil(np.degrees(np.linalg.norm(self.edge_u) / dist) / cell_deg)))
        nv = max(2, int(np.ceil(np.degrees(np.linalg.norm(self.edge_v) / dist) / cell_deg)))
        su = np.linspace(0, 1, nu + 1)
        sv = np.linspace(0, 1, nv + 1)
        P = self.origin + su[:, None, None] * self.edge_u + sv[None, :, None] * self.edge_v  # (nu+1, nv+1, 3)
        a, b, c, d = P[:-1, :-1], P[1:, :-1], P[1:, 1:], P[:-1, 1:]
        dw = triangle_solid_angle(a, b, c) + triangle_solid_angle(a, c, d)
        centres = 0.25 * (a + b + c + d)
        self.grid_shape = (nu, nv)
        return _normalize(centres).reshape(-1, 3), dw.reshape(-1)

    def solid_angle(self) -> float:
        c = self.origin + np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) @ np.stack([self.edge_u, self.edge_v])
        return float(triangle_solid_angle(c[0], c[1], c[2]) + triangle_solid_angle(c[0], c[2], c[3]))

    def contains(self, w: np.ndarray) -> np.ndarray:
        """True where the ray from the origin along ``w`` (..., 3) passes through the rectangle."""
        w = np.asarray(w, dtype=np.float64)
        dn = w @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.origin @ self.normal) / dn
        p = w * t[..., None] - self.origin
        eu, ev = self.edge_u, self.edge_v
        a = p @ eu / (eu @ eu)
        b = p @ ev / (ev @ ev)
        return (t > 0) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)

    def to_json(self) -> dict:
        return {"type": "rect", "name": self.name, "origin_m": self.origin.tolist(), "edge_u_m": self.edge_u.tolist(),
                "edge_v_m": self.edge_v.tolist(), "radiance": self.radiance.tolist(),
                "solid_angle_sr": self.solid_angle()}


@dataclass
class DiscEmitter:
    """A disc of constant radiance (a cone of directions of half-angle ``radius_rad``), e.g. the sun."""

    name: str
    direction: np.ndarray
    radius_rad: float
    radiance: np.ndarray

    def __post_init__(self):
        self.direction = _normalize(np.asarray(self.direction, dtype=np.float64))
        self.radiance = np.asarray(self.radiance, dtype=np.float64)
        self.center_dir = self.direction
        self.cone_cos = float(np.cos(self.radius_rad))

    def cells(self, cell_deg: float):
        """Polar cells (rings x sectors) of exact solid angle; see :meth:`RectEmitter.cells`."""
        nr = max(2, int(np.ceil(np.degrees(self.radius_rad) / cell_deg * 2)))
        ns = max(8, 4 * nr)
        r = np.linspace(0, self.radius_rad, nr + 1)
        dw_ring = 2 * np.pi * (np.cos(r[:-1]) - np.cos(r[1:])) / ns
        rc = np.arccos(0.5 * (np.cos(r[:-1]) + np.cos(r[1:])))  # ring centre by equal solid angle
        ph = (np.arange(ns) + 0.5) * 2 * np.pi / ns
        R, P = np.meshgrid(rc, ph, indexing="ij")
        t = _normalize(np.cross(self.direction, [0.0, 0.0, 1.0] if abs(self.direction[2]) < 0.9 else [1.0, 0, 0]))
        b = np.cross(self.direction, t)
        d = (np.cos(R)[..., None] * self.direction + np.sin(R)[..., None] * (np.cos(P)[..., None] * t
                                                                             + np.sin(P)[..., None] * b))
        self.grid_shape = (nr, ns)
        return d.reshape(-1, 3), np.repeat(dw_ring, ns)

    def solid_angle(self) -> float:
        return float(2 * np.pi * (1 - np.cos(self.radius_rad)))

    def contains(self, w: np.ndarray) -> np.ndarray:
        w = _normalize(w)
        return w @ self.direction >= self.cone_cos

    def to_json(self) -> dict:
        return {"type": "disc", "name": self.name, "direction": self.direction.tolist(),
                "radius_rad": self.radius_rad, "radiance": self.radiance.tolist(), "solid_angle_sr": self.solid_angle()}


# -- lat-long helpers --------------------------------------------------------------------------------

def latlong_dirs(height: int, width: int | None = None) -> np.ndarray:
    """Pixel-centre directions of a lat-long map, (H, W, 3) (row 0 = zenith, column 0 at azimuth -pi)."""
    width = width or 2 * height
    th = (np.arange(height) + 0.5) * np.pi / height
    ph = (np.arange(width) + 0.5) * 2 * np.pi / width - np.pi
    P, T = np.meshgrid(ph, th)
    return np.stack([np.cos(P) * np.sin(T), np.sin(P) * np.sin(T), np.cos(T)], axis=-1)


def latlong_cells(n_theta: int):
    """Quadrature over the sphere: lat-long cells, ``n_theta`` rows x ``2 n_theta`` columns.

    Rows are equal in theta, so with an even ``n_theta`` a row boundary lies exactly on the horizon
    (z = 0) of the marker frame, where the support plane cuts the lower hemisphere off.

    Returns
    -------
    dirs : (K, 3) cell-centre directions; dw : (K,) exact cell solid angles (sum 4 pi)
    """
    n_phi = 2 * n_theta
    t0 = np.arange(n_theta) * np.pi / n_theta
    t1 = t0 + np.pi / n_theta
    tc = np.arccos(0.5 * (np.cos(t0) + np.cos(t1)))
    ph = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi - np.pi
    T, P = np.meshgrid(tc, ph, indexing="ij")
    d = np.stack([np.cos(P) * np.sin(T), np.sin(P) * np.sin(T), np.cos(T)], axis=-1).reshape(-1, 3)
    dw = np.repeat((np.cos(t0) - np.cos(t1)) * 2 * np.pi / n_phi, n_phi)
    return d, dw


def hemisphere_cells(n_up: int, n_down: int):
    """Quadrature over the sphere with a finer upper hemisphere: lat-long cells with ``n_up`` rows x
    ``4 n_up`` columns above the horizon and ``n_down`` rows x ``4 n_down`` columns below it (the
    horizon z = 0 is a row boundary of both). Returns dirs (K, 3) and exact solid angles (K,)."""
    out_d, out_w = [], []
    for rows, lo, hi in ((n_up, 0.0, np.pi / 2), (n_down, np.pi / 2, np.pi)):
        if rows <= 0:
            continue
        n_phi = 4 * rows
        t0 = lo + np.arange(rows) * (hi - lo) / rows
        t1 = t0 + (hi - lo) / rows
        tc = np.arccos(0.5 * (np.cos(t0) + np.cos(t1)))
        ph = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi - np.pi
        T, P = np.meshgrid(tc, ph, indexing="ij")
        out_d.append(np.stack([np.cos(P) * np.sin(T), np.sin(P) * np.sin(T), np.cos(T)], axis=-1).reshape(-1, 3))
        out_w.append(np.repeat((np.cos(t0) - np.cos(t1)) * 2 * np.pi / n_phi, n_phi))
    return np.concatenate(out_d), np.concatenate(out_w)


def sample_octa(table: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Bilinear look-up of a (2, n, n, C) pair of hemisphere octahedral squares (Praun & Hoppe 2003,
    rotated 45 degrees so a hemisphere fills its square; index 0: z >= 0, 1: z < 0 mirrored) in
    directions ``w`` (..., 3). Near the equator look-ups clamp to the square's border."""
    n = table.shape[1]
    shp = np.shape(w)[:-1]
    w = np.asarray(w, dtype=np.float64).reshape(-1, 3)
    s = np.abs(w).sum(axis=1)
    s = np.where(s > 0, s, 1.0)
    px, py = w[:, 0] / s, w[:, 1] / s
    face = (w[:, 2] < 0).astype(np.int64)
    fx = (px + py + 1.0) * (0.5 * n) - 0.5
    fy = (px - py + 1.0) * (0.5 * n) - 0.5
    x0 = np.clip(np.floor(fx), 0, n - 2)
    y0 = np.clip(np.floor(fy), 0, n - 2)
    ax = np.clip(fx - x0, 0.0, 1.0).astype(np.float32)[:, None]
    ay = np.clip(fy - y0, 0.0, 1.0).astype(np.float32)[:, None]
    base = face * (n * n) + y0.astype(np.int64) * n + x0.astype(np.int64)
    flat = table.reshape(2 * n * n, -1)
    top = flat[base] * (1 - ax) + flat[base + 1] * ax
    bot = flat[base + n] * (1 - ax) + flat[base + n + 1] * ax
    return (top * (1 - ay) + bot * ay).reshape(shp + (flat.shape[1],))


def sample_latlong(img: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Bilinear look-up of a lat-long image (H, W, C) in directions ``w`` (..., 3) (azimuth wraps)."""
    h, wd = img.shape[:2]
    shp = np.shape(w)[:-1]
    w = np.asarray(w, dtype=np.float64).reshape(-1, 3)
    r = np.sqrt(np.einsum("ij,ij->i", w, w))
    th = np.arccos(np.clip(w[:, 2] / np.where(r > 0, r, 1.0), -1.0, 1.0))
    ph = np.arctan2(w[:, 1], w[:, 0])
    fy = th * (h / np.pi) - 0.5
    fx = (ph + np.pi) * (wd / (2 * np.pi)) - 0.5
    y0 = np.floor(fy)
    x0 = np.floor(fx)
    ay = (fy - y0).astype(np.float32)[:, None]
    ax = (fx - x0).astype(np.float32)[:, None]
    y0 = y0.astype(np.int64)
    x0 = x0.astype(np.int64)
    y1 = np.minimum(y0 + 1, h - 1)
    y0 = np.maximum(y0, 0)
    x1 = (x0 + 1) % wd
    x0 = x0 % wd
    flat = img.reshape(h * wd, -1)
    top = flat[y0 * wd + x0] * (1 - ax) + flat[y0 * wd + x1] * ax
    bot = flat[y1 * wd + x0] * (1 - ax) + flat[y1 * wd + x1] * ax
    return (top * (1 - ay) + bot * ay).reshape(shp + (flat.shape[1],))


# -- the environment ------------------------------------------------------------------------------

@dataclass
class Environment:
    """Distant lighting: a smooth background function plus sharp constant-radiance emitters.

    Attributes
    ----------
    name : str
    background_fn : callable (..., 3) unit directions -> (..., 3) RGB radiance
    emitters : list of RectEmitter / DiscEmitter
    params : dict
        Every number that defines the map (for ``scene.json``).
    table_height : int
        Rows of the lat-long table :meth:`background` interpolates (exact function: :meth:`background_exact`).
    """

    name: str
    background_fn: Callable[[np.ndarray], np.ndarray]
    emitters: list = field(default_factory=list)
    params: dict = field(default_factory=dict)
    table_height: int = 512

    def __post_init__(self):
        self._table = None

    # -- evaluation -------------------------------------------------------------------------------
    def background_exact(self, w: np.ndarray) -> np.ndarray:
        """Background radiance B(w), evaluated analytically; (..., 3)."""
        return np.asarray(self.background_fn(_normalize(w)), dtype=np.float64)

    def background(self, w: np.ndarray) -> np.ndarray:
        """B(w) from a fine table (two octahedral squares of ``table_height``^2 texels, one per hemisphere,
        bilinear); B is smooth, so this differs from the exact function by ~1e-3 relative at most
        (measured in the tests). No trigonometry: much faster than a lat-long look-up."""
        if self._table is None:
            n = self.table_height
            c = (np.arange(n) + 0.5) * (2.0 / n) - 1.0
            U, Vv = np.meshgrid(c, c)
            x, y = 0.5 * (U + Vv), 0.5 * (U - Vv)
            z = np.maximum(1.0 - np.abs(x) - np.abs(y), 0.0)
            up = _normalize(np.stack([x, y, z], -1))
            down = up * np.array([1.0, 1.0, -1.0])
            self._table = np.stack([self.background_exact(up), self.background_exact(down)]).astype(np.float32)
        return sample_octa(self._table, w)

    def emitter_radiance(self, w: np.ndarray) -> np.ndarray:
        """Sum of the emitters' radiance in directions ``w`` (..., 3) (``w`` need not be unit)."""
        shp = np.shape(w)[:-1]
        w = np.asarray(w, dtype=np.float64).reshape(-1, 3)
        out = np.zeros((len(w), 3))
        if self.emitters:
            r = np.sqrt(np.einsum("ij,ij->i", w, w))
            for e in self.emitters:
                near = np.nonzero(w @ e.center_dir >= (e.cone_cos - 1e-9) * r)[0]
                if len(near):
                    out[near] += e.contains(w[near])[:, None] * e.radiance
        return out.reshape(shp + (3,))

    def radiance(self, w: np.ndarray, exact: bool = False) -> np.ndarray:
        """Total radiance ``B(w) + emitters`` in directions ``w`` (..., 3)."""
        b = self.background_exact(w) if exact else self.background(w)
        return b + self.emitter_radiance(w)

    def emitter_cells(self, cell_deg: float = 1.5):
        """All emitters split into cells: dirs (K, 3), dw (K,), radiance (K, 3), emitter index (K,)."""
        dirs, dws, Ls, idx = [], [], [], []
        for i, e in enumerate(self.emitters):
            d, dw = e.cells(cell_deg)
            dirs.append(d)
            dws.append(dw)
            Ls.append(np.broadcast_to(e.radiance, (len(dw), 3)))
            idx.append(np.full(len(dw), i))
        if not dirs:
            return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        return np.concatenate(dirs), np.concatenate(dws), np.concatenate(Ls), np.concatenate(idx)

    def emitter_groups(self, cell_deg: float, block: int) -> np.ndarray:
        """Coarse group of every cell of :meth:`emitter_cells`: blocks of ``block`` x ``block`` cells of
        each emitter's cell grid (global group ids, (K,) int64)."""
        out, base = [], 0
        for e in self.emitters:
            e.cells(cell_deg)
            nu, nv = e.grid_shape
            gu, gv = -(-nu // block), -(-nv // block)
            I, J = np.meshgrid(np.arange(nu) // block, np.arange(nv) // block, indexing="ij")
            out.append(base + (I * gv + J).ravel())
            base += gu * gv
        return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)

    # -- rasterisation and files -----------------------------------------------------------------
    def to_latlong(self, height: int = 256, width: int | None = None, ss_bg: int = 2, ss_em: int = 8) -> np.ndarray:
        """Box-filtered lat-long image (H, W, 3) float32 of the radiance: the background with ``ss_bg``^2
        and each emitter's coverage with ``ss_em``^2 sub-samples per texel (only in texels near the
        emitter), each sub-sample weighted by its solid angle (sin theta)."""
        width = width or 2 * height
        out = np.zeros((height, width, 3))

        def box(fn, ss, rows, cols):
            """Mean of fn over ss x ss sub-samples of texels (rows, cols) (1-D index arrays)."""
            o = (np.arange(ss) + 0.5) / ss
            th = (rows[:, None, None] + o[None, :, None]) * np.pi / height                 # (n, ss, 1)
            ph = (cols[:, None, None] + o[None, None, :]) * 2 * np.pi / width - np.pi      # (n, 1, ss)
            th, ph = np.broadcast_arrays(th, ph)
            d = np.stack([np.cos(ph) * np.sin(th), np.sin(ph) * np.sin(th), np.cos(th)], axis=-1)
            wgt = np.sin(th)
            v = fn(d.reshape(-1, 3)).reshape(th.shape + (3,))
            return (v * wgt[..., None]).sum(axis=(1, 2)) / wgt.sum(axis=(1, 2))[:, None]

        R, Cc = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
        R, Cc = R.ravel(), Cc.ravel()
        for s in range(0, len(R), 65536):
            out.reshape(-1, 3)[s:s + 65536] = box(self.background_exact, ss_bg, R[s:s + 65536], Cc[s:s + 65536])
        centres = latlong_dirs(height, width).reshape(-1, 3)
        texel_rad = np.pi / height * 1.5  # > half-diagonal of the largest texel
        for e in self.emitters:
            near = centres @ e.center_dir >= np.cos(np.arccos(np.clip(e.cone_cos, -1, 1)) + texel_rad)
            ix = np.nonzero(near)[0]
            if len(ix):
                out.reshape(-1, 3)[ix] += box(lambda d: e.contains(d)[:, None] * e.radiance, ss_em, R[ix], Cc[ix])
        return out.astype(np.float32)

    def save(self, folder: Path, height: int = 256) -> dict[str, str]:
        """Write ``NAME.exr`` and ``NAME.hdr`` (lat-long, linear RGB) into ``folder``; returns their paths."""
        import cv2

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        key = (self.name, repr(self.to_json()), height)
        if key not in _RASTER_CACHE:
            _RASTER_CACHE.clear() if len(_RASTER_CACHE) > 4 else None
            _RASTER_CACHE[key] = self.to_latlong(height)
        img = _RASTER_CACHE[key]
        bgr = np.ascontiguousarray(img[..., ::-1])
        paths = {}
        for ext in ("exr", "hdr"):
            p = folder / f"{self.name}.{ext}"
            if not cv2.imwrite(str(p), bgr):
                raise AppFusionError(f"environment {self.name}: OpenCV could not write {p} "
                                     f"(OpenEXR needs OPENCV_IO_ENABLE_OPENEXR=1 before cv2 is imported)")
            paths[ext] = str(p)
        return paths

    def to_json(self) -> dict:
        return {"name": self.name, "params": self.params, "emitters": [e.to_json() for e in self.emitters],
                "latlong": "row 0 = zenith (+z), column 0 at azimuth -pi, x = cos(phi) sin(theta), "
                           "y = sin(phi) sin(theta), z = cos(theta)"}


_RASTER_CACHE: dict = {}


def load_latlong(path: str | os.PathLike) -> np.ndarray:
    """Read an ``.exr`` / ``.hdr`` written by :meth:`Environment.save` as (H, W, 3) float32 linear RGB."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise AppFusionError(f"{path}: cannot be read as an HDR image")
    return np.ascontiguousarray(img[..., :3][..., ::-1]).astype(np.float32)


# -- the maps -------------------------------------------------------------------------------------

def _room_hit(w, box_min, box_max):
    """Point where rays from the origin along unit ``w`` leave an axis-aligned box containing the origin."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(w > 0, box_max / w, np.where(w < 0, box_min / w, np.inf))
    tm = np.min(t, axis=-1)
    return w * tm[..., None]


def office() -> Environment:
    """The paper's setting (§7): a small office with four rectangular ceiling lights and a window.

    The room is a box around the table (x in [-2.2, 2.6], y in [-2.0, 2.3] m; floor 0.75 m below the
    support plane, ceiling 1.65 m above it). Its background radiance B is a smooth function of the
    point where a direction leaves the box: floor, walls and ceiling colours blended over 0.35-0.4 m
    bands at the corners, a gentle sinusoidal wall texture and a few soft coloured blobs (a shelf, a
    plant, a poster) of at least 0.35 m standard deviation. Emitters: four 0.6 x 1.2 m ceiling panels
    of radiance 22 x (1.0, 0.96, 0.88) and a 1.6 x 1.0 m window of radiance 5 x (0.85, 0.95, 1.15)
    on the +x wall (above the background).
    """
    bmin = np.array([-2.2, -2.0, -0.75])
    bmax = np.array([2.6, 2.3, 1.65])
    floor_c = np.array([0.22, 0.19, 0.16])
    wall_c = np.array([0.62, 0.56, 0.46])
    ceil_c = np.array([0.85, 0.85, 0.82])
    blobs = [  # centre (m), sigma (m), multiplicative tint
        (np.array([-1.0, 2.3, 0.2]), 0.45, np.array([0.45, 0.35, 0.28])),   # dark wooden shelf
        (np.array([2.6, 1.6, -0.2]), 0.35, np.array([0.55, 1.10, 0.55])),   # plant beside the window
        (np.array([-2.2, -0.6, 0.7]), 0.40, np.array([1.35, 0.70, 0.60])),  # red poster
        (np.array([0.4, -2.0, 0.3]), 0.50, np.array([0.70, 0.80, 1.20])),   # blue cabinet
    ]

    def bg(w):
        p = _room_hit(w, bmin, bmax)
        z = p[..., 2]
        wall_w = _smoothstep(-0.75, -0.35, z)
        ceil_w = _smoothstep(1.3, 1.65, z)
        col = floor_c * (1 - wall_w)[..., None] + wall_c * wall_w[..., None]
        col = col * (1 - ceil_w)[..., None] + ceil_c * ceil_w[..., None]
        tex = (1 + 0.10 * np.sin(2 * np.pi * p[..., 0] / 1.4 + 0.3) * np.sin(2 * np.pi * p[..., 1] / 1.7)
               + 0.06 * np.sin(2 * np.pi * p[..., 2] / 1.1 + 1.0))
        col = col * tex[..., None]
        for c, s, tint in blobs:
            g = np.exp(-np.sum((p - c) ** 2, axis=-1) / (2 * s * s))[..., None]
            col = col * (1 + g * (tint - 1))
        return col

    lights = []
    for i, (cx, cy) in enumerate([(-1.0, -0.8), (-1.0, 0.9), (1.1, -0.8), (1.1, 0.9)]):
        lights.append(RectEmitter(f"ceiling-light-{i + 1}", origin=[cx - 0.3, cy - 0.6, 1.64], edge_u=[0.6, 0, 0],
                                  edge_v=[0, 1.2, 0], radiance=22.0 * np.array([1.0, 0.96, 0.88])))
    window = RectEmitter("window", origin=[2.6, 0.7, 0.25], edge_u=[0, -1.6, 0], edge_v=[0, 0, 1.0],
                         radiance=5.0 * np.array([0.85, 0.95, 1.15]))
    params = {"room_box_min_m": bmin.tolist(), "room_box_max_m": bmax.tolist(), "floor_rgb": floor_c.tolist(),
              "wall_rgb": wall_c.tolist(), "ceiling_rgb": ceil_c.tolist(),
              "blobs": [{"centre_m": c.tolist(), "sigma_m": s, "tint": t.tolist()} for c, s, t in blobs]}
    return Environment("office", bg, lights + [window], params)


def sunset() -> Environment:
    """A warm evening sky: horizon-to-zenith gradient, a soft glow around a small bright sun, dark ground.

    The sun is a disc of half-angle 1.5 degrees (wider than the real 0.27 so a 512 x 256 map and the
    mirror ball resolve it) at elevation 12 degrees, azimuth 215 degrees, radiance 3000 x (1, 0.72, 0.45)
    above the sky; it gives about 40% of the irradiance of an upward-facing surface and most of a
    surface facing it.
    """
    el, az = np.radians(12.0), np.radians(215.0)
    sun_dir = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    horizon = np.array([1.5, 0.78, 0.42])
    zenith = np.array([0.22, 0.38, 0.78])
    ground = np.array([0.10, 0.08, 0.065])
    glow = np.array([6.0, 3.4, 1.6])

    def bg(w):
        z = w[..., 2]
        up = np.clip(z, 0, 1)
        m = np.exp(-up / 0.22)[..., None]
        sky = zenith + (horizon - zenith) * m
        ang2 = 2 * (1 - np.clip(w @ sun_dir, -1, 1))  # ~ angle^2 near the sun
        sky = sky + glow * np.exp(-ang2 / (2 * 0.12 ** 2))[..., None]
        g = np.exp(-np.clip(-z, 0, 1) / 0.06)[..., None]
        below = ground + (horizon + glow * np.exp(-ang2 / (2 * 0.12 ** 2))[..., None] - ground) * g
        return np.where((z >= 0)[..., None], sky, below)

    sun = DiscEmitter("sun", sun_dir, np.radians(1.5), 3000.0 * np.array([1.0, 0.72, 0.45]))
    params = {"sun_elevation_deg": 12.0, "sun_azimuth_deg": 215.0, "horizon_rgb": horizon.tolist(),
              "zenith_rgb": zenith.tolist(), "ground_rgb": ground.tolist(), "glow_rgb": glow.tolist(),
              "glow_sigma_rad": 0.12}
    return Environment("sunset", bg, [sun], params)


def constant(value=1.0, name: str = "constant") -> Environment:
    """A uniform environment of radiance ``value`` (scalar or RGB) in every direction (tests)."""
    v = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    return Environment(name, lambda w: np.broadcast_to(v, np.shape(w)[:-1] + (3,)).copy(), [], {"value": v.tolist()},
                       table_height=16)


ENVIRONMENTS = {"office": office, "sunset": sunset}


def get(name: str) -> Environment:
    """An environment by name ("office", "sunset")."""
    try:
        return ENVIRONMENTS[name]()
    except KeyError:
        raise AppFusionError(f"unknown environment {name!r} (known: {', '.join(ENVIRONMENTS)})") from None
