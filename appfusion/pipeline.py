"""Scan orchestration: the paper's passes over one source, in order, as an incremental engine.

A :class:`ScanRunner` consumes frames from a :class:`~appfusion.source.Source` (a recording or a live
device) and routes each to the pass it belongs to (``Frame.pass_name``, set by recordings from their
``pass`` events, or by the runner's current pass for live sources):

1. ``ir-calibration`` (§6): IR background, response curve and shifted-Gamma emitter model.
2. ``environment`` (§4.3): tracking, mirror-ball sphere fit, environment map.
3. ``geometry`` (§4.1 then §5.1-5.2): tracking + TSDF fusion; at the end of the fusion the object's
   points are sampled, then the same pass's IR frames feed BRDF fusion (HBSAB, BRDF cut, Ward fit).
4. ``rgb`` (§4.2, §5.3): white balance, rho_d histograms and rho_s sums.
5. ``scan``: a device that streams depth, IR and RGB at once runs 3 and 4 on the same frames.

Every pass keeps constant-size state. The runner publishes :class:`Snapshot` objects (small copies
of that state) for the GUI and the CLI's progress; the GUI never touches the engine's arrays.
Each finished stage is checkpointed in ``out_dir/state/`` so a scan that was killed resumes from the
last finished stage when run again with the same output folder. A checkpoint is keyed on what its
stage depends on (:data:`STAGE_UPSTREAM`, :data:`STAGE_CONFIG`), so a rerun with another colour option
or environment map recomputes only the stages that depend on it.
"""

from __future__ import annotations

import itertools
import json
import os
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import AppFusionError, EstimationError, PassMissingError
from .frame import Frame

#: the passes in the order they are scanned
PASSES = ("ir-calibration", "environment", "geometry", "rgb", "scan")
#: version of what the stages compute: bump it when a stage's output changes, so that checkpoints
#: written by an older engine (``out_dir/state``) are recomputed instead of reused (3: 3 mm voxels, the
#: near-field plane and diffuse weighting in the RGB pass, the colour split's voxel neighbourhoods;
#: 5: small holes of the fused mesh closed, the RGB pass's second sweep; 6: IR samples with their own
#: normals and poses re-registered to the final mesh; 7: filled holes wound like the mesh around them;
#: 8: the IR fits without the leaves at the surface's open boundary, the lobes refitted to the final clusters
#: and a third colour sweep when a measured lobe moved; 9: complete depth blocks only and marker anchors
#: weighted 3 in tracking; 10: the anchors' error across the support plane weighted 30, normals filtered
#: over 128 neighbours; 11: circle centres fitted to the blobs' pixels; 12: the colour pass's rho_s from a
#: cluster's interior points and the model ladder's significance rule; 13: the geometry fused again at
#: poses re-registered with the circles; 14: normals filtered in adaptive stages; 15: the environment map
#: splatted with a 0.25 px pixel kernel; 16: circle centres weighted by their view's elevation and
#: fused again at the refused poses; 17: a third adaptive stage of the normal filter, 12 passes;
#: 18: no elevation weights on the anchors, lost frames' stale poses no longer passed on, the IR's
#: automatic k with split_gain 3; 19: the captured map's blur variance and S read at the effective
#: roughness; 20: the normal filter's stages run only while it converges; 21: refuse_voxel_scale in
#: the configuration; 22: specular normal refinement, its normals saved with the RGB stage; 23: normals
#: sharpened at creases, the re-fusion finer where the object curves tightly, its truncation in the
#: configuration; 24: rho_d corrected for the noise clipped at black; 25: the colour split only where
#: the lobe varies; 26: a cluster whose IR lobe runs to the roughness bound is diffuse; 27: normals of
#: planar faces snapped to their plane; 28: refuse_fine_trunc_voxels in the configuration; 29: circles
#: matched by their shape while lost, the motion over a relocalisation's gap, frames before the marker
#: frame anchored on the circles seen so far and given marker-frame poses; 30: those poses only where
#: the frames' own circles confirm them; 31: tracking normals' discontinuity threshold grows with depth;
#: 32: a complete keyed detection pairs its circles by number, tracking starts from the circles' pose
#: where it lies beyond the jump limit from the prediction; 33: three circles numbered by the key
#: circle start the marker frame and pair by number; 34: the fine re-fusion truncates at 2 voxels by
#: default, from 60 frames on; 35: holes closed by boundary loop (clipped to a star, a web of rings,
#: faired), no longer by VTK's filler; 36: specular normal refinement by default where the fine
#: re-fusion fired, moved points keep their rho_d; 37: normals from cubic jet fits where the normal
#: filter's stages do not converge, a crease's rounded band split between its faces; 38: the IR fit
#: chooses each cluster's lobe, Ward or GGX, the model ladder's third rung)
CHECKPOINT_VERSION = 38


def _compare_lobes(model, lobes, alpha, specular) -> tuple[np.ndarray, np.ndarray]:
    """The lobes every point is measured against in the second colour sweep
    (:meth:`appfusion.rgb_pass.RGBPass.reassign_by_model`): one per distinct (lobe, alpha) of the
    specular clusters whose lobe the first sweep's model ladder kept (``model`` not ``"diffuse"``),
    each with the cluster's current lobe name and alpha. Returns the alphas (K,) and names (K,).

    Until session 37 only Ward lobes were compared: on the ``ggx-two-material`` scene the GGX paint
    then kept the points the colour split had given it, labels 0.855 against 0.997.
    """
    n = min(len(alpha), len(model))
    pairs = sorted({(str(lobes[c]), float(alpha[c])) for c in range(n) if model[c] != "diffuse" and specular[c]})
    return np.array([a for _, a in pairs], np.float64), np.array([lb for lb, _ in pairs], dtype="<U8")


def _broad_lobe(alpha) -> np.ndarray:
    """(C,) bool: clusters whose fitted IR roughness ran to its upper bound (``ward_fit.ALPHA_MAX``, 1).

    Such a fit found no highlight: a Ward lobe of alpha 1 spreads over the whole hemisphere, and what it
    models there (a grazing brightening from the lobe's ``1 / sqrt(cos_i cos_o)``) is the diffuse
    model's own error. The synthetic ``matte`` scene (rho_s 0 in colour and IR; session 26) fitted
    alpha 1.000 with IR rho_s 0.046, and the colour pass then kept a false lobe of rho_s 0.004, 0.001,
    0.002 at held-out z 5.2. So the model ladder's first rung takes such a cluster as diffuse.
    """
    from .ward_fit import ALPHA_MAX

    return np.asarray(alpha, np.float64).reshape(-1) >= ALPHA_MAX * (1 - 1e-6)


def _ir_lobes(ir, k: int) -> np.ndarray:
    """(k,) names of the IR clusters' lobes (``ir["lobe"]``; Ward where the IR arrays have none)."""
    out = np.full(k, "ward", dtype="<U8")
    if ir is not None and "lobe" in ir:
        lb = np.asarray(ir["lobe"], str).reshape(-1)[:k]
        out[:len(lb)] = lb
    return out


#: stages the runner reports (a pass may hold two stages: geometry = fusion then IR)
STAGES = ("ir-calibration", "environment", "geometry", "ir", "rgb", "export", "done")


@dataclass
class ScanConfig:
    """Quality knobs of a scan (the bench sweeps these; defaults sit on its Pareto front).

    Attributes
    ----------
    n_points : int
        Points sampled on the object's surface (§4.1; paper 100K).
    voxel_m : float or None
        TSDF voxel size; None chooses it from the object box.
    hbsab_n : int
        HBSAB square side (§5.1).
    envmap_n : int
        Environment map square side (paper 2 x 128^2).
    k_clusters : int or None
        Number of specular clusters (§5.2); None chooses automatically.
    rho_d_percentile : float
        Percentile of L/D taken as rho_d (Eq. 6; paper: 10th).
    rho_d_bins : int
        Per-point histogram size for rho_d.
    rho_d_estimator : {"lsq", "percentile"}
        rho_d and rho_s by the joint least squares of Eq. 5 (default) or by the paper's Eq. 6 + 8
        (:class:`appfusion.rgb_pass.RGBPass`).
    rho_d_pool_k, rho_d_pool_z : int, float
        The final rho_d of each point is pooled with those of its ``rho_d_pool_k`` nearest points of
        the same cluster that agree within ``rho_d_pool_z`` standard errors, weighted by inverse
        variance (:func:`appfusion.rgb_pass.denoise_rho_d`; ``lsq`` only; ``rho_d_pool_k`` 0 or 1:
        off). Each point's own estimate scatters by its samples' noise; edges that stand out of the
        noise are kept.
    rho_d_clip_correction : bool
        Correct each point's least-squares rho_d for the sensor noise clipped at black in its dark
        channels, from the fraction of its samples (pooled with its 31 nearest points) that read 0
        (:func:`appfusion.rgb_pass.clipped_mean_factor`; ``lsq`` only; docs/rgb-pass.md §5h).
    rgb_split : bool
        Let the RGB pass split off the part of an IR cluster that shows far less specular reflection
        in colour (:meth:`appfusion.rgb_pass.RGBPass.split_by_specular`).
    rgb_colour_regions : bool
        After the split, let a point whose own neighbourhood cannot tell the clusters' colour models
        apart take the model its whole colour region fits best
        (:func:`appfusion.rgb_pass.colour_regions`; beyond the paper).
    near_field : bool
        Light the object with the support plane as seen from each point (black paper, the white
        circles, the object's shadow on them: :mod:`appfusion.near_field`) instead of as the mirror
        ball saw it, in D and S of Eq. 5 (beyond the paper's distant-light model, §3).
    near_field_final_samples : int
        Lobe samples of the support plane's ``dS`` (:meth:`appfusion.near_field.SupportPlaneLight.delta_S`)
        in the RGB pass's offline re-sweeps (the second and third sweeps over the recording); the
        live first sweep keeps 4 for its update rate. Monte Carlo noise in S is noise in the
        regressor of rho_s, which dilutes the slope: the demo's matte label (truth 0.03) read 0.026,
        0.025, 0.020 with 4 samples, 0.029, 0.029, 0.024 with 9 and 0.031, 0.032, 0.025 with 16
        (``docs/rgb-pass.md`` §5c). Rounded to a square (k x k).
    rho_s_replicate : int
        Lobe samples of a second, independent ``dS`` estimate per RGB sample in the offline re-sweeps
        (:attr:`appfusion.rgb_pass.RGBPass.s_replicate`; the live first sweep keeps its update rate, as
        with ``near_field_final_samples``): rho_s's denominator becomes the covariance of the two
        estimates, which the Monte Carlo noise does not inflate, so the slope is not diluted (the
        demo's label with 800 colour frames, truth 0.03: 0.025, 0.026, 0.022 without, 0.029, 0.030,
        0.026 with; ``docs/rgb-pass.md`` §5k). It costs ~15 % of a re-sweep. 0: the plain slope.
    rho_s_footprint : bool
        Model the pixel footprint's blur of the print in rho_s's regression in the offline re-sweeps
        (:attr:`appfusion.rgb_pass.RGBPass.footprint`): a sample averages the albedo over its pixel's
        footprint, which changes with the view, and on a printed label that change goes with S (the
        demo label's darkest quarter read -0.06, its brightest +0.09, for 0.03). The blur's constant is
        fitted with rho_s; it costs ~7 % of a re-sweep and 216 bytes a point (``docs/rgb-pass.md`` §5l).
    map_blur_correction : bool
        Read S against the captured map at each lobe's effective roughness
        (:func:`appfusion.envmap.effective_alpha`, with the map's own blur ``blur_var_rad2``): a sharp
        lobe would otherwise see the lights widened by the ball image's pixels, and rho_s come out
        high (beyond the paper).
    diffuse_tau : float or None
        rho_d by the least squares of Eq. 5 with each sample weighted by ``1 / (1 + (S / (tau D))^2)``
        (diffuse-dominated views count most, as Eq. 6's minimum intends); None: unweighted.
    rgb_sampling : {"nearest", "bilinear"}
        How an RGB sample reads the image where its point projects (the nearest pixel, or bilinear
        between the four around it; :class:`appfusion.rgb_pass.RGBPass`). Bilinear helped the demo's
        rho_d a little and cost the 320 x 240 small scan its labels (``docs/rgb-pass.md`` §6).
    refine_poses : bool
        Re-register each depth frame of the IR pass (and of a combined IR + RGB pass) to the final mesh
        before its samples are taken (:class:`appfusion.geometry_pass.PoseRefiner`; beyond the
        paper): tracking's poses are relative to the model fused so far.
    refuse_geometry : bool
        After tracking, re-register every geometry frame to the object fused from all of them with
        its circle centres as anchors, and fuse the frames again at those poses
        (:meth:`appfusion.geometry_pass.GeometryPass.refuse`; beyond the paper). Demo: relit error
        0.072 -> 0.051, the scan ~7 s longer.
    refuse_rounds : int
        Rounds of that re-registration and fusion (each reads the geometry frames again). Each round
        ends by fusing the circle centres again at its poses (:meth:`appfusion.markers.MarkerTracker.refit`),
        so a second round is anchored to better centres and registers to a better mesh: relit on
        seed 1 / seed 3 / demo 0.049 / 0.061 / 0.044 -> 0.043 / 0.052 / 0.038, normals 0.087 /
        0.094 / 0.093 -> 0.082 / 0.082 / 0.083 deg, ~16 s more on the demo (session 13, with the
        anchors weighted by elevation, an idea since dropped). 1 by default: with two rounds the
        demo's IR clustering took k = 2 (excess ratio 2.31 against
        ``split_gain`` 2.0, 3.0 since) with a spurious alpha = 0.86 cluster, and its labels came out
        at 0.905 and the scan at 257 s (docs/geometry-pass.md); not measured again since.
    refuse_voxel_scale : float
        Voxel of the re-fusion at the re-registered poses, as a fraction of tracking's (session 14;
        in [0.25, 1]). 1 (default) keeps tracking's voxel. 2/3 (2 mm where tracking fuses at 3 mm;
        tracking itself at 2 mm lost frames) keeps more of a sharp rim's shape, where the sun's glints
        sit: relit on the pepper 0.370 -> 0.204, vase 0.244 -> 0.230, demo 0.0387 -> 0.0315; but
        seed 3 0.057 -> 0.080 and the sphere 0.018 -> 0.021, and the normals' median rose on the
        capsules and the sphere (demo 0.085 -> 0.109 deg), so it is not the default; since session
        17 ``refuse_fine_scale`` applies it where the object curves tightly.
    refuse_fine_scale : float or None
        The re-fusion's voxel scale where the object curves tightly (session 17;
        ``GeometryConfig.refuse_fine_scale``): with ``refuse_voxel_scale`` 1, if at least 1 % of the
        first mesh's vertices curve tighter than 6.5 voxels (pepper 2.2 %, vase 2.8 %, the capsules
        none), the re-fusion runs at this fraction of tracking's voxel (2/3: 2 mm for 3). None: never.
    refuse_fine_trunc_voxels : float or None
        The re-fusion's truncation where the object curves tightly (``refuse_fine_scale`` applies) and
        at least ``refuse_fine_trunc_min_frames`` frames are re-fused, unless ``refuse_trunc_voxels``
        is given (session 26; ``GeometryConfig``; default 2 since session 30; None: 4). 2 removes the
        vase's neck bulge below its lid; 200 frames a pass, 4 -> 2: vase relit 0.134 -> 0.115, pepper
        0.200 -> 0.197 (rho_d 3.06 -> 2.87 %).
    refuse_fine_trunc_min_frames : int
        Frames re-fused below which the fine truncation is not applied (default 60): on a few noisy
        frames the fine re-fusion triggers on the noise, and a 12-frame sphere's alpha read 0.180 for
        0.12 at 2 voxels.
    refuse_trunc_voxels : float or None
        Truncation of that re-fusion in voxels (session 17; :class:`appfusion.geometry_pass.GeometryConfig`);
        None (default): tracking's 4, or ``refuse_fine_trunc_voxels`` where the object curves
        tightly. A ray that hits an overhanging edge writes "behind the surface" into the free space
        under it for a truncation's length: the vase's neck bulged 1.5-2.4 mm below its lid at 4
        voxels, 0.15-0.4 mm at 2. Relit at 4 / 3 / 2 voxels (one run each):
        demo 0.0387 / 0.0384 / 0.0352, seed 3 0.057 / 0.058 / 0.066, vase (creases sharpened) 0.162 /
        0.183 / 0.145; so not the default (docs/geometry-pass.md).
    crease_radius_voxels : float or None
        Normals near sharp creases from one-sided plane fits (:func:`appfusion.points.sharpen_creases`;
        session 17), within this many voxels; None: off. No point of the capsules qualifies.
    plane_snap : bool
        Points on large planar faces, up to their rounded edges, take the face's plane normal
        (:func:`appfusion.points.snap_planes`; session 26): the vase's lid drooped at its rim and its
        normals tilted 4-11 degrees there; relit 0.157 -> 0.138 in a full scan
        (docs/geometry-pass.md). No face is found on the capsules, the sphere or the pepper.
    normal_refine_rounds : int or None
        Sweeps of specular normal refinement after the RGB pass (:mod:`appfusion.normal_refine`;
        beyond the paper): each glossy point's normal moves to the candidate whose highlights fit its
        RGB samples significantly better, the candidates' tilt halved each round. 0: off. None
        (default): 3 where the geometry pass's fine re-fusion fired (the object curves tighter than
        its voxel: the pepper's dimple, the vase's rim) over at least ``refuse_fine_trunc_min_frames``
        frames, else 0 (the capsules, the sphere: their TSDF normals are right to 0.1 degrees and the
        refinement tilted them; docs/rgb-pass.md §5f). Session 31, fresh 200-frame scans: pepper
        relit 0.197 -> 0.129, rho_d 2.88 % either way. A first round whose median move reaches the
        outer ring is undone (the vase's body, the demo capsule's shoulder: right normals pulled by
        the highlights' registration), so the vase keeps 0.133.
    normal_refine_jet_residual : float or None
        Where the normals are cubic jet fits (``GeometryConfig.jet_radius``: the pepper, the vase),
        the refinement's first round considers only the points whose fit left a residual over this
        many times the median (a rim or ridge the cubic does not describe; session 32). Pepper (200
        frames a pass): relit 0.0755 without refinement, 0.0836 refining every point (its body's
        glints got worse: views 2 and 3 0.052 -> 0.077, 0.039 -> 0.076), **0.0637** refining the
        13913 points over 1.5 times the median (view 1, the grazing top around the stem, 0.129 ->
        0.101; views 2 and 3 unchanged); 0.0751 over 2 times (4154 points). None: every point.
    normal_refine_deg : float
        Largest tilt of the first round's candidates, degrees (rings at this and at half of it).
    normal_refine_screen : float or None
        The first round refines only the glossy points whose residual variance is over this many times
        the median (:class:`appfusion.normal_refine.NormalRefiner`'s ``screen``); None: all of them.
    normal_refine_min_gain : float
        Fraction of a point's residual a move must explain (``NormalRefiner``'s ``min_gain``).
    ir_rim_m : float
        Points within this distance of the fused surface's open boundary (where the object box cut it
        off the support plane) stay out of the IR pass's Ward fits (``rim`` of
        :class:`appfusion.brdf_cut.BRDFCut`); 0 keeps them.
    ir_lobes : tuple of str
        The lobes the IR fits may choose between per cluster (:data:`appfusion.brdf.LOBES`; the model
        ladder's Ward and GGX rungs, :func:`appfusion.ward_fit.choose_lobe`): GGX is kept only where
        it lowers the HBSAB fit's chi-square by 5 % and 25 of its reduced chi-squares. ``("ward",)``:
        the paper's model only.
    ir_interior_m : float
        The colour pass's refits of the IR lobes to its clusters read only the points farther than this
        from another cluster (metres; :func:`appfusion.points.interior_mask`): along a seam a label
        point's IR pixels include the paint's sharp highlight. Seed 1's label (truth 0.35) refitted
        0.319 with every point, 0.3225 even with the true labels, 0.337 at 5 mm and 0.340 at 10 mm
        on one geometry (end to end 0.319-0.324 -> 0.327-0.329). 0 uses every point.
    ir_pattern : bool
        Calibrate the IR emitter's fixed pattern from the calibration sheet and divide it out of every
        IR sample (:mod:`calibration.ir_pattern`; beyond the paper's stationary-noise model, §6).
    frame_stride : int
        Use every n-th frame of each pass.
    ball_radius_m : float or None
        Mirror-ball radius if known (else the session meta's ``extra.ball_radius_m``, else fitted).
    ball_max_scatter : float
        Largest RMS scatter of the ball's depth points about the fitted sphere, relative to its
        radius: a mirror returns weak, noisy depth (§4.3), so this is looser than a matte sphere's.
    mirror_reflectance : float or None
        Reflectance of the mirror ball (divided out of the environment map); None: the session's
        ``extra.mirror_ball.reflectance``, else 1.0. A real chrome ball reflects ~0.6-0.7: give it, or
        every rho_d comes out that much too low.
    ball_on_plane : bool, "auto" or None
        The ball rests on the marker plane (centre height = radius): True, False, "auto" (when the
        free fit agrees), None: the session's ``extra.mirror_ball.on_plane``, else "auto".
    box_height_m : float
        Height of the object box above the marker plane.
    texture_size : int
        Side of the exported texture maps.
    snapshot_interval_s : float
        Minimum time between two published snapshots.
    """

    n_points: int = 100_000
    voxel_m: float | None = None
    hbsab_n: int = 32
    envmap_n: int = 128
    k_clusters: int | None = None
    rho_d_percentile: float = 10.0
    rho_d_bins: int = 64
    rho_d_estimator: str = "lsq"
    rho_d_pool_k: int = 32
    rho_d_pool_z: float = 2.5
    rho_d_clip_correction: bool = True
    rgb_split: bool = True
    rgb_colour_regions: bool = True
    rgb_resweep: bool = True
    near_field: bool = True
    near_field_final_samples: int = 16
    rho_s_replicate: int = 4
    rho_s_footprint: bool = True
    map_blur_correction: bool = True
    diffuse_tau: float | None = 0.25
    rgb_sampling: str = "nearest"
    refine_poses: bool = True
    refuse_geometry: bool = True
    refuse_rounds: int = 1
    refuse_voxel_scale: float = 1.0
    refuse_fine_scale: float | None = 2.0 / 3.0
    refuse_trunc_voxels: float | None = None
    refuse_fine_trunc_voxels: float | None = 2.0
    refuse_fine_trunc_min_frames: int = 60
    crease_radius_voxels: float | None = 2.5
    plane_snap: bool = True
    normal_refine_rounds: int | None = None
    normal_refine_jet_residual: float | None = 1.5
    normal_refine_deg: float = 3.0
    normal_refine_screen: float | None = None
    normal_refine_min_gain: float = 0.0
    ir_rim_m: float = 0.004
    ir_lobes: tuple = ("ward", "ggx")
    ir_interior_m: float = 0.005
    ir_pattern: bool = True
    frame_stride: int = 1
    ball_radius_m: float | None = None
    mirror_reflectance: float | None = None
    ball_on_plane: bool | str | None = None
    ball_max_scatter: float = 0.2
    box_height_m: float = 0.30
    texture_size: int = 1024
    snapshot_interval_s: float = 0.1

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


