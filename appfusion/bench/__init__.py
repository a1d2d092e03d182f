"""``appfusion bench``: run time against error for every stage, against ground truth.

Each stage of the pipeline contributes a module in :mod:`appfusion.bench.stages` that defines
``run(ctx) -> dict[str, float | None]`` returning measured values for some of the metric names in
:data:`METRICS`. Metrics of stages that do not exist yet stay ``null`` in the JSON.
"""

from __future__ import annotations

#: name -> (unit, goal, better). Goals are the acceptance figures of the issues.
METRICS: dict[str, tuple[str, float | None, str]] = {
    "ate_mm": ("mm", 5.0, "lower"),
    "chamfer_mm": ("mm", 2.0, "lower"),
    "normal_err_deg": ("deg", 3.0, "lower"),
    "marker_detect_rate": ("fraction", 0.99, "higher"),
    "white_err": ("fraction", 0.01, "lower"),
    "envmap_median_rel_err": ("fraction", 0.05, "lower"),
    "sphere_center_err_mm": ("mm", 2.0, "lower"),
    "alpha_protocol_max_rel_err": ("fraction", 0.001, "lower"),
    "alpha_cluster_rel_err": ("fraction", 0.05, "lower"),
    "label_accuracy": ("fraction", 0.95, "higher"),
    "rho_d_median_rel_err": ("fraction", 0.03, "lower"),
    "rho_s_rel_err": ("fraction", 0.05, "lower"),
    "double_product_rel_err": ("fraction", 0.01, "lower"),
    "relit_rel_rmse": ("fraction", 0.05, "lower"),
    "fps_tracking_fusion": ("fps", 15.0, "higher"),
    "fps_ir_update": ("fps", 30.0, "higher"),
    "fps_rgb_update": ("fps", 30.0, "higher"),
    "wavelet_tables_mb": ("MB", 64.0, "lower"),
    "wavelet_build_s": ("s", 10.0, "lower"),
    "peak_rss_mb": ("MB", None, "lower"),
    "demo_scan_s": ("s", 300.0, "lower"),
}
