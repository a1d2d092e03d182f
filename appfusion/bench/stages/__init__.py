"""Benchmark stages: each module defines ``run(ctx) -> dict`` of metric values (see appfusion.bench)."""

#: stage modules run by ``appfusion bench``, in pipeline order
STAGES = ["synth", "geometry", "lighting", "ir", "rgb", "scan", "stability"]