#: The checkpointed stages and the stages whose output each one takes (directly or not). A stage's
#: checkpoint is reused only while the configuration fields of the stage and of its upstream
#: (:data:`STAGE_CONFIG`), the given map or IR profile they take, the recording and the engine
#: version are what they were, and no upstream stage was recomputed in this run; a stage that is
#: not upstream of another never invalidates it (a new environment map recomputes the colour stage
#: only, a colour option keeps the geometry, the IR clusters and the map).
STAGE_UPSTREAM = {
    "ir-calibration": (),
    "environment": (),
    "geometry": (),
    "ir": ("ir-calibration", "geometry"),
    "rgb": ("ir-calibration", "environment", "geometry", "ir"),
}

#: The :class:`ScanConfig` fields each stage's result depends on (its own; a stage's checkpoint key
#: also holds its upstream's). The environment pass tracks the camera with the geometry pass's
#: tracker and object box, so it keys on the geometry's fields as well. Every field is listed under
#: a stage or in :data:`UNKEYED_CONFIG` (a test checks this), so a new field must say which.
_GEOMETRY_FIELDS = ("frame_stride", "n_points", "voxel_m", "box_height_m", "refuse_geometry", "refuse_rounds",
                    "refuse_voxel_scale", "refuse_fine_scale", "refuse_trunc_voxels", "refuse_fine_trunc_voxels",
                    "refuse_fine_trunc_min_frames", "crease_radius_voxels", "plane_snap")
STAGE_CONFIG = {
    "ir-calibration": ("frame_stride", "ir_pattern"),
    "environment": _GEOMETRY_FIELDS + ("envmap_n", "ball_radius_m", "mirror_reflectance", "ball_on_plane",
                                       "ball_max_scatter"),
    "geometry": _GEOMETRY_FIELDS,
    "ir": ("hbsab_n", "k_clusters", "ir_rim_m", "ir_lobes", "ir_interior_m", "refine_poses"),
    "rgb": ("rho_d_percentile", "rho_d_bins", "rho_d_estimator", "rho_d_pool_k", "rho_d_pool_z",
            "rho_d_clip_correction", "rgb_split", "rgb_colour_regions", "rgb_resweep", "near_field",
            "near_field_final_samples", "rho_s_replicate", "rho_s_footprint", "map_blur_correction", "diffuse_tau",
            "rgb_sampling", "normal_refine_rounds", "normal_refine_jet_residual", "normal_refine_deg",
            "normal_refine_screen", "normal_refine_min_gain"),
}
#: Fields no checkpoint depends on: the export's texture size and the GUI's snapshot rate.
UNKEYED_CONFIG = ("texture_size", "snapshot_interval_s")


def stage_closure(stage: str) -> tuple[str, ...]:
    """``stage`` and every stage upstream of it (:data:`STAGE_UPSTREAM`), in the order they run."""
    up = set(STAGE_UPSTREAM[stage]) | {stage}
    return tuple(s for s in STAGE_UPSTREAM if s in up)


def stage_config(config: ScanConfig, stage: str) -> dict[str, Any]:
    """The configuration ``stage``'s checkpoint is keyed on: the fields of the stage and of its
    upstream (:data:`STAGE_CONFIG`), as JSON values."""
    cfg = config.to_json()
    names = sorted({f for s in stage_closure(stage) for f in STAGE_CONFIG[s]})
    return {k: cfg[k] for k in names}


def _digest(*parts) -> str:
    """A short content hash of arrays and JSON-able values (the given map or IR profile of a scan)."""
    import hashlib

    h = hashlib.blake2b(digest_size=12)
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _key_change(old, new: str) -> str:
    """What differs between a stored checkpoint key ``old`` and the key ``new`` a stage has now
    (:meth:`ScanRunner._checkpoint_key`), in words."""
    try:
        was = json.loads(old)
    except (TypeError, ValueError):
        was = None
    if not isinstance(was, dict) or "stage" not in was:
        return "a key this engine does not read (an older engine's, keyed another way)"
    now = json.loads(new)
    if was.get("engine") != now["engine"]:
        return f"engine version {was.get('engine')} (this one is {now['engine']})"
    if was.get("source") != now["source"]:
        return "another recording"
    what = []
    cfg0, cfg1 = was.get("config") or {}, now["config"]
    changed = [k for k in sorted(set(cfg0) | set(cfg1)) if cfg0.get(k, "(unset)") != cfg1.get(k, "(unset)")]
    if changed:
        what.append("another configuration (" + ", ".join(
            f"{k} {cfg0.get(k, '(unset)')!r} -> {cfg1.get(k, '(unset)')!r}" for k in changed[:4])
            + (f", and {len(changed) - 4} more" if len(changed) > 4 else "") + ")")
    g0, g1 = was.get("given") or {}, now["given"]
    for k, name in (("envmap", "environment map"), ("ir_profile", "IR profile")):
        if g0.get(k) != g1.get(k):
            what.append(f"another given {name}" if g1.get(k) and g0.get(k) else
                        (f"a given {name} (none now)" if g0.get(k) else f"no given {name} (one now)"))
    return " and ".join(what) or "another key"


@dataclass
class Snapshot:
    """What the engine looks like now: small copies the GUI may keep and draw.

    Attributes
    ----------
    stage : str
        One of :data:`STAGES`.
    frame : int
        Frames processed in this stage so far; ``frames_total`` the stage's total (0 if unknown/live).
    fps : dict
        Frames per second of each stage's processing, measured.
    tracking : str
        "ok", "lost" or "n/a" (no tracking in this stage).
    markers_visible : int
        White circles seen in the last frame (0-4).
    last_frame : Frame or None
        The last frame processed (its images feed the stream views).
    positions, normals : (P, 3) float32 or None
        Sampled points once the geometry is fused.
    labels : (P,) int32 or None; rho_d : (P, 3) or None
    alpha, alpha_sigma : (C,) or None; rho_s : (C, 3) or None
    lobes : list of str or None
        The lobe each cluster's alpha belongs to, "ward" or "ggx" (the IR fit's choice).
    rho_s_sigma : (C, 3) or None
        Standard error of each cluster's rho_s per channel (``RGBResult.rho_s_sigma``, docs/rgb-pass.md
        §5i); NaN where unknown (the ``percentile`` estimator, a cluster without samples).
    envmap : (2, N, N, 3) float32 or None; env_coverage : (2, N, N) bool or None
    hbsabs : list of (n, n) float arrays per cluster, or None; hbsab_fits : same with the fitted lobes
    guidance : str
        What the user should do next (shown by the GUI).
    messages : list of str
        Warnings and notes so far (lost tracking, frames without markers, ...).
    """

    stage: str = "ir-calibration"
    frame: int = 0
    frames_total: int = 0
    fps: dict[str, float] = field(default_factory=dict)
    tracking: str = "n/a"
    markers_visible: int = 0
    last_frame: Frame | None = None
    positions: np.ndarray | None = None
    normals: np.ndarray | None = None
    labels: np.ndarray | None = None
    rho_d: np.ndarray | None = None
    alpha: np.ndarray | None = None
    alpha_sigma: np.ndarray | None = None
    lobes: list | None = None
    rho_s: np.ndarray | None = None
    rho_s_sigma: np.ndarray | None = None
    envmap: np.ndarray | None = None
    env_coverage: np.ndarray | None = None
    hbsabs: list | None = None
    hbsab_fits: list | None = None
    guidance: str = ""
    messages: list[str] = field(default_factory=list)
    history: dict[str, list] = field(default_factory=dict)


GUIDANCE = {
    "ir-calibration": "Cover the emitter for the dark frames, then hold a white sheet at 50-120 cm.",
    "environment": "Place the mirror ball inside the markers and orbit it slowly, keeping the circles in view.",
    "geometry": "Replace the ball by the object and orbit it at 40-100 cm, at several heights down to the "
                "table (each side shows its IR highlight only from near its own height); watch the model fill in.",
    "ir": "Keep orbiting: the IR highlights are being fused into the material clusters.",
    "rgb": "Orbit once more with the colour camera; rho_d and rho_s converge as views accumulate.",
    "export": "Writing the mesh, textures and report.",
    "done": "Done: open the report or export again.",
}


def plan_passes(source) -> dict[str, tuple[int, int]]:
    """Frame index ranges ``[start, stop)`` of each pass in a recording.

    Sessions of our format say where each pass starts (``pass`` events). Recordings without pass
    events (TUM, Redwood, Azure Kinect) are one ``scan`` pass. Raises :class:`PassMissingError` for
    a live source (it has no ranges: passes follow the user).
    """
    if not getattr(source, "is_recording", False):
        raise PassMissingError("a live source has no recorded passes; the runner follows next_pass()")
    n = len(source)
    events = [e for e in getattr(source, "events", []) if e[1] == "pass"]
    if not events:
        return {"scan": (0, n)} if n else {}
    times = np.asarray(source.timestamps() if callable(getattr(source, "timestamps", None)) else source.timestamps)
    ev_t = np.array([e[0] for e in events])
    # pass of each frame = last pass event at or before its time (frames before the first event: none)
    which = np.searchsorted(ev_t, times + 1e-9, side="right") - 1
    ranges: dict[str, tuple[int, int]] = {}
    for k, (t, _, name) in enumerate(events):
        idx = np.flatnonzero(which == k)
        if len(idx) == 0:
            continue
        if name in ranges:  # a pass recorded twice: keep the longer run
            a, b = ranges[name]
            if b - a >= len(idx):
                continue
        ranges[name] = (int(idx[0]), int(idx[-1]) + 1)
    return ranges


