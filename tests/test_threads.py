"""Importing appfusion defaults OpenMP to one thread before Open3D loads libgomp (appfusion.__init__):
Open3D's parallel loops on threads of its own otherwise add floats in an order that depends on load."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = """
import ctypes, os, threading, appfusion, open3d
gomp = ctypes.CDLL("libgomp.so.1")
seen = []
t = threading.Thread(target=lambda: seen.append(gomp.omp_get_max_threads()))
t.start(); t.join()
from threadpoolctl import threadpool_info
blas = [i["num_threads"] for i in threadpool_info() if i["internal_api"] == "openblas"]
print(os.environ.get("OMP_NUM_THREADS", "unset"), seen[0], min(blas))
"""


def _probe(**env) -> list[str]:
    e = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    e.update(env)
    out = subprocess.run([sys.executable, "-c", PROBE], env=e, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="one core: libgomp's default is one thread anyway")
def test_import_sets_one_openmp_thread_for_every_thread_and_keeps_blas_threads():
    cores = len(os.sched_getaffinity(0))
    env, new_thread, blas = _probe()
    # a thread started after the import (as Open3D's own are) gets one OpenMP thread, not one per core
    assert env == "1" and int(new_thread) == 1
    assert int(blas) == cores                      # numpy's OpenBLAS pool is left as it was
    # a user's own setting wins
    env, new_thread, _ = _probe(OMP_NUM_THREADS="2")
    assert env == "2" and int(new_thread) == 2
