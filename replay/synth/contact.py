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


def _closeup(f, centre_w: np.ndarray, radius_m: float, pose: np.ndarray | None, gain: float) -> np.ndarray | None:
    """Crop of an RGB frame around a world point (using the true pose), brightened by ``gain`` in linear."""
    from appfusion.frame import invert_pose, linear_to_srgb

    if pose is None or f.rgb is None:
        return None
    cam = invert_pose(pose @ invert_pose(f.depth_to_rgb))
    pc = cam[:3, :3] @ centre_w + cam[:3, 3]
    K = f.rgb_intrinsics
    if pc[2] <= 0:
        return None
    u, v = K.fx * pc[0] / pc[2] + K.cx, K.fy * pc[1] / pc[2] + K.cy
    r = int(np.ceil(2.2 * radius_m * K.fx / pc[2]))
    h, w = f.rgb.shape[:2]
    x0, y0 = int(round(u)) - r, int(round(v)) - int(round(0.75 * r))
    x1, y1 = x0 + 2 * r, y0 + int(round(1.5 * r))
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h or r < 4:
        return None
    lin = f.rgb_linear()[y0:y1, x0:x1] * gain
    return np.rint(linear_to_srgb(lin) * 255).astype(np.uint8)


def contact_sheet(session: str | os.PathLike, out_png: str | os.PathLike, tile_width: int = 320) -> Path:
    """Write a 2 x 4 contact sheet PNG of a session: the environment pass (RGB, a brightened close-up of
    the mirror ball, depth), an IR calibration frame (white sheet), the object's depth and IR, an RGB
    frame of the object and its close-up. Picks the middle frame of each pass; close-ups use the true
    poses in ``truth/``."""
    import cv2

    from replay.session import SessionReader, parse_groundtruth

    session = Path(session)
    r = SessionReader(session)
    gt = session / "truth" / "groundtruth.txt"
    poses = {}
    if gt.exists():
        times, P, _, _ = parse_groundtruth(gt.read_bytes())
        poses = {round(float(t), 6): p for t, p in zip(times, P)}
    scene = {}
    if (session / "truth" / "scene.json").exists():
        import json

        scene = json.loads((session / "truth" / "scene.json").read_text())
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
    ball = scene.get("ball", {})
    height = scene.get("object_height_m")
    if height is None and (session / "truth" / "object.npz").exists():
        height = float(np.load(session / "truth" / "object.npz")["vertices"][:, 2].max())
    obj_c = np.array([0.0, 0.0, 0.5 * float(height or 0.15)])
    picks = [("environment", "rgb", None, "environment: RGB (mirror ball)", None),
             ("environment", "rgb", None, "environment: ball close-up, x8 brightness",
              (np.array(ball.get("centre_m", (0, 0, 0.035))), float(ball.get("radius_m", 0.035)), 8.0)),
             ("environment", "depth", None, "environment: depth", None),
             ("ir-calibration", "ir", True, "ir-calibration: IR (white sheet)", None),
             (geo, "depth", None, f"{geo}: depth", None),
             (geo, "ir", None, f"{geo}: IR", None),
             (rgbp, "rgb", None, f"{rgbp}: RGB", None),
             (rgbp, "rgb", None, f"{rgbp}: close-up", (obj_c, 0.07, 1.0))]
    tiles = []
    th = int(round(tile_width * 3 / 4))
    for name, stream, em, label, crop in picks:
        f = mid(name, stream, em)
        img = None
        if f is not None and crop is not None:
            img = _closeup(f, crop[0], crop[1], poses.get(round(f.timestamp, 6)), crop[2])
        elif f is not None and stream == "rgb":
            img = f.rgb if f.rgb_encoding == "srgb8" else np.rint(np.clip(f.rgb, 0, 1) * 255).astype(np.uint8)
        elif f is not None and stream == "depth":
            img = _depth_vis(f.depth)
        elif f is not None:
            img = _ir_vis(f.ir)
        if img is None:
            img = np.zeros((th, tile_width, 3), np.uint8)
            label += " (not available)"
        img = cv2.resize(img, (tile_width, th), interpolation=cv2.INTER_AREA if img.shape[1] > tile_width
                         else cv2.INTER_NEAREST)
        tiles.append(_label(img, label))
    sheet = np.concatenate([np.concatenate(tiles[:4], axis=1), np.concatenate(tiles[4:], axis=1)], axis=0)
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out_png), sheet[..., ::-1]):
        raise AppFusionError(f"cannot write {out_png}")
    return out_png
