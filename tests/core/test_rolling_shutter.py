"""A rolling shutter's frames turned back to their stamps' camera by the gyro (``vi3_core.rolling_shutter``), and the
stream doing so before the backbone (``StreamOptions.rolling_shutter_readout``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vi3_core import so3
from vi3_core.backbones.classical import ClassicalBackbone
from vi3_core.dataset.generate import REALSENSE_CAM
from vi3_core.online.stream import StreamEstimator, StreamOptions
from vi3_core.render.raycast import Renderer
from vi3_core.render.scene import make_scene
from vi3_core.rolling_shutter import derolled, row_times
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.types import Clip, GroundTruth, ImuSamples

READOUT = 0.025


@pytest.fixture(scope="module")
def turning_frames():
    """The bedroom seen by a camera turning at W (rad/s, camera frame) through its stamp: the rolling-shutter frame
    (each row from its own time's pose) and the global-shutter frame at the stamp, uint8."""
    scene = make_scene("bedroom", seed=1)
    renderer = Renderer(scene, REALSENSE_CAM)
    traj = make_trajectory("drone", 3, motion="handheld", center=tuple(scene.center), extent=tuple(scene.extent))
    T0 = traj.T_WB(np.array([2.0]))[0] @ REALSENSE_CAM.T_BC
    H = REALSENSE_CAM.size[1]
    w = np.array([0.3, 1.2, -0.4])
    tau = row_times(0.0, H, READOUT)
    rows_T = T0 @ so3.make_T(so3.exp(tau[:, None] * w), np.zeros((H, 3)))
    shutter, _ = renderer.radiance(rows_T)
    still, _ = renderer.radiance(np.repeat(T0[None], H, 0))
    gain = 110.0 / float(np.mean(still))
    return [np.clip(im * gain, 0, 255).astype(np.uint8) for im in (shutter, still)], w


def _shift(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(dx, dy) px that moves ``b``'s content onto ``a``'s (phase correlation, Hann window)."""
    window = cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(b.astype(np.float32), a.astype(np.float32), window)
    return np.array([dx, dy])


def test_derolling_puts_every_row_where_a_global_shutter_has_it(turning_frames):
    (shutter, still), w = turning_frames
    K = REALSENSE_CAM.K
    fixed = derolled(shutter[None], K, w[None], READOUT)[0]
    band = slice(200, 520)  # columns away from the borders the turn brings in
    for rows in (slice(40, 168), slice(552, 680)):  # the top rows were read before the stamp, the bottom ones after
        before = _shift(shutter[rows, band], still[rows, band])
        after = _shift(fixed[rows, band], still[rows, band])
        assert np.linalg.norm(before) > 3.0, before  # the turn during the readout moves them by pixels
        assert np.linalg.norm(after) < 0.35, (before, after)


def test_a_still_camera_or_a_global_shutter_is_left_as_it_is(turning_frames):
    (shutter, _), w = turning_frames
    frames = np.stack([shutter, shutter[::-1]])
    assert derolled(frames, REALSENSE_CAM.K, np.stack([w, w]), 0.0) is frames
    same = derolled(frames, REALSENSE_CAM.K, np.zeros((2, 3)), READOUT)
    assert np.abs(same.astype(int) - frames).max() <= 1
    rgb = np.repeat(frames[..., None], 3, -1)
    assert derolled(rgb, REALSENSE_CAM.K, np.stack([w, w]), READOUT).shape == rgb.shape
    with pytest.raises(ValueError, match="one rate per frame"):
        derolled(frames, REALSENSE_CAM.K, w[None], READOUT)


def test_the_readout_is_a_cameras():
    assert StreamOptions(rolling_shutter_readout=0.03).rolling_shutter_readout == 0.03
    for bad in (-0.01, 0.5, float("nan")):
        with pytest.raises(ValueError, match="rolling_shutter_readout"):
            StreamOptions(rolling_shutter_readout=bad)


def test_the_stream_derolls_its_clips_by_the_gyro_and_the_setting_reaches_it(turning_frames):
    """The stream turns each frame back by the gyro's rate over that frame's readout (in the body frame, through the
    mount; here a rate growing with time, so each frame has its own), and the ground truth's depth with it, except
    frames another clip already turned (``skip``); ``vi3 eval``'s options reach it."""
    (shutter, still), w = turning_frames
    T_BC = REALSENSE_CAM.T_BC
    t = np.arange(-0.1, 0.2, 0.005)
    gyro = (1.0 + 4.0 * t)[:, None] * (T_BC[:3, :3] @ w)  # w at 0 s, 1.2 w at 0.05 s
    imu = ImuSamples(t=t, gyro=gyro, accel=np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    stamps = np.array([0.0, 0.05])
    depth = np.stack([np.linspace(1.0, 3.0, shutter.size).reshape(shutter.shape).astype(np.float32)] * 2)
    gt = GroundTruth(T_WB=np.tile(np.eye(4), (2, 1, 1)), v_WB=np.zeros((2, 3)), bg=np.zeros(3), ba=np.zeros(3),
                     g_W=np.array([0.0, 0.0, -9.81]), depth=depth)
    clip = Clip(stamps=stamps, images=np.stack([shutter, still]), K=REALSENSE_CAM.K, T_BC=T_BC,
                imu=imu.window(-0.02, 0.07), gt=gt)
    stream = StreamEstimator(ClassicalBackbone(), options=StreamOptions(rolling_shutter_readout=READOUT))
    assert stream.options.rolling_shutter_readout == READOUT
    rates = np.stack([w, 1.2 * w])
    turned = stream._derolled(clip, 0)
    expected = derolled(clip.images, clip.K, rates, READOUT)
    assert np.abs(turned.images.astype(int) - expected).max() <= 1 and turned.images is not clip.images
    assert not np.array_equal(expected[1], derolled(clip.images[1:], clip.K, w[None], READOUT)[0])
    np.testing.assert_array_equal(turned.gt.depth, derolled(depth, clip.K, rates, READOUT,
                                                            interpolation=cv2.INTER_NEAREST))
    later = stream._derolled(clip, 1)
    assert np.array_equal(later.images[0], shutter) and np.array_equal(later.gt.depth[0], depth[0])
    assert np.abs(later.images[1].astype(int) - expected[1]).max() <= 1
    assert StreamEstimator(ClassicalBackbone())._derolled(clip, 0) is clip


def test_a_frame_two_clips_share_is_turned_once(turning_frames):
    """The last frame of a clip and the first of the next are one frame: the next clip takes it as the clip before
    turned it (each clip's IMU reaches one sample past its ends, so the two would turn it by different rates), and a
    reset forgets it."""
    (shutter, still), w = turning_frames
    T_BC = REALSENSE_CAM.T_BC
    t = np.arange(-0.1, 0.3, 0.005)
    imu = ImuSamples(t=t, gyro=(1.0 + 4.0 * t)[:, None] * (T_BC[:3, :3] @ w),
                     accel=np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    first = Clip(stamps=np.array([0.0, 0.05]), images=np.stack([still, shutter]), K=REALSENSE_CAM.K, T_BC=T_BC,
                 imu=imu.window(-0.005, 0.055))
    second = Clip(stamps=np.array([0.05, 0.1]), images=np.stack([shutter, still]), K=REALSENSE_CAM.K, T_BC=T_BC,
                  imu=imu.window(0.045, 0.105))
    stream = StreamEstimator(ClassicalBackbone(), options=StreamOptions(rolling_shutter_readout=READOUT))
    a = stream._derolled(first, 0)
    b = stream._derolled(second, 0)
    assert np.array_equal(b.images[0], a.images[1])
    alone = StreamEstimator(ClassicalBackbone(), options=StreamOptions(rolling_shutter_readout=READOUT))
    alone = alone._derolled(second, 0)
    assert not np.array_equal(alone.images[0], a.images[1])  # its own IMU turns it otherwise
    stream.reset("time went back")
    assert np.array_equal(stream._derolled(second, 0).images[0], alone.images[0])
