"""The RGB-pass tests' shared scene: a two-material sphere rendered from 32 orbit views
(:func:`appfusion.rgb_synth.two_material_sphere`, 1 % relative noise)."""

import numpy as np

from appfusion.rgb_synth import orbit_poses, two_material_sphere

# tables for the tests: coarser r grids than the defaults (faster to build, S ~1.5 % RMS)
TABLES = {"r_res": lambda a: 65 if a < 0.15 else 41, "d_res": 49}


def sphere_frames():
    """``(scene, poses, rng, frames)``: ``frames`` are ``(rgb, depth, ...)`` renders, one per pose; ``rng``
    is the generator that rendered them, passed on so that callers draw from the same stream."""
    sc = two_material_sphere(1200, env_n=32, seed=0, image_scale=0.4,
                             materials=((0.08, (0.35, 0.3, 0.25)), (0.25, (0.5, 0.5, 0.5))))
    poses = orbit_poses(sc.center, 0.45, 32, seed=1)
    rng = np.random.default_rng(5)
    frames = [sc.render(T, rng, noise_rel=0.01, noise_abs=0.001) for T in poses]
    return sc, poses, rng, frames
