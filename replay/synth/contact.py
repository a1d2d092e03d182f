"""Contact sheets of synthetic sessions: one picture with depth, IR, RGB and mirror-ball frames."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from appfusion.errors import AppFusionError


def _depth_vis(d: np.ndarray, lo: float = 0.3, hi: float = 1.5) -> np.ndarray:
    import cv2

    v = np.clip((np.nan_to_num(d, nan=0.0) - lo) / (hi - lo), 0, 1)
    img = cv2.applyColorMap((255 - v * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    img[~np.isfinite(d)] = 0
    return img


def _ir_vis(ir: np.ndarray) -> np.ndarray:
    g = np.clip(ir / 1023.0 * 255.0, 0, 255).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    import cv2

    img = np.ascontiguousarray(img.copy())
    s = max(img.shape[0] / 480.0, 0.4)
    cv2.rectangle(img, (0, 0), (img.shape[1], int(26 * s)), (0, 0, 0), -1)
    cv2.putText(img, text, (6, int(19 * s)), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * s, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def contact_sheet(session: str | os.PathLike, out_png: str | os.PathLike, tile_width: int = 320) -> Path:
    """Write a 2 x 3 contact sheet PNG of a session: the environment pass (RGB of the mirror ball, its
    depth), an IR calibration frame (white sheet), the object's depth and IR, and an RGB frame of the
    object. Picks the middle frame of each pass."""
    import cv2

    from replay.session import SessionReader

    r = SessionReader(session)
    by_pass: dict[str, list[int]] = {}
    for i in range(len(r)):
        by_pass.setdefault(r._pass[i] or "?", []).append(i)

    def mid(name, need, emitter=None):
        idx = by_pass.get(name, [])
        if emitter is not None:
            idx = [i for i in idx if r._emit[i] == emitter]
        for i in idx[len(idx) // 2:] + idx[: len(idx) // 2]:
            f = r.frame(i)
            if getattr(f, need) is not None:
                return f
        return None

    geo = "geometry" if "geometry" in by_pass else "scan"
    rgbp = "rgb" if "rgb" in by_pass else "scan"
    picks = [("environment", "rgb", None, "environment: RGB (mirror ball)"),
             ("environment", "depth", None, "environment: depth"),
             ("ir-calibration", "ir", True, "ir-calibration: IR (white sheet)"),
             (geo, "depth", None, f"{geo}: depth"),
             (geo, "ir", None, f"{geo}: IR"),
             (rgbp, "rgb", None, f"{rgbp}: RGB")]
    tiles = []
    th = None
    for name, stream, em, label in picks:
        f = mid(name, stream, em)
        if f is None:
            img = np.zeros((240, 320, 3), np.uint8)
            label += " (missing)"
        elif stream == "rgb":
            img = f.rgb if f.rgb_encoding == "srgb8" else np.rint(np.clip(f.rgb, 0, 1) * 255).astype(np.uint8)
        elif stream == "depth":
            img = _depth_vis(f.depth)
        else:
            img = _ir_vis(f.ir)
        h = int(round(img.shape[0] * tile_width / img.shape[1]))
        th = th or h
        img = cv2.resize(img, (tile_width, th), interpolation=cv2.INTER_AREA)
        tiles.append(_label(img, label))
    if len(tiles) != 6:
        raise AppFusionError(f"{session}: could not assemble a contact sheet")
    sheet = np.concatenate([np.concatenate(tiles[:3], axis=1), np.concatenate(tiles[3:], axis=1)], axis=0)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out_png), sheet[..., ::-1]):
        raise AppFusionError(f"cannot write {out_png}")
    return out_png
