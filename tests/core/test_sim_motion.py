"""Realistic generated motion: the presets' statistics and spectra, a multirotor's thrust-aligned attitude with exact
derivatives, the IMU streamed in chunks (noise, vibration, accelerometer bias), and the motion statistics tool."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt, welch

from vi3_core import so3
from vi3_core.dataset.asl import read_asl
from vi3_core.dataset.generate import cached_sequence
from vi3_core.dataset.motion_stats import motion_stats
from vi3_core.render.scene import make_scene
from vi3_core.sim.imu import ACCEL_BIAS_RANGE, EUROC_VIBRATION, ImuSimulator, draw_accel_bias, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import MOTIONS, PRESETS, make_trajectory

T = np.arange(0.0, 120.0, 0.005)


def _band_power(x: np.ndarray, lo: float, hi: float, fs: float = 200.0) -> float:
    f, p = welch(x, fs=fs, nperseg=4096, axis=0)
    sel = (f >= lo) & (f < hi)
    return float(np.trapezoid(p.sum(1)[sel], f[sel]))


@pytest.mark.slow
@pytest.mark.parametrize("motion", ["easy", "medium", "difficult"])
def test_presets_fly_at_their_medians_smoothly_inside_the_volume(motion):
    preset, room = PRESETS[motion], make_scene("room", 0)
    for seed in range(3):
        traj = make_trajectory("drone", seed, motion=motion, center=tuple(room.center), extent=tuple(room.extent))
        p = traj.position_W(T)
        assert np.all(np.abs(p - room.center) <= room.extent + 1e-9)
        med = [np.median(np.linalg.norm(f(T), axis=1))
               for f in (traj.velocity_W, traj.acceleration_W, traj.angular_velocity_B)]
        np.testing.assert_allclose(med, [preset.speed, preset.accel, preset.angular_rate], rtol=0.06)
        # Real flight: most acceleration below 2 Hz, but not only slow drift.
        a = traj.acceleration_W(T)
        total = _band_power(a, 0.0, 100.0)
        assert _band_power(a, 2.0, 100.0) < 0.05 * total
        assert _band_power(a, 0.5, 100.0) > 0.05 * total
    # The presets differ where EuRoC's sequences do: easy is slow, difficult turns faster than medium.
    assert PRESETS["easy"].speed < 0.5 * PRESETS["medium"].speed
    assert PRESETS["difficult"].angular_rate > PRESETS["medium"].angular_rate


def test_thrust_attitude_has_exact_derivatives_and_follows_the_acceleration():
    t, h = np.linspace(3.0, 60.0, 500), 1e-5
    for motion in MOTIONS:
        traj = make_trajectory("drone", 4, motion=motion)
        w_fd = so3.log(np.swapaxes(traj.rotation(t - h), 1, 2) @ traj.rotation(t + h)) / (2 * h)
        np.testing.assert_allclose(traj.angular_velocity_B(t), w_fd, atol=1e-6)
        jerk_fd = (traj.position.derivative(t + h, 2) - traj.position.derivative(t - h, 2)) / (2 * h)
        np.testing.assert_allclose(traj.position.derivative(t, 3), jerk_fd, atol=1e-5)
        # Specific force against the body x axis (EuRoC: x up, the thrust axis of a level multirotor).
        f_B = np.einsum("nji,nj->ni", traj.rotation(t), traj.acceleration_W(t) + [0.0, 0.0, 9.81])
        angle = np.degrees(np.arccos(f_B[:, 0] / np.linalg.norm(f_B, axis=1)))
        tilt = np.degrees(np.arccos(np.clip(traj.rotation(t)[:, 2, 0], -1.0, 1.0)))  # body x against world up
        if motion == "agile":  # the earlier generator: attitude independent of the acceleration
            assert np.median(angle) > 2.0
        elif motion == "handheld":  # held level by hand, not tilted along the acceleration
            assert tilt.max() < 3 * PRESETS[motion].wobble_deg and np.median(angle) > 1.0
        else:  # thrust-aligned up to the wobble
            assert angle.max() < 1.0 and np.median(angle) < 0.6


@pytest.mark.slow
def test_imu_streams_in_chunks_exactly_and_in_bounded_memory():
    traj = make_trajectory("drone", 2)
    t = imu_stamps(0.0, 30.0)
    kw = dict(bg0=np.array([0.01, -0.02, 0.0]), ba0=draw_accel_bias(np.random.default_rng(1)), seed=5,
              vibration=EUROC_VIBRATION)
    whole = simulate_imu(traj, t, **kw)
    sim = ImuSimulator(traj, dt=0.005, **kw)
    parts = [sim(t[i:i + 401]) for i in range(0, len(t), 401)]
    for name in ("gyro", "accel"):  # the same samples, up to the rounding of sums restarted per chunk
        np.testing.assert_allclose(np.concatenate([getattr(p.samples, name) for p in parts]),
                                   getattr(whole.samples, name), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.concatenate([p.ba for p in parts]), whole.ba, rtol=0, atol=1e-12)
    # A 20-minute IMU stream in 2 s chunks: memory is that of a chunk, not of the stream.
    sim = ImuSimulator(traj, dt=0.005, **kw)
    tracemalloc.start()
    for k in range(600):
        sim(2.0 * k + np.arange(400) * 0.005)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 5e6, peak  # the whole stream's gyro and accel alone would be 11.5 MB


def test_vibration_and_accel_bias_are_euroc_sized():
    traj = make_trajectory("drone", 1)
    t = imu_stamps(0.0, 60.0)
    quiet = simulate_imu(traj, t, seed=3)
    loud = simulate_imu(traj, t, seed=3, vibration=EUROC_VIBRATION)
    vib = loud.samples.accel - quiet.samples.accel
    rms = np.sqrt((vib[200:] ** 2).mean(0))
    np.testing.assert_allclose(rms, EUROC_VIBRATION.accel_rms, rtol=0.1)
    np.testing.assert_allclose(np.sqrt(((loud.samples.gyro - quiet.samples.gyro)[200:] ** 2).mean(0)),
                               EUROC_VIBRATION.gyro_rms, rtol=0.1)
    assert _band_power(vib, 0.0, 5.0) < 1e-3 * _band_power(vib, 0.0, 100.0)  # above the motion's band only
    lo_pass = sosfiltfilt(butter(4, 5.0, fs=200.0, output="sos"), vib, axis=0)[200:-200]  # past the edges
    assert np.abs(lo_pass).max() < 0.05
    mags = np.array([np.linalg.norm(draw_accel_bias(np.random.default_rng(s))) for s in range(200)])
    assert mags.min() >= ACCEL_BIAS_RANGE[0] and mags.max() <= ACCEL_BIAS_RANGE[1]
    assert mags.max() - mags.min() > 0.1  # spread over the range, not one value


def test_generated_sequence_has_the_bias_and_the_stats_tool_sees_the_true_motion(cache_dir):
    seq = read_asl(cached_sequence(cache_dir, seconds=10.0, seed=0, with_depth=False))
    ba = np.linalg.norm(seq.gt.ba[0])
    assert ACCEL_BIAS_RANGE[0] <= ba <= ACCEL_BIAS_RANGE[1]
    stats = motion_stats(cache_dir / "room_seed0_10s_nodepth")
    # The IMU-derived numbers (vibration and noise filtered out) are the trajectory's own.
    gt = seq.gt
    keep = (seq.imu.t >= gt.t[0]) & (seq.imu.t <= gt.t[-1])
    traj = make_trajectory("drone", 0, motion="medium", center=(0.0, 0.0, 1.4), extent=(1.6, 1.4, 0.4))
    t = seq.imu.t[keep] - seq.imu.t[0]
    np.testing.assert_allclose(stats["speed_mps"][1], np.median(np.linalg.norm(gt.v_WB, axis=1)), rtol=1e-3)
    np.testing.assert_allclose(stats["accel_mps2"][1], np.median(np.linalg.norm(traj.acceleration_W(t), axis=1)),
                               rtol=0.01)
    np.testing.assert_allclose(stats["angular_rate_radps"][1],
                               np.median(np.linalg.norm(traj.angular_velocity_B(t), axis=1)), rtol=0.01)
    no_bias = read_asl(cached_sequence(cache_dir, seconds=2.0, seed=5, accel_bias=False, imu_noise=False,
                                       with_depth=False))
    assert np.abs(no_bias.gt.ba).max() == 0.0


def test_stats_of_real_euroc_v102(euroc_v102):
    """V1_02_medium's own numbers, the ones the medium preset is matched to (docs/evaluation.md)."""
    stats = motion_stats(euroc_v102)
    np.testing.assert_allclose(stats["speed_mps"], [0.26, 0.925, 1.532], atol=0.005)
    np.testing.assert_allclose(stats["accel_mps2"], [0.164, 1.117, 2.056], atol=0.005)
    np.testing.assert_allclose(stats["angular_rate_radps"], [0.068, 0.422, 0.919], atol=0.005)
    assert PRESETS["medium"].speed == pytest.approx(stats["speed_mps"][1], rel=0.01)
    assert PRESETS["medium"].accel == pytest.approx(stats["accel_mps2"][1], rel=0.01)
    assert PRESETS["medium"].angular_rate == pytest.approx(stats["angular_rate_radps"][1], rel=0.01)
