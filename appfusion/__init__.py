"""appfusion: interactive appearance acquisition with a consumer depth camera.

The system of Wu & Zhou, "AppFusion: Interactive Appearance Acquisition Using a Kinect Sensor"
(Computer Graphics Forum 2015). Importing this package is cheap: heavy modules (Open3D, Qt) are
imported by the modules that need them.

Importing it first (as ``appfusion`` and ``python -m appfusion`` do) sets ``OMP_NUM_THREADS=1``
unless the environment already sets it: see :func:`_one_openmp_thread`.
"""

import os as _os
import sys as _sys

__version__ = "0.1.0"


def _one_openmp_thread() -> bool:
    """Default OpenMP to one thread before Open3D loads libgomp; True when it was set here.

    libgomp reads ``OMP_NUM_THREADS`` once, when it is loaded, for every thread of the process.
    :func:`appfusion.fusion.set_openmp_threads` sets one thread on the thread that tracks, but
    Open3D also runs parallel loops from threads of its own, which keep the default of one thread
    per core. Their float reductions then add up in an order that depends on which thread ends
    first, so the same session scanned twice at once gave poses up to 3e-5 apart (and a split
    cluster's alpha of 0.47 vs 0.50); with the variable set before the import, bit-identical. On
    2 cores it costs nothing (geometry pass of a 40-frame session 13.1 s either way, see
    ``appfusion.fusion``). OpenBLAS also reads the variable: ``OPENBLAS_NUM_THREADS`` is set to
    the cores available so that numpy keeps its thread pool.
    """
    if "OMP_NUM_THREADS" in _os.environ or "open3d" in _sys.modules:
        return False
    if "numpy" not in _sys.modules:
        cores = len(_os.sched_getaffinity(0)) if hasattr(_os, "sched_getaffinity") else (_os.cpu_count() or 1)
        _os.environ.setdefault("OPENBLAS_NUM_THREADS", str(cores))
    _os.environ["OMP_NUM_THREADS"] = "1"
    return True


_one_openmp_thread()
