"""Tests of calibration.white_balance: per-frame reference white from the marker circles (§4.2)."""

from __future__ import annotations

import numpy as np
import pytest

from appfusion.errors import AppFusionError
from appfusion.frame import invert_pose, linear_to_srgb, make_pose, transform_points
from appfusion.geometry_synth import make_sequence
from calibration.white_balance import WhiteBalancer, circle_pixel_masks

UP = np.array([0.0, 0.0, 1.0])


@pytest.fixture(scope="module")
def seq():
    return make_sequence(16, 320, 240, seed=2)


def _rgb_world_to_cam(f):
    return invert_pose(f.pose @ invert_pose(f.depth_to_rgb))


def _circle_mean(rgb, f, center, radius):
    m = circle_pixel_masks(center[None], radius, UP, _rgb_world_to_cam(f), f.rgb_intrinsics)[0]
    assert m is not None
    mask, (r0, r1, c0, c1) = m
    return rgb[r0:r1, c0:c1][mask].mean(0)


def test_white_balance_removes_cast_and_exposure(seq):
    """Reference from three circles; the fourth (held out) reads neutral white within 1% in every
    frame although each frame has its own colour cast and exposure."""
    errs = []
    for hold in range(4):
        use = [i for i in range(4) if i != hold]
        wb = WhiteBalancer(seq.marker_centers[use], seq.marker_radius)
        for f, cast in zip(seq.frames, seq.rgb_gain):
            r = wb.balance(f, f.pose)
            assert not r.flagged and sorted(r.circles) == [0, 1, 2]
            mean = _circle_mean(r.rgb, f, seq.marker_centers[hold], seq.marker_radius)
            errs.append(np.abs(mean - 1.0).max())
            # the applied gain undoes the cast: gain x cast is grey and the same in every frame
            g = r.gain * cast
            assert np.ptp(g) / g.mean() < 0.01
    assert max(errs) < 0.01, f"held-out circle off white by {max(errs):.4f}"
    # before balancing the same circle is far from white
    f = seq.frames[3]
    raw = _circle_mean(f.rgb_linear(), f, seq.marker_centers[0], seq.marker_radius)
    assert np.abs(raw - 1.0).max() > 0.1


def test_white_level_and_srgb_input(seq):
    f = seq.frames[5]
    wb = WhiteBalancer(seq.marker_centers, seq.marker_radius, white_level=0.8)
    r = wb.balance(f, f.pose)
    assert np.allclose(_circle_mean(r.rgb, f, seq.marker_centers[1], seq.marker_radius), 0.8, atol=0.008)
    s8 = (linear_to_srgb(f.rgb) * 255 + 0.5).astype(np.uint8)
    r8 = WhiteBalancer(seq.marker_centers, seq.marker_radius).balance(f.replace(rgb=s8, rgb_encoding="srgb8"), f.pose)
    assert r8.rgb.dtype == np.float32
    assert np.allclose(_circle_mean(r8.rgb, f, seq.marker_centers[1], seq.marker_radius), 1.0, atol=0.01)


def test_frames_without_visible_markers_are_flagged(seq):
    wb = WhiteBalancer(seq.marker_centers, seq.marker_radius)
    f0, f1 = seq.frames[0], seq.frames[1]
    away = f0.pose @ make_pose(np.diag([-1.0, 1.0, -1.0]))     # camera turned away from the table
    first = wb.balance(f0, away)
    assert first.flagged and first.reference is None and np.allclose(first.gain, 1.0)
    assert np.array_equal(first.rgb, f0.rgb)
    good = wb.balance(f1, f1.pose)
    assert not good.flagged
    later = wb.balance(seq.frames[2], away)
    assert later.flagged and np.allclose(later.reference, good.reference) and np.allclose(later.gain, good.gain)
    assert wb.flagged_frames == [0, 2]


def test_occluded_and_saturated_circles_are_skipped(seq):
    f = seq.frames[6]
    wb = WhiteBalancer(seq.marker_centers, seq.marker_radius)
    assert sorted(wb.balance(f, f.pose).circles) == [0, 1, 2, 3]
    # something 10 cm in front of circle 1 in the depth image
    K = f.depth_intrinsics
    uv, z = K.project(transform_points(invert_pose(f.pose), seq.marker_centers[[0]]))
    depth = f.depth.copy()
    u, v = np.rint(uv[0]).astype(int)
    depth[max(v - 12, 0):v + 13, max(u - 12, 0):u + 13] = z[0] - 0.1
    assert sorted(wb.balance(f.replace(depth=depth), f.pose).circles) == [1, 2, 3]
    # circle 2 blown out in RGB
    rgb = f.rgb.copy()
    m = circle_pixel_masks(seq.marker_centers[[1]], seq.marker_radius, UP, _rgb_world_to_cam(f), f.rgb_intrinsics,
                           shrink=0.0)[0]
    mask, (r0, r1, c0, c1) = m
    rgb[r0:r1, c0:c1][mask] = 1.0
    r = wb.balance(f.replace(rgb=rgb), f.pose)
    assert sorted(r.circles) == [0, 2, 3]
    assert np.allclose(_circle_mean(r.rgb, f, seq.marker_centers[2], seq.marker_radius), 1.0, atol=0.01)


def test_white_balance_bad_input(seq):
    f = seq.frames[0]
    wb = WhiteBalancer(seq.marker_centers, seq.marker_radius)
    with pytest.raises(AppFusionError, match="no RGB"):
        wb.balance(f.replace(rgb=None), f.pose)
    with pytest.raises(AppFusionError, match="pose"):
        wb.balance(f, np.full((4, 4), np.nan))
    with pytest.raises(AppFusionError, match="does not match"):
        wb.balance(f.replace(rgb=f.rgb[:100]), f.pose)
    with pytest.raises(AppFusionError):
        WhiteBalancer(seq.marker_centers, -0.02)


def test_a_pose_that_puts_the_circles_on_paper_gives_no_reference(seq):
    """Tracking gone wrong by a few centimetres: the circles' outlines fall on the black paper. Their
    pixels are no brighter than the paper around them, so no reference is taken from them (it would
    have been the paper, ~20 times too dark) and the frame is flagged without a reference."""
    f = seq.frames[4]
    wb = WhiteBalancer(seq.marker_centers, seq.marker_radius)
    good = wb.balance(f, f.pose)
    assert good.reference is not None and not good.flagged
    off = f.pose.copy()
    off[:3, 3] += np.array([0.06, -0.05, 0.0])          # 8 cm sideways: every circle lands on paper
    bad = wb.balance(f, off)
    assert bad.reference is None and bad.flagged and bad.circles == []
    # a contrast of 1 accepts anything (the old behaviour): the paper becomes the reference
    lax = WhiteBalancer(seq.marker_centers, seq.marker_radius, min_contrast=1.0).balance(f, off)
    assert lax.reference is not None and lax.reference.mean() < 0.3 * good.reference.mean()
