"""Helper for tests/test_session.py: record frames in a loop until killed.

Usage: ``python tests/_kill_writer.py SESSION_DIR [WIDTH HEIGHT]``.

Frame ``i`` has timestamp ``i * 0.01`` s and deterministic content (see :func:`frame_images`), so
the test can check every replayed frame bit for bit. After each ``write`` returns, the script prints
``i`` and the wall-clock time, flushed, so the parent knows what was written and when.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DT = 0.01


def frame_images(i: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth PNG units (uint16), IR counts (uint16) and sRGB (uint8) of frame ``i``."""
    base = np.arange(width * height, dtype=np.int64).reshape(height, width)
    depth_u = ((base * 7 + i * 131) % 20000 + 1500).astype(np.uint16)
    depth_u[(base + i) % 17 == 0] = 0
    ir = ((base * 3 + i * 11) % 1024).astype(np.uint16)
    rgb = np.stack([(base + i) % 256, (base * 5 + i) % 256, (base * 11 + 2 * i) % 256], axis=-1).astype(np.uint8)
    return depth_u, ir, rgb


def main() -> None:
    from appfusion.frame import Frame, Intrinsics
    from replay.session import SessionWriter

    path = sys.argv[1]
    w_, h_ = (int(sys.argv[2]), int(sys.argv[3])) if len(sys.argv) > 3 else (160, 120)
    K = Intrinsics(w_, h_, 0.8 * w_, 0.8 * w_, (w_ - 1) / 2, (h_ - 1) / 2)
    w = SessionWriter(path, device="kill-test", intrinsics={"depth": K, "ir": K, "rgb": K})
    w.event(0.0, "pass", "scan")
    print("ready", time.time(), flush=True)
    i = 0
    while True:
        du, ir, rgb = frame_images(i, w_, h_)
        depth = du.astype(np.float32) / np.float32(5000.0)
        depth[du == 0] = np.nan
        w.write(Frame(i, i * DT, depth=depth, ir=ir.astype(np.float32), rgb=rgb))
        print(i, time.time(), flush=True)
        i += 1


if __name__ == "__main__":
    main()
