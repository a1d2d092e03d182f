"""Camera poses from the printed circles for a separate RGB pass (appfusion.pipeline._MarkerPose)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from appfusion.frame import invert_pose
from appfusion.markers import MarkerDetection
from appfusion.pipeline import _MarkerPose

META = {"extra": {"markers": {"radius_m": 0.025, "key_radius_m": 0.035, "side_m": 0.3, "layout": "square"}}}


def _pose(seed):
    """A camera above the plane looking at the centre (camera to marker frame)."""
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(20, 70))
    eye = 0.7 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


@pytest.mark.parametrize("seed", range(4))
def test_any_three_circles_give_the_pose(seed):
    mp = _MarkerPose(META)
    T = _pose(seed)
    Ti = invert_pose(T)
    layout_cam = mp.layout @ Ti[:3, :3].T + Ti[:3, 3]
    normal = Ti[:3, :3] @ np.array([0, 0, 1.0])
    radii = np.array([0.035, 0.025, 0.025, 0.025])
    rng = np.random.default_rng(seed)
    for keep in itertools.combinations(range(4), 3):
        keep = list(rng.permutation(keep))              # detection order is arbitrary
        det = MarkerDetection(layout_cam[keep] + rng.normal(0, 3e-4, (3, 3)), radii[keep], np.zeros((3, 2)),
                              normal, 0.0, False, "rgb")
        idx = mp._three(det)
        assert idx is not None and list(idx) == keep
        tr = mp.track_detection(det)
        assert tr.state == "ok" and np.linalg.norm(tr.pose[:3, 3] - T[:3, 3]) < 3e-3


def _two_detection(mp, T, keep, rng):
    Ti = invert_pose(T)
    layout_cam = mp.layout @ Ti[:3, :3].T + Ti[:3, 3]
    normal = Ti[:3, :3] @ np.array([0, 0, 1.0])
    radii = np.array([0.035, 0.025, 0.025, 0.025])
    return MarkerDetection(layout_cam[keep] + rng.normal(0, 3e-4, (2, 3)), radii[keep], np.zeros((2, 2)),
                           normal * rng.choice([-1.0, 1.0]), 0.0, False, "rgb")


@pytest.mark.parametrize("seed", range(4))
def test_two_circles_and_the_plane_give_the_pose_once_numbered(seed):
    """Two circles and the support plane's normal fix the pose once the circles are numbered: by the
    key circle with the one across the diagonal alone, else by the last frame's pose (the nearest
    numbering, when every other one puts the camera far from it). A pair that no numbering makes
    unambiguous is lost."""
    rng = np.random.default_rng(seed)
    T = _pose(seed)
    step = np.eye(4)
    step[:3, 3] = rng.normal(0, 0.04, 3)                 # the last frame: 4-7 cm away
    for keep in itertools.permutations(range(4), 2):
        keep = list(keep)
        mp = _MarkerPose(META)
        tr = mp.track_detection(_two_detection(mp, T, keep, rng))
        if sorted(keep) == [0, 2]:                       # key + diagonal: no prior needed
            assert tr.state == "ok" and tr.markers_visible == 2
            assert np.linalg.norm(tr.pose[:3, 3] - T[:3, 3]) < 3e-3
            assert np.allclose(tr.pose[:3, :3], T[:3, :3], atol=3e-3)
        else:
            assert tr.pose is None and tr.state == "lost"
        mp.last = T @ step                               # the last frame tracked, nearby
        tr = mp.track_detection(_two_detection(mp, T, keep, rng))
        assert tr.state == "ok", keep
        assert np.linalg.norm(tr.pose[:3, 3] - T[:3, 3]) < 3e-3
        assert np.allclose(tr.pose[:3, :3], T[:3, :3], atol=3e-3)
        assert mp.last is tr.pose
        if sorted(keep) != [0, 2]:
            far = T.copy()
            far[:3, 3] += [0.3, 0.0, 0.0]                    # a last pose 30 cm away numbers nothing
            mp.last = far
            assert mp.track_detection(_two_detection(mp, T, keep, rng)).pose is None


def test_three_circles_not_forming_the_layout_are_refused():
    mp = _MarkerPose(META)
    pts = np.array([[0.0, 0, 0.7], [0.3, 0, 0.7], [0.0, 0.2, 0.7]])   # a 0.3 x 0.2 right triangle
    det = MarkerDetection(pts, np.full(3, 0.025), np.zeros((3, 2)), np.array([0, 0, -1.0]), 0.7, False, "rgb")
    assert mp._three(det) is None
    two = MarkerDetection(pts[:2], np.full(2, 0.025), np.zeros((2, 2)), np.array([0, 0, -1.0]), 0.7, False, "rgb")
    assert mp.track_detection(two).pose is None                      # two circles, no key, no last pose
    mp.last = np.eye(4)
    short = MarkerDetection(pts[[0, 2]], np.full(2, 0.025), np.zeros((2, 2)), np.array([0, 0, -1.0]), 0.7, False,
                            "rgb")
    assert mp.track_detection(short).pose is None                    # 0.2 m apart: no side, no diagonal


def _pass_with_square(pose, lost=True):
    """A geometry pass whose tracker has fused the four circles of the 0.3 m square (marker frame =
    world) and whose fusion predicts ``pose`` (the stale last good pose while ``lost``)."""
    from types import SimpleNamespace

    from appfusion.geometry_pass import GeometryPass

    gp = GeometryPass()
    C = np.array([[0.15, -0.15, 0.0], [0.15, 0.15, 0.0], [-0.15, 0.15, 0.0], [-0.15, -0.15, 0.0]])
    gp.tracker.sums[:] = C
    gp.tracker.counts[:] = 1
    gp.tracker.weights[:] = 1
    gp.tracker.normal_sum[:] = [0, 0, 2.0]
    gp.fusion = SimpleNamespace(predicted_pose=lambda: pose.copy(), lost=lost)
    return gp, C


def test_a_circle_detected_twice_keeps_the_frame_anchored():
    """Two detections near one fused circle: the nearer is that circle's anchor, the others stay
    anchors (dropping every anchor of the frame let the ICP slide 4 cm on the quick bench session)."""
    from appfusion.markers import MarkerDetection

    gp, C = _pass_with_square(np.eye(4), lost=False)
    seen = C[[0, 1, 3, 1]] + np.array([[0.002, 0, 0], [0.0, 0.003, 0], [0, 0, 0.001], [0.006, 0.0, 0.0]])
    det = MarkerDetection(seen, np.full(4, 0.03), np.zeros((4, 2)), np.array([0, 0, 1.0]), 0.0, False, "ir")
    src, dst, normal = gp._anchors(det)
    assert len(src) == 3
    assert np.allclose(dst, C[[0, 1, 3]]) and np.allclose(src, seen[:3])
    assert np.allclose(normal, [0, 0, 1])   # the support plane's normal, for the anchors' weights


def _orbit_pose(azimuth_deg, radius=0.65, height=0.45):
    """Camera-to-world pose on an orbit about the square's centre, looking at it (z forward)."""
    a = np.radians(azimuth_deg)
    eye = np.array([radius * np.cos(a), radius * np.sin(a), height])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return T


