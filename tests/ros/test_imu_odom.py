"""``vi3_ros.imu_odom.ImuOdometry``: a sample that the pipeline's buffer took while a newly chained clip restarted the
propagation (the restart catches up through it) is still published, once, from the new state."""

from __future__ import annotations

import numpy as np

from msg_adapters.types import jazzy_types
from vi3_core.online import OdomState
from vi3_core.sim.imu import ImuNoise, imu_stamps, simulate_imu
from vi3_core.sim.trajectory import make_trajectory
from vi3_ros.imu_odom import ImuOdometry
from vi3_ros.params import resolve

T_C = 3.0  # s, the chained frame


def test_a_sample_the_restart_caught_up_through_is_published_from_the_new_state():
    traj = make_trajectory("drone", seed=3)
    imu = simulate_imu(traj, imu_stamps(0.0, 4.0), noise=ImuNoise.zero()).samples
    t = np.array([T_C])
    state = OdomState(t, traj.T_WB(t), traj.velocity_W(t), np.zeros(3), np.zeros(3), 0.01, 0.001)
    sent: list[int] = []
    odom = ImuOdometry(resolve({}), types=jazzy_types(), publish=lambda key, msg, stamp_ns: sent.append(stamp_ns))
    ns = np.round(imu.t * 1e9).astype(np.int64)
    k = int(np.searchsorted(imu.t, T_C + 0.2))  # the buffer holds samples up to k when the clip is chained ...
    odom.restart(state, lambda t0: imu.select(slice(int(np.searchsorted(imu.t, t0)) - 1, k + 1)))
    for i in range(k, k + 20):  # ... and the input thread hands sample k on only now
        odom.add(ns[i], imu.gyro[i], imu.accel[i])
    assert sent == ns[k:k + 20].tolist()  # every sample once, sample k included
    odom.add(ns[k], imu.gyro[k], imu.accel[k])  # a repeated sample is not published again
    assert len(sent) == 20


def test_the_accelerometer_matrix_applies_to_the_imu_rate_odometry():
    """An accelerometer read through a matrix and ``accel_matrix`` set to it propagate as the accelerometer as is, in
    the restart's catch-up and in every sample after it; without the matrix the positions go elsewhere."""
    traj = make_trajectory("drone", seed=3)
    imu = simulate_imu(traj, imu_stamps(0.0, 4.0), noise=ImuNoise.zero()).samples
    A = np.array([[1.02, 0.04, 0.0], [-0.05, 0.99, 0.03], [0.0, 0.02, 1.01]])
    read = imu.read_through(np.linalg.inv(A))
    t = np.array([T_C])
    state = OdomState(t, traj.T_WB(t), traj.velocity_W(t), np.zeros(3), np.zeros(3), 0.01, 0.001)
    ns = np.round(imu.t * 1e9).astype(np.int64)
    k = int(np.searchsorted(imu.t, T_C + 0.2))

    def positions(samples, matrix: str) -> np.ndarray:
        sent = []
        odom = ImuOdometry(resolve({"accel_matrix": matrix}), types=jazzy_types(),
                           publish=lambda key, msg, stamp_ns: sent.append(msg))
        odom.restart(state, lambda t0: samples.select(slice(int(np.searchsorted(samples.t, t0)) - 1, k + 1)))
        for i in range(k, k + 100):
            odom.add(ns[i], samples.gyro[i], samples.accel[i])
        p = [m.pose.pose.position for m in sent if hasattr(m, "pose") and hasattr(m.pose, "pose")]
        return np.array([[q.x, q.y, q.z] for q in p])

    clean = positions(imu, "")
    assert len(clean) >= 10
    np.testing.assert_allclose(positions(read, " ".join(repr(float(x)) for x in A.ravel())), clean, atol=1e-9)
    assert np.abs(positions(read, "") - clean).max() > 1e-4
