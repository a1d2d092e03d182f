"""``appfusion render``: relight a scanned object under any environment map from any view."""

from __future__ import annotations

import json
import os
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("render", help="relight a scan result under an environment map from a view (PNG + EXR)",
                       description="Renders the captured object (mesh + rho_d, rho_s, lobe alpha: Ward or GGX) under an "
                                   "environment map by Monte Carlo integration with self-shadowing.")
    p.add_argument("result", type=Path, help="scan output folder (with result.npz) or the result.npz itself")
    p.add_argument("--env", type=Path, help="environment map (.exr/.hdr lat-long, or .npz from a scan); "
                                            "default: the scan's own environment map")
    p.add_argument("--view", default="orbit:30:25:0.5",
                   help="camera: 'orbit:AZIMUTH_DEG:ELEVATION_DEG:RADIUS_M' around the object, or a JSON file "
                        "with a 4x4 camera-to-world 'pose' (OpenCV axes, marker frame) and optional 'intrinsics'")
    p.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel per strategy (default 64)")
    p.add_argument("--no-shadows", action="store_true")
    p.add_argument("--crease-deg", type=float, default=30.0,
                   help="shade hits on a triangle whose vertex normals differ by more than this (degrees) with "
                        "the nearest point's normal, not interpolated across the crease (default 30; 0: always "
                        "interpolate)")
    p.add_argument("--out", type=Path, default=None, help="output file stem (default RESULT/render)")
    p.set_defaults(func=run)


def parse_view(view: str, result, size: tuple[int, int]):
    """(Intrinsics, pose) from a --view argument."""
    import numpy as np

    from appfusion.errors import AppFusionError
    from appfusion.frame import Intrinsics, make_pose

    w, h = size
    K = Intrinsics(w, h, 0.85 * w, 0.85 * w, (w - 1) / 2, (h - 1) / 2)
    if view.startswith("orbit:"):
        try:
            az, el, r = (float(x) for x in view.split(":")[1:4])
        except ValueError:
            raise AppFusionError(f"--view {view!r}: expected orbit:AZIMUTH_DEG:ELEVATION_DEG:RADIUS_M") from None
        if not (np.isfinite([az, el]).all() and np.isfinite(r) and r > 0):
            raise AppFusionError(f"--view {view!r}: angles must be finite and RADIUS_M a positive distance "
                                 f"(metres from the object's centre)")
        P = result.positions
        target = np.array([P[:, 0].mean(), P[:, 1].mean(), 0.5 * (P[:, 2].min() + P[:, 2].max())])
        a, e = np.radians(az), np.radians(el)
        eye = target + r * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, [0, 0, 1.0])
        if np.linalg.norm(x) < 1e-6:
            x = np.array([1.0, 0, 0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return K, make_pose(np.stack([x, y, z], 1), eye)
    path = Path(view)
    if not path.exists():
        raise AppFusionError(f"--view {view!r}: neither orbit:... nor an existing JSON file")
    try:
        d = json.loads(path.read_text())
        pose = np.asarray(d["pose"], float).reshape(4, 4)
    except (ValueError, KeyError, TypeError) as e:
        raise AppFusionError(f"{path}: expected JSON with a 4x4 'pose' ({e})") from None
    if not np.isfinite(pose).all():
        raise AppFusionError(f"{path}: the 'pose' holds non-finite numbers")
    if "intrinsics" in d:
        K = Intrinsics.from_json(d["intrinsics"])
    return K, pose


def run(args) -> int:
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2
    import numpy as np

    from appfusion.errors import AppFusionError
    from appfusion.frame import linear_to_srgb
    from appfusion.relight import render_view
    from appfusion.result import ScanResult

    if args.spp < 1:
        raise AppFusionError(f"render: --spp must be at least 1 sample per pixel, got {args.spp}")
    if not (np.isfinite(args.crease_deg) and 0 <= args.crease_deg <= 180):
        raise AppFusionError(f"render: --crease-deg must be in [0, 180] degrees, got {args.crease_deg}")
    res = ScanResult.load(args.result)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise AppFusionError(f"--size {args.size!r}: expected WxH, e.g. 640x480") from None
    if args.env is None:
        if res.envmap is None:
            raise AppFusionError("the scan has no environment map: give --env MAP")
        env = res.envmap
    else:
        from appfusion.envmap import EnvMap

        env = EnvMap.load(args.env, n=64).radiance
    K, pose = parse_view(args.view, res, (w, h))
    img, mask = render_view(res, env, K, pose, spp=args.spp, shadows=not args.no_shadows,
                            crease_deg=args.crease_deg or None)
    stem = args.out or (args.result if args.result.is_dir() else args.result.parent) / "render"
    stem.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(stem.with_suffix(".exr")), np.ascontiguousarray(img[..., ::-1]))
    expo = 0.9 / max(float(np.percentile(img[mask], 99.5)) if mask.any() else 1.0, 1e-9)
    png = np.rint(linear_to_srgb(img * expo) * 255).astype(np.uint8)
    cv2.imwrite(str(stem.with_suffix(".png")), np.ascontiguousarray(png[..., ::-1]))
    print(f"wrote {stem.with_suffix('.png')} and {stem.with_suffix('.exr')} ({int(mask.sum())} object pixels)")
    return 0