@pytest.mark.parametrize("seen", [[0, 1, 2], [1, 3, 0], [2, 3, 1, 0]])
def test_circles_seen_while_lost_are_matched_by_their_shape(seen):
    """Three or four circles in a frame after tracking was lost 30 degrees of orbit ago: each one is
    paired with the fused circle it is, found from the square's shape and the last good pose's
    rotation, not from where that stale pose puts it (9-16 cm off: too far for the nearest-circle
    rule, which kept fewer than three anchors or none, and the relocalised pose ran away on the
    30-frame quick matte session)."""
    from appfusion.frame import invert_pose, transform_points
    from appfusion.markers import MarkerDetection

    true, stale = _orbit_pose(40.0), _orbit_pose(10.0)
    gp, C = _pass_with_square(stale)
    rng = np.random.default_rng(len(seen))
    cam = transform_points(invert_pose(true), C[seen]) + rng.normal(0, 0.001, (len(seen), 3))
    det = MarkerDetection(cam, np.full(len(seen), 0.02), np.zeros((len(seen), 2)), np.array([0, 0, 1.0]), 0.0,
                          len(seen) == 4, "ir")
    src, dst, _ = gp._anchors(det)
    assert len(src) == len(seen)
    assert np.allclose(dst, C[seen])
    # the nearest-circle rule through the stale pose would not have given these anchors
    W = transform_points(stale, cam)
    d = np.linalg.norm(W[:, None] - C[None], axis=2)
    assert not (d.min(1) < 0.06).all() or not np.array_equal(d.argmin(1), seen)


def test_circles_that_fit_no_square_give_no_anchors_while_lost():
    """A false circle among three (a reflection, 7 cm from where any circle could be): no one-to-one
    assignment fits the square, so the frame relocalises without anchors rather than on wrong ones."""
    from appfusion.frame import invert_pose, transform_points
    from appfusion.markers import MarkerDetection

    true = _orbit_pose(40.0)
    gp, C = _pass_with_square(_orbit_pose(10.0))
    pts = np.vstack([C[[0, 1]], [[0.0, 0.07, 0.0]]])
    cam = transform_points(invert_pose(true), pts)
    det = MarkerDetection(cam, np.full(3, 0.02), np.zeros((3, 2)), np.array([0, 0, 1.0]), 0.0, False, "ir")
    assert gp._anchors(det) is None