class _Control:
    """Thread-safe pause / stop flags and the live pass selector, set by the GUI and the CLI.

    Live sources: ``live_pass`` tags the frames being recorded, ``live_emitter`` (None: as the device
    says) their emitter state; ``live_left`` frames remain in the current step of a plan
    (:meth:`ScanRunner.set_live_plan`; None: until the next :meth:`ScanRunner.next_pass` or stop) and
    ``live_plan`` holds the steps after it. ``live_gen`` counts changes, so that the recording loop
    applies each (stream selection, emitter control) once, between two frames.
    """

    def __init__(self):
        self.run_event = threading.Event()
        self.run_event.set()
        self.stop_event = threading.Event()
        self.lock = threading.Lock()
        self.live_pass = "environment"
        self.live_emitter: bool | None = None
        self.live_left: int | None = None
        self.live_plan: list[tuple[str, int | None, bool | None]] = []
        self.live_gen = 0

    def set_step(self, name: str, frames: int | None, emitter: bool | None) -> None:
        """Make ``(name, frames, emitter)`` the current live step (call with ``lock`` held)."""
        self.live_pass = name
        if emitter is not None:
            self.live_emitter = bool(emitter)
        self.live_left = frames
        self.live_gen += 1

    def wait_if_paused(self) -> bool:
        """Block while paused; returns False once a stop was asked for."""
        while not self.run_event.wait(0.05):
            if self.stop_event.is_set():
                return False
        return not self.stop_event.is_set()


