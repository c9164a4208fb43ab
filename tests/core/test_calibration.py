"""Self-calibration of the rig (``vi3_core.online.calibration``) through the stream estimator: a camera mount and a
camera-IMU time offset that the configuration gets wrong are recovered on a real flight (EuRoC V1_02's IMU and
ground truth, ``../shared``, with the evaluation's ground-truth pose instrument standing in for a 3DFM); a flight that
turns about one body axis only leaves the mount's rotation about that axis unobserved and says so, and hovering
observes nothing, so nothing replaces the configuration."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.backbones.ground_truth import GroundTruthPoses
from vi3_core.dataset.calib import CameraCalib
from vi3_core.dataset.sequence import GroundTruthTrack, Sequence, make_clip, sample_clips
from vi3_core.eval.perturb import RigError
from vi3_core.online import StreamEstimator
from vi3_core.online.calibration import CalibrationOptions, RigEstimate, _pair_weights
from vi3_core.sim.euroc import DISTORTION_CAM0, RESOLUTION_CAM0, T_BS_CAM0, K_cam0
from vi3_core.sim.imu import imu_stamps, simulate_imu
from vi3_core.sim.trajectory import Sines, Trajectory, make_trajectory
from vi3_core.sim.visual import PoseNoise

HOP = 14  # input frames between clips: the default clip (8 frames at stride 2) sharing its first frame


def _run(seq: Sequence, rig: RigError, *, seconds: float, seed: int = 0, stream: StreamEstimator | None = None):
    """The stream over the first ``seconds`` of ``seq`` as a user with the wrong calibration ``rig`` sees it, the
    ground-truth instrument predicting the true camera (1 mm / 0.05 deg noise): [(outcome, true metres per unit)]."""
    seen = rig.apply(seq)
    instrument = GroundTruthPoses(noise=PoseNoise(0.001, 0.05), mount_error=rig.rotation, seed=seed)
    stream = stream or StreamEstimator(instrument)
    stream.backbone = instrument
    out = []
    for idx in sample_clips(len(seq), mode="sliding", hop=HOP):
        if seq.stamps[idx[-1]] - seq.stamps[0] > seconds:
            break
        clip = make_clip(seen, idx, history_s=stream.online_options.online_max_bridge, lead_s=stream.imu_lead,
                         with_images=False)
        out.append((stream.process(clip), instrument.last_scale))
    return out


def _error(estimate: RigEstimate, rig: RigError, reference: RigEstimate | None = None) -> tuple[float, float]:
    """(the largest error about a body axis, deg; the time offset's error, ms) of ``estimate`` against the error
    ``rig`` put into the configuration, beyond the recording's own rig as ``reference`` estimated it."""
    rotation = np.degrees(estimate.rotation - (reference.rotation if reference is not None else 0.0))
    offset = estimate.time_offset - (reference.time_offset if reference is not None else 0.0)
    return float(np.abs(rotation - rig.rotation_deg).max()), abs(1e3 * (offset - rig.imu_delay_s))


@pytest.fixture(scope="module")
def v102_reference(v102):
    """The rig of the recording itself as the stream estimates it with the calibration as given: EuRoC's ground
    truth and IMU are aligned to about a millisecond (the estimate of its offset moves from -2 to -0.5 ms over the
    flight), which is no error of the configuration."""
    return _run(v102, RigError(), seconds=20.0)


def test_the_recording_as_calibrated_is_left_as_it_is(v102_reference):
    """EuRoC's own mount agrees with the flight within the estimate's sigma: it is kept, never replaced by an
    estimate a few tenths of a degree wide."""
    final = v102_reference[-1][0].calibration
    assert final.rotation_observed.all() and not final.rotation_applied, final.describe()
    assert "mount rotation" in final.describe() and "(configured; agrees)" in final.describe()
    deg, ms = _error(final, RigError())
    assert deg < 0.3 and ms < 3.0, final.describe()
    assert final.off_by() == "", final.describe()


@pytest.mark.parametrize("rig", [RigError((3.0, 0.0, 0.0), 0.020), RigError((0.0, -2.0, 2.0), -0.010)],
                         ids=["3deg-x+20ms", "2deg-yz-10ms"])
def test_a_wrong_mount_and_time_offset_are_recovered_on_a_real_flight_and_no_claim_is_wrong(v102, v102_reference,
                                                                                           rig):
    outcomes = _run(v102, rig, seconds=20.0)
    final = outcomes[-1][0].calibration
    assert final.rotation_applied and final.offset_applied, final.describe()
    deg, ms = _error(final, rig, v102_reference[-1][0].calibration)
    assert deg < 0.3 and ms < 2.0, final.describe()
    assert "camera mount" in final.off_by() and "time offset" in final.off_by(), final.describe()
    applied = next(o for o, _ in outcomes if o.calibration.rotation_applied and o.calibration.offset_applied)
    assert applied.clip.stamps[0] - v102.stamps[0] < 15.0  # within seconds of flight
    # the clip after runs with the corrected rig: the configured mount turned, its IMU moved onto the frames' clock
    (used, _), (o, _) = outcomes[-2:]
    seen = rig.apply(v102)
    assert np.allclose(o.clip.T_BC[:3, :3], so3.exp(used.calibration.rotation) @ seen.calib.T_BC[:3, :3])
    first = int(np.searchsorted(v102.stamps_ns, o.clip.stamps_ns[0]))
    assert o.clip.stamps[0] == v102.stamps[first]  # the frames keep their stamps
    k = int(np.searchsorted(seen.imu.t, o.clip.imu.t[0] + used.calibration.time_offset - 1e-6))
    assert o.clip.imu.t[0] == pytest.approx(seen.imu.t[k] - used.calibration.time_offset, abs=1e-6)
    assert np.array_equal(o.clip.imu.gyro[0], seen.imu.gyro[k])
    claims = [abs(o.init.scale / truth - 1) for o, truth in outcomes if o.init.ok]
    assert len(claims) >= 5 and max(claims) < 0.1, claims


def test_the_window_keeps_each_imu_sample_once_on_the_clips_clock(v102):
    """Once the time offset is applied, each clip's IMU is on its frames' clock; the IMU the window keeps for its
    ties and bridges holds every sample once, on the newest clip's clock, never the same sample at two times."""
    stream = StreamEstimator(GroundTruthPoses())
    outcomes = _run(v102, RigError((0.0, 0.0, 0.0), 0.020), seconds=12.0, stream=stream)
    assert outcomes[-1][0].calibration.offset_applied
    kept = stream.window._imu  # white box: what the window integrates between clips
    assert np.all(np.diff(kept.t) > 0.004), np.diff(kept.t).min()  # 200 Hz: no interleaved copy
    last = outcomes[-1][0].clip.imu
    assert np.isin(last.t, kept.t).all()


def _sequence(traj: Trajectory, seconds: float, name: str) -> Sequence:
    """``traj`` flown for ``seconds`` with EuRoC's cam0 at 20 Hz and a 200 Hz IMU with EuRoC's noise and a gyro
    bias, no images (the ground-truth instrument needs none)."""
    stamps = np.arange(0.05, seconds, 0.05)
    imu = simulate_imu(traj, imu_stamps(0.0, seconds + 0.1), bg0=np.array([0.01, -0.02, 0.015]), seed=3)
    t = imu.samples.t
    gt = GroundTruthTrack(t, traj.T_WB(t), traj.velocity_W(t), imu.bg, imu.ba)
    calib = CameraCalib(K_cam0(), "radtan", np.asarray(DISTORTION_CAM0), RESOLUTION_CAM0, T_BS_CAM0.copy(), 20.0)

    def no_image(i: int) -> np.ndarray:
        raise AssertionError("the ground-truth instrument reads no image")

    return Sequence(name=name, stamps=stamps, imu=imu.samples, calib=calib, gt=gt, load_image=no_image,
                    has_images=False)


def test_turning_about_one_axis_leaves_the_mount_about_it_unobserved():
    """A flight that only yaws turns about body x (EuRoC's body x points up): the mount's rotation about x cannot be
    told from the gyro's (a hand-eye problem sees only rotations across the turning axis), so it keeps its prior's
    sigma and the estimate is not applied, while the rotations across it and the time offset are found."""
    flight = make_trajectory("drone", seed=5, motion="medium")
    yaw = Sines(amp=np.array([[0.6, 0.3], [0.0, 0.0], [0.0, 0.0]]), freq=np.array([[0.11, 0.27], [0.1, 0.1],
                                                                                    [0.1, 0.1]]),
                phase=np.array([[0.3, 1.9], [0.0, 0.0], [0.0, 0.0]]), offset=np.zeros(3), rate=np.zeros(3))
    seq = _sequence(dataclasses.replace(flight, attitude=yaw), 20.0, "yaw_only")
    rig = RigError((2.0, 2.0, -2.0), 0.010)
    final = _run(seq, rig, seconds=20.0)[-1][0].calibration
    sigma = np.degrees(final.rotation_sigma)
    prior = CalibrationOptions().calib_prior_rotation
    assert sigma[0] > 0.5 * prior, final.describe()  # about the turning axis: still the prior's
    assert not final.rotation_applied and "unobserved about body x" in final.describe()
    assert np.all(np.abs(np.degrees(final.rotation[1:]) - rig.rotation_deg[1:]) < 0.3), final.describe()
    assert abs(1e3 * (final.time_offset - rig.imu_delay_s)) < 2.0 and final.offset_applied, final.describe()


def test_hovering_observes_nothing_and_changes_nothing():
    seq = _sequence(make_trajectory("hover", seed=2), 10.0, "hover")
    outcomes = _run(seq, RigError((3.0, 0.0, -3.0), 0.020), seconds=10.0)
    final = outcomes[-1][0].calibration
    assert not final.rotation_applied and not final.offset_applied, final.describe()
    limits = CalibrationOptions()  # the sigmas stay well above the limits at which an estimate is applied
    assert np.all(np.degrees(final.rotation_sigma) > 2 * limits.calib_max_rotation_sigma), final.describe()
    assert final.time_offset_sigma > limits.calib_max_offset_sigma, final.describe()
    assert all(np.array_equal(o.clip.T_BC, seq.calib.T_BC) or not o.calibration.rotation_applied
               for o, _ in outcomes)


def test_an_applied_estimate_moves_the_imu_not_the_frames_and_needs_the_imu_history():
    seq = _sequence(make_trajectory("drone", seed=1, motion="medium"), 3.0, "short")
    clip = make_clip(seq, np.arange(0, 16, 2), history_s=1.0, lead_s=0.03, with_images=False)
    est = RigEstimate(np.radians([1.0, -2.0, 0.5]), 0.012, np.eye(4) * 1e-9, 9, True, True)
    assert est.for_clip(clip) is est
    moved = est.apply(clip)
    assert np.array_equal(moved.stamps, clip.stamps)
    assert np.allclose(moved.imu_history.t, clip.imu_history.t - 0.012)
    assert moved.imu.t[0] <= moved.stamps[0] and moved.imu.t[-1] >= moved.stamps[-1]
    assert np.allclose(moved.T_BC[:3, :3], so3.exp(est.rotation) @ clip.T_BC[:3, :3])
    # without IMU beyond the last frame the offset cannot be applied: the clip keeps its IMU (mount still turned)
    short = dataclasses.replace(clip, imu_history=clip.imu)
    used = est.for_clip(short)
    assert used.rotation_applied and not used.offset_applied
    kept = used.apply(short)
    assert kept.imu is short.imu and not np.allclose(kept.T_BC, clip.T_BC)


@pytest.mark.parametrize(("text", "expected"), [
    ("1000,0,0", "the rotation (RX, RY, RZ) is 1000 deg about its axis; give one of at most 180 deg"),
    ("150,150,0", "is 212.132 deg about its axis"),
    ("0,0,0,1500", "IMU_DELAY_MS 1500 is outside [-1000, 1000] ms"),
    ("3,0", "expected RX_DEG,RY_DEG,RZ_DEG[,IMU_DELAY_MS], finite"),
])
def test_a_calibration_error_outside_what_it_can_mean_is_refused(text, expected):
    """Issue 31: ``--calib-error 1000,0,0`` was accepted (a rotation vector longer than 180 deg is a shorter one)."""
    with pytest.raises(ValueError, match=re.escape(expected)):
        RigError.parse(text)
    assert RigError.parse("-180,0,0,-1000").rotation_deg == (-180.0, 0.0, 0.0)


def test_the_pair_weights_hold_for_clips_of_every_length():
    """The weights of a clip's pair residuals (the pseudo-inverse of D D^T) have n - 1 eigenvalues 1 / n and the rest
    0 for clips of up to 64 frames; with numpy's default cutoff the rounding in D D^T's null space came out as weights
    of +-1e13 from 19 frames on, and a 40-frame clip stopped the evaluation with a negative variance."""
    for n in range(2, 65):
        ev = np.sort(np.linalg.eigvalsh(_pair_weights(n)))
        np.testing.assert_allclose(ev[-(n - 1):], 1.0 / n, rtol=1e-9, err_msg=str(n))
        np.testing.assert_allclose(ev[:-(n - 1)], 0.0, atol=1e-12, err_msg=str(n))