def _keyed_pass(pose, lost=False):
    """:func:`_pass_with_square` with a key circle (35 mm, the others 25 mm): circle 1 at (+, +), then
    clockwise seen from +z, as printed (``MarkerConfig.centres``)."""
    from types import SimpleNamespace

    from appfusion.geometry_pass import GeometryConfig, GeometryPass
    from appfusion.markers import MarkerConfig

    cfg = MarkerConfig(radius_m=0.025, side_m=0.3, key_radius_m=0.035)
    gp = GeometryPass(GeometryConfig(markers=cfg))
    C = cfg.centres()
    gp.tracker.sums[:] = C
    gp.tracker.counts[:] = 1
    gp.tracker.weights[:] = 1
    gp.tracker.normal_sum[:] = [0, 0, 2.0]
    gp.fusion = SimpleNamespace(predicted_pose=lambda: pose.copy(), lost=lost)
    return gp, C, cfg


@pytest.mark.parametrize("seen", [[0, 1, 2], [3, 1, 0], [2, 3, 1], [1, 2, 3]])
def test_three_circles_numbered_by_the_key_pair_by_number_through_a_stale_prediction(seen):
    """Three circles seen 30 degrees of orbit from the prediction (tracking not lost: a fast sweep
    between two tracked frames): numbered by the key circle, they pair with the fused circles they
    are. A key misread as a plain circle numbers them a quarter turn off; where the prediction is
    right and pairs all three otherwise, the prediction's pairing is kept."""
    from appfusion.frame import invert_pose, transform_points
    from appfusion.markers import MarkerDetection

    true = _orbit_pose(40.0)
    rng = np.random.default_rng(len(seen) + seen[0])
    Ti = invert_pose(true)
    normal = Ti[:3, :3] @ np.array([0, 0, 1.0])
    gp, C, cfg = _keyed_pass(_orbit_pose(10.0))
    cam = transform_points(Ti, C[seen]) + rng.normal(0, 0.001, (3, 3))
    det = MarkerDetection(cam, cfg.radii()[seen], np.zeros((3, 2)), normal, 0.0, False, "ir")
    src, dst, _ = gp._anchors(det)
    assert np.allclose(dst, C[seen]) and np.allclose(src, cam)
    W = transform_points(_orbit_pose(10.0), cam)          # the stale pose pairs them otherwise, or not at all
    d = np.linalg.norm(W[:, None] - C[None], axis=2)
    assert not (d.min(1) < 0.075).all() or not np.array_equal(d.argmin(1), seen)
    # a misread radius, a right prediction: the prediction's pairing
    misread = MarkerDetection(cam, np.full(3, 0.025) if 0 in seen else np.r_[0.035, 0.025, 0.025], np.zeros((3, 2)),
                              normal, 0.0, False, "ir")
    gp, C, cfg = _keyed_pass(true)
    assert gp.tracker.number_three(misread) is not None
    assert not np.array_equal(gp.tracker.number_three(misread), seen)
    src, dst, _ = gp._anchors(misread)
    assert np.allclose(dst, C[seen])


def test_the_key_circle_and_the_one_across_the_diagonal_fix_the_pose_with_the_plane():
    """Two circles: only the key circle with circle 3 is numbered (any other pair fits two or more
    places of the square), and with the support plane's normal in both frames the two give the
    camera pose (``fusion.anchor_pose``); the geometry pass passes that normal only for a numbered
    pair, so that two circles paired by nearness never move tracking."""
    from appfusion.frame import invert_pose, transform_points
    from appfusion.fusion import anchor_pose, rotation_angle_deg
    from appfusion.markers import MarkerDetection

    true = _orbit_pose(40.0)
    Ti = invert_pose(true)
    normal = Ti[:3, :3] @ np.array([0, 0, 1.0])
    rng = np.random.default_rng(3)
    for keep in itertools.permutations(range(4), 2):
        gp, C, cfg = _keyed_pass(_orbit_pose(10.0), lost=True)
        cam = transform_points(Ti, C[list(keep)]) + rng.normal(0, 5e-4, (2, 3))
        det = MarkerDetection(cam, cfg.radii()[list(keep)], np.zeros((2, 2)), normal, 0.0, False, "ir")
        idx = gp.tracker.number_two(det)
        a = gp._anchors(det)
        if sorted(keep) == [0, 2]:
            assert list(idx) == list(keep)
            assert len(a) == 4 and np.allclose(a[1], C[list(keep)]) and np.allclose(a[3], normal)
            T = anchor_pose(a)
            assert np.linalg.norm(T[:3, 3] - true[:3, 3]) < 6e-3 and rotation_angle_deg(T[:3, :3].T @ true[:3, :3]) < 0.5
        else:
            assert idx is None and (a is None or len(a) == 3)
    assert anchor_pose((cam, C[:2], None)) is None                     # two points without the normals
    assert np.allclose(anchor_pose((C[:3], C[:3])), np.eye(4), atol=1e-9)   # three: their rigid fit
