"""The GUI's views: streams, fused points (3-D, with the §5.2 paint brush), environment map, HBSAB, plots.

Each view has an ``update_from(snapshot)`` that draws what the snapshot holds and skips work when
the data it shows did not change (a cheap fingerprint of a strided sample of each array), so the
UI thread's timer stays fast while the engine publishes.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from .. import octahedral as oc
from ..brdf import lobe_retro
from ..frame import REC709_LUMA
from . import colours as C
from .paint import brush_select, qmatrix_to_numpy

pg.setConfigOptions(imageAxisOrder="row-major", antialias=False)
if QtWidgets.QApplication.instance() is None:  # must precede the QApplication (see _make_gl_view)
    QtCore.QCoreApplication.setAttribute(QtCore.Qt.ApplicationAttribute.AA_ShareOpenGLContexts)


def fingerprint(a):
    """A cheap identity of an array's content: shape, dtype and a hash of <= 4096 strided samples."""
    if a is None:
        return None
    if isinstance(a, (list, tuple)):
        return tuple(fingerprint(x) for x in a)
    a = np.asarray(a)
    flat = a.reshape(-1)
    step = max(1, flat.size // 4096)
    return (a.shape, a.dtype.str, hash(np.ascontiguousarray(flat[::step]).tobytes()))


def _image_box(layout: pg.GraphicsLayoutWidget, title: str, row: int, col: int, **kw):
    vb = layout.addViewBox(row=row, col=col, lockAspect=True, invertY=True, enableMouse=True, **kw)
    item = pg.ImageItem()
    vb.addItem(item)
    label = pg.TextItem(title, color=(230, 230, 230), anchor=(0, 0), fill=(0, 0, 0, 140))
    label.setZValue(10)
    vb.addItem(label, ignoreBounds=True)
    return vb, item, label


class StreamsView(pg.GraphicsLayoutWidget):
    """The RGB, IR and depth images of the last processed frame (IR auto-levelled, depth colour-mapped)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setBackground((20, 20, 24))
        self.boxes = {}
        for col, name in enumerate(("rgb", "ir", "depth")):
            self.boxes[name] = _image_box(self, {"rgb": "RGB", "ir": "IR", "depth": "depth"}[name], 0, col)
        self._frame_key = None
        self.shown: dict[str, bool] = {"rgb": False, "ir": False, "depth": False}

    def update_from(self, frame) -> None:
        if frame is None:
            return
        key = (frame.index, frame.timestamp, id(frame))
        if key == self._frame_key:
            return
        self._frame_key = key
        for name, (vb, item, label) in self.boxes.items():
            img = getattr(frame, name)
            if img is None:
                continue
            if name == "rgb":
                item.setImage(C.rgb_image(frame), autoLevels=False, levels=(0, 255))
            elif name == "ir":
                item.setImage(img, autoLevels=False, levels=C.ir_levels(img))
            else:
                d = img[np.isfinite(img) & (img > 0)]
                lo, hi = (np.percentile(d[::16], [2, 98]) if d.size else (0.3, 1.5))
                item.setImage(C.depth_image(img, float(lo), float(hi) + 1e-3), autoLevels=False, levels=(0, 255))
                label.setText(f"depth {lo:.2f}-{hi:.2f} m")
            if not self.shown[name]:
                vb.autoRange(padding=0)
                self.shown[name] = True


class EnvMapView(pg.GraphicsLayoutWidget):
    """The environment map filling in (§4.3): lat-long radiance, unseen directions checkered."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setBackground((20, 20, 24))
        self.vb, self.item, self.label = _image_box(self, "no environment map yet", 0, 0)
        self._fp = None
        self.coverage = float("nan")

    def update_from(self, snap) -> None:
        env = getattr(snap, "envmap", None)
        if env is None:
            return
        fp = (fingerprint(env), fingerprint(snap.env_coverage))
        if fp == self._fp:
            return
        first = self._fp is None
        self._fp = fp
        img, self.coverage = C.envmap_latlong(env, snap.env_coverage, height=96)
        self.item.setImage(img, autoLevels=False, levels=(0, 255))
        cov = "" if not np.isfinite(self.coverage) else f": {100 * self.coverage:.0f}% of the sphere seen"
        self.label.setText(f"environment map{cov}")
        if first:
            self.vb.autoRange(padding=0)


class HBSABView(pg.GraphicsLayoutWidget):
    """The selected cluster's HBSAB (§5.1, Eq. 3) beside its fitted lobe (Ward or GGX, the snapshot's
    ``lobes``), and a slice through both.

    The slice is the square's middle row, plotted against the signed half-vector angle theta_h
    (degrees), so a broader lobe is a rougher material.
    """

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setBackground((20, 20, 24))
        self.cluster = 0
        self.vb_m, self.img_m, self.lab_m = _image_box(self, "HBSAB", 0, 0)
        self.vb_f, self.img_f, self.lab_f = _image_box(self, "lobe fit", 0, 1)
        lut = pg.colormap.get("viridis").getLookupTable(nPts=256)
        self.img_m.setLookupTable(lut)
        self.img_f.setLookupTable(lut)
        self.plot = self.addPlot(row=1, col=0, colspan=2)
        self.plot.setLabel("bottom", "theta_h (deg)")
        self.plot.setLabel("left", "HBSAB")
        self.plot.showGrid(x=True, y=True, alpha=0.2)
        self.curve_m = self.plot.plot([], [], pen=None, symbol="o", symbolSize=4, symbolBrush=(255, 200, 60),
                                      name="measured")
        self.curve_f = self.plot.plot([], [], pen=pg.mkPen((90, 200, 255), width=2), name="lobe fit")
        self.ci.layout.setRowStretchFactor(0, 3)
        self.ci.layout.setRowStretchFactor(1, 2)
        self._fp = None
        self.coverage = float("nan")

    def set_cluster(self, c: int) -> None:
        self.cluster = int(c)
        self._fp = None

    def update_from(self, snap) -> None:
        hb = getattr(snap, "hbsabs", None)
        if not hb:
            return
        c = min(self.cluster, len(hb) - 1)
        h = np.asarray(hb[c], np.float64) if hb[c] is not None else None
        fits = getattr(snap, "hbsab_fits", None)
        f = np.asarray(fits[c], np.float64) if fits and c < len(fits) and fits[c] is not None else None
        alpha = getattr(snap, "alpha", None)
        lobes = getattr(snap, "lobes", None) or []
        lobe_name = str(lobes[c]) if c < len(lobes) and str(lobes[c]) in ("ward", "ggx") else "ward"
        name = "GGX" if lobe_name == "ggx" else "Ward"
        fp = (c, fingerprint(h), fingerprint(f), fingerprint(alpha), lobe_name)
        if fp == self._fp or h is None:
            return
        first = self._fp is None
        self._fp = fp
        finite = np.isfinite(h)
        self.coverage = float(np.mean(finite & (h != 0))) if h.size else 0.0
        both = h[finite] if f is None else np.concatenate([h[finite], f[np.isfinite(f)]])
        hi = float(np.percentile(both, 99.5)) if both.size else 1.0
        hi = hi if hi > 0 else 1.0
        self.img_m.setImage(np.nan_to_num(h), autoLevels=False, levels=(0, hi))
        a_txt = ""
        if alpha is not None and c < len(alpha):
            a_txt = f" \u03b1 {float(alpha[c]):.3f}"
            s = getattr(snap, "alpha_sigma", None)
            if s is not None and c < len(s):
                a_txt += f"\u00b1{float(s[c]):.3f}"
        self.lab_m.setText(f"HBSAB {c} ({100 * self.coverage:.0f}%)")
        n = h.shape[0]
        mid = n // 2
        uv = np.stack([(np.arange(n) + 0.5) * 2.0 / n - 1.0, np.full(n, (mid + 0.5) * 2.0 / n - 1.0)], 1)
        d = oc.hemi_decode(uv)
        theta = np.degrees(np.arccos(np.clip(d[:, 2], -1, 1))) * np.sign(uv[:, 0])
        row = h[mid]
        ok = np.isfinite(row)
        self.curve_m.setData(theta[ok], row[ok])
        # scale the slice to the measurements: a fitted lobe much sharper than the bins can reach
        # peaks far above them, and would flatten the measured points to a line at zero
        ref = row[ok] if ok.any() else (f[mid] if f is not None else np.ones(1))
        top = float(np.nanmax(ref)) if np.any(np.isfinite(ref)) else 1.0
        self.plot.setYRange(min(0.0, float(np.nanmin(ref)) if ok.any() else 0.0), max(top, 1e-9) * 1.4, padding=0)
        if f is not None:
            self.img_f.setImage(np.nan_to_num(f), autoLevels=False, levels=(0, hi))
            self.lab_f.setText(f"{name}{a_txt}")
            tt = np.linspace(theta.min(), theta.max(), 181)
            # the fitted lobe's own values along the same row, densely: interpolate its slice
            self.curve_f.setData(tt, np.interp(tt, theta, f[mid]))
        elif alpha is not None and c < len(alpha):
            self.lab_f.setText(f"{name}{a_txt}")
            self.img_f.clear()
            tt = np.linspace(theta.min(), theta.max(), 181)
            lobe = lobe_retro(lobe_name, float(alpha[c]), np.cos(np.radians(tt)))
            scale = np.nanmax(row) / max(np.nanmax(lobe), 1e-12) if ok.any() else 1.0
            self.curve_f.setData(tt, lobe * scale)
        if first:
            self.vb_m.autoRange(padding=0)
            self.vb_f.autoRange(padding=0)


_SHORT = {"ir-calibration": "ir-cal", "environment": "env", "geometry": "geom"}


def _fmt(v: float, sig: float | None = None) -> str:
    """``v`` to three decimals (or three significant digits below 0.01), with ``± sig`` to two."""
    if not np.isfinite(v):
        return "-"
    txt = f"{v:.3f}" if abs(v) >= 0.01 or v == 0 else f"{v:.3g}"
    if sig is not None and np.isfinite(sig):
        txt += f" \u00b1 {sig:.2g}"
    return txt


def materials_text(alpha, alpha_sigma=None, rho_s=None, rho_s_sigma=None, html: bool = True) -> str:
    """One line per cluster: its roughness alpha and specular rho_s (R, G, B), each with its standard
    error where the engine has one (``Snapshot.alpha_sigma``, ``Snapshot.rho_s_sigma``; NaN or None:
    left out); "diffuse" for a cluster whose rho_s is 0 (the model ladder chose no lobe). ``"-"``
    before the IR pass has clusters.

    Parameters
    ----------
    alpha, alpha_sigma : (C,) arrays or None
    rho_s, rho_s_sigma : (C, 3) arrays or None
    html : bool
        Prefix each line with a dot in the cluster's palette colour (rich text for a QLabel); else
        plain text.
    """
    if alpha is None or len(alpha) == 0:
        return "-"
    a = np.asarray(alpha, np.float64).reshape(-1)
    sa = None if alpha_sigma is None else np.asarray(alpha_sigma, np.float64).reshape(-1)
    rs = None if rho_s is None else np.asarray(rho_s, np.float64).reshape(-1, 3)
    ss = None if rho_s_sigma is None else np.asarray(rho_s_sigma, np.float64).reshape(-1, 3)
    lines = []
    for c in range(len(a)):
        line = f"{c}: \u03b1 {_fmt(a[c], sa[c] if sa is not None and c < len(sa) else None)}"
        if rs is not None and c < len(rs) and np.all(rs[c] == 0):
            line += "; diffuse (\u03c1s 0)"                   # the model ladder's lower rung
        elif rs is not None and c < len(rs):
            line += "; \u03c1s " + ", ".join(_fmt(v) for v in rs[c])
            if ss is not None and c < len(ss) and np.isfinite(ss[c]).all():
                line += " \u00b1 " + ", ".join(f"{e:.2g}" for e in ss[c])
        if html:
            col = "#%02x%02x%02x" % tuple(int(255 * v) for v in C.cluster_rgb([c])[0])
            line = f"<span style='color:{col}'>\u25cf</span> " + line
        lines.append(line)
    return ("<br>" if html else "\n").join(lines)


def luminance_sigma(rho_s_sigma) -> np.ndarray:
    """Standard error (C,) of each cluster's rho_s luminance (Rec. 709 weights) from the channels'
    standard errors (C, 3), taking the channels' errors as independent; NaN where a channel's is."""
    s = np.asarray(rho_s_sigma, np.float64).reshape(-1, 3)
    return np.sqrt(((s * REC709_LUMA) ** 2).sum(axis=1))


class PlotsView(pg.GraphicsLayoutWidget):
    """Live figures: fps per stage, per-cluster alpha with its uncertainty, alpha and rho_s convergence
    (rho_s with its standard error at the latest frame)."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setBackground((20, 20, 24))
        self.p_fps = self.addPlot(row=0, col=0, title="fps per stage")
        self.p_alpha = self.addPlot(row=0, col=1, title="alpha per cluster (+- 1 sigma)")
        self.p_conv = self.addPlot(row=1, col=0, title="alpha convergence")
        self.p_rhos = self.addPlot(row=1, col=1, title="rho_s convergence (luminance, +- 1 sigma)")
        for p in (self.p_fps, self.p_alpha, self.p_conv, self.p_rhos):
            p.showGrid(x=False, y=True, alpha=0.2)
        self.p_conv.setLabel("bottom", "frame")
        self.p_rhos.setLabel("bottom", "frame")
        self.p_alpha.setLabel("bottom", "cluster")
        self.bars = pg.BarGraphItem(x=[], height=[], width=0.6, brush=(90, 160, 255))
        self.p_fps.addItem(self.bars)
        self.alpha_bars = pg.ScatterPlotItem(size=10)
        self.alpha_err = pg.ErrorBarItem(x=np.zeros(0), y=np.zeros(0), beam=0.25, pen=pg.mkPen((220, 220, 220)))
        self.p_alpha.addItem(self.alpha_err)
        self.p_alpha.addItem(self.alpha_bars)
        self.p_alpha.setXRange(-0.5, 1.5)
        self.p_alpha.setYRange(0, 0.5)
        self.p_alpha.getAxis("bottom").setTicks([[(0, "0"), (1, "1")]])
        self.rhos_err = pg.ErrorBarItem(x=np.zeros(0), y=np.zeros(0), beam=0.0, pen=pg.mkPen((220, 220, 220)))
        self.rhos_err.setVisible(False)
        self.p_rhos.addItem(self.rhos_err)
        self.conv_curves: list = []
        self.rhos_curves: list = []
        self._fp = None

    @staticmethod
    def _series(hist):
        """History list of (frame, values) as frames (T,) and values (T, C) padded with NaN."""
        if not hist:
            return np.zeros(0), np.zeros((0, 0))
        frames = np.array([float(h[0]) for h in hist])
        vals = [np.atleast_1d(np.asarray(h[1], np.float64)) for h in hist]
        vals = [v @ REC709_LUMA if v.ndim == 2 and v.shape[-1] == 3 else v.reshape(-1)
                for v in vals]
        c = max(len(v) for v in vals)
        out = np.full((len(vals), c), np.nan)
        for i, v in enumerate(vals):
            out[i, :len(v)] = v
        return frames, out

    def _curves(self, plot, store, frames, vals):
        while len(store) < vals.shape[1]:
            col = tuple(int(255 * x) for x in C.cluster_rgb([len(store)])[0])
            store.append(plot.plot([], [], pen=pg.mkPen(col, width=2)))
        for k, curve in enumerate(store):
            if k < vals.shape[1]:
                ok = np.isfinite(vals[:, k])
                curve.setData(frames[ok], vals[ok, k])
            else:
                curve.setData([], [])

    def update_from(self, snap) -> None:
        fps = dict(getattr(snap, "fps", None) or {})
        hist = getattr(snap, "history", None) or {}
        fp = (tuple(sorted((k, round(float(v), 1)) for k, v in fps.items())),
              fingerprint(snap.alpha), fingerprint(snap.alpha_sigma), fingerprint(snap.rho_s),
              fingerprint(getattr(snap, "rho_s_sigma", None)), tuple((k, len(v)) for k, v in sorted(hist.items())))
        if fp == self._fp:
            return
        self._fp = fp
        names = list(fps)
        self.bars.setOpts(x=np.arange(len(names)), height=[float(fps[k]) for k in names], width=0.6)
        self.p_fps.getAxis("bottom").setTicks([[(i, _SHORT.get(k, k)) for i, k in enumerate(names)]])
        if snap.alpha is not None and len(snap.alpha):
            a = np.asarray(snap.alpha, np.float64)
            s = np.zeros_like(a) if snap.alpha_sigma is None else np.asarray(snap.alpha_sigma, np.float64)
            x = np.arange(len(a), dtype=float)
            brushes = [pg.mkBrush(*(int(255 * v) for v in col)) for col in C.cluster_rgb(np.arange(len(a)))]
            self.alpha_bars.setData(x=x, y=a, brush=brushes)
            self.alpha_err.setData(x=x, y=a, top=s, bottom=s)
            self.p_alpha.getAxis("bottom").setTicks([[(i, str(i)) for i in range(len(a))]])
            self.p_alpha.setXRange(-0.5, len(a) - 0.5, padding=0.05)
            hi = float(np.nanmax(a + s)) if np.any(np.isfinite(a + s)) else 0.5
            self.p_alpha.setYRange(0, max(hi * 1.15, 0.05), padding=0)
        f, v = self._series(hist.get("alpha"))
        self._curves(self.p_conv, self.conv_curves, f, v)
        f, v = self._series(hist.get("rho_s"))
        self._curves(self.p_rhos, self.rhos_curves, f, v)
        self._rho_s_error_bars(snap, f)

    def _rho_s_error_bars(self, snap, frames) -> None:
        """Each cluster's rho_s (luminance) +- its standard error, at the latest frame of the curves
        (the engine's estimate now, which may differ from the curve's last point once the colour
        split and second sweep have run)."""
        sig = getattr(snap, "rho_s_sigma", None)
        if snap.rho_s is None or sig is None:
            # hidden, not emptied: an empty ErrorBarItem still puts x = 0 into the plot's auto range
            self.rhos_err.setVisible(False)
            return
        y = np.asarray(snap.rho_s, np.float64).reshape(-1, 3) @ REC709_LUMA
        s = luminance_sigma(sig)[:len(y)]
        y = y[:len(s)]
        ok = np.isfinite(y) & np.isfinite(s)
        x0 = float(frames[-1]) if len(frames) else float(snap.frame)
        x = np.full(int(ok.sum()), x0)
        self.rhos_err.setData(x=x, y=y[ok], top=s[ok], bottom=s[ok], beam=max(x0, 1.0) * 0.02)
        self.rhos_err.setVisible(bool(ok.any()))


def point_spacing(positions: np.ndarray, n_query: int = 100, k: int = 6, chunk: int = 16384) -> float:
    """Typical spacing of surface points (metres): the median, over ``n_query`` random points, of the
    distance to their ``k``-th nearest neighbour (numpy, chunked).

    The k-th (not the first) neighbour makes it a measure of density that holds for random samples as
    well as for regular ones: on a surface of density rho it is 1.07 / sqrt(rho) for a hexagonal
    lattice and 1.38 / sqrt(rho) for uniformly random points (k = 6), whereas the nearest neighbour of
    random points is only 0.47 / sqrt(rho) and discs of that size leave holes.
    """
    p = np.asarray(positions, np.float32).reshape(-1, 3)
    P = len(p)
    if P <= k:
        return 0.004
    qi = np.random.default_rng(0).choice(P, min(P, n_query), replace=False)
    q = p[qi]
    best = np.full((len(q), k), np.inf, np.float32)
    qq = np.sum(q * q, 1)[:, None]
    for a in range(0, P, chunk):
        blk = p[a:a + chunk]
        d2 = qq + np.sum(blk * blk, 1)[None, :] - 2.0 * q @ blk.T
        own = (qi >= a) & (qi < a + len(blk))
        d2[np.flatnonzero(own), qi[own] - a] = np.inf
        both = np.concatenate([best, d2], axis=1)
        best = np.partition(both, k - 1, axis=1)[:, :k]
    s = float(np.sqrt(max(np.median(best.max(axis=1)), 0.0)))
    return s if np.isfinite(s) and s > 0 else 0.004


def _make_gl_view():
    """pyqtgraph's GL view as a native ``QOpenGLWindow`` (embedded with a window container).

    A ``QOpenGLWidget`` (pyqtgraph's GLViewWidget) makes Qt compose the *whole* window through
    OpenGL on every repaint of any widget in it; with a software renderer (Mesa llvmpipe under Xvfb)
    that halved the UI's redraw rate. A separate native GL window repaints only when the 3-D view
    changes. ``GLViewMixin`` is pyqtgraph's own view logic (camera, items, mouse orbit/zoom).
    """
    import pyqtgraph.opengl as gl
    from pyqtgraph.opengl.GLViewWidget import GLViewMixin
    from PySide6 import QtOpenGL

    class _PointsGL(GLViewMixin, QtOpenGL.QOpenGLWindow):
        """GL view that counts its repaints and hands left-drags to a painter in paint mode."""

        def __init__(self, owner):
            # share GL objects with every other context: pyqtgraph caches compiled shader programs per
            # item class, which a second, unshared view's context would not know (GL_INVALID_VALUE)
            share = QtGui.QOpenGLContext.globalShareContext()
            super().__init__(share) if share is not None else super().__init__()
            fmt = QtGui.QSurfaceFormat.defaultFormat()
            fmt.setDepthBufferSize(24)  # a QOpenGLWindow has none by default: no occlusion between points
            self.setFormat(fmt)
            self.owner = owner
            self.paints = 0

        def devicePixelRatioF(self):
            return float(self.devicePixelRatio())

        def paintGL(self, *a, **k):
            super().paintGL(*a, **k)
            self.paints += 1

        def mousePressEvent(self, ev):
            if self.owner.paint_mode and ev.button() == QtCore.Qt.MouseButton.LeftButton:
                self.owner.stroke_begin(ev.position())
                ev.accept()
                return
            super().mousePressEvent(ev)

        def mouseMoveEvent(self, ev):
            if self.owner.painting and ev.buttons() & QtCore.Qt.MouseButton.LeftButton:
                self.owner.stroke_move(ev.position())
                ev.accept()
                return
            super().mouseMoveEvent(ev)

        def mouseReleaseEvent(self, ev):
            if self.owner.painting and ev.button() == QtCore.Qt.MouseButton.LeftButton:
                self.owner.stroke_end()
                ev.accept()
                return
            super().mouseReleaseEvent(ev)

    return gl, _PointsGL


class PointsView(QtWidgets.QWidget):
    """The fused points in 3-D (pyqtgraph.opengl), coloured by cluster, rho_d, rho_s, alpha or appearance.

    In paint mode a left-drag paints the current label with a screen-space brush of ``brush_px``
    pixels radius (paper §5.2 manual refinement, :func:`appfusion.gui.paint.brush_select`); other
    buttons still orbit / pan and the wheel zooms. Each finished stroke calls ``on_stroke(idx, label)``.
    """

    def __init__(self, parent=None, on_stroke=None):
        super().__init__(parent)
        gl, Cls = _make_gl_view()
        self.gl = Cls(self)
        self.gl.setBackgroundColor((24, 24, 30))
        self.container = QtWidgets.QWidget.createWindowContainer(self.gl, self)
        self.container.setFocusPolicy(QtCore.Qt.FocusPolicy.ClickFocus)
        self.container.setMinimumSize(200, 200)
        lay = QtWidgets.QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(self.container)
        grid = gl.GLGridItem()
        grid.setSize(0.4, 0.4)
        grid.setSpacing(0.05, 0.05)
        grid.setColor((90, 90, 110, 120))
        self.gl.addItem(grid)
        self.axes = gl.GLAxisItem(size=QtGui.QVector3D(0.05, 0.05, 0.05))
        self.gl.addItem(self.axes)
        # points are discs of a world size (pxMode False) matched to their spacing, so the surface
        # looks closed at any zoom and points behind it do not show through
        self.scatter = gl.GLScatterPlotItem(pos=np.zeros((0, 3)), size=0.004, pxMode=False)
        self.scatter.setGLOptions("opaque")
        self.gl.addItem(self.scatter)
        self.gl.setCameraPosition(distance=0.8, elevation=30, azimuth=-60)
        self.gl.opts["center"] = QtGui.QVector3D(0, 0, 0.08)
        self.on_stroke = on_stroke
        self.paint_mode = False
        self.painting = False
        self.brush_px = 15.0
        self.label = 0
        self.positions = None
        self.normals = None
        self.colours = None
        self.base_colours = None
        self._stroke: set[int] = set()
        self._fitted = False
        self.point_size = 0.004

    # -- data ----------------------------------------------------------------------------------
    def set_points(self, positions, normals, colours) -> None:
        p = None if positions is None else np.asarray(positions, np.float32)
        self.positions = p
        self.normals = None if normals is None else np.asarray(normals, np.float32)
        self.base_colours = colours
        self.colours = colours
        if p is None or len(p) == 0:
            self.scatter.setData(pos=np.zeros((0, 3), np.float32))
            return
        self.point_size = point_spacing(p) * 1.2
        self.scatter.setData(pos=p, color=colours, size=self.point_size)
        if not self._fitted:
            self.fit_camera()

    def set_colours(self, colours) -> None:
        self.base_colours = colours
        self.colours = colours
        if self.positions is not None and len(self.positions):
            self.scatter.setData(color=colours)

    def fit_camera(self) -> None:
        """Look at the points: centre on their bounding box, distance from their extent."""
        p = self.positions
        if p is None or len(p) == 0:
            return
        lo, hi = np.percentile(p, [1, 99], axis=0)
        c = 0.5 * (lo + hi)
        ext = float(np.linalg.norm(hi - lo))
        self.gl.opts["center"] = QtGui.QVector3D(float(c[0]), float(c[1]), float(c[2]))
        self.gl.setCameraPosition(distance=max(1.3 * ext, 0.05))
        self._fitted = True

    def camera_matrices(self):
        """(mvp, view) of the current camera as numpy (4, 4), world -> clip / eye (OpenGL)."""
        w, h = max(self.gl.width(), 1), max(self.gl.height(), 1)
        vp = (0, 0, w, h)
        proj = qmatrix_to_numpy(self.gl.projectionMatrix(vp, vp))
        view = qmatrix_to_numpy(self.gl.viewMatrix())
        return proj @ view, view

    def grab_image(self) -> QtGui.QImage:
        """The 3-D view rendered now with the current camera and colours (for screenshots, tests)."""
        self.gl.makeCurrent()
        self.gl.paintGL()  # into the back buffer, which grabFramebuffer reads
        img = self.gl.grabFramebuffer()
        self.gl.doneCurrent()
        return img

    def eye(self) -> np.ndarray:
        c = self.gl.cameraPosition()
        return np.array([c.x(), c.y(), c.z()], np.float64)

    def camera_key(self):
        o = self.gl.opts
        c = o["center"]
        return (round(o["distance"], 5), round(o["elevation"], 2), round(o["azimuth"], 2),
                round(c.x(), 5), round(c.y(), 5), round(c.z(), 5), round(o["fov"], 2))

    # -- painting ------------------------------------------------------------------------------
    def set_paint_mode(self, on: bool) -> None:
        self.paint_mode = bool(on)
        self._update_cursor()

    def set_brush(self, px: float) -> None:
        self.brush_px = float(px)
        self._update_cursor()

    def _update_cursor(self) -> None:
        if not self.paint_mode:
            self.gl.unsetCursor()
            return
        r = int(round(self.brush_px))
        size = 2 * r + 3
        pm = QtGui.QPixmap(size, size)
        pm.fill(QtCore.Qt.GlobalColor.transparent)
        qp = QtGui.QPainter(pm)
        qp.setPen(QtGui.QPen(QtGui.QColor(255, 255, 255), 1.5))
        qp.drawEllipse(QtCore.QPointF(size / 2, size / 2), r, r)
        qp.end()
        self.gl.setCursor(QtGui.QCursor(pm, size // 2, size // 2))

    def select(self, x: float, y: float) -> np.ndarray:
        """Indices of the points under the brush centred at widget pixel (x, y)."""
        if self.positions is None or len(self.positions) == 0:
            return np.zeros(0, np.int64)
        mvp, view = self.camera_matrices()
        return brush_select(self.positions, mvp, view, self.gl.width(), self.gl.height(), (x, y),
                            self.brush_px, normals=self.normals, eye=self.eye(),
                            cell_px=max(2.0 * self.point_px(), 4.0))

    def point_px(self) -> float:
        """On-screen diameter of a point at the view's centre (pixels)."""
        import math

        o = self.gl.opts
        return self.point_size / (2 * o["distance"] * math.tan(math.radians(o["fov"]) / 2)) * self.gl.width()

    def stroke_begin(self, pos) -> None:
        self.painting = True
        self._stroke = set()
        self.stroke_move(pos)

    def stroke_move(self, pos) -> None:
        idx = self.select(pos.x(), pos.y())
        if len(idx) == 0:
            return
        self._stroke.update(idx.tolist())
        if self.colours is not None:
            col = np.array(self.colours, copy=True)
            col[idx, :3] = C.cluster_rgb([self.label])[0]
            self.colours = col
            self.scatter.setData(color=col)

    def stroke_end(self) -> np.ndarray:
        self.painting = False
        idx = np.array(sorted(self._stroke), np.int64)
        self._stroke = set()
        if len(idx) and self.on_stroke is not None:
            self.on_stroke(idx, self.label)
        return idx

    def paint_at(self, points_xy, label: int | None = None) -> np.ndarray:
        """Paint a stroke through widget pixels ``points_xy`` [(x, y), ...] programmatically (tests, macros)."""
        if label is not None:
            self.label = int(label)
        pts = [QtCore.QPointF(float(x), float(y)) for x, y in points_xy]
        self.stroke_begin(pts[0])
        for p in pts[1:]:
            self.stroke_move(p)
        return self.stroke_end()
