"""The synthetic scanner: complete scan sessions of known objects with ground truth.

``render_session(scene, out, frames=..., size=..., seed=..., device=...)`` writes a session in our
format (``replay.session``) plus a ``truth/`` folder the engine never reads; ``demo_session(cache_dir)``
generates (once) and returns the bundled demo. Models and parameters: ``docs/synthetic-scanner.md``.

This package imports no engine code (only ``appfusion.frame``, ``appfusion.errors``,
``appfusion.progress`` and ``replay.session``): it has its own BRDFs, integrators and direction maps.
"""

from __future__ import annotations

from .objects import OBJECTS
from .scanner import DEVICES, demo_session, render_session, scene_names

__all__ = ["OBJECTS", "DEVICES", "render_session", "demo_session", "scene_names"]
