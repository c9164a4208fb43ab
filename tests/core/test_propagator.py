"""``vi3_core.online.propagator``: the chained state propagated with the IMU between clips (~/odom/imu), on analytic
drone trajectories with simulated IMU (``vi3_core.sim``): exact from an exact state, the same per sample as in one
batch, stopped where the IMU stops supporting it, and uncertain as much as ``SigmaModel`` says."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from vi3_core import so3
from vi3_core.init.options import InitOptions
from vi3_core.online import OdomState
from vi3_core.online.propagator import ImuPropagator, SigmaModel
from vi3_core.preintegration import preintegrate
from vi3_core.sim.imu import ImuNoise, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_core.types import ImuSamples

G = 9.81
T_C = 3.0  # s, the chained frame the propagation starts from


def _state(traj, *, ba=(0.0, 0.0, 0.0), dv=(0.0, 0.0, 0.0), tilt=(0.0, 0.0, 0.0)) -> OdomState:
    """The state at T_C (odom = the trajectory's world, gravity -z, zero gyro bias), its attitude turned by ``tilt``
    (rad, about the world axes), its velocity off by ``dv`` (m/s), accelerometer bias ``ba`` (m/s^2)."""
    t = np.array([T_C])
    T = traj.T_WB(t)
    T[0, :3, :3] = so3.exp(np.asarray(tilt)) @ T[0, :3, :3]
    return OdomState(t, T, traj.velocity_W(t) + np.asarray(dv), np.zeros(3), np.asarray(ba, np.float64), 0.0, 0.0)


def _prop(state: OdomState, **kw) -> ImuPropagator:
    return ImuPropagator(state, gravity_norm=G, max_gap_s=kw.get("max_gap_s", 0.05), max_tau_s=kw.get("max_tau_s", 60))


@dataclass(frozen=True)
class _Batch:
    """``advance_states``' states as arrays: t [m] s, T_OB [m,4,4], v_O [m,3] m/s, omega [m,3] rad/s, tau [m] s."""

    t: np.ndarray
    T_OB: np.ndarray
    v_O: np.ndarray
    omega: np.ndarray
    tau: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


def _advance(prop: ImuPropagator, imu: ImuSamples) -> _Batch:
    states = prop.advance_states(imu)
    T = np.stack([s.T_OB for s in states]) if states else np.zeros((0, 4, 4))
    return _Batch(np.array([s.t for s in states]), T, np.array([s.v for s in states]).reshape(-1, 3),
                  np.array([s.omega for s in states]).reshape(-1, 3), np.array([s.tau for s in states]))


@pytest.fixture(scope="module")
def drone():
    traj = make_trajectory("drone", seed=3)
    imu = simulate_imu(traj, imu_stamps(0.0, 8.0), noise=ImuNoise.zero()).samples
    return traj, imu


def test_an_exact_state_propagates_onto_the_trajectory_per_sample_as_in_one_batch(drone):
    traj, imu = drone
    batch = _advance(_prop(_state(traj)), imu)
    assert batch.t[0] > T_C and batch.t[-1] == imu.t[-1] and np.all(np.diff(batch.t) > 0)
    truth = traj.T_WB(batch.t)
    err = np.linalg.norm(batch.T_OB[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert err[batch.tau <= 2.0].max() < 2e-3 and np.linalg.norm(truth[-1, :3, 3] - truth[0, :3, 3]) > 1.0
    assert np.degrees(so3.angle(np.swapaxes(batch.T_OB[:, :3, :3], 1, 2) @ truth[:, :3, :3])).max() < 0.01
    np.testing.assert_allclose(batch.v_O[batch.tau <= 2.0], traj.velocity_W(batch.t[batch.tau <= 2.0]), atol=2e-3)
    np.testing.assert_allclose(batch.omega, imu.gyro[imu.t > T_C])

    one = _prop(_state(traj))  # the node: one sample at a time, after the catch-up of the samples up to T_C + 0.5
    first = _advance(one, imu.select(imu.t <= T_C + 0.5))
    rest = [_advance(one, imu.select(slice(i, i + 1))) for i in np.flatnonzero(imu.t > T_C + 0.5)]
    np.testing.assert_allclose(np.concatenate([first.T_OB, *(r.T_OB for r in rest)]), batch.T_OB, atol=1e-9)
    assert len(_advance(one, imu)) == 0  # samples already integrated are not integrated twice

    wrong = _advance(_prop(_state(traj, ba=(0.05, 0.0, 0.0))), imu)  # the check can fail
    assert np.linalg.norm(wrong.T_OB[-1, :3, 3] - truth[-1, :3, 3]) > 0.3


def test_one_step_at_a_time_is_the_clips_preintegration(drone):
    """The per-sample float step integrates exactly as ``vi3_core.preintegration`` (the clips' IMU targets) does:
    from a state with biases, over 2 s of noisy IMU, the same poses and velocities to 1e-9."""
    traj, _ = drone
    imu = simulate_imu(traj, imu_stamps(T_C - 0.1, T_C + 2.0), noise=ImuNoise(), seed=4).samples
    state = _state(traj, ba=(0.03, -0.02, 0.05))
    state = OdomState(state.stamps, state.T_OB, state.v_O, np.array([0.002, -0.003, 0.001]), state.ba, 0.0, 0.0)
    out = _advance(_prop(state), imu)
    stamps = np.concatenate([[T_C], out.t])
    pre = preintegrate(imu, stamps, state.bg, state.ba)
    R0, p0 = state.T_OB[0, :3, :3], state.T_OB[0, :3, 3]
    rel = pre.propagate(R0.T @ np.array([0.0, 0.0, -G]), R0.T @ state.v_O[0])
    np.testing.assert_allclose(out.T_OB[:, :3, :3], R0 @ rel.R[1:], atol=1e-9)
    np.testing.assert_allclose(out.T_OB[:, :3, 3], p0 + rel.p[1:] @ R0.T, atol=1e-9)
    np.testing.assert_allclose(out.v_O, rel.v[1:] @ R0.T, atol=1e-9)


def test_propagation_stops_where_the_imu_no_longer_supports_it(drone):
    traj, imu = drone
    keep = ~((imu.t > T_C + 1.0) & (imu.t < T_C + 1.2))  # a 0.2 s hole
    p = _prop(_state(traj))
    out = _advance(p, imu.select(keep))
    assert abs(out.t[-1] - (T_C + 1.0)) < 1e-9 and "IMU gap of 0.200 s" in p.stopped
    assert len(_advance(p, imu)) == 0  # stopped for good: the next chained clip starts a new propagator

    bad = ImuSamples(imu.t, np.where(np.isclose(imu.t, T_C + 0.5)[:, None], np.nan, imu.gyro), imu.accel)
    p = _prop(_state(traj))
    assert _advance(p, bad).t[-1] < T_C + 0.5 and "non-finite IMU sample" in p.stopped

    p = _prop(_state(traj), max_tau_s=2.0)
    assert _advance(p, imu).tau.max() <= 2.0 and "2.0 s since the last chained clip" in p.stopped

    p = _prop(_state(traj))
    assert len(_advance(p, imu.select(imu.t > T_C + 0.1))) == 0 and "IMU starts at" in p.stopped
    p = _prop(_state(traj))  # the samples up to T_C first (a clip just chained), then one at a time
    assert len(_advance(p, imu.select(imu.t <= T_C))) == 0 and not p.stopped
    after = np.flatnonzero(imu.t > T_C)
    steps = [_advance(p, imu.select(slice(i, i + 1))) for i in after[:3]]
    assert [len(s) for s in steps] == [1, 1, 1] and not p.stopped
    np.testing.assert_allclose(steps[-1].T_OB[0], _advance(_prop(_state(traj)), imu).T_OB[2], atol=1e-12)


def test_the_spread_of_propagation_errors_is_what_the_sigmas_say(drone):
    """Monte Carlo: states off by their velocity and gravity-direction sigmas, IMU with the model's white noise."""
    traj, _ = drone
    noise = InitOptions().noise_model
    v_sigma, g_sigma = 0.05, np.radians(0.2)
    sim = ImuNoise(gyro_noise_density=noise.gyro_noise_density, gyro_random_walk=0.0,
                   accel_noise_density=noise.accel_noise_density, accel_random_walk=0.0)
    rng = np.random.default_rng(0)
    taus = np.array([0.5, 1.0, 2.0])
    errors = []
    for trial in range(120):
        imu = simulate_imu(traj, imu_stamps(T_C - 0.1, T_C + 2.05), noise=sim, seed=trial).samples
        state = _state(traj, dv=rng.normal(0.0, v_sigma, 3), tilt=np.append(rng.normal(0.0, g_sigma, 2), 0.0))
        out = _advance(_prop(state), imu)
        idx = np.searchsorted(out.tau, taus - 1e-9)
        errors.append(out.T_OB[idx, :3, 3] - traj.position_W(out.t[idx]))
    spread = np.array(errors).std(axis=0)  # [taus, xyz]
    model = SigmaModel.of(v_sigma=v_sigma, g_sigma=g_sigma, noise=noise, gravity_norm=G)
    s = model.at(taus)
    np.testing.assert_allclose(spread[:, :2], np.stack([s.position_h] * 2, 1), rtol=0.25)
    np.testing.assert_allclose(spread[:, 2], s.position_v, rtol=0.25)
    assert np.all(np.diff(s.position_h) > 0) and np.all(s.position_h > s.position_v)
    zero = model.at(np.asarray(0.0))
    assert zero.position_h == 0.0 and zero.velocity == v_sigma and zero.tilt == g_sigma
