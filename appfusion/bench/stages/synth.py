"""Bench stage ``synth``: the synthetic scanner's own render error and speed (no engine metric).

Reports, under ``extra["synth"]``: the RMS and mean relative error of the fast RGB renderer against its
16x brute-force reference on a few pixels (``replay.synth.accuracy.render_error``), and the seconds per
frame of every stream (``replay.synth.accuracy.frame_timing``): with ``--quick`` for the fast "test"
settings at 160 x 120, otherwise for the full settings at 320 x 240. A full run also leaves a synthetic
session in the bench work folder, its path in ``ctx.cache["synth_session"]``.
"""

from __future__ import annotations


BUDGET_S = (10.0, 120.0)


def run(ctx) -> dict:
    from replay.synth import render_session
    from replay.synth.accuracy import frame_timing, render_error
    from replay.synth.render import Quality

    cache = ctx.workdir / "synth-cache"
    if ctx.quick:
        # the fast "test" settings on a coarse mesh (the full settings' figures come from a full run)
        q, detail, size = Quality.preset("test"), "test", (160, 120)
        err = render_error("two-material", n_pixels=24, frames=1, size=size, detail=detail, quality=q, seed=ctx.seed,
                           factor=4, cache_dir=cache)
        tim = frame_timing("two-material", size=size, frames=1, detail=detail, quality=q, seed=ctx.seed,
                           cache_dir=cache)
    else:
        q, detail, size = Quality(), "full", (320, 240)
        err = render_error("two-material", n_pixels=200, frames=2, size=size, detail=detail, quality=q,
                           seed=ctx.seed, cache_dir=cache)
        tim = frame_timing("two-material", size=size, frames=5, detail=detail, quality=q, seed=ctx.seed,
                           cache_dir=cache)
        path = ctx.workdir / f"synth-two-material-{ctx.seed}"
        if not (path / "truth" / "scene.json").exists():
            if path.exists():
                import shutil

                shutil.rmtree(path)
            render_session("two-material", path, frames=30, size=(320, 240), seed=ctx.seed, show_progress=False,
                           cache_dir=cache)
        ctx.cache["synth_session"] = path
    ctx.extra["synth"] = {
        "quality": "test" if ctx.quick else "full", "size": list(size),
        "render_rms_rel": err["rms_rel"], "render_mean_rel": err["mean_rel"], "render_error_pixels": err["pixels"],
        "reference_factor": err["factor"], "seconds_per_frame_all_streams": tim["all_streams_s"],
        "depth_ir_s": tim["depth_ir_s"], "rgb_s": tim["rgb_s"], "precompute_s": tim["precompute_s"],
    }
    return {}