def _read_npz(path) -> dict[str, np.ndarray]:
    """Every array of a checkpoint ``.npz``, read whole (a damaged file fails here, not in a stage)."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _stack_images(images: list | None) -> np.ndarray:
    """Per-cluster images (each (n, n) or None) as one (k, n, n) float32 array for a checkpoint; a
    missing image is all NaN; no images at all: shape (0, 0, 0)."""
    imgs = [None if im is None else np.asarray(im, np.float32) for im in (images or [])]
    shapes = {im.shape for im in imgs if im is not None}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        return np.zeros((0, 0, 0), np.float32)
    shape = shapes.pop()
    return np.stack([np.full(shape, np.nan, np.float32) if im is None else im for im in imgs])


def _unstack_images(stack: np.ndarray | None) -> list:
    """Inverse of :func:`_stack_images`: a list with None for the all-NaN images ([] for none)."""
    if stack is None or stack.ndim != 3 or not len(stack):
        return []
    return [None if not np.isfinite(im).any() else im for im in stack]


class ScanRunner:
    """Runs a whole scan over one source; the GUI and the CLI drive it.

    Parameters
    ----------
    source : Source
        A recording (passes from its events) or a live device (passes from :meth:`next_pass`).
    out_dir : path-like
        Where the result, the checkpoints (``state/``) and the exports go.
    config : ScanConfig, optional
    envmap : EnvMap, path or None
        A previously captured environment map for the same markers (§4.3): the environment pass is
        skipped (and its frames ignored) when given.
    ir_profile : path, IR profile or None
        A saved IR device profile (§6); the ir-calibration pass is skipped when given.
    log : callable
        Receives one-line progress messages.
    progress : bool
        Show progress bars on stderr.

    Notes
    -----
    Contract used by the GUI: :meth:`subscribe`, :meth:`run` (blocking; call it in a worker thread),
    :meth:`pause`, :meth:`resume`, :meth:`stop`, :meth:`next_pass`, :meth:`paint`, :meth:`undo_paint`,
    :meth:`result`, :meth:`snapshot`, :meth:`export`.
    """

    def __init__(self, source, out_dir, config: ScanConfig | None = None, envmap=None, ir_profile=None,
                 log: Callable[[str], None] | None = None, progress: bool = False):
        self.source = source
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise AppFusionError(f"{self.out_dir}: the scan's output folder is an existing file; "
                                 f"give a folder (new or one of an earlier scan)")
        self.config = config or ScanConfig()
        if not 0.25 <= float(self.config.refuse_voxel_scale) <= 1.0:
            raise AppFusionError(f"scan config: refuse_voxel_scale must be in [0.25, 1] (the re-fusion's voxel "
                                 f"as a fraction of tracking's), got {self.config.refuse_voxel_scale}")
        if self.config.refuse_geometry and not int(self.config.refuse_rounds) >= 1:
            raise AppFusionError(f"scan config: refuse_rounds must be at least 1 (refuse_geometry=False turns the "
                                 f"re-registration off), got {self.config.refuse_rounds}")
        c = self.config
        from .brdf import LOBES

        lobes = (c.ir_lobes,) if isinstance(c.ir_lobes, str) else tuple(c.ir_lobes or ())
        if not lobes or any(str(x) not in LOBES for x in lobes):
            raise AppFusionError(f"scan config: ir_lobes must name one or more lobes among {LOBES}, got {c.ir_lobes!r}")
        self._ir_lobe_names = tuple(str(x) for x in lobes)          # what the IR fits choose between
        if not (isinstance(c.texture_size, (int, np.integer)) and 16 <= int(c.texture_size) <= 16384):
            raise AppFusionError(f"scan config: texture_size (side of the exported texture maps, texels) must be an "
                                 f"integer in [16, 16384], got {c.texture_size!r}")
        if not (isinstance(c.n_points, (int, np.integer)) and int(c.n_points) >= 1):
            raise AppFusionError(f"scan config: n_points (points sampled on the surface) must be a positive "
                                 f"integer, got {c.n_points!r}")
        if c.k_clusters is not None and not (isinstance(c.k_clusters, (int, np.integer)) and int(c.k_clusters) >= 1):
            raise AppFusionError(f"scan config: k_clusters must be None (automatic) or a positive integer, "
                                 f"got {c.k_clusters!r}")
        if not (isinstance(c.frame_stride, (int, np.integer)) and int(c.frame_stride) >= 1):
            raise AppFusionError(f"scan config: frame_stride must be a positive integer (1: every frame), "
                                 f"got {c.frame_stride!r}")
        if c.ball_radius_m is not None and not (np.isfinite(float(c.ball_radius_m)) and float(c.ball_radius_m) > 0):
            raise AppFusionError(f"scan config: ball_radius_m must be None (fitted) or a positive radius in "
                                 f"metres, got {c.ball_radius_m!r}")
        if c.refuse_fine_scale is not None and not 0.25 <= float(c.refuse_fine_scale) <= 1.0:
            raise AppFusionError(f"scan config: refuse_fine_scale must be None or in [0.25, 1], got {c.refuse_fine_scale}")
        if not (isinstance(c.near_field_final_samples, (int, np.integer)) and 1 <= int(c.near_field_final_samples) <= 256):
            raise AppFusionError("scan config: near_field_final_samples must be an integer in [1, 256] (lobe samples of "
                                 f"the support plane's dS in the RGB re-sweeps), got {c.near_field_final_samples!r}")
        if not (isinstance(c.rho_s_replicate, (int, np.integer)) and not isinstance(c.rho_s_replicate, bool)
                and 0 <= int(c.rho_s_replicate) <= 256):
            raise AppFusionError("scan config: rho_s_replicate must be an integer in [0, 256] (lobe samples of the "
                                 f"second dS estimate that keeps rho_s undiluted; 0: none), got {c.rho_s_replicate!r}")
        for name in ("rho_s_footprint", "plane_snap", "rho_d_clip_correction"):
            if not isinstance(getattr(c, name), (bool, np.bool_)):
                raise AppFusionError(f"scan config: {name} must be True or False, got {getattr(c, name)!r}")
        if not (isinstance(c.rho_d_pool_k, (int, np.integer)) and 0 <= int(c.rho_d_pool_k) <= 1024):
            raise AppFusionError("scan config: rho_d_pool_k must be an integer in [0, 1024] (neighbours a point's "
                                 f"rho_d is pooled with; 0 or 1: off), got {c.rho_d_pool_k!r}")
        if not (isinstance(c.rho_d_pool_z, (int, float, np.integer, np.floating)) and 0 < float(c.rho_d_pool_z) < np.inf):
            raise AppFusionError("scan config: rho_d_pool_z must be a positive number of standard errors, got "
                                 f"{c.rho_d_pool_z!r}")
        if c.rgb_sampling not in ("nearest", "bilinear"):
            raise AppFusionError(f"scan config: rgb_sampling must be 'nearest' or 'bilinear', got {c.rgb_sampling!r}")
        if not (isinstance(c.refuse_fine_trunc_min_frames, (int, np.integer)) and c.refuse_fine_trunc_min_frames >= 0):
            raise AppFusionError("scan config: refuse_fine_trunc_min_frames must be an integer >= 0, got "
                                 f"{c.refuse_fine_trunc_min_frames!r}")
        for name in ("refuse_trunc_voxels", "refuse_fine_trunc_voxels", "crease_radius_voxels"):
            v = getattr(c, name)
            if v is not None and not (np.isfinite(float(v)) and 1.0 <= float(v) <= 8.0):
                raise AppFusionError(f"scan config: {name} must be None or in [1, 8] voxels, got {v}")
        if not ((c.normal_refine_rounds is None or int(c.normal_refine_rounds) >= 0)
                and 0 < float(c.normal_refine_deg) <= 20
                and 0 <= float(c.normal_refine_min_gain) < 1
                and (c.normal_refine_screen is None or float(c.normal_refine_screen) > 0)):
            raise AppFusionError(f"scan config: normal refinement needs rounds None or >= 0, 0 < deg <= 20, 0 <= min_gain < 1 "
                                 f"and screen None or > 0; got {c.normal_refine_rounds}, {c.normal_refine_deg}, "
                                 f"{c.normal_refine_min_gain}, {c.normal_refine_screen}")
        self.log = log or (lambda msg: None)
        self.show_progress = progress
        self._ctl = _Control()
        self._subscribers: list[Callable[[Snapshot], None]] = []
        self._snap = Snapshot()
        self._snap_lock = threading.Lock()
        self._last_publish = 0.0
        self._paint_log: list[tuple[np.ndarray, np.ndarray]] = []  # (point_idx, previous labels) for undo
        self._painted: dict[int, int] = {}
        self.timings: dict[str, dict[str, float]] = {}
        self.messages: list[str] = []
        # pass state
        self.ir_profile = self._load_ir_profile(ir_profile)
        self.env = self._load_envmap(envmap)
        # what a given map or IR profile is, for the checkpoint keys of the stages that take them
        self._given = {"envmap": None if self.env is None else _digest(self.env.radiance, self.env.meta),
                       "ir_profile": None if self.ir_profile is None else self._profile_digest(self.ir_profile)}
        self._recomputed: set[str] = set()      # stages recomputed in this run (their downstream follows)
        self.geometry = None      # fusion + tracking state of the object passes
        self.env_geometry = None  # tracking state of the environment pass
        self.lighting = None
        self.ir = None
        self.rgb = None
        self.points: tuple[np.ndarray, np.ndarray] | None = None
        self.mesh: tuple[np.ndarray, np.ndarray] | None = None
        self.poses: dict[int, np.ndarray] = {}
        #: each geometry point's jet fit residual over the median (GeometryPass.jet_residual; None: no jets)
        self.jet_residual: np.ndarray | None = None
        self._result = None
        self._refiner = None                  # PoseRefiner of the final mesh, built on first use
        self._refined: dict[int, np.ndarray] = {}   # frame index -> pose re-registered to the mesh

    # -- control (thread-safe; called from the GUI thread) -------------------------------------------
    def subscribe(self, callback: Callable[[Snapshot], None]) -> None:
        """Call ``callback(snapshot)`` (from the worker thread) whenever the state changes, rate-limited."""
        self._subscribers.append(callback)

    def pause(self) -> None:
        self._ctl.run_event.clear()

    def resume(self) -> None:
        self._ctl.run_event.set()

    def stop(self) -> None:
        """Stop after the current frame; everything computed so far is kept (see :meth:`result`)."""
        self._ctl.stop_event.set()
        self._ctl.run_event.set()

    @property
    def paused(self) -> bool:
        return not self._ctl.run_event.is_set()

    @property
    def stopped(self) -> bool:
        return self._ctl.stop_event.is_set()

    def next_pass(self, name: str | None = None, emitter: bool | None = None) -> str:
        """Live sources: move to pass ``name`` (or the next one in :data:`PASSES`); returns it.

        The device's streams switch to what the pass needs before the next frame (a Kinect v1:
        depth + IR for ``ir-calibration`` / ``geometry``, depth + RGB for ``environment`` / ``rgb``).
        ``emitter`` (optional) tags the frames from now on as emitter off (False: the §6 background
        frames; a device with an emitter control is switched, on a Kinect v1 the user covers it) or
        on (True). A plan given to :meth:`set_live_plan` is dropped: the caller drives the passes.
        """
        with self._ctl.lock:
            if name is None:
                order = [p for p in PASSES if p != "scan"]
                i = order.index(self._ctl.live_pass) if self._ctl.live_pass in order else -1
                name = order[min(i + 1, len(order) - 1)]
            if name not in PASSES:
                raise AppFusionError(f"unknown pass {name!r}; passes are {', '.join(PASSES)}")
            self._ctl.live_plan = []
            self._ctl.set_step(name, None, emitter)
        return name

    def set_live_plan(self, steps) -> None:
        """Live sources: record these steps one after another, each for a number of frames.

        Parameters
        ----------
        steps : sequence of (pass, frames, emitter)
            ``pass`` one of :data:`PASSES`; ``frames`` >= 1, or None for the last step only (until
            :meth:`stop`); ``emitter`` as in :meth:`next_pass` (None: unchanged). The recording ends
            after the last step's frames and the recording is processed.
        """
        steps = [(str(n), None if f is None else int(f), None if e is None else bool(e)) for n, f, e in steps]
        if not steps:
            raise AppFusionError("live plan: no steps given")
        for k, (name, frames, _) in enumerate(steps):
            if name not in PASSES:
                raise AppFusionError(f"live plan: unknown pass {name!r}; passes are {', '.join(PASSES)}")
            if frames is None and k != len(steps) - 1:
                raise AppFusionError(f"live plan: step {k + 1} ({name}) needs a frame count (only the last "
                                     f"step may run until stopped)")
            if frames is not None and frames < 1:
                raise AppFusionError(f"live plan: step {k + 1} ({name}) must last at least 1 frame, got {frames}")
        with self._ctl.lock:
            self._ctl.live_plan = steps[1:]
            self._ctl.set_step(*steps[0])

    def paint(self, point_idx, label: int) -> int:
        """Manual cluster refinement (§5.2): give points a cluster label that re-clustering keeps.

        Returns the number of points changed. Undo with :meth:`undo_paint`.
        """
        idx = np.unique(np.asarray(point_idx, dtype=np.int64).ravel())
        if self.points is None:
            raise AppFusionError("nothing to paint yet: the object's points exist after the geometry pass")
        P = len(self.points[0])
        if idx.size and (idx.min() < 0 or idx.max() >= P):
            raise AppFusionError(f"paint: point indices must lie in 0..{P - 1}")
        label = int(label)
        if label < 0:
            raise AppFusionError("paint: cluster labels are >= 0")
        labels = self._current_labels()
        prev = labels[idx].copy()
        self._paint_log.append((idx, prev))
        for i in idx:
            self._painted[int(i)] = label
        self._apply_paint()
        return int(np.sum(prev != label))

    def undo_paint(self) -> bool:
        """Undo the last :meth:`paint`; returns False when there is nothing to undo."""
        if not self._paint_log:
            return False
        idx, prev = self._paint_log.pop()
        for i, p in zip(idx, prev):
            self._painted[int(i)] = int(p)
        self._apply_paint()
        return True

    # -- snapshots --------------------------------------------------------------------------------
    def snapshot(self) -> Snapshot:
        with self._snap_lock:
            return self._snap

    def _publish(self, force: bool = False, **changes) -> None:
        with self._snap_lock:
            snap = Snapshot(**{**self._snap.__dict__, **changes})
            snap.messages = list(self.messages[-50:])
            self._snap = snap
        now = time.perf_counter()
        if not force and now - self._last_publish < self.config.snapshot_interval_s:
            return
        self._last_publish = now
        for cb in list(self._subscribers):
            try:
                cb(snap)
            except Exception as e:  # an observer must never break the scan
                self._note(f"snapshot observer failed: {type(e).__name__}: {e}")

    def _progress_due(self, used: int, every: int) -> bool:
        """Whether a pass should publish its running estimates after ``used`` frames: every ``every``
        frames while someone watches (:meth:`subscribe`, the GUI), else at ``every`` x 1, 2, 4, 8, ...
        frames, enough for the report's convergence plots. The estimates cost 0.7-0.9 s each on the
        demo (the rho_d percentiles of 100k histograms, the IR clusters' fits): 25 s of a headless scan
        when taken every 10-15 frames, ~7 s on the doubling schedule."""
        if used <= 0 or used % every:
            return False
        if self._subscribers:
            return True
        k = used // every
        return k & (k - 1) == 0

    def _note(self, msg: str) -> None:
        if not self.messages or self.messages[-1] != msg:
            self.messages.append(msg)
            self.log(msg)

    # -- checkpoints --------------------------------------------------------------------------------
    @property
    def state_dir(self) -> Path:
        return self.out_dir / "state"

    @staticmethod
    def _profile_digest(profile) -> str:
        pat = getattr(profile, "pattern", None)
        arrays = [np.asarray(getattr(pat, k)) for k in ("values", "counts")] if pat is not None else []
        return _digest(profile.to_json(), *arrays)

    def _checkpoint_key(self, stage: str) -> str:
        """What ``stage``'s checkpoint was computed from: engine version, the configuration of the
        stage and of its upstream (:func:`stage_config`), the map or IR profile given to the runner
        where the stage takes it, the recording (path, frame count, creation time)."""
        src = self.source
        meta = src.meta if isinstance(src.meta, dict) else {}
        ident = {"path": str(getattr(src, "path", getattr(src, "name", ""))),
                 "frames": len(src) if getattr(src, "is_recording", False) else None,
                 "created": meta.get("created")}
        closure = stage_closure(stage)
        given = {"envmap": self._given["envmap"] if "environment" in closure else None,
                 "ir_profile": self._given["ir_profile"] if "ir-calibration" in closure else None}
        return json.dumps({"engine": CHECKPOINT_VERSION, "stage": stage, "config": stage_config(self.config, stage),
                           "given": given, "source": ident}, sort_keys=True, default=str)

    def _stage_done(self, stage: str) -> bool:
        """A valid checkpoint of ``stage`` exists: the same key (:meth:`_checkpoint_key`) and no stage
        upstream of it (:data:`STAGE_UPSTREAM`) recomputed in this run. A stage that will run is
        recorded as recomputed, so that its downstream follows."""
        path = self.state_dir / f"{stage}.done"
        ok = False
        if path.exists() and not self._recomputed.intersection(STAGE_UPSTREAM[stage]):
            try:
                old = json.loads(path.read_text()).get("key")
                why = None
            except (OSError, ValueError, AttributeError) as e:
                old, why = None, f"its record {path.name} is unreadable ({type(e).__name__})"
            key = self._checkpoint_key(stage)
            ok = old == key
            if not ok:
                why = why or f"it was made from {_key_change(old, key)}"
                self._note(f"{stage}: the checkpoint in {self.state_dir} is not reused: {why}; recomputing")
        if not ok:
            self._recomputed.add(stage)
        return ok

    def _reuse(self, stage: str, what: str, path=None, load=None):
        """The checkpoint of ``stage`` (``load(path)``; by default the arrays of ``STAGE.npz``), or None
        when the stage must run: no valid checkpoint, or a file that does not load (a disk that filled,
        a copy cut short: noted, and this stage and those downstream of it are recomputed)."""
        path = self.state_dir / f"{stage}.npz" if path is None else path
        if not self._stage_done(stage):
            return None
        try:
            obj = (load or _read_npz)(path)
        except Exception as e:  # noqa: BLE001 - numpy, zipfile and the loaders raise many types for a bad file
            # a missing file lands here too: recompute this stage and, since it changes, its downstream
            self._note(f"{stage}: the checkpoint {path} is unreadable ({type(e).__name__}: {e}): recomputing")
            self._recomputed.add(stage)
            return None
        self._note(f"{stage}: reusing the checkpointed {what}")
        return obj

    def _done_info(self, stage: str) -> dict:
        """What :meth:`_mark_done` stored beside a stage's key ({} when unreadable)."""
        try:
            info = json.loads((self.state_dir / f"{stage}.done").read_text())
        except (OSError, ValueError):
            return {}
        return info if isinstance(info, dict) else {}

    def _restore_history(self, stage: str, key: str) -> list:
        """The live sweep's running estimates ``history[key]`` that a checkpointed stage kept, back into
        the snapshot (the report's convergence curves of a resumed scan); returns them ([] if none)."""
        h = (self._done_info(stage).get("history") or {}).get(key)
        if not isinstance(h, list):
            return []
        hist = self._snap.history
        hist[key] = [(int(f), v) for f, v in h if isinstance(f, (int, float))]
        return hist[key]

    def _mark_done(self, stage: str, info: dict | None = None) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.state_dir / f"{stage}.done.tmp"
        tmp.write_text(json.dumps({"key": self._checkpoint_key(stage), "config": self.config.to_json(), **(info or {})},
                                  default=str))
        os.replace(tmp, self.state_dir / f"{stage}.done")

    def _save_npz(self, name: str, **arrays) -> None:
        self.state_dir.mkdir(parents=True, exist_ok=True)
        tmp = self.state_dir / f"{name}.tmp.npz"
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, self.state_dir / f"{name}.npz")

    # -- frames -------------------------------------------------------------------------------------
    def _frames(self, start: int, stop: int, stage: str):
        """Frames ``start..stop-1`` of a recording with the stride applied; honours pause/stop."""
        from .progress import progress

        stride = max(1, int(self.config.frame_stride))
        n = len(range(start, stop, stride))
        self.source.seek(start)
        it = iter(self.source)
        t0 = time.perf_counter()
        done = 0
        for k in progress(range(start, stop), total=stop - start, desc=stage, enable=self.show_progress):
            if not self._ctl.wait_if_paused():
                self._note(f"{stage}: stopped by the user after {done} frames")
                return
            try:
                frame = next(it)
            except StopIteration:
                return
            if (k - start) % stride:
                continue
            yield frame
            done += 1
            dt = time.perf_counter() - t0
            self._publish(stage=stage, frame=done, frames_total=n,
                          fps={**self._snap.fps, stage: done / dt if dt > 0 else 0.0}, last_frame=frame)
        dt = time.perf_counter() - t0
        self.timings[stage] = {"frames": done, "seconds": round(dt, 3),
                               "ms_per_frame": round(1000 * dt / max(done, 1), 2)}

    # -- loading reusable inputs -----------------------------------------------------------------------
    def _load_ir_profile(self, profile):
        if profile is None:
            return None
        from calibration.ir_profile import IRProfile

        return profile if isinstance(profile, IRProfile) else IRProfile.load(profile)

    def _load_envmap(self, envmap):
        if envmap is None:
            return None
        from .envmap import EnvMap

        if isinstance(envmap, EnvMap):
            return envmap
        if isinstance(envmap, np.ndarray):
            return EnvMap(radiance=envmap.astype(np.float32))
        return EnvMap.load(envmap, n=self.config.envmap_n)

    # -- the stages ----------------------------------------------------------------------------------
    def _stage_ir_calibration(self, start: int, stop: int) -> None:
        """§6: background (emitter off), response curve and emitter model (white sheet)."""
        from calibration.ir_pattern import describe
        from calibration.ir_profile import IRProfile
        from calibration.ir_response import calibrate_ir

        path = self.state_dir / "ir_profile.json"
        profile = self._reuse("ir-calibration", "IR profile", path, IRProfile.load)
        if profile is not None:
            self.ir_profile = profile
            return
        meta = self.source.meta if isinstance(self.source.meta, dict) else {}
        emitter = meta.get("emitter_position_m", (0.075, 0.0, 0.0))
        self._publish(force=True, stage="ir-calibration", guidance=GUIDANCE["ir-calibration"])
        frames = (f for f in self._frames(start, stop, "ir-calibration") if f.ir is not None)
        t0 = time.perf_counter()
        self.ir_profile = calibrate_ir(frames, emitter_position=emitter, device=str(meta.get("device", "")),
                                       pattern=self.config.ir_pattern)
        self.ir_profile.save(path)
        self._mark_done("ir-calibration", {"seconds": time.perf_counter() - t0})
        p = self.ir_profile
        pat = p.fit.get("pattern")
        self._note(f"ir-calibration: background {p.background:.1f} counts, gamma {p.gamma:.3f}, "
                   f"emitter model {p.emitter_model}"
                   + (f", pattern map {describe(pat)}{'' if pat['used'] else ', not used'}" if pat else ""))

    def _stage_environment(self, start: int, stop: int) -> None:
        """§4.3: track the camera on the markers, fit the ball, accumulate the environment map.

        Two sweeps over the pass. The first tracks every frame on the markers and collects the ball's
        depth: with the emitter position known (session meta ``emitter_position_m``) the mirror's own
        cues, its specular spot (points with known normals) and its silhouette (the hole it leaves in
        the depth against the plane), fitted once over the whole pass
        (:func:`appfusion.sphere_fit.fit_mirror_ball`; resting on the marker plane when the fit agrees).
        The second white-balances each RGB frame on the circles (§4.2), re-locates the ball in that
        frame's depth (its silhouette, against tracking error) and accumulates it.
        """
        from .envmap import EnvMap
        from .lighting_pass import LightingPass

        path = self.state_dir / "envmap.npz"
        env = self._reuse("environment", "environment map", path, EnvMap.load)
        if env is not None:
            self.env = env
            return
        cfg = self.config
        geo = _Geometry(self.source.meta, self.config, surface=False)      # tracks only
        meta = self.source.meta if isinstance(self.source.meta, dict) else {}
        extra = meta.get("extra") or {}
        ball = extra.get("mirror_ball") or {}
        radius = cfg.ball_radius_m or extra.get("ball_radius_m")
        rho_mirror = cfg.mirror_reflectance if cfg.mirror_reflectance is not None else ball.get("reflectance", 1.0)
        emitter = meta.get("emitter_position_m")
        on_plane = getattr(cfg, "ball_on_plane", None)
        if on_plane is None:
            on_plane = ball.get("on_plane", "auto")
        light = LightingPass(n=cfg.envmap_n, radius=radius, rho_mirror=rho_mirror,
                             fit_kwargs={"max_rms_rel": cfg.ball_max_scatter}, emitter=emitter,
                             on_plane=on_plane, per_frame_center=emitter is not None)
        self._publish(force=True, stage="environment", guidance=GUIDANCE["environment"], tracking="ok")
        poses: dict[int, np.ndarray] = {}
        for frame in self._frames(start, stop, "environment"):           # sweep 1: tracking, ball depth
            track = geo.track(frame)
            if track.pose is None:
                self._publish(tracking="lost")
                continue
            poses[frame.index] = track.pose
            if frame.depth is not None and frame.depth_intrinsics is not None and geo.box is not None:
                light.add_depth(frame.depth, frame.depth_intrinsics, track.pose, box=geo.box)
            self._publish(tracking=track.state, markers_visible=track.markers_visible)
        light.box = geo.box
        sphere = light.fit()  # raises a clear EstimationError when the ball was never seen well enough
        for msg in light.fit_notes:
            self._note(f"environment: {msg}")
        how = ("specular spot + silhouette" if sphere.method == "mirror" else "sphere fit of the depth points")
        self._note(f"environment: mirror ball r = {1000 * sphere.radius:.1f} mm"
                   f"{' (given)' if sphere.radius_fixed else ''} at "
                   f"({', '.join(f'{1000 * x:.1f}' for x in sphere.center)}) mm, {how}"
                   f"{', resting on the marker plane' if sphere.on_plane else ''}")
        wb = None
        no_marker = 0
        for frame in self._frames(start, stop, "environment"):           # sweep 2: radiance
            pose = poses.get(frame.index)
            if pose is None or frame.rgb is None:
                continue
            wb = wb or self._white_balancer(geo)
            b = wb.balance(frame, pose)
            if b.reference is None:
                no_marker += 1
                continue
            light.add_frame(frame, pose=pose, rgb_linear=b.rgb)
            if light.n_rgb_frames and light.n_rgb_frames % 10 == 0:
                env = light.envmap()
                self._publish(envmap=env.radiance.copy(), env_coverage=env.known.copy())
        if no_marker:
            self._note(f"environment: {no_marker} RGB frames were skipped: no white reference (no circle in view yet, "
                       "or the circles in view not where the frame's pose puts them)")
        if light.n_unlocated_frames:
            self._note(f"environment: the ball's silhouette was not found in {light.n_unlocated_frames} frames "
                       "(mapped with the tracked pose)")
        self.env = light.envmap()
        self.env.save_npz(path)
        self._publish(force=True, envmap=self.env.radiance.copy(), env_coverage=self.env.known.copy())
        self._mark_done("environment", {"sphere": light.sphere.to_json() if light.sphere else None,
                                        "coverage": self.env.coverage_fraction()})
        self._note(f"environment: ball fitted, map coverage {100 * self.env.coverage_fraction():.0f}%")

    def _stage_geometry(self, start: int, stop: int, pass_name: str) -> None:
        """§4.1: tracking + TSDF fusion, markers and object box, then point sampling."""
        cfg = self.config
        g = self._reuse("geometry", "geometry")
        if g is not None:
            self.points = (g["positions"], g["normals"])
            self.mesh = (g["mesh_vertices"], g["mesh_faces"])
            jr = g["jet_residual"] if "jet_residual" in g else np.zeros(0)
            self.jet_residual = jr if len(jr) == len(g["positions"]) else None
            self.poses = {int(i): p for i, p in zip(g["pose_index"], g["poses"])}
            self._publish(force=True, positions=self.points[0], normals=self.points[1])
            return
        self.geometry = _Geometry(self.source.meta, self.config)
        self._publish(force=True, stage="geometry", guidance=GUIDANCE["geometry"], tracking="ok")
        lost = 0
        for frame in self._frames(start, stop, "geometry"):
            track = self.geometry.track(frame)
            lost += track.state == "lost"
            if track.pose is not None:
                self.poses[frame.index] = track.pose
            self._publish(tracking=track.state, markers_visible=track.markers_visible)
        if lost:
            self._note(f"geometry: tracking lost in {lost} frames (not fused; the scan resumed when the view returned)")
        rejected = self.geometry.gp.backfill_rejected
        if rejected:
            self._note(f"geometry: {rejected} frames tracked before the circles defined the marker frame left out: "
                       "their circles did not confirm the tracked pose")
        if cfg.refuse_geometry:
            rounds = int(cfg.refuse_rounds)
            t0 = time.perf_counter()
            n = 0
            for r in range(rounds):
                n = self.geometry.gp.refuse(self._frames(start, stop, "geometry-refuse"
                                                         + (f" {r + 1}/{rounds}" if rounds > 1 else "")))
                if not n:
                    break
            if n:
                how = f"{rounds} rounds, " if rounds > 1 else ""
                gp = self.geometry.gp
                if gp.refuse_scale not in (None, 1.0):
                    how += f"at {gp.fusion.config.voxel_size * 1e3:.1f} mm voxels"
                    if getattr(gp, "fine_triggered", False):
                        how += f", truncation {gp.fusion.config.trunc_voxels:g} voxels"
                    if gp.tight_fraction is not None:
                        how += (f": {gp.tight_fraction:.1%} of the object curves tighter than "
                                f"{gp.config.refuse_fine_radius_voxels:g} voxels")
                    how += ", "
                self._note(f"geometry: {n} frames re-registered to the fused object with their circles and fused "
                           f"again ({how}{time.perf_counter() - t0:.0f} s)")
        try:
            V, F, P, N, poses = self.geometry.finish(cfg.n_points)
        except AppFusionError as e:
            kept = self._keep_unaligned_surface()
            if not kept:
                raise
            raise EstimationError(f"{e}{kept}") from None
        self.poses.update(poses)  # every fused frame's final pose in the marker frame
        self.points, self.mesh = (P, N), (V, F)
        idx = np.array(sorted(self.poses), np.int64)
        gp = self.geometry.gp
        self.jet_residual = getattr(gp, "jet_residual", None)
        self._save_npz("geometry", positions=P, normals=N, mesh_vertices=V, mesh_faces=F, pose_index=idx,
                       jet_residual=np.zeros(0) if self.jet_residual is None else self.jet_residual,
                       poses=np.array([self.poses[i] for i in idx]).reshape(-1, 4, 4))
        self._mark_done("geometry", {"points": len(P), "faces": len(F), "frames_lost": lost,
                                     "fine_triggered": bool(getattr(gp, "fine_triggered", False)),
                                     "refused_frames": int(n) if cfg.refuse_geometry else 0,
                                     "jet_fraction": getattr(gp, "jet_fraction", None)})
        self._publish(force=True, positions=P.copy(), normals=N.copy())
        jet = getattr(gp, "jet_fraction", None)
        self._note(f"geometry: {len(F)} mesh faces, {len(P)} points sampled on the object"
                   + ("" if jet is None else
                      f" (the normal filter's stages did not converge: {jet:.0%} of the normals from cubic "
                      f"fits over {gp.config.jet_radius * 1e3:g} mm)"))

    def _keep_unaligned_surface(self) -> str:
        """When the circles never gave a marker frame, write the surface fused so far (uncropped, the
        first depth camera's frame) to ``geometry-unaligned.ply`` so that the geometry pass's work is
        not lost; returns the sentence to append to the error ('' when there is nothing to keep)."""
        gp = self.geometry.gp
        if gp.tracker.initialised:
            return ""
        import open3d as o3d

        path = self.out_dir / "geometry-unaligned.ply"
        try:
            mesh = gp.fused_mesh()                      # raises when no frame was fused
            if len(mesh.triangles) == 0:
                return ""
            self.out_dir.mkdir(parents=True, exist_ok=True)
            if not o3d.io.write_triangle_mesh(str(path), mesh):
                return ""
        except Exception:  # keeping the surface must not hide the error itself
            return ""
        n = gp.fusion.n_integrated
        return (f". The surface fused from {n} frame{'s' if n != 1 else ''} without a marker frame is kept in "
                f"{path} ({len(mesh.triangles)} faces; the first tracked depth camera's frame, metres): "
                f"geometry only, no object box and no appearance")

    def _stage_ir(self, start: int, stop: int) -> None:
        """§5.1-5.2: IR frames of the geometry pass into the BRDF cut; clusters and Ward fits."""
        ir_arrays = self._reuse("ir", "clusters")
        if ir_arrays is not None:
            self._ir_result = ir_arrays
            leaf = self._ir_result.pop("leaf_hbsab", None)
            hb = _unstack_images(self._ir_result.pop("hbsab_images", None))
            fits = _unstack_images(self._ir_result.pop("hbsab_fit_images", None))
            self._restore_history("ir", "alpha")
            extra = {"hbsabs": hb, "hbsab_fits": fits} if hb else {}
            self._publish(force=True, labels=self._ir_result["labels"], alpha=self._ir_result["alpha"],
                          lobes=[str(x) for x in _ir_lobes(self._ir_result, len(self._ir_result["alpha"]))],
                          history=self._snap.history, **extra)
            if leaf is not None and self.ir_profile is not None and self.points is not None:
                # the BRDF cut's leaf buffers come back, so that the colour pass can refit the lobes
                # of its clusters as in an uninterrupted scan (the tree is rebuilt from the points)
                ir = self._new_ir_pass()
                if ir.cut.leaves.data.shape == leaf.shape:
                    ir.cut.leaves.data[...] = leaf
                    self.ir = ir
                else:
                    self._note(f"ir: the checkpoint's leaf buffers {leaf.shape} do not fit the BRDF cut "
                               f"rebuilt from the points {ir.cut.leaves.data.shape}: the lobes are not refitted")
            return
        if self.ir_profile is None:
            raise PassMissingError("the IR pass needs an IR profile: record an ir-calibration pass or give "
                                   "--ir-profile")
        self.ir = self._new_ir_pass()
        meta = self.source.meta if isinstance(self.source.meta, dict) else {}
        emitter = meta.get("emitter_position_m")
        self._publish(force=True, stage="ir", guidance=GUIDANCE["ir"])
        used = 0
        for frame in self._frames(start, stop, "ir"):
            pose = self.poses.get(frame.index)
            if pose is None or frame.ir is None or frame.depth is None or frame.emitter is False:
                continue
            pose = self._refined_pose(frame, pose)
            self.ir.add_frame(frame.ir, frame.depth, frame.depth_intrinsics, pose, emitter)
            used += 1
            if self._progress_due(used, 15):
                self._publish_ir(self.ir.result(fit=True), used)
        if used == 0:
            raise PassMissingError("the geometry pass has no IR frames with tracked poses: clusters and "
                                   "roughness cannot be estimated")
        res = self.ir.result(fit=True)
        self._publish_ir(res, used, force=True)
        self._ir_result = self._ir_arrays(res)
        # the leaf HBSABs too (constant size: leaves x channels x texels), for a resumed scan's refits,
        # and what the report shows of this stage: the clusters' HBSABs, their fits, the running alphas
        snap = self._snap
        self._save_npz("ir", **self._ir_result, leaf_hbsab=self.ir.cut.leaves.data,
                       hbsab_images=_stack_images(snap.hbsabs), hbsab_fit_images=_stack_images(snap.hbsab_fits))
        self._mark_done("ir", {"frames": used, "k": res.k, "k_auto": res.k_auto, "notes": res.notes,
                               "history": {"alpha": snap.history.get("alpha", [])}})
        broad = _broad_lobe(self._ir_result["alpha"])
        al = ", ".join(f"{a:.3f}" + (" (at the roughness bound: no lobe)" if b else "")
                       for a, b in zip(self._ir_result["alpha"], broad))
        self._note(f"ir: {res.k} specular cluster(s){' (automatic k)' if res.k_auto else ''}, alpha = {al}")

    def _new_ir_pass(self):
        """An empty IR pass over the sampled points (its BRDF-cut tree is a function of them and the
        config), with the surface's open boundary marked and the painted labels applied."""
        from .ir_pass import IRPass

        P, N = self.points
        rim = None
        if self.config.ir_rim_m > 0 and self.mesh is not None:
            from .geometry_pass import open_boundary_points

            rim = open_boundary_points(P, self.mesh[0], self.mesh[1], self.config.ir_rim_m)
        ir = IRPass(P, N, self.ir_profile, hbsab_n=self.config.hbsab_n, k=self.config.k_clusters, rim=rim,
                    lobes=self._ir_lobe_names)
        for i, lab in self._painted.items():
            ir.set_labels([i], lab)
        return ir

    def _refined_pose(self, frame: Frame, pose: np.ndarray) -> np.ndarray:
        """A tracked pose re-registered to the final mesh (``refine_poses``), once per frame index;
        the tracked pose itself without a mesh or with the option off. :attr:`poses` keeps the
        tracked ones (the trajectory the scan reports)."""
        if not self.config.refine_poses or self.mesh is None or len(self.mesh[1]) == 0 or frame.depth is None:
            return pose
        cache = self._refined
        if frame.index not in cache:
            if self._refiner is None:
                from .geometry_pass import PoseRefiner

                self._refiner = PoseRefiner(*self.mesh)
            K = frame.depth_intrinsics
            cache[frame.index] = self._refiner.refine(frame.depth, K, pose)[0] if K is not None else pose
        return cache[frame.index]

    @staticmethod
    def _ir_arrays(res) -> dict[str, np.ndarray]:
        alpha = res.alphas()
        sig = np.array([c.alpha_sigma if c.alpha_sigma is not None else np.nan for c in res.clusters])
        fitted = res.fitted
        rho_s_ir = np.array([c.fit.rho_s if c.fit is not None else 0.0 for c in res.clusters])
        lobe = np.array([getattr(c.fit, "lobe", "ward") if c.fit is not None else "ward" for c in res.clusters],
                        dtype="<U8")
        return {"labels": res.labels.astype(np.int32), "alpha": alpha.astype(np.float32),
                "alpha_sigma": np.nan_to_num(sig, nan=0.0).astype(np.float32), "fitted": fitted,
                "rho_s_ir": rho_s_ir.astype(np.float32), "lobe": lobe}

    def _publish_ir(self, res, used: int, force: bool = False) -> None:
        arr = self._ir_arrays(res)
        hb, fits = [], []
        for c in res.clusters:
            img = c.hbsab.value[0].copy() if c.hbsab is not None else None
            hb.append(img)
            fits.append(self._ward_image(c) if img is not None else None)
        hist = self._snap.history
        hist.setdefault("alpha", []).append((used, arr["alpha"].tolist()))
        self._publish(force=force, labels=self._apply_paint_to(arr["labels"]), alpha=arr["alpha"],
                      alpha_sigma=arr["alpha_sigma"], lobes=[str(x) for x in arr["lobe"]], hbsabs=hb,
                      hbsab_fits=fits, history=hist)

    def _ward_image(self, cluster) -> np.ndarray | None:
        """The fitted lobe on the HBSAB's square (w_i = w_o = h convention of §5.1)."""
        if cluster.fit is None:
            return None
        from . import octahedral as oc
        from .brdf import lobe_retro

        n = cluster.hbsab.n
        ch = oc.hemi_directions(n)[..., 2]
        f = cluster.fit
        return (f.diffuse + f.rho_s * lobe_retro(getattr(f, "lobe", "ward"), f.alpha, ch)).astype(np.float32)

    def _stage_rgb(self, start: int, stop: int, pass_name: str = "rgb") -> None:
        """§4.2 + §5.3: white-balanced RGB frames into per-point rho_d and per-cluster rho_s."""
        from .rgb_pass import RGBPass

        rgb_arrays = self._reuse("rgb", "rho_d / rho_s")
        if rgb_arrays is not None:
            # the HBSABs and lobes the colour pass refitted to its clusters (a split, a merge), if it did
            hb = _unstack_images(rgb_arrays.pop("hbsab_images", None))
            fits = _unstack_images(rgb_arrays.pop("hbsab_fit_images", None))
            self._rgb_result = rgb_arrays
            if hb:
                self._publish(force=True, hbsabs=hb, hbsab_fits=fits,
                              **({"lobes": [str(x) for x in rgb_arrays["lobe"]]} if "lobe" in rgb_arrays else {}))
            if "normals" in rgb_arrays and self.points is not None:     # refined (_refine_normals)
                self.points = (self.points[0], np.asarray(rgb_arrays["normals"], np.float32))
            restored = self._restore_history("rgb", "rho_s")
            self._publish(force=True, rho_d=np.asarray(rgb_arrays["rho_d"], np.float32),
                          rho_s=np.asarray(rgb_arrays["rho_s"], np.float32),
                          rho_s_sigma=(np.asarray(rgb_arrays["rho_s_sigma"], np.float32)
                                       if "rho_s_sigma" in rgb_arrays else None),
                          **({"history": self._snap.history} if restored else {}))
            return
        P, N = self.points
        labels = self._current_labels()
        ir = getattr(self, "_ir_result", None)
        alpha = ir["alpha"] if ir is not None else np.array([0.3])
        lobes = _ir_lobes(ir, len(alpha))
        # model ladder, first rung from the IR pass: a cluster whose IR shows no lobe (no fit, rho_s 0,
        # or a lobe as broad as the model allows) is diffuse, and the RGB pass builds no
        # double-product table for it
        specular = None
        if ir is not None and "rho_s_ir" in ir:
            broad = _broad_lobe(ir["alpha"])
            specular = np.asarray(ir["fitted"], bool) & (np.asarray(ir["rho_s_ir"]) > 1e-6) & ~broad
            if int(labels.max()) + 1 > len(specular):           # painted new clusters: let RGB decide
                specular = np.r_[specular, np.ones(int(labels.max()) + 1 - len(specular), bool)]
                alpha = np.r_[alpha, np.full(len(specular) - len(alpha), 0.3, np.float32)]
                lobes = np.append(lobes, np.full(len(specular) - len(lobes), "ward"))
            if not specular.all():
                why = (f" (the fit of cluster(s) {', '.join(str(c) for c in np.flatnonzero(broad))} ran to the roughness "
                       "bound, alpha 1: no highlight the Ward model can tell from diffuse)" if broad.any() else "")
                self._note(f"rgb: cluster(s) {', '.join(str(c) for c in np.flatnonzero(~specular))} show no "
                           f"specular lobe in the IR{why}: diffuse only, no double-product tables for them")
        self.rgb = RGBPass(P, N, labels, alpha, self.env.radiance, specular=specular, lobes=lobes,
                           near_field=self._near_field(), **self._rgb_kwargs())
        self._publish(force=True, stage="rgb", guidance=GUIDANCE["rgb"], tracking="ok")
        used = self._rgb_sweep(self.rgb, start, stop, pass_name, live=True)
        splits = self.rgb.split_by_specular() if self.config.rgb_split and not self._painted else []
        for c, new, n in splits:
            self._note(f"rgb: {n} points of cluster {c} show far less specular reflection in colour than the "
                       f"rest (a material the IR never showed a highlight of): new cluster {new}")
        merges = []
        if self.config.rgb_split and not self._painted and self.config.k_clusters is None:
            merges = self.rgb.merge_alike()
            for i, j in merges:
                self._note(f"rgb: clusters {i} and {j} have the same alpha and rho_s: merged")
        r = self.rgb.result()
        labels = self.rgb.labels_caller_order()
        alpha = np.asarray(self.rgb.alphas, np.float32)
        lobes = np.asarray(self.rgb.lobes, dtype="<U8")
        sigma = np.full(len(alpha), np.nan, np.float32)
        if splits or merges:
            alpha, sigma, lobes = self._refit_ir(labels, alpha, sigma, lobes=lobes)
            if self.config.rgb_resweep and not (np.allclose(alpha, self.rgb.alphas, rtol=1e-3)
                                                and np.array_equal(lobes, self.rgb.lobes)):
                r, labels = self._rgb_resweep(labels, alpha, np.isfinite(sigma), start, stop, pass_name, lobes=lobes)
                alpha2, sigma2, lobes2, again = self._refit_ir_final(labels, alpha, sigma, r.model, lobes)
                if again:                                   # a measured lobe moved: rho_s with its new S
                    r, labels = self._rgb_resweep(labels, alpha2, np.isfinite(sigma2), start, stop, pass_name,
                                                  reassign=False, lobes=lobes2)
                alpha, sigma, lobes = alpha2, sigma2, lobes2
        if int(self.config.rho_d_pool_k) > 1 and self.config.rho_d_estimator == "lsq":
            from .rgb_pass import denoise_rho_d

            t0 = time.perf_counter()
            se = self.rgb.rho_d_stderr(r.rho_s)
            rd = denoise_rho_d(self.points[0], r.rho_d, se, labels, k=int(self.config.rho_d_pool_k),
                               z=float(self.config.rho_d_pool_z))
            pooled = np.isfinite(se).all(axis=1)
            change = np.abs(rd - r.rho_d)[pooled] / np.maximum(np.abs(r.rho_d[pooled]), 1e-6)
            r.rho_d = rd.astype(np.float32)
            self._note(f"rgb: rho_d of {int(pooled.sum())} points pooled with neighbours that agree within "
                       f"{float(self.config.rho_d_pool_z):g} standard errors (median change "
                       f"{100 * float(np.median(change)) if len(change) else 0.0:.1f} %, {time.perf_counter() - t0:.1f} s)")
        self._rgb_result = {"rho_d": np.asarray(r.rho_d, np.float32), "rho_s": np.asarray(r.rho_s, np.float32),
                            "counts": np.asarray(r.counts), "model": np.array(r.model or ["ward"] * len(r.rho_s)),
                            "labels": labels, "alpha": alpha, "alpha_sigma": sigma, "lobe": np.asarray(lobes, dtype="<U8")}
        if r.rho_s_sigma is not None:
            self._rgb_result["rho_s_sigma"] = np.asarray(r.rho_s_sigma, np.float32)
        rounds = self._normal_refine_rounds()
        if rounds > 0:
            self._refine_normals(start, stop, pass_name, rounds)
        if r.heldout_rss is not None:
            ward = r.rho_s_ward if r.rho_s_ward is not None else np.full((len(r.model), 3), np.nan)
            zs = r.heldout_z if r.heldout_z is not None else np.full(len(r.model), np.nan)
            self._note("rgb: model ladder (held-out RSS diffuse / the cluster's lobe, improvement in standard errors): " + "; ".join(
                f"cluster {c} {m} ({a:.3g} / {b:.3g}, z {z:.1f}" + (f"; Ward's rho_s would be {np.mean(w):.4f})"
                                                                   if m == "diffuse" else ")")
                for c, (m, (a, b), w, z) in enumerate(zip(r.model, r.heldout_rss, ward, zs))))
        # what the report and the GUI show of the clusters: the HBSABs and lobes refitted to the colour
        # pass's clusters (_refit_ir) when it split or merged any; a rerun on the checkpoints shows them
        imgs = {}
        if splits or merges:
            imgs = {"hbsab_images": _stack_images(self._snap.hbsabs),
                    "hbsab_fit_images": _stack_images(self._snap.hbsab_fits)}
        self._save_npz("rgb", **self._rgb_result, **imgs)
        self._mark_done("rgb", {"frames": used, "history": {"rho_s": self._snap.history.get("rho_s", [])}})
        sig = self._rgb_result.get("rho_s_sigma")
        self._publish(force=True, rho_d=self._rgb_result["rho_d"], rho_s=self._rgb_result["rho_s"], rho_s_sigma=sig)
        self._note(f"rgb: rho_d from {used} frames; rho_s per cluster = "
                   + "; ".join(", ".join(f"{v:.3f}" for v in row)
                               + (f" (± {', '.join(f'{e:.2g}' for e in sig[c])})"
                                  if sig is not None and c < len(sig) and np.isfinite(sig[c]).all() else "")
                               for c, row in enumerate(self._rgb_result["rho_s"])))

    def _normal_refine_rounds(self) -> int:
        """``ScanConfig.normal_refine_rounds``, or where it is None (the default) 3 when the geometry
        pass's fine re-fusion fired over at least ``refuse_fine_trunc_min_frames`` frames (read from
        the geometry stage's checkpoint, so a resumed scan decides the same), else 0. Where the
        normals are jet fits, :meth:`_refine_normals` refines only the points the fits describe
        worst (``ScanConfig.normal_refine_jet_residual``)."""
        if self.config.normal_refine_rounds is not None:
            return int(self.config.normal_refine_rounds)
        info = self._done_info("geometry")
        fired = bool(info.get("fine_triggered")) and int(info.get("refused_frames") or 0) >= int(
            self.config.refuse_fine_trunc_min_frames)
        return 3 if fired else 0

    def _refine_normals(self, start: int, stop: int, pass_name: str, rounds: int) -> None:
        """Specular normal refinement (:mod:`appfusion.normal_refine`): ``rounds`` more sweeps of the
        RGB frames with the final clusters, lobes and rho_s; the moved points get their new normals
        (``self.points``). Their rho_d stays the exported one (session 31: scaling it by the refit's
        factor between the new and the old normal took the pepper's rho_d from 2.88 to 2.99 % and
        changed its relit error by 6e-5). The normals are saved with the RGB stage (``rgb.npz``), so
        a resumed scan keeps them."""
        from .normal_refine import NormalRefiner

        res = self._rgb_result
        rho_s = np.where((np.asarray(res["model"]) == "diffuse")[:, None], 0.0, np.asarray(res["rho_s"], np.float64))
        if not (rho_s.max(axis=1) > 0).any():
            return
        P, N = self.points
        t_rgb = self.timings.get("rgb")
        deg = float(self.config.normal_refine_deg)
        moved = None
        jr, jmax = getattr(self, "jet_residual", None), self.config.normal_refine_jet_residual
        first = None if jr is None or jmax is None or len(jr) != len(N) else ~(np.asarray(jr) <= float(jmax))
        self._note(f"rgb: specular normal refinement, {rounds} rounds"
                   + (" (the object curves tighter than the voxel: the fine re-fusion fired)"
                      if self.config.normal_refine_rounds is None else "")
                   + ("" if first is None else
                      f"; {int(first.sum())} points whose jet fit's residual is over {float(jmax):g} times the median"))
        for k in range(int(rounds)):
            # round 1: the points whose highlights the pass fits worst (of those the jets fit worst,
            # where the normals are jet fits); later rounds: the ones that moved
            ref = NormalRefiner(self.rgb, rho_s, N, radii_deg=(deg / 2, deg), only=first if moved is None else moved,
                                min_gain=self.config.normal_refine_min_gain,
                                screen=self.config.normal_refine_screen if moved is None else None)
            if not len(ref.sel):
                break
            self._rgb_sweep(ref, start, stop, pass_name, live=False, calibrated=getattr(self, "_rgb_calibration", None))
            N_before = N
            N, rd, st = ref.result()
            moved = np.isfinite(rd).all(axis=1)          # rd: the moved points' refit rho_d (not used)
            self._note(f"rgb: normal refinement round {k + 1} (tilts {deg / 2:.2g}, {deg:.2g} deg): "
                       f"{st['moved']} of {st['points']} points moved (median {st['median_move_deg']:.2f} deg, "
                       f"residual explained {st['gain_pct']}; "
                       f"{100 * st['full_fraction']:.0f} % of {st['samples']} samples near a highlight), "
                       f"{st['seconds']:.1f} s")
            if not moved.any():
                break
            if k == 0 and st["median_move_deg"] >= 0.9 * deg:
                # most first moves ran to the outer ring: the signature of the highlights' half-pixel
                # registration on normals that were right (the demo capsule's shoulder, the vase's
                # body: 0.6 -> 2.9 degrees off the truth), not of the TSDF's rounded rims, whose
                # first moves mostly stop at the inner ring (the pepper: median 1.5 of 3 degrees)
                N = N_before
                self._note(f"rgb: normal refinement undone: most first moves ran to the outer ring "
                           f"({st['median_move_deg']:.2f} of {deg:.2g} deg), which the highlights' registration "
                           f"does on normals that were right (docs/rgb-pass.md §5f)")
                break
            if st["median_move_deg"] < 0.9 * deg:             # most moves stopped short of the outer ring:
                deg /= 2                                      # finer; else walk on at the same tilts
        self.timings["normal-refine"] = self.timings.pop("rgb", {})
        if t_rgb is not None:
            self.timings["rgb"] = t_rgb
        self.points = (P, N.astype(np.float32))
        res["normals"] = self.points[1]
        self._publish(force=True, normals=self.points[1])

    def _rgb_sweep(self, rgb, start: int, stop: int, pass_name: str, live: bool,
                   calibrated: dict | None = None) -> int:
        """One sweep of the RGB pass's frames into ``rgb`` (white balance §4.2, then Eq. 5's sums);
        returns the frames used. ``live``: publish rho_d / rho_s every 10 frames (on the doubling
        schedule of :meth:`_progress_due` when nobody subscribes).

        ``calibrated``: per frame index, the ``(pose, white-balance gain)`` an earlier sweep found
        (None: no pose or no white reference), reused instead of tracking the markers and balancing
        again; without it, this sweep's are stored in ``self._rgb_calibration`` (a pose and three
        gains a frame, like :attr:`poses`)."""
        record = calibrated is None
        if record:
            self._rgb_calibration = {}
            wb = self._white_balancer(self.geometry)
            # frames of a separate RGB pass get their pose from the markers (the key circle makes it absolute)
            marker_pose = _MarkerPose(self.source.meta) if pass_name != getattr(self, "_obj_pass", None) else None
        used = no_marker = lost = 0
        for frame in self._frames(start, stop, "rgb"):
            if frame.rgb is None or frame.depth is None:
                continue
            if not record:
                pose, gain = calibrated.get(frame.index) or (None, None)
                if pose is None or gain is None:
                    continue
                raw = frame.rgb_linear()
                balanced = raw * gain                          # as WhiteBalancer.balance: float64 gain
            else:
                pose = self.poses.get(frame.index)
                if pose is not None:                           # a depth-tracked frame (combined pass)
                    pose = self._refined_pose(frame, pose)
                if pose is None and marker_pose is not None:
                    track = marker_pose.track(frame)
                    pose = track.pose
                    if live:
                        self._publish(tracking=track.state, markers_visible=track.markers_visible)
                if pose is None:
                    lost += 1
                    self._rgb_calibration[frame.index] = None
                    continue
                b = wb.balance(frame, pose)
                if b.reference is None:
                    no_marker += 1
                    self._rgb_calibration[frame.index] = (pose, None)
                    continue
                self._rgb_calibration[frame.index] = (np.asarray(pose), np.asarray(b.gain, np.float64))
                raw, balanced = frame.rgb_linear(), b.rgb
            # saturation is a property of the sensor's raw values, not of the balanced ones (a highlight
            # may be brighter than the white paper): mark raw-saturated pixels NaN, which RGBPass skips
            rgb_b = np.where((raw >= 0.98).any(axis=-1, keepdims=True), np.nan, balanced).astype(np.float32)
            rgb.add_frame(rgb_b, frame.depth, frame.rgb_intrinsics, frame.depth_intrinsics, pose,
                          frame.depth_to_rgb)
            used += 1
            if live and self._progress_due(used, 10):
                self._publish_rgb_running(rgb, used)
        # the running estimate at the sweep's last frame too, so that the report's convergence plot
        # reaches the end of the pass (the doubling schedule stopped the demo's at 160 of 200 frames)
        last = self._snap.history.get("rho_s")
        if live and used and not (last and last[-1][0] == used):
            self._publish_rgb_running(rgb, used)
        if used == 0:
            raise PassMissingError("the RGB pass has no usable frames (no RGB with depth, tracking lost, or "
                                   "no marker visible for white balance)")
        if live and no_marker:
            self._note(f"rgb: {no_marker} frames were skipped: no white reference (no circle in view yet, or the "
                       "circles in view not where the frame's pose puts them)")
        if live and lost:
            self._note(f"rgb: tracking lost in {lost} frames")
        return used

    def _publish_rgb_running(self, rgb, used: int) -> None:
        """The live sweep's running rho_d and rho_s after ``used`` frames, to the GUI and the history."""
        r = rgb.result()
        hist = self._snap.history
        hist.setdefault("rho_s", []).append((used, np.asarray(r.rho_s).tolist()))
        self._publish(rho_d=np.asarray(r.rho_d, np.float32), rho_s=np.asarray(r.rho_s, np.float32),
                      rho_s_sigma=None if r.rho_s_sigma is None else np.asarray(r.rho_s_sigma, np.float32),
                      history=hist)

    def _rgb_resweep(self, labels: np.ndarray, alpha: np.ndarray, refitted: np.ndarray, start: int, stop: int,
                     pass_name: str, reassign: bool = True, lobes=None):
        """Eq. 5 again over the RGB frames, with the clusters and lobes the first sweep settled.

        The first sweep's double products S were built with the IR clusters' alphas. Once the colour
        pass has split a cluster and the IR lobes were refitted to the new clusters (:meth:`_refit_ir`),
        S of every point changes: on the demo the one IR cluster (alpha 0.051) becomes the paint
        (0.066) and the label (0.35). rho_s of Eq. 8 is only meaningful with the S of the alpha it is
        exported with, and the split-off cluster's rho_s was not measured at all (it was made
        diffuse). The sums of §5.3 cannot be re-weighted after the fact (S enters them per sample),
        so the frames are swept once more -- the recording is on disk, live scans included
        (``live-session``), and offline, so the support plane's ``dS`` takes
        ``near_field_final_samples`` lobe samples instead of the live sweep's 4. No further split. A
        cluster gets a lobe if it had one in the first sweep or its lobe was refitted (``refitted``; a split-off cluster without an IR fit stays diffuse: a
        borrowed alpha would be a guess), and the model ladder decides again which clusters keep it.
        With ``rgb_split``, the lobes the first sweep kept are measured on every point too, and each
        point then goes to the cluster whose model fits its neighbourhood best
        (:meth:`appfusion.rgb_pass.RGBPass.reassign_by_model`). Returns the new :class:`RGBResult`
        and labels (caller order). ``reassign=False``: the third sweep of :meth:`_refit_ir_final`,
        with the final clusters kept as they are. ``lobes``: each cluster's lobe name (default Ward);
        each kept lobe is measured on the other points with its own shape (Ward or GGX).
        """
        from .rgb_pass import RGBPass

        P, N = self.points
        first = self.rgb
        self._note(("rgb: second sweep with the refitted lobes (alpha " if reassign else
                    "rgb: third sweep with the lobes of the final clusters (alpha ")
                   + ", ".join(f"{a:.3f}" for a in alpha) + ")")
        specular = (np.asarray(first.specular, bool) | np.asarray(refitted, bool)) & ~_broad_lobe(alpha)
        # the lobes the first sweep measured (its model ladder kept them) are also measured on every
        # other point, so that each point can go to the model that explains it best
        lobes = np.full(len(alpha), "ward", dtype="<U8") if lobes is None else np.asarray(lobes, dtype="<U8")
        compare = compare_lobes = None
        if self.config.rgb_split and reassign:
            compare, compare_lobes = _compare_lobes(first.model, lobes, alpha, specular)
        rgb = RGBPass(P, N, labels, alpha, self.env.radiance, specular=specular, tables=first.tables, lobes=lobes,
                      near_field=first.near_field, near_field_samples=int(self.config.near_field_final_samples),
                      s_replicate=int(self.config.rho_s_replicate), footprint=bool(self.config.rho_s_footprint),
                      compare_alphas=compare,
                      compare_lobes=compare_lobes, **self._rgb_kwargs())
        t_first = self.timings.get("rgb")
        self._rgb_sweep(rgb, start, stop, pass_name, live=False, calibrated=getattr(self, "_rgb_calibration", None))
        self.timings["rgb-resweep" if reassign else "rgb-third-sweep"] = self.timings.pop("rgb", {})
        if t_first is not None:
            self.timings["rgb"] = t_first
        self.rgb = rgb
        # the tables of lobes no pass reads any more (the first sweep's, an earlier refit's) go
        freed = rgb.tables.keep_only(rgb.table_keys)
        if freed > 0:
            self._note(f"rgb: S tables of earlier lobes released ({freed:.1f} MB; {rgb.tables.nbytes / 2**20:.1f} MB kept)")
        if compare is not None and len(compare):
            moved = rgb.reassign_by_model(colour_regions_on=self.config.rgb_colour_regions)
            self._note(f"rgb: {moved} points moved to the cluster whose colour model fits their neighbourhood best")
        res = rgb.result()
        if rgb.footprint_c is not None:
            # the fitted blur as a length: the footprint's standard deviation per axis at 1 m
            self._note(f"rgb: the pixel footprint's blur of the print, fitted with rho_s: {1e3 * rgb.footprint_c ** 0.5:.2f} mm "
                       "at 1 m (its standard deviation); rho_s without it " + "; ".join(
                           ", ".join(f"{v:.3f}" for v in row) for row in rgb.rho_s_unblurred))
        return res, rgb.labels_caller_order()

    def _refit_ir_final(self, labels: np.ndarray, alpha: np.ndarray, sigma: np.ndarray,
                        model, lobes) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """The IR lobes fitted once more, to the clusters the second sweep left; returns alpha, sigma,
        the lobes' names and whether a third sweep is needed.

        The second sweep moves the points whose colour fits the other cluster's model better
        (:meth:`appfusion.rgb_pass.RGBPass.reassign_by_model`: 3.6-4.6k of 100k on the demo and seed 1),
        mostly along the seam, where the first sweep's split had put paint into the label's cluster.
        The label's lobe (Ward 0.35, 5 % above its diffuse level in the IR) is the one they bias:
        fitted to the split's clusters seed 1 gave 0.332 (-5.1 %), to the final ones 0.346. Every
        cluster takes its new fit. A cluster whose S was in the sweep's sums (Ward, or made diffuse by
        the model ladder) had its rho_s measured, and the ladder's choice made, with the double
        products of the swept alpha: if that alpha moved by more than 1 %, the RGB frames are swept a
        third time with the new one (the caller; no reassignment). The 40-frame bench scan's label
        was swept at 0.067 (the split's cluster fitted in IR) and refitted to 0.317: the ladder had
        judged a lobe five times too narrow (session 31). A cluster without S in its sums (no lobe in
        IR) needs none.
        """
        if self.ir is None:                                  # reused IR checkpoint: _refit_ir said so already
            return alpha, sigma, lobes, False
        new, new_sigma, new_lobes = self._refit_ir(labels, alpha, sigma, what="the final clusters", lobes=lobes)
        alpha, sigma, lobes = alpha.copy(), sigma.copy(), np.array(lobes, dtype="<U8")
        measured = np.asarray(getattr(getattr(self, "rgb", None), "specular", np.zeros(0, bool)), bool)
        again = []
        for c in range(min(len(alpha), len(new))):
            if new[c] == alpha[c] and new_lobes[c] == lobes[c]:
                continue
            swept = c < len(model) and (model[c] != "diffuse" or (c < len(measured) and measured[c]))
            if swept and (abs(new[c] / alpha[c] - 1.0) > 0.01 or new_lobes[c] != lobes[c]):
                again.append(f"cluster {c} {lobes[c]} {alpha[c]:.3f} -> {new_lobes[c]} {new[c]:.3f}")
            alpha[c], sigma[c], lobes[c] = new[c], new_sigma[c], new_lobes[c]
        if again:
            self._note("rgb: the final clusters' lobes moved by more than 1 % (" + ", ".join(again)
                       + "): their rho_s is measured once more")
        self._publish(force=True, alpha=np.asarray(alpha, np.float32), alpha_sigma=np.asarray(sigma, np.float32),
                      lobes=[str(x) for x in lobes])
        return alpha, sigma, lobes, bool(again)

    def _refit_ir(self, labels: np.ndarray, alpha: np.ndarray, sigma: np.ndarray,
                  what: str = "the colour pass's clusters", lobes=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """IR Ward fits of the clusters the colour pass left (split / merged), from the IR pass's buffers.

        A material the IR clustering could not tell apart (the demo's near-matte label, inside the
        paint's cluster) dilutes the cluster's lobe: on the demo the one IR cluster fitted alpha 0.051,
        while the paint's and the label's leaves fitted alone give 0.066 and 0.345 (truth 0.06 and
        0.35). Returns alpha, alpha_sigma and the lobe's name per cluster (the IR fit chooses Ward or
        GGX, :mod:`appfusion.ward_fit`); a cluster without a fit (or at a bound) keeps the given alpha
        and lobe (``lobes``, default Ward). Without the IR pass's buffers (its stage reused from an older checkpoint)
        nothing is refitted, and the scan log says so.
        """
        lobes = np.full(len(alpha), "ward", dtype="<U8") if lobes is None else np.array(lobes, dtype="<U8")
        if self.ir is None:
            self._note("rgb: the IR clusters' lobes were not refitted to the colour pass's clusters (the IR "
                       "pass was reused from a checkpoint, without the leaf HBSABs: written by an older engine)")
            return alpha, sigma, lobes
        alpha, sigma = alpha.copy(), sigma.copy()
        fitted = []
        infos = self.ir.fit_clusters(self._interior_labels(labels))[:len(alpha)]
        for c in infos:
            f = c.fit
            if f is not None and not f.at_bound and np.isfinite(f.alpha):
                alpha[c.label] = f.alpha
                sigma[c.label] = f.alpha_sigma
                lobes[c.label] = getattr(f, "lobe", "ward")
                fitted.append(f"cluster {c.label} {lobes[c.label]} alpha {f.alpha:.3f}")
        if fitted:
            self._note(f"rgb: IR lobes refitted to {what}: " + ", ".join(fitted))
        # the GUI and the report show these clusters' buffers, lobes and alphas from now on, not the IR's
        hb = [c.hbsab.value[0].copy() if c.hbsab is not None else None for c in infos]
        self._publish(force=True, hbsabs=hb, alpha=np.asarray(alpha, np.float32), alpha_sigma=np.asarray(sigma, np.float32),
                      lobes=[str(x) for x in lobes],
                      hbsab_fits=[self._ward_image(c) if h is not None else None for c, h in zip(infos, hb)])
        return alpha, sigma, lobes

    def _interior_labels(self, labels: np.ndarray) -> np.ndarray:
        """``labels`` with the points within ``ir_interior_m`` of another cluster moved to an extra label
        (``labels.max() + 1``) that no cluster's refit reads; a cluster that would keep under a quarter
        of its points keeps them all (as the colour pass's interior rule, ``RGBPass.interior_m``)."""
        from .points import interior_mask, interior_or_all

        r = float(self.config.ir_interior_m)
        lab = np.asarray(labels)
        if r <= 0 or self.points is None or lab.size == 0 or lab.max() == lab.min():
            return lab
        keep = interior_or_all(interior_mask(self.points[0], lab, r), lab)
        return np.where(keep, lab, int(lab.max()) + 1).astype(lab.dtype)

    # -- labels and painting ---------------------------------------------------------------------------
    def _current_labels(self) -> np.ndarray:
        rgb = getattr(self, "_rgb_result", None)
        if rgb is not None and "labels" in rgb:             # the RGB pass refined the IR clusters
            base = rgb["labels"]
        elif getattr(self, "_ir_result", None) is not None:
            base = self._ir_result["labels"]
        elif self.points is not None:
            base = np.zeros(len(self.points[0]), np.int32)
        else:
            return np.zeros(0, np.int32)
        return self._apply_paint_to(base)

    def _apply_paint_to(self, labels: np.ndarray) -> np.ndarray:
        if not self._painted:
            return labels
        out = np.array(labels, np.int32, copy=True)
        idx = np.fromiter(self._painted.keys(), np.int64)
        out[idx] = np.fromiter(self._painted.values(), np.int64)
        return out

    def _apply_paint(self) -> None:
        if self.ir is not None:
            for i, lab in self._painted.items():
                self.ir.set_labels([i], lab)
        self._publish(force=True, labels=self._current_labels())

    def _white_balancer(self, geo: "_Geometry | None"):
        """§4.2 white balance on the circles: centres from the printed layout, else as fused so far."""
        from calibration.white_balance import WhiteBalancer
        from .markers import marker_config_from_meta

        mc = marker_config_from_meta(self.source.meta if isinstance(self.source.meta, dict) else {})
        if mc.side_m:
            centers = mc.centres()
        elif geo is not None and geo.gp.tracker.initialised:
            from .frame import invert_pose, transform_points

            t = geo.gp.tracker
            centers = transform_points(invert_pose(t.marker_to_world()), t.centers)
        else:
            raise PassMissingError("white balance needs the marker layout (session meta extra.markers.side_m) "
                                   "or a frame showing all four circles first")
        return WhiteBalancer(centers=centers, radius=mc.radius_m)

    def _rgb_kwargs(self) -> dict[str, Any]:
        blur = float((self.env.meta or {}).get("blur_var_rad2", 0.0) or 0.0) if self.env is not None else 0.0
        return {"percentile": self.config.rho_d_percentile, "bins": self.config.rho_d_bins, "saturated": np.inf,
                "estimator": self.config.rho_d_estimator, "diffuse_tau": self.config.diffuse_tau,
                "rgb_sampling": self.config.rgb_sampling, "clip_correction": bool(self.config.rho_d_clip_correction),
                "map_blur_var": blur if self.config.map_blur_correction else 0.0}

    def _near_field(self):
        """The support plane as near-field light for the RGB pass (:mod:`appfusion.near_field`), or None
        (switched off, or the printed layout or the ball's centre unknown: noted)."""
        if not self.config.near_field or self.env is None:
            return None
        from .markers import marker_config_from_meta
        from .near_field import SupportPlaneLight

        mc = marker_config_from_meta(self.source.meta if isinstance(self.source.meta, dict) else {})
        sphere = (self.env.meta or {}).get("sphere") or {}
        if not mc.side_m or "center" not in sphere:
            self._note("rgb: near-field plane off (needs the printed marker layout and the mirror ball's centre); "
                       "the plane is lit as the ball saw it")
            return None
        try:
            nf = SupportPlaneLight.from_scan(self.env.radiance, mc.centres(), mc.radii(), sphere["center"],
                                             sphere.get("radius"))
        except AppFusionError as e:
            self._note(f"rgb: near-field plane off ({e})")
            return None
        if self.mesh is not None and len(self.mesh[1]):
            nf.with_object_shadow(*self.mesh)
        self._note("rgb: support plane as near-field light (paper radiance "
                   + ", ".join(f"{v:.3f}" for v in nf.paper) + ", circles 1, object shadow "
                   + ("on" if nf.shadow is not None else "off") + ")")
        return nf

    # -- results -------------------------------------------------------------------------------------
    def result(self):
        """The :class:`~appfusion.result.ScanResult` so far (partial before the scan ends)."""
        from .brdf import LOBES
        from .result import ScanResult

        if self.points is None:
            raise PassMissingError("no geometry yet: the object's points exist after the geometry pass")
        P, N = self.points
        labels = self._current_labels()
        ir = getattr(self, "_ir_result", None)
        rgb = getattr(self, "_rgb_result", None)
        k = int(labels.max()) + 1 if len(labels) else 1
        alpha = np.full(k, 0.3, np.float32)
        sigma = np.zeros(k, np.float32)
        model = ["diffuse"] * k
        lobes = np.full(k, "ward", dtype="<U8")
        if ir is not None:
            m = min(k, len(ir["alpha"]))
            alpha[:m], sigma[:m] = ir["alpha"][:m], ir["alpha_sigma"][:m]
            lobes[:m] = _ir_lobes(ir, len(ir["alpha"]))[:m]
            model[:m] = [str(lb) if f else "diffuse" for f, lb in zip(ir["fitted"][:m], lobes[:m])]
        if rgb is not None and "labels" in rgb and "alpha" in rgb:
            # the RGB pass refined the clusters (split / merged): its alphas are the clusters' alphas;
            # an IR sigma is kept where the cluster's alpha is an IR cluster's own
            ra = np.asarray(rgb["alpha"], np.float32)
            m = min(k, len(ra))
            alpha[:m] = ra[:m]
            sig_ir = {float(a): float(s_) for a, s_ in zip(ir["alpha"], ir["alpha_sigma"])} if ir is not None else {}
            sigma[:m] = [sig_ir.get(float(a), 0.0) for a in ra[:m]]
            if "alpha_sigma" in rgb:                          # lobes refitted to these clusters (_refit_ir)
                rs = np.asarray(rgb["alpha_sigma"], np.float32)[:m]
                sigma[:m] = np.where(np.isfinite(rs), rs, sigma[:m])
            if "lobe" in rgb:
                lobes[:m] = np.asarray(rgb["lobe"], str)[:m]
            model[:m] = [str(lb) for lb in lobes[:m]]
        rho_s = np.zeros((k, 3), np.float32)
        rho_s_sigma = np.full((k, 3), np.nan, np.float32)
        rho_d = np.full((len(P), 3), 0.5, np.float32)
        if rgb is not None:
            m = min(k, len(rgb["rho_s"]))
            rho_s[:m] = np.maximum(rgb["rho_s"][:m], 0)
            if "rho_s_sigma" in rgb:
                ms = min(k, len(rgb["rho_s_sigma"]))
                rho_s_sigma[:ms] = rgb["rho_s_sigma"][:ms]
            rho_d = np.clip(np.nan_to_num(rgb["rho_d"], nan=0.5), 0, None)
        if rgb is not None and "model" in rgb:             # the RGB pass's held-out model ladder
            for c, mm in enumerate(np.asarray(rgb["model"]).tolist()[:k]):
                if mm == "diffuse":
                    model[c] = "diffuse"
        model = [(mm if (mm in LOBES and rho_s[c].max() > 0) else "diffuse") for c, mm in enumerate(model)]
        V, F = self.mesh if self.mesh is not None else (np.zeros((0, 3)), np.zeros((0, 3), np.int32))
        info = {"timings": self.timings, "messages": self.messages, "config": self.config.to_json(),
                "rho_d_source": "rgb pass (Eq. 6)" if rgb is not None else "not estimated (0.5 grey)",
                "alpha_source": "ir pass (§5.1)" if ir is not None else "not estimated (0.3)"}
        return ScanResult(P, N, rho_d, labels, rho_s, alpha, sigma, mesh_vertices=V, mesh_faces=F,
                          envmap=None if self.env is None else self.env.radiance, model=model, info=info,
                          rho_s_sigma=rho_s_sigma)

    # -- running ---------------------------------------------------------------------------------------
    def run(self):
        """Run the whole scan (blocking) and return the :class:`~appfusion.result.ScanResult`.

        Recordings run their passes in order; a live source is recorded pass by pass into
        ``out_dir/live-session`` (crash-safe) and each pass is processed when the user moves on
        (:meth:`next_pass`) or stops. A stop keeps everything computed so far.
        """
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if not self.source.is_open:
            self.source.open()
        if not getattr(self.source, "is_recording", False):
            return self._run_live()
        return self._run_recording()

    def _run_recording(self):
        ranges = plan_passes(self.source)
        has = set(ranges)
        obj = "geometry" if "geometry" in has else ("scan" if "scan" in has else None)
        rgbp = "rgb" if "rgb" in has else ("scan" if "scan" in has else None)
        if obj is None:
            raise PassMissingError(f"the recording has no geometry or scan pass (it has: "
                                   f"{', '.join(sorted(has)) or 'no frames'}): nothing to reconstruct")
        caps = self.source.caps
        self._plan = {"passes": {k: list(v) for k, v in ranges.items()}}
        self._note("passes: " + ", ".join(f"{k} ({b - a} frames)" for k, (a, b) in ranges.items()))
        if self.ir_profile is None and "ir-calibration" in has:
            self._stage_ir_calibration(*ranges["ir-calibration"])
        if self.env is None and "environment" in has:
            self._stage_environment(*ranges["environment"])
        elif self.env is not None:
            self._note("environment: reusing the given environment map; the lighting pass is skipped")
        self._obj_pass = obj
        self._stage_geometry(*ranges[obj], obj)
        if self.stopped:
            return self._finish_partial()
        if "ir" in caps.streams and self.ir_profile is not None:
            try:
                self._stage_ir(*ranges[obj])
            except PassMissingError as e:                  # keep the geometry; the RGB pass can still run
                self._note(f"ir: {e}; continuing with one cluster and no roughness (diffuse-only model)")
        elif "ir" not in caps.streams:
            self._note("ir: the recording has no IR stream: one specular cluster, roughness not estimated "
                       "(diffuse-only model)")
        else:
            self._note("ir: no ir-calibration pass and no --ir-profile: roughness and clusters cannot be estimated")
        if self.stopped:
            return self._finish_partial()
        if rgbp is not None and "rgb" in caps.streams:
            if self.env is None:
                self._note("rgb: no environment pass and no --envmap: rho_d and rho_s need the lighting; "
                           "the result keeps geometry, clusters and roughness only")
            else:
                try:
                    self._stage_rgb(*ranges[rgbp], rgbp)
                except PassMissingError as e:              # keep geometry, clusters and roughness
                    self._note(f"rgb: {e}; the result keeps geometry, clusters and roughness only")
        else:
            self._note("rgb: the recording has no RGB pass: rho_d and rho_s cannot be estimated")
        return self._finish_partial()

    def _finish_partial(self):
        res = self.result()
        res.save(self.out_dir / "result.npz")
        self._result = res
        self._publish(force=True, stage="done", guidance=GUIDANCE["done"])
        return res

    def _run_live(self):
        """Record a live source pass by pass into ``out_dir/live-session``, then process the recording.

        Between two frames the pass and emitter state asked for (:meth:`next_pass`,
        :meth:`set_live_plan`) is applied to the device: its streams switch to what the pass needs
        (``select_pass``; a failure is noted and the running streams are kept) and an ``emitter``
        control, where the device has one, is switched. Frames are tagged with the pass (``pass``
        events) and, when asked, the emitter state (``emitter`` events). Recording ends at the end
        of the plan, at :meth:`stop`, or when the source ends or fails; the device is closed, the
        frames so far stay in the crash-safe session, and it is processed like any recording.

        Raises
        ------
        PassMissingError
            Not one frame was recorded.
        """
        from replay.session import SessionReader, SessionWriter

        from .errors import SourceError

        src, ctl = self.source, self._ctl
        name = str(getattr(src, "name", "live source"))
        rec_path = self.out_dir / "live-session"
        writer, it, applied = None, None, None
        n, per_pass = 0, {}
        why = "the source ended"
        try:
            while True:
                if not ctl.wait_if_paused():
                    why = "stopped"
                    break
                with ctl.lock:
                    if ctl.live_left == 0:
                        if not ctl.live_plan:
                            why = "the planned frames were recorded"
                            break
                        ctl.set_step(*ctl.live_plan.pop(0))
                    gen, p, em = ctl.live_gen, ctl.live_pass, ctl.live_emitter
                if gen != applied:
                    applied = gen
                    select = getattr(src, "select_pass", None)
                    if callable(select):
                        try:
                            select(p)
                        except SourceError as e:
                            self._note(f"live: {e}; the {p} frames keep the streams running now")
                    if em is not None and "emitter" in (src.controls or {}):
                        try:
                            src.set_control("emitter", em)
                        except SourceError as e:
                            self._note(f"live: {e}")
                    self._publish(force=True, stage=p, guidance=GUIDANCE.get(p, ""))
                if it is None:
                    it = iter(src)
                try:
                    frame = next(it)
                except StopIteration:
                    break
                frame = frame.replace(pass_name=p, **({} if em is None else {"emitter": em}))
                if writer is None:
                    writer = self._live_writer(SessionWriter, rec_path, frame)
                writer.write(frame)
                n += 1
                per_pass[p] = per_pass.get(p, 0) + 1
                with ctl.lock:
                    if ctl.live_gen == gen and ctl.live_left is not None:
                        ctl.live_left -= 1
                self._publish(stage=p, frame=n, last_frame=frame, guidance=GUIDANCE.get(p, ""))
        except AppFusionError as e:
            why = "the source failed"
            self._note(f"live source stopped: {e} (the {n} frames recorded so far are kept)")
        finally:
            try:
                if writer is not None:
                    writer.close()
            finally:
                if it is not None and hasattr(it, "close"):
                    it.close()
                src.close()  # release the device before the long processing
        if writer is None:
            raise PassMissingError(f"live: no frame was recorded from {name} ({why})")
        self._note(f"live: recorded {n} frames ({', '.join(f'{k} {v}' for k, v in per_pass.items())}) into "
                   f"{rec_path}; {why}; processing the passes")
        self.source = SessionReader(rec_path)
        self._ctl.stop_event.clear()
        return self._run_recording()

    def _live_writer(self, writer_cls, path: Path, first: Frame):
        """The session writer of a live recording, opened at its first frame (intrinsics, extrinsics,
        IR bits, emitter position and the source's ``extra`` meta such as the marker layout)."""
        src = self.source
        meta = src.meta if isinstance(src.meta, dict) else {}
        intr = dict(src.intrinsics or {})
        for s in first.streams:
            fi = getattr(first, f"{s}_intrinsics")
            if fi is not None:
                intr[s] = fi
        extra = json.loads(json.dumps(meta.get("extra") or {}, default=str))
        extra.setdefault("recorded_from", str(getattr(src, "name", "live")))
        ir_bits = meta.get("ir_bits") or extra.get("ir_bits") or 10
        return writer_cls(path, device=str(meta.get("device", getattr(src, "name", "live"))), intrinsics=intr,
                          depth_to_ir=first.depth_to_ir, depth_to_rgb=first.depth_to_rgb,
                          rgb_encoding=first.rgb_encoding, ir_bits=int(ir_bits), extra=extra,
                          emitter_position_m=meta.get("emitter_position_m") or (0.075, 0.0, 0.0),
                          notes="live scan (appfusion.pipeline.ScanRunner)")

    # -- export --------------------------------------------------------------------------------------
    def export(self, out_dir=None, truth=None, session=None) -> dict[str, Path]:
        """Write mesh, textures, environment map and report; returns the written paths. With ``truth``
        (a dict of metrics, shown in the report) and a synthetic ``session``, the exported files'
        own errors (:func:`appfusion.evaluate.export_error`) are added to ``truth``."""
        from .export import export_result
        from .report import write_report

        out = Path(out_dir or self.out_dir)
        res = self._result if self._result is not None else self.result()
        self._publish(force=True, stage="export", guidance=GUIDANCE["export"])
        files = export_result(res, out, texture_size=self.config.texture_size)
        if self.env is not None:
            files["envmap_npz"] = self.env.save_npz(out / "envmap.npz")
            files["envmap_exr"] = self.env.export_exr(out / "envmap.exr")
            files["envmap_hdr"] = self.env.export_hdr(out / "envmap.hdr")
        if truth is not None and session is not None:
            from .evaluate import export_error

            import cv2

            try:
                truth.update({k: round(v, 5) for k, v in export_error(out, session).items()})
            except (AppFusionError, OSError, ValueError, cv2.error) as e:   # the files are written: say so, go on
                self._note(f"export: the exported files could not be evaluated against the truth ({e})")
        figures = self._report_figures(out, res)
        figures.update(getattr(self, "_extra_figs", {}))
        tables = {"Time per stage": {k: v for k, v in self.timings.items()}}
        if truth is not None:
            tables["Errors against ground truth"] = truth
        files["report"] = write_report(out, res, title=f"appfusion scan of {getattr(self.source, 'path', self.source.name)}",
                                       figures=figures, tables=tables, notes=self.messages)
        self._publish(force=True, stage="done", guidance=GUIDANCE["done"])
        return files

    def _report_figures(self, out: Path, res) -> dict[str, Path]:
        from .report import fig_convergence, fig_envmap, fig_hbsabs

        rep = out / "report"
        rep.mkdir(parents=True, exist_ok=True)
        figs: dict[str, Path] = {}
        snap = self.snapshot()
        if snap.hbsabs and any(h is not None for h in snap.hbsabs):
            figs["HBSAB of each cluster with its fitted lobe, Ward or GGX (§5.1)"] = fig_hbsabs(
                list(snap.hbsabs), snap.hbsab_fits or [], rep / "hbsabs.png", lobes=snap.lobes)
        if snap.history or len(res.alpha):                  # resumed from checkpoints: the markers alone
            figs["Convergence of alpha and rho_s over frames (lines: the live sweep; markers: the exported "
                 "clusters' values, after any colour split and second sweep)"] = fig_convergence(
                snap.history, rep / "convergence.png", final={"alpha": np.asarray(res.alpha), "rho_s": np.asarray(res.rho_s)})
        if self.env is not None:
            figs["Environment map and coverage (§4.3)"] = fig_envmap(self.env.radiance, rep / "envmap.png",
                                                                    self.env.known)
        return figs


def run_scan(session, out_dir, config: ScanConfig | None = None, envmap=None, ir_profile=None,
             skip_bad: bool = False, progress: bool = True, log=print, evaluate: bool = True) -> str:
    """``appfusion scan``: open a recording, run every pass, export, evaluate against truth, report.

    Returns a short human-readable summary. Checkpoints in ``out_dir/state`` make a rerun after a
    crash resume from the last finished stage.
    """
    from replay.open import open_recording

    from .evaluate import evaluate_result, truth_dir

    out_dir = Path(out_dir)
    t0 = time.perf_counter()
    src = open_recording(session, skip_bad=skip_bad)
    with src:
        runner = ScanRunner(src, out_dir, config=config, envmap=envmap, ir_profile=ir_profile, log=log,
                            progress=progress)
        res = runner.run()
        truth_table = None
        if evaluate and truth_dir(session) is not None:
            times = src.timestamps() if callable(getattr(src, "timestamps", None)) else getattr(src, "timestamps", None)
            m = evaluate_result(res, session, poses=runner.poses, timestamps=times)
            pairs = m.pop("_relit_pairs", None)
            m.pop("cluster_to_material", None)
            truth_table = {k: (round(v, 5) if isinstance(v, float) else v) for k, v in m.items()}
            (out_dir / "metrics.json").write_text(json.dumps(truth_table, indent=2))
            if pairs:
                from .report import fig_pairs

                (out_dir / "report").mkdir(parents=True, exist_ok=True)
                runner._extra_figs = {"Relit under the second environment map: capture vs reference":
                                      fig_pairs(pairs, out_dir / "report" / "relit.png")}
        files = runner.export(out_dir, truth=truth_table, session=session if truth_table is not None else None)
        if truth_table is not None:
            (out_dir / "metrics.json").write_text(json.dumps(truth_table, indent=2))
    elapsed = time.perf_counter() - t0
    lines = [f"scan of {session}: {len(res.positions)} points, {res.n_clusters} cluster(s), "
             f"alpha = {', '.join(f'{a:.3f}' for a in res.alpha)}; {elapsed:.1f} s",
             f"wrote {files['glb']}, {files['obj']}, {files['ply']}, report {files['report']}"]
    if truth_table:
        lines.append("against truth: " + ", ".join(f"{k} {v:.4g}" for k, v in truth_table.items()
                                                   if isinstance(v, float)))
    (out_dir / "summary.txt").write_text("\n".join(lines) + "\n")
    return "\n".join(lines)


@dataclass
class _Track:
    """Tracking outcome of one frame, in the marker frame."""

    pose: np.ndarray | None
    state: str
    markers_visible: int


class _MarkerPose:
    """Camera pose from the circles of one frame (rigid fit of the detected centres to the printed
    layout, marker frame). Needs the layout (``extra.markers.side_m``) and, to be unambiguous, the key
    circle (``key_radius_m``); without a key circle the pose is only defined up to a quarter turn and
    this tracker refuses.

    Four or three circles fix the pose on their own; two fix it with the support plane's normal, once
    they are numbered (:meth:`_two`: by the key circle, or by the pose of the last frame tracked, kept
    in :attr:`last`). Frames are expected in recording order, as a pass plays them."""

    #: the last frame's pose numbers two circles when one numbering puts the camera within this
    #: distance of it (metres, a radian of turn counted as 0.5 m) and every other numbering at least
    #: twice as far and beyond it (another numbering turns the camera by 90 or 180 degrees about the
    #: plane's normal: 0.8 m or more)
    TWO_CIRCLE_PRIOR_M = 0.25

    def __init__(self, meta: dict):
        from .markers import marker_config_from_meta

        self.cfg = marker_config_from_meta(meta if isinstance(meta, dict) else {})
        if not (self.cfg.side_m and self.cfg.key_radius_m):
            raise PassMissingError("the RGB pass has no depth-tracked poses, and marker poses need the printed "
                                   "layout with its key circle (session meta extra.markers side_m, key_radius_m)")
        self.layout = self.cfg.centres()
        self.last: np.ndarray | None = None

    def track(self, frame: Frame) -> _Track:
        from .markers import detect_markers

        return self.track_detection(detect_markers(frame, self.cfg))

    def track_detection(self, det) -> _Track:
        """:meth:`track` from a :class:`~appfusion.markers.MarkerDetection` (four, three or two
        circles); a pose found is kept as :attr:`last`."""
        from .fusion import kabsch

        if det.complete:
            T = kabsch(det.centers, self.layout)  # depth camera -> marker frame = camera-to-world pose
            tr = _Track(T, "ok", 4)
        elif det.n == 3:
            idx = self._three(det)
            tr = _Track(None, "lost", 3) if idx is None else _Track(kabsch(det.centers, self.layout[idx]), "ok", 3)
        else:
            T = self._two(det)
            tr = _Track(T, "lost" if T is None else "ok", det.n)
        if tr.pose is not None:
            self.last = tr.pose
        return tr

    def _two(self, det) -> np.ndarray | None:
        """The pose from two circles and the support plane's normal (beyond the paper), or None.

        The rotation takes the normal to the marker frame's +z and the line between the two centres
        (projected on the plane) to the line between the layout's circles; the translation matches
        their midpoints. Each numbering of the pair consistent with the layout (their distance within
        1.5 cm of the side or the diagonal; a detection with the key's radius is circle 1 and only it)
        gives a pose. One numbering alone (the key circle and the one across the diagonal) is taken;
        else the one whose pose is nearest :attr:`last` (translation plus 0.5 m per radian of
        rotation), when it is within :attr:`TWO_CIRCLE_PRIOR_M` and every other numbering at least
        twice as far and beyond it. On the demo session 30 of the RGB pass's 200 frames see two
        circles only.
        """
        from .fusion import anchor_pose, rotation_angle_deg

        if det.n != 2 or det.normal is None:
            return None
        P = np.asarray(det.centers, float)
        n = np.asarray(det.normal, float)
        n = n / np.linalg.norm(n)
        if float(n @ P.mean(axis=0)) > 0:                       # the normal must face the camera
            n = -n
        dist = float(np.linalg.norm(P[1] - P[0]))
        is_key = self._is_key(det)
        if is_key.all():
            return None
        z = np.array([0.0, 0.0, 1.0])
        poses = []
        for i, j in itertools.permutations(range(4), 2):
            if (i == 0) != bool(is_key[0]) or (j == 0) != bool(is_key[1]):
                continue
            if abs(float(np.linalg.norm(self.layout[j] - self.layout[i])) - dist) > 0.015:
                continue
            # the two centres and the plane's normal, in the camera and in the marker frame
            T = anchor_pose((P, self.layout[[i, j]], z, n))
            if T is not None:
                poses.append(T)
        if len(poses) == 1 and is_key.any():
            return poses[0]
        if not poses or self.last is None:
            return None

        def gap(T):                                           # metres, a radian counted as 0.5 m
            turn = np.radians(rotation_angle_deg(T[:3, :3].T @ self.last[:3, :3]))
            return float(np.linalg.norm(T[:3, 3] - self.last[:3, 3]) + 0.5 * turn)

        d = np.array([gap(T) for T in poses])
        order = np.argsort(d)
        best = d[order[0]]
        if best > self.TWO_CIRCLE_PRIOR_M:
            return None
        if len(d) > 1 and (d[order[1]] < 2 * best or d[order[1]] <= self.TWO_CIRCLE_PRIOR_M):
            return None
        return poses[order[0]]

    def _is_key(self, det) -> np.ndarray:
        """(K,) bool: detections whose radius is the key circle's (nearer it than the others')."""
        key_r, r0 = float(self.cfg.key_radius_m), float(self.cfg.radius_m)
        return np.abs(np.asarray(det.radii, float) - key_r) < 0.5 * abs(key_r - r0)

    def _three(self, det) -> np.ndarray | None:
        """Circle numbers (0-based) of three detected circles, or None
        (:func:`appfusion.markers.number_three` with the printed side)."""
        from .markers import number_three

        return number_three(det, self.cfg, self.cfg.side_m)


class _Geometry:
    """The pipeline's view of :class:`appfusion.geometry_pass.GeometryPass` (§4.1).

    ``track`` returns marker-frame poses once the four circles have defined the marker frame (frames
    before that have no usable pose for the appearance passes and are skipped by them).
    """

    def __init__(self, meta: dict, config: ScanConfig, surface: bool = True):
        """``surface=False``: tracking only (the environment pass), no surface volume to feed
        (``FusionConfig.surface_max_incidence_deg``): its mesh is never extracted."""
        from .fusion import FusionConfig
        from .geometry_pass import GeometryConfig, GeometryPass

        gcfg = GeometryConfig(n_points=config.n_points, box_height=config.box_height_m,
                              refuse_voxel_scale=float(config.refuse_voxel_scale),
                              refuse_fine_scale=config.refuse_fine_scale,
                              refuse_trunc_voxels=config.refuse_trunc_voxels,
                              refuse_fine_trunc_voxels=config.refuse_fine_trunc_voxels,
                              refuse_fine_trunc_min_frames=int(config.refuse_fine_trunc_min_frames),
                              crease_radius_voxels=config.crease_radius_voxels,
                              plane_snap=bool(config.plane_snap))
        fc = {} if surface else {"surface_max_incidence_deg": None}
        if config.voxel_m:
            fc["voxel_size"] = config.voxel_m
            gcfg.fixed_voxel = True
        if fc:
            gcfg.fusion = FusionConfig(**fc)
        self.gp = GeometryPass(gcfg, meta=meta)

    @property
    def box(self):
        return self.gp.box

    def track(self, frame: Frame) -> _Track:
        st = self.gp.add_frame(frame)
        pose = st.pose_marker if st.ok else None
        state = st.state if st.state != "first" else "ok"
        return _Track(pose, state, int(st.markers_found))

    def finish(self, n_points: int):
        """Mesh (V, F), points and normals in the marker frame, and marker-frame poses per frame index."""
        res = self.gp.result(n_points=n_points)
        V = np.asarray(res.mesh.vertices, np.float32)
        F = np.asarray(res.mesh.triangles, np.int32)
        # only frames with a marker-frame pose: those tracked once the four circles had fixed the
        # marker frame, and those before it anchored on the circles seen so far (session 27: the first
        # two of the synthetic demo's geometry pass show three circles; unanchored, such frames came
        # out 5-10 cm off after the final marker transform and were left out here),
        # and only frames tracked: a lost frame's state keeps the last good pose (the previous frame's,
        # 9 cm away on the --quick bench's coarse orbit), which is no pose of this frame
        since = np.array([st.pose_marker is not None and st.ok for st in res.states], bool)
        poses = {int(i): p for i, p, ok in zip(res.frame_indices, res.poses, since) if ok and np.all(np.isfinite(p))}
        return V, F, res.points.astype(np.float32), res.normals.astype(np.float32), poses
