"""Renderer: deterministic textured scenes, exact depth, and geometry that agrees with the poses (warp test)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vi3_core import so3
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import EUROC_CAM0, cached_sequence
from vi3_core.dataset.sequence import make_clip
from vi3_core.render.raycast import Renderer
from vi3_core.render.scene import SCENES, make_scene
from vi3_core.sim.trajectory import make_trajectory


@pytest.fixture(scope="module")
def room():
    return make_scene("room", 3)


@pytest.mark.slow
def test_render_is_deterministic_textured_and_inside_the_room(room):
    traj = make_trajectory("drone", 3, center=tuple(room.center), extent=tuple(room.extent))
    T_WC = traj.T_WB(np.array([1.3]))[0] @ EUROC_CAM0.T_BC
    image, depth = Renderer(room, EUROC_CAM0).render(T_WC)
    image2, depth2 = Renderer(make_scene("room", 3), EUROC_CAM0).render(T_WC)
    assert image.shape == (480, 752) and image.dtype == np.uint8
    assert np.array_equal(image, image2) and np.array_equal(depth, depth2, equal_nan=True)
    assert not np.array_equal(image, Renderer(make_scene("room", 4), EUROC_CAM0).render(T_WC)[0])
    # Enough well-spread corners for a classical tracker in every quadrant of the image.
    corners = cv2.goodFeaturesToTrack(image, 400, 0.01, 10).reshape(-1, 2)
    assert len(corners) >= 300
    quadrant = (corners[:, 0] > 376).astype(int) + 2 * (corners[:, 1] > 240)
    assert np.bincount(quadrant, minlength=4).min() >= 30
    assert np.isfinite(depth).all() and depth.min() > 0.3
    assert depth.max() < np.linalg.norm(room.room_hi - room.room_lo)


def test_depth_is_the_exact_distance_to_a_known_wall(room):
    """A camera looking straight at the +x wall from a known point sees it at exactly that z-depth."""
    R_WC = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axis along +x, y down
    p = np.array([room.room_hi[0] - 0.9, 0.0, 2.5])  # above every box (<= 1.6 m) in the whole field of view
    assert room.box_hi[:, 2].max() < 2.5 - 0.9 * np.tan(np.radians(32))
    depth = Renderer(room, EUROC_CAM0).render(so3.make_T(R_WC, p))[1]
    np.testing.assert_allclose(depth, 0.9, atol=2e-6)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENES))
def test_flight_stays_in_the_room_and_clear_of_boxes(name):
    scene = make_scene(name, 1)
    for seed in range(3):
        traj = make_trajectory("drone", seed, center=tuple(scene.center), extent=tuple(scene.extent))
        p = traj.position_W(np.linspace(0, 60, 1201))
        assert np.all(p > scene.room_lo + 0.4) and np.all(p < scene.room_hi - 0.4)
        # Distance from each position to each box (0 inside) stays above 0.3 m.
        gap = np.maximum(np.maximum(scene.box_lo[None] - p[:, None], p[:, None] - scene.box_hi[None]), 0.0)
        assert np.linalg.norm(gap, axis=2).min() > 0.3


@pytest.mark.slow
def test_scene_grows_around_a_given_flight_volume():
    """A recorded trajectory's box (here V1_02's, 4.4 x 5.4 x 1.4 m) gets the scene's wall, floor and ceiling
    distances around it and proportionally more boxes, all clear of it."""
    spec, center, extent = SCENES["room"], np.array([-0.2, 0.7, 1.6]), np.array([2.2, 2.7, 0.7])
    scene = make_scene("room", 2, center=center, extent=extent)
    np.testing.assert_allclose(center - extent - scene.room_lo,
                               np.asarray(spec.center) - spec.extent - spec.room_lo)
    np.testing.assert_allclose(scene.room_hi - center - extent,
                               np.asarray(spec.room_hi) - spec.center - spec.extent)
    assert len(scene.box_lo) > spec.n_boxes
    keep_lo, keep_hi = center - extent - spec.clearance, center + extent + spec.clearance
    assert np.all(np.any((scene.box_hi < keep_lo) | (scene.box_lo > keep_hi), axis=1))
    assert np.all(scene.box_lo >= scene.room_lo) and np.all(scene.box_hi <= scene.room_hi)


def _warp_error(clip, i: int, j: int) -> tuple[np.ndarray, float]:
    """|I_j(p) - I_i(pi(T_CiCj X_j(p)))| on co-visible pixels of frame j (GT depth, poses, K, T_BC)."""
    K, gt = clip.K, clip.gt
    T_WC = gt.T_WB @ clip.T_BC
    T_ij = so3.inv_T(T_WC[i]) @ T_WC[j]
    h, w = clip.images.shape[1:]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = gt.depth[j].astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1) @ T_ij[:3, :3].T + T_ij[:3, 3]
    ui = K[0, 0] * X[..., 0] / X[..., 2] + K[0, 2]
    vi = K[1, 1] * X[..., 1] / X[..., 2] + K[1, 2]
    warped = cv2.remap(clip.images[i].astype(np.float32), ui.astype(np.float32), vi.astype(np.float32),
                       cv2.INTER_LINEAR)
    z_i = cv2.remap(gt.depth[i], ui.astype(np.float32), vi.astype(np.float32), cv2.INTER_NEAREST)
    ok = np.isfinite(z) & (X[..., 2] > 0) & (ui > 2) & (ui < w - 3) & (vi > 2) & (vi < h - 3)
    ok &= np.abs(z_i - X[..., 2]) < 0.01 * X[..., 2]  # not occluded in frame i
    err = np.abs(clip.images[j].astype(np.float32) - warped)[ok]
    return err, ok.mean()


def _assert_geometry_agrees(clip) -> None:
    """Frames 0, 1, 2 of ``clip`` warp onto each other with GT depth and poses; a 5 cm pose error breaks it."""
    for i, j in ((0, 1), (0, 2), (2, 0)):
        err, covisible = _warp_error(clip, i, j)
        assert covisible > 0.3
        assert np.median(err) < 3.0, (i, j, np.median(err))
    # A wrong pose must break it: the test can fail.
    shifted = clip.gt.T_WB.copy()
    shifted[2, :3, 3] += 0.05
    bad = type(clip)(clip.stamps, clip.images, clip.K, clip.T_BC, clip.imu,
                     type(clip.gt)(shifted, clip.gt.v_WB, clip.gt.bg, clip.gt.ba, depth=clip.gt.depth))
    assert np.median(_warp_error(bad, 0, 2)[0]) > 6.0


def test_geometry_agrees_warping_with_gt_depth_and_poses(cache_dir):
    seq = read_asl(cached_sequence(cache_dir, seconds=2.0, seed=0))
    _assert_geometry_agrees(make_clip(seq, np.array([10, 14, 18])))


def test_geometry_agrees_along_a_real_euroc_trajectory(euroc_v102, cache_dir):
    """Frames rendered along V1_02's ground truth (10 s in, flying at about 1 m/s) warp onto each other with the GT
    depth and the GT body poses at their stamps times cam0's T_BS: the rendered camera is where the GT says."""
    seq = read_asl(cached_sequence(cache_dir, seconds=0.5, from_euroc=euroc_v102, start_s=10.0))
    clip = make_clip(seq, np.array([0, 4, 8]))
    assert np.linalg.norm(clip.gt.T_WB[2, :3, 3] - clip.gt.T_WB[0, :3, 3]) > 0.2  # real parallax
    _assert_geometry_agrees(clip)
