"""``appfusion bench``: run time against error for every stage, against ground truth.

Stages
------
Each stage of the pipeline contributes a module in :mod:`appfusion.bench.stages` that defines
``run(ctx) -> dict[str, float | None]`` returning measured values for some of the metric names in
:data:`METRICS`. Metrics of stages that do not exist yet stay ``null`` in the JSON. A stage that
reports a name outside :data:`METRICS` is rejected (reported as failed); stage-specific figures go
to ``ctx.extra[STAGE]`` instead. A stage that raises is reported and the others still run.

The context (:class:`appfusion.bench.runner.BenchContext`) tells a stage how hard to try:
``ctx.quick`` (small inputs; the whole ``--quick`` bench must finish in under 2 minutes on 2 cores),
``ctx.budget_s`` (this stage's share of that time, seconds; the runner warns when a stage overruns)
and ``ctx.time_left()`` (seconds of the budget still left), plus ``ctx.seed``, ``ctx.workdir`` and a
``ctx.cache`` shared between stages. A module may set ``BUDGET_S = (quick_s, full_s)`` to override the
runner's default budget for it.

Sweeps
------
Besides its metrics a stage may measure time against error over a quality knob (points sampled, HBSAB
resolution, wavelet coefficients kept, env-map resolution, voxel size, frame stride, ...)::

    ctx.extra["sweeps"][KNOB] = {
        "metric": NAME,            # what "error" is (a METRICS name where one fits)
        "default": VALUE,          # the engine's default setting of the knob; must be one of the values
        "points": [{"value": v, "ms_per_frame": t, "error": e}, ...],
        "note": "...",             # optional: what the time and the error cover
    }

with ``t`` in milliseconds per frame (finite, >= 0) and ``e`` >= 0, or ``None`` where that setting
failed. Use ``ctx.add_sweep(knob, metric, default, points, note=None)``, which validates the sweep.
Knob names are global: two stages must not sweep the same name. The runner moves the sweeps to the
report's top-level ``"sweeps"`` (each with the ``"stage"`` that measured it, its Pareto ``"front"`` and
``"default_on_front"``), reports ``"defaults_on_front": {knob: bool | None}`` and draws the Pareto plot
(:mod:`appfusion.bench.pareto`).

Report
------
``run_bench`` returns (and ``--json FILE`` writes)::

    {"metrics": {NAME: {"value": v | null, "unit": u, "goal": g | null, "better": "lower" | "higher"}},
     "stages": {STAGE: {"status": "ok" | "error" | "not built yet", "seconds", "budget_s",
                        "over_budget", "metrics", "peak_rss_mb", ...}},
     "sweeps": {KNOB: {...}}, "defaults_on_front": {KNOB: bool | null},
     "extra": {STAGE: {...}}, "notes": {METRIC: "how this value was measured"}, "quick": bool,
     "seconds": total, "budget_s": total budget, "plot": path | null, "host": {...}}

A stage may qualify a metric it reports with ``ctx.note(metric, text)`` (e.g. ``demo_scan_s`` measured on
a small session with ``--quick``); the notes go to the report's ``"notes"`` and are printed under the
metric table.
"""

from __future__ import annotations

