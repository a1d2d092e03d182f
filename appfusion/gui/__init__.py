"""The live scanning GUI (PySide6 + pyqtgraph): ``appfusion gui [SOURCE]``.

Modules: :mod:`~appfusion.gui.app` (the main window), :mod:`~appfusion.gui.views` (streams, 3-D points
with the paint brush, environment map, HBSAB, plots), :mod:`~appfusion.gui.worker` (the engine's worker
thread, snapshot hand-over, pacing and recording), :mod:`~appfusion.gui.paint` (the §5.2 screen-space
brush), :mod:`~appfusion.gui.colours` (point colourings and image tone mapping). Only ``app`` and
``views`` import Qt. See ``docs/gui.md``.
"""

from __future__ import annotations

__all__ = ["run_gui", "MainWindow"]


def __getattr__(name):  # Qt is imported only when the window is asked for
    if name in __all__:
        from . import app

        return getattr(app, name)
    raise AttributeError(name)
