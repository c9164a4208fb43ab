"""Renders that look like a real camera (issue 36): the sensor model (rolling shutter, motion blur, auto exposure and
the frame rates it sets, vignetting, noise, JPEG), the handheld motion preset, the bedroom scene and the RealSense
sequence written end to end (its frames, its merged IMU stream, its clock offset)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vi3_core import so3
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import REALSENSE_CAM, RS_IMU_DELAY_NS, SequenceSpec, write_sequence
from vi3_core.render.raycast import Renderer
from vi3_core.render.scene import make_scene
from vi3_core.render.sensor import REALSENSE, Exposure, SensorModel, blur, finish
from vi3_core.rolling_shutter import row_times
from vi3_core.sim.trajectory import PRESETS, make_trajectory


@pytest.fixture(scope="module")
def bedroom():
    return make_scene("bedroom", seed=1)


@pytest.fixture(scope="module")
def realsense_seq(tmp_path_factory):
    """2.5 s of the RealSense camera carried by hand around the bedroom."""
    mav0 = tmp_path_factory.mktemp("rs") / "mav0"
    write_sequence(mav0, SequenceSpec(seconds=2.5, seed=3, scene="bedroom", motion="handheld", camera="realsense",
                                      with_depth=False))
    return read_asl(mav0)


def test_each_row_is_exposed_at_its_own_time_and_rendered_from_its_own_pose(bedroom):
    """Rolling shutter: rows span the readout, the middle row at the stamp; a frame rendered with one pose per row
    has each row as the global-shutter frame of that row's pose has it."""
    t = row_times(10.0, 720, 0.025)
    assert t[0] == pytest.approx(10.0 - 0.0125, abs=1e-4) and t[-1] == pytest.approx(10.0 + 0.0125, abs=1e-4)
    assert np.all(np.diff(t) > 0)
    renderer = Renderer(bedroom, REALSENSE_CAM)
    traj = make_trajectory("drone", 3, motion="handheld", center=tuple(bedroom.center), extent=tuple(bedroom.extent))
    H = REALSENSE_CAM.size[1]
    rows_T = traj.T_WB(row_times(2.0, H, 0.025)) @ REALSENSE_CAM.T_BC
    shutter, _ = renderer.radiance(rows_T)
    for r in (5, H // 2, H - 6):
        single, _ = renderer.radiance(rows_T[r])
        np.testing.assert_allclose(shutter[r], single[r], atol=1e-3)


def test_blur_integrates_the_motion_over_the_exposure(bedroom):
    """A still camera's exposure is its frame; a turning one's smears along the turn (less high-frequency energy),
    the longer the exposure the more."""
    renderer = Renderer(bedroom, REALSENSE_CAM)
    K, H = REALSENSE_CAM.K, REALSENSE_CAM.size[1]
    T0 = make_trajectory("drone", 3, motion="handheld", center=tuple(bedroom.center),
                         extent=tuple(bedroom.extent)).T_WB(np.array([2.0]))[0] @ REALSENSE_CAM.T_BC
    rows = np.repeat(T0[None], H, 0)
    image, depth = renderer.radiance(rows)
    depth = np.where(np.isfinite(depth), depth, np.nan)
    still = blur(image, depth, K, rows, lambda t: np.repeat(T0[None], len(t), 0), np.zeros(H), 0.06, 5)
    np.testing.assert_allclose(still, image, atol=1e-3)

    def turning(t):  # 1 rad/s about the camera's y axis
        return T0 @ so3.make_T(so3.exp(np.outer(np.asarray(t), [0.0, 1.0, 0.0])), np.zeros((len(t), 3)))

    sharpness = []
    for exposure in (0.0, 0.01, 0.05):
        out = blur(image, depth, K, rows, turning, np.zeros(H), exposure, 5)
        # the turn moves the image sideways: its horizontal gradients go, its vertical ones stay
        sharpness.append(float(np.mean(np.abs(cv2.Sobel(out.astype(np.float32), cv2.CV_32F, 1, 0)))))
    assert sharpness[0] > 1.2 * sharpness[1] > 1.2 * sharpness[2] > 0


def test_auto_exposure_sets_the_frame_rate_and_follows_the_light():
    """In a dim room the exposure needs more than a 30 Hz frame holds: the camera drops to its slower rates; in
    bright light it runs at its fastest; the grey level the loop settles on is its target."""
    dim = Exposure(SensorModel(exposure_s=0.058, frame_intervals_s=REALSENSE.frame_intervals_s), seed=0)
    intervals = [dim.next(20.0, 1 / 30)[0] for _ in range(50)]
    assert intervals[-1] == pytest.approx(1 / 16.67)
    bright = Exposure(SensorModel(exposure_s=0.058, frame_intervals_s=REALSENSE.frame_intervals_s), seed=0)
    for _ in range(50):
        interval, exposure, gain = bright.next(400.0, 1 / 30)
    assert interval == pytest.approx(1 / 30) and exposure < 0.5
    assert 400.0 * exposure * gain == pytest.approx(86, rel=0.05)


def test_the_stored_frame_has_the_sensors_noise_vignetting_and_jpeg():
    flat = np.full((120, 160), 100.0, np.float32)
    rng = np.random.default_rng(0)
    plain = finish(flat, 1.0, SensorModel(), rng)
    assert plain.dtype == np.uint8 and np.all(plain == 100)
    real = finish(flat, 1.0, REALSENSE, rng)
    assert real.mean() < 100 and real[60, 80] > real[2, 2] + 15  # the corners fall off
    centre = real[40:80, 60:100].astype(float)
    assert 0.7 < np.std(centre - cv2.blur(centre, (9, 9))) < 2.0  # about a grey level, as the recording


def test_the_handheld_preset_moves_like_the_recording():
    traj, t = make_trajectory("drone", 5, motion="handheld"), np.linspace(0.0, 120.0, 2400)
    preset = PRESETS["handheld"]
    for f, want in ((traj.velocity_W, preset.speed), (traj.acceleration_W, preset.accel),
                    (traj.angular_velocity_B, preset.angular_rate)):
        assert np.median(np.linalg.norm(f(t), axis=1)) == pytest.approx(want, rel=0.15)


@pytest.mark.slow
def test_a_realsense_sequence_has_its_cameras_rates_drops_merged_imu_and_clock_offset(realsense_seq):
    seq = realsense_seq
    assert seq.calib.size == (1280, 720) and seq.calib.dist_model == "none"
    dt = np.diff(seq.stamps_ns) * 1e-9
    rates = np.array(REALSENSE.frame_intervals_s)
    on_a_rate = np.min(np.abs(dt[:, None] - rates[None]), axis=1) < 1e-3
    assert on_a_rate.mean() > 0.8 and np.all(dt > 1 / 31)  # the auto exposure's rates, and gaps (drops, stalls)
    imu_dt = np.diff(seq.imu.t_ns) * 1e-9
    assert 0.02 < np.mean(imu_dt < 1.5e-3) < 0.2 and imu_dt.min() > 0  # merged streams: near-duplicate stamps
    # the IMU's clock runs RS_IMU_DELAY_NS off the camera's and the ground truth's
    assert seq.imu.t_ns[0] - seq.gt.t_ns[0] == pytest.approx(RS_IMU_DELAY_NS, abs=5e6)
    frame = seq.image(len(seq) // 2)
    assert frame.shape == (720, 1280) and 40 < frame.mean() < 140