#: name -> (unit, goal, better). Goals are the acceptance figures of the issues.
METRICS: dict[str, tuple[str, float | None, str]] = {
    "ate_mm": ("mm", 5.0, "lower"),
    "chamfer_mm": ("mm", 2.0, "lower"),
    "normal_err_deg": ("deg", 3.0, "lower"),
    "crease_normal_err_deg": ("deg", None, "lower"),           # points within 6 mm of the object's sharp edges
    "marker_detect_rate": ("fraction", 0.99, "higher"),
    "white_err": ("fraction", 0.01, "lower"),
    "envmap_median_rel_err": ("fraction", 0.05, "lower"),
    "sphere_center_err_mm": ("mm", 2.0, "lower"),
    "alpha_protocol_max_rel_err": ("fraction", 0.001, "lower"),
    "alpha_cluster_rel_err": ("fraction", 0.05, "lower"),
    "label_accuracy": ("fraction", 0.95, "higher"),
    "rho_d_median_rel_err": ("fraction", 0.03, "lower"),
    "rho_d_dark_bias": ("fraction", 0.03, "lower"),            # median signed rho_d error of channels near black
    "rho_s_rel_err": ("fraction", 0.05, "lower"),
    "double_product_rel_err": ("fraction", 0.01, "lower"),
    "double_product_ggx_rel_err": ("fraction", 0.01, "lower"),     # the GGX rung's tables (alpha 0.15)
    "relit_rel_rmse": ("fraction", 0.05, "lower"),
    "fps_tracking_fusion": ("fps", 15.0, "higher"),
    "fps_ir_update": ("fps", 30.0, "higher"),
    "fps_ir_update_pattern": ("fps", 30.0, "higher"),           # the same with the emitter pattern map divided out
    "fps_rgb_update": ("fps", 30.0, "higher"),
    "fps_rgb_update_near_field": ("fps", 30.0, "higher"),       # the same with the support plane's near field
    "wavelet_tables_mb": ("MB", 64.0, "lower"),
    "wavelet_build_s": ("s", 10.0, "lower"),
    "peak_rss_mb": ("MB", None, "lower"),
    "demo_scan_s": ("s", 300.0, "lower"),
    # end to end (stage "scan"): the same quantities as above after the whole pipeline on a synthetic session
    "scan_ate_mm": ("mm", 5.0, "lower"),
    "scan_chamfer_mm": ("mm", 2.0, "lower"),
    "scan_normal_err_deg": ("deg", 3.0, "lower"),
    "scan_label_accuracy": ("fraction", 0.95, "higher"),
    "scan_alpha_cluster_rel_err": ("fraction", 0.05, "lower"),
    "scan_rho_d_median_rel_err": ("fraction", 0.03, "lower"),
    "scan_rho_s_rel_err": ("fraction", 0.05, "lower"),
    "scan_envmap_median_rel_err": ("fraction", 0.05, "lower"),
    "scan_envmap_energy_rel_err": ("fraction", 0.03, "lower"),      # issue #5: total energy within 3 %
    "scan_alpha_sharpest_rel_err": ("fraction", 0.05, "lower"),     # the material with a visible IR highlight
    "scan_ir_pattern_heldout_cv": ("fraction", None, "lower"),     # IR emitter pattern map, held-out spread
    "scan_relit_interior_rel_rmse": ("fraction", None, "lower"),   # relit without the 1-px silhouette band (diagnostic)
    "scan_rho_s_err_sigmas": ("standard errors", None, "lower"),  # rho_s error over its own standard error (diagnostic)
    # the exported files: the .glb's vertex normals, the rho_d map at the triangles' centroids (session 33)
    "scan_export_normal_err_deg": ("deg", 3.0, "lower"),
    "scan_export_rho_d_median_rel_err": ("fraction", 0.03, "lower"),
    # the matte scene (one material, no lobe): exported rho_s over its area (0: diffuse; no goal, 0 is right)
    "scan_matte_rho_s": ("rho_s", None, "lower"),
    "scan_matte_rho_d_median_rel_err": ("fraction", 0.03, "lower"),
    "scan_matte_relit_rel_rmse": ("fraction", 0.05, "lower"),
    # a GGX paint over a Ward label (ggx-two-material; the full bench only)
    "scan_ggx_label_accuracy": ("fraction", 0.95, "higher"),
    "scan_ggx_lobe_accuracy": ("fraction", 1.0, "higher"),
    "scan_ggx_rho_s_rel_err": ("fraction", 0.05, "lower"),
    "scan_ggx_relit_rel_rmse": ("fraction", 0.05, "lower"),
    # a fast sweep (30 degrees of orbit a frame): geometry frames tracked within 1 cm / 1 degree
    "fast_sweep_tracked": ("fraction", None, "higher"),
    # "skip what the scene doesn't need": fraction of the run time saved by each skip (no goal; the
    # before / after figures and the error check are in extra and docs/performance.md)
    "skip_fusion_saving": ("fraction", None, "higher"),
    "skip_lighting_saving": ("fraction", None, "higher"),
    "skip_wavelet_saving": ("fraction", None, "higher"),
    "skip_rerun_saving": ("fraction", None, "higher"),        # a rerun with a colour option: checkpoints reused
}
